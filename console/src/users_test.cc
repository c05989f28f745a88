#include "users.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <sys/stat.h>
#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <thread>

namespace stage::console {
namespace {

std::string TempPath(const std::string& name) {
  const std::string dir = ::testing::TempDir() + "/users_test_" + std::to_string(::getpid());
  std::filesystem::create_directories(dir);
  return dir + "/" + name;
}

TEST(UsersTest, PasswordsAreCheckedAgainstSaltedHashesAndGiveTheRole) {
  const std::string path = TempPath("users");
  std::filesystem::remove(path);
  ASSERT_TRUE(AddUser(path, "ana", Role::kOperator, "correct horse", 1000).ok());
  ASSERT_TRUE(AddUser(path, "bo", Role::kObserver, "battery staple", 1000).ok());
  struct stat st {};
  ASSERT_EQ(::stat(path.c_str(), &st), 0);
  EXPECT_EQ(st.st_mode & 0777, 0600u);
  auto book = UserBook::Load(path);
  ASSERT_TRUE(book.ok()) << book.status();
  EXPECT_EQ(book->size(), 2u);
  auto ana = book->Verify("ana", "correct horse");
  ASSERT_TRUE(ana.ok());
  EXPECT_EQ(*ana, Role::kOperator);
  EXPECT_EQ(*book->Verify("bo", "battery staple"), Role::kObserver);
  EXPECT_EQ(book->Verify("ana", "battery staple").status().code(), absl::StatusCode::kPermissionDenied);
  EXPECT_EQ(book->Verify("cy", "x").status().message(), book->Verify("ana", "x").status().message());
  // The file holds no password, and two users with one password have different hashes (their salts).
  std::ifstream in(path);
  std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  EXPECT_EQ(text.find("correct horse"), std::string::npos);
  ASSERT_TRUE(AddUser(path, "bo", Role::kObserver, "correct horse", 1000).ok());  // replaces bo
  book = UserBook::Load(path);
  EXPECT_EQ(book->size(), 2u);
  EXPECT_TRUE(book->Verify("bo", "correct horse").ok());
  EXPECT_FALSE(book->Verify("bo", "battery staple").ok());
}

TEST(UsersTest, ABadFileOrUserIsNamed) {
  const std::string path = TempPath("bad-users");
  std::ofstream(path) << "# users\nana:admin:pbkdf2-sha256:1000:00112233445566778899:00\n";
  auto book = UserBook::Load(path);
  EXPECT_EQ(book.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(book.status().message()), ::testing::HasSubstr(path + " line 2: role 'admin'"));
  EXPECT_EQ(UserBook::Load(path + ".missing").status().code(), absl::StatusCode::kNotFound);
  EXPECT_EQ(AddUser(path, "a:b", Role::kObserver, "x").code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(AddUser(path, "ana", Role::kObserver, "").code(), absl::StatusCode::kInvalidArgument);
  EXPECT_FALSE(ParseRole("root").ok());
}

TEST(UsersTest, SessionsAreRandomTokensThatExpire) {
  Sessions sessions(std::chrono::seconds(3600));
  const std::string a = sessions.Open("ana", Role::kOperator);
  const std::string b = sessions.Open("ana", Role::kOperator);
  EXPECT_NE(a, b);
  EXPECT_EQ(a.size(), 64u);
  ASSERT_TRUE(sessions.Find(a).has_value());
  EXPECT_EQ(sessions.Find(a)->user, "ana");
  EXPECT_FALSE(sessions.Find("not-a-token").has_value());
  sessions.Close(a);
  EXPECT_FALSE(sessions.Find(a).has_value());
  Sessions brief(std::chrono::seconds(0));
  const std::string c = brief.Open("bo", Role::kObserver);
  std::this_thread::sleep_for(std::chrono::milliseconds(2));
  EXPECT_FALSE(brief.Find(c).has_value());
}

}  // namespace
}  // namespace stage::console
