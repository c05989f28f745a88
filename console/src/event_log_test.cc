#include "event_log.h"

#include <gtest/gtest.h>

#include <thread>

namespace stage::console {
namespace {

using namespace std::chrono_literals;

TEST(EventLogTest, AFollowerGetsWhatCameAfterItsLastIdAndWaitsForMore) {
  EventLog log(10);
  EXPECT_EQ(log.Publish("status", "{\"a\":\n1}"), 1u);
  EXPECT_EQ(log.Publish("alarm", "{}"), 2u);
  bool gap = true;
  auto events = log.After(1, 0ms, &gap);
  EXPECT_FALSE(gap);
  ASSERT_EQ(events.size(), 1u);
  EXPECT_EQ(events[0].id, 2u);
  EXPECT_EQ(events[0].type, "alarm");
  // A newline would end the SSE data line: it is a space.
  EXPECT_EQ(log.After(0, 0ms, &gap)[0].data, "{\"a\": 1}");
  std::thread publisher([&] {
    std::this_thread::sleep_for(50ms);
    log.Publish("log", "{\"line\":\"x\"}");
  });
  events = log.After(2, 10s, &gap);
  publisher.join();
  ASSERT_EQ(events.size(), 1u);
  EXPECT_EQ(events[0].id, 3u);
  EXPECT_EQ(FormatServerSentEvent(events[0]), "id: 3\nevent: log\ndata: {\"line\":\"x\"}\n\n");
  // Data of several lines (an event not published through the log) is a data line each.
  EXPECT_EQ(FormatServerSentEvent({4, "status", "{\n \"a\": 1\n}"}),
            "id: 4\nevent: status\ndata: {\ndata:  \"a\": 1\ndata: }\n\n");
}

TEST(EventLogTest, AFollowerThatFellBehindTheRingOrCameFromAnotherConsoleIsToldOfTheGap) {
  EventLog log(3);
  for (int i = 0; i < 6; ++i) log.Publish("status", "{}");
  bool gap = false;
  auto events = log.After(1, 0ms, &gap);
  EXPECT_TRUE(gap);  // 2 was dropped
  ASSERT_EQ(events.size(), 3u);
  EXPECT_EQ(events.front().id, 4u);
  events = log.After(3, 0ms, &gap);
  EXPECT_FALSE(gap);
  EXPECT_EQ(events.size(), 3u);
  // An id this log never gave (the browser followed a console that has since restarted).
  events = log.After(99, 0ms, &gap);
  EXPECT_TRUE(gap);
  EXPECT_EQ(events.size(), 3u);
}

TEST(EventLogTest, CloseWakesAFollower) {
  EventLog log(3);
  std::thread closer([&] {
    std::this_thread::sleep_for(50ms);
    log.Close();
  });
  bool gap = false;
  EXPECT_TRUE(log.After(0, 60s, &gap).empty());
  closer.join();
}

}  // namespace
}  // namespace stage::console
