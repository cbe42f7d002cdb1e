#include "client_sdk/session.h"

#include "client_sdk/internal/session_impl.h"

namespace fd::client {

ImageView Frame::view() const {
  if (data == nullptr) return ImageView();
  return ImageView::Raw(data->data(), width, height, channels, dtype);
}

Session::Session(std::unique_ptr<SessionImpl> impl) : impl_(std::move(impl)) {}
Session::~Session() = default;

std::string Session::session_id() const { return impl_->session_id(); }
SessionSettings Session::settings() const { return impl_->settings(); }
uint32_t Session::frames_in_flight() const { return impl_->frames_in_flight(); }
int Session::failover_count() const { return impl_->failover_count(); }

absl::StatusOr<Frame> Session::Render(const FrameRequest& request) {
  return RenderAsync(request).get();
}

absl::Status Session::Submit(const FrameRequest& request, FrameCallback done) {
  return impl_->Submit(request, std::move(done));
}

std::future<absl::StatusOr<Frame>> Session::RenderAsync(const FrameRequest& request) {
  auto promise = std::make_shared<std::promise<absl::StatusOr<Frame>>>();
  std::future<absl::StatusOr<Frame>> future = promise->get_future();
  absl::Status submitted = impl_->Submit(
      request, [promise](absl::StatusOr<Frame> frame) { promise->set_value(std::move(frame)); });
  if (!submitted.ok()) promise->set_value(submitted);
  return future;
}

absl::Status Session::Close() { return impl_->Close(); }

}  // namespace fd::client
