// One camera's take on disk: see recorder.h.
#include "recorder.h"

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <utility>

#include "absl/strings/str_cat.h"
#include "stage/common/logging.h"

namespace stage::camera {
namespace {

using storage::LossReason;

// Mean pixel value over a sample of the frame: every 7th pixel (odd, so every Bayer colour is in the sample).
double MeanBrightness(const Frame& f) {
  // On a fixed grid of about 64k pixels: the alignment self-test's identities are linear in the pixels, so they hold
  // on any fixed subset, and reading every row of a 5 MP frame would cost the writer thread a third of its time.
  const size_t pixels = static_cast<size_t>(f.width) * f.height;
  if (pixels == 0) return 0;
  const std::span<const uint8_t> data = f.pixels();
  const bool wide = data.size() >= pixels * 2;
  const size_t step = std::max<size_t>(1, static_cast<size_t>(std::sqrt(static_cast<double>(pixels) / 65536.0)));
  double sum = 0;
  size_t n = 0;
  for (size_t y = step / 2; y < f.height; y += step) {
    const size_t row = y * f.width;
    for (size_t x = step / 2; x < f.width; x += step, ++n) {
      const size_t i = row + x;
      sum += wide ? static_cast<double>(data[2 * i] | (data[2 * i + 1] << 8)) : data[i];
    }
  }
  return n > 0 ? sum / static_cast<double>(n) : 0;
}

}  // namespace

TakeRecorder::TakeRecorder(TakePlan plan) : plan_(std::move(plan)) {}

int64_t TakeRecorder::SlotStart(int64_t slot) const {
  return plan_.slot_start_ns ? plan_.slot_start_ns(slot) : slot * plan_.slot_ns;
}

absl::StatusOr<std::unique_ptr<TakeRecorder>> TakeRecorder::Start(TakePlan plan) {
  if (plan.slots <= 0) return absl::InvalidArgumentError("a take needs at least one slot");
  if (plan.divider == 0 || plan.phase >= plan.divider) {
    return absl::InvalidArgumentError(
        absl::StrCat("trigger phase ", plan.phase, " is not below the divider ", plan.divider));
  }
  if (plan.patterns_per_cycle == 0) return absl::InvalidArgumentError("no patterns per cycle");
  std::unique_ptr<TakeRecorder> r(new TakeRecorder(std::move(plan)));
  const TakePlan& p = r->plan_;
  r->Rebuild();
  std::error_code ec;
  std::filesystem::create_directories(std::filesystem::path(p.path).parent_path(), ec);
  if (ec) return absl::UnavailableError(absl::StrCat(p.path, ": cannot create its directory: ", ec.message()));
  if (p.info.width > 0) {
    auto writer = storage::FrameFileWriter::Create(p.path, p.info);
    if (!writer.ok()) return writer.status();
    r->writer_ = std::move(*writer);
  } else if (std::filesystem::exists(p.path, ec)) {
    return absl::AlreadyExistsError(absl::StrCat(p.path, ": exists; a take's frames are never overwritten"));
  }
  if (!p.burst) {
    r->thread_ = std::thread([raw = r.get()] { raw->WriterLoop(); });
  }
  return r;
}

bool TakeRecorder::IsPaused(int64_t slot) const {
  for (const auto& [first, end] : paused_) {
    if (slot >= first && slot < end) return true;
  }
  return false;
}

void TakeRecorder::Rebuild() {
  std::map<int64_t, size_t> index_of;
  std::vector<SlotOutcome> slots;
  for (int64_t k = plan_.phase; k < plan_.slots; k += plan_.divider) {
    if (IsPaused(k)) continue;
    index_of[k] = slots.size();
    auto old = index_of_.find(k);
    slots.push_back(
        old != index_of_.end()
            ? rec_.slots[old->second]
            : SlotOutcome{k, static_cast<int32_t>(k % plan_.patterns_per_cycle), LossReason::kTriggerMissed, {}, ""});
  }
  index_of_ = std::move(index_of);
  rec_.slots = std::move(slots);
  // Received: the frames matched to a slot the take still has (a pause or an abort can take slots away).
  rec_.frames_received = 0;
  for (const auto& [slot, frame_id] : matched_) rec_.frames_received += index_of_.count(slot) ? 1 : 0;
}

absl::Status TakeRecorder::Update(const PlanUpdate& update) {
  std::lock_guard<std::mutex> lock(mutex_);
  if (finishing_) return absl::FailedPreconditionError("the take is finishing");
  const int64_t slots = update.slots > 0 ? update.slots : plan_.slots;
  int64_t last_end = 0;
  for (const auto& [first, end] : update.paused) {
    if (first < last_end || end <= first || end > slots) {
      return absl::InvalidArgumentError(absl::StrCat("pause [", first, ", ", end, ") is not a gap of a take of ", slots,
                                                     " slots after the one before it"));
    }
    last_end = end;
  }
  if (update.t0_ns) {
    plan_.t0_ns = *update.t0_ns;
    plan_.started = true;
  }
  if (update.first_frame_id) plan_.first_frame_id = update.first_frame_id;
  plan_.slots = slots;
  paused_ = update.paused;
  Rebuild();
  return absl::OkStatus();
}

int64_t TakeRecorder::frames_lost() const {
  std::lock_guard<std::mutex> lock(mutex_);
  int64_t dropped = 0;
  if (max_frame_id_ && plan_.first_frame_id && *max_frame_id_ >= *plan_.first_frame_id) {
    const auto exposed = static_cast<int64_t>(*max_frame_id_ - *plan_.first_frame_id + 1);
    dropped = std::max<int64_t>(0, exposed - static_cast<int64_t>(matched_.size()));
  }
  return dropped + write_failures_;
}

int64_t TakeRecorder::expected_frames() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return static_cast<int64_t>(index_of_.size());
}

std::vector<int64_t> TakeRecorder::expected_slots() const {
  std::lock_guard<std::mutex> lock(mutex_);
  std::vector<int64_t> slots;
  for (const auto& [slot, index] : index_of_) slots.push_back(slot);
  return slots;
}

std::optional<PreviewFrame> TakeRecorder::LatestPreview() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return preview_;
}

TakeRecorder::~TakeRecorder() {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    finishing_ = true;
  }
  changed_.notify_all();
  if (thread_.joinable()) thread_.join();
}

int64_t TakeRecorder::frames_received() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return rec_.frames_received;
}

int64_t TakeRecorder::frames_written() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return rec_.frames_written;
}

void TakeRecorder::OnFrame(std::shared_ptr<const Frame> frame) {
  std::unique_lock<std::mutex> lock(mutex_);
  if (!plan_.started) return;  // not the take's yet
  // The bus time of the exposure start, and the nearest trigger time to it.
  const long double device = static_cast<long double>(frame->device_timestamp_ns - plan_.clock_offset_ns);
  const auto bus = static_cast<int64_t>(std::llround(device / (1.0L + plan_.clock_drift_ppm * 1e-6L)));
  const int64_t rel = bus - plan_.t0_ns - plan_.trigger_delay_ns;
  const int64_t guess =
      static_cast<int64_t>(std::llround(static_cast<double>(rel) / static_cast<double>(plan_.slot_ns)));
  int64_t slot = guess;
  int64_t error = INT64_MAX;
  for (int64_t k = guess - 1; k <= guess + 1; ++k) {
    const int64_t e = std::llabs(rel - SlotStart(k));
    if (e < error) {
      error = e;
      slot = k;
    }
  }
  const size_t bytes = frame->pixels().size();
  if (!frame->after_outage.empty()) {
    pending_outage_ = frame->after_outage;
    ++outage_notes_;
  }
  auto it = index_of_.find(slot);
  if (it == index_of_.end() || matched_.count(slot) || finishing_) {
    // Not the take's: outside its slots (a clock that ran before T0 or runs on after the end), or a second frame.
    ++rec_.frames_unmatched;
    return;
  }
  ++rec_.frames_received;
  if (plan_.preview_pattern >= -1 &&
      (plan_.preview_pattern == -1 || slot % plan_.patterns_per_cycle == plan_.preview_pattern)) {
    preview_ = PreviewFrame{frame, slot, bus - plan_.t0_ns};
  }
  matched_[slot] = frame->frame_id;
  if (!pending_outage_.empty()) outage_before_[slot] = std::exchange(pending_outage_, std::string());
  max_frame_id_ = std::max(max_frame_id_.value_or(0), frame->frame_id);
  rec_.max_timing_error_ns = std::max(rec_.max_timing_error_ns, error);
  SlotOutcome& out = rec_.slots[it->second];
  out.frame_id = frame->frame_id;
  const uint64_t budget = plan_.burst ? plan_.burst_bytes : plan_.queue_bytes;
  if (queued_bytes_ + bytes > budget) {
    ++write_failures_;
    out.reason = LossReason::kWriteFailed;
    out.detail = plan_.burst ? absl::StrCat("burst memory full (", budget >> 20, " MiB)")
                             : "the recorder fell behind (the disk is slower than the camera)";
    return;
  }
  // Tentatively: the writer may still fail. A frame with data missing is kept in the file, marked, and lost.
  out.reason = frame->incomplete.empty() ? LossReason::kNone : LossReason::kIncomplete;
  out.detail = frame->incomplete;
  queued_bytes_ += bytes;
  queue_.push_back({std::move(frame), slot, bus});
  lock.unlock();
  changed_.notify_all();
}

void TakeRecorder::OnFrameLost() {
  std::lock_guard<std::mutex> lock(mutex_);
  if (!plan_.started || finishing_) return;  // not the take's
  ++frames_without_id_;
}

void TakeRecorder::WriterLoop() {
  while (true) {
    Tagged t;
    {
      std::unique_lock<std::mutex> lock(mutex_);
      changed_.wait(lock, [&] { return !queue_.empty() || finishing_; });
      if (queue_.empty()) return;  // finishing, and all written
      t = std::move(queue_.front());
      queue_.pop_front();
    }
    Write(t);
  }
}

void TakeRecorder::Write(const Tagged& t) {
  const Frame& f = *t.frame;
  storage::FrameRecord record;
  record.frame_id = f.frame_id;
  record.device_timestamp_ns = f.device_timestamp_ns;
  record.controller_time_ns = t.bus_ns - plan_.t0_ns;
  record.slot = t.slot;
  record.pattern = static_cast<int32_t>(t.slot % plan_.patterns_per_cycle);
  record.status = f.incomplete.empty() ? storage::FrameStatus::kOk : storage::FrameStatus::kIncomplete;
  absl::Status s = absl::OkStatus();
  if (writer_ == nullptr) {
    // The file takes the frames' shape from the first one.
    storage::FrameFileInfo info = plan_.info;
    info.width = f.width;
    info.height = f.height;
    const size_t pixels = static_cast<size_t>(f.width) * f.height;
    info.bytes_per_pixel = pixels > 0 ? static_cast<uint32_t>(f.pixels().size() / pixels) : 0;
    auto writer = storage::FrameFileWriter::Create(plan_.path, info);
    if (writer.ok()) {
      writer_ = std::move(*writer);
    } else {
      s = writer.status();
    }
  }
  if (s.ok()) s = writer_->Append(record, f.pixels());
  const double brightness = s.ok() ? MeanBrightness(f) - plan_.black_level : 0;
  std::lock_guard<std::mutex> lock(mutex_);
  queued_bytes_ -= std::min<uint64_t>(queued_bytes_, f.pixels().size());
  auto at = index_of_.find(t.slot);
  if (at == index_of_.end()) return;  // an abort cut the take short before this slot: written, not expected
  SlotOutcome& out = rec_.slots[at->second];
  if (s.ok()) {
    ++rec_.frames_written;
    if (f.incomplete.empty()) rec_.brightness[t.slot] = brightness;  // part of an incomplete frame is zero
  } else {
    ++write_failures_;
    out.reason = LossReason::kWriteFailed;
    out.detail = rec_.error.empty() ? std::string(s.message()) : rec_.error;
    if (rec_.error.empty()) {
      rec_.error = std::string(s.message());
      Logger("camera")->error("{}", rec_.error);
    }
  }
}

void TakeRecorder::ReportLinkOutages(int64_t outages, std::string detail) {
  std::lock_guard<std::mutex> lock(mutex_);
  outages_reported_ = outages;
  outage_detail_ = std::move(detail);
}

void TakeRecorder::ReportUndelivered(int64_t frames, std::string activity) {
  std::lock_guard<std::mutex> lock(mutex_);
  undelivered_ = std::max<int64_t>(0, frames);
  undelivered_activity_ = std::move(activity);
}

TakeRecording TakeRecorder::Finish(const std::function<void(int64_t, int64_t)>& progress) {
  if (plan_.burst) {
    // The take is over: offload what the camera held, in slot order.
    std::deque<Tagged> held;
    {
      std::lock_guard<std::mutex> lock(mutex_);
      finishing_ = true;
      held.swap(queue_);
    }
    std::sort(held.begin(), held.end(), [](const Tagged& a, const Tagged& b) { return a.slot < b.slot; });
    const auto total = static_cast<int64_t>(held.size());
    int64_t done = 0;
    for (const Tagged& t : held) {
      Write(t);
      if (progress) progress(++done, total);
    }
  } else {
    {
      std::lock_guard<std::mutex> lock(mutex_);
      finishing_ = true;
    }
    changed_.notify_all();
    if (thread_.joinable()) thread_.join();
  }
  if (writer_ != nullptr) {
    if (absl::Status s = writer_->Close(); !s.ok() && rec_.error.empty()) rec_.error = std::string(s.message());
  }
  std::error_code ec;
  const auto size = std::filesystem::file_size(plan_.path, ec);
  std::lock_guard<std::mutex> lock(mutex_);
  rec_.bytes = ec ? 0 : size;

  // Slots without a frame: the frame counter tells exposures the camera made and never delivered (camera dropped)
  // from triggers it never exposed on (trigger missed). Between two delivered frames with ids a and b, b - a - 1
  // exposures were lost; they are the first of the silent slots there (which ones exactly the counter cannot say).
  std::vector<std::pair<int64_t, uint64_t>> delivered;  // slot, frame id, of expected slots
  for (const auto& [slot, id] : matched_) {
    if (index_of_.count(slot)) delivered.emplace_back(slot, id);
  }
  int64_t marked_exposed = 0;  // slots marked exposed and not delivered so far
  auto account = [&](size_t first, size_t last, int64_t exposed, bool rest_never_exposed, const std::string& how,
                     const std::string& where, const std::string& outage = std::string(), int64_t owed = 0) {
    // Expected slots [first, last) (indexes) are silent; the first `exposed` of them were exposed (`how` says how that
    // is known), the `owed` after those the camera was still producing, and the rest never were exposed if
    // `rest_never_exposed`, else nothing is known of them. In an outage of the camera's link (its note) they are all
    // the outage's: the frame counter goes on across it.
    for (size_t i = first; i < last; ++i) {
      SlotOutcome& out = rec_.slots[i];
      if (matched_.count(out.slot)) continue;
      if (!outage.empty()) {
        out.reason = LossReason::kLinkDown;
        out.detail = outage;
      } else if (exposed > 0) {
        out.reason = LossReason::kCameraDropped;
        out.detail = absl::StrCat("exposed (", how, ") but not delivered", where);
        --exposed;
        ++marked_exposed;
      } else if (owed > 0) {
        out.reason = LossReason::kNotDelivered;
        out.detail = absl::StrCat("triggered; the camera was still producing it when the take ended",
                                  undelivered_activity_.empty() ? "" : absl::StrCat(" (", undelivered_activity_, ")"));
        --owed;
      } else {
        out.reason = LossReason::kTriggerMissed;
        out.detail = rest_never_exposed ? absl::StrCat("never exposed", where) : absl::StrCat("no frame", where);
      }
    }
  };
  // After the last delivered frame the counter says nothing; the frames that came without their leader (no id) say
  // how many were exposed there, as far as there are more of them than the counter's gaps before. (A gap the camera
  // sent nothing of at all counts in the gaps and not in those frames: the tail's figure is a lower bound.)
  auto tail_exposed = [&] { return std::max<int64_t>(0, frames_without_id_ - marked_exposed); };
  constexpr char kLeaderless[] = "a frame came without its leader";
  // The link was down after the last frame: as the take ended, or until a frame that came after the take.
  const std::string tail_outage = outages_reported_ > outage_notes_ ? outage_detail_ : pending_outage_;
  if (delivered.empty()) {
    account(0, rec_.slots.size(), tail_exposed(), false, kLeaderless, " (the camera delivered nothing)", tail_outage,
            undelivered_);
    AddPausedSlots();
    return rec_;
  }
  // The counter of the exposure before the next delivered frame's silent run (the take's first: first_frame_id - 1).
  std::optional<int64_t> before;
  if (plan_.first_frame_id) before = static_cast<int64_t>(*plan_.first_frame_id) - 1;
  size_t from = 0;
  for (const auto& [slot, id] : delivered) {
    const size_t at = index_of_.at(slot);
    const auto silent = static_cast<int64_t>(at - from);
    if (silent > 0) {
      auto outage = outage_before_.find(slot);
      // Without a counter before (the take's first frame id unknown), nothing is known of the run.
      const int64_t exposed = before ? std::clamp<int64_t>(static_cast<int64_t>(id) - *before - 1, 0, silent) : 0;
      account(from, at, exposed, before.has_value(), "frame counter", "",
              outage != outage_before_.end() ? outage->second : std::string());
    }
    before = static_cast<int64_t>(id);
    from = at + 1;
  }
  account(from, rec_.slots.size(), tail_exposed(), false, kLeaderless, " after the last frame the camera delivered",
          tail_outage, undelivered_);
  AddPausedSlots();
  return rec_;
}

void TakeRecorder::AddPausedSlots() {
  // Listed as such: nothing expected there, nothing lost.
  for (const auto& [first, end] : paused_) {
    for (int64_t k = first; k < end; ++k) {
      if (k % plan_.divider != plan_.phase) continue;
      rec_.slots.push_back(
          {k, static_cast<int32_t>(k % plan_.patterns_per_cycle), LossReason::kPaused, {}, "the take was paused"});
    }
  }
  std::sort(rec_.slots.begin(), rec_.slots.end(),
            [](const SlotOutcome& a, const SlotOutcome& b) { return a.slot < b.slot; });
}

}  // namespace stage::camera
