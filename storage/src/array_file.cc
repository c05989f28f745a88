// Files of named arrays in HDF5: see array_file.h.
#include "stage/storage/array_file.h"

#include <hdf5.h>

#include <cstdio>
#include <filesystem>
#include <map>
#include <numeric>

#include "absl/strings/str_cat.h"
#include "hdf5_util.h"

namespace stage::storage {
namespace {

hid_t FileType(ArrayType type) {
  switch (type) {
    case ArrayType::kFloat32:
      return H5T_IEEE_F32LE;
    case ArrayType::kInt64:
      return H5T_STD_I64LE;
    case ArrayType::kInt32:
      return H5T_STD_I32LE;
    case ArrayType::kUint8:
      return H5T_STD_U8LE;
  }
  return H5T_STD_U8LE;
}

hid_t MemType(ArrayType type) {
  switch (type) {
    case ArrayType::kFloat32:
      return H5T_NATIVE_FLOAT;
    case ArrayType::kInt64:
      return H5T_NATIVE_INT64;
    case ArrayType::kInt32:
      return H5T_NATIVE_INT32;
    case ArrayType::kUint8:
      return H5T_NATIVE_UINT8;
  }
  return H5T_NATIVE_UINT8;
}

template <typename T>
constexpr ArrayType TypeOf();
template <>
constexpr ArrayType TypeOf<float>() {
  return ArrayType::kFloat32;
}
template <>
constexpr ArrayType TypeOf<int64_t>() {
  return ArrayType::kInt64;
}
template <>
constexpr ArrayType TypeOf<int32_t>() {
  return ArrayType::kInt32;
}
template <>
constexpr ArrayType TypeOf<uint8_t>() {
  return ArrayType::kUint8;
}

}  // namespace

int ArrayTypeSize(ArrayType type) {
  switch (type) {
    case ArrayType::kFloat32:
    case ArrayType::kInt32:
      return 4;
    case ArrayType::kInt64:
      return 8;
    case ArrayType::kUint8:
      return 1;
  }
  return 1;
}

struct ArrayFileWriter::State {
  std::string path, tmp;
  Id file;
  struct Array {
    Id dataset;
    ArrayType type;
    std::vector<hsize_t> row;  // the shape of a row
    hsize_t rows = 0;
  };
  std::map<std::string, Array> arrays;
};

ArrayFileWriter::ArrayFileWriter(std::unique_ptr<State> state) : state_(std::move(state)) {}

ArrayFileWriter::~ArrayFileWriter() {
  if (state_ != nullptr && state_->file.ok()) {
    state_->arrays.clear();
    state_->file.Reset();
    std::remove(state_->tmp.c_str());
  }
}

absl::StatusOr<std::unique_ptr<ArrayFileWriter>> ArrayFileWriter::Create(const std::string& path) {
  QuietHdf5();
  auto state = std::make_unique<State>();
  state->path = path;
  state->tmp = path + ".tmp";
  // No modification times in the objects' headers: the same arrays make the same bytes.
  Id fcpl(H5Pcreate(H5P_FILE_CREATE), H5Pclose);
  H5Pset_obj_track_times(fcpl.get(), false);
  state->file = Id(H5Fcreate(state->tmp.c_str(), H5F_ACC_TRUNC, fcpl.get(), H5P_DEFAULT), H5Fclose);
  if (!state->file.ok()) return Hdf5Error(absl::StatusCode::kUnavailable, state->tmp, "cannot create");
  return std::unique_ptr<ArrayFileWriter>(new ArrayFileWriter(std::move(state)));
}

absl::Status ArrayFileWriter::AddArray(const std::string& name, ArrayType type, const std::vector<int64_t>& row_shape,
                                       int deflate) {
  if (state_->arrays.count(name) > 0) {
    return absl::InvalidArgumentError(absl::StrCat(state_->path, ": array \"", name, "\" added twice"));
  }
  std::vector<hsize_t> dims = {0}, max = {H5S_UNLIMITED}, chunk = {1};
  for (int64_t d : row_shape) {
    if (d < 1) return absl::InvalidArgumentError(absl::StrCat(state_->path, ": array \"", name, "\" has an empty row"));
    dims.push_back(static_cast<hsize_t>(d));
    max.push_back(static_cast<hsize_t>(d));
    chunk.push_back(static_cast<hsize_t>(d));
  }
  const int rank = static_cast<int>(dims.size());
  Id space(H5Screate_simple(rank, dims.data(), max.data()), H5Sclose);
  Id dcpl(H5Pcreate(H5P_DATASET_CREATE), H5Pclose);
  H5Pset_chunk(dcpl.get(), rank, chunk.data());
  H5Pset_obj_track_times(dcpl.get(), false);
  if (deflate > 0) H5Pset_deflate(dcpl.get(), static_cast<unsigned>(std::min(deflate, 9)));
  State::Array array;
  array.dataset = Id(
      H5Dcreate2(state_->file.get(), name.c_str(), FileType(type), space.get(), H5P_DEFAULT, dcpl.get(), H5P_DEFAULT),
      H5Dclose);
  if (!array.dataset.ok()) {
    return Hdf5Error(absl::StatusCode::kInternal, state_->tmp, absl::StrCat("cannot create array \"", name, "\""));
  }
  array.type = type;
  array.row.assign(dims.begin() + 1, dims.end());
  state_->arrays.emplace(name, std::move(array));
  return absl::OkStatus();
}

absl::Status ArrayFileWriter::Append(const std::string& name, const void* row) {
  auto it = state_->arrays.find(name);
  if (it == state_->arrays.end()) {
    return absl::InvalidArgumentError(absl::StrCat(state_->path, ": no array \"", name, "\""));
  }
  State::Array& a = it->second;
  std::vector<hsize_t> dims = {a.rows + 1}, start = {a.rows}, count = {1};
  for (hsize_t d : a.row) {
    dims.push_back(d);
    start.push_back(0);
    count.push_back(d);
  }
  if (H5Dset_extent(a.dataset.get(), dims.data()) < 0) {
    return Hdf5Error(absl::StatusCode::kUnavailable, state_->tmp, absl::StrCat("cannot grow \"", name, "\""));
  }
  Id file_space(H5Dget_space(a.dataset.get()), H5Sclose);
  H5Sselect_hyperslab(file_space.get(), H5S_SELECT_SET, start.data(), nullptr, count.data(), nullptr);
  Id memory(H5Screate_simple(static_cast<int>(count.size()), count.data(), nullptr), H5Sclose);
  if (H5Dwrite(a.dataset.get(), MemType(a.type), memory.get(), file_space.get(), H5P_DEFAULT, row) < 0) {
    return Hdf5Error(absl::StatusCode::kUnavailable, state_->tmp, absl::StrCat("cannot write a row of \"", name, "\""));
  }
  ++a.rows;
  return absl::OkStatus();
}

absl::Status ArrayFileWriter::SetAttribute(const std::string& name, const std::string& value) {
  if (!WriteStringAttribute(state_->file.get(), name.c_str(), value)) {
    return Hdf5Error(absl::StatusCode::kInternal, state_->tmp, absl::StrCat("cannot write attribute \"", name, "\""));
  }
  return absl::OkStatus();
}

absl::Status ArrayFileWriter::Close() {
  state_->arrays.clear();
  if (H5Fflush(state_->file.get(), H5F_SCOPE_GLOBAL) < 0 || state_->file.Reset() < 0) {
    return Hdf5Error(absl::StatusCode::kUnavailable, state_->tmp, "cannot close");
  }
  std::error_code ec;
  std::filesystem::rename(state_->tmp, state_->path, ec);
  if (ec) return absl::UnavailableError(absl::StrCat(state_->path, ": cannot rename into place: ", ec.message()));
  return absl::OkStatus();
}

struct ArrayFileReader::State {
  std::string path;
  Id file;
};

ArrayFileReader::ArrayFileReader(std::unique_ptr<State> state) : state_(std::move(state)) {}
ArrayFileReader::~ArrayFileReader() = default;

absl::StatusOr<std::unique_ptr<ArrayFileReader>> ArrayFileReader::Open(const std::string& path) {
  QuietHdf5();
  if (!std::filesystem::exists(path)) return absl::NotFoundError(absl::StrCat(path, ": no such file"));
  auto state = std::make_unique<State>();
  state->path = path;
  state->file = Id(H5Fopen(path.c_str(), H5F_ACC_RDONLY, H5P_DEFAULT), H5Fclose);
  if (!state->file.ok()) return Hdf5Error(absl::StatusCode::kInvalidArgument, path, "not an HDF5 file");
  return std::unique_ptr<ArrayFileReader>(new ArrayFileReader(std::move(state)));
}

const std::string& ArrayFileReader::path() const { return state_->path; }

bool ArrayFileReader::Has(const std::string& name) const {
  return H5Lexists(state_->file.get(), name.c_str(), H5P_DEFAULT) > 0;
}

absl::StatusOr<std::vector<int64_t>> ArrayFileReader::Shape(const std::string& name) const {
  if (!Has(name)) return absl::NotFoundError(absl::StrCat(state_->path, ": no array \"", name, "\""));
  Id dataset(H5Dopen2(state_->file.get(), name.c_str(), H5P_DEFAULT), H5Dclose);
  Id space(H5Dget_space(dataset.get()), H5Sclose);
  const int rank = H5Sget_simple_extent_ndims(space.get());
  if (rank < 1) return absl::InvalidArgumentError(absl::StrCat(state_->path, ": \"", name, "\" is not an array"));
  std::vector<hsize_t> dims(static_cast<size_t>(rank));
  H5Sget_simple_extent_dims(space.get(), dims.data(), nullptr);
  return std::vector<int64_t>(dims.begin(), dims.end());
}

absl::Status ArrayFileReader::ReadRows(const std::string& name, ArrayType type, int64_t first, int64_t count,
                                       void* out) const {
  auto shape = Shape(name);
  if (!shape.ok()) return shape.status();
  if (first < 0 || count < 0 || first + count > (*shape)[0]) {
    return absl::OutOfRangeError(absl::StrCat(state_->path, ": rows [", first, ", ", first + count, ") of \"", name,
                                              "\", which has ", (*shape)[0]));
  }
  if (count == 0) return absl::OkStatus();
  Id dataset(H5Dopen2(state_->file.get(), name.c_str(), H5P_DEFAULT), H5Dclose);
  Id file_space(H5Dget_space(dataset.get()), H5Sclose);
  std::vector<hsize_t> start(shape->size(), 0), extent(shape->begin(), shape->end());
  start[0] = static_cast<hsize_t>(first);
  extent[0] = static_cast<hsize_t>(count);
  H5Sselect_hyperslab(file_space.get(), H5S_SELECT_SET, start.data(), nullptr, extent.data(), nullptr);
  Id memory(H5Screate_simple(static_cast<int>(extent.size()), extent.data(), nullptr), H5Sclose);
  if (H5Dread(dataset.get(), MemType(type), memory.get(), file_space.get(), H5P_DEFAULT, out) < 0) {
    return Hdf5Error(absl::StatusCode::kInvalidArgument, state_->path, absl::StrCat("cannot read \"", name, "\""));
  }
  return absl::OkStatus();
}

template <typename T>
absl::StatusOr<std::vector<T>> ArrayFileReader::ReadAll(const std::string& name) const {
  auto shape = Shape(name);
  if (!shape.ok()) return shape.status();
  const int64_t n = std::accumulate(shape->begin(), shape->end(), int64_t{1}, std::multiplies<int64_t>());
  std::vector<T> out(static_cast<size_t>(n));
  if (auto s = ReadRows(name, TypeOf<T>(), 0, (*shape)[0], out.data()); !s.ok()) return s;
  return out;
}
template absl::StatusOr<std::vector<float>> ArrayFileReader::ReadAll(const std::string&) const;
template absl::StatusOr<std::vector<int64_t>> ArrayFileReader::ReadAll(const std::string&) const;
template absl::StatusOr<std::vector<int32_t>> ArrayFileReader::ReadAll(const std::string&) const;
template absl::StatusOr<std::vector<uint8_t>> ArrayFileReader::ReadAll(const std::string&) const;

absl::StatusOr<std::string> ArrayFileReader::Attribute(const std::string& name) const {
  std::string value;
  if (!ReadStringAttribute(state_->file.get(), name.c_str(), &value)) {
    return absl::NotFoundError(absl::StrCat(state_->path, ": no text attribute \"", name, "\""));
  }
  return value;
}

}  // namespace stage::storage
