// Records one camera's frames of one take (docs/storage.md, docs/operators.md): tags every frame with its slot by its
// timestamp (never by arrival order), checks the camera's frame counter against it, and writes it to the camera's
// HDF5 frame file on one writer thread. Live (machine-vision cameras): frames are written as they come. Burst
// (high-speed cameras, whose data rate no disk takes live): frames are held in memory up to a budget during the take
// and written after it, with progress. At the end, the report accounts for every slot the camera was to fire in:
// stored, or lost with a reason.
#pragma once

#include <condition_variable>
#include <cstdint>
#include <deque>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "absl/status/statusor.h"
#include "stage/camera/camera_device.h"
#include "stage/storage/catalog.h"
#include "stage/storage/frame_file.h"

namespace stage::camera {

struct TakePlan {
  std::string path;  // the frame file to create
  // Width, height and bytes per pixel 0: taken from the first frame (a simulated camera renders at a scale).
  storage::FrameFileInfo info;
  // The take's time base on the sync bus: slot k's edge is at t0_ns + k * slot_ns (bus time, ns).
  int64_t t0_ns = 0;
  int64_t slot_ns = 1'096'491;  // exact slot lengths come from the caller as slot_start_ns when given
  // Bus time of each slot's edge relative to t0 (from the time base, exact); empty: k * slot_ns.
  std::function<int64_t(int64_t)> slot_start_ns;
  int64_t slots = 0;
  // The camera fires in slots k with k mod divider == phase, exposing from edge + trigger_delay_ns.
  uint32_t divider = 1;
  uint32_t phase = 0;
  int64_t trigger_delay_ns = 0;
  uint32_t patterns_per_cycle = 38;
  // The camera's clock against the bus: device = bus * (1 + drift_ppm 1e-6) + offset_ns.
  int64_t clock_offset_ns = 0;
  double clock_drift_ppm = 0;
  // Burst: hold frames in memory (up to burst_bytes) and write them after the take.
  bool burst = false;
  uint64_t burst_bytes = 16ull << 30;
  // Live: frames waiting for the writer beyond this many bytes are lost (the disk fell behind).
  uint64_t queue_bytes = 1ull << 30;
  // Subtracted from each frame's mean brightness in the report (the camera's black level, DN).
  double black_level = 0;
  // The frame counter the take's first exposure will carry (the device restarts it at Start()); unknown: judged
  // from the first frame that arrives.
  std::optional<uint64_t> first_frame_id;
  // false: T0 is not known yet (an armed take that waits for the operator); no frame belongs to the take until
  // Update() gives it.
  bool started = true;
  // Frames of this pattern (index in the cycle) are kept for previews; -1: every frame; below -1: none.
  int32_t preview_pattern = -2;
};

// A change to a take's plan while it is armed (see UpdateTakeRequest in camera_node.proto).
struct PlanUpdate {
  std::optional<int64_t> t0_ns;  // the take starts: slot 0's edge on the bus
  std::optional<uint64_t> first_frame_id;
  int64_t slots = 0;  // above 0: the take's new length
  // Every gap of the take, [first, end) in slots, sorted and disjoint: no frame is expected there.
  std::vector<std::pair<int64_t, int64_t>> paused;
};

// The latest frame of the preview pattern.
struct PreviewFrame {
  std::shared_ptr<const Frame> frame;
  int64_t slot = 0;
  int64_t controller_time_ns = 0;
};

struct SlotOutcome {
  int64_t slot = 0;
  int32_t pattern = 0;
  storage::LossReason reason = storage::LossReason::kNone;
  std::optional<uint64_t> frame_id;
  std::string detail;
};

struct TakeRecording {
  // Every slot the camera was to fire in, in order.
  std::vector<SlotOutcome> slots;
  // Mean brightness above black of every stored frame, by slot (the alignment self-test's input).
  std::map<int64_t, double> brightness;
  // Frames matched to a slot of the take (the unmatched are counted apart).
  int64_t frames_received = 0;
  int64_t frames_written = 0;
  // Frames whose timestamp matched no slot this camera fires in (or one already taken).
  int64_t frames_unmatched = 0;
  uint64_t bytes = 0;  // of the frame file
  // Largest distance of a matched frame's timestamp from its slot's trigger time, ns.
  int64_t max_timing_error_ns = 0;
  // The writer's error, if it stopped (disk full, I/O).
  std::string error;
};

class TakeRecorder final : public FrameSink {
 public:
  // Creates the frame file and, live, starts the writer thread.
  static absl::StatusOr<std::unique_ptr<TakeRecorder>> Start(TakePlan plan);
  ~TakeRecorder() override;

  // Tags the frame and queues it; on the camera's thread, never blocking on the disk.
  void OnFrame(std::shared_ptr<const Frame> frame) override;
  // Counts frames exposed in the take and not deliverable (leader lost): the slots after the last delivered frame
  // are theirs as far as there are more of them than the counter's gaps before it.
  void OnFrameLost() override;

  const std::string& path() const { return plan_.path; }
  // How many slots the camera fires in (what the ledger expects of it), pauses excluded.
  int64_t expected_frames() const;
  // The slots the camera fires in, in order.
  std::vector<int64_t> expected_slots() const;
  // Changes the plan (start, length, gaps); frames already tagged keep their slots. InvalidArgument for a bad plan.
  absl::Status Update(const PlanUpdate& update);
  // The latest frame of the preview pattern; nullopt before there is one.
  std::optional<PreviewFrame> LatestPreview() const;
  // Frames received and written so far (progress during the take).
  int64_t frames_received() const;
  int64_t frames_written() const;
  // Lost so far: exposures the frame counter says were made and not delivered (yet: frames may come out of order),
  // and frames that could not be written.
  int64_t frames_lost() const;

  // Ends the take once no more frames come (the camera stopped): writes what is held (burst: with `progress(done,
  // total)`), closes the file and accounts for every expected slot.
  TakeRecording Finish(const std::function<void(int64_t, int64_t)>& progress = nullptr);

  // The camera's link went down `outages` times during the take (`detail`: the device's word on it). Those not followed
  // by a frame (Frame::after_outage) reach the end of the take: Finish gives the slots after the last frame as "link
  // down". Before Finish.
  void ReportLinkOutages(int64_t outages, std::string detail);
  // The camera still owes `frames` it was triggered for (reading them out, rendering) as the take ends (`activity`:
  // what it was doing). They are the slots right after its last delivered frame: Finish gives them as "not delivered",
  // never as triggers missed. Before Finish.
  void ReportUndelivered(int64_t frames, std::string activity);

 private:
  struct Tagged {
    std::shared_ptr<const Frame> frame;
    int64_t slot;
    int64_t bus_ns;
  };
  explicit TakeRecorder(TakePlan plan);
  void WriterLoop();
  void Write(const Tagged& t);  // writer thread only
  int64_t SlotStart(int64_t slot) const;
  bool IsPaused(int64_t slot) const;  // mutex_ held
  // Builds the expected slots from the plan and the pauses, keeping the outcomes of slots that stay (mutex_ held).
  void Rebuild();
  void AddPausedSlots();  // mutex_ held, at the end of Finish

  TakePlan plan_;
  std::map<int64_t, size_t> index_of_;               // expected slot -> its index; guarded by mutex_
  std::vector<std::pair<int64_t, int64_t>> paused_;  // guarded by mutex_
  std::optional<PreviewFrame> preview_;              // guarded by mutex_
  std::optional<uint64_t> max_frame_id_;             // guarded by mutex_
  int64_t write_failures_ = 0;                       // guarded by mutex_
  std::unique_ptr<storage::FrameFileWriter> writer_;

  mutable std::mutex mutex_;
  std::condition_variable changed_;
  std::deque<Tagged> queue_;  // guarded by mutex_
  uint64_t queued_bytes_ = 0;
  bool finishing_ = false;
  std::thread thread_;
  TakeRecording rec_;                    // guarded by mutex_ (outcomes set by both threads)
  std::map<int64_t, uint64_t> matched_;  // slot -> frame id of every tagged frame; guarded by mutex_
  // Outages of the camera's link (Frame::after_outage): the note of one not yet tied to a slot, and the slot of the
  // first frame after each (the silent slots before it are the outage's). Guarded by mutex_.
  std::string pending_outage_;
  std::map<int64_t, std::string> outage_before_;
  int64_t outages_reported_ = 0;
  int64_t outage_notes_ = 0;       // frames with after_outage seen
  int64_t frames_without_id_ = 0;  // OnFrameLost calls during the take
  std::string outage_detail_;
  int64_t undelivered_ = 0;  // ReportUndelivered
  std::string undelivered_activity_;
};

}  // namespace stage::camera
