// Writes a take's events to one client on a thread of its own, so that a client slow to read (or stopped: its flow
// control window full) never holds the take up. States, messages and the summary are all kept in order; a progress
// event replaces one that is queued and not yet written, so the queue stays small. A client that goes away stops the
// writing, not the take.
#pragma once

#include <grpcpp/grpcpp.h>

#include <chrono>
#include <condition_variable>
#include <deque>
#include <mutex>
#include <thread>

#include "stage/v1/controller.pb.h"

namespace stage::controller {

class EventWriter {
 public:
  EventWriter(grpc::ServerContext* context, grpc::ServerWriter<v1::CaptureEvent>* writer);
  // Finish(), if not yet.
  ~EventWriter();

  // Queues `e`; never blocks on the client.
  void Push(const v1::CaptureEvent& e);
  // Writes what is queued, at most `grace` more (then the call is cancelled: a client that stopped reading is let go),
  // and stops the thread.
  void Finish(std::chrono::milliseconds grace = std::chrono::seconds(30));

 private:
  void Run();

  grpc::ServerContext* context_;
  grpc::ServerWriter<v1::CaptureEvent>* writer_;
  std::mutex mutex_;
  std::condition_variable changed_;
  std::deque<v1::CaptureEvent> queue_;  // guarded by mutex_
  bool finishing_ = false;              // guarded by mutex_
  bool drained_ = false;                // guarded by mutex_: the thread wrote everything and stopped
  std::thread thread_;
};

}  // namespace stage::controller
