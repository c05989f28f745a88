// A take's events to one client, on a thread of its own: see event_writer.h.
#include "event_writer.h"

#include <grpcpp/support/sync_stream.h>

namespace stage::controller {

EventWriter::EventWriter(grpc::ServerContext* context, grpc::ServerWriter<v1::CaptureEvent>* writer)
    : context_(context), writer_(writer), thread_([this] { Run(); }) {}

EventWriter::~EventWriter() { Finish(); }

void EventWriter::Push(const v1::CaptureEvent& e) {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (finishing_) return;
    if (e.has_progress() && !queue_.empty() && queue_.back().has_progress()) {
      queue_.back() = e;  // the newer progress says all the older one did
    } else {
      queue_.push_back(e);
    }
  }
  changed_.notify_all();
}

void EventWriter::Finish(std::chrono::milliseconds grace) {
  {
    std::unique_lock<std::mutex> lock(mutex_);
    if (!thread_.joinable()) return;
    finishing_ = true;
    changed_.notify_all();
    if (!changed_.wait_for(lock, grace, [this] { return drained_; })) {
      context_->TryCancel();  // the client stopped reading: its pending write returns, and the thread ends
    }
  }
  thread_.join();
}

void EventWriter::Run() {
  bool writing = true;  // until the client goes away
  std::unique_lock<std::mutex> lock(mutex_);
  while (true) {
    changed_.wait(lock, [this] { return finishing_ || !queue_.empty(); });
    if (queue_.empty()) break;  // finishing, all written
    v1::CaptureEvent e = std::move(queue_.front());
    queue_.pop_front();
    lock.unlock();
    if (writing && (context_->IsCancelled() || !writer_->Write(e))) writing = false;
    lock.lock();
  }
  drained_ = true;
  changed_.notify_all();
}

}  // namespace stage::controller
