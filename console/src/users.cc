#include "users.h"

#include <fcntl.h>
#include <openssl/crypto.h>
#include <openssl/evp.h>
#include <openssl/rand.h>
#include <sys/stat.h>
#include <unistd.h>

#include <fstream>
#include <sstream>
#include <vector>

#include "absl/strings/ascii.h"
#include "absl/strings/escaping.h"
#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"

namespace stage::console {
namespace {

constexpr absl::string_view kScheme = "pbkdf2-sha256";

std::string RandomBytes(size_t n) {
  std::string out(n, '\0');
  if (RAND_bytes(reinterpret_cast<unsigned char*>(out.data()), static_cast<int>(n)) != 1) {
    // OpenSSL's generator failing means the system has no entropy source: nothing safe can go on.
    std::abort();
  }
  return out;
}

bool ValidName(absl::string_view name) {
  if (name.empty() || name.size() > 64) return false;
  for (char c : name) {
    if (c == ':' || absl::ascii_isspace(static_cast<unsigned char>(c)) || !absl::ascii_isprint(c)) return false;
  }
  return true;
}

// Hex to bytes; false when `hex` is not an even number of hex digits.
bool FromHex(absl::string_view hex, std::string* bytes) {
  if (hex.size() % 2 != 0) return false;
  for (char c : hex) {
    if (!absl::ascii_isxdigit(static_cast<unsigned char>(c))) return false;
  }
  *bytes = absl::HexStringToBytes(hex);
  return true;
}

absl::StatusOr<UserEntry> ParseLine(absl::string_view line) {
  std::vector<std::string> f = absl::StrSplit(line, ':');
  if (f.size() != 6) return absl::InvalidArgumentError("expected NAME:ROLE:pbkdf2-sha256:ITERATIONS:SALT:HASH");
  UserEntry u;
  u.name = f[0];
  if (!ValidName(u.name)) return absl::InvalidArgumentError(absl::StrCat("bad user name '", u.name, "'"));
  auto role = ParseRole(f[1]);
  if (!role.ok()) return role.status();
  u.role = *role;
  if (f[2] != kScheme) return absl::InvalidArgumentError(absl::StrCat("unknown hash scheme '", f[2], "'"));
  if (!absl::SimpleAtoi(f[3], &u.iterations) || u.iterations < 1000) {
    return absl::InvalidArgumentError("iterations must be a number of at least 1000");
  }
  if (!FromHex(f[4], &u.salt) || u.salt.size() < 8) {
    return absl::InvalidArgumentError("the salt must be hex, at least 8 bytes");
  }
  if (!FromHex(f[5], &u.hash) || u.hash.size() != 32) {
    return absl::InvalidArgumentError("the hash must be 32 bytes of hex");
  }
  return u;
}

std::string FormatLine(const UserEntry& u) {
  return absl::StrCat(u.name, ":", RoleName(u.role), ":", kScheme, ":", u.iterations, ":",
                      absl::BytesToHexString(u.salt), ":", absl::BytesToHexString(u.hash));
}

}  // namespace

absl::string_view RoleName(Role role) { return role == Role::kOperator ? "operator" : "observer"; }

absl::StatusOr<Role> ParseRole(absl::string_view name) {
  if (name == "operator") return Role::kOperator;
  if (name == "observer") return Role::kObserver;
  return absl::InvalidArgumentError(absl::StrCat("role '", name, "': expected observer or operator"));
}

std::string HashPassword(absl::string_view password, absl::string_view salt, uint32_t iterations) {
  std::string out(32, '\0');
  PKCS5_PBKDF2_HMAC(password.data(), static_cast<int>(password.size()),
                    reinterpret_cast<const unsigned char*>(salt.data()), static_cast<int>(salt.size()),
                    static_cast<int>(iterations), EVP_sha256(), static_cast<int>(out.size()),
                    reinterpret_cast<unsigned char*>(out.data()));
  return out;
}

absl::StatusOr<UserBook> UserBook::Load(const std::string& path) {
  std::ifstream in(path);
  if (!in) return absl::NotFoundError(absl::StrCat("users file ", path, ": cannot be read"));
  UserBook book;
  std::string line;
  int number = 0;
  while (std::getline(in, line)) {
    ++number;
    const absl::string_view text = absl::StripAsciiWhitespace(line);
    if (text.empty() || text[0] == '#') continue;
    auto user = ParseLine(text);
    if (!user.ok()) {
      return absl::InvalidArgumentError(
          absl::StrCat("users file ", path, " line ", number, ": ", user.status().message()));
    }
    book.users_[user->name] = *std::move(user);
  }
  return book;
}

absl::StatusOr<Role> UserBook::Verify(absl::string_view name, absl::string_view password) const {
  auto it = users_.find(name);
  if (it == users_.end()) {
    // The same work as for a user who exists: the answer's time does not say which names are users.
    (void)HashPassword(password, "not-a-user-salt!", 200000);
    return absl::PermissionDeniedError("unknown user or wrong password");
  }
  const UserEntry& u = it->second;
  const std::string hash = HashPassword(password, u.salt, u.iterations);
  if (CRYPTO_memcmp(hash.data(), u.hash.data(), hash.size()) != 0) {
    return absl::PermissionDeniedError("unknown user or wrong password");
  }
  return u.role;
}

absl::Status AddUser(const std::string& path, absl::string_view name, Role role, absl::string_view password,
                     uint32_t iterations) {
  if (!ValidName(name)) {
    return absl::InvalidArgumentError(
        absl::StrCat("user name '", name, "': 1-64 printable characters, no ':' or space"));
  }
  if (password.empty()) return absl::InvalidArgumentError("the password is empty");
  if (iterations < 1000) return absl::InvalidArgumentError("iterations must be at least 1000");
  std::vector<std::string> lines;
  {
    std::ifstream in(path);
    std::string line;
    while (std::getline(in, line)) {
      const absl::string_view text = absl::StripAsciiWhitespace(line);
      if (absl::StartsWith(text, absl::StrCat(name, ":"))) continue;  // replaced
      lines.push_back(line);
    }
  }
  UserEntry u;
  u.name = std::string(name);
  u.role = role;
  u.iterations = iterations;
  u.salt = RandomBytes(16);
  u.hash = HashPassword(password, u.salt, iterations);
  lines.push_back(FormatLine(u));
  const std::string temp = path + ".tmp";
  const int fd = ::open(temp.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0600);
  if (fd < 0) return absl::PermissionDeniedError(absl::StrCat("users file ", path, ": cannot write ", temp));
  const std::string text = absl::StrCat(absl::StrJoin(lines, "\n"), "\n");
  const bool written = ::write(fd, text.data(), text.size()) == static_cast<ssize_t>(text.size());
  ::close(fd);
  if (!written || ::rename(temp.c_str(), path.c_str()) != 0) {
    ::unlink(temp.c_str());
    return absl::InternalError(absl::StrCat("users file ", path, ": cannot be written"));
  }
  return absl::OkStatus();
}

std::string Sessions::Open(const std::string& user, Role role) {
  const std::string token = absl::BytesToHexString(RandomBytes(32));
  std::lock_guard<std::mutex> lock(mutex_);
  const auto now = std::chrono::steady_clock::now();
  for (auto it = sessions_.begin(); it != sessions_.end();) {
    it = it->second.expires < now ? sessions_.erase(it) : std::next(it);
  }
  sessions_[token] = {user, role, now + lifetime_};
  return token;
}

std::optional<Sessions::Session> Sessions::Find(absl::string_view token) {
  std::lock_guard<std::mutex> lock(mutex_);
  auto it = sessions_.find(token);
  if (it == sessions_.end()) return std::nullopt;
  const auto now = std::chrono::steady_clock::now();
  if (it->second.expires < now) {
    sessions_.erase(it);
    return std::nullopt;
  }
  it->second.expires = now + lifetime_;
  return it->second;
}

void Sessions::Close(absl::string_view token) {
  std::lock_guard<std::mutex> lock(mutex_);
  if (auto it = sessions_.find(token); it != sessions_.end()) sessions_.erase(it);
}

}  // namespace stage::console
