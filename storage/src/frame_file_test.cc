// Frame files: what is written reads back (records, pixels, attributes); a writer killed mid-take leaves every frame
// it had appended readable; a writer that runs out of space stops with an error that says so, and what it appended
// stays readable.
#include "stage/storage/frame_file.h"

#include <sched.h>
#include <signal.h>
#include <sys/mount.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>

#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace stage::storage {
namespace {

using ::testing::HasSubstr;

FrameFileInfo Info(uint32_t bytes_per_pixel = 2) {
  FrameFileInfo info;
  info.camera_id = "hs-2";
  info.take_id = "fastage-20261123-0001";
  info.width = 48;
  info.height = 32;
  info.bytes_per_pixel = bytes_per_pixel;
  info.pixel_format = bytes_per_pixel == 1 ? "BayerRG8" : "BayerRG12";
  info.exposure_us = 850;
  info.gain_db = 1.5;
  info.calibration_json = R"({"fx": 1234.5})";
  return info;
}

// Frame i's pixels: every byte a function of i and its position, so a mixed-up frame shows.
std::vector<uint8_t> Pixels(const FrameFileInfo& info, int64_t i) {
  std::vector<uint8_t> p(static_cast<size_t>(info.width) * info.height * info.bytes_per_pixel);
  for (size_t k = 0; k < p.size(); ++k) p[k] = static_cast<uint8_t>((k * 7 + static_cast<size_t>(i) * 13) & 0xff);
  return p;
}

FrameRecord Record(int64_t i) {
  return {static_cast<uint64_t>(100 + i),
          5'000'000 + i * 1'096'491,
          i * 1'096'491,
          i,
          static_cast<int32_t>(i % 38),
          i % 5 == 4 ? FrameStatus::kIncomplete : FrameStatus::kOk};
}

void ExpectFrames(const std::string& path, int64_t at_least, int64_t at_most) {
  auto reader = FrameFileReader::Open(path);
  ASSERT_TRUE(reader.ok()) << reader.status();
  const int64_t n = (*reader)->frames();
  EXPECT_GE(n, at_least);
  EXPECT_LE(n, at_most);
  auto records = (*reader)->Records();
  ASSERT_TRUE(records.ok()) << records.status();
  ASSERT_EQ(static_cast<int64_t>(records->size()), n);
  const FrameFileInfo& info = (*reader)->info();
  for (int64_t i = 0; i < n; ++i) {
    const FrameRecord want = Record(i), got = (*records)[static_cast<size_t>(i)];
    EXPECT_EQ(got.frame_id, want.frame_id);
    EXPECT_EQ(got.device_timestamp_ns, want.device_timestamp_ns);
    EXPECT_EQ(got.controller_time_ns, want.controller_time_ns);
    EXPECT_EQ(got.slot, want.slot);
    EXPECT_EQ(got.pattern, want.pattern);
    EXPECT_EQ(got.status, want.status);
    auto pixels = (*reader)->Pixels(i);
    ASSERT_TRUE(pixels.ok()) << pixels.status();
    EXPECT_EQ(*pixels, Pixels(info, i)) << "frame " << i;
  }
}

TEST(FrameFileTest, WhatIsWrittenReadsBack) {
  const std::string path = ::testing::TempDir() + "/frames-roundtrip.h5";
  std::filesystem::remove(path);
  for (uint32_t bpp : {2u, 1u}) {
    std::filesystem::remove(path);
    const FrameFileInfo info = Info(bpp);
    auto writer = FrameFileWriter::Create(path, info);
    ASSERT_TRUE(writer.ok()) << writer.status();
    for (int64_t i = 0; i < 9; ++i) ASSERT_TRUE((*writer)->Append(Record(i), Pixels(info, i)).ok());
    EXPECT_EQ((*writer)->frames(), 9);
    ASSERT_TRUE((*writer)->Close().ok());
    ExpectFrames(path, 9, 9);
    auto reader = FrameFileReader::Open(path);
    ASSERT_TRUE(reader.ok());
    const FrameFileInfo& got = (*reader)->info();
    EXPECT_EQ(got.camera_id, "hs-2");
    EXPECT_EQ(got.take_id, info.take_id);
    EXPECT_EQ(got.width, 48u);
    EXPECT_EQ(got.height, 32u);
    EXPECT_EQ(got.bytes_per_pixel, bpp);
    EXPECT_EQ(got.pixel_format, info.pixel_format);
    EXPECT_DOUBLE_EQ(got.exposure_us, 850);
    EXPECT_DOUBLE_EQ(got.gain_db, 1.5);
    EXPECT_EQ(got.calibration_json, info.calibration_json);
    EXPECT_TRUE(absl::IsOutOfRange((*reader)->Pixels(9).status()));
  }
}

// Bytes the file system holds for `path` (what `du` counts).
int64_t OnDisk(const std::string& path) {
  struct stat st {};
  EXPECT_EQ(stat(path.c_str(), &st), 0) << path;
  return static_cast<int64_t>(st.st_blocks) * 512;
}

// The writer reserves space ahead of the frames it appends (16 MiB, or 16 frames); closing gives back what it did not
// use, so the file holds on disk what its size says (the catalog's figure), give or take a block.
TEST(FrameFileTest, ClosingGivesBackTheSpaceReservedBeyondTheFrames) {
  const std::string path = ::testing::TempDir() + "/frames-reserve.h5";
  std::filesystem::remove(path);
  const FrameFileInfo info = Info();
  auto writer = FrameFileWriter::Create(path, info);
  ASSERT_TRUE(writer.ok()) << writer.status();
  for (int64_t i = 0; i < 5; ++i) ASSERT_TRUE((*writer)->Append(Record(i), Pixels(info, i)).ok());
  const int64_t reserved = OnDisk(path);
  const auto size = static_cast<int64_t>(std::filesystem::file_size(path));
  if (reserved < size + (8 << 20))
    GTEST_SKIP() << "this file system reserves no space ahead (" << reserved << " bytes)";
  ASSERT_TRUE((*writer)->Close().ok());
  const auto closed_size = static_cast<int64_t>(std::filesystem::file_size(path));
  EXPECT_LE(OnDisk(path), closed_size + 65536) << "size " << closed_size << ", reserved while open " << reserved;
  ExpectFrames(path, 5, 5);
}

TEST(FrameFileTest, TheSpaceAWriterThatDiedReservedIsGivenBackOnRecovery) {
  const std::string path = ::testing::TempDir() + "/frames-reserve-died.h5";
  std::filesystem::remove(path);
  const FrameFileInfo info = Info();
  const pid_t child = fork();
  ASSERT_GE(child, 0);
  if (child == 0) {
    auto writer = FrameFileWriter::Create(path, info);
    if (!writer.ok()) _exit(3);
    for (int64_t i = 0; i < 3; ++i) {
      if (!(*writer)->Append(Record(i), Pixels(info, i)).ok()) _exit(4);
    }
    kill(getpid(), SIGKILL);  // dies with the file open: no Close()
  }
  int status = 0;
  ASSERT_EQ(waitpid(child, &status, 0), child);
  ASSERT_TRUE(WIFSIGNALED(status)) << status;
  const auto size = static_cast<int64_t>(std::filesystem::file_size(path));
  if (OnDisk(path) < size + (8 << 20)) GTEST_SKIP() << "this file system reserves no space ahead";
  ASSERT_TRUE(ReleaseReservedSpace(path).ok());
  EXPECT_LE(OnDisk(path), size + 65536);
  EXPECT_EQ(static_cast<int64_t>(std::filesystem::file_size(path)), size);
  ExpectFrames(path, 3, 3);  // what it appended still reads back
  const absl::Status missing = ReleaseReservedSpace(path + ".none");
  EXPECT_TRUE(absl::IsUnavailable(missing));
  EXPECT_THAT(missing.message(), HasSubstr(path + ".none"));
}

// The text attributes as a Python user reads them (h5py): str, not bytes (HDF5 variable-length UTF-8 strings).
TEST(FrameFileTest, H5pyReadsTheTextAttributesAsStr) {
  const std::string path = ::testing::TempDir() + "/frames-h5py.h5";
  std::filesystem::remove(path);
  FrameFileInfo info = Info(1);
  info.patterns_json = R"([{"index": 0, "name": "cross-full", "polarization": "cross"}])";
  info.camera_id = "hs-2 \u00e9";  // UTF-8 survives
  {
    auto writer = FrameFileWriter::Create(path, info);
    ASSERT_TRUE(writer.ok()) << writer.status();
    ASSERT_TRUE((*writer)->Append(Record(0), Pixels(info, 0)).ok());
    ASSERT_TRUE((*writer)->Close().ok());
  }
  const std::string script =
      "import h5py, sys\n"
      "f = h5py.File(sys.argv[1], 'r')\n"
      "for k in ('format', 'camera_id', 'take_id', 'pixel_format', 'calibration', 'patterns'):\n"
      "    v = f.attrs[k]\n"
      "    print(k, type(v).__name__, v)\n";
  const std::string command = "/usr/bin/python3 -c \"" + script + "\" " + path + " 2>&1";
  std::string out;
  if (FILE* p = popen(command.c_str(), "r")) {
    char buffer[4096];
    for (size_t got; (got = fread(buffer, 1, sizeof buffer, p)) > 0;) out.append(buffer, got);
    EXPECT_EQ(pclose(p), 0) << out;
  }
  EXPECT_THAT(out, HasSubstr("format str fastage-frames-1"));
  EXPECT_THAT(out, HasSubstr("camera_id str hs-2 \u00e9"));
  EXPECT_THAT(out, HasSubstr("pixel_format str BayerRG8"));
  EXPECT_THAT(out, HasSubstr("patterns str [{\"index\": 0, \"name\": \"cross-full\""));
  // And this project's reader reads them back...
  auto reader = FrameFileReader::Open(path);
  ASSERT_TRUE(reader.ok()) << reader.status();
  EXPECT_EQ((*reader)->info().camera_id, info.camera_id);
  EXPECT_EQ((*reader)->info().patterns_json, info.patterns_json);
  reader->reset();
  // ...as it reads the fixed-length strings of files written before (h5py writes numpy bytes that way).
  const std::string rewrite =
      "/usr/bin/python3 -c \"import h5py, numpy, sys; f = h5py.File(sys.argv[1], 'r+'); "
      "f.attrs['camera_id'] = numpy.bytes_(b'mv-07')\" " +
      path + " 2>&1";
  ASSERT_EQ(std::system(rewrite.c_str()), 0);
  auto old = FrameFileReader::Open(path);
  ASSERT_TRUE(old.ok()) << old.status();
  EXPECT_EQ((*old)->info().camera_id, "mv-07");
  EXPECT_EQ((*old)->info().pixel_format, "BayerRG8");
}

TEST(FrameFileTest, RefusesToOverwriteAndWrongSizes) {
  const std::string path = ::testing::TempDir() + "/frames-refuse.h5";
  std::filesystem::remove(path);
  const FrameFileInfo info = Info();
  auto writer = FrameFileWriter::Create(path, info);
  ASSERT_TRUE(writer.ok()) << writer.status();
  const absl::Status short_frame = (*writer)->Append(Record(0), std::vector<uint8_t>(10));
  EXPECT_TRUE(absl::IsInvalidArgument(short_frame));
  EXPECT_THAT(short_frame.message(), HasSubstr("has 10 bytes, the file holds frames of 3072"));
  ASSERT_TRUE((*writer)->Close().ok());
  auto again = FrameFileWriter::Create(path, info);
  ASSERT_FALSE(again.ok());
  EXPECT_THAT(again.status().message(), HasSubstr("never overwritten"));
  FrameFileInfo bad = info;
  bad.bytes_per_pixel = 3;
  EXPECT_FALSE(FrameFileWriter::Create(path + ".3", bad).ok());
  auto not_ours = FrameFileReader::Open("/nonexistent/frames.h5");
  ASSERT_FALSE(not_ours.ok());
  EXPECT_THAT(not_ours.status().message(), HasSubstr("/nonexistent/frames.h5"));
}

// A child process writes frames as fast as it can and reports each one appended through a pipe; it is killed
// (SIGKILL, by pid) at once after the 40th: every frame it had reported reads back intact.
TEST(FrameFileTest, AWriterKilledMidTakeLeavesEveryAppendedFrameReadable) {
  const std::string path = ::testing::TempDir() + "/frames-killed.h5";
  std::filesystem::remove(path);
  int acks[2];
  ASSERT_EQ(pipe(acks), 0);
  const FrameFileInfo info = Info();
  const pid_t child = fork();
  ASSERT_GE(child, 0);
  if (child == 0) {
    close(acks[0]);
    auto writer = FrameFileWriter::Create(path, info);
    if (!writer.ok()) _exit(3);
    for (int64_t i = 0; i < 100000; ++i) {
      if (!(*writer)->Append(Record(i), Pixels(info, i)).ok()) _exit(4);
      const char one = 1;
      if (write(acks[1], &one, 1) != 1) _exit(5);
    }
    _exit(0);
  }
  close(acks[1]);
  int acked = 0;
  char c;
  while (acked < 40 && read(acks[0], &c, 1) == 1) ++acked;
  ASSERT_EQ(kill(child, SIGKILL), 0);
  int status = 0;
  ASSERT_EQ(waitpid(child, &status, 0), child);
  ASSERT_TRUE(WIFSIGNALED(status)) << "the writer ended by itself: " << status;
  while (read(acks[0], &c, 1) == 1) ++acked;  // acks still in the pipe
  close(acks[0]);
  ASSERT_GE(acked, 40);
  // Every acknowledged frame, and at most the one being written.
  ExpectFrames(path, acked, acked + 1);
  auto reader = FrameFileReader::Open(path);
  ASSERT_TRUE(reader.ok());
  const int64_t n = (*reader)->frames();

  // An independent reader (HDF5's own tools) reads the same after the documented repair of a crashed SWMR file.
  const std::string copy = path + ".repaired.h5";
  std::filesystem::copy_file(path, copy, std::filesystem::copy_options::overwrite_existing);
  ASSERT_EQ(std::system(("h5clear -s --increment " + copy + " 2>&1").c_str()), 0);
  auto dump = [&](const std::string& column) {
    std::string out;
    if (FILE* p = popen(("h5dump -d " + column + " -y -w 0 " + copy + " 2>&1").c_str(), "r")) {
      char buffer[4096];
      for (size_t got; (got = fread(buffer, 1, sizeof buffer, p)) > 0;) out.append(buffer, got);
      pclose(p);
    }
    return out;
  };
  // /status is written last of a frame's columns: it holds exactly the frames the reader counts. A column written
  // before it (/slot) may hold one more, the frame the kill interrupted.
  EXPECT_THAT(dump("/status"), HasSubstr("SIMPLE { ( " + std::to_string(n) + " ) / ( H5S_UNLIMITED ) }"));
  const std::string slot_dump = dump("/slot");
  EXPECT_THAT(slot_dump,
              ::testing::AnyOf(HasSubstr("SIMPLE { ( " + std::to_string(n) + " ) / ( H5S_UNLIMITED ) }"),
                               HasSubstr("SIMPLE { ( " + std::to_string(n + 1) + " ) / ( H5S_UNLIMITED ) }")));
  std::string slots;
  for (int64_t i = 0; i < n; ++i) slots += (i ? ", " : "") + std::to_string(i);
  EXPECT_THAT(slot_dump, HasSubstr(slots)) << slot_dump;
}

// A full disk: the child writes into a 512 KiB tmpfs of its own (a private mount namespace; needs root, else the test
// is skipped) until appending fails with RESOURCE_EXHAUSTED, and nothing after; then copies the file out. What it
// appended reads back, every frame.
TEST(FrameFileTest, AFullDiskStopsTheWriterCleanly) {
  const std::string out = ::testing::TempDir() + "/frames-full.h5";
  const std::string mount_point = ::testing::TempDir() + "/frames-full-tmpfs";
  std::filesystem::remove(out);
  std::filesystem::create_directories(mount_point);
  int report[2];
  ASSERT_EQ(pipe(report), 0);
  const FrameFileInfo info = Info();
  const pid_t child = fork();
  ASSERT_GE(child, 0);
  if (child == 0) {
    close(report[0]);
    auto say = [&](const std::string& line) {
      if (write(report[1], line.data(), line.size()) < 0) _exit(5);
    };
    if (unshare(CLONE_NEWNS) != 0 || mount(nullptr, "/", nullptr, MS_REC | MS_PRIVATE, nullptr) != 0 ||
        mount("tmpfs", mount_point.c_str(), "tmpfs", 0, "size=512k") != 0) {
      say(std::string("skip|") + std::strerror(errno));
      _exit(0);
    }
    const std::string path = mount_point + "/frames.h5";
    auto writer = FrameFileWriter::Create(path, info);
    if (!writer.ok()) {
      say("create failed|" + std::string(writer.status().message()));
      _exit(3);
    }
    int64_t i = 0;
    absl::Status s;
    for (; i < 10000; ++i) {
      s = (*writer)->Append(Record(i), Pixels(info, i));
      if (!s.ok()) break;
    }
    const absl::Status after = (*writer)->Append(Record(i + 1), Pixels(info, i + 1));
    const absl::Status closed = (*writer)->Close();
    std::error_code ec;
    std::filesystem::copy_file(path, out, ec);
    say(std::to_string(i) + "|" + std::to_string(static_cast<int>(s.code())) + "|" +
        std::to_string(static_cast<int>(after.code())) + "|" + (ec ? "copy failed " + ec.message() : "") +
        std::string(s.message()));
    _exit(0);
  }
  close(report[1]);
  std::string line;
  char buffer[512];
  for (ssize_t got; (got = read(report[0], buffer, sizeof buffer)) > 0;) line.append(buffer, static_cast<size_t>(got));
  close(report[0]);
  int status = 0;
  ASSERT_EQ(waitpid(child, &status, 0), child);
  ASSERT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0) << status << " " << line;
  if (line.rfind("skip|", 0) == 0) GTEST_SKIP() << "no private tmpfs for the full disk (needs root): " << line;
  const size_t a = line.find('|'), b = line.find('|', a + 1), d = line.find('|', b + 1);
  ASSERT_NE(d, std::string::npos) << line;
  const int64_t appended = std::stoll(line.substr(0, a));
  EXPECT_GT(appended, 20) << line;     // 512 KiB hold well over a hundred 3 KiB frames...
  EXPECT_LT(appended, 10000) << line;  // ...and not all of them
  EXPECT_EQ(std::stoi(line.substr(a + 1, b - a - 1)), static_cast<int>(absl::StatusCode::kResourceExhausted)) << line;
  EXPECT_EQ(std::stoi(line.substr(b + 1, d - b - 1)), static_cast<int>(absl::StatusCode::kFailedPrecondition));
  EXPECT_THAT(line.substr(d + 1), HasSubstr("no space for another frame"));
  ExpectFrames(out, appended, appended);
}

}  // namespace
}  // namespace stage::storage
