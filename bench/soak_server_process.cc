#include "bench/soak_server_process.h"

#include <fcntl.h>
#include <signal.h>
#include <sys/prctl.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <utility>

#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"

namespace fd::bench {
namespace {

constexpr size_t kTailLines = 200;
constexpr absl::string_view kListening = "framediffuser-server listening on port ";

std::string Errno(absl::string_view what) { return absl::StrCat(what, ": ", std::strerror(errno)); }

// The value of `"key":"value"` in a JSON log line, or "".
absl::string_view JsonString(absl::string_view line, absl::string_view key) {
  const std::string needle = absl::StrCat("\"", key, "\":\"");
  const size_t at = line.find(needle);
  if (at == absl::string_view::npos) return "";
  const size_t begin = at + needle.size();
  const size_t end = line.find('"', begin);
  return end == absl::string_view::npos ? "" : line.substr(begin, end - begin);
}

int ShellStatus(int status) {
  if (WIFEXITED(status)) return WEXITSTATUS(status);
  if (WIFSIGNALED(status)) return 128 + WTERMSIG(status);
  return -1;
}

}  // namespace

absl::StatusOr<ProcessSample> SampleProcess(pid_t pid) {
  ProcessSample sample;
  const std::string dir = absl::StrCat("/proc/", pid);
  std::ifstream status(dir + "/status");
  if (!status) return absl::InternalError(absl::StrCat("cannot read ", dir, "/status"));
  std::string line;
  bool rss = false, threads = false;
  while (std::getline(status, line)) {
    auto value = [&line](absl::string_view key, int64_t* out) {
      if (!absl::StartsWith(line, key)) return false;
      absl::string_view rest = absl::string_view(line).substr(key.size());
      rest = rest.substr(0, rest.find(" kB"));
      while (!rest.empty() && (rest.front() == ' ' || rest.front() == '\t')) rest.remove_prefix(1);
      return absl::SimpleAtoi(rest, out);
    };
    int64_t n = 0;
    if (value("VmRSS:", &sample.rss_kib)) {
      rss = true;
    } else if (value("VmHWM:", &sample.hwm_kib)) {
    } else if (value("Threads:", &n)) {
      sample.threads = static_cast<int>(n);
      threads = true;
    }
  }
  if (!rss || !threads) {
    return absl::InternalError(absl::StrCat(dir, "/status has no VmRSS or Threads line"));
  }
  std::error_code ec;
  int fds = 0;
  for (std::filesystem::directory_iterator it(dir + "/fd", ec), end; !ec && it != end;
       it.increment(ec)) {
    ++fds;
  }
  if (ec) return absl::InternalError(absl::StrCat("cannot list ", dir, "/fd: ", ec.message()));
  sample.fds = fds;
  for (std::filesystem::directory_iterator it(dir + "/task", ec), end; !ec && it != end;
       it.increment(ec)) {
    std::ifstream comm(it->path() / "comm");
    std::string name;
    // comm holds at most 15 characters.
    if (!std::getline(comm, name)) continue;
    if (name == "default-executo") ++sample.grpc_executor_threads;
    if (name == "grpc_global_tim") ++sample.grpc_timer_threads;
  }
  return sample;
}

std::string ThreadNames(pid_t pid) {
  std::map<std::string, int> names;
  std::error_code ec;
  for (std::filesystem::directory_iterator it(absl::StrCat("/proc/", pid, "/task"), ec), end;
       !ec && it != end; it.increment(ec)) {
    std::ifstream comm(it->path() / "comm");
    std::string name;
    if (std::getline(comm, name)) ++names[name];
  }
  std::vector<std::string> parts;
  for (const auto& [name, count] : names) {
    parts.push_back(count > 1 ? absl::StrCat(name, " x", count) : name);
  }
  return absl::StrJoin(parts, ", ");
}

absl::StatusOr<std::unique_ptr<ServerProcess>> ServerProcess::Start(
    const std::string& binary, const std::vector<std::string>& args, const std::string& log_path,
    absl::Duration timeout) {
  if (access(binary.c_str(), X_OK) != 0) return absl::NotFoundError(Errno(binary));
  int log_fd = -1;
  if (!log_path.empty()) {
    log_fd = open(log_path.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
    if (log_fd < 0) return absl::InternalError(Errno(log_path));
  }
  int pipe_fds[2];
  if (pipe2(pipe_fds, O_CLOEXEC) != 0) return absl::InternalError(Errno("pipe2"));
  const int dev_null = open("/dev/null", O_RDWR | O_CLOEXEC);
  if (dev_null < 0) return absl::InternalError(Errno("/dev/null"));
  // Everything the child needs is made before fork: between fork and exec
  // only async-signal-safe calls are allowed (this process has threads).
  std::vector<std::string> argv_strings = {binary};
  argv_strings.insert(argv_strings.end(), args.begin(), args.end());
  std::vector<char*> argv;
  for (std::string& arg : argv_strings) argv.push_back(arg.data());
  argv.push_back(nullptr);
  const pid_t parent = getpid();
  const pid_t pid = fork();
  if (pid < 0) return absl::InternalError(Errno("fork"));
  if (pid == 0) {
    // The server must not outlive a soak run that crashed or was killed.
    prctl(PR_SET_PDEATHSIG, SIGKILL);
    if (getppid() != parent) _exit(126);
    dup2(dev_null, STDIN_FILENO);
    dup2(dev_null, STDOUT_FILENO);
    dup2(pipe_fds[1], STDERR_FILENO);
    execv(argv[0], argv.data());
    _exit(127);
  }
  close(dev_null);
  close(pipe_fds[1]);
  std::unique_ptr<ServerProcess> process(new ServerProcess(pid, pipe_fds[0], log_fd));
  absl::MutexLock lock(&process->mu_);
  auto listening_or_gone = [p = process.get()]() { return p->port_.has_value() || p->eof_; };
  process->mu_.AwaitWithTimeout(absl::Condition(&listening_or_gone), timeout);
  if (!process->port_.has_value()) {
    return absl::UnavailableError(absl::StrCat(
        process->eof_ ? "the server exited before listening" : "the server did not listen within ",
        process->eof_ ? "" : absl::FormatDuration(timeout), "; its log ends:\n",
        absl::StrJoin(process->tail_, "\n")));
  }
  return process;
}

ServerProcess::ServerProcess(pid_t pid, int stderr_fd, int log_fd)
    : pid_(pid), stderr_fd_(stderr_fd), log_fd_(log_fd) {
  reader_ = std::thread([this] { ReadLoop(); });
}

ServerProcess::~ServerProcess() {
  bool reaped;
  {
    absl::MutexLock lock(&mu_);
    reaped = exit_status_.has_value();
  }
  if (!reaped) {
    kill(pid_, SIGKILL);
    int status = 0;
    waitpid(pid_, &status, 0);
  }
  reader_.join();  // EOF once the child is gone
  close(stderr_fd_);
  if (log_fd_ >= 0) close(log_fd_);
}

int ServerProcess::port() const {
  absl::MutexLock lock(&mu_);
  return port_.value_or(0);
}

void ServerProcess::ReadLoop() {
  std::string pending;
  char buffer[1 << 16];
  while (true) {
    const ssize_t n = read(stderr_fd_, buffer, sizeof(buffer));
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) break;
    if (log_fd_ >= 0) {
      // A copy for the reader of a failed run; a short write loses only that.
      [[maybe_unused]] const ssize_t written = write(log_fd_, buffer, static_cast<size_t>(n));
    }
    pending.append(buffer, static_cast<size_t>(n));
    size_t start = 0;
    absl::MutexLock lock(&mu_);
    for (size_t newline; (newline = pending.find('\n', start)) != std::string::npos;
         start = newline + 1) {
      OnLineLocked(pending.substr(start, newline - start));
    }
    pending.erase(0, start);
  }
  absl::MutexLock lock(&mu_);
  if (!pending.empty()) OnLineLocked(std::move(pending));
  eof_ = true;
}

void ServerProcess::OnLineLocked(std::string line) {
  if (!port_.has_value()) {
    if (const size_t at = absl::string_view(line).find(kListening); at != absl::string_view::npos) {
      int port = 0;
      absl::string_view digits = absl::string_view(line).substr(at + kListening.size());
      digits = digits.substr(0, digits.find_first_not_of("0123456789"));
      if (absl::SimpleAtoi(digits, &port)) port_ = port;
    }
  }
  if (line.rfind("{", 0) == 0) {
    if (absl::string_view event = JsonString(line, "event"); !event.empty()) {
      ++events_[std::string(event)];
    }
    const absl::string_view level = JsonString(line, "level");
    if (level == "warning") ++warnings_;
    if (level == "error") ++errors_;
  }
  tail_.push_back(std::move(line));
  if (tail_.size() > kTailLines) tail_.pop_front();
}

bool ServerProcess::WaitForEvent(absl::string_view event, int count, absl::Duration timeout) {
  absl::MutexLock lock(&mu_);
  auto arrived = [&]() {
    auto it = events_.find(event);
    return eof_ || (it != events_.end() && it->second >= count);
  };
  mu_.AwaitWithTimeout(absl::Condition(&arrived), timeout);
  auto it = events_.find(event);
  return it != events_.end() && it->second >= count;
}

int ServerProcess::EventCount(absl::string_view event) const {
  absl::MutexLock lock(&mu_);
  auto it = events_.find(event);
  return it == events_.end() ? 0 : it->second;
}

int ServerProcess::WarningCount() const {
  absl::MutexLock lock(&mu_);
  return warnings_;
}

int ServerProcess::ErrorCount() const {
  absl::MutexLock lock(&mu_);
  return errors_;
}

std::string ServerProcess::Tail(int lines) const {
  absl::MutexLock lock(&mu_);
  const size_t keep = std::min(tail_.size(), static_cast<size_t>(std::max(lines, 0)));
  return absl::StrJoin(tail_.end() - static_cast<std::ptrdiff_t>(keep), tail_.end(), "\n");
}

absl::StatusOr<int> ServerProcess::Terminate(absl::Duration timeout) {
  {
    absl::MutexLock lock(&mu_);
    if (exit_status_.has_value()) return *exit_status_;
  }
  if (kill(pid_, SIGTERM) != 0) return absl::InternalError(Errno("kill(SIGTERM)"));
  bool ended;
  {
    absl::MutexLock lock(&mu_);
    ended = mu_.AwaitWithTimeout(absl::Condition(&eof_), timeout);
  }
  if (!ended) kill(pid_, SIGKILL);
  int status = 0;
  if (waitpid(pid_, &status, 0) != pid_) return absl::InternalError(Errno("waitpid"));
  absl::MutexLock lock(&mu_);
  exit_status_ = ShellStatus(status);
  if (!ended) {
    return absl::DeadlineExceededError(absl::StrCat(
        "the server did not exit within ", absl::FormatDuration(timeout), " of SIGTERM; killed"));
  }
  return *exit_status_;
}

}  // namespace fd::bench
