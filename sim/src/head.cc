// The procedural head, its expressions, performances and skin.
#include "stage/sim/head.h"

#include <fcntl.h>
#include <sys/file.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <unistd.h>
#include <yaml-cpp/yaml.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <functional>
#include <map>
#include <numeric>
#include <optional>
#include <random>
#include <set>
#include <tuple>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"
#include "image_decoder.h"
#include "stage/common/logging.h"
#include "stage/common/module.h"
#include "stage/common/rig.h"
#include "stage/common/status.h"

namespace stage::sim {
namespace {

constexpr float kPi = 3.14159265358979323846f;
constexpr const char* kNames[kExpressionCount] = {"jaw_open",    "smile_left", "smile_right", "blink_left",
                                                  "blink_right", "brow_raise", "frown",       "pucker"};
enum { kJaw, kSmileL, kSmileR, kBlinkL, kBlinkR, kBrow, kFrown, kPucker };

// Eye placement (head frame, angles): azimuth from +z towards +x, elevation.
constexpr float kEyeTheta = 0.36f, kEyePhi = 0.10f, kEyeRadius = 12;
// The mouth line's elevation.
constexpr float kMouthPhi = -0.485f;
// The jaw's hinge (it turns about the x axis through it), mm.
const Eigen::Vector3f kJawHinge(0, -20, -30);
// The neck pivot the head turns about, mm.
const Eigen::Vector3f kPivot(0, -95, -15);

float AngleDiff(float a, float b) { return std::remainder(a - b, 2 * kPi); }
float G(float d, float s) { return std::exp(-0.5f * (d / s) * (d / s)); }
// A bump centred at (th0, ph0) with angular widths (sth, sph).
float Blob(float th, float ph, float th0, float ph0, float sth, float sph) {
  return G(AngleDiff(th, th0), sth) * G(ph - ph0, sph);
}
float Both(float th, float ph, float th0, float ph0, float sth, float sph) {
  return Blob(th, ph, th0, ph0, sth, sph) + Blob(th, ph, -th0, ph0, sth, sph);
}
float Smooth(float e0, float e1, float x) {
  const float t = std::clamp((x - e0) / (e1 - e0), 0.0f, 1.0f);
  return t * t * (3 - 2 * t);
}
Eigen::Vector3f Dir(float th, float ph) {
  return {std::sin(th) * std::cos(ph), std::sin(ph), std::cos(th) * std::cos(ph)};
}
Eigen::Vector3f ETheta(float th) { return {std::cos(th), 0, -std::sin(th)}; }
Eigen::Vector3f EPhi(float th, float ph) {
  return {-std::sin(th) * std::sin(ph), std::cos(ph), -std::cos(th) * std::sin(ph)};
}

// Distance from the head centre to the skin in direction (th, ph), neutral, mm, for the head of proportions `s`.
float Radius(float th, float ph, const HeadShape& s) {
  const Eigen::Vector3f d = Dir(th, ph);
  const float ax = s.width_mm, ay = s.height_mm, az = s.depth_mm;
  float r = 1 / std::sqrt((d.x() / ax) * (d.x() / ax) + (d.y() / ay) * (d.y() / ay) + (d.z() / az) * (d.z() / az));
  // The jaw narrows below the cheekbones.
  r *= 1 - s.jaw * Smooth(-0.15f, -0.8f, ph) * std::sin(th) * std::sin(th);
  r += s.nose_mm * Blob(th, ph, 0, -0.08f, 0.10f, 0.20f) + s.nose_tip_mm * Blob(th, ph, 0, -0.22f, 0.07f, 0.06f);
  r += s.nostrils_mm * Both(th, ph, 0.11f, -0.24f, 0.05f, 0.05f);
  r -= s.eye_sockets_mm * Both(th, ph, kEyeTheta, kEyePhi, 0.15f, 0.09f);
  r += s.brows_mm * Both(th, ph, kEyeTheta, 0.23f, 0.20f, 0.05f);
  r += s.cheekbones_mm * Both(th, ph, 0.62f, -0.08f, 0.18f, 0.15f);
  r += s.lips_mm * (Blob(th, ph, 0, -0.43f, 0.22f, 0.05f) + Blob(th, ph, 0, -0.54f, 0.20f, 0.05f));
  r -= 4 * Blob(th, ph, 0, kMouthPhi, 0.18f, 0.012f);  // mouth line
  r += s.chin_mm * Blob(th, ph, 0, -0.78f, 0.22f, 0.12f);
  r += s.ears_mm * Both(th, ph, kPi / 2 + 0.05f, 0.02f, 0.10f, 0.20f);
  r += 6 * Blob(th, ph, kPi, 0.2f, 0.6f, 0.5f);  // back of the skull
  return r;
}

// Displacement of the skin point in direction (th, ph) at weight 1 of expression `e`, mm.
Eigen::Vector3f Delta(int e, float th, float ph, const Eigen::Vector3f& p) {
  const Eigen::Vector3f d = Dir(th, ph), et = ETheta(th), ep = EPhi(th, ph);
  const float side = th >= 0 ? 1.0f : -1.0f;  // +: the performer's left
  switch (e) {
    case kJaw: {
      // The lower face turns down about the jaw hinge; the mouth line sinks into a dark opening.
      const float s = Smooth(-0.45f, -0.53f, ph) * G(AngleDiff(th, 0), 1.1f);
      const Eigen::Vector3f& hinge = kJawHinge;
      const Eigen::AngleAxisf turn(14 * kPi / 180, Eigen::Vector3f::UnitX());
      return s * (turn * (p - hinge) + hinge - p) - 14 * Blob(th, ph, 0, kMouthPhi, 0.16f, 0.02f) * d;
    }
    case kSmileL:
    case kSmileR: {
      const float sgn = e == kSmileL ? 1.0f : -1.0f;
      const float corner = Blob(th, ph, sgn * 0.2f, -0.48f, 0.12f, 0.10f);
      const float cheek = Blob(th, ph, sgn * 0.45f, -0.2f, 0.15f, 0.12f);
      return corner * (5 * ep + 3 * d + 3 * sgn * et) + 3 * cheek * d;
    }
    case kBlinkL:
    case kBlinkR: {
      const float sgn = e == kBlinkL ? 1.0f : -1.0f;
      return 5.5f * Blob(th, ph, sgn * kEyeTheta, kEyePhi, 0.13f, 0.085f) * d;
    }
    case kBrow:
      return 6 * Both(th, ph, kEyeTheta, 0.25f, 0.25f, 0.10f) * ep + 2 * Blob(th, ph, 0, 0.45f, 0.5f, 0.12f) * ep;
    case kFrown: {
      const float b = Both(th, ph, 0.25f, 0.22f, 0.15f, 0.08f);
      return b * (-4 * ep - 4 * side * et + 1.5f * d);
    }
    case kPucker: {
      const float b = Blob(th, ph, 0, kMouthPhi, 0.2f, 0.09f);
      return b * (9 * d - 5 * side * std::min(1.0f, std::abs(th) / 0.1f) * et);
    }
    default:
      return Eigen::Vector3f::Zero();
  }
}

uint64_t Mix(uint64_t x) {
  x += 0x9e3779b97f4a7c15ull;
  x = (x ^ (x >> 30)) * 0xbf58476d1ce4e5b9ull;
  x = (x ^ (x >> 27)) * 0x94d049bb133111ebull;
  return x ^ (x >> 31);
}
float Rand(uint64_t seed, int64_t ix, int64_t iy, int k) {
  const uint64_t h = Mix(seed ^ Mix(static_cast<uint64_t>(ix) * 73856093ull ^ static_cast<uint64_t>(iy) * 19349663ull ^
                                    static_cast<uint64_t>(k) * 83492791ull));
  return static_cast<float>(h >> 40) / static_cast<float>(1ull << 24);
}

// Smooth value noise in [0, 1] at (x, y) in cells.
float ValueNoise(uint64_t seed, float x, float y) {
  const float fx = std::floor(x), fy = std::floor(y);
  const auto ix = static_cast<int64_t>(fx), iy = static_cast<int64_t>(fy);
  const float tx = Smooth(0, 1, x - fx), ty = Smooth(0, 1, y - fy);
  const float a = Rand(seed, ix, iy, 0), b = Rand(seed, ix + 1, iy, 0), c = Rand(seed, ix, iy + 1, 0),
              d = Rand(seed, ix + 1, iy + 1, 0);
  return (a * (1 - tx) + b * tx) * (1 - ty) + (c * (1 - tx) + d * tx) * ty;
}

// Texels across the skin maps at their nominal ("4K") resolution.
constexpr float kTexels = 4096;
// Pores: one candidate per 12x12-texel cell; diameters 2 to 10 texels.
constexpr float kPoreCell = 12;

// Spots scattered one per cell of `cell` texels: a cell holds one with probability `p` (draw `salt`), at a random place
// (draws salt + 1, salt + 2) with a radius of `r0 + r1 x draw(salt + 3)` texels. Returns the largest
// `shape(q, i, j)` over the spots near uv, q being the squared distance over the squared radius.
template <typename Shape>
float Spots(uint64_t seed, const Eigen::Vector2f& uv, float cell, float p, int salt, float r0, float r1, Shape shape) {
  const float x = uv.x() * kTexels / cell, y = uv.y() * kTexels / cell;
  const auto cx = static_cast<int64_t>(std::floor(x)), cy = static_cast<int64_t>(std::floor(y));
  float out = 0;
  for (int64_t j = cy - 1; j <= cy + 1; ++j) {
    for (int64_t i = cx - 1; i <= cx + 1; ++i) {
      if (Rand(seed, i, j, salt) > p) continue;
      const float px = static_cast<float>(i) + Rand(seed, i, j, salt + 1);
      const float py = static_cast<float>(j) + Rand(seed, i, j, salt + 2);
      const float radius = (r0 + r1 * Rand(seed, i, j, salt + 3)) / cell;  // in cells
      const float q = ((x - px) * (x - px) + (y - py) * (y - py)) / (radius * radius);
      out = std::max(out, shape(q, i, j));
    }
  }
  return out;
}

// The pore field at uv: depth in [0, 1] (1 at a pore's centre); radii 1..5 texels.
float Pores(uint64_t seed, const Eigen::Vector2f& uv) {
  return Spots(seed, uv, kPoreCell, 0.8f, 1, 1, 4,
               [](float q, int64_t, int64_t) { return q < 1 ? (1 - q) * (1 - q) : 0.0f; });
}

// Freckles: soft spots of 20 to 60 texels, in [0, 1].
float Freckles(uint64_t seed, const Eigen::Vector2f& uv) {
  return Spots(seed, uv, 64, 0.35f, 5, 10, 20, [seed](float q, int64_t i, int64_t j) {
    return std::exp(-3 * q) * (0.5f + 0.5f * Rand(seed, i, j, 9));
  });
}

// An image read for the skin maps: float texels, row 0 at the image's top (v = 1). The texels are the image's own or a
// view of a shared cache file (HeadMapsCache); `owner` keeps them alive.
struct Image {
  int width = 0, height = 0, channels = 0;
  const float* texels = nullptr;
  std::shared_ptr<const void> owner;
  bool empty() const { return texels == nullptr; }
  size_t size() const {
    return static_cast<size_t>(width) * static_cast<size_t>(height) * static_cast<size_t>(channels);
  }
  static Image Own(int width, int height, int channels, std::vector<float> texels) {
    auto data = std::make_shared<std::vector<float>>(std::move(texels));
    Image image;
    image.width = width;
    image.height = height;
    image.channels = channels;
    image.texels = data->data();
    image.owner = std::move(data);
    return image;
  }
  // Bilinear at texture coordinate uv (clamped to the edge), into out[0..channels).
  void Sample(const Eigen::Vector2f& uv, float* out) const {
    const float x = std::clamp(uv.x() * static_cast<float>(width) - 0.5f, 0.0f, static_cast<float>(width - 1));
    const float y = std::clamp((1 - uv.y()) * static_cast<float>(height) - 0.5f, 0.0f, static_cast<float>(height - 1));
    const int x0 = static_cast<int>(x), y0 = static_cast<int>(y);
    const int x1 = std::min(x0 + 1, width - 1), y1 = std::min(y0 + 1, height - 1);
    const float fx = x - static_cast<float>(x0), fy = y - static_cast<float>(y0);
    auto at = [&](int xx, int yy, int c) {
      return texels[(static_cast<size_t>(yy) * static_cast<size_t>(width) + static_cast<size_t>(xx)) * channels + c];
    };
    for (int c = 0; c < channels; ++c) {
      out[c] = (at(x0, y0, c) * (1 - fx) + at(x1, y0, c) * fx) * (1 - fy) +
               (at(x0, y1, c) * (1 - fx) + at(x1, y1, c) * fx) * fy;
    }
  }
};

enum class Encoding { kSrgb, kLinear, kSigned };

// Reads `path` (what rig field `field` names) as `channels` (1: grey, 3: RGB) floats. Integer images map to [0, 1],
// then through the sRGB curve (kSrgb) or to [-1, 1] (kSigned); OpenEXR values are taken as they are.
absl::StatusOr<Image> ReadImage(const std::string& path, const std::string& field, int channels, Encoding encoding) {
  // The decoder's module (image_decoder.h), opened the first time a process decodes an image.
  static const absl::StatusOr<internal::DecodeImageFn> decode =
      OpenModuleAs<internal::DecodeImageFn>({.target = internal::kSimImagesTarget,
                                             .entry = internal::kSimImagesEntry,
                                             .what = "the simulator's image decoder module"});
  if (!decode.ok()) return decode.status();
  internal::DecodedImage decoded;
  if (absl::Status s = (*decode)(path, channels, &decoded); !s.ok()) {
    return absl::InvalidArgumentError(absl::StrCat(field, ": \"", path, "\": ", s.message()));
  }
  std::vector<float>& texels = decoded.texels;
  if (decoded.integer && encoding == Encoding::kSrgb) {
    for (float& v : texels) v = v <= 0.04045f ? v / 12.92f : std::pow((v + 0.055f) / 1.055f, 2.4f);
  }
  if (decoded.integer && encoding == Encoding::kSigned) {
    for (float& v : texels) v = 2 * v - 1;
  }
  return Image::Own(decoded.width, decoded.height, channels, std::move(texels));
}

// ---- the decoded maps, shared by the processes of a stage ---------------------------------------------------------
//
// Every camera process of a simulated stage samples the same head images. Decoded to floats they are large (a 4K
// albedo alone is 200 MB), and 27 copies would not fit a small machine. The first process to load an asset writes the
// decoded images to a cache file; every process (the first too) maps that file read-only, so the page cache holds one
// copy for all. The file is named by a hash of the images' paths, sizes, modification times and how they are read, so
// a changed image makes a new file. Concurrent loaders take turns on a lock file: one decodes, the others wait and map.
//
// Layout: "FSTGHM01", uint32 count (4: albedo, specular, roughness, normal), then per image int32 width, height,
// channels, pad, uint64 offset (0: no image); the texels (float32, native order) at 64-byte aligned offsets.

constexpr char kCacheMagic[8] = {'F', 'S', 'T', 'G', 'H', 'M', '0', '1'};
constexpr int kCachedMaps = 4;

struct CacheEntry {
  int32_t width, height, channels, pad;
  uint64_t offset;
};

// The cache file of `images` (path, encoding, channels), or an error naming why there is none.
absl::StatusOr<std::string> CachePath(const std::vector<std::tuple<std::string, Encoding, int>>& images) {
  std::string key = "head-maps-1";
  for (const auto& [path, encoding, channels] : images) {
    struct stat st {};
    if (!path.empty() && stat(path.c_str(), &st) != 0) return absl::NotFoundError(path);
    absl::StrAppend(&key, "|", path.empty() ? "" : std::filesystem::absolute(path).string(), "|",
                    path.empty() ? 0 : st.st_size, "|", path.empty() ? 0 : st.st_mtim.tv_sec, ".",
                    path.empty() ? 0 : st.st_mtim.tv_nsec, "|", static_cast<int>(encoding), "|", channels);
  }
  const std::string dir = DefaultCacheDir();
  std::error_code ec;
  std::filesystem::create_directories(dir, ec);
  if (ec) return absl::UnavailableError(absl::StrCat("cannot create the cache directory ", dir, ": ", ec.message()));
  return absl::StrFormat("%s/head-maps-%016x.bin", dir, Fnv1a64(key));
}

// Maps cache file `path` (read-only, shared) as `count` images; an error if it is not a whole cache file.
absl::StatusOr<std::vector<Image>> MapCache(const std::string& path) {
  const int fd = open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) return absl::NotFoundError(path);
  struct stat st {};
  const bool sized = fstat(fd, &st) == 0;
  const auto bytes = sized ? static_cast<size_t>(st.st_size) : 0;
  void* base = bytes > 0 ? mmap(nullptr, bytes, PROT_READ, MAP_SHARED, fd, 0) : MAP_FAILED;
  close(fd);
  if (base == MAP_FAILED) return absl::UnavailableError(absl::StrCat(path, ": cannot map it"));
  std::shared_ptr<const void> mapping(base, [bytes](const void* p) { munmap(const_cast<void*>(p), bytes); });
  const auto* at = static_cast<const char*>(base);
  const size_t header = sizeof(kCacheMagic) + sizeof(uint32_t) + kCachedMaps * sizeof(CacheEntry);
  uint32_t count = 0;
  if (bytes < header || std::memcmp(at, kCacheMagic, sizeof(kCacheMagic)) != 0) {
    return absl::DataLossError(absl::StrCat(path, ": not a head maps cache"));
  }
  std::memcpy(&count, at + sizeof(kCacheMagic), sizeof(count));
  if (count != kCachedMaps) return absl::DataLossError(absl::StrCat(path, ": not a head maps cache"));
  std::vector<Image> images(kCachedMaps);
  for (int i = 0; i < kCachedMaps; ++i) {
    CacheEntry e;
    std::memcpy(&e, at + sizeof(kCacheMagic) + sizeof(uint32_t) + i * sizeof(CacheEntry), sizeof(e));
    if (e.offset == 0) continue;
    const size_t floats =
        static_cast<size_t>(e.width) * static_cast<size_t>(e.height) * static_cast<size_t>(e.channels);
    if (e.width <= 0 || e.height <= 0 || e.channels <= 0 || e.offset % 64 != 0 || e.offset > bytes ||
        floats > (bytes - e.offset) / 4) {
      return absl::DataLossError(absl::StrCat(path, ": image ", i, " runs past the end of the file"));
    }
    images[i].width = e.width;
    images[i].height = e.height;
    images[i].channels = e.channels;
    images[i].texels = reinterpret_cast<const float*>(at + e.offset);
    images[i].owner = mapping;
  }
  return images;
}

// Writes `images` as a cache file at `path`: beside it first, then renamed, so a reader sees a whole file or none.
absl::Status WriteCache(const std::string& path, const std::vector<Image>& images) {
  const std::string tmp = absl::StrCat(path, ".", getpid(), ".tmp");
  std::ofstream out(tmp, std::ios::binary | std::ios::trunc);
  std::vector<CacheEntry> entries(kCachedMaps);
  uint64_t offset = 64 * ((sizeof(kCacheMagic) + sizeof(uint32_t) + kCachedMaps * sizeof(CacheEntry) + 63) / 64);
  for (int i = 0; i < kCachedMaps; ++i) {
    const Image& image = images[i];
    entries[i] = {image.width, image.height, image.channels, 0, image.empty() ? 0 : offset};
    if (!image.empty()) offset += 64 * ((image.size() * 4 + 63) / 64);
  }
  const uint32_t count = kCachedMaps;
  out.write(kCacheMagic, sizeof(kCacheMagic));
  out.write(reinterpret_cast<const char*>(&count), sizeof(count));
  out.write(reinterpret_cast<const char*>(entries.data()),
            static_cast<std::streamsize>(entries.size() * sizeof(CacheEntry)));
  for (int i = 0; i < kCachedMaps; ++i) {
    if (images[i].empty()) continue;
    const auto at = static_cast<std::streamoff>(entries[i].offset);
    out.seekp(at);
    out.write(reinterpret_cast<const char*>(images[i].texels), static_cast<std::streamsize>(images[i].size() * 4));
  }
  out.close();
  if (!out) {
    std::filesystem::remove(tmp);
    return absl::UnavailableError(absl::StrCat(path, ": cannot write the head maps cache"));
  }
  std::error_code ec;
  std::filesystem::rename(tmp, path, ec);
  if (ec) return absl::UnavailableError(absl::StrCat(path, ": ", ec.message()));
  return absl::OkStatus();
}

// The four maps of `files` (albedo, specular, roughness, normal; an empty path: no image), from the shared cache when
// another process has decoded them, else decoded here and put there. Where no cache can be used (no writable cache
// directory), decoded here, with a warning. `origin` says which: the cache file, or "decoded".
absl::StatusOr<std::vector<Image>> LoadMaps(const HeadAssetFiles& files, std::string* origin) {
  const std::vector<std::tuple<std::string, Encoding, int>> images = {{files.albedo, Encoding::kSrgb, 3},
                                                                      {files.specular, Encoding::kLinear, 1},
                                                                      {files.roughness, Encoding::kLinear, 1},
                                                                      {files.normal, Encoding::kSigned, 3}};
  constexpr const char* kFields[kCachedMaps] = {"sim.subject.asset.albedo", "sim.subject.asset.specular",
                                                "sim.subject.asset.roughness", "sim.subject.asset.normal"};
  auto decode = [&]() -> absl::StatusOr<std::vector<Image>> {
    std::vector<Image> out(kCachedMaps);
    for (int i = 0; i < kCachedMaps; ++i) {
      const auto& [path, encoding, channels] = images[i];
      if (path.empty()) continue;
      STAGE_ASSIGN_OR_RETURN(out[i], ReadImage(path, kFields[i], channels, encoding));
    }
    return out;
  };
  auto path = CachePath(images);
  if (!path.ok()) {
    if (absl::IsNotFound(path.status())) return decode();  // ReadImage names the missing file and its field
    Logger("sim")->warn("head maps decoded in this process only: {}", path.status().message());
    *origin = "decoded";
    return decode();
  }
  if (auto mapped = MapCache(*path); mapped.ok()) {
    *origin = *path;
    return mapped;
  }
  // One process decodes; the others wait for it and map what it wrote. The lock goes with its descriptor, on every
  // way out.
  struct Lock {
    int fd;
    ~Lock() {
      if (fd >= 0) close(fd);
    }
  } lock{open((*path + ".lock").c_str(), O_RDWR | O_CREAT | O_CLOEXEC, 0644)};
  if (lock.fd >= 0) flock(lock.fd, LOCK_EX);
  absl::StatusOr<std::vector<Image>> result = MapCache(*path);
  if (!result.ok()) {
    STAGE_ASSIGN_OR_RETURN(std::vector<Image> decoded, decode());
    if (absl::Status s = WriteCache(*path, decoded); !s.ok()) {
      Logger("sim")->warn("head maps decoded in this process only: {}", s.message());
      result = std::move(decoded);
      *origin = "decoded";
    } else {
      result = MapCache(*path);  // this process shares the pages too
      *origin = *path;
    }
  } else {
    *origin = *path;
  }
  return result;
}

// ---- what the simulator can render of a user's mesh ---------------------------------------------------------------

// Texture coordinates must lie in the one tile [0, 1]^2 the maps cover: a scan laid out in UV tiles (one a material,
// UDIM 1001, 1002, ...) would otherwise be clamped to the tile's edge without a word.
absl::Status CheckUvTile(const std::string& obj, const TriangleMesh& m) {
  constexpr float kSlack = 1e-4f;
  Eigen::Vector2f lo = Eigen::Vector2f::Constant(INFINITY), hi = Eigen::Vector2f::Constant(-INFINITY);
  std::set<int> tiles;
  for (const auto& t : m.triangles) {
    Eigen::Vector2f centre = Eigen::Vector2f::Zero();
    for (int k = 0; k < 3; ++k) {
      lo = lo.cwiseMin(m.uvs[t[k]]);
      hi = hi.cwiseMax(m.uvs[t[k]]);
      centre += m.uvs[t[k]] / 3;
    }
    tiles.insert(1001 + static_cast<int>(std::floor(centre.x())) + 10 * static_cast<int>(std::floor(centre.y())));
  }
  if (lo.minCoeff() >= -kSlack && hi.maxCoeff() <= 1 + kSlack) return absl::OkStatus();
  std::vector<std::string> names;
  for (int tile : tiles) names.push_back(absl::StrCat(tile));
  if (names.size() > 8) names.resize(8), names.push_back("...");
  return absl::InvalidArgumentError(absl::StrFormat(
      "%s: texture coordinates reach outside [0, 1] (u %.3g..%.3g, v %.3g..%.3g): the mesh is laid out in UV tiles "
      "(UDIM %s), and the simulator reads one image per map covering [0, 1]. Pack the UVs into that one tile and bake "
      "each map into one image (Blender: UV > Pack Islands, then bake the tiles' textures onto it), or leave out of "
      "the OBJ the materials that are not skin",
      obj, lo.x(), hi.x(), lo.y(), hi.y(), absl::StrJoin(names, ", ")));
}

// The materials of `m`'s libraries (relative to the OBJ) that are transparent, with why: a dissolve `d` below 1;
// without a `d`, a `Tr` strictly between 0 and 1 (exporters disagree on Tr's sense: some write Tr 1 for opaque, so 0
// and 1 are taken as opaque); or an alpha map `map_d` other than the diffuse texture (an exporter may point it at the
// opaque diffuse image).
std::map<std::string, std::string> TransparentMaterials(const std::string& obj, const TriangleMesh& m,
                                                        std::vector<std::string>* notes) {
  struct Material {
    std::optional<float> d, tr;
    std::string map_d, map_kd;
  };
  std::map<std::string, std::string> out;
  for (const std::string& library : m.material_libraries) {
    const std::filesystem::path path = std::filesystem::path(obj).parent_path() / library;
    std::ifstream in(path);
    if (!in) {
      notes->push_back(absl::StrCat(obj, ": its material library ", path.string(),
                                    " cannot be read: every material is taken as opaque"));
      continue;
    }
    std::map<std::string, Material> materials;
    std::string line, current;
    while (std::getline(in, line)) {
      std::vector<std::string> f = absl::StrSplit(line, absl::ByAnyChar(" \t\r"), absl::SkipEmpty());
      if (f.size() < 2) continue;
      float value = 1;
      if (f[0] == "newmtl") {
        current = f[1];
        materials[current];
      } else if (f[0] == "d" && absl::SimpleAtof(f[1], &value)) {
        materials[current].d = value;
      } else if (f[0] == "Tr" && absl::SimpleAtof(f[1], &value)) {
        materials[current].tr = value;
      } else if (f[0] == "map_d") {
        materials[current].map_d = f.back();
      } else if (f[0] == "map_Kd") {
        materials[current].map_kd = f.back();
      }
    }
    for (const auto& [name, mat] : materials) {
      std::vector<std::string> why;
      if (mat.d && *mat.d < 0.999f) why.push_back(absl::StrFormat("d %g", *mat.d));
      if (!mat.d && mat.tr && *mat.tr > 0.001f && *mat.tr < 0.999f) why.push_back(absl::StrFormat("Tr %g", *mat.tr));
      if (!mat.map_d.empty() && mat.map_d != mat.map_kd) why.push_back(absl::StrCat("map_d ", mat.map_d));
      if (!why.empty()) out[name] = absl::StrJoin(why, ", ");
    }
  }
  return out;
}

// Leaves the triangles of transparent materials out of `m` (the simulator renders opaque surfaces: an eye shell or an
// eyelash card would hide what is under it), and says which.
void LeaveOutTransparent(const std::string& obj, TriangleMesh* m, std::vector<std::string>* notes) {
  if (m->materials.empty()) return;
  const std::map<std::string, std::string> transparent = TransparentMaterials(obj, *m, notes);
  if (transparent.empty()) return;
  auto left_out = [&](size_t t) {
    const int32_t mat = m->materials[t];
    return mat >= 0 && transparent.count(m->material_names[static_cast<size_t>(mat)]) > 0;
  };
  std::vector<int64_t> dropped(m->material_names.size(), 0);
  int64_t total = 0;
  for (size_t t = 0; t < m->triangles.size(); ++t) {
    if (!left_out(t)) continue;
    ++dropped[static_cast<size_t>(m->materials[t])];
    ++total;
  }
  if (total == 0) return;
  std::vector<std::string> named;
  for (size_t i = 0; i < dropped.size(); ++i) {
    if (dropped[i] == 0) continue;
    named.push_back(absl::StrCat(m->material_names[i], " (", transparent.at(m->material_names[i]), ", ", dropped[i],
                                 " triangles)"));
  }
  if (2 * total > static_cast<int64_t>(m->triangles.size())) {
    // Most of the mesh would go: the library more likely means something else than a scan of mostly eye shells.
    notes->push_back(absl::StrCat(obj, ": materials that look transparent hold ", total, " of ", m->triangles.size(),
                                  " triangles, most of the mesh: kept and rendered opaque (check its material "
                                  "library): ",
                                  absl::StrJoin(named, "; ")));
    return;
  }
  size_t kept = 0;
  for (size_t t = 0; t < m->triangles.size(); ++t) {
    if (left_out(t)) continue;
    m->triangles[kept] = m->triangles[t];
    m->materials[kept] = m->materials[t];
    if (!m->parts.empty()) m->parts[kept] = m->parts[t];
    ++kept;
  }
  m->triangles.resize(kept);
  m->materials.resize(kept);
  if (!m->parts.empty()) m->parts.resize(kept);
  notes->push_back(absl::StrCat(obj, ": left out ", total,
                                " triangles of transparent materials, as the simulator renders opaque surfaces only: ",
                                absl::StrJoin(named, "; ")));
}

// Says where `m` is open: its holes (loops of edges that only one triangle has, vertices welded by position), largest
// first, with where they are. A camera that looks into one sees through the head.
void DescribeHoles(const std::string& obj, const TriangleMesh& m, std::vector<std::string>* notes) {
  std::map<std::array<float, 3>, int32_t> weld;
  std::vector<int32_t> id(m.positions.size());
  for (size_t v = 0; v < m.positions.size(); ++v) {
    const Eigen::Vector3f& p = m.positions[v];
    id[v] = weld.try_emplace({p.x(), p.y(), p.z()}, static_cast<int32_t>(weld.size())).first->second;
  }
  std::map<std::pair<int32_t, int32_t>, int> edges;
  for (const auto& t : m.triangles) {
    for (int k = 0; k < 3; ++k) {
      const int32_t a = id[t[k]], b = id[t[(k + 1) % 3]];
      if (a != b) ++edges[{std::min(a, b), std::max(a, b)}];
    }
  }
  // Union-find over the boundary edges' vertices: each component is a hole.
  std::map<int32_t, int32_t> parent;
  std::function<int32_t(int32_t)> find = [&](int32_t x) {
    auto it = parent.find(x);
    if (it == parent.end()) return parent[x] = x;
    return it->second == x ? x : it->second = find(it->second);
  };
  std::vector<std::pair<int32_t, int32_t>> boundary;
  for (const auto& [e, n] : edges) {
    if (n != 1) continue;
    boundary.push_back(e);
    parent[find(e.first)] = find(e.second);
  }
  if (boundary.empty()) return;
  std::vector<Eigen::Vector3f> welded(weld.size());
  for (size_t v = 0; v < m.positions.size(); ++v) welded[static_cast<size_t>(id[v])] = m.positions[v];
  std::map<int32_t, std::pair<int, Eigen::Vector3f>> holes;  // root -> (edges, sum of their first ends)
  for (const auto& [a, b] : boundary) {
    auto& h = holes.try_emplace(find(a), 0, Eigen::Vector3f::Zero()).first->second;
    ++h.first;
    h.second += welded[static_cast<size_t>(a)];
  }
  std::vector<std::pair<int, Eigen::Vector3f>> sorted;
  for (const auto& [root, h] : holes) sorted.emplace_back(h.first, h.second / static_cast<float>(h.first));
  std::sort(sorted.begin(), sorted.end(), [](const auto& x, const auto& y) { return x.first > y.first; });
  std::vector<std::string> where;
  for (size_t i = 0; i < sorted.size() && i < 5; ++i) {
    const Eigen::Vector3f& c = sorted[i].second;
    where.push_back(absl::StrFormat("%d edges around (%.0f, %.0f, %.0f) mm", sorted[i].first, c.x(), c.y(), c.z()));
  }
  if (sorted.size() > 5) where.push_back(absl::StrCat("and ", sorted.size() - 5, " more"));
  notes->push_back(absl::StrCat(
      obj, ": the mesh is open: ", sorted.size(), sorted.size() == 1 ? " hole (" : " holes (",
      absl::StrJoin(where, "; "),
      "); a camera looking into one sees through the head, black. A head for the stage is closed: eyes, mouth "
      "interior, ears and the back of the head (head frame: +y up, +z the way the face looks)"));
}

}  // namespace

struct HeadModel::Maps {
  Image albedo, specular, roughness, normal;
  float specular_value = 0.03f, roughness_value = 0.3f, specular_scale = 0.1f;

  SurfaceSample Sample(const Eigen::Vector2f& uv) const {
    SurfaceSample s;
    float v[3];
    albedo.Sample(uv, v);
    s.material.albedo = Eigen::Vector3f(v[0], v[1], v[2]).cwiseMax(0.0f).cwiseMin(1.0f);
    s.material.specular = specular_value;
    if (!specular.empty()) {
      specular.Sample(uv, v);
      s.material.specular = std::clamp(v[0] * specular_scale, 0.0f, 1.0f);
    }
    s.material.roughness = roughness_value;
    if (!roughness.empty()) {
      roughness.Sample(uv, v);
      s.material.roughness = std::clamp(v[0], 0.01f, 1.0f);
    }
    if (!normal.empty()) {
      normal.Sample(uv, v);
      const Eigen::Vector3f n(v[0], v[1], v[2]);
      if (n.z() > 1e-3f) s.tangent_normal = n.normalized();
    }
    return s;
  }
};

absl::StatusOr<std::shared_ptr<const HeadModel>> HeadModel::FromAsset(const HeadAssetFiles& files) {
  std::shared_ptr<HeadModel> head(new HeadModel());
  STAGE_ASSIGN_OR_RETURN(head->neutral_, ReadObj(files.neutral_obj));
  TriangleMesh& m = head->neutral_;
  if (std::all_of(m.uvs.begin(), m.uvs.end(), [](const Eigen::Vector2f& t) { return t.isZero(); })) {
    return absl::InvalidArgumentError(
        absl::StrCat(files.neutral_obj, ": has no texture coordinates (vt), which the skin maps need"));
  }
  for (auto& p : m.positions) p *= files.units_mm;
  head->pivot_ = files.pivot_mm;
  for (const auto& [name, path] : files.blendshapes) {
    const int e = ExpressionIndex(name);
    if (e < 0) {
      std::string names;
      for (int i = 0; i < kExpressionCount; ++i) absl::StrAppend(&names, i ? ", " : "", kNames[i]);
      return absl::InvalidArgumentError(
          absl::StrCat("sim.subject.asset.blendshapes: \"", name, "\" is not an expression (", names, ")"));
    }
    STAGE_ASSIGN_OR_RETURN(TriangleMesh shape, ReadObj(path));
    if (shape.positions.size() != m.positions.size() || shape.triangles != m.triangles) {
      return absl::InvalidArgumentError(absl::StrCat(
          "sim.subject.asset.blendshapes.", name, ": ", path, " does not have the topology of ", files.neutral_obj,
          " (", shape.positions.size(), " vertices and ", shape.triangles.size(), " triangles against ",
          m.positions.size(), " and ", m.triangles.size(), ", or faces in another order)"));
    }
    auto& delta = head->deltas_[e];
    delta.resize(m.positions.size());
    for (size_t v = 0; v < delta.size(); ++v) delta[v] = shape.positions[v] * files.units_mm - m.positions[v];
  }
  // What of the mesh the simulator renders, said now rather than seen later as black or opaque patches.
  LeaveOutTransparent(files.neutral_obj, &m, &head->notes_);
  STAGE_RETURN_IF_ERROR(CheckUvTile(files.neutral_obj, m));  // of what is rendered: a lash card's tile does not count
  DescribeHoles(files.neutral_obj, m, &head->notes_);
  auto maps = std::make_shared<Maps>();
  maps->specular_value = files.specular_value;
  maps->roughness_value = files.roughness_value;
  maps->specular_scale = files.specular_scale;
  if (files.albedo.empty()) return absl::InvalidArgumentError("sim.subject.asset.albedo: required with neutral_obj");
  STAGE_ASSIGN_OR_RETURN(std::vector<Image> images, LoadMaps(files, &head->maps_origin_));
  maps->albedo = std::move(images[0]);
  maps->specular = std::move(images[1]);
  maps->roughness = std::move(images[2]);
  maps->normal = std::move(images[3]);
  head->maps_ = std::move(maps);
  return std::shared_ptr<const HeadModel>(std::move(head));
}

const char* ExpressionName(int index) { return index >= 0 && index < kExpressionCount ? kNames[index] : ""; }

int ExpressionIndex(const std::string& name) {
  for (int i = 0; i < kExpressionCount; ++i) {
    if (name == kNames[i]) return i;
  }
  return -1;
}

HeadPose Performance::At(double t_s) const {
  if (keys.empty()) return {};
  if (t_s <= keys.front().first) return keys.front().second;
  if (t_s >= keys.back().first) return keys.back().second;
  auto next = std::upper_bound(keys.begin(), keys.end(), t_s,
                               [](double t, const std::pair<double, HeadPose>& k) { return t < k.first; });
  const auto& [t1, b] = *next;
  const auto& [t0, a] = *std::prev(next);
  const float s = Smooth(0, 1, static_cast<float>((t_s - t0) / (t1 - t0)));
  HeadPose out;
  for (int i = 0; i < kExpressionCount; ++i)
    out.expression[i] = a.expression[i] + s * (b.expression[i] - a.expression[i]);
  out.rotation_deg = a.rotation_deg + s * (b.rotation_deg - a.rotation_deg);
  out.translation_mm = a.translation_mm + s * (b.translation_mm - a.translation_mm);
  return out;
}

std::string Performance::SequenceAt(double t_s) const {
  std::string name;
  for (const auto& [start, n] : sequences) {
    if (start > t_s) break;
    name = n;
  }
  return name;
}

Performance Performance::RangeOfMotion(uint64_t seed, double seconds) {
  struct Group {
    const char* name;
    std::vector<int> expressions;  // worked together, at one drawn weight each
  };
  const std::vector<Group> groups = {{"jaw", {kJaw}},
                                     {"smile", {kSmileL, kSmileR}},
                                     {"blink", {kBlinkL, kBlinkR}},
                                     {"brows", {kBrow}},
                                     {"frown", {kFrown}},
                                     {"pucker", {kPucker}},
                                     {"asymmetric", {kSmileL, kBlinkR, kBrow}},
                                     {"speech", {kJaw, kPucker, kSmileL, kSmileR}}};
  std::seed_seq seq{static_cast<uint32_t>(seed), static_cast<uint32_t>(seed >> 32), 0x5e9u};
  std::mt19937_64 rng(seq);
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  constexpr double kSequenceS = 6.0, kKeyS = 0.5;
  // The head's motion: a target every 1.5 s drawn anew, eased between (the keys sample it every half second).
  constexpr double kMotionS = 1.5;
  const int motion_keys = static_cast<int>(std::ceil(seconds / kMotionS)) + 2;
  std::vector<Eigen::Matrix<float, 6, 1>> motion(static_cast<size_t>(motion_keys));
  const Eigen::Matrix<float, 6, 1> range = (Eigen::Matrix<float, 6, 1>() << 30, 12, 6, 12, 12, 12).finished();
  for (int m = 0; m < motion_keys; ++m) {
    for (int c = 0; c < 6; ++c)
      motion[static_cast<size_t>(m)][c] = (m == 0 ? 0.f : 1.f) * range[c] * static_cast<float>(2 * unit(rng) - 1);
  }
  auto motion_at = [&](double t) {
    const int m = std::min(motion_keys - 2, static_cast<int>(t / kMotionS));
    const float s = Smooth(0, 1, static_cast<float>(t / kMotionS - m));
    return Eigen::Matrix<float, 6, 1>(motion[static_cast<size_t>(m)] +
                                      s * (motion[static_cast<size_t>(m) + 1] - motion[static_cast<size_t>(m)]));
  };
  Performance p;
  std::vector<int> order(groups.size());
  int round = 0;
  size_t next = order.size();
  for (double start = 0; start < seconds; start += kSequenceS) {
    if (next == order.size()) {
      std::iota(order.begin(), order.end(), 0);
      std::shuffle(order.begin(), order.end(), rng);
      next = 0;
      ++round;
    }
    const Group& group = groups[static_cast<size_t>(order[next++])];
    p.sequences.emplace_back(start, absl::StrCat(group.name, "-", round));
    // Each sequence starts and ends neutral; between, its expressions rise and fall at drawn weights.
    for (double t = start; t < std::min(seconds, start + kSequenceS) - 1e-9; t += kKeyS) {
      HeadPose pose;
      const bool rest = t == start || t + kKeyS >= start + kSequenceS - 1e-9;
      for (int e : group.expressions) {
        const double w = unit(rng);  // drawn for every key, so the stream does not depend on which are at rest
        if (!rest) pose.expression[static_cast<size_t>(e)] = static_cast<float>(0.2 + 0.8 * w);
      }
      const Eigen::Matrix<float, 6, 1> m = motion_at(t);
      pose.rotation_deg = m.head<3>();
      pose.translation_mm = m.tail<3>();
      p.keys.emplace_back(t, pose);
    }
  }
  HeadPose last;
  const Eigen::Matrix<float, 6, 1> m = motion_at(seconds);
  last.rotation_deg = m.head<3>();
  last.translation_mm = m.tail<3>();
  p.keys.emplace_back(seconds, last);
  return p;
}

Performance Performance::Default() {
  Performance p;
  auto key = [&](double t, std::initializer_list<std::pair<int, float>> expr, Eigen::Vector3f rot = {0, 0, 0}) {
    HeadPose pose;
    for (auto [i, w] : expr) pose.expression[i] = w;
    pose.rotation_deg = rot;
    p.keys.emplace_back(t, pose);
  };
  key(0.0, {});
  key(0.4, {{kBrow, 1}});
  key(0.8, {{kSmileL, 1}, {kSmileR, 1}});
  key(1.2, {{kJaw, 1}});
  key(1.5, {{kBlinkL, 1}, {kBlinkR, 1}});
  key(1.8, {{kFrown, 1}});
  key(2.2, {{kPucker, 1}});
  key(2.5, {{kSmileL, 1}, {kBlinkR, 1}});
  key(2.8, {{kSmileR, 1}, {kBlinkL, 1}});
  key(3.2, {}, {20, 5, 0});
  key(3.6, {}, {-20, -8, 6});
  key(4.0, {});
  return p;
}

absl::StatusOr<Performance> Performance::FromYaml(const std::string& path) {
  YAML::Node root;
  try {
    root = YAML::LoadFile(path);
  } catch (const YAML::Exception& e) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": ", e.what()));
  }
  if (!root["keys"] || !root["keys"].IsSequence() || root["keys"].size() == 0) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": needs a non-empty list `keys`"));
  }
  Performance p;
  double last = -INFINITY;
  for (size_t k = 0; k < root["keys"].size(); ++k) {
    const YAML::Node key = root["keys"][k];
    const std::string where = absl::StrCat(path, ": keys[", k, "]");
    if (!key.IsMap() || !key["t"]) return absl::InvalidArgumentError(absl::StrCat(where, ": needs a time `t`"));
    HeadPose pose;
    double t = 0;
    try {
      t = key["t"].as<double>();
      for (const auto& field : key) {
        const std::string name = field.first.as<std::string>();
        if (name == "sequence") {
          p.sequences.emplace_back(t, field.second.as<std::string>());
          continue;
        }
        const double v = field.second.as<double>();
        const int e = ExpressionIndex(name);
        if (e >= 0) {
          if (v < 0 || v > 1)
            return absl::InvalidArgumentError(absl::StrCat(where, ".", name, ": ", v, " is not in [0, 1]"));
          pose.expression[e] = static_cast<float>(v);
        } else if (name == "yaw") {
          pose.rotation_deg.x() = static_cast<float>(v);
        } else if (name == "pitch") {
          pose.rotation_deg.y() = static_cast<float>(v);
        } else if (name == "roll") {
          pose.rotation_deg.z() = static_cast<float>(v);
        } else if (name == "x" || name == "y" || name == "z") {
          pose.translation_mm[name[0] - 'x'] = static_cast<float>(v);
        } else if (name != "t") {
          std::string known;
          for (const char* n : kNames) absl::StrAppend(&known, n, ", ");
          return absl::InvalidArgumentError(absl::StrCat(where, ": unknown field \"", name, "\" (t, ", known,
                                                         "yaw, pitch, roll, x, y, z, sequence)"));
        }
      }
    } catch (const YAML::Exception& e) {
      return absl::InvalidArgumentError(absl::StrCat(where, ": ", e.what()));
    }
    if (t <= last) return absl::InvalidArgumentError(absl::StrCat(where, ": times must increase"));
    last = t;
    p.keys.emplace_back(t, pose);
  }
  return p;
}

HeadLandmarks ProceduralHeadLandmarks() { return {kEyeTheta, kEyePhi, kMouthPhi, kJawHinge, Eigen::Vector3f::UnitX()}; }

HeadShape HeadShape::Drawn(uint64_t identity) {
  HeadShape s;
  if (identity == 0) return s;
  // Normal draws (Box-Muller over the hash's uniforms), one per proportion.
  int k = 0;
  auto vary = [&](float* value, float relative) {
    const float u1 = std::max(Rand(identity, 0, 0, 2 * k), 1e-7f), u2 = Rand(identity, 0, 0, 2 * k + 1);
    ++k;
    const float n = std::sqrt(-2 * std::log(u1)) * std::cos(2 * kPi * u2);
    *value *= 1 + relative * std::clamp(n, -2.5f, 2.5f);
  };
  vary(&s.width_mm, 0.04f);
  vary(&s.height_mm, 0.04f);
  vary(&s.depth_mm, 0.04f);
  vary(&s.jaw, 0.25f);
  for (float* feature : {&s.nose_mm, &s.nose_tip_mm, &s.nostrils_mm, &s.eye_sockets_mm, &s.brows_mm, &s.cheekbones_mm,
                         &s.lips_mm, &s.chin_mm, &s.ears_mm}) {
    vary(feature, 0.2f);
  }
  return s;
}

std::shared_ptr<const HeadModel> HeadModel::Procedural(uint64_t seed, int resolution, const HeadShape& shape,
                                                       float blood_flow) {
  std::shared_ptr<HeadModel> head(new HeadModel());
  head->seed_ = seed;
  head->blood_flow_ = std::clamp(blood_flow, 0.0f, 1.0f);
  head->pivot_ = kPivot;
  TriangleMesh& m = head->neutral_;
  const int cols = std::max(16, resolution), rows = std::max(8, resolution / 2);
  // Skin: a (cols + 1) x (rows + 1) grid over azimuth and elevation; the seam column repeats the first with u = 1.
  std::vector<float> th_of, ph_of;
  for (int j = 0; j <= rows; ++j) {
    const float v = static_cast<float>(j) / rows;
    const float ph = v * kPi - kPi / 2;
    for (int i = 0; i <= cols; ++i) {
      const float u = static_cast<float>(i) / cols;
      const float th = u * 2 * kPi - kPi;
      // The poles are one point each (exactly, or the fan around them has slivers).
      m.positions.push_back(j == 0 || j == rows
                                ? Eigen::Vector3f(0, j == 0 ? -Radius(0, ph, shape) : Radius(0, ph, shape), 0)
                                : Eigen::Vector3f(Dir(th, ph) * Radius(th, ph, shape)));
      m.uvs.emplace_back(u, v);
      th_of.push_back(th);
      ph_of.push_back(ph);
    }
  }
  auto at = [&](int i, int j) { return static_cast<int32_t>(j * (cols + 1) + i); };
  for (int j = 0; j < rows; ++j) {
    for (int i = 0; i < cols; ++i) {
      // Counter-clockwise seen from outside (outward normals; u grows towards +x from the back, th = -pi, through
      // the face, v upwards).
      m.triangles.push_back({at(i, j), at(i + 1, j), at(i, j + 1)});
      m.triangles.push_back({at(i + 1, j), at(i + 1, j + 1), at(i, j + 1)});
    }
  }
  m.parts.assign(m.triangles.size(), 0);
  const size_t skin_vertices = m.positions.size();
  // Eyes: spheres in the sockets, 2 mm proud of the socket's floor; uv.x = angle from the gaze / pi.
  for (float sgn : {1.0f, -1.0f}) {
    const float th = sgn * kEyeTheta;
    const Eigen::Vector3f center = Dir(th, kEyePhi) * (Radius(th, kEyePhi, shape) + 2 - kEyeRadius);
    const int er = 24, ec = 12;
    const auto first = static_cast<int32_t>(m.positions.size());
    for (int j = 0; j <= ec; ++j) {
      const float a = kPi * j / ec;  // from the gaze direction (+z)
      for (int i = 0; i <= er; ++i) {
        const float b = 2 * kPi * i / er;
        const Eigen::Vector3f n(std::sin(a) * std::cos(b), std::sin(a) * std::sin(b), std::cos(a));
        m.positions.push_back(center + kEyeRadius * n);
        m.uvs.emplace_back(a / kPi, static_cast<float>(i) / er);
      }
    }
    for (int j = 0; j < ec; ++j) {
      for (int i = 0; i < er; ++i) {
        const int32_t a = first + j * (er + 1) + i, b = a + er + 1;
        m.triangles.push_back({a, b, a + 1});  // counter-clockwise seen from outside
        m.triangles.push_back({a + 1, b, b + 1});
        m.parts.push_back(1);
        m.parts.push_back(1);
      }
    }
  }
  for (int e = 0; e < kExpressionCount; ++e) {
    auto& delta = head->deltas_[e];
    delta.assign(m.positions.size(), Eigen::Vector3f::Zero());
    for (size_t v = 0; v < skin_vertices; ++v) delta[v] = Delta(e, th_of[v], ph_of[v], m.positions[v]);
  }
  return head;
}

Eigen::Matrix3f PoseRotation(const HeadPose& pose) {
  const float k = kPi / 180;
  return (Eigen::AngleAxisf(pose.rotation_deg.x() * k, Eigen::Vector3f::UnitY()) *
          Eigen::AngleAxisf(pose.rotation_deg.y() * k, Eigen::Vector3f::UnitX()) *
          Eigen::AngleAxisf(pose.rotation_deg.z() * k, Eigen::Vector3f::UnitZ()))
      .toRotationMatrix();
}

TriangleMesh RiggedModel::PosedMesh(const HeadPose& pose) const {
  TriangleMesh m = neutral_;
  for (int e = 0; e < kExpressionCount; ++e) {
    const float w = pose.expression[e];
    if (w == 0 || deltas_[e].empty()) continue;
    for (size_t v = 0; v < m.positions.size(); ++v) m.positions[v] += w * deltas_[e][v];
  }
  const Eigen::Matrix3f r = PoseRotation(pose);
  for (auto& p : m.positions) p = r * (p - pivot_) + pivot_ + pose.translation_mm;
  return m;
}

std::unique_ptr<MeshSubject> RiggedModel::Posed(const HeadPose& pose) const {
  const auto expr = pose.expression;
  return std::make_unique<MeshSubject>(
      PosedMesh(pose), [this, expr](const Eigen::Vector2f& uv, int part) { return Surface(uv, part, expr); }, Convex());
}

float HeadModel::Height(const Eigen::Vector2f& uv, const std::array<float, kExpressionCount>& e) const {
  const float th = uv.x() * 2 * kPi - kPi, ph = uv.y() * kPi - kPi / 2;
  float h = -0.04f * Pores(seed_, uv);
  // Expression wrinkles (mm deep at full weight).
  if (e[kBrow] > 0) {
    h -= 0.25f * e[kBrow] * Blob(th, ph, 0, 0.45f, 0.45f, 0.09f) *
         (0.5f + 0.5f * std::cos(2 * kPi * (ph - 0.35f) / 0.035f));
  }
  if (e[kFrown] > 0) {
    h -= 0.3f * e[kFrown] * Blob(th, ph, 0, 0.25f, 0.07f, 0.05f) * std::pow(std::cos(2 * kPi * th / 0.06f), 8.0f);
  }
  for (int s = 0; s < 2; ++s) {
    const float w = e[s == 0 ? kSmileL : kSmileR];
    if (w <= 0) continue;
    const float th0 = (s == 0 ? 1 : -1) * 0.62f;
    h -= 0.2f * w * Blob(th, ph, th0, 0.08f, 0.06f, 0.06f) *
         std::pow(0.5f + 0.5f * std::cos(2 * kPi * (ph - 0.08f + 0.3f * AngleDiff(th, th0)) / 0.025f), 4.0f);
  }
  return h;
}

SurfaceSample HeadModel::Surface(const Eigen::Vector2f& uv, int part,
                                 const std::array<float, kExpressionCount>& e) const {
  if (maps_ != nullptr) return maps_->Sample(uv);
  SurfaceSample s;
  if (part == 1) {
    const float a = uv.x();  // angle from the gaze / pi
    if (a < 0.06f) {
      s.material.albedo = Eigen::Vector3f::Constant(0.02f);
    } else if (a < 0.16f) {
      s.material.albedo = Eigen::Vector3f(0.22f, 0.14f, 0.07f);
    } else {
      s.material.albedo = Eigen::Vector3f(0.78f, 0.76f, 0.72f);
    }
    s.material.specular = 0.05f;
    s.material.roughness = 0.08f;
    return s;
  }
  const float th = uv.x() * 2 * kPi - kPi, ph = uv.y() * kPi - kPi / 2;
  const float lips =
      std::clamp(1.3f * (Blob(th, ph, 0, -0.43f, 0.2f, 0.035f) + Blob(th, ph, 0, -0.54f, 0.18f, 0.035f)), 0.0f, 1.0f);
  const float brows = std::clamp(1.5f * Both(th, ph, kEyeTheta, 0.245f, 0.15f, 0.025f), 0.0f, 1.0f);
  const float tzone = std::clamp(Blob(th, ph, 0, 0.4f, 0.35f, 0.15f) + Blob(th, ph, 0, -0.1f, 0.1f, 0.2f), 0.0f, 1.0f);
  const float face = Smooth(0.0f, 0.6f, std::cos(th));
  const float pore = Pores(seed_, uv);
  // Albedo: skin with low-frequency variation and redness, freckles on the face, pores a little darker.
  Eigen::Vector3f albedo(0.60f, 0.40f, 0.31f);
  albedo *= 0.92f + 0.16f * ValueNoise(seed_ + 11, uv.x() * 60, uv.y() * 40);
  const float red = Both(th, ph, 0.5f, -0.15f, 0.2f, 0.15f) + 0.6f * Blob(th, ph, 0, -0.15f, 0.08f, 0.1f);
  albedo.y() *= 1 - 0.12f * std::min(1.0f, red);
  albedo *= 1 - 0.35f * face * Freckles(seed_ + 3, uv);
  albedo *= 1 - 0.12f * pore;
  if (blood_flow_ > 0) {
    // Blood flow (as Jimenez et al. 2010 measure it): where an expression works the face, the skin flushes, green and
    // blue absorbed by the blood that comes: the cheeks with a smile, the forehead with a frown or a brow raise, the
    // chin with the jaw open.
    const float flush =
        blood_flow_ * std::min(1.0f, e[kSmileL] * Blob(th, ph, 0.5f, -0.15f, 0.25f, 0.18f) +
                                         e[kSmileR] * Blob(th, ph, -0.5f, -0.15f, 0.25f, 0.18f) +
                                         (0.7f * e[kFrown] + 0.5f * e[kBrow]) * Blob(th, ph, 0, 0.4f, 0.4f, 0.15f) +
                                         0.6f * e[kJaw] * Blob(th, ph, 0, -0.75f, 0.25f, 0.12f));
    albedo = albedo.cwiseProduct(Eigen::Vector3f(1 + 0.05f * flush, 1 - 0.35f * flush, 1 - 0.25f * flush));
  }
  albedo = (1 - lips) * albedo + lips * Eigen::Vector3f(0.52f, 0.22f, 0.22f);
  albedo = (1 - brows) * albedo + brows * Eigen::Vector3f(0.10f, 0.07f, 0.05f);
  // The open mouth is dark inside.
  albedo *= 1 - 0.9f * e[kJaw] * Blob(th, ph, 0, kMouthPhi, 0.15f, 0.03f);
  s.material.albedo = albedo;
  s.material.specular = (0.028f + 0.012f * tzone + 0.007f * lips) * (1 - 0.4f * pore) * (1 - 0.6f * brows);
  s.material.roughness = std::clamp(0.35f - 0.07f * tzone - 0.12f * lips + 0.3f * brows, 0.05f, 1.0f);
  // Detail normals: central differences of the height field at a quarter texel.
  const float step = 0.25f / kTexels;
  s.height = Height(uv, e);
  s.dh_du = (Height(uv + Eigen::Vector2f(step, 0), e) - Height(uv - Eigen::Vector2f(step, 0), e)) / (2 * step);
  s.dh_dv = (Height(uv + Eigen::Vector2f(0, step), e) - Height(uv - Eigen::Vector2f(0, step), e)) / (2 * step);
  return s;
}

}  // namespace stage::sim
