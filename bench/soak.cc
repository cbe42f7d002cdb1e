// Soak and load: many concurrent sessions for a long time against the real
// framediffuser-server binary (a child process, so that its memory, threads
// and file descriptors are measured apart from this load generator), with
// clients that misbehave the way real ones do. Not a timed test: the checks
// are about correctness and leaks; the latencies are reported, not judged.
//
//   fd_soak [--sessions 64] [--seconds 60] [--warmup_seconds 10]
//           [--server PATH] [--size 32] [--steps 2] [--max_frames_in_flight 4]
//           [--seed 1] [--rss_growth_mib 8] [--fd_slack 0] [--thread_slack 0]
//           [--replay_sessions -1] [--server_log FILE] [--json FILE]
//           [--server_arg ARG]...
//
// The server serves the tiny random-weight environment (session/
// random_environment.h) from a model repository in a scratch folder, with
// --batch_invariant, on 127.0.0.1 port 0 (the port comes from its log).
// Each of --sessions client threads drives one session at a time through
// the generated stubs (bench/soak_client.h says what each one does and
// checks on the wire). The run:
//   1. warm-up: the same load for --warmup_seconds; every session closed,
//      every channel gone; the server's RSS, threads and fds once they
//      settle are the baseline;
//   2. load: --seconds of it; closed again, settled, measured again;
//   3. replay: every session of both phases (or --replay_sessions of them)
//      rendered again alone, one at a time, with the same seed and inputs:
//      under --batch_invariant every frame must be bitwise the same;
//   4. SIGTERM: the server must drain and exit 0.
// Fails (exit 1, saying why) when a client check fails, a replayed frame
// differs, the RSS grew by --rss_growth_mib or more from the baseline, the
// fds or threads did not come back to the baseline (+ slack), or the
// server's log has an error line or it did not exit 0.
#include <sys/types.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <functional>
#include <memory>
#include <nlohmann/json.hpp>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/synchronization/mutex.h"
#include "absl/time/clock.h"
#include "absl/time/time.h"
#include "base/scratch_dir.h"
#include "bench/soak_client.h"
#include "bench/soak_server_process.h"
#include "session/random_environment.h"

namespace fd::bench {
namespace {

constexpr char kEnvironment[] = "tiny";

struct Options {
  std::string server = FD_SOAK_SERVER_BINARY;
  int sessions = 64;
  double seconds = 60;
  double warmup_seconds = 10;
  uint32_t size = 32;
  uint32_t steps = 2;
  uint32_t max_frames_in_flight = 4;
  uint64_t seed = 1;
  double rss_growth_mib = 8;
  int fd_slack = 0;
  int thread_slack = 0;
  int replay_sessions = -1;  // -1: all
  std::string server_log;
  std::string json;
  std::vector<std::string> server_args;
};

constexpr char kUsage[] =
    "usage: fd_soak [--sessions N] [--seconds S] [--warmup_seconds S] [--server PATH]\n"
    "               [--size PIXELS] [--steps K] [--max_frames_in_flight N] [--seed N]\n"
    "               [--rss_growth_mib MIB] [--fd_slack N] [--thread_slack N]\n"
    "               [--replay_sessions N] [--server_log FILE] [--json FILE]\n"
    "               [--server_arg ARG]...\n"
    "defaults: --sessions 64 --seconds 60 --warmup_seconds 10 --size 32 --steps 2\n"
    "          --max_frames_in_flight 4 --seed 1 --rss_growth_mib 8 --fd_slack 0\n"
    "          --thread_slack 0 --replay_sessions -1 (all) --server " FD_SOAK_SERVER_BINARY
    "\n"
    "--server_arg passes one more flag to the server (repeatable).\n";

[[noreturn]] void Usage(const std::string& error) {
  std::fprintf(stderr, "fd_soak: %s\n%s", error.c_str(), kUsage);
  std::exit(2);
}

Options ParseFlags(int argc, char** argv) {
  Options options;
  for (int i = 1; i < argc; ++i) {
    std::string flag = argv[i];
    std::string value;
    bool has_value = false;
    if (const size_t eq = flag.find('='); eq != std::string::npos) {
      value = flag.substr(eq + 1);
      flag = flag.substr(0, eq);
      has_value = true;
    }
    auto next = [&]() -> std::string {
      if (has_value) return value;
      if (i + 1 >= argc) Usage(flag + ": missing value");
      return argv[++i];
    };
    auto integer = [&](int64_t min) {
      const std::string text = next();
      int64_t n = 0;
      if (!absl::SimpleAtoi(text, &n) || n < min) {
        Usage(absl::StrCat(flag, ": expected an integer >= ", min, ", got '", text, "'"));
      }
      return n;
    };
    auto real = [&](double min) {
      const std::string text = next();
      double x = 0;
      if (!absl::SimpleAtod(text, &x) || !(x >= min)) {
        Usage(absl::StrCat(flag, ": expected a number >= ", min, ", got '", text, "'"));
      }
      return x;
    };
    if (flag == "--help" || flag == "-h") {
      std::printf("%s", kUsage);
      std::exit(0);
    } else if (flag == "--server") {
      options.server = next();
    } else if (flag == "--sessions") {
      options.sessions = static_cast<int>(integer(1));
    } else if (flag == "--seconds") {
      options.seconds = real(0.1);
    } else if (flag == "--warmup_seconds") {
      options.warmup_seconds = real(0.1);
    } else if (flag == "--size") {
      options.size = static_cast<uint32_t>(integer(16));
      if (options.size % 8 != 0) Usage("--size: must be a multiple of 8");
    } else if (flag == "--steps") {
      options.steps = static_cast<uint32_t>(integer(1));
    } else if (flag == "--max_frames_in_flight") {
      options.max_frames_in_flight = static_cast<uint32_t>(integer(1));
    } else if (flag == "--seed") {
      options.seed = static_cast<uint64_t>(integer(0));
    } else if (flag == "--rss_growth_mib") {
      options.rss_growth_mib = real(0);
    } else if (flag == "--fd_slack") {
      options.fd_slack = static_cast<int>(integer(0));
    } else if (flag == "--thread_slack") {
      options.thread_slack = static_cast<int>(integer(0));
    } else if (flag == "--replay_sessions") {
      options.replay_sessions = static_cast<int>(integer(-1));
    } else if (flag == "--server_log") {
      options.server_log = next();
    } else if (flag == "--json") {
      options.json = next();
    } else if (flag == "--server_arg") {
      options.server_args.push_back(next());
    } else {
      Usage("unknown flag " + flag);
    }
  }
  return options;
}

double Mib(int64_t kib) { return static_cast<double>(kib) / 1024.0; }

// The machine may be shared: the figures mean little without it.
double LoadAverage() {
  double load[1] = {0};
  return getloadavg(load, 1) == 1 ? load[0] : -1;
}

double Percentile(std::vector<double> values, double p) {
  if (values.empty()) return 0;
  std::sort(values.begin(), values.end());
  const size_t rank =
      static_cast<size_t>(std::ceil(p / 100.0 * static_cast<double>(values.size())));
  return values[std::clamp<size_t>(rank, 1, values.size()) - 1];
}

// What one phase of load did.
struct PhaseResult {
  std::vector<SessionRecord> sessions;
  ClientCounts counts;
  std::vector<double> latency_ms;
  std::vector<std::string> failures;
  double wall_seconds = 0;
  ProcessSample peak;  // the largest of each figure seen while it ran
};

// Runs `sessions` clients until `seconds` from now, sampling the server
// every second meanwhile.
PhaseResult RunPhase(const Options& options, const ServerProcess& server, double seconds,
                     uint64_t run_seed) {
  SoakClientOptions client_options;
  client_options.target = absl::StrCat("127.0.0.1:", server.port());
  client_options.environment = kEnvironment;
  client_options.size = options.size;
  client_options.steps = options.steps;
  client_options.max_frames_in_flight = options.max_frames_in_flight;
  client_options.run_seed = run_seed;
  const auto start = std::chrono::steady_clock::now();
  client_options.deadline = absl::Now() + absl::Seconds(seconds);

  std::vector<ClientResult> results(static_cast<size_t>(options.sessions));
  absl::Mutex mu;
  int running = options.sessions;
  std::vector<std::thread> threads;
  for (int i = 0; i < options.sessions; ++i) {
    threads.emplace_back([&, i] {
      results[static_cast<size_t>(i)] = RunSoakClient(i, client_options);
      absl::MutexLock lock(&mu);
      --running;
    });
  }
  PhaseResult phase;
  auto track_peak = [&] {
    if (absl::StatusOr<ProcessSample> s = SampleProcess(server.pid()); s.ok()) {
      phase.peak.rss_kib = std::max(phase.peak.rss_kib, s->rss_kib);
      phase.peak.hwm_kib = std::max(phase.peak.hwm_kib, s->hwm_kib);
      phase.peak.threads = std::max(phase.peak.threads, s->threads);
      phase.peak.fds = std::max(phase.peak.fds, s->fds);
    }
  };
  auto all_done = [&running] { return running == 0; };
  while (true) {
    {
      absl::MutexLock lock(&mu);
      if (mu.AwaitWithTimeout(absl::Condition(&all_done), absl::Seconds(1))) break;
    }
    track_peak();
  }
  for (std::thread& thread : threads) thread.join();
  phase.wall_seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  for (ClientResult& result : results) {
    phase.counts.Add(result.counts);
    phase.latency_ms.insert(phase.latency_ms.end(), result.latency_ms.begin(),
                            result.latency_ms.end());
    for (SessionRecord& session : result.sessions) phase.sessions.push_back(std::move(session));
    if (!result.failure.empty()) phase.failures.push_back(result.failure);
  }
  return phase;
}

// Samples the server every 100 ms until `settled` holds for the sample (and
// has held for the last `stable` samples when that is > 1), or `timeout`
// passed; returns the last sample. Connections the clients closed take a
// moment to be noticed, and a thread pool a moment to shrink: this waits for
// the state, it does not guess a time.
absl::StatusOr<ProcessSample> Settle(
    pid_t pid, const std::function<bool(const ProcessSample&, const ProcessSample&)>& settled,
    absl::Duration timeout) {
  const absl::Time deadline = absl::Now() + timeout;
  absl::StatusOr<ProcessSample> previous = SampleProcess(pid);
  if (!previous.ok()) return previous;
  while (true) {
    std::this_thread::sleep_for(std::chrono::milliseconds(100));  // sampling period
    absl::StatusOr<ProcessSample> now = SampleProcess(pid);
    if (!now.ok()) return now;
    if (settled(*previous, *now) || absl::Now() >= deadline) return now;
    previous = now;
  }
}

// Threads that must come back to the baseline: all but gRPC core's own
// self-sizing pools (executor: grows to its cap on demand and stays, checked
// apart; timer threads: reported).
int OwnThreads(const ProcessSample& s) {
  return s.threads - s.grpc_executor_threads - s.grpc_timer_threads;
}

std::string Figures(const ProcessSample& s) {
  return absl::StrFormat("RSS %.1f MiB, %d threads (gRPC core's executor %d, timer %d), %d fds",
                         Mib(s.rss_kib), s.threads, s.grpc_executor_threads, s.grpc_timer_threads,
                         s.fds);
}

nlohmann::json SampleJson(const ProcessSample& s) {
  return {{"rss_mib", Mib(s.rss_kib)},
          {"hwm_mib", Mib(s.hwm_kib)},
          {"threads", s.threads},
          {"grpc_executor_threads", s.grpc_executor_threads},
          {"grpc_timer_threads", s.grpc_timer_threads},
          {"fds", s.fds}};
}

nlohmann::json CountsJson(const ClientCounts& c) {
  return {{"sessions_opened", c.sessions_opened}, {"sessions_closed", c.sessions_closed},
          {"frames_written", c.frames_written},   {"frames_answered", c.frames_answered},
          {"frame_errors", c.frame_errors},       {"answers_lost", c.answers_lost},
          {"frames_resent", c.frames_resent},     {"cancels", c.cancels},
          {"reconnects", c.reconnects},           {"takeovers", c.takeovers},
          {"slow_segments", c.slow_segments},     {"closed_resume_checks", c.closed_resume_checks}};
}

void PrintCounts(const char* name, const PhaseResult& phase) {
  const ClientCounts& c = phase.counts;
  std::printf(
      "%s: %.1f s; sessions opened %lld, closed %lld; frames written %lld, rendered and answered "
      "%lld (%.1f/s), FrameErrors %lld, answers lost with broken streams %lld, re-sent %lld; "
      "cancels %lld, reconnects %lld, takeovers %lld, slow-reading stretches %lld, closed-session "
      "resume checks %lld\n",
      name, phase.wall_seconds, static_cast<long long>(c.sessions_opened),
      static_cast<long long>(c.sessions_closed), static_cast<long long>(c.frames_written),
      static_cast<long long>(c.frames_answered),
      static_cast<double>(c.frames_answered) / std::max(phase.wall_seconds, 1e-9),
      static_cast<long long>(c.frame_errors), static_cast<long long>(c.answers_lost),
      static_cast<long long>(c.frames_resent), static_cast<long long>(c.cancels),
      static_cast<long long>(c.reconnects), static_cast<long long>(c.takeovers),
      static_cast<long long>(c.slow_segments), static_cast<long long>(c.closed_resume_checks));
}

int Main(int argc, char** argv) {
  const Options options = ParseFlags(argc, argv);
  const auto started = std::chrono::steady_clock::now();
  std::vector<std::string> failures;
  auto fail = [&failures](std::string why) {
    std::printf("FAIL: %s\n", why.c_str());
    std::fflush(stdout);
    failures.push_back(std::move(why));
  };

  absl::StatusOr<ScratchDir> scratch = ScratchDir::Create("", "fd-soak-");
  if (!scratch.ok()) {
    std::fprintf(stderr, "fd_soak: %s\n", scratch.status().ToString().c_str());
    return 1;
  }
  const std::string repository = scratch->path() + "/repository";
  if (absl::Status written =
          session::WriteRandomTinyEnvironment(absl::StrCat(repository, "/", kEnvironment));
      !written.ok()) {
    std::fprintf(stderr, "fd_soak: %s\n", written.ToString().c_str());
    return 1;
  }
  std::vector<std::string> server_args = {
      "--listen=127.0.0.1:0",
      "--model_repository=" + repository,
      "--batch_invariant",
      "--log_format=json",
      "--min_size=16",
      absl::StrCat("--max_frames_in_flight=", options.max_frames_in_flight),
      // The load, not a limit, is under test: no open or frame may be refused.
      "--max_sessions=100000",
      "--max_sessions_per_environment=100000",
      "--max_sessions_per_client=100000",
      "--max_queue_size=100000",
      "--drain_timeout=30s",
  };
  server_args.insert(server_args.end(), options.server_args.begin(), options.server_args.end());
  absl::StatusOr<std::unique_ptr<ServerProcess>> started_server =
      ServerProcess::Start(options.server, server_args, options.server_log, absl::Minutes(2));
  if (!started_server.ok()) {
    std::fprintf(stderr, "fd_soak: %s\n", started_server.status().ToString().c_str());
    return 1;
  }
  ServerProcess& server = **started_server;
  // The repository loads in the background after the server listens.
  if (!server.WaitForEvent("environment_load", 1, absl::Minutes(2))) {
    std::fprintf(stderr, "fd_soak: the environment did not load; the server's log ends:\n%s\n",
                 server.Tail(40).c_str());
    return 1;
  }
  const char* coretype = std::getenv("OPENBLAS_CORETYPE");
  std::printf(
      "fd_soak: %d sessions x %.0f s (after a %.0f s warm-up) against %s (pid %d, port %d): tiny "
      "random environment, %ux%u, %u steps, --batch_invariant, max_frames_in_flight 1..%u; %u "
      "CPUs, OPENBLAS_CORETYPE=%s, seed %llu, load average %.2f\n",
      options.sessions, options.seconds, options.warmup_seconds, options.server.c_str(),
      static_cast<int>(server.pid()), server.port(), options.size, options.size, options.steps,
      options.max_frames_in_flight, std::thread::hardware_concurrency(),
      coretype != nullptr ? coretype : "(unset)", static_cast<unsigned long long>(options.seed),
      LoadAverage());
  std::fflush(stdout);

  absl::StatusOr<ProcessSample> idle = SampleProcess(server.pid());
  if (!idle.ok()) {
    std::fprintf(stderr, "fd_soak: %s\n", idle.status().ToString().c_str());
    return 1;
  }

  // 1. Warm-up, then the baseline once connections are gone and the thread
  // count has stopped moving for a second.
  PhaseResult warmup = RunPhase(options, server, options.warmup_seconds, options.seed * 2 + 1);
  PrintCounts("warm-up", warmup);
  for (const std::string& failure : warmup.failures) fail("warm-up: " + failure);
  const int idle_fds = idle->fds;
  int unchanged = 0;
  absl::StatusOr<ProcessSample> baseline = Settle(
      server.pid(),
      [idle_fds, &unchanged](const ProcessSample& before, const ProcessSample& now) {
        unchanged = now.threads == before.threads && now.fds == before.fds ? unchanged + 1 : 0;
        return now.fds <= idle_fds && unchanged >= 10;
      },
      absl::Seconds(30));
  if (!baseline.ok()) {
    std::fprintf(stderr, "fd_soak: %s\n", baseline.status().ToString().c_str());
    return 1;
  }
  std::printf("server before load: %s\nserver after warm-up, idle: %s (the baseline)\n",
              Figures(*idle).c_str(), Figures(*baseline).c_str());
  const std::string baseline_threads = ThreadNames(server.pid());
  std::fflush(stdout);

  // 2. The load.
  PhaseResult load = RunPhase(options, server, options.seconds, options.seed * 2 + 2);
  PrintCounts("load", load);
  for (const std::string& failure : load.failures) fail("load: " + failure);
  const ProcessSample base = *baseline;
  const int fd_slack = options.fd_slack;
  const int thread_slack = options.thread_slack;
  absl::StatusOr<ProcessSample> after = Settle(
      server.pid(),
      [&](const ProcessSample&, const ProcessSample& now) {
        return now.fds <= base.fds + fd_slack && OwnThreads(now) <= OwnThreads(base) + thread_slack;
      },
      absl::Seconds(30));
  if (!after.ok()) {
    std::fprintf(stderr, "fd_soak: %s\n", after.status().ToString().c_str());
    return 1;
  }
  const double latency_p50 = Percentile(load.latency_ms, 50);
  const double latency_p99 = Percentile(load.latency_ms, 99);
  const double latency_max = Percentile(load.latency_ms, 100);
  std::printf(
      "latency, write to answer (normal streaming, %zu frames): p50 %.1f ms, p99 %.1f ms, max "
      "%.1f ms\n",
      load.latency_ms.size(), latency_p50, latency_p99, latency_max);
  std::printf("server under load, largest seen: RSS %.1f MiB, %d threads, %d fds\n",
              Mib(load.peak.rss_kib), load.peak.threads, load.peak.fds);
  std::printf("server after load, idle: %s (peak RSS so far, VmHWM %.1f MiB)\n",
              Figures(*after).c_str(), Mib(after->hwm_kib));
  const double growth_mib = Mib(after->rss_kib - base.rss_kib);
  std::printf("RSS growth from the baseline: %+.1f MiB (bound %.1f MiB)\n", growth_mib,
              options.rss_growth_mib);
  std::fflush(stdout);
  if (growth_mib >= options.rss_growth_mib) {
    fail(absl::StrFormat("the server's RSS grew by %.1f MiB from the baseline (bound %.1f MiB)",
                         growth_mib, options.rss_growth_mib));
  }
  if (after->fds > base.fds + fd_slack) {
    fail(absl::StrCat("file descriptors leak: ", after->fds, " open after the load, ", base.fds,
                      " after the warm-up (slack ", fd_slack, ")"));
  }
  if (OwnThreads(*after) > OwnThreads(base) + thread_slack) {
    fail(absl::StrCat(
        "threads leak: ", OwnThreads(*after), " besides gRPC core's pools after the load, ",
        OwnThreads(base), " after the warm-up (slack ", thread_slack,
        "); after the warm-up: ", baseline_threads, "; now: ", ThreadNames(server.pid())));
  }
  if (const int cap = 2 * static_cast<int>(std::thread::hardware_concurrency());
      after->grpc_executor_threads > cap) {
    fail(absl::StrCat("gRPC executor threads: ", after->grpc_executor_threads,
                      ", more than its cap of 2 x cores = ", cap));
  }

  // 3. Replay, each session alone.
  std::vector<const SessionRecord*> to_replay;
  for (const PhaseResult* phase : {&warmup, &load}) {
    for (const SessionRecord& session : phase->sessions) to_replay.push_back(&session);
  }
  if (options.replay_sessions >= 0 &&
      to_replay.size() > static_cast<size_t>(options.replay_sessions)) {
    // Spread over the run: every k-th session.
    std::vector<const SessionRecord*> picked;
    const double step =
        static_cast<double>(to_replay.size()) / std::max(options.replay_sessions, 1);
    for (int i = 0; i < options.replay_sessions; ++i) {
      picked.push_back(to_replay[static_cast<size_t>(i * step)]);
    }
    to_replay = std::move(picked);
  }
  SoakClientOptions replay_options;
  replay_options.environment = kEnvironment;
  replay_options.size = options.size;
  replay_options.steps = options.steps;
  const auto replay_start = std::chrono::steady_clock::now();
  int64_t compared = 0;
  int64_t replayed_frames = 0;
  int replay_failures = 0;
  {
    std::shared_ptr<grpc::Channel> channel = NewChannel(absl::StrCat("127.0.0.1:", server.port()));
    for (const SessionRecord* session : to_replay) {
      replayed_frames += static_cast<int64_t>(session->rendered.size());
      if (absl::Status status = ReplaySession(channel, replay_options, *session, &compared);
          !status.ok()) {
        if (++replay_failures <= 10) fail(std::string(status.message()));
      }
    }
  }
  if (replay_failures > 10) fail(absl::StrCat(replay_failures, " sessions failed the replay"));
  const double replay_seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - replay_start).count();
  std::printf(
      "replay alone: %zu sessions, %lld frames rendered again in %.1f s, %lld with an answer to "
      "compare: %s\n",
      to_replay.size(), static_cast<long long>(replayed_frames), replay_seconds,
      static_cast<long long>(compared),
      replay_failures == 0 ? "all bitwise equal" : "DIFFERENCES (above)");

  // 4. Drain and exit.
  absl::StatusOr<int> exit_status = server.Terminate(absl::Seconds(60));
  const int errors = server.ErrorCount();
  std::printf(
      "server log: %d warning lines, %d error lines, frame_failed %d, session_open %d, "
      "session_resume %d, session_close %d, session_detach %d; exit after SIGTERM: %s\n",
      server.WarningCount(), errors, server.EventCount("frame_failed"),
      server.EventCount("session_open"), server.EventCount("session_resume"),
      server.EventCount("session_close"), server.EventCount("session_detach"),
      exit_status.ok() ? absl::StrCat(*exit_status).c_str()
                       : exit_status.status().ToString().c_str());
  if (!exit_status.ok() || *exit_status != 0) {
    fail(absl::StrCat(
        "the server did not drain and exit 0 after SIGTERM: ",
        exit_status.ok() ? absl::StrCat("exit ", *exit_status) : exit_status.status().ToString()));
  }
  if (errors > 0 || server.EventCount("frame_failed") > 0) {
    fail(absl::StrCat("the server logged ", errors, " error lines and ",
                      server.EventCount("frame_failed"), " frame_failed lines; its log ends:\n",
                      server.Tail(20)));
  }
  const double wall =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - started).count();
  std::printf("wall time %.1f s, load average %.2f at the end\n", wall, LoadAverage());

  if (!options.json.empty()) {
    nlohmann::json json = {
        {"sessions", options.sessions},
        {"seconds", options.seconds},
        {"warmup_seconds", options.warmup_seconds},
        {"size", options.size},
        {"steps", options.steps},
        {"cpus", std::thread::hardware_concurrency()},
        {"warmup", CountsJson(warmup.counts)},
        {"load", CountsJson(load.counts)},
        {"load_wall_seconds", load.wall_seconds},
        {"latency_ms",
         {{"p50", latency_p50},
          {"p99", latency_p99},
          {"max", latency_max},
          {"frames", load.latency_ms.size()}}},
        {"server_idle_before", SampleJson(*idle)},
        {"server_baseline", SampleJson(base)},
        {"server_peak_under_load", SampleJson(load.peak)},
        {"server_after", SampleJson(*after)},
        {"rss_growth_mib", growth_mib},
        {"replay",
         {{"sessions", to_replay.size()},
          {"frames", replayed_frames},
          {"compared", compared},
          {"failures", replay_failures},
          {"seconds", replay_seconds}}},
        {"wall_seconds", wall},
        {"load_average_end", LoadAverage()},
        {"failures", failures},
    };
    std::ofstream(options.json) << json.dump(2) << "\n";
  }
  if (!failures.empty()) {
    std::printf("RESULT: FAIL (%zu)\n", failures.size());
    return 1;
  }
  std::printf("RESULT: PASS\n");
  return 0;
}

}  // namespace
}  // namespace fd::bench

int main(int argc, char** argv) { return fd::bench::Main(argc, argv); }
