// HDF5 frame files in SWMR mode: see frame_file.h.
#include "stage/storage/frame_file.h"

#include <fcntl.h>
#include <hdf5.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <bit>
#include <cerrno>
#include <cstring>
#include <filesystem>

#include "absl/strings/str_cat.h"
#include "hdf5_util.h"
#include "stage/common/logging.h"

namespace stage::storage {
namespace {

constexpr const char* kFormat = "fastage-frames-1";
// The per-frame datasets, written in this order; `status` last, so that a frame counts (the status extent) only once
// everything else of it is on disk.
enum Column { kFrameId, kDeviceTs, kControllerTs, kSlot, kPattern, kStatus, kColumns };
constexpr const char* kColumnNames[kColumns] = {
    "frame_id", "device_timestamp_ns", "controller_time_ns", "slot", "pattern", "status"};
hid_t ColumnFileType(int c) {
  switch (c) {
    case kFrameId:
      return H5T_STD_U64LE;
    case kPattern:
    case kStatus:
      return H5T_STD_I32LE;
    default:
      return H5T_STD_I64LE;
  }
}
hid_t ColumnMemType(int c) {
  switch (c) {
    case kFrameId:
      return H5T_NATIVE_UINT64;
    case kPattern:
    case kStatus:
      return H5T_NATIVE_INT32;
    default:
      return H5T_NATIVE_INT64;
  }
}

}  // namespace

struct FrameFileWriter::Handles {
  Id file;
  Id frames;
  std::array<Id, kColumns> columns;
  int fd = -1;  // the file's descriptor (HDF5's sec2 driver), for reserving space
};

struct FrameFileReader::Handles {
  Id file;
  Id frames;
  std::array<Id, kColumns> columns;
};

absl::StatusOr<std::unique_ptr<FrameFileWriter>> FrameFileWriter::Create(const std::string& path,
                                                                         const FrameFileInfo& info) {
  QuietHdf5();
  if (info.width == 0 || info.height == 0) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": frames need a width and a height"));
  }
  if (info.bytes_per_pixel != 1 && info.bytes_per_pixel != 2) {
    return absl::InvalidArgumentError(
        absl::StrCat(path, ": ", info.bytes_per_pixel, " bytes a pixel (frames hold 8 or 16-bit pixels)"));
  }
  std::error_code ec;
  if (std::filesystem::exists(path, ec)) {
    return absl::AlreadyExistsError(absl::StrCat(path, ": exists; a take's frames are never overwritten"));
  }
  std::unique_ptr<FrameFileWriter> w(new FrameFileWriter());
  w->path_ = path;
  w->info_ = info;
  w->h_ = std::make_unique<Handles>();
  Handles& h = *w->h_;
  Id fapl = LatestFormatAccess();
  h.file = Id(H5Fcreate(path.c_str(), H5F_ACC_EXCL, H5P_DEFAULT, fapl.get()), H5Fclose);
  if (!h.file.ok()) return Hdf5Error(absl::StatusCode::kUnavailable, path, "cannot create the frame file");

  const hid_t root = h.file.get();
  bool ok = WriteStringAttribute(root, "format", kFormat) && WriteStringAttribute(root, "camera_id", info.camera_id) &&
            WriteStringAttribute(root, "take_id", info.take_id) &&
            WriteStringAttribute(root, "pixel_format", info.pixel_format) &&
            WriteStringAttribute(root, "calibration", info.calibration_json) &&
            WriteStringAttribute(root, "patterns", info.patterns_json) &&
            WriteScalarAttribute(root, "width", H5T_STD_U32LE, H5T_NATIVE_UINT32, info.width) &&
            WriteScalarAttribute(root, "height", H5T_STD_U32LE, H5T_NATIVE_UINT32, info.height) &&
            WriteScalarAttribute(root, "bytes_per_pixel", H5T_STD_U32LE, H5T_NATIVE_UINT32, info.bytes_per_pixel) &&
            WriteScalarAttribute(root, "exposure_us", H5T_IEEE_F64LE, H5T_NATIVE_DOUBLE, info.exposure_us) &&
            WriteScalarAttribute(root, "gain_db", H5T_IEEE_F64LE, H5T_NATIVE_DOUBLE, info.gain_db);
  if (!ok) return Hdf5Error(absl::StatusCode::kUnavailable, path, "cannot write the file's attributes");

  // /frames: (N, H, W), one frame a chunk.
  {
    const hsize_t dims[3] = {0, info.height, info.width};
    const hsize_t max[3] = {H5S_UNLIMITED, info.height, info.width};
    const hsize_t chunk[3] = {1, info.height, info.width};
    Id space(H5Screate_simple(3, dims, max), H5Sclose);
    Id dcpl(H5Pcreate(H5P_DATASET_CREATE), H5Pclose);
    H5Pset_chunk(dcpl.get(), 3, chunk);
    const hid_t type = info.bytes_per_pixel == 1 ? H5T_STD_U8LE : H5T_STD_U16LE;
    h.frames = Id(H5Dcreate2(root, "frames", type, space.get(), H5P_DEFAULT, dcpl.get(), H5P_DEFAULT), H5Dclose);
    if (!h.frames.ok()) return Hdf5Error(absl::StatusCode::kUnavailable, path, "cannot create /frames");
  }
  for (int c = 0; c < kColumns; ++c) {
    const hsize_t dims[1] = {0}, max[1] = {H5S_UNLIMITED}, chunk[1] = {512};
    Id space(H5Screate_simple(1, dims, max), H5Sclose);
    Id dcpl(H5Pcreate(H5P_DATASET_CREATE), H5Pclose);
    H5Pset_chunk(dcpl.get(), 1, chunk);
    h.columns[c] =
        Id(H5Dcreate2(root, kColumnNames[c], ColumnFileType(c), space.get(), H5P_DEFAULT, dcpl.get(), H5P_DEFAULT),
           H5Dclose);
    if (!h.columns[c].ok()) {
      return Hdf5Error(absl::StatusCode::kUnavailable, path, absl::StrCat("cannot create /", kColumnNames[c]));
    }
  }
  if (H5Fstart_swmr_write(root) < 0) {
    return Hdf5Error(absl::StatusCode::kUnavailable, path, "cannot start single-writer/multiple-reader mode");
  }
  void* handle = nullptr;
  if (H5Fget_vfd_handle(root, fapl.get(), &handle) >= 0 && handle != nullptr) h.fd = *static_cast<int*>(handle);
  return w;
}

absl::Status FrameFileWriter::Reserve(size_t frame_bytes) {
  // The space the next frame may take (its pixels, and the index and metadata HDF5 adds) is taken from the file
  // system before HDF5 writes anything: a full disk then stops the take between frames, with the file consistent.
  // (Were HDF5 to hit the full disk itself, the superblock would promise more file than there is, and no reader
  // would open it.)
  constexpr uint64_t kMetadataMargin = 256 * 1024;
  haddr_t eoa = HADDR_UNDEF;
  if (H5Fget_eoa(h_->file.get(), &eoa) < 0) return absl::OkStatus();
  struct stat st {};
  const uint64_t end = std::max<uint64_t>(eoa, fstat(h_->fd, &st) == 0 ? static_cast<uint64_t>(st.st_size) : 0);
  const uint64_t need = end + frame_bytes + kMetadataMargin;
  if (need <= reserved_end_) return absl::OkStatus();
  // Ahead by 16 frames or 16 MiB when the disk has it, else just what this frame needs.
  const uint64_t ahead = std::max<uint64_t>(16 * frame_bytes, 16ull << 20);
  for (uint64_t want : {need + ahead, need}) {
    if (fallocate(h_->fd, FALLOC_FL_KEEP_SIZE, static_cast<off_t>(end), static_cast<off_t>(want - end)) == 0) {
      reserved_end_ = want;
      return absl::OkStatus();
    }
    if (errno == EOPNOTSUPP || errno == ENOSYS) {
      if (!reserve_unsupported_) {
        Logger("storage")->warn(
            "{}: the file system cannot reserve space; a full disk may leave the frame file "
            "unreadable",
            path_);
        reserve_unsupported_ = true;
      }
      reserved_end_ = UINT64_MAX;
      return absl::OkStatus();
    }
    if (errno != ENOSPC && errno != EDQUOT && errno != EFBIG) break;  // EFBIG: the file size limit (RLIMIT_FSIZE)
  }
  const int error = errno;
  return absl::ResourceExhaustedError(absl::StrCat(path_, ": no space for another frame (", std::strerror(error), "); ",
                                                   frames_, " frame(s) recorded"));
}

FrameFileWriter::~FrameFileWriter() {
  if (h_ == nullptr) return;
  if (absl::Status s = Close(); !s.ok()) Logger("storage")->error("{}", s.message());
}

absl::Status FrameFileWriter::Append(const FrameRecord& record, absl::Span<const uint8_t> pixels) {
  if (h_ == nullptr) return absl::FailedPreconditionError(absl::StrCat(path_, ": closed"));
  if (failed_) return absl::FailedPreconditionError(absl::StrCat(path_, ": an earlier write failed; not recording"));
  const size_t expected = static_cast<size_t>(info_.width) * info_.height * info_.bytes_per_pixel;
  if (pixels.size() != expected) {
    return absl::InvalidArgumentError(absl::StrCat(path_, ": frame ", record.frame_id, " has ", pixels.size(),
                                                   " bytes, the file holds frames of ", expected));
  }
  if (h_->fd >= 0) {
    if (absl::Status s = Reserve(expected); !s.ok()) {
      failed_ = true;
      return s;
    }
  }
  errno = 0;
  const auto n = static_cast<hsize_t>(frames_);
  auto fail = [&](const std::string& what) {
    failed_ = true;
    return Hdf5Error(absl::StatusCode::kDataLoss, path_, absl::StrCat(what, " of frame ", record.frame_id));
  };
  {
    const hsize_t size[3] = {n + 1, info_.height, info_.width};
    if (H5Dset_extent(h_->frames.get(), size) < 0) return fail("cannot extend /frames");
    // A frame is exactly one chunk, stored unfiltered in the file's (little-endian) order: written as it is, with no
    // selection or type conversion in between.
    static_assert(std::endian::native == std::endian::little, "frames are stored little-endian as they come");
    const hsize_t offset[3] = {n, 0, 0};
    if (H5Dwrite_chunk(h_->frames.get(), H5P_DEFAULT, 0, offset, pixels.size(), pixels.data()) < 0) {
      return fail("cannot write the pixels");
    }
    if (H5Dflush(h_->frames.get()) < 0) return fail("cannot flush the pixels");
  }
  const int32_t status = static_cast<int32_t>(record.status);
  const void* values[kColumns] = {
      &record.frame_id, &record.device_timestamp_ns, &record.controller_time_ns, &record.slot, &record.pattern,
      &status};
  for (int c = 0; c < kColumns; ++c) {
    const hid_t d = h_->columns[c].get();
    const hsize_t size[1] = {n + 1};
    if (H5Dset_extent(d, size) < 0) return fail(absl::StrCat("cannot extend /", kColumnNames[c]));
    Id space(H5Dget_space(d), H5Sclose);
    const hsize_t start[1] = {n}, count[1] = {1};
    H5Sselect_hyperslab(space.get(), H5S_SELECT_SET, start, nullptr, count, nullptr);
    Id memory(H5Screate_simple(1, count, nullptr), H5Sclose);
    if (H5Dwrite(d, ColumnMemType(c), memory.get(), space.get(), H5P_DEFAULT, values[c]) < 0) {
      return fail(absl::StrCat("cannot write /", kColumnNames[c]));
    }
    if (H5Dflush(d) < 0) return fail(absl::StrCat("cannot flush /", kColumnNames[c]));
  }
  ++frames_;
  return absl::OkStatus();
}

absl::Status FrameFileWriter::Close() {
  if (h_ == nullptr) return absl::OkStatus();
  std::unique_ptr<Handles> h = std::move(h_);
  bool ok = true;
  for (auto& c : h->columns) ok = c.Reset() >= 0 && ok;
  ok = h->frames.Reset() >= 0 && ok;
  ok = h->file.Reset() >= 0 && ok;
  if (!ok) return Hdf5Error(absl::StatusCode::kDataLoss, path_, "cannot close the frame file");
  if (reserved_end_ > 0 && !reserve_unsupported_) return ReleaseReservedSpace(path_);
  return absl::OkStatus();
}

absl::Status ReleaseReservedSpace(const std::string& path) {
  // Truncating a file to its own size frees the blocks allocated beyond it (fallocate's KEEP_SIZE reserve).
  const int fd = open(path.c_str(), O_WRONLY | O_CLOEXEC);
  if (fd < 0)
    return absl::UnavailableError(
        absl::StrCat(path, ": cannot open to give back its reserved space: ", std::strerror(errno)));
  struct stat st {};
  int rc = fstat(fd, &st);
  if (rc == 0) rc = ftruncate(fd, st.st_size);
  const int error = errno;
  close(fd);
  if (rc != 0) {
    return absl::UnavailableError(absl::StrCat(path, ": cannot give back its reserved space: ", std::strerror(error)));
  }
  return absl::OkStatus();
}

absl::StatusOr<std::unique_ptr<FrameFileReader>> FrameFileReader::Open(const std::string& path) {
  QuietHdf5();
  std::unique_ptr<FrameFileReader> r(new FrameFileReader());
  r->path_ = path;
  r->h_ = std::make_unique<Handles>();
  Handles& h = *r->h_;
  Id fapl = LatestFormatAccess();
  h.file = Id(H5Fopen(path.c_str(), H5F_ACC_RDONLY | H5F_ACC_SWMR_READ, fapl.get()), H5Fclose);
  if (!h.file.ok()) return Hdf5Error(absl::StatusCode::kNotFound, path, "cannot open the frame file");
  const hid_t root = h.file.get();
  std::string format;
  if (!ReadStringAttribute(root, "format", &format) || format != kFormat) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": not a FaStage frame file (format \"", format, "\")"));
  }
  FrameFileInfo& info = r->info_;
  ReadStringAttribute(root, "camera_id", &info.camera_id);
  ReadStringAttribute(root, "take_id", &info.take_id);
  ReadStringAttribute(root, "pixel_format", &info.pixel_format);
  ReadStringAttribute(root, "calibration", &info.calibration_json);
  ReadStringAttribute(root, "patterns", &info.patterns_json);
  ReadScalarAttribute(root, "width", H5T_NATIVE_UINT32, &info.width);
  ReadScalarAttribute(root, "height", H5T_NATIVE_UINT32, &info.height);
  ReadScalarAttribute(root, "bytes_per_pixel", H5T_NATIVE_UINT32, &info.bytes_per_pixel);
  ReadScalarAttribute(root, "exposure_us", H5T_NATIVE_DOUBLE, &info.exposure_us);
  ReadScalarAttribute(root, "gain_db", H5T_NATIVE_DOUBLE, &info.gain_db);
  h.frames = Id(H5Dopen2(root, "frames", H5P_DEFAULT), H5Dclose);
  if (!h.frames.ok()) return Hdf5Error(absl::StatusCode::kDataLoss, path, "has no /frames");
  for (int c = 0; c < kColumns; ++c) {
    h.columns[c] = Id(H5Dopen2(root, kColumnNames[c], H5P_DEFAULT), H5Dclose);
    if (!h.columns[c].ok())
      return Hdf5Error(absl::StatusCode::kDataLoss, path, absl::StrCat("has no /", kColumnNames[c]));
  }
  // A frame counts once its status is written (the writer writes it last); the other datasets are at least as long.
  Id space(H5Dget_space(h.columns[kStatus].get()), H5Sclose);
  hsize_t n = 0;
  H5Sget_simple_extent_dims(space.get(), &n, nullptr);
  r->frames_ = static_cast<int64_t>(n);
  return r;
}

FrameFileReader::~FrameFileReader() = default;

absl::StatusOr<std::vector<FrameRecord>> FrameFileReader::Records() const {
  const auto n = static_cast<size_t>(frames_);
  std::vector<uint64_t> ids(n);
  std::vector<int64_t> device(n), controller(n), slots(n);
  std::vector<int32_t> patterns(n), statuses(n);
  void* out[kColumns] = {ids.data(), device.data(), controller.data(), slots.data(), patterns.data(), statuses.data()};
  for (int c = 0; c < kColumns && n > 0; ++c) {
    const hid_t d = h_->columns[c].get();
    Id space(H5Dget_space(d), H5Sclose);
    const hsize_t start[1] = {0}, count[1] = {n};
    H5Sselect_hyperslab(space.get(), H5S_SELECT_SET, start, nullptr, count, nullptr);
    Id memory(H5Screate_simple(1, count, nullptr), H5Sclose);
    if (H5Dread(d, ColumnMemType(c), memory.get(), space.get(), H5P_DEFAULT, out[c]) < 0) {
      return Hdf5Error(absl::StatusCode::kDataLoss, path_, absl::StrCat("cannot read /", kColumnNames[c]));
    }
  }
  std::vector<FrameRecord> records(n);
  for (size_t i = 0; i < n; ++i) {
    records[i] = {ids[i], device[i], controller[i], slots[i], patterns[i], static_cast<FrameStatus>(statuses[i])};
  }
  return records;
}

absl::StatusOr<std::vector<uint8_t>> FrameFileReader::Pixels(int64_t index) const {
  if (index < 0 || index >= frames_) {
    return absl::OutOfRangeError(absl::StrCat(path_, ": no frame ", index, " (the file holds ", frames_, ")"));
  }
  std::vector<uint8_t> pixels(static_cast<size_t>(info_.width) * info_.height * info_.bytes_per_pixel);
  Id space(H5Dget_space(h_->frames.get()), H5Sclose);
  const hsize_t start[3] = {static_cast<hsize_t>(index), 0, 0}, count[3] = {1, info_.height, info_.width};
  H5Sselect_hyperslab(space.get(), H5S_SELECT_SET, start, nullptr, count, nullptr);
  Id memory(H5Screate_simple(3, count, nullptr), H5Sclose);
  const hid_t type = info_.bytes_per_pixel == 1 ? H5T_STD_U8LE : H5T_STD_U16LE;
  if (H5Dread(h_->frames.get(), type, memory.get(), space.get(), H5P_DEFAULT, pixels.data()) < 0) {
    return Hdf5Error(absl::StatusCode::kDataLoss, path_, absl::StrCat("cannot read frame ", index));
  }
  return pixels;
}

}  // namespace stage::storage
