// Internal: the channel, stub and per-call metadata shared by a Client and
// its Sessions. Not part of the public SDK headers.
#ifndef FD_CLIENT_SDK_INTERNAL_CONNECTION_H_
#define FD_CLIENT_SDK_INTERNAL_CONNECTION_H_

#include <grpcpp/grpcpp.h>

#include <memory>
#include <string>

#include "client_sdk/client.h"
#include "framediffuser/v1/render_service.grpc.pb.h"

namespace fd::client {

class Connection {
 public:
  Connection(ClientOptions options, std::shared_ptr<grpc::Channel> channel)
      : options_(std::move(options)),
        channel_(std::move(channel)),
        stub_(framediffuser::v1::FrameDiffuser::NewStub(channel_)) {}

  const ClientOptions& options() const { return options_; }
  grpc::Channel* channel() const { return channel_.get(); }
  const std::shared_ptr<grpc::Channel>& shared_channel() const { return channel_; }
  framediffuser::v1::FrameDiffuser::Stub* stub() const { return stub_.get(); }

  // Adds the metadata every call carries (authorization).
  void Prepare(grpc::ClientContext* context) const {
    if (!options_.bearer_token.empty()) {
      context->AddMetadata("authorization", "Bearer " + options_.bearer_token);
    }
  }

 private:
  const ClientOptions options_;
  const std::shared_ptr<grpc::Channel> channel_;
  const std::unique_ptr<framediffuser::v1::FrameDiffuser::Stub> stub_;
};

}  // namespace fd::client

#endif  // FD_CLIENT_SDK_INTERNAL_CONNECTION_H_
