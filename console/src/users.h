// Who may use the console: a users file of salted password hashes (PBKDF2-HMAC-SHA256, OpenSSL), two roles, and the
// sessions of those logged in (a random token in an HttpOnly cookie).
//
// The file: one user a line, "NAME:ROLE:pbkdf2-sha256:ITERATIONS:SALT_HEX:HASH_HEX"; '#' starts a comment. Written
// by `stage-console users add` (docs/console.md), never by hand with a password in it.
#pragma once

#include <chrono>
#include <cstdint>
#include <map>
#include <mutex>
#include <optional>
#include <string>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"

namespace stage::console {

enum class Role {
  kObserver,  // reads: the stage, previews, takes, alarms, logs; may press the emergency stop
  kOperator,  // and commands: arm, capture, pause, resume, abort, reset the emergency stop, acknowledge alarms
};

absl::string_view RoleName(Role role);
// "observer" or "operator"; InvalidArgument otherwise.
absl::StatusOr<Role> ParseRole(absl::string_view name);

struct UserEntry {
  std::string name;
  Role role = Role::kObserver;
  uint32_t iterations = 0;
  std::string salt;  // bytes
  std::string hash;  // bytes: PBKDF2-HMAC-SHA256(password, salt, iterations), 32
};

// PBKDF2-HMAC-SHA256 of `password`: 32 bytes.
std::string HashPassword(absl::string_view password, absl::string_view salt, uint32_t iterations);

class UserBook {
 public:
  // Reads the users file. NotFound when it is missing; InvalidArgument naming the file and line when a line is bad.
  static absl::StatusOr<UserBook> Load(const std::string& path);

  // The user's role when `password` is theirs; PermissionDenied otherwise (the same words whether the user is unknown
  // or the password wrong).
  absl::StatusOr<Role> Verify(absl::string_view name, absl::string_view password) const;

  size_t size() const { return users_.size(); }

 private:
  std::map<std::string, UserEntry, std::less<>> users_;
};

// Adds (or replaces) a user in the users file, creating it (mode 0600) when missing: a fresh 16-byte salt and
// `iterations` rounds. InvalidArgument for a name with ':' or whitespace, or an empty password.
absl::Status AddUser(const std::string& path, absl::string_view name, Role role, absl::string_view password,
                     uint32_t iterations = 200000);

// Those logged in: a token (32 random bytes, hex) to the user and role, until it expires.
class Sessions {
 public:
  explicit Sessions(std::chrono::seconds lifetime) : lifetime_(lifetime) {}

  struct Session {
    std::string user;
    Role role = Role::kObserver;
    std::chrono::steady_clock::time_point expires;
  };

  // A new session's token.
  std::string Open(const std::string& user, Role role);
  // The live session of `token`; each use extends it by the lifetime.
  std::optional<Session> Find(absl::string_view token);
  void Close(absl::string_view token);

 private:
  std::chrono::seconds lifetime_;
  std::mutex mutex_;
  std::map<std::string, Session, std::less<>> sessions_;  // guarded by mutex_
};

}  // namespace stage::console
