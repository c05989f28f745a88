// Subprocess: spawn, output redirection, exit codes, and the SIGTERM -> SIGKILL escalation on a child that ignores
// SIGTERM.
#include "stage/common/subprocess.h"

#include <signal.h>

#include <fstream>
#include <sstream>

#include "gtest/gtest.h"

namespace stage {
namespace {

std::string Slurp(const std::string& path) {
  std::ifstream in(path);
  std::stringstream s;
  s << in.rdbuf();
  return s.str();
}

TEST(SubprocessTest, RunsAndCapturesOutput) {
  std::string out = "/tmp/fastage-subprocess-test.out";
  auto p = Subprocess::Spawn(
      {.argv = {"sh", "-c", "echo hello $GREETING; exit 3"}, .env = {"GREETING=world"}, .stdout_path = out});
  ASSERT_TRUE(p.ok()) << p.status();
  auto exit = (*p)->Wait(std::chrono::seconds(10));
  ASSERT_TRUE(exit.has_value());
  EXPECT_EQ(exit->exit_code, 3);
  EXPECT_EQ(exit->signal, 0);
  EXPECT_EQ(Slurp(out), "hello world\n");
  std::remove(out.c_str());
}

TEST(SubprocessTest, MissingProgramIsAnErrorNotAnExitCode) {
  auto p = Subprocess::Spawn({.argv = {"/nonexistent/program"}});
  ASSERT_FALSE(p.ok());
  EXPECT_EQ(p.status().code(), absl::StatusCode::kNotFound);
  EXPECT_FALSE(Subprocess::Spawn({.argv = {"no-such-program-fastage"}}).ok());
}

TEST(SubprocessTest, TerminateEscalatesToSigkill) {
  // The child ignores SIGTERM: only SIGKILL ends it.
  auto p = Subprocess::Spawn({.argv = {"sh", "-c", "trap '' TERM; echo ready; while :; do sleep 0.05; done"},
                              .stdout_path = "/tmp/fastage-subprocess-term.out"});
  ASSERT_TRUE(p.ok());
  while (Slurp("/tmp/fastage-subprocess-term.out").empty()) std::this_thread::sleep_for(std::chrono::milliseconds(5));
  bool killed = false;
  ExitInfo info = (*p)->Terminate(std::chrono::milliseconds(200), &killed);
  EXPECT_TRUE(killed);
  EXPECT_EQ(info.signal, SIGKILL);
  EXPECT_EQ(kill((*p)->pid(), 0), -1);  // reaped: the pid is gone
  std::remove("/tmp/fastage-subprocess-term.out");
}

TEST(SubprocessTest, TerminateStopsAWellBehavedChildWithSigterm) {
  auto p = Subprocess::Spawn({.argv = {"sleep", "30"}});
  ASSERT_TRUE(p.ok());
  bool killed = true;
  ExitInfo info = (*p)->Terminate(std::chrono::seconds(10), &killed);
  EXPECT_FALSE(killed);
  EXPECT_EQ(info.signal, SIGTERM);
  EXPECT_EQ(info.Describe(), "killed by signal 15 (Terminated)");
}

TEST(SubprocessTest, DestructorKillsAndReaps) {
  pid_t pid;
  {
    auto p = Subprocess::Spawn({.argv = {"sleep", "30"}});
    ASSERT_TRUE(p.ok());
    pid = (*p)->pid();
  }
  EXPECT_EQ(kill(pid, 0), -1);
}

}  // namespace
}  // namespace stage
