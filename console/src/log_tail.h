// The log tail the console shows: new lines of the stage's log files (a file, or every *.log of a directory, new ones
// included), each published on the event log and the last ones kept for a page that opens.
#pragma once

#include <atomic>
#include <condition_variable>
#include <cstdint>
#include <deque>
#include <map>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "absl/status/status.h"
#include "event_log.h"

namespace stage::console {

struct LogTailOptions {
  // Files, or directories whose *.log files are followed.
  std::vector<std::string> paths;
  // Lines kept for a page that opens.
  size_t keep_lines = 1000;
  // Time between looks at the files, ms.
  int poll_ms = 200;
  // Of a file found when the tail starts, its last bytes only.
  int64_t start_bytes = 16384;

  // InvalidArgument naming the field: a path whose directory does not exist (--tail-log), a count that is not
  // positive.
  absl::Status Validate() const;
};

class LogTail {
 public:
  LogTail(LogTailOptions options, EventLog* events);
  ~LogTail();
  void Start();
  void Stop();

  // The last lines kept, oldest first, as a JSON array of {"source", "line"}.
  std::string RecentJson() const;

 private:
  struct File {
    int64_t offset = -1;  // -1: not read yet
    std::string partial;  // a line not ended yet
  };
  void Run();
  void Look();
  void ReadNew(const std::string& path, File& file);

  LogTailOptions options_;
  EventLog* events_;
  std::map<std::string, File> files_;  // the tail thread's
  mutable std::mutex mutex_;
  std::condition_variable wake_;
  bool stopping_ = false;           // guarded by mutex_
  std::deque<std::string> recent_;  // JSON objects; guarded by mutex_
  std::thread thread_;
};

}  // namespace stage::console
