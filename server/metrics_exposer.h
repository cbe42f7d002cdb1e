// MetricsExposer: a minimal HTTP/1.x server for GET /metrics (Prometheus
// text exposition format 0.0.4) on its own port.
//
// Why not prometheus::Exposer (prometheus-cpp pull): Debian's civetweb
// creates its worker threads with a fixed 100 KiB stack (USE_STACK_SIZE),
// and glibc carves every thread's static TLS out of its stack. With
// LibTorch's dependencies loaded (libopenblas 60 KiB + libglog 30 KiB +
// libtorch_cpu 10 KiB of TLS) pthread_create fails with EINVAL, so the
// Exposer throws "null context when constructing CivetServer" in any process
// that links fd::model. This server's one thread has the default stack.
//
// Scope: one request per connection (Connection: close), handled one at a
// time with 5 s socket timeouts; GET and HEAD of /metrics (any query) give
// 200, other paths 404, other methods 405. Enough for Prometheus scrapes
// and curl; not a general web server.
#ifndef FD_SERVER_METRICS_EXPOSER_H_
#define FD_SERVER_METRICS_EXPOSER_H_

#include <functional>
#include <memory>
#include <string>
#include <thread>

#include "absl/status/statusor.h"

namespace fd::server {

class MetricsExposer {
 public:
  // Produces the /metrics body; called on the exposer's thread per request.
  using ScrapeFn = std::function<std::string()>;

  // Listens on `address` ("host:port", "[ipv6]:port" or "port" for all
  // interfaces; port 0 picks a free one) and serves until destroyed. Serving
  // has started when it returns. INVALID_ARGUMENT naming the address when it
  // is malformed or its host does not resolve, UNAVAILABLE when it cannot be
  // bound (e.g. the port is taken).
  static absl::StatusOr<std::unique_ptr<MetricsExposer>> Start(const std::string& address,
                                                               ScrapeFn scrape);

  // Stops accepting, waits for the request in progress, closes the socket.
  ~MetricsExposer();

  MetricsExposer(const MetricsExposer&) = delete;
  MetricsExposer& operator=(const MetricsExposer&) = delete;

  // The bound port.
  int port() const { return port_; }

 private:
  MetricsExposer(int listen_fd, int wake_read_fd, int wake_write_fd, int port, ScrapeFn scrape);
  void Serve();
  void HandleConnection(int fd);

  const int listen_fd_;
  const int wake_read_fd_;  // readable once the destructor asks Serve to stop
  const int wake_write_fd_;
  const int port_;
  const ScrapeFn scrape_;
  std::thread thread_;  // last: started once the fields above are set
};

}  // namespace fd::server

#endif  // FD_SERVER_METRICS_EXPOSER_H_
