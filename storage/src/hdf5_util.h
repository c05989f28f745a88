// HDF5 helpers shared by the storage's files (frame files, array files): ids closed by RAII, HDF5's error stack read
// into statuses, string and scalar attributes that h5py reads as str and numbers. Internal to storage/.
#pragma once

#include <hdf5.h>

#include <cerrno>
#include <cstring>
#include <string>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"

namespace stage::storage {

// HDF5 reports errors on a stack; its default printer writes them to stderr. Silence it once and read the stack
// into our messages instead.
inline void QuietHdf5() {
  static const bool once = [] {
    H5Eset_auto2(H5E_DEFAULT, nullptr, nullptr);
    return true;
  }();
  (void)once;
}

inline herr_t CollectError(unsigned n, const H5E_error2_t* e, void* data) {
  auto* out = static_cast<std::string*>(data);
  if (n < 3 && e->desc != nullptr && *e->desc != '\0') absl::StrAppend(out, out->empty() ? "" : "; ", e->desc);
  return 0;
}

inline absl::Status Hdf5Error(absl::StatusCode code, const std::string& path, const std::string& what) {
  std::string reasons;
  H5Ewalk2(H5E_DEFAULT, H5E_WALK_DOWNWARD, CollectError, &reasons);
  H5Eclear2(H5E_DEFAULT);
  if (errno == ENOSPC || errno == EFBIG || errno == EDQUOT) {
    code = absl::StatusCode::kResourceExhausted;
    absl::StrAppend(&reasons, reasons.empty() ? "" : "; ", std::strerror(errno));
  }
  return absl::Status(code,
                      absl::StrCat(path, ": ", what, reasons.empty() ? "" : " (", reasons, reasons.empty() ? "" : ")"));
}

// RAII for HDF5 ids.
class Id {
 public:
  Id() = default;
  Id(hid_t id, herr_t (*close)(hid_t)) : id_(id), close_(close) {}
  Id(const Id&) = delete;
  Id& operator=(const Id&) = delete;
  Id(Id&& o) noexcept : id_(o.id_), close_(o.close_) { o.id_ = H5I_INVALID_HID; }
  Id& operator=(Id&& o) noexcept {
    Reset();
    id_ = o.id_;
    close_ = o.close_;
    o.id_ = H5I_INVALID_HID;
    return *this;
  }
  ~Id() { Reset(); }
  hid_t get() const { return id_; }
  bool ok() const { return id_ >= 0; }
  herr_t Reset() {
    herr_t r = 0;
    if (id_ >= 0 && close_ != nullptr) r = close_(id_);
    id_ = H5I_INVALID_HID;
    return r;
  }

 private:
  hid_t id_ = H5I_INVALID_HID;
  herr_t (*close_)(hid_t) = nullptr;
};

inline Id LatestFormatAccess() {
  Id fapl(H5Pcreate(H5P_FILE_ACCESS), H5Pclose);
  H5Pset_libver_bounds(fapl.get(), H5F_LIBVER_LATEST, H5F_LIBVER_LATEST);  // SWMR needs the latest format
  return fapl;
}

// A variable-length UTF-8 string: h5py reads it as str (a fixed-length one comes back as bytes).
inline bool WriteStringAttribute(hid_t where, const char* name, const std::string& value) {
  Id type(H5Tcopy(H5T_C_S1), H5Tclose);
  H5Tset_size(type.get(), H5T_VARIABLE);
  H5Tset_cset(type.get(), H5T_CSET_UTF8);
  Id space(H5Screate(H5S_SCALAR), H5Sclose);
  Id attr(H5Acreate2(where, name, type.get(), space.get(), H5P_DEFAULT, H5P_DEFAULT), H5Aclose);
  const char* text = value.c_str();
  return attr.ok() && H5Awrite(attr.get(), type.get(), &text) >= 0;
}

template <typename T>
bool WriteScalarAttribute(hid_t where, const char* name, hid_t file_type, hid_t mem_type, T value) {
  Id space(H5Screate(H5S_SCALAR), H5Sclose);
  Id attr(H5Acreate2(where, name, file_type, space.get(), H5P_DEFAULT, H5P_DEFAULT), H5Aclose);
  return attr.ok() && H5Awrite(attr.get(), mem_type, &value) >= 0;
}

// A string attribute, variable-length (written since 2026-11-27) or fixed-length (files written before).
inline bool ReadStringAttribute(hid_t where, const char* name, std::string* out) {
  if (H5Aexists(where, name) <= 0) return false;
  Id attr(H5Aopen(where, name, H5P_DEFAULT), H5Aclose);
  Id type(H5Aget_type(attr.get()), H5Tclose);
  if (H5Tget_class(type.get()) != H5T_STRING) return false;
  if (H5Tis_variable_str(type.get()) > 0) {
    Id memory(H5Tcopy(H5T_C_S1), H5Tclose);
    H5Tset_size(memory.get(), H5T_VARIABLE);
    H5Tset_cset(memory.get(), H5Tget_cset(type.get()));
    char* text = nullptr;
    if (H5Aread(attr.get(), memory.get(), &text) < 0) return false;
    *out = text != nullptr ? text : "";
    Id space(H5Aget_space(attr.get()), H5Sclose);
    H5Dvlen_reclaim(memory.get(), space.get(), H5P_DEFAULT, &text);
    return true;
  }
  std::string buffer(H5Tget_size(type.get()), '\0');
  if (H5Aread(attr.get(), type.get(), buffer.data()) < 0) return false;
  buffer.resize(strnlen(buffer.data(), buffer.size()));
  *out = std::move(buffer);
  return true;
}

template <typename T>
bool ReadScalarAttribute(hid_t where, const char* name, hid_t mem_type, T* out) {
  if (H5Aexists(where, name) <= 0) return false;
  Id attr(H5Aopen(where, name, H5P_DEFAULT), H5Aclose);
  return H5Aread(attr.get(), mem_type, out) >= 0;
}

}  // namespace stage::storage
