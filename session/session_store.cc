#include "session/session_store.h"

#include <utility>

#include "absl/strings/str_cat.h"
#include "base/bounded_text.h"
#include "session/random_token.h"
#include "session/string_view_compat.h"

namespace fd::session {
namespace {

// An id that cannot collide with a live or remembered one is found on the
// first draw with overwhelming probability (128 random bits); the bound only
// guards against a broken random source.
constexpr int kMaxIdDraws = 8;

absl::Status CheckSessionId(std::string_view session_id) {
  if (!IsWellFormedToken(session_id)) {
    return absl::InvalidArgumentError(absl::StrCat("session_id: must be ", kTokenHexChars,
                                                   " lowercase hex characters, got ",
                                                   session_id.size(), " characters"));
  }
  return absl::OkStatus();
}

// Decrements a per-key counter, erasing the key at zero so the maps stay as
// small as the set of keys with live sessions.
void Decrement(absl::flat_hash_map<std::string, size_t>& counts, const std::string& key) {
  auto it = counts.find(ToAbsl(key));
  if (it == counts.end()) return;
  if (--it->second == 0) counts.erase(it);
}

size_t CountOf(const absl::flat_hash_map<std::string, size_t>& counts, std::string_view key) {
  auto it = counts.find(ToAbsl(key));
  return it == counts.end() ? 0 : it->second;
}

absl::Status PermissionDenied(std::string_view session_id, std::string_view what) {
  return absl::PermissionDeniedError(
      absl::StrCat("session ", ToAbsl(session_id), ": ", ToAbsl(what)));
}

}  // namespace

absl::Status ValidateSessionStoreOptions(const SessionStoreOptions& options) {
  const std::pair<const char*, size_t> limits[] = {
      {"max_sessions", options.max_sessions},
      {"max_sessions_per_environment", options.max_sessions_per_environment},
      {"max_sessions_per_client", options.max_sessions_per_client},
      {"max_ended_remembered", options.max_ended_remembered},
  };
  for (const auto& [name, value] : limits) {
    if (value < 1) {
      return absl::InvalidArgumentError(absl::StrCat("options.", name, ": must be at least 1"));
    }
  }
  if (options.idle_timeout <= absl::ZeroDuration()) {
    return absl::InvalidArgumentError("options.idle_timeout: must be positive");
  }
  if (options.ended_retention <= absl::ZeroDuration()) {
    return absl::InvalidArgumentError("options.ended_retention: must be positive");
  }
  return absl::OkStatus();
}

absl::StatusOr<std::unique_ptr<SessionStore>> SessionStore::Create(SessionStoreOptions options,
                                                                   const Clock* clock,
                                                                   SessionStoreObserver* observer) {
  absl::Status valid = ValidateSessionStoreOptions(options);
  if (!valid.ok()) return valid;
  if (clock == nullptr) return absl::InvalidArgumentError("clock: must not be null");
  return std::unique_ptr<SessionStore>(new SessionStore(
      std::move(options), clock, observer != nullptr ? observer : NoopSessionStoreObserver::Get()));
}

SessionStore::SessionStore(SessionStoreOptions options, const Clock* clock,
                           SessionStoreObserver* observer)
    : options_(std::move(options)), clock_(clock), observer_(observer) {}

absl::StatusOr<CreatedSession> SessionStore::Create(std::string client_identity,
                                                    SessionState initial_state,
                                                    std::string_view preferred_id) {
  const std::string environment = initial_state.settings().environment;
  // Draw the random tokens before taking the lock (syscalls); the id is
  // redrawn under the lock only in the (2^-128) case that it is taken.
  absl::StatusOr<std::string> secret = NewRandomToken();
  if (!secret.ok()) return secret.status();
  absl::StatusOr<std::string> first_id = NewRandomToken();
  if (!first_id.ok()) return first_id.status();

  std::vector<Event> events;
  absl::StatusOr<CreatedSession> result;
  {
    absl::MutexLock lock(&mu_);
    PruneEndedLocked();
    auto reject = [&](RejectReason reason, absl::Status status) {
      events.push_back({Event::kRejected, environment, EndReason::kClosed, reason});
      return status;
    };
    if (draining_) {
      result = reject(RejectReason::kDraining,
                      absl::UnavailableError("the server is draining; open the session elsewhere"));
    } else if (live_.size() >= options_.max_sessions) {
      result = reject(RejectReason::kTotalLimit,
                      absl::ResourceExhaustedError(absl::StrCat(
                          "session limit reached: max_sessions = ", options_.max_sessions)));
    } else if (CountOf(live_per_environment_, environment) >=
               options_.max_sessions_per_environment) {
      result = reject(
          RejectReason::kEnvironmentLimit,
          absl::ResourceExhaustedError(absl::StrCat(
              "session limit reached: max_sessions_per_environment = ",
              options_.max_sessions_per_environment, " (environment \"", environment, "\")")));
    } else if (CountOf(live_per_client_, client_identity) >= options_.max_sessions_per_client) {
      result = reject(RejectReason::kClientLimit,
                      absl::ResourceExhaustedError(
                          absl::StrCat("session limit reached: max_sessions_per_client = ",
                                       options_.max_sessions_per_client, " (for this client)")));
    } else {
      std::string id;
      if (IsWellFormedToken(preferred_id) && !live_.contains(ToAbsl(preferred_id)) &&
          !ended_.contains(ToAbsl(preferred_id))) {
        id = std::string(preferred_id);
      }
      for (int draw = 0; draw < kMaxIdDraws && id.empty(); ++draw) {
        absl::StatusOr<std::string> candidate = draw == 0 ? *first_id : NewRandomToken();
        if (!candidate.ok()) {
          result = candidate.status();
          break;
        }
        if (!live_.contains(*candidate) && !ended_.contains(*candidate)) {
          id = *std::move(candidate);
        }
      }
      if (id.empty() && result.ok()) {
        result = absl::InternalError("could not draw an unused session id");
      }
      if (!id.empty()) {
        auto session =
            std::make_shared<Session>(id, client_identity, std::move(initial_state), clock_);
        ++live_per_environment_[environment];
        ++live_per_client_[client_identity];
        live_.emplace(id, LiveEntry{session, *secret});
        events.push_back({Event::kOpened, environment});
        result = CreatedSession{std::move(session), *std::move(secret)};
      }
    }
  }
  Notify(events);
  return result;
}

absl::Status SessionStore::NotLiveErrorLocked(std::string_view session_id) const {
  auto ended = ended_.find(ToAbsl(session_id));
  if (ended != ended_.end()) {
    return SessionEndedError(session_id, ended->second.info.reason, ended->second.info.detail);
  }
  return absl::NotFoundError(absl::StrCat("unknown session ", BoundedText(session_id)));
}

absl::StatusOr<std::shared_ptr<Session>> SessionStore::Lookup(std::string_view session_id) const {
  absl::Status well_formed = CheckSessionId(session_id);
  if (!well_formed.ok()) return well_formed;
  absl::ReaderMutexLock lock(&mu_);
  auto live = live_.find(ToAbsl(session_id));
  if (live != live_.end()) return live->second.session;
  return NotLiveErrorLocked(session_id);
}

absl::StatusOr<std::shared_ptr<Session>> SessionStore::Resume(std::string_view session_id,
                                                              std::string_view resume_secret,
                                                              std::string_view client_identity) {
  absl::Status well_formed = CheckSessionId(session_id);
  if (!well_formed.ok()) return well_formed;
  std::vector<Event> events;
  absl::StatusOr<std::shared_ptr<Session>> result;
  {
    absl::MutexLock lock(&mu_);
    PruneEndedLocked();
    // Ownership first, for live and remembered sessions alike, so that
    // neither the session nor why it ended is revealed to anyone else.
    const std::string* owner = nullptr;
    const std::string* secret = nullptr;
    std::string environment;
    auto live = live_.find(ToAbsl(session_id));
    auto ended = ended_.find(ToAbsl(session_id));
    if (live != live_.end()) {
      owner = &live->second.session->client_identity();
      secret = &live->second.resume_secret;
      environment = live->second.session->environment();
    } else if (ended != ended_.end()) {
      owner = &ended->second.client_identity;
      secret = &ended->second.resume_secret;
      environment = ended->second.info.environment;
    }
    if (owner == nullptr) {
      result = draining_
                   ? absl::UnavailableError("the server is draining; open a new session elsewhere")
                   : NotLiveErrorLocked(session_id);
    } else if (*owner != client_identity) {
      events.push_back(
          {Event::kRejected, environment, EndReason::kClosed, RejectReason::kPermissionDenied});
      result = PermissionDenied(session_id, "belongs to another client");
    } else if (!ConstantTimeEquals(*secret, resume_secret)) {
      events.push_back(
          {Event::kRejected, environment, EndReason::kClosed, RejectReason::kPermissionDenied});
      result = PermissionDenied(session_id, "wrong resume_token");
    } else if (live == live_.end()) {
      result = NotLiveErrorLocked(session_id);
    } else {
      live->second.session->Touch();
      events.push_back({Event::kResumed, environment});
      result = live->second.session;
    }
  }
  Notify(events);
  return result;
}

void SessionStore::EndLocked(const std::string& session_id_ref, EndReason reason,
                             std::string_view detail, std::vector<Event>* events) {
  // A copy: the caller may pass a reference to the key erased below.
  const std::string session_id = session_id_ref;
  auto live = live_.find(ToAbsl(session_id));
  if (live == live_.end()) return;
  LiveEntry entry = std::move(live->second);
  live_.erase(live);
  const Session& session = *entry.session;
  Decrement(live_per_environment_, session.environment());
  Decrement(live_per_client_, session.client_identity());
  entry.session->MarkEnded(reason);
  EndedEntry ended{
      EndedSessionInfo{reason, std::string(detail), session.environment(), clock_->Now()},
      session.client_identity(), std::move(entry.resume_secret)};
  ended_.insert_or_assign(session_id, std::move(ended));
  ended_order_.push_back(session_id);
  events->push_back({Event::kEnded, session.environment(), reason});
}

void SessionStore::PruneEndedLocked() {
  const absl::Time now = clock_->Now();
  while (!ended_order_.empty()) {
    auto it = ended_.find(ended_order_.front());
    const bool too_many = ended_.size() > options_.max_ended_remembered;
    const bool too_old =
        it == ended_.end() || now - it->second.info.ended_at >= options_.ended_retention;
    if (!too_many && !too_old) break;
    if (it != ended_.end()) ended_.erase(it);
    ended_order_.pop_front();
  }
}

absl::Status SessionStore::EndOne(std::string_view session_id, EndReason reason,
                                  std::string_view detail) {
  absl::Status well_formed = CheckSessionId(session_id);
  if (!well_formed.ok()) return well_formed;
  std::vector<Event> events;
  absl::Status result;
  {
    absl::MutexLock lock(&mu_);
    auto live = live_.find(ToAbsl(session_id));
    if (live == live_.end()) {
      result = NotLiveErrorLocked(session_id);
    } else {
      EndLocked(live->first, reason, detail, &events);
      PruneEndedLocked();
    }
  }
  Notify(events);
  return result;
}

absl::Status SessionStore::Close(std::string_view session_id) {
  return EndOne(session_id, EndReason::kClosed, "");
}

absl::Status SessionStore::Evict(std::string_view session_id, std::string_view detail) {
  return EndOne(session_id, EndReason::kEvicted, detail);
}

std::vector<std::shared_ptr<Session>> SessionStore::EvictEnvironment(std::string_view environment,
                                                                     std::string_view detail) {
  std::vector<Event> events;
  std::vector<std::shared_ptr<Session>> evicted;
  {
    absl::MutexLock lock(&mu_);
    std::vector<std::string> ids;
    for (const auto& [id, entry] : live_) {
      if (entry.session->environment() == environment) ids.push_back(id);
    }
    for (const std::string& id : ids) {
      evicted.push_back(live_.at(id).session);
      EndLocked(id, EndReason::kEvicted, detail, &events);
    }
    PruneEndedLocked();
  }
  Notify(events);
  return evicted;
}

std::vector<std::shared_ptr<Session>> SessionStore::DrainAll() {
  std::vector<Event> events;
  std::vector<std::shared_ptr<Session>> drained;
  {
    absl::MutexLock lock(&mu_);
    draining_ = true;
    std::vector<std::string> ids;
    ids.reserve(live_.size());
    for (const auto& [id, entry] : live_) ids.push_back(id);
    for (const std::string& id : ids) {
      drained.push_back(live_.at(id).session);
      EndLocked(id, EndReason::kDraining, "", &events);
    }
    PruneEndedLocked();
  }
  Notify(events);
  return drained;
}

std::vector<std::shared_ptr<Session>> SessionStore::ExpireIdle() {
  std::vector<Event> events;
  std::vector<std::shared_ptr<Session>> expired;
  {
    absl::MutexLock lock(&mu_);
    const absl::Time now = clock_->Now();
    std::vector<std::string> ids;
    for (const auto& [id, entry] : live_) {
      // Checked and marked in one step under the session's lock: a frame
      // that begins concurrently either makes the session busy first or
      // sees it expired (TryBeginFrame then fails).
      if (entry.session->MarkEndedIfIdle(now, options_.idle_timeout, EndReason::kExpired)) {
        ids.push_back(id);
      }
    }
    const std::string detail =
        absl::StrCat("no activity for ", absl::FormatDuration(options_.idle_timeout));
    for (const std::string& id : ids) {
      expired.push_back(live_.at(id).session);
      EndLocked(id, EndReason::kExpired, detail, &events);
    }
    PruneEndedLocked();
  }
  Notify(events);
  return expired;
}

std::optional<EndedSessionInfo> SessionStore::EndedInfo(std::string_view session_id) const {
  absl::ReaderMutexLock lock(&mu_);
  auto ended = ended_.find(ToAbsl(session_id));
  if (ended == ended_.end()) return std::nullopt;
  return ended->second.info;
}

std::optional<EndReason> SessionStore::EndReasonOf(std::string_view session_id) const {
  std::optional<EndedSessionInfo> info = EndedInfo(session_id);
  if (!info.has_value()) return std::nullopt;
  return info->reason;
}

size_t SessionStore::live_sessions() const {
  absl::ReaderMutexLock lock(&mu_);
  return live_.size();
}

size_t SessionStore::live_sessions_in(std::string_view environment) const {
  absl::ReaderMutexLock lock(&mu_);
  return CountOf(live_per_environment_, environment);
}

size_t SessionStore::ended_remembered() const {
  absl::ReaderMutexLock lock(&mu_);
  return ended_.size();
}

bool SessionStore::draining() const {
  absl::ReaderMutexLock lock(&mu_);
  return draining_;
}

void SessionStore::Notify(const std::vector<Event>& events) const {
  for (const Event& event : events) {
    switch (event.kind) {
      case Event::kOpened:
        observer_->OnOpened(event.environment);
        break;
      case Event::kResumed:
        observer_->OnResumed(event.environment);
        break;
      case Event::kEnded:
        observer_->OnEnded(event.environment, event.end_reason);
        break;
      case Event::kRejected:
        observer_->OnRejected(event.environment, event.reject_reason);
        break;
    }
  }
}

}  // namespace fd::session
