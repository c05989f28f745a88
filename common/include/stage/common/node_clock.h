// The NodeClock service every FaStage process serves: the four-timestamp exchange the controller measures clock
// offsets with, and the node's PTP state (linuxptp's ptp4l, read with pmc) where it has one. Include only where the
// service is wired (it brings in gRPC generated code).
#pragma once

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <memory>
#include <mutex>
#include <string>
#include <thread>

#include "absl/strings/string_view.h"
#include "stage/common/clock.h"
#include "stage/v1/node.grpc.pb.h"

namespace stage {

// The PTP state of this host, as a source of it reports it.
class PtpProbe {
 public:
  virtual ~PtpProbe() = default;
  // The latest reading; cheap (no I/O on the caller's thread).
  virtual v1::PtpStatus Latest() const = 0;
};

// Reads ptp4l's state through its management socket with linuxptp's pmc ("GET TIME_STATUS_NP", "GET
// PORT_DATA_SET", "GET CURRENT_DATA_SET") every `interval` on its own thread.
class LinuxPtpProbe final : public PtpProbe {
 public:
  // `uds_path`: ptp4l's socket (ptp4l --uds_address; /var/run/ptp4l by default). `pmc`: the program.
  LinuxPtpProbe(std::string uds_path, std::string pmc = "pmc",
                std::chrono::milliseconds interval = std::chrono::milliseconds(2000));
  ~LinuxPtpProbe() override;
  v1::PtpStatus Latest() const override;
  // One reading now, on the calling thread (the background thread calls it).
  v1::PtpStatus ReadNow() const;

 private:
  void Run();
  std::string uds_path_;
  std::string pmc_;
  std::chrono::milliseconds interval_;
  mutable std::mutex mutex_;
  std::condition_variable wake_;
  v1::PtpStatus latest_;   // guarded by mutex_
  bool stopping_ = false;  // guarded by mutex_
  std::thread thread_;
};

// The PtpStatus in pmc's text output (the three GETs above); `error` set when it holds no answer.
v1::PtpStatus ParsePmcOutput(absl::string_view text);

// The probe for this host: `uds_path` if given ("none" disables it), else ptp4l's default socket if it exists,
// else none (nullptr).
std::unique_ptr<PtpProbe> MakePtpProbe(const std::string& uds_path);

class NodeClockService final : public v1::NodeClock::Service {
 public:
  // `clock` (not owned) is the clock the node fires triggers and stamps frames with; `ptp` may be null.
  NodeClockService(Clock* clock, std::string clock_name, const PtpProbe* ptp)
      : clock_(clock), clock_name_(std::move(clock_name)), ptp_(ptp) {}
  grpc::Status Sync(grpc::ServerContext*, const v1::SyncRequest* request, v1::SyncResponse* response) override;

 private:
  Clock* clock_;
  std::string clock_name_;
  const PtpProbe* ptp_;
};

}  // namespace stage
