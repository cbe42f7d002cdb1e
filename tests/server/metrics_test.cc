// ServerMetrics: every family after events, label values, outcome mapping,
// cardinality (no per-session labels), the /metrics exposer on port 0 and a
// promtool lint of a real scrape; session::DeviceMemoryInUseBytes.
#include "server/metrics.h"

#include <arpa/inet.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <map>
#include <optional>
#include <set>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "prometheus/client_metric.h"
#include "prometheus/metric_family.h"
#include "prometheus/registry.h"

namespace fd::server {
namespace {

using ::testing::HasSubstr;
using ::testing::IsEmpty;
using ::testing::Not;

BuildInfo TestBuild() { return {"0.1.0", "abc1234", "1.13.1", "cpu"}; }

// label name -> value, compared as a whole against a metric's labels.
using LabelMap = std::map<std::string, std::string>;

std::optional<prometheus::ClientMetric> Find(const ServerMetrics& metrics, const std::string& name,
                                             const LabelMap& labels) {
  for (const prometheus::MetricFamily& family : metrics.registry()->Collect()) {
    if (family.name != name) continue;
    for (const prometheus::ClientMetric& metric : family.metric) {
      LabelMap got;
      for (const auto& label : metric.label) got[label.name] = label.value;
      if (got == labels) return metric;
    }
  }
  return std::nullopt;
}

double CounterValue(const ServerMetrics& metrics, const std::string& name, const LabelMap& labels) {
  const auto metric = Find(metrics, name, labels);
  EXPECT_TRUE(metric.has_value()) << name << " with the given labels is missing";
  return metric ? metric->counter.value : -1;
}

double GaugeValue(const ServerMetrics& metrics, const std::string& name, const LabelMap& labels) {
  const auto metric = Find(metrics, name, labels);
  EXPECT_TRUE(metric.has_value()) << name << " with the given labels is missing";
  return metric ? metric->gauge.value : -1;
}

// Every event kind once or more, so every family has a sample.
void RecordEveryEvent(ServerMetrics& metrics) {
  metrics.SetEnvironmentState("street", "loading");
  metrics.OnModelLoad("street", /*ok=*/true, 1.5);
  metrics.SetEnvironmentState("street", "ready");
  metrics.OnModelLoad("broken", /*ok=*/false, 0.2);
  metrics.SetEnvironmentState("broken", "failed");
  metrics.OnStreamStarted();
  metrics.OnStreamStarted();
  metrics.OnStreamEnded(absl::StatusCode::kOk);
  metrics.OnOpened("street");
  metrics.OnOpened("street");
  metrics.OnResumed("street");
  metrics.OnEnded("street", session::EndReason::kClosed);
  metrics.OnRejected("", session::RejectReason::kPermissionDenied);
  metrics.OnQueueDepth("street", 3);
  metrics.OnStepBatch("street", 3);
  session::FrameTimings timings;
  timings.queue_ms = 2;
  timings.encode_ms = 30;
  timings.denoise_ms = 400;
  timings.decode_ms = 50;
  timings.total_ms = 482;
  timings.batch_size = 3;
  metrics.OnFrameDone("street", absl::StatusCode::kOk, timings);
  metrics.OnFrameDone("street", absl::StatusCode::kCancelled, {});
  metrics.OnRejected("street", absl::StatusCode::kResourceExhausted);
  metrics.OnFrameRejectedByServer("street", absl::StatusCode::kInvalidArgument);
  metrics.UpdateDeviceMemory("cpu");
}

TEST(ServerMetricsTest, EveryFamilyIsPresentWithHelpAfterEvents) {
  ServerMetrics metrics(TestBuild());
  RecordEveryEvent(metrics);
  std::set<std::string> names;
  for (const prometheus::MetricFamily& family : metrics.registry()->Collect()) {
    EXPECT_FALSE(family.help.empty()) << family.name;
    EXPECT_FALSE(family.metric.empty()) << family.name << " has no sample";
    EXPECT_TRUE(absl::StartsWith(family.name, "framediffuser_")) << family.name;
    names.insert(family.name);
  }
  for (const char* name : {
           "framediffuser_build_info",
           "framediffuser_frames_total",
           "framediffuser_frame_stage_seconds",
           "framediffuser_step_batch_size",
           "framediffuser_queue_depth",
           "framediffuser_active_sessions",
           "framediffuser_sessions_opened_total",
           "framediffuser_sessions_resumed_total",
           "framediffuser_sessions_ended_total",
           "framediffuser_sessions_rejected_total",
           "framediffuser_model_loads_total",
           "framediffuser_model_load_seconds",
           "framediffuser_environment_state",
           "framediffuser_streams_open",
           "framediffuser_streams_ended_total",
           "framediffuser_device_memory_in_use_bytes",
       }) {
    EXPECT_EQ(names.count(name), 1u) << name;
  }
}

TEST(ServerMetricsTest, BuildInfoIsOneWithTheBuildLabels) {
  ServerMetrics metrics(TestBuild());
  EXPECT_EQ(GaugeValue(metrics, "framediffuser_build_info",
                       {{"version", "0.1.0"},
                        {"git_commit", "abc1234"},
                        {"torch_version", "1.13.1"},
                        {"device", "cpu"}}),
            1);
  EXPECT_THAT(metrics.Scrape(), HasSubstr("# HELP framediffuser_build_info "));
}

TEST(ServerMetricsTest, FrameOutcomesMapToStatusCodeNames) {
  ServerMetrics metrics(TestBuild());
  RecordEveryEvent(metrics);
  metrics.OnFrameDone("street", absl::StatusCode::kInternal, {});
  metrics.OnFrameDone("street", absl::StatusCode::kOk, {});
  metrics.OnRejected("street", absl::StatusCode::kUnavailable);
  metrics.OnFrameRejectedByServer("other", absl::StatusCode::kFailedPrecondition);
  const std::string family = "framediffuser_frames_total";
  EXPECT_EQ(CounterValue(metrics, family, {{"environment", "street"}, {"outcome", "ok"}}), 2);
  EXPECT_EQ(CounterValue(metrics, family, {{"environment", "street"}, {"outcome", "cancelled"}}),
            1);
  EXPECT_EQ(CounterValue(metrics, family, {{"environment", "street"}, {"outcome", "internal"}}), 1);
  EXPECT_EQ(
      CounterValue(metrics, family, {{"environment", "street"}, {"outcome", "resource_exhausted"}}),
      1);
  EXPECT_EQ(
      CounterValue(metrics, family, {{"environment", "street"}, {"outcome", "invalid_argument"}}),
      1);
  EXPECT_EQ(CounterValue(metrics, family, {{"environment", "street"}, {"outcome", "unavailable"}}),
            1);
  EXPECT_EQ(
      CounterValue(metrics, family, {{"environment", "other"}, {"outcome", "failed_precondition"}}),
      1);
  // Only outcomes that happened have a series.
  EXPECT_FALSE(
      Find(metrics, family, {{"environment", "street"}, {"outcome", "not_found"}}).has_value());
}

TEST(ServerMetricsTest, StatusCodeLabelIsLowercaseCanonicalName) {
  EXPECT_EQ(StatusCodeLabel(absl::StatusCode::kOk), "ok");
  EXPECT_EQ(StatusCodeLabel(absl::StatusCode::kCancelled), "cancelled");
  EXPECT_EQ(StatusCodeLabel(absl::StatusCode::kDeadlineExceeded), "deadline_exceeded");
  EXPECT_EQ(StatusCodeLabel(absl::StatusCode::kUnauthenticated), "unauthenticated");
  EXPECT_EQ(StatusCodeLabel(static_cast<absl::StatusCode>(99)), "unknown");
}

TEST(ServerMetricsTest, StageHistogramsInSecondsOnlyForOkFrames) {
  ServerMetrics metrics(TestBuild());
  RecordEveryEvent(metrics);  // one OK frame, one cancelled
  session::FrameTimings partial;
  partial.queue_ms = 5;
  metrics.OnFrameDone("street", absl::StatusCode::kInternal, partial);
  const std::map<std::string, double> expected_seconds = {
      {"queue", 0.002}, {"encode", 0.030}, {"denoise", 0.400}, {"decode", 0.050}, {"total", 0.482}};
  for (const auto& [stage, seconds] : expected_seconds) {
    const auto metric = Find(metrics, "framediffuser_frame_stage_seconds",
                             {{"environment", "street"}, {"stage", stage}});
    ASSERT_TRUE(metric.has_value()) << stage;
    EXPECT_EQ(metric->histogram.sample_count, 1u) << stage;
    EXPECT_NEAR(metric->histogram.sample_sum, seconds, 1e-12) << stage;
    // Buckets span 1 ms .. 60 s (+Inf).
    ASSERT_GE(metric->histogram.bucket.size(), 2u);
    EXPECT_DOUBLE_EQ(metric->histogram.bucket.front().upper_bound, 0.001);
    EXPECT_DOUBLE_EQ(metric->histogram.bucket[metric->histogram.bucket.size() - 2].upper_bound, 60);
  }
}

TEST(ServerMetricsTest, StepBatchSizeHistogramBuckets) {
  ServerMetrics metrics(TestBuild());
  metrics.OnStepBatch("street", 3);
  metrics.OnStepBatch("street", 64);
  const auto metric = Find(metrics, "framediffuser_step_batch_size", {{"environment", "street"}});
  ASSERT_TRUE(metric.has_value());
  EXPECT_EQ(metric->histogram.sample_count, 2u);
  EXPECT_EQ(metric->histogram.sample_sum, 67);
  for (const auto& bucket : metric->histogram.bucket) {
    const uint64_t expected = bucket.upper_bound < 3 ? 0 : bucket.upper_bound < 64 ? 1 : 2;
    EXPECT_EQ(bucket.cumulative_count, expected) << "le=" << bucket.upper_bound;
  }
  EXPECT_DOUBLE_EQ(metric->histogram.bucket.front().upper_bound, 1);
}

TEST(ServerMetricsTest, SessionCountersAndActiveGauge) {
  ServerMetrics metrics(TestBuild());
  metrics.OnOpened("street");
  metrics.OnOpened("street");
  metrics.OnOpened("street");
  metrics.OnOpened("room");
  metrics.OnResumed("street");
  metrics.OnEnded("street", session::EndReason::kClosed);
  metrics.OnEnded("street", session::EndReason::kExpired);
  metrics.OnEnded("room", session::EndReason::kEvicted);
  metrics.OnRejected("street", session::RejectReason::kEnvironmentLimit);
  metrics.OnRejected("", session::RejectReason::kPermissionDenied);

  EXPECT_EQ(GaugeValue(metrics, "framediffuser_active_sessions", {{"environment", "street"}}), 1);
  EXPECT_EQ(GaugeValue(metrics, "framediffuser_active_sessions", {{"environment", "room"}}), 0);
  EXPECT_EQ(
      CounterValue(metrics, "framediffuser_sessions_opened_total", {{"environment", "street"}}), 3);
  EXPECT_EQ(
      CounterValue(metrics, "framediffuser_sessions_resumed_total", {{"environment", "street"}}),
      1);
  const std::string ended = "framediffuser_sessions_ended_total";
  EXPECT_EQ(CounterValue(metrics, ended, {{"environment", "street"}, {"reason", "closed"}}), 1);
  EXPECT_EQ(CounterValue(metrics, ended, {{"environment", "street"}, {"reason", "expired"}}), 1);
  EXPECT_EQ(CounterValue(metrics, ended, {{"environment", "room"}, {"reason", "evicted"}}), 1);
  const std::string rejected = "framediffuser_sessions_rejected_total";
  EXPECT_EQ(
      CounterValue(metrics, rejected, {{"environment", "street"}, {"reason", "environment_limit"}}),
      1);
  EXPECT_EQ(CounterValue(metrics, rejected, {{"environment", ""}, {"reason", "permission_denied"}}),
            1);
  // A rejection with no environment creates no active-sessions series.
  EXPECT_FALSE(Find(metrics, "framediffuser_active_sessions", {{"environment", ""}}).has_value());
}

TEST(ServerMetricsTest, QueueDepthGaugeFollowsTheLatestValue) {
  ServerMetrics metrics(TestBuild());
  metrics.OnQueueDepth("street", 5);
  metrics.OnQueueDepth("street", 2);
  metrics.OnQueueDepth("room", 7);
  EXPECT_EQ(GaugeValue(metrics, "framediffuser_queue_depth", {{"environment", "street"}}), 2);
  EXPECT_EQ(GaugeValue(metrics, "framediffuser_queue_depth", {{"environment", "room"}}), 7);
}

TEST(ServerMetricsTest, ModelLoadsAndEnvironmentState) {
  ServerMetrics metrics(TestBuild());
  metrics.SetEnvironmentState("street", "loading");
  metrics.OnModelLoad("street", /*ok=*/false, 0.5);
  metrics.OnModelLoad("street", /*ok=*/true, 12);
  metrics.SetEnvironmentState("street", "ready");
  EXPECT_EQ(CounterValue(metrics, "framediffuser_model_loads_total",
                         {{"environment", "street"}, {"outcome", "ok"}}),
            1);
  EXPECT_EQ(CounterValue(metrics, "framediffuser_model_loads_total",
                         {{"environment", "street"}, {"outcome", "error"}}),
            1);
  const auto seconds =
      Find(metrics, "framediffuser_model_load_seconds", {{"environment", "street"}});
  ASSERT_TRUE(seconds.has_value());
  EXPECT_EQ(seconds->histogram.sample_count, 2u);
  EXPECT_DOUBLE_EQ(seconds->histogram.sample_sum, 12.5);
  for (const char* state : {"loading", "ready", "failed", "unloading"}) {
    EXPECT_EQ(GaugeValue(metrics, "framediffuser_environment_state",
                         {{"environment", "street"}, {"state", state}}),
              std::string(state) == "ready" ? 1 : 0)
        << state;
  }
}

TEST(ServerMetricsTest, AKnownEnvironmentStartsItsMainSeriesAtZero) {
  ServerMetrics metrics(TestBuild());
  metrics.SetEnvironmentState("street", "ready");
  const LabelMap env = {{"environment", "street"}};
  EXPECT_EQ(CounterValue(metrics, "framediffuser_frames_total",
                         {{"environment", "street"}, {"outcome", "ok"}}),
            0);
  EXPECT_EQ(CounterValue(metrics, "framediffuser_sessions_opened_total", env), 0);
  EXPECT_EQ(GaugeValue(metrics, "framediffuser_active_sessions", env), 0);
  EXPECT_EQ(GaugeValue(metrics, "framediffuser_queue_depth", env), 0);
  EXPECT_EQ(CounterValue(metrics, "framediffuser_model_loads_total",
                         {{"environment", "street"}, {"outcome", "ok"}}),
            0);
  EXPECT_EQ(CounterValue(metrics, "framediffuser_model_loads_total",
                         {{"environment", "street"}, {"outcome", "error"}}),
            0);
  metrics.OnOpened("street");
  EXPECT_EQ(GaugeValue(metrics, "framediffuser_active_sessions", env), 1);
}

TEST(ServerMetricsTest, RemoveEnvironmentDropsItsGaugesKeepsCounters) {
  ServerMetrics metrics(TestBuild());
  RecordEveryEvent(metrics);
  metrics.OnQueueDepth("room", 1);
  metrics.RemoveEnvironment("street");
  metrics.RemoveEnvironment("never-existed");  // no-op
  EXPECT_FALSE(Find(metrics, "framediffuser_queue_depth", {{"environment", "street"}}).has_value());
  EXPECT_FALSE(
      Find(metrics, "framediffuser_active_sessions", {{"environment", "street"}}).has_value());
  EXPECT_FALSE(Find(metrics, "framediffuser_environment_state",
                    {{"environment", "street"}, {"state", "ready"}})
                   .has_value());
  EXPECT_EQ(GaugeValue(metrics, "framediffuser_queue_depth", {{"environment", "room"}}), 1);
  EXPECT_EQ(CounterValue(metrics, "framediffuser_frames_total",
                         {{"environment", "street"}, {"outcome", "ok"}}),
            1);
  // Re-added: its gauges come back, fresh.
  metrics.SetEnvironmentState("street", "loading");
  metrics.OnOpened("street");
  EXPECT_EQ(GaugeValue(metrics, "framediffuser_environment_state",
                       {{"environment", "street"}, {"state", "loading"}}),
            1);
  EXPECT_EQ(GaugeValue(metrics, "framediffuser_active_sessions", {{"environment", "street"}}), 1);
}

TEST(ServerMetricsTest, StreamsOpenAndEndedByCode) {
  ServerMetrics metrics(TestBuild());
  metrics.OnStreamStarted();
  metrics.OnStreamStarted();
  metrics.OnStreamStarted();
  metrics.OnStreamEnded(absl::StatusCode::kOk);
  metrics.OnStreamEnded(absl::StatusCode::kUnauthenticated);
  EXPECT_EQ(GaugeValue(metrics, "framediffuser_streams_open", {}), 1);
  EXPECT_EQ(CounterValue(metrics, "framediffuser_streams_ended_total", {{"code", "ok"}}), 1);
  EXPECT_EQ(
      CounterValue(metrics, "framediffuser_streams_ended_total", {{"code", "unauthenticated"}}), 1);
}

TEST(ServerMetricsTest, NoLabelOutsideTheBoundedSet) {
  ServerMetrics metrics(TestBuild());
  RecordEveryEvent(metrics);
  const std::set<std::string> allowed = {"environment", "outcome",      "stage",  "reason",
                                         "state",       "code",         "device", "version",
                                         "git_commit",  "torch_version"};
  for (const prometheus::MetricFamily& family : metrics.registry()->Collect()) {
    for (const prometheus::ClientMetric& metric : family.metric) {
      for (const auto& label : metric.label) {
        EXPECT_EQ(allowed.count(label.name), 1u) << family.name << " has label " << label.name;
        EXPECT_THAT(label.name, Not(HasSubstr("session"))) << family.name;
        EXPECT_THAT(label.name, Not(HasSubstr("client"))) << family.name;
      }
    }
  }
}

TEST(ServerMetricsTest, ConcurrentEventsAreAllCounted) {
  ServerMetrics metrics(TestBuild());
  constexpr int kThreads = 4;
  constexpr int kEvents = 500;
  std::vector<std::thread> threads;
  for (int t = 0; t < kThreads; ++t) {
    threads.emplace_back([&metrics, t] {
      const std::string environment = t % 2 == 0 ? "even" : "odd";
      for (int i = 0; i < kEvents; ++i) {
        metrics.OnOpened(environment);
        metrics.OnFrameDone(environment, absl::StatusCode::kOk, {});
        metrics.OnEnded(environment, session::EndReason::kClosed);
        metrics.OnStreamStarted();
        metrics.OnStreamEnded(absl::StatusCode::kOk);
      }
    });
  }
  for (std::thread& thread : threads) thread.join();
  for (const char* environment : {"even", "odd"}) {
    EXPECT_EQ(CounterValue(metrics, "framediffuser_frames_total",
                           {{"environment", environment}, {"outcome", "ok"}}),
              2 * kEvents);
    EXPECT_EQ(GaugeValue(metrics, "framediffuser_active_sessions", {{"environment", environment}}),
              0);
  }
  EXPECT_EQ(GaugeValue(metrics, "framediffuser_streams_open", {}), 0);
  EXPECT_EQ(CounterValue(metrics, "framediffuser_streams_ended_total", {{"code", "ok"}}),
            kThreads * kEvents);
}

TEST(ServerMetricsTest, DeviceMemoryGaugeByDeviceAndSampledAtScrape) {
  ServerMetrics metrics(TestBuild());
  EXPECT_THAT(metrics.Scrape(), Not(HasSubstr("framediffuser_device_memory_in_use_bytes{")));
  metrics.SampleDeviceMemoryAtScrape("cpu");
  EXPECT_GT(GaugeValue(metrics, "framediffuser_device_memory_in_use_bytes", {{"device", "cpu"}}),
            1 << 20);
  EXPECT_THAT(metrics.Scrape(),
              HasSubstr("framediffuser_device_memory_in_use_bytes{device=\"cpu\"}"));
  // A device this build cannot measure leaves no sample (and no error).
  metrics.UpdateDeviceMemory("meta");
  EXPECT_FALSE(
      Find(metrics, "framediffuser_device_memory_in_use_bytes", {{"device", "meta"}}).has_value());
}

// Sends `request` to 127.0.0.1:`port` and reads until the server closes the
// connection (it does after every response): the raw response.
std::string HttpRequest(int port, const std::string& request) {
  const int fd = socket(AF_INET, SOCK_STREAM, 0);
  EXPECT_GE(fd, 0);
  sockaddr_in address{};
  address.sin_family = AF_INET;
  address.sin_port = htons(static_cast<uint16_t>(port));
  EXPECT_EQ(inet_pton(AF_INET, "127.0.0.1", &address.sin_addr), 1);
  if (connect(fd, reinterpret_cast<const sockaddr*>(&address), sizeof(address)) != 0) {
    ADD_FAILURE() << "connect to 127.0.0.1:" << port << " failed";
    close(fd);
    return "";
  }
  size_t sent = 0;
  while (sent < request.size()) {
    const ssize_t n = send(fd, request.data() + sent, request.size() - sent, 0);
    if (n <= 0) break;
    sent += static_cast<size_t>(n);
  }
  std::string response;
  char buffer[4096];
  for (ssize_t n; (n = recv(fd, buffer, sizeof(buffer), 0)) > 0;) response.append(buffer, n);
  close(fd);
  return response;
}

// GET `path` with HTTP/1.0: the raw response, headers included.
std::string HttpGet(int port, const std::string& path) {
  return HttpRequest(port, absl::StrCat("GET ", path, " HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n"));
}

std::string Body(const std::string& response) {
  const size_t end = response.find("\r\n\r\n");
  return end == std::string::npos ? "" : response.substr(end + 4);
}

TEST(ServerMetricsExposerTest, ServesMetricsOnAPickedPort) {
  ServerMetrics metrics(TestBuild());
  RecordEveryEvent(metrics);
  metrics.SampleDeviceMemoryAtScrape("cpu");
  const absl::StatusOr<int> port = metrics.StartExposer("127.0.0.1:0");
  ASSERT_TRUE(port.ok()) << port.status();
  EXPECT_GT(*port, 0);
  const std::string response = HttpGet(*port, "/metrics");
  EXPECT_TRUE(absl::StartsWith(response, "HTTP/1.1 200")) << response.substr(0, 200);
  const std::string body = Body(response);
  EXPECT_THAT(body, HasSubstr("framediffuser_build_info{"));
  EXPECT_THAT(body,
              HasSubstr("framediffuser_frames_total{environment=\"street\",outcome=\"ok\"} 1"));
  EXPECT_THAT(body, HasSubstr("framediffuser_device_memory_in_use_bytes{device=\"cpu\"}"));
  // Events after the exposer started show up in the next scrape.
  metrics.OnFrameDone("street", absl::StatusCode::kOk, {});
  EXPECT_THAT(Body(HttpGet(*port, "/metrics")),
              HasSubstr("framediffuser_frames_total{environment=\"street\",outcome=\"ok\"} 2"));
}

TEST(ServerMetricsExposerTest, OnlyGetAndHeadOfMetrics) {
  ServerMetrics metrics(TestBuild());
  const absl::StatusOr<int> port = metrics.StartExposer("127.0.0.1:0");
  ASSERT_TRUE(port.ok()) << port.status();
  EXPECT_TRUE(absl::StartsWith(HttpGet(*port, "/"), "HTTP/1.1 404"));
  EXPECT_TRUE(absl::StartsWith(HttpGet(*port, "/metricsx"), "HTTP/1.1 404"));
  EXPECT_TRUE(absl::StartsWith(HttpGet(*port, "/metrics?name[]=x"), "HTTP/1.1 200"));
  EXPECT_TRUE(
      absl::StartsWith(HttpRequest(*port, "POST /metrics HTTP/1.0\r\n\r\n"), "HTTP/1.1 405"));
  const std::string head = HttpRequest(*port, "HEAD /metrics HTTP/1.0\r\n\r\n");
  EXPECT_TRUE(absl::StartsWith(head, "HTTP/1.1 200")) << head;
  EXPECT_THAT(head, HasSubstr("Content-Type: text/plain; version=0.0.4"));
  EXPECT_THAT(Body(head), IsEmpty());
  EXPECT_TRUE(absl::StartsWith(HttpRequest(*port, "nonsense\r\n\r\n"), "HTTP/1.1 400"));
}

TEST(ServerMetricsExposerTest, Errors) {
  ServerMetrics metrics(TestBuild());
  for (const char* address :
       {"", "127.0.0.1", "127.0.0.1:http", ":9464", "127.0.0.1:99999", "127.0.0.1:-1"}) {
    const absl::StatusOr<int> port = metrics.StartExposer(address);
    EXPECT_EQ(port.status().code(), absl::StatusCode::kInvalidArgument) << address;
    EXPECT_THAT(std::string(port.status().message()), HasSubstr("metrics address")) << address;
  }
  const absl::StatusOr<int> port = metrics.StartExposer("127.0.0.1:0");
  ASSERT_TRUE(port.ok()) << port.status();
  EXPECT_EQ(metrics.StartExposer("127.0.0.1:0").status().code(),
            absl::StatusCode::kFailedPrecondition);
  // The port is taken: a second server cannot bind it.
  ServerMetrics other(TestBuild());
  const absl::StatusOr<int> taken = other.StartExposer(absl::StrCat("127.0.0.1:", *port));
  EXPECT_EQ(taken.status().code(), absl::StatusCode::kUnavailable) << taken.status();
}

// promtool from PATH (scripts/setup-deps.sh installs it with Debian's
// `prometheus` package), else /usr/bin/promtool; empty when missing.
std::string FindPromtool() {
  const char* path = std::getenv("PATH");
  for (const auto& dir : absl::StrSplit(path != nullptr ? path : "", ':')) {
    if (dir.empty()) continue;
    const std::string candidate = absl::StrCat(dir, "/promtool");
    if (access(candidate.c_str(), X_OK) == 0) return candidate;
  }
  return access("/usr/bin/promtool", X_OK) == 0 ? "/usr/bin/promtool" : "";
}

// A real scrape over HTTP must pass `promtool check metrics` (format and
// lint: HELP text, _total on counters, base units, snake_case) with no
// output at all. A missing promtool fails the test: it is a declared
// dependency, not an optional one.
TEST(MetricsPromtoolTest, RealScrapePassesPromtoolCheckMetrics) {
  const std::string promtool = FindPromtool();
  ASSERT_FALSE(promtool.empty())
      << "promtool not found on PATH or at /usr/bin/promtool; install Debian's `prometheus` "
         "package (scripts/setup-deps.sh)";
  ServerMetrics metrics(TestBuild());
  RecordEveryEvent(metrics);
  metrics.OnRejected("street", session::RejectReason::kDraining);
  metrics.OnEnded("street", session::EndReason::kEvicted);
  metrics.SampleDeviceMemoryAtScrape("cpu");
  const absl::StatusOr<int> port = metrics.StartExposer("127.0.0.1:0");
  ASSERT_TRUE(port.ok()) << port.status();
  const std::string scrape = Body(HttpGet(*port, "/metrics"));
  ASSERT_THAT(scrape, HasSubstr("framediffuser_frame_stage_seconds_bucket"));

  const std::string file =
      absl::StrCat(::testing::TempDir(), "/fd_metrics_scrape_", getpid(), ".prom");
  {
    std::ofstream out(file, std::ios::binary);
    out << scrape;
    ASSERT_TRUE(out.good()) << file;
  }
  const std::string command = absl::StrCat("'", promtool, "' check metrics < '", file, "' 2>&1");
  FILE* pipe = popen(command.c_str(), "r");
  ASSERT_NE(pipe, nullptr) << command;
  std::string output;
  char buffer[1024];
  for (size_t n; (n = fread(buffer, 1, sizeof(buffer), pipe)) > 0;) output.append(buffer, n);
  const int status = pclose(pipe);
  std::remove(file.c_str());
  ASSERT_TRUE(WIFEXITED(status)) << command;
  EXPECT_EQ(WEXITSTATUS(status), 0) << command << "\n" << output;
  EXPECT_THAT(output, IsEmpty()) << "promtool reported problems:\n" << output;
}

}  // namespace
}  // namespace fd::server
