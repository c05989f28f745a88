// Files of named arrays (HDF5, as h5py and h5dump read them): what processing writes for other programs and reads back
// whole, a neural asset's dataset (docs/asset.md). Each array grows a row at a time along its first dimension; text
// attributes on the file's root describe it. Written to PATH.tmp and renamed onto PATH when closed, so a reader never
// sees half a file and a killed writer leaves nothing under PATH. No times are stored: the same arrays give the same
// bytes.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"

namespace stage::storage {

enum class ArrayType { kFloat32, kInt64, kInt32, kUint8 };
int ArrayTypeSize(ArrayType type);

class ArrayFileWriter {
 public:
  // A new file at `path` (replacing one there once closed). Errors name the path.
  static absl::StatusOr<std::unique_ptr<ArrayFileWriter>> Create(const std::string& path);
  ~ArrayFileWriter();  // without Close: the file is abandoned (PATH.tmp removed)

  // An array `name` of rows of `row_shape` (its first dimension grows with each Append; chunked by row, deflated at
  // `deflate` 0-9). InvalidArgument: a name already added.
  absl::Status AddArray(const std::string& name, ArrayType type, const std::vector<int64_t>& row_shape,
                        int deflate = 0);
  // One row of `name`: the product of its row shape in elements of its type.
  absl::Status Append(const std::string& name, const void* row);
  // A text attribute of the file (a JSON document, a format name).
  absl::Status SetAttribute(const std::string& name, const std::string& value);
  // Flushes, closes and renames the file into place.
  absl::Status Close();

 private:
  struct State;
  explicit ArrayFileWriter(std::unique_ptr<State> state);
  std::unique_ptr<State> state_;
};

class ArrayFileReader {
 public:
  static absl::StatusOr<std::unique_ptr<ArrayFileReader>> Open(const std::string& path);
  ~ArrayFileReader();

  bool Has(const std::string& name) const;
  // The array's shape (rows first). NotFound names the file and array.
  absl::StatusOr<std::vector<int64_t>> Shape(const std::string& name) const;
  // Rows [first, first + count) of `name` converted to `type`, into `out` (count x row elements).
  absl::Status ReadRows(const std::string& name, ArrayType type, int64_t first, int64_t count, void* out) const;
  // The whole array into a vector of T (float, int64_t, int32_t or uint8_t).
  template <typename T>
  absl::StatusOr<std::vector<T>> ReadAll(const std::string& name) const;
  absl::StatusOr<std::string> Attribute(const std::string& name) const;
  const std::string& path() const;

 private:
  struct State;
  explicit ArrayFileReader(std::unique_ptr<State> state);
  std::unique_ptr<State> state_;
};

}  // namespace stage::storage
