#include "log_tail.h"

#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/strings/strip.h"

namespace stage::console {

namespace fs = std::filesystem;

absl::Status LogTailOptions::Validate() const {
  for (const std::string& p : paths) {
    // A file may come later (a process not started yet), in a directory that is there.
    std::error_code ec;
    const fs::path parent = fs::path(p).parent_path();
    if (!fs::exists(p, ec) && !fs::is_directory(parent.empty() ? fs::path(".") : parent, ec)) {
      return absl::InvalidArgumentError(absl::StrCat("--tail-log ", p, ": neither it nor its directory exists"));
    }
  }
  if (keep_lines < 1) return absl::InvalidArgumentError("log tail: keep_lines must be at least 1");
  if (poll_ms < 1) return absl::InvalidArgumentError("log tail: poll_ms must be positive");
  if (start_bytes < 0) return absl::InvalidArgumentError("log tail: start_bytes must not be negative");
  return absl::OkStatus();
}

LogTail::LogTail(LogTailOptions options, EventLog* events) : options_(std::move(options)), events_(events) {}

LogTail::~LogTail() { Stop(); }

void LogTail::Start() {
  if (options_.paths.empty()) return;
  thread_ = std::thread([this] { Run(); });
}

void LogTail::Stop() {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    stopping_ = true;
  }
  wake_.notify_all();
  if (thread_.joinable()) thread_.join();
}

std::string LogTail::RecentJson() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return "[" + absl::StrJoin(recent_, ",") + "]";
}

void LogTail::Run() {
  while (true) {
    Look();
    std::unique_lock<std::mutex> lock(mutex_);
    if (wake_.wait_for(lock, std::chrono::milliseconds(options_.poll_ms), [&] { return stopping_; })) return;
  }
}

void LogTail::Look() {
  for (const std::string& p : options_.paths) {
    std::error_code ec;
    if (fs::is_directory(p, ec)) {
      for (const auto& entry : fs::directory_iterator(p, ec)) {
        if (entry.path().extension() == ".log") ReadNew(entry.path().string(), files_[entry.path().string()]);
      }
    } else {
      ReadNew(p, files_[p]);
    }
  }
}

void LogTail::ReadNew(const std::string& path, File& file) {
  std::error_code ec;
  const auto size = static_cast<int64_t>(fs::file_size(path, ec));
  if (ec) return;
  if (file.offset < 0) file.offset = std::max<int64_t>(0, size - options_.start_bytes);
  if (size < file.offset) file.offset = 0;  // truncated or replaced: from its start
  if (size == file.offset) return;
  std::ifstream in(path, std::ios::binary);
  in.seekg(file.offset);
  std::string chunk(static_cast<size_t>(size - file.offset), '\0');
  in.read(chunk.data(), static_cast<std::streamsize>(chunk.size()));
  chunk.resize(static_cast<size_t>(in.gcount()));
  file.offset += static_cast<int64_t>(chunk.size());
  file.partial += chunk;
  const std::string source = fs::path(path).stem().string();
  size_t start = 0, end;
  while ((end = file.partial.find('\n', start)) != std::string::npos) {
    std::string line = file.partial.substr(start, end - start);
    start = end + 1;
    if (!line.empty() && line.back() == '\r') line.pop_back();
    if (line.empty()) continue;
    std::string json = nlohmann::json{{"source", source}, {"line", line}}.dump(
        -1, ' ', false, nlohmann::json::error_handler_t::replace);
    {
      std::lock_guard<std::mutex> lock(mutex_);
      recent_.push_back(json);
      while (recent_.size() > options_.keep_lines) recent_.pop_front();
    }
    events_->Publish("log", std::move(json));
  }
  file.partial.erase(0, start);
}

}  // namespace stage::console
