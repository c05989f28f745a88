// Plugin modules: found where the spec says, and every way of not finding one is an error that names the file.
#include "stage/common/module.h"

#include <dlfcn.h>
#include <stdlib.h>

#include <cmath>

#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace stage {
namespace {

using ::testing::HasSubstr;

ModuleSpec Spec(const std::string& entry) {
  return {.target = "stage_no_such_module", .entry = entry, .what = "the test's module"};
}

class ModuleTest : public ::testing::Test {
 protected:
  void TearDown() override { unsetenv("FASTAGE_NO_SUCH_MODULE"); }
};

TEST_F(ModuleTest, ItIsLookedForInLibBesideTheProgramsDirectory) {
  EXPECT_EQ(ModuleVariable(Spec("f")), "FASTAGE_NO_SUCH_MODULE");
  EXPECT_THAT(ModulePath(Spec("f")), ::testing::EndsWith("/lib/libstage_no_such_module.so"));
  auto entry = OpenModule(Spec("f"));
  ASSERT_FALSE(entry.ok());
  EXPECT_EQ(entry.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(entry.status().message(), HasSubstr("the test's module "));
  EXPECT_THAT(entry.status().message(), HasSubstr("/lib/libstage_no_such_module.so: no such file"));
  EXPECT_THAT(entry.status().message(), HasSubstr("target stage_no_such_module"));
}

TEST_F(ModuleTest, TheVariableNamesAnotherFileAndItsEntryPointIsFound) {
  // libm is a shared library every program here has: its cos is the entry point asked for.
  Dl_info info{};
  ASSERT_NE(dladdr(reinterpret_cast<void*>(static_cast<double (*)(double)>(&::cos)), &info), 0);
  setenv("FASTAGE_NO_SUCH_MODULE", info.dli_fname, 1);
  EXPECT_EQ(ModulePath(Spec("cos")), info.dli_fname);
  auto entry = OpenModule(Spec("cos"));
  ASSERT_TRUE(entry.ok()) << entry.status();
  EXPECT_DOUBLE_EQ(reinterpret_cast<double (*)(double)>(*entry)(0.0), 1.0);

  auto missing = OpenModule(Spec("stage_no_such_entry"));
  ASSERT_FALSE(missing.ok());
  EXPECT_THAT(missing.status().message(), HasSubstr("no entry point stage_no_such_entry"));
}

TEST_F(ModuleTest, AFileThatIsNoLibraryIsRefusedInDlopensWords) {
  setenv("FASTAGE_NO_SUCH_MODULE", "/proc/self/cmdline", 1);
  auto entry = OpenModule(Spec("f"));
  ASSERT_FALSE(entry.ok());
  EXPECT_THAT(entry.status().message(), HasSubstr("/proc/self/cmdline: "));
  EXPECT_THAT(entry.status().message(), ::testing::Not(HasSubstr("no such file")));
}

}  // namespace
}  // namespace stage
