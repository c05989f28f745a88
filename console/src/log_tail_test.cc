#include "log_tail.h"

#include <gtest/gtest.h>
#include <unistd.h>

#include <filesystem>
#include <fstream>

namespace stage::console {
namespace {

using namespace std::chrono_literals;

TEST(LogTailTest, NewLinesOfAFileInADirectoryAreEventsAndKept) {
  const std::string dir = ::testing::TempDir() + "/log_tail_test_" + std::to_string(::getpid());
  std::filesystem::create_directories(dir);
  std::ofstream(dir + "/a.log") << "old line\n";
  EventLog events(100);
  LogTailOptions options{.paths = {dir}, .poll_ms = 10};
  ASSERT_TRUE(options.Validate().ok());
  LogTail tail(options, &events);
  tail.Start();
  {
    std::ofstream out(dir + "/b.log");  // a file that comes later
    out << "new one\npartial";
  }
  bool gap = false;
  std::vector<ConsoleEvent> seen;
  for (int i = 0; i < 100 && seen.size() < 2; ++i) {
    for (ConsoleEvent& e : events.After(seen.empty() ? 0 : seen.back().id, 100ms, &gap)) seen.push_back(std::move(e));
  }
  tail.Stop();
  ASSERT_EQ(seen.size(), 2u);
  EXPECT_EQ(seen[0].type, "log");
  EXPECT_EQ(tail.RecentJson().find("partial"), std::string::npos);  // not a line until it ends
  EXPECT_NE(tail.RecentJson().find(R"({"line":"new one","source":"b"})"), std::string::npos) << tail.RecentJson();
  std::filesystem::remove_all(dir);
}

TEST(LogTailTest, OptionsNameWhatIsWrong) {
  EXPECT_FALSE(LogTailOptions{.paths = {"/no/such/dir/x.log"}}.Validate().ok());
  EXPECT_TRUE(LogTailOptions{.paths = {"/tmp/not-yet.log"}}.Validate().ok());
  EXPECT_FALSE(LogTailOptions{.keep_lines = 0}.Validate().ok());
  EXPECT_FALSE(LogTailOptions{.poll_ms = 0}.Validate().ok());
}

}  // namespace
}  // namespace stage::console
