// NodeClock service and the linuxptp probe.
#include "stage/common/node_clock.h"

#include <unistd.h>

#include <filesystem>
#include <sstream>

#include "absl/strings/ascii.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "stage/common/clock.h"
#include "stage/common/file_util.h"
#include "stage/common/subprocess.h"

namespace stage {
namespace {

constexpr const char* kDefaultPtp4lSocket = "/var/run/ptp4l";

}  // namespace

grpc::Status NodeClockService::Sync(grpc::ServerContext*, const v1::SyncRequest* request, v1::SyncResponse* response) {
  const int64_t t2 = clock_->NowNs();
  response->set_t1_ns(request->t1_ns());
  response->set_clock(clock_name_);
  if (ptp_ != nullptr) *response->mutable_ptp() = ptp_->Latest();
  response->set_t2_ns(t2);
  response->set_t3_ns(clock_->NowNs());
  return grpc::Status::OK;
}

v1::PtpStatus ParsePmcOutput(absl::string_view text) {
  v1::PtpStatus status;
  status.set_source("linuxptp");
  bool any = false;
  for (absl::string_view line : absl::StrSplit(text, '\n')) {
    std::vector<absl::string_view> f = absl::StrSplit(absl::StripAsciiWhitespace(line), ' ', absl::SkipEmpty());
    if (f.size() < 2) continue;
    const absl::string_view key = f[0], value = f[1];
    double number = 0;
    if (key == "portState") {
      status.set_port_state(std::string(value));
      any = true;
    } else if (key == "master_offset" && absl::SimpleAtod(value, &number)) {
      status.set_master_offset_ns(static_cast<int64_t>(number));
      any = true;
    } else if (key == "meanPathDelay" && absl::SimpleAtod(value, &number)) {
      status.set_mean_path_delay_ns(static_cast<int64_t>(number));
    } else if (key == "gmIdentity") {
      status.set_grandmaster_id(std::string(value));
    } else if (key == "gmPresent") {
      status.set_grandmaster_present(value == "true");
    } else if (key == "stepsRemoved" && absl::SimpleAtod(value, &number)) {
      status.set_steps_removed(static_cast<int32_t>(number));
    }
  }
  if (!any) status.set_error("pmc got no answer from ptp4l");
  return status;
}

LinuxPtpProbe::LinuxPtpProbe(std::string uds_path, std::string pmc, std::chrono::milliseconds interval)
    : uds_path_(std::move(uds_path)), pmc_(std::move(pmc)), interval_(interval) {
  latest_.set_source("linuxptp");
  latest_.set_error("not read yet");
  thread_ = std::thread([this] { Run(); });
}

LinuxPtpProbe::~LinuxPtpProbe() {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    stopping_ = true;
  }
  wake_.notify_all();
  thread_.join();
}

v1::PtpStatus LinuxPtpProbe::Latest() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return latest_;
}

v1::PtpStatus LinuxPtpProbe::ReadNow() const {
  v1::PtpStatus failed;
  failed.set_source("linuxptp");
  failed.set_read_unix_ns(UnixNowNs());
  auto program = FindExecutable(pmc_);
  if (!program.ok() && pmc_.find('/') == std::string::npos) program = FindExecutable("/usr/sbin/" + pmc_);
  if (!program.ok()) {
    failed.set_error(absl::StrCat("cannot read PTP state: ", program.status().message(), " (package linuxptp)"));
    return failed;
  }
  char dir_template[] = "/tmp/fastage-pmc.XXXXXX";
  const char* dir = mkdtemp(dir_template);
  if (dir == nullptr) {
    failed.set_error("cannot read PTP state: no temporary directory");
    return failed;
  }
  const std::string out = std::string(dir) + "/out";
  auto process = Subprocess::Spawn({.argv = {*program, "-u", "-b", "0", "-s", uds_path_, "GET TIME_STATUS_NP",
                                             "GET PORT_DATA_SET", "GET CURRENT_DATA_SET"},
                                    .stdout_path = out,
                                    .stderr_path = std::string(dir) + "/err"});
  v1::PtpStatus status;
  if (!process.ok()) {
    failed.set_error(absl::StrCat("cannot run pmc: ", process.status().message()));
    status = failed;
  } else if (auto exit = (*process)->Wait(std::chrono::milliseconds(3000)); !exit) {
    (*process)->Terminate(std::chrono::milliseconds(200));
    failed.set_error(absl::StrCat("pmc did not answer within 3 s (ptp4l socket ", uds_path_, ")"));
    status = failed;
  } else {
    status = ParsePmcOutput(ReadFileToString(out).value_or(""));
    if (!status.error().empty()) status.set_error(absl::StrCat(status.error(), " at ", uds_path_));
    status.set_read_unix_ns(UnixNowNs());
  }
  std::error_code ec;
  std::filesystem::remove_all(dir, ec);
  return status;
}

void LinuxPtpProbe::Run() {
  std::unique_lock<std::mutex> lock(mutex_);
  while (!stopping_) {
    lock.unlock();
    v1::PtpStatus status = ReadNow();
    lock.lock();
    latest_ = std::move(status);
    wake_.wait_for(lock, interval_, [this] { return stopping_; });
  }
}

std::unique_ptr<PtpProbe> MakePtpProbe(const std::string& uds_path) {
  if (uds_path == "none") return nullptr;
  if (!uds_path.empty()) return std::make_unique<LinuxPtpProbe>(uds_path);
  std::error_code ec;
  if (std::filesystem::exists(kDefaultPtp4lSocket, ec)) return std::make_unique<LinuxPtpProbe>(kDefaultPtp4lSocket);
  return nullptr;
}

}  // namespace stage
