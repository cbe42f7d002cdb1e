#include "server/metrics_exposer.h"

#include <fcntl.h>
#include <netdb.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <sys/time.h>
#include <unistd.h>

#include <cctype>
#include <cerrno>
#include <cstring>
#include <string_view>
#include <utility>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"

namespace fd::server {
namespace {

// Requests are a few hundred bytes; anything larger is not a scrape.
constexpr size_t kMaxRequestBytes = 16 * 1024;
constexpr int kSocketTimeoutSeconds = 5;

absl::Status InvalidAddress(const std::string& address, std::string_view why) {
  return absl::InvalidArgumentError(absl::StrCat(
      "metrics address \"", address, "\": ", std::string(why),
      " (expected host:port, [ipv6]:port or port, e.g. 127.0.0.1:9464; port 0 picks a free port)"));
}

struct HostPort {
  std::string host;  // empty: all interfaces
  std::string port;
};

absl::StatusOr<HostPort> ParseAddress(const std::string& address) {
  HostPort parsed;
  const size_t colon = address.rfind(':');
  if (colon == std::string::npos) {
    parsed.port = address;
  } else {
    parsed.host = address.substr(0, colon);
    parsed.port = address.substr(colon + 1);
    if (parsed.host.empty()) return InvalidAddress(address, "empty host");
    if (parsed.host.front() == '[') {
      if (parsed.host.size() < 3 || parsed.host.back() != ']') {
        return InvalidAddress(address, "unterminated [ipv6] host");
      }
      parsed.host = parsed.host.substr(1, parsed.host.size() - 2);
    } else if (parsed.host.find(':') != std::string::npos) {
      return InvalidAddress(address, "an IPv6 host must be in brackets");
    }
  }
  if (parsed.port.empty() || parsed.port.size() > 5) return InvalidAddress(address, "bad port");
  int value = 0;
  for (const char c : parsed.port) {
    if (!std::isdigit(static_cast<unsigned char>(c))) return InvalidAddress(address, "bad port");
    value = value * 10 + (c - '0');
  }
  if (value > 65535) return InvalidAddress(address, "port above 65535");
  return parsed;
}

std::string ErrnoText(int error) { return std::strerror(error); }

// Writes all of `data`; false when the peer went away or timed out.
bool SendAll(int fd, std::string_view data) {
  while (!data.empty()) {
    const ssize_t n = send(fd, data.data(), data.size(), MSG_NOSIGNAL);
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) return false;
    data.remove_prefix(static_cast<size_t>(n));
  }
  return true;
}

std::string Response(std::string_view status, std::string_view content_type,
                     const std::string& body, bool head) {
  return absl::StrCat(
      "HTTP/1.1 ", std::string(status), "\r\nContent-Type: ", std::string(content_type),
      "\r\nContent-Length: ", body.size(), "\r\nConnection: close\r\n\r\n", head ? "" : body);
}

}  // namespace

absl::StatusOr<std::unique_ptr<MetricsExposer>> MetricsExposer::Start(const std::string& address,
                                                                      ScrapeFn scrape) {
  absl::StatusOr<HostPort> parsed = ParseAddress(address);
  if (!parsed.ok()) return parsed.status();

  addrinfo hints{};
  hints.ai_family = AF_UNSPEC;
  hints.ai_socktype = SOCK_STREAM;
  hints.ai_flags = AI_PASSIVE | AI_NUMERICSERV;
  addrinfo* results = nullptr;
  const int gai = getaddrinfo(parsed->host.empty() ? nullptr : parsed->host.c_str(),
                              parsed->port.c_str(), &hints, &results);
  if (gai != 0) return InvalidAddress(address, absl::StrCat("host: ", gai_strerror(gai)));

  int listen_fd = -1;
  std::string bind_error = "no address to bind";
  for (addrinfo* ai = results; ai != nullptr && listen_fd < 0; ai = ai->ai_next) {
    const int fd = socket(ai->ai_family, ai->ai_socktype | SOCK_CLOEXEC, ai->ai_protocol);
    if (fd < 0) {
      bind_error = absl::StrCat("socket: ", ErrnoText(errno));
      continue;
    }
    // Restarts may rebind while old connections linger in TIME_WAIT; Linux
    // still refuses a port another socket listens on.
    const int one = 1;
    setsockopt(fd, SOL_SOCKET, SO_REUSEADDR, &one, sizeof(one));
    if (bind(fd, ai->ai_addr, ai->ai_addrlen) != 0 || listen(fd, 16) != 0) {
      bind_error = ErrnoText(errno);
      close(fd);
      continue;
    }
    listen_fd = fd;
  }
  freeaddrinfo(results);
  if (listen_fd < 0) {
    return absl::UnavailableError(
        absl::StrCat("metrics address \"", address, "\": cannot listen there: ", bind_error));
  }

  sockaddr_storage bound{};
  socklen_t bound_size = sizeof(bound);
  if (getsockname(listen_fd, reinterpret_cast<sockaddr*>(&bound), &bound_size) != 0) {
    const int error = errno;
    close(listen_fd);
    return absl::UnavailableError(
        absl::StrCat("metrics address \"", address, "\": getsockname: ", ErrnoText(error)));
  }
  const int port = bound.ss_family == AF_INET6
                       ? ntohs(reinterpret_cast<const sockaddr_in6*>(&bound)->sin6_port)
                       : ntohs(reinterpret_cast<const sockaddr_in*>(&bound)->sin_port);

  int wake[2];
  if (pipe2(wake, O_CLOEXEC) != 0) {
    const int error = errno;
    close(listen_fd);
    return absl::UnavailableError(absl::StrCat("metrics exposer: pipe: ", ErrnoText(error)));
  }
  return std::unique_ptr<MetricsExposer>(
      new MetricsExposer(listen_fd, wake[0], wake[1], port, std::move(scrape)));
}

MetricsExposer::MetricsExposer(int listen_fd, int wake_read_fd, int wake_write_fd, int port,
                               ScrapeFn scrape)
    : listen_fd_(listen_fd),
      wake_read_fd_(wake_read_fd),
      wake_write_fd_(wake_write_fd),
      port_(port),
      scrape_(std::move(scrape)),
      thread_([this] { Serve(); }) {}

MetricsExposer::~MetricsExposer() {
  const char byte = 0;
  while (write(wake_write_fd_, &byte, 1) < 0 && errno == EINTR) {
  }
  thread_.join();
  close(listen_fd_);
  close(wake_read_fd_);
  close(wake_write_fd_);
}

void MetricsExposer::Serve() {
  pollfd fds[2] = {{listen_fd_, POLLIN, 0}, {wake_read_fd_, POLLIN, 0}};
  while (true) {
    fds[0].revents = fds[1].revents = 0;
    if (poll(fds, 2, -1) < 0) {
      if (errno == EINTR) continue;
      return;  // cannot happen with valid fds; nothing to serve without poll
    }
    if (fds[1].revents != 0) return;
    if ((fds[0].revents & POLLIN) == 0) continue;
    const int fd = accept4(listen_fd_, nullptr, nullptr, SOCK_CLOEXEC);
    if (fd < 0) continue;  // e.g. the client reset before accept
    HandleConnection(fd);
    close(fd);
  }
}

void MetricsExposer::HandleConnection(int fd) {
  timeval timeout{};
  timeout.tv_sec = kSocketTimeoutSeconds;
  setsockopt(fd, SOL_SOCKET, SO_RCVTIMEO, &timeout, sizeof(timeout));
  setsockopt(fd, SOL_SOCKET, SO_SNDTIMEO, &timeout, sizeof(timeout));

  std::string request;
  char buffer[2048];
  while (request.find("\r\n\r\n") == std::string::npos &&
         request.find("\n\n") == std::string::npos) {
    if (request.size() > kMaxRequestBytes) {
      SendAll(fd, Response("431 Request Header Fields Too Large", "text/plain", "", false));
      return;
    }
    const ssize_t n = recv(fd, buffer, sizeof(buffer), 0);
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) return;  // closed or timed out before a whole request
    request.append(buffer, static_cast<size_t>(n));
  }

  // Request line: METHOD SP TARGET SP VERSION.
  const std::string_view line = std::string_view(request).substr(0, request.find_first_of("\r\n"));
  const size_t method_end = line.find(' ');
  const size_t target_end = method_end == std::string_view::npos ? std::string_view::npos
                                                                 : line.find(' ', method_end + 1);
  if (target_end == std::string_view::npos) {
    SendAll(fd, Response("400 Bad Request", "text/plain", "bad request line\n", false));
    return;
  }
  const std::string_view method = line.substr(0, method_end);
  std::string_view target = line.substr(method_end + 1, target_end - method_end - 1);
  target = target.substr(0, target.find('?'));
  const bool head = method == "HEAD";
  if (method != "GET" && !head) {
    SendAll(fd, Response("405 Method Not Allowed", "text/plain", "use GET /metrics\n", false));
    return;
  }
  if (target != "/metrics") {
    SendAll(fd, Response("404 Not Found", "text/plain", "metrics are at /metrics\n", head));
    return;
  }
  SendAll(fd, Response("200 OK", "text/plain; version=0.0.4; charset=utf-8", scrape_(), head));
}

}  // namespace fd::server
