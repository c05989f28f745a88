// The RGB albedo from a Bayer mosaic's one colour a pixel (internal::DemosaicAlbedo): see photometric_internal.h and
// docs/processing.md ("Albedo from a Bayer mosaic").
#include <algorithm>
#include <cmath>
#include <iterator>
#include <limits>
#include <utility>

#include "photometric_internal.h"

namespace stage::processing::internal {
namespace {

constexpr int kChunk = 64;           // rows a thread takes at a time (each with kHalo rows above and below)
constexpr int kWin = 2;              // the hue's window: 5 x 5 pixels
constexpr int kShift = 2;            // the off-centre windows' offset
constexpr int kPad = kWin + kShift;  // rows and columns of the hue planes beyond the output's
constexpr int kHalo = kPad + 1;      // rows of log albedo beyond the output's (a site's 8 neighbours)
constexpr float kMinSites = 3;       // the fewest hue samples a window is taken with
// The share of a missing colour taken from the pixel's own albedo and the hue, the rest from its neighbours of that
// colour: 0.7 measured best on the simulated head (1.06 % against 1.05-1.14 % for 0.5-0.8) and keeps the uniform
// sphere at 0.67 % (0.59 % with the neighbours alone, 0.75 % with the hue alone); docs/processing.md.
constexpr float kHueWeight = 0.7f;

// One thread's planes for a chunk of rows, kept from chunk to chunk. Columns are offset by kPad (zero there).
struct DemosaicBuffers {
  size_t stride = 0;
  // Own albedo, its log, and 1 where it is usable (0, 0 and 0 elsewhere); kChunk + 2 kHalo rows each.
  std::vector<float> values, logs, usable;
  std::vector<float> hue;     // per site: 1, log(R/G), log(B/G), their squares summed; kChunk + 2 kPad rows each
  std::vector<float> column;  // the hue planes summed over kWin rows either side: kChunk + 2 kShift rows each
  std::vector<float> box;     // and over kWin columns either side
  std::vector<float> pick;    // per column of a row: the chosen window's mean hue (R/G, B/G) and whether there was one
  std::vector<float> planar;  // a row of the output, each colour's plane (w floats)
  std::vector<float> row;     // and interleaved (3 floats a pixel)
  void Resize(int w) {
    stride = static_cast<size_t>(w) + 2 * kPad;
    values.assign((kChunk + 2 * kHalo) * stride, 0.f);
    logs.assign(values.size(), 0.f);
    usable.assign(values.size(), 0.f);
    hue.assign(4 * (kChunk + 2 * kPad) * stride, 0.f);
    column.assign(4 * (kChunk + 2 * kShift) * stride, 0.f);
    box.assign(column.size(), 0.f);
    pick.resize(3 * static_cast<size_t>(w));
    planar.resize(3 * static_cast<size_t>(w));
    row.resize(3 * static_cast<size_t>(w));
  }
};

// Whether a pixel's own albedo can be used (for the hue, the neighbours' means and the texture): positive and finite.
// & rather than &&, so that the row loops that test it run in vector lanes.
inline bool Usable(float v) { return (v > 0) & (v < std::numeric_limits<float>::infinity()); }

// A pixel whose albedo the map leaves out: not solved (too dark), or solved to an albedo no surface has.
constexpr uint8_t kNotSolved = kLowSignal | kImplausible;

// The means of a plane (v; u: 1 where usable, else 0) over site x's usable neighbours of each colour it does not
// measure (c: its colour; beside: when it is green, the colour beside it): the 2 beside it and the 2 above and below
// for green, the 4 at its sides and the 4 at its corners for red and blue. NaN for a colour with none, and for c.
// Every mean is computed and the site's colour selects among them, so that a row's loop runs in vector lanes (the
// colour tested by its bits: tests of c == 0, 1 and 2 become a three-way choice GCC does not turn into lane selects).
struct Rgb {
  float r, g, b;
};
inline Rgb NeighbourMeans(const float* v, const float* u, size_t stride, int x, int c, int beside) {
  const float* vu = v - stride;
  const float* vd = v + stride;
  const float* uu = u - stride;
  const float* ud = u + stride;
  const float sh = v[x - 1] + v[x + 1], nh = u[x - 1] + u[x + 1];
  const float sv = vu[x] + vd[x], nv = uu[x] + ud[x];
  const float sd = vu[x - 1] + vu[x + 1] + vd[x - 1] + vd[x + 1];
  const float nd = uu[x - 1] + uu[x + 1] + ud[x - 1] + ud[x + 1];
  const float none = std::numeric_limits<float>::quiet_NaN();
  const float beside_mean = nh > 0 ? sh / nh : none;                    // green: the colour beside it
  const float across_mean = nv > 0 ? sv / nv : none;                    // green: the other, above and below
  const float edges_mean = nh + nv > 0 ? (sh + sv) / (nh + nv) : none;  // red or blue: green
  const float corners_mean = nd > 0 ? sd / nd : none;                   // red or blue: the other of the two
  const float green_r = beside == 0 ? beside_mean : across_mean, green_b = beside == 0 ? across_mean : beside_mean;
  const bool green = (c & 1) != 0, blue = (c & 2) != 0;
  return {.r = green  ? green_r
               : blue ? corners_mean
                      : none,
          .g = green ? none : edges_mean,
          .b = green  ? green_b
               : blue ? none
                      : corners_mean};
}

// A row's hue planes over columns [x0, x1) (lm: log albedo, um: 1 where usable; color: each column's colour; beside:
// the colour beside a green site): at each usable site with all three colours, 1, log(R/G), log(B/G) and their
// squares summed, its own colour's log albedo and the others' means over its usable neighbours of that colour; 0
// elsewhere.
STAGE_ROW_LOOP void HueRow(const float* __restrict lm, const float* __restrict um, size_t stride,
                           const uint8_t* __restrict color, int beside, int x0, int x1, float* __restrict q0,
                           float* __restrict q1, float* __restrict q2, float* __restrict q3) {
  for (int x = x0; x < x1; ++x) {
    const int c = color[x];
    const Rgb near = NeighbourMeans(lm, um, stride, x, c, beside);
    const float own = lm[x];
    const bool green = (c & 1) != 0, blue = (c & 2) != 0, red = !(green | blue);
    const float lr = red ? own : near.r, lg = green ? own : near.g, lb = blue ? own : near.b;
    const bool ok = (um[x] != 0) & (lr == lr) & (lg == lg) & (lb == lb);  // usable, none missing
    const float r = ok ? lr - lg : 0.f, b = ok ? lb - lg : 0.f;
    q0[x] = ok ? 1.f : 0.f;
    q1[x] = r;
    q2[x] = b;
    q3[x] = r * r + b * b;
  }
}

// A row's RGB albedo over columns [x0, x1), planar (out_r, out_g, out_b): at each solved pixel (flags), its own colour
// as solved (own), each other colour kHueWeight of its own albedo times the hue (ratio_r: R/G, ratio_b: B/G, where
// found) and the rest the mean of its usable neighbours of that colour (vm, um); the neighbours alone where no hue was
// found, 0 for a colour with none; 0 where not solved.
STAGE_ROW_LOOP void AlbedoRow(const float* __restrict own, const uint8_t* __restrict flags, const float* __restrict vm,
                              const float* __restrict um, size_t stride, const uint8_t* __restrict color, int beside,
                              const float* __restrict ratio_r, const float* __restrict ratio_b,
                              const float* __restrict found, int x0, int x1, float* __restrict out_r,
                              float* __restrict out_g, float* __restrict out_b) {
  for (int x = x0; x < x1; ++x) {
    const int c = color[x];
    const float mine = own[x];
    const Rgb near = NeighbourMeans(vm, um, stride, x, c, beside);
    const bool solved = (flags[x] & kNotSolved) == 0;
    const bool hued = (found[x] != 0) & Usable(mine);
    const float hr = ratio_r[x], hb = ratio_b[x];  // each colour over green
    const bool green = (c & 1) != 0, blue = (c & 2) != 0, red = !(green | blue);
    const float hc = green ? 1.f : blue ? hb : hr;
    auto missing = [&](float hk, float nk) {
      const float textured = mine * (hk / hc);
      const float blended = nk != nk ? textured : kHueWeight * textured + (1 - kHueWeight) * nk;
      const float alone = nk == nk ? nk : 0.f;
      return hued ? blended : alone;
    };
    const float ar = missing(hr, near.r), ag = missing(1.f, near.g), ab = missing(hb, near.b);
    out_r[x] = solved ? (red ? mine : ar) : 0.f;
    out_g[x] = solved ? (green ? mine : ag) : 0.f;
    out_b[x] = solved ? (blue ? mine : ab) : 0.f;
  }
}

// A row's albedo over columns [x0, x1) where it is usable (solved, positive and finite; else 0), its log (else 0), and
// 1 where it is usable (else 0).
STAGE_ROW_LOOP void LogRow(const float* __restrict own, const uint8_t* __restrict flags, int x0, int x1,
                           float* __restrict values, float* __restrict logs, float* __restrict usable) {
  for (int x = x0; x < x1; ++x) {
    const float v = own[x];
    const float lg = PortableLog(v);  // computed for every column, so that the loop runs in vector lanes
    const bool ok = ((flags[x] & kNotSolved) == 0) & Usable(v);
    values[x] = ok ? v : 0.f;
    logs[x] = ok ? lg : 0.f;
    usable[x] = ok ? 1.f : 0.f;
  }
}

// Per column x in [x0, x1) of a row, of the five windows centred at offsets[k] + x in the window sums (`box`: the
// count, the sums of log(R/G) and log(B/G) and of their squares, `plane` floats apart), the one with kMinSites samples
// whose hue varies least: its mean hue as ratios (r: R/G, b: B/G, the exponentials of the mean logs) and whether there
// was one (found: 1 or 0).
STAGE_ROW_LOOP void PickWindows(const float* __restrict box, size_t plane, const size_t (&offsets)[5], int x0, int x1,
                                float* __restrict r, float* __restrict b, float* __restrict found) {
  const float* n[5];
  for (int k = 0; k < 5; ++k) n[k] = box + offsets[k];
  for (int x = x0; x < x1; ++x) {
    float least = std::numeric_limits<float>::infinity(), best_r = 0, best_b = 0, any = 0;
    for (int k = 0; k < 5; ++k) {
      const float count = n[k][x];
      const float mr = n[k][plane + x] / count, mb = n[k][2 * plane + x] / count;
      const float var = n[k][3 * plane + x] / count - (mr * mr + mb * mb);
      const bool take = count >= kMinSites && var < least;
      least = take ? var : least;
      best_r = take ? mr : best_r;
      best_b = take ? mb : best_b;
      any = count >= kMinSites ? 1.f : any;
    }
    r[x] = PortableExp(best_r);
    b[x] = PortableExp(best_b);
    found[x] = any;
  }
}

}  // namespace

void FlagImplausibleRgbAlbedo(float max_albedo, PhotometricMaps* m) {
  for (size_t i = 0; i < m->flags.size(); ++i) {
    if (m->flags[i] & kLowSignal) continue;
    float* a = &m->albedo.pixels[3 * i];
    if (a[0] <= max_albedo && a[1] <= max_albedo && a[2] <= max_albedo) continue;  // NaN fails too
    m->flags[i] |= kImplausible;
    a[0] = a[1] = a[2] = 0.f;
    if (!m->confidence.pixels.empty()) m->confidence.pixels[i] = 0.f;
  }
}

void DemosaicAlbedo(const Mosaic& mosaic, const float* own, float max_albedo, int threads, PhotometricMaps* m) {
  const int w = m->width, h = m->height;
  // An albedo no surface has is left out before anything borrows from it.
  ParallelRows(h, threads, [&](int y0, int y1) {
    for (size_t i = static_cast<size_t>(y0) * w; i < static_cast<size_t>(y1) * w; ++i) {
      if ((m->flags[i] & kLowSignal) == 0 && !(own[i] <= max_albedo)) {
        m->flags[i] |= kImplausible;
        if (!m->confidence.pixels.empty()) m->confidence.pixels[i] = 0.f;
      }
    }
  });
  const uint8_t* flags = m->flags.data();
  auto solved_at = [&](size_t i) { return (flags[i] & kNotSolved) == 0; };
  if (mosaic.mono) {
    ParallelRows(h, threads, [&](int y0, int y1) {
      for (size_t i = static_cast<size_t>(y0) * w; i < static_cast<size_t>(y1) * w; ++i) {
        float* a = &m->albedo.pixels[3 * i];
        a[0] = a[1] = a[2] = solved_at(i) ? own[i] : 0.f;
      }
    });
    return;
  }
  std::vector<uint8_t> colors(2 * static_cast<size_t>(w));  // each column's colour on even rows and on odd ones
  for (int x = 0; x < w; ++x) {
    for (int parity = 0; parity < 2; ++parity) {
      colors[parity * static_cast<size_t>(w) + x] = static_cast<uint8_t>(mosaic.Color(x, parity));
    }
  }
  // The colour beside a green site: the red or blue of its row.
  auto beside_green = [&](int y) { return mosaic.Color(0, y) == 1 ? mosaic.Color(1, y) : mosaic.Color(0, y); };
  // A row's solved pixels lie in [lo, hi) (lo == hi: none).
  auto row_span = [&](int y) {
    if (y < 0 || y >= h) return std::pair<int, int>(0, 0);
    const uint8_t* f = &flags[static_cast<size_t>(y) * w];
    auto is_solved = [](uint8_t v) { return (v & kNotSolved) == 0; };
    const uint8_t* first = std::find_if(f, f + w, is_solved);
    if (first == f + w) return std::pair<int, int>(0, 0);
    const uint8_t* last =
        std::find_if(std::make_reverse_iterator(f + w), std::make_reverse_iterator(first), is_solved).base();
    return std::pair<int, int>(static_cast<int>(first - f), static_cast<int>(last - f));
  };
  const int chunks = (h + kChunk - 1) / kChunk;
  ParallelRows(chunks, threads, [&](int c0, int c1) {
    static thread_local DemosaicBuffers buf;
    if (buf.stride != static_cast<size_t>(w) + 2 * kPad) buf.Resize(w);
    const size_t stride = buf.stride;
    for (int chunk = c0; chunk < c1; ++chunk) {
      const int y0 = chunk * kChunk, y1 = std::min(h, y0 + kChunk);
      // Which rows have a solved pixel, from y0 - kHalo (index 0) to y1 + kHalo, and the columns [xlo, xhi) that hold
      // every solved pixel of those rows. Each step below works only where the next reads (the planes hold the last
      // chunk's values elsewhere; their padding columns stay 0): the albedo and its log over [xlo - kPad - 1,
      // xhi + kPad + 1), the hue and its sums down the columns over [xlo - kPad, xhi + kPad), the window sums over
      // [xlo - kShift, xhi + kShift), the output over [xlo, xhi); all within the image's columns.
      bool any[kChunk + 2 * kHalo];
      int xlo = w, xhi = 0;
      for (int y = y0 - kHalo; y < y1 + kHalo; ++y) {
        const auto [lo, hi] = row_span(y);
        any[y - y0 + kHalo] = lo < hi;
        if (lo < hi) {
          xlo = std::min(xlo, lo);
          xhi = std::max(xhi, hi);
        }
      }
      if (!std::any_of(any + kHalo, any + kHalo + (y1 - y0), [](bool b) { return b; })) {
        for (int y = y0; y < y1; ++y) StreamZeros(m->albedo.at(0, y), 3 * static_cast<size_t>(w));
        continue;
      }
      const int l0 = std::max(0, xlo - kPad - 1), l1 = std::min(w, xhi + kPad + 1);
      const int q0 = std::max(0, xlo - kPad), q1 = std::min(w, xhi + kPad);
      // The albedo and its log where it is usable (solved, positive and finite).
      for (int y = y0 - kHalo; y < y1 + kHalo; ++y) {
        const size_t li = static_cast<size_t>(y - y0 + kHalo) * stride + kPad;
        float* va = &buf.values[li];
        float* lg = &buf.logs[li];
        float* us = &buf.usable[li];
        if (!any[y - y0 + kHalo]) {
          std::fill(va + l0, va + l1, 0.f);
          std::fill(lg + l0, lg + l1, 0.f);
          std::fill(us + l0, us + l1, 0.f);
          continue;
        }
        const size_t r0 = static_cast<size_t>(y) * w;
        LogRow(own + r0, flags + r0, l0, l1, va, lg, us);
      }
      // Per usable site, its hue: log(R/G) and log(B/G), its own colour's log albedo and the others' means over its
      // usable neighbours of that colour (the 2 beside it, the 2 above and below, the 4 diagonal), none missing.
      const size_t plane_q = static_cast<size_t>(kChunk + 2 * kPad) * stride;
      for (int y = y0 - kPad; y < y1 + kPad; ++y) {
        float* q[4];
        for (int k = 0; k < 4; ++k) q[k] = &buf.hue[k * plane_q + static_cast<size_t>(y - y0 + kPad) * stride + kPad];
        const size_t li = static_cast<size_t>(y - y0 + kHalo) * stride + kPad;
        const float* lm = &buf.logs[li];
        const float* um = &buf.usable[li];
        if (!any[y - y0 + kHalo]) {
          for (int k = 0; k < 4; ++k) std::fill(q[k] + q0, q[k] + q1, 0.f);
          continue;
        }
        const uint8_t* color = &colors[static_cast<size_t>(y & 1) * w];
        const int beside = beside_green(y);
        HueRow(lm, um, stride, color, beside, q0, q1, q[0], q[1], q[2], q[3]);
      }
      // The hue planes summed over every 5 x 5 window: down the columns, then along the rows.
      const size_t plane_v = static_cast<size_t>(kChunk + 2 * kShift) * stride;
      for (int k = 0; k < 4; ++k) {
        for (int y = y0 - kShift; y < y1 + kShift; ++y) {
          const float* in = &buf.hue[k * plane_q + static_cast<size_t>(y - y0 + kPad) * stride];
          float* col = &buf.column[k * plane_v + static_cast<size_t>(y - y0 + kShift) * stride];
          float* out = &buf.box[k * plane_v + static_cast<size_t>(y - y0 + kShift) * stride];
          for (size_t x = kPad + q0; x < kPad + static_cast<size_t>(q1); ++x) {
            float s = in[x - 2 * stride];
            s += in[x - stride];
            s += in[x];
            s += in[x + stride];
            s += in[x + 2 * stride];
            col[x] = s;
          }
          const size_t b0 = kPad + std::max(-kShift, xlo - kShift), b1 = kPad + std::min(w + kShift, xhi + kShift);
          for (size_t x = b0; x < b1; ++x) {
            float s = col[x - 2];
            s += col[x - 1];
            s += col[x];
            s += col[x + 1];
            s += col[x + 2];
            out[x] = s;
          }
        }
      }
      // Per solved pixel, of the five windows (centred, and kShift to the left, right, above and below) the one whose
      // hue varies least. Each colour the pixel does not measure: kHueWeight of its own albedo times that window's
      // mean hue (the pixel's texture, with its noise), the rest the mean of its usable neighbours of that colour
      // (their noise averaged, the texture blurred); the neighbours alone where no window has kMinSites hue samples, 0
      // for a colour with none.
      for (int y = y0; y < y1; ++y) {
        if (!any[y - y0 + kHalo]) {
          StreamZeros(m->albedo.at(0, y), 3 * static_cast<size_t>(w));
          continue;
        }
        const size_t r0 = static_cast<size_t>(y) * w;
        const uint8_t* color = &colors[static_cast<size_t>(y & 1) * w];
        const int beside = beside_green(y);
        const size_t centre = static_cast<size_t>(y - y0 + kShift) * stride + kPad;
        const size_t offsets[5] = {centre, centre - kShift, centre + kShift, centre - kShift * stride,
                                   centre + kShift * stride};
        const size_t li = static_cast<size_t>(y - y0 + kHalo) * stride + kPad;
        const float* vm = &buf.values[li];
        const float* um = &buf.usable[li];
        // The windows, across the row (no branches, so that it runs in vector lanes): the least varying hue's means.
        float* ratio_r = buf.pick.data();
        float* ratio_b = ratio_r + w;
        float* found = ratio_b + w;
        PickWindows(buf.box.data(), plane_v, offsets, xlo, xhi, ratio_r, ratio_b, found);
        float* const planar = buf.planar.data();
        AlbedoRow(own + r0, flags + r0, vm, um, stride, color, beside, ratio_r, ratio_b, found, xlo, xhi, planar,
                  planar + w, planar + 2 * static_cast<size_t>(w));
        std::fill(buf.row.begin(), buf.row.begin() + 3 * static_cast<size_t>(xlo), 0.f);
        std::fill(buf.row.begin() + 3 * static_cast<size_t>(xhi), buf.row.end(), 0.f);
        for (int x = xlo; x < xhi; ++x) {
          for (int k = 0; k < 3; ++k) buf.row[3 * static_cast<size_t>(x) + k] = planar[k * static_cast<size_t>(w) + x];
        }
        StreamCopy(m->albedo.at(0, y), buf.row.data(), buf.row.size());
      }
    }
    StreamFence();
  });
}

}  // namespace stage::processing::internal
