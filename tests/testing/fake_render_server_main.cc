// fd_fake_render_server: the SDK tests' FakeRenderServer as a process, for
// trying framediffuser-client by hand before the real server exists. It
// renders a trivial formula, not FrameDiffuser (see fake_render_server.h).
//
//   fd_fake_render_server [--port N] [--native-size S] [--max-size M]
// Prints "listening on 127.0.0.1:PORT" and serves until SIGINT/SIGTERM.
#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>

#include "tests/testing/fake_render_server.h"

int main(int argc, char** argv) {
  fd::testing::FakeRenderServerOptions options;
  options.max_size = 2048;
  for (int i = 1; i + 1 < argc; i += 2) {
    const std::string flag = argv[i];
    const unsigned long value = std::strtoul(argv[i + 1], nullptr, 10);
    if (flag == "--native-size") {
      options.native_size = static_cast<uint32_t>(value);
    } else if (flag == "--max-size") {
      options.max_size = static_cast<uint32_t>(value);
    } else if (flag != "--port") {
      std::fprintf(stderr, "usage: %s [--port N] [--native-size S] [--max-size M]\n", argv[0]);
      return 2;
    }
  }
  // Block the stop signals before gRPC starts its threads, then wait for one.
  sigset_t signals;
  sigemptyset(&signals);
  sigaddset(&signals, SIGINT);
  sigaddset(&signals, SIGTERM);
  pthread_sigmask(SIG_BLOCK, &signals, nullptr);
  fd::testing::FakeRenderServer server(options);
  // --port: bind a fixed port through the restart path (Start reuses port()).
  for (int i = 1; i + 1 < argc; i += 2) {
    if (std::strcmp(argv[i], "--port") == 0) server.SetPortForTesting(std::atoi(argv[i + 1]));
  }
  if (absl::Status s = server.Start(); !s.ok()) {
    std::fprintf(stderr, "error: %s\n", std::string(s.message()).c_str());
    return 1;
  }
  std::printf("fake FrameDiffuser server (NOT a model) listening on %s, environment 'tiny'\n",
              server.address().c_str());
  std::fflush(stdout);
  int received = 0;
  sigwait(&signals, &received);
  server.Stop();
  return 0;
}
