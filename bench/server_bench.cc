// End-to-end frames/s over loopback gRPC versus the same frames through the
// session engine in-process (session::SessionStore + session::FrameBatcher),
// on the embedded tiny environment. Not a test: nothing is asserted; results
// go to docs/BENCHMARKS.md ("Server: gRPC vs in-process (CPU)").
//
//   fd_server_bench [--sessions 1,8] [--frames F] [--warmup W] [--size S]
//       [--steps K] [--threads T] [--workers W] [--mode grpc|inprocess|both]
//       [--in_flight 1,2] [--repeats R] [--shared_channel] [--verbose]
//       [--batch_invariant] [--json FILE]
//
// --batch_invariant: both paths run the pipeline batch-invariant (the
// server's --batch_invariant), so a frame does not depend on what shared its
// batches, and same_out counts every frame equal although the two paths
// batch differently.
//
// --json writes the run's settings, every printed row and the median ratios
// as one JSON object (bench/run_benchmarks.py collects it).
//
// Both paths use the SAME loaded model object (session::CreateRandomTinyEnvironment,
// fixed seed), the same session settings (ResolveOpenSettings on the same
// OpenSession: size, steps, seed 1000 + session, the environment's sampler
// and sky mode), the same G-buffers (one wire RenderRequest per frame, built
// up front) and the same batcher settings (ServerConfig defaults: step-level
// batching, max_batch_size 8, max_queue_delay 2 ms, max_queue_size 64).
//
//   inprocess  one client thread per session enqueues frame k, waits for its
//              callback, then enqueues frame k+1 (one frame in flight, like a
//              client with max_frames_in_flight 1). The G-buffers were decoded
//              from the wire frames before the clock starts, so this path
//              pays neither wire decoding nor output encoding.
//   grpc       FrameDiffuserServer::Start on 127.0.0.1:0 in this process; one
//              client thread per session, synchronous API, one Render stream
//              each. in_flight 1: write frame k+1 after reading answer k.
//              in_flight 2: keep two frames written ahead (the server decodes
//              the next frame while the current one renders).
//              Channels: one per session, each with its own TCP connection
//              (local subchannel pool); --shared_channel puts every stream on
//              one channel (one HTTP/2 connection).
//
// Each measurement opens fresh sessions, renders W warm-up frames per session
// (excluded), lines the sessions up, then times F frames per session:
// frames/s = sessions * F / wall seconds from the start of the timed phase
// until the last session's last frame. Latency: from handing frame k to the
// engine (Enqueue / stream Write) until its result arrived at the client
// thread (callback / stream Read). Output images are hashed in both paths so
// that the table can say whether the gRPC path rendered the same frames.
//
// Columns besides the obvious: vs_inproc = frames/s over the in-process run of
// the same repeat and session count; cpu_ms/frm = process CPU time (every
// thread) during the timed phase per frame; same_out = frames (warm-up
// included) whose output bytes equal the in-process run's; load = 1-minute
// load average after the row (the machine is shared). --repeats alternates
// the order of the paths and prints the median ratio; --verbose prints every
// frame's stage timings (the server's, for gRPC) to stderr. torch's intra-op
// threads are set in main and on the batcher worker threads (OpenMP keeps
// the setting per thread); OpenMP's and OpenBLAS's own environment variables
// (OMP_WAIT_POLICY, OPENBLAS_CORETYPE) apply as usual, except that with
// neither OMP_WAIT_POLICY nor GOMP_SPINCOUNT set the OpenMP threads get the
// server's bounded spin (model/runtime/cpu_runtime.h), as in
// framediffuser-server.
#include <grpc/grpc.h>
#include <grpcpp/grpcpp.h>
#include <stdlib.h>
#include <sys/resource.h>
#include <torch/torch.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <map>
#include <memory>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_split.h"
#include "absl/synchronization/mutex.h"
#include "framediffuser/v1/render_service.grpc.pb.h"
#include "model/runtime/cpu_runtime.h"
#include "server/embedded_environment.h"
#include "server/frame_input.h"
#include "server/log.h"
#include "server/open_settings.h"
#include "server/server.h"
#include "server/server_config.h"
#include "session/clock.h"
#include "session/environment_registry.h"
#include "session/frame_batcher.h"
#include "session/frame_pipeline_interface.h"
#include "session/random_environment.h"
#include "session/session_state.h"
#include "session/session_store.h"

namespace fd::server {
namespace {

namespace v1 = ::framediffuser::v1;
using Clock = std::chrono::steady_clock;

struct BenchOptions {
  std::vector<int> sessions = {1, 8};
  int frames = 0;  // per session and measurement; 0 = auto (see AutoFrames)
  int warmup = 2;  // per session, excluded
  uint32_t size = session::kRandomEnvironmentSize;
  uint32_t steps = session::kRandomEnvironmentSteps;
  int threads = 0;  // per batcher worker; 0 = as the server: cores / workers
  int workers = 0;  // batcher workers; 0 = as the server: one per core (CPU)
  std::string mode = "both";
  std::vector<int> in_flight = {1, 2};
  int repeats = 1;
  bool shared_channel = false;
  bool verbose = false;
  bool batch_invariant = false;
  std::string json_path;  // --json; empty: no JSON
};

// Every printed row, for --json.
nlohmann::json& JsonRows() {
  static auto* rows = new nlohmann::json(nlohmann::json::array());
  return *rows;
}

// Timed frames per session when --frames is not given: 80 frames in all, which
// is 10-15 s per measurement on the idle 2-core development VM at 128x128, 10
// steps (6-8 frames/s), and up to minutes when other work loads the cores.
int AutoFrames(int sessions) { return std::max(4, 80 / sessions); }

[[noreturn]] void Die(const std::string& what) {
  std::fprintf(stderr, "fd_server_bench: %s\n", what.c_str());
  std::exit(1);
}

// ------------------------------------------------------------------ inputs

uint64_t SplitMix(uint64_t& state) {
  uint64_t z = (state += 0x9e3779b97f4a7c15ULL);
  z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ULL;
  z = (z ^ (z >> 27)) * 0x94d049bb133111ebULL;
  return z ^ (z >> 31);
}

// A uint8 image of pseudo-random bytes drawn from `seed`.
v1::Image NoiseImage(uint32_t size, uint32_t channels, uint64_t seed) {
  v1::Image image;
  image.set_width(size);
  image.set_height(size);
  image.set_channels(channels);
  image.set_dtype(v1::DTYPE_UINT8);
  std::string data(static_cast<size_t>(size) * size * channels, '\0');
  uint64_t state = seed;
  for (size_t i = 0; i < data.size(); i += 8) {
    const uint64_t bits = SplitMix(state);
    std::memcpy(&data[i], &bits, std::min<size_t>(8, data.size() - i));
  }
  image.set_data(std::move(data));
  return image;
}

// Frame `index` of session `session`: every G-buffer plane, seeded by both.
v1::RenderRequest MakeFrame(uint32_t size, int session, uint64_t index) {
  v1::RenderRequest request;
  v1::FrameInput* frame = request.mutable_frame();
  frame->set_frame_index(index);
  const uint64_t seed = (static_cast<uint64_t>(session) << 32) ^ (index * 16);
  v1::GBuffer* gbuffer = frame->mutable_gbuffer();
  *gbuffer->mutable_basecolor() = NoiseImage(size, 3, seed + 1);
  *gbuffer->mutable_normals() = NoiseImage(size, 3, seed + 2);
  *gbuffer->mutable_depth() = NoiseImage(size, 1, seed + 3);
  *gbuffer->mutable_roughness() = NoiseImage(size, 1, seed + 4);
  *gbuffer->mutable_metallic() = NoiseImage(size, 1, seed + 5);
  return request;
}

v1::OpenSession MakeOpen(const BenchOptions& options, int session, int in_flight) {
  v1::OpenSession open;
  open.set_environment(kEmbeddedEnvironmentName);
  open.set_width(options.size);
  open.set_height(options.size);
  open.set_steps(options.steps);
  open.set_seed(1000 + static_cast<uint64_t>(session));
  open.set_max_frames_in_flight(static_cast<uint32_t>(in_flight));
  return open;
}

uint64_t Fnv1a(const void* data, size_t size) {
  uint64_t hash = 0xcbf29ce484222325ULL;
  const auto* bytes = static_cast<const uint8_t*>(data);
  for (size_t i = 0; i < size; ++i) hash = (hash ^ bytes[i]) * 0x100000001b3ULL;
  return hash;
}

// ------------------------------------------------------------ measurement

// Lines the client threads up between the warm-up and the timed phase.
class Gate {
 public:
  explicit Gate(int parties) : waiting_for_(parties) {}
  // Client threads: arrive, then wait for Open().
  void ArriveAndWait() {
    absl::MutexLock lock(&mu_);
    --waiting_for_;
    mu_.Await(absl::Condition(&open_));
  }
  // Main thread: waits until every client arrived, opens, returns the time.
  Clock::time_point AwaitAllAndOpen() {
    absl::MutexLock lock(&mu_);
    mu_.Await(absl::Condition(
        +[](int* n) { return *n == 0; }, &waiting_for_));
    open_ = true;
    return Clock::now();
  }

 private:
  absl::Mutex mu_;
  int waiting_for_ ABSL_GUARDED_BY(mu_);
  bool open_ ABSL_GUARDED_BY(mu_) = false;
};

// What one client thread measured.
struct ClientRecord {
  std::vector<double> latencies_ms;  // timed frames only
  std::vector<uint64_t> hashes;      // every frame's output (warm-up too)
  Clock::time_point finished;
};

struct RunResult {
  std::string mode;
  int sessions = 0;
  int in_flight = 1;
  int frames = 0;  // timed, all sessions
  double seconds = 0;
  double cpu_seconds = 0;  // process CPU time during the timed phase
  std::vector<double> latencies_ms;
  std::vector<std::vector<uint64_t>> hashes;  // [session][frame]
};

RunResult Collect(std::string mode, int in_flight, int frames_per_session, Clock::time_point start,
                  double cpu_seconds, std::vector<ClientRecord>& records) {
  RunResult result;
  result.cpu_seconds = cpu_seconds;
  result.mode = std::move(mode);
  result.sessions = static_cast<int>(records.size());
  result.in_flight = in_flight;
  result.frames = result.sessions * frames_per_session;
  Clock::time_point end = start;
  for (ClientRecord& record : records) {
    end = std::max(end, record.finished);
    result.latencies_ms.insert(result.latencies_ms.end(), record.latencies_ms.begin(),
                               record.latencies_ms.end());
    result.hashes.push_back(std::move(record.hashes));
  }
  result.seconds = std::chrono::duration<double>(end - start).count();
  return result;
}

double Ms(Clock::duration d) { return std::chrono::duration<double, std::milli>(d).count(); }

// User + system CPU seconds of the whole process so far (every thread: the
// clients, gRPC's, the batcher worker and its intra-op threads).
double ProcessCpuSeconds() {
  rusage usage{};
  getrusage(RUSAGE_SELF, &usage);
  auto seconds = [](const timeval& t) { return t.tv_sec + t.tv_usec * 1e-6; };
  return seconds(usage.ru_utime) + seconds(usage.ru_stime);
}

// Makes the batcher worker thread use `threads` intra-op threads too
// (at::set_num_threads is per thread under OpenMP). Used identically in both
// paths; the work is the real ModelFramePipeline's.
class ThreadsPinnedPipeline final : public session::FramePipelineInterface {
 public:
  ThreadsPinnedPipeline(std::shared_ptr<const model::Environment> env, int threads,
                        bool batch_invariant)
      : inner_(std::move(env), Options(batch_invariant)), threads_(threads) {}

  absl::StatusOr<std::vector<model::FrameState>> Begin(
      absl::Span<const model::PipelineInput> items) const override {
    if (at::get_num_threads() != threads_) at::set_num_threads(threads_);
    return inner_.Begin(items);
  }
  absl::Status Step(absl::Span<model::FrameState* const> states) const override {
    return inner_.Step(states);
  }
  absl::StatusOr<std::vector<model::FrameOutput>> Finish(
      absl::Span<model::FrameState* const> states) const override {
    return inner_.Finish(states);
  }

 private:
  static model::FramePipelineOptions Options(bool batch_invariant) {
    model::FramePipelineOptions options;
    options.batch_invariant = batch_invariant;
    return options;
  }
  session::ModelFramePipeline inner_;
  const int threads_;
};

// The server's defaults for everything the two paths share.
ServerConfig BenchConfig() {
  ServerConfig config;
  config.listen = "127.0.0.1:0";
  config.max_steps = 1000;
  config.min_size = 8;
  config.max_size = 4096;
  config.max_sessions_per_client = 1024;
  config.reflection = false;
  return config;
}

SessionLimits LimitsOf(const ServerConfig& config) {
  SessionLimits limits;
  limits.min_size = static_cast<uint32_t>(config.min_size);
  limits.max_size = static_cast<uint32_t>(config.max_size);
  limits.max_steps = static_cast<uint32_t>(config.max_steps);
  limits.max_frames_in_flight = static_cast<uint32_t>(config.max_frames_in_flight);
  return limits;
}

// ------------------------------------------------------------- in-process

RunResult RunInProcess(const BenchOptions& options, std::shared_ptr<const model::Environment> env,
                       const std::vector<std::vector<v1::RenderRequest>>& frames, int timed) {
  const ServerConfig config = BenchConfig();
  const int sessions = static_cast<int>(frames.size());
  session::SessionStoreOptions store_options;
  store_options.max_sessions_per_client = static_cast<size_t>(config.max_sessions_per_client);
  absl::StatusOr<std::unique_ptr<session::SessionStore>> store =
      session::SessionStore::Create(store_options, session::RealClock::Get());
  if (!store.ok()) Die(store.status().ToString());
  session::FrameBatcherOptions batcher_options;
  batcher_options.environment = kEmbeddedEnvironmentName;
  batcher_options.mode = ToBatchingMode(config);
  batcher_options.max_batch_size = config.max_batch_size;
  batcher_options.max_queue_delay = config.max_queue_delay;
  batcher_options.max_queue_size = config.max_queue_size;
  batcher_options.workers = options.workers;
  session::FrameBatcher batcher(
      std::make_unique<ThreadsPinnedPipeline>(env, options.threads, options.batch_invariant),
      batcher_options);
  const session::EnvironmentInfo info =
      session::DescribeEnvironment(kEmbeddedEnvironmentName, "", *env);

  // Sessions and decoded G-buffers, before the clock starts.
  std::vector<std::shared_ptr<session::Session>> all;
  std::vector<std::vector<DecodedFrame>> decoded(sessions);
  for (int i = 0; i < sessions; ++i) {
    absl::StatusOr<session::SessionSettings> settings =
        ResolveOpenSettings(MakeOpen(options, i, 1), info, LimitsOf(config), 0);
    if (!settings.ok()) Die(settings.status().ToString());
    absl::StatusOr<session::SessionState> state =
        session::SessionState::StartFromGBufferOnly(*settings);
    if (!state.ok()) Die(state.status().ToString());
    absl::StatusOr<session::CreatedSession> created = (*store)->Create("", *std::move(state));
    if (!created.ok()) Die(created.status().ToString());
    all.push_back(created->session);
    for (const v1::RenderRequest& request : frames[i]) {
      absl::StatusOr<DecodedFrame> frame = DecodeFrameInput(request.frame(), *settings);
      if (!frame.ok()) Die(frame.status().ToString());
      decoded[i].push_back(*std::move(frame));
    }
  }

  // Where a session's callback leaves its result for the client thread;
  // outlives the batcher's last callback (the worker may still be unlocking
  // `mu` when the client thread moves on).
  struct Mailbox {
    absl::Mutex mu;
    std::optional<absl::StatusOr<session::FrameResult>> result ABSL_GUARDED_BY(mu);
  };
  std::vector<Mailbox> mailboxes(sessions);
  std::vector<ClientRecord> records(sessions);
  Gate gate(sessions);
  std::vector<std::thread> clients;
  for (int i = 0; i < sessions; ++i) {
    clients.emplace_back([&, i] {
      ClientRecord& record = records[i];
      Mailbox& mailbox = mailboxes[i];
      const int total = static_cast<int>(decoded[i].size());
      for (int k = 0; k < total; ++k) {
        if (k == total - timed) gate.ArriveAndWait();
        session::FrameJob job;
        job.session = all[i];
        job.frame_index = frames[i][k].frame().frame_index();
        job.gbuffer = decoded[i][k].gbuffer;
        job.done = [&mailbox](absl::StatusOr<session::FrameResult> r) {
          absl::MutexLock lock(&mailbox.mu);
          mailbox.result = std::move(r);
        };
        const Clock::time_point sent = Clock::now();
        if (absl::Status queued = batcher.Enqueue(std::move(job)); !queued.ok()) {
          Die(queued.ToString());
        }
        absl::StatusOr<session::FrameResult> result;
        {
          absl::MutexLock lock(&mailbox.mu);
          mailbox.mu.Await(absl::Condition(
              +[](std::optional<absl::StatusOr<session::FrameResult>>* r) {
                return r->has_value();
              },
              &mailbox.result));
          result = *std::move(mailbox.result);
          mailbox.result.reset();
        }
        const Clock::time_point received = Clock::now();
        if (!result.ok()) Die(result.status().ToString());
        record.hashes.push_back(Fnv1a(result->image.data(), result->image.size_bytes()));
        if (k >= total - timed) record.latencies_ms.push_back(Ms(received - sent));
        if (options.verbose) {
          const session::FrameTimings& t = result->timings;
          std::fprintf(stderr,
                       "in-process session %d frame %d: client %.1f ms (queue %.1f, encode %.1f, "
                       "denoise %.1f, decode %.1f, batch %d)\n",
                       i, k, Ms(received - sent), t.queue_ms, t.encode_ms, t.denoise_ms,
                       t.decode_ms, t.batch_size);
        }
      }
      record.finished = Clock::now();
    });
  }
  const double cpu_start = ProcessCpuSeconds();
  const Clock::time_point start = gate.AwaitAllAndOpen();
  for (std::thread& client : clients) client.join();
  RunResult result =
      Collect("in-process", 1, timed, start, ProcessCpuSeconds() - cpu_start, records);
  for (const auto& session : all) (void)(*store)->Close(session->id());
  batcher.Shutdown();
  return result;
}

// ------------------------------------------------------------------- gRPC

std::shared_ptr<grpc::Channel> MakeChannel(const std::string& address) {
  grpc::ChannelArguments args;
  args.SetMaxReceiveMessageSize(-1);
  args.SetMaxSendMessageSize(-1);
  // Its own subchannel, hence its own TCP connection (channels with equal
  // arguments share one otherwise).
  args.SetInt(GRPC_ARG_USE_LOCAL_SUBCHANNEL_POOL, 1);
  return grpc::CreateCustomChannel(address, grpc::InsecureChannelCredentials(), args);
}

RunResult RunGrpc(const BenchOptions& options, const FrameDiffuserServer& server, int in_flight,
                  const std::vector<std::vector<v1::RenderRequest>>& frames, int timed) {
  const int sessions = static_cast<int>(frames.size());
  std::shared_ptr<grpc::Channel> shared =
      options.shared_channel ? MakeChannel(server.address()) : nullptr;
  std::vector<ClientRecord> records(sessions);
  Gate gate(sessions);
  std::vector<std::thread> clients;
  for (int i = 0; i < sessions; ++i) {
    clients.emplace_back([&, i] {
      ClientRecord& record = records[i];
      std::shared_ptr<grpc::Channel> channel = shared ? shared : MakeChannel(server.address());
      std::unique_ptr<v1::FrameDiffuser::Stub> stub = v1::FrameDiffuser::NewStub(channel);
      grpc::ClientContext context;
      std::unique_ptr<grpc::ClientReaderWriter<v1::RenderRequest, v1::RenderResponse>> stream =
          stub->Render(&context);
      v1::RenderRequest open;
      *open.mutable_open() = MakeOpen(options, i, in_flight);
      v1::RenderResponse response;
      if (!stream->Write(open) || !stream->Read(&response) || !response.has_opened()) {
        Die("session " + std::to_string(i) + ": open failed: " + stream->Finish().error_message());
      }
      if (response.opened().settings().max_frames_in_flight() != static_cast<uint32_t>(in_flight)) {
        Die("the server capped max_frames_in_flight below " + std::to_string(in_flight));
      }
      const int total = static_cast<int>(frames[i].size());
      std::vector<Clock::time_point> sent(total);
      // One phase: frames [begin, end) with at most `in_flight` outstanding,
      // all answered before it returns.
      auto run_phase = [&](int begin, int end, bool timed_phase) {
        int written = begin;
        for (int k = begin; k < end; ++k) {
          while (written < end && written < k + in_flight) {
            sent[written] = Clock::now();
            if (!stream->Write(frames[i][written])) Die("stream write failed");
            ++written;
          }
          if (!stream->Read(&response)) Die("stream ended: " + stream->Finish().error_message());
          const Clock::time_point received = Clock::now();
          if (!response.has_frame()) Die("unexpected response: " + response.DebugString());
          if (response.frame().frame_index() != frames[i][k].frame().frame_index()) {
            Die("answers out of order");
          }
          const std::string& data = response.frame().image().data();
          record.hashes.push_back(Fnv1a(data.data(), data.size()));
          if (timed_phase) record.latencies_ms.push_back(Ms(received - sent[k]));
          if (options.verbose) {
            const v1::StageTimings& t = response.frame().timings();
            std::fprintf(stderr,
                         "grpc session %d frame %d: client %.1f ms, server total %.1f ms "
                         "(queue %.1f, encode %.1f, denoise %.1f, decode %.1f, batch %u)\n",
                         i, k, Ms(received - sent[k]), t.total_ms(), t.queue_ms(), t.encode_ms(),
                         t.denoise_ms(), t.decode_ms(), t.batch_size());
          }
        }
      };
      run_phase(0, total - timed, false);
      gate.ArriveAndWait();
      run_phase(total - timed, total, true);
      record.finished = Clock::now();
      stream->WritesDone();
      while (stream->Read(&response)) {
      }
      const grpc::Status status = stream->Finish();
      if (!status.ok()) Die("stream finished with " + status.error_message());
    });
  }
  // The clients are all waiting at the gate: from here on the process
  // only works on timed frames.
  const double cpu_start = ProcessCpuSeconds();
  const Clock::time_point start = gate.AwaitAllAndOpen();
  for (std::thread& client : clients) client.join();
  return Collect("grpc", in_flight, timed, start, ProcessCpuSeconds() - cpu_start, records);
}

// ------------------------------------------------------------------ output

double Percentile(std::vector<double> values, double p) {
  if (values.empty()) return 0;
  std::sort(values.begin(), values.end());
  // Nearest rank.
  size_t rank = static_cast<size_t>(std::ceil(p / 100.0 * static_cast<double>(values.size())));
  rank = std::clamp<size_t>(rank, 1, values.size());
  return values[rank - 1];
}

double Mean(const std::vector<double>& values) {
  double sum = 0;
  for (double v : values) sum += v;
  return values.empty() ? 0 : sum / static_cast<double>(values.size());
}

double LoadAverage() {
  double load[1] = {0};
  return getloadavg(load, 1) == 1 ? load[0] : -1;
}

void PrintHeader() {
  std::printf("%-10s %8s %9s %6s %7s %8s %8s %8s %8s %9s %10s %10s %5s\n", "mode", "sessions",
              "in_flight", "frames", "seconds", "frames/s", "mean_ms", "p50_ms", "p99_ms",
              "vs_inproc", "cpu_ms/frm", "same_out", "load");
}

// `baseline`: the in-process run of the same repeat and session count.
void PrintRow(const RunResult& r, const RunResult* baseline) {
  const double fps = r.frames / r.seconds;
  std::string ratio = "-";
  std::string same = "-";
  nlohmann::json row = {{"mode", r.mode},
                        {"sessions", r.sessions},
                        {"in_flight", r.in_flight},
                        {"frames", r.frames},
                        {"seconds", r.seconds},
                        {"frames_per_second", fps},
                        {"latency_mean_ms", Mean(r.latencies_ms)},
                        {"latency_p50_ms", Percentile(r.latencies_ms, 50)},
                        {"latency_p99_ms", Percentile(r.latencies_ms, 99)},
                        {"cpu_ms_per_frame", 1000.0 * r.cpu_seconds / r.frames},
                        {"load_average", LoadAverage()}};
  if (baseline != nullptr && r.mode != "in-process") {
    char text[32];
    const double vs = fps / (baseline->frames / baseline->seconds);
    std::snprintf(text, sizeof(text), "%.3f", vs);
    ratio = text;
    row["vs_inprocess"] = vs;
    int equal = 0;
    int total = 0;
    for (size_t s = 0; s < r.hashes.size() && s < baseline->hashes.size(); ++s) {
      for (size_t f = 0; f < r.hashes[s].size() && f < baseline->hashes[s].size(); ++f) {
        ++total;
        equal += r.hashes[s][f] == baseline->hashes[s][f] ? 1 : 0;
      }
    }
    same = std::to_string(equal) + "/" + std::to_string(total);
    row["same_output_frames"] = equal;
    row["compared_frames"] = total;
  }
  JsonRows().push_back(std::move(row));
  std::printf("%-10s %8d %9d %6d %7.2f %8.3f %8.1f %8.1f %8.1f %9s %10.1f %10s %5.2f\n",
              r.mode.c_str(), r.sessions, r.in_flight, r.frames, r.seconds, fps,
              Mean(r.latencies_ms), Percentile(r.latencies_ms, 50), Percentile(r.latencies_ms, 99),
              ratio.c_str(), 1000.0 * r.cpu_seconds / r.frames, same.c_str(), LoadAverage());
  std::fflush(stdout);
}

// ------------------------------------------------------------------- flags

std::vector<int> ParseList(const std::string& flag, const std::string& text) {
  std::vector<int> values;
  for (absl::string_view part : absl::StrSplit(text, ',')) {
    int value = 0;
    if (!absl::SimpleAtoi(part, &value) || value < 1) {
      Die(flag + ": expected positive integers separated by commas, got '" + text + "'");
    }
    values.push_back(value);
  }
  return values;
}

int ParseInt(const std::string& flag, const std::string& text, int min) {
  int value = 0;
  if (!absl::SimpleAtoi(text, &value) || value < min) {
    Die(flag + ": expected an integer >= " + std::to_string(min) + ", got '" + text + "'");
  }
  return value;
}

constexpr char kUsage[] =
    "usage: fd_server_bench [--sessions N[,N...]] [--frames F] [--warmup W] [--size S]\n"
    "           [--steps K] [--threads T] [--workers W] [--mode grpc|inprocess|both]\n"
    "           [--in_flight D[,D...]]\n"
    "           [--repeats R] [--shared_channel] [--verbose] [--batch_invariant]\n"
    "           [--json FILE]\n"
    "defaults: --sessions 1,8 --frames auto (80/N per session: 80 at 1 session, 10 at 8)\n"
    "          --warmup 2 --size 128 --steps 10 --mode both --in_flight 1,2\n"
    "          --workers and --threads as the server's auto: one worker per core (at most\n"
    "          max_batch_size), cores / workers threads each\n"
    "          --repeats 1\n";

BenchOptions ParseFlags(int argc, char** argv) {
  BenchOptions options;
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
      if (i + 1 >= argc) Die(flag + ": missing value");
      return argv[++i];
    };
    if (flag == "--help" || flag == "-h") {
      std::printf("%s", kUsage);
      std::exit(0);
    } else if (flag == "--sessions") {
      options.sessions = ParseList(flag, next());
    } else if (flag == "--frames") {
      options.frames = ParseInt(flag, next(), 1);
    } else if (flag == "--warmup") {
      options.warmup = ParseInt(flag, next(), 0);
    } else if (flag == "--size") {
      options.size = static_cast<uint32_t>(ParseInt(flag, next(), 8));
    } else if (flag == "--steps") {
      options.steps = static_cast<uint32_t>(ParseInt(flag, next(), 1));
    } else if (flag == "--threads") {
      options.threads = ParseInt(flag, next(), 1);
    } else if (flag == "--workers") {
      options.workers = ParseInt(flag, next(), 1);
    } else if (flag == "--mode") {
      options.mode = next();
      if (options.mode != "grpc" && options.mode != "inprocess" && options.mode != "both") {
        Die("--mode: expected grpc, inprocess or both, got '" + options.mode + "'");
      }
    } else if (flag == "--in_flight") {
      options.in_flight = ParseList(flag, next());
    } else if (flag == "--repeats") {
      options.repeats = ParseInt(flag, next(), 1);
    } else if (flag == "--shared_channel") {
      options.shared_channel = true;
    } else if (flag == "--verbose") {
      options.verbose = true;
    } else if (flag == "--batch_invariant") {
      options.batch_invariant = true;
    } else if (flag == "--json") {
      options.json_path = next();
    } else {
      Die("unknown flag " + flag + "\n" + kUsage);
    }
  }
  return options;
}

}  // namespace
}  // namespace fd::server

int main(int argc, char** argv) {
  // As framediffuser-server: OpenMP threads sleep when idle (may re-execute).
  fd::model::UseBoundedOpenMpSpin(argv);
  using namespace fd::server;
  BenchOptions options = ParseFlags(argc, argv);
  // The server's auto settings (server.cc), used by both paths.
  const int cores = static_cast<int>(std::max(1u, std::thread::hardware_concurrency()));
  if (options.workers == 0) options.workers = std::min(cores, BenchConfig().max_batch_size);
  if (options.threads == 0) options.threads = std::max(1, cores / options.workers);
  const std::string malloc_tuning = fd::model::TuneMallocForInference();
  const std::string blas_threads = fd::model::UseSingleThreadedBlas();
  at::set_num_threads(options.threads);
  if (!options.verbose) SetLogSink([](std::string_view) {});  // session open/close lines

  absl::StatusOr<std::shared_ptr<fd::model::Environment>> created =
      fd::session::CreateRandomTinyEnvironment(fd::model::EnvironmentOptions{});
  if (!created.ok()) Die(created.status().ToString());
  const std::shared_ptr<const fd::model::Environment> env = *created;

  const bool run_inprocess = options.mode != "grpc";
  const bool run_grpc = options.mode != "inprocess";
  std::unique_ptr<FrameDiffuserServer> server;
  if (run_grpc) {
    ServerOptions server_options;
    server_options.config = BenchConfig();
    server_options.config.scheduler_workers = options.workers;
    server_options.config.batch_invariant = options.batch_invariant;
    server_options.environments.emplace_back(kEmbeddedEnvironmentName, env);
    const int threads = options.threads;
    const bool batch_invariant = options.batch_invariant;
    server_options.pipeline_factory =
        [threads, batch_invariant](std::shared_ptr<const fd::model::Environment> e) {
          return std::make_unique<ThreadsPinnedPipeline>(std::move(e), threads, batch_invariant);
        };
    absl::StatusOr<std::unique_ptr<FrameDiffuserServer>> started =
        FrameDiffuserServer::Start(std::move(server_options));
    if (!started.ok()) Die(started.status().ToString());
    server = *std::move(started);
  }

  const ServerConfig config = BenchConfig();
  const char* coretype = std::getenv("OPENBLAS_CORETYPE");
  std::printf(
      "fd_server_bench: the tiny test environment (random weights, seed %llu), %ux%u, %u steps, "
      "UniPC, sky previous_output\n",
      static_cast<unsigned long long>(fd::session::kRandomEnvironmentSeed), options.size,
      options.size, options.steps);
  std::printf(
      "batcher: %s batching, max_batch_size %d, max_queue_delay %s, max_queue_size %d "
      "(both paths)\n",
      config.batching == "step" ? "step-level" : "whole-frame", config.max_batch_size,
      absl::FormatDuration(config.max_queue_delay).c_str(), config.max_queue_size);
  std::printf(
      "%d batcher worker(s) x %d torch intra-op threads%s, OPENBLAS_CORETYPE=%s, %u CPUs,"
      " load average %.2f at start (shared machine); %s; %s\n",
      options.workers, options.threads, options.batch_invariant ? ", batch-invariant" : "",
      coretype != nullptr ? coretype : "(unset)", std::thread::hardware_concurrency(),
      LoadAverage(), malloc_tuning.c_str(), blas_threads.c_str());
  std::printf("warm-up %d frames/session excluded; grpc: 127.0.0.1, sync API, %s\n", options.warmup,
              options.shared_channel ? "one shared channel"
                                     : "one channel (own TCP connection) per session");
  PrintHeader();

  std::map<int, std::vector<double>> ratios;  // key: sessions * 100 + in_flight
  for (int repeat = 0; repeat < options.repeats; ++repeat) {
    for (int sessions : options.sessions) {
      const int timed = options.frames > 0 ? options.frames : AutoFrames(sessions);
      std::vector<std::vector<framediffuser::v1::RenderRequest>> frames(sessions);
      for (int i = 0; i < sessions; ++i) {
        for (int k = 0; k < options.warmup + timed; ++k) {
          frames[i].push_back(MakeFrame(options.size, i, static_cast<uint64_t>(k)));
        }
      }
      // Odd repeats run the gRPC measurements first, so that load that
      // drifts over a repeat does not always favour the same path. Rows are
      // printed as they finish; ratios once both sides exist.
      std::optional<RunResult> baseline;
      std::vector<RunResult> grpc_runs;
      auto run_inprocess_now = [&] {
        baseline = RunInProcess(options, env, frames, timed);
        PrintRow(*baseline, nullptr);
      };
      if (run_inprocess && repeat % 2 == 0) run_inprocess_now();
      if (run_grpc) {
        for (int in_flight : options.in_flight) {
          grpc_runs.push_back(RunGrpc(options, *server, in_flight, frames, timed));
          if (baseline || !run_inprocess)
            PrintRow(grpc_runs.back(), baseline ? &*baseline : nullptr);
        }
      }
      if (run_inprocess && repeat % 2 == 1) {
        run_inprocess_now();
        for (const RunResult& r : grpc_runs) PrintRow(r, &*baseline);
      }
      if (baseline) {
        for (const RunResult& r : grpc_runs) {
          ratios[sessions * 100 + r.in_flight].push_back((r.frames / r.seconds) /
                                                         (baseline->frames / baseline->seconds));
        }
      }
    }
  }
  nlohmann::json medians = nlohmann::json::array();
  for (auto& [key, values] : ratios) {
    medians.push_back({{"sessions", key / 100},
                       {"in_flight", key % 100},
                       {"repeats", values.size()},
                       {"median_vs_inprocess", Percentile(values, 50)}});
  }
  if (options.repeats > 1 && !ratios.empty()) {
    std::printf("median grpc/in-process frames/s ratio over %d repeats:\n", options.repeats);
    for (auto& [key, values] : ratios) {
      std::printf("  sessions %d in_flight %d: %.3f\n", key / 100, key % 100,
                  Percentile(values, 50));
    }
  }
  if (server != nullptr) server->Shutdown(absl::Seconds(5));
  if (!options.json_path.empty()) {
    const nlohmann::json out = {{"benchmark", "fd_server_bench"},
                                {"settings",
                                 {{"environment", "embedded tiny (random weights)"},
                                  {"size", options.size},
                                  {"steps", options.steps},
                                  {"threads", options.threads},
                                  {"workers", options.workers},
                                  {"batch_invariant", options.batch_invariant},
                                  {"warmup_frames_per_session", options.warmup},
                                  {"shared_channel", options.shared_channel},
                                  {"batching", config.batching},
                                  {"max_batch_size", config.max_batch_size},
                                  {"openblas_coretype", coretype != nullptr ? coretype : ""},
                                  {"malloc", malloc_tuning},
                                  {"blas", blas_threads},
                                  {"cpus", std::thread::hardware_concurrency()}}},
                                {"rows", JsonRows()},
                                {"median_ratios", medians}};
    std::ofstream file(options.json_path);
    file << out.dump(2) << "\n";
    if (!file) Die("--json: cannot write " + options.json_path);
  }
  return 0;
}
