// Tile-based multi-threaded CPU rasterizer: forward and full backward (incl. camera gradient).
// Loops only: the per-Gaussian maths lives in ../common/{math,sh,raster}.h (and its vector twin in
// preprocess_simd.h). See ../ops.h for the API; DESIGN.md "CPU kernel" for the layout.
//
// Pipeline (forward; steps 1-2 over fixed contiguous chunks of Gaussians, one per thread):
//   1. preprocess: cull, project, cov2D/conic, radius, tile rect, colour, on vectors of kLanes
//      Gaussians (preprocess_simd.h; the same bits as the scalar preprocess_gaussian); writes the
//      geom record and a 32-byte tile footprint (rect, tile count, depth key) per Gaussian; then
//      the slot offsets and the visible Gaussians in index order.
//   2. binning (binning.h): the visible Gaussians radix-sorted by view depth (stable -> ties by
//      index), then a stable counting sort by tile fills the per-tile lists in that order.
//      Entry = (gaussian, slot); the slot (offsets[g] + position in g's rect) is where the
//      backward of that tile writes g's partial gradient, so no two threads ever write the same
//      memory.
//   3. render, parallel over tiles (dynamic): each tile walks its list front to back, and for each
//      Gaussian updates the pixel rows that its alpha >= 1/255 ellipse can reach and that still
//      have an active pixel (kRowVecs vectors a row, branch-free masked updates; exp by a
//      vectorised polynomial); stops when every pixel of the tile is done.
// Backward:
//   4. per tile, walk the list back to front from the last contributor (upstream renderCUDA bwd,
//      T recovered by division), over the rows that hold a pixel the entry reaches; reduce each
//      Gaussian's per-pixel terms over the tile in a fixed order (rows, then lanes by a fixed tree:
//      simd.h hsum), store them in its slot and mark
//      the slot live.
//   5. per Gaussian (parallel over fixed-size blocks): sum its live slots in tile order (a
//      Gaussian with none reaches no pixel and is skipped), chain through the per-Gaussian VJPs;
//      camera terms summed per block in double, then blocks in order. Without
//      compute_gaussian_grads only the camera terms are computed (no Gaussian gradient is
//      allocated, zero-filled or written); with neither flag the step is skipped.
// Temporaries live in per-thread scratch arrays kept between calls, the large outputs in blocks
// recycled through a process-wide cache (cpu_support.h): a render of a large model does not fault
// in and zero fresh pages. GRP_CPU_TIMING=1 prints each call's phase times to stderr.
#include <ATen/ATen.h>
#include <ATen/Parallel.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <memory>
#include <vector>

#include "../common/config.h"
#include "../common/math.h"
#include "../common/raster.h"
#include "../common/raster_args_torch.h"
#include "../common/sh.h"
#include "../ops.h"
#include "binning.h"
#include "cpu_support.h"
#include "preprocess_simd.h"
#include "simd.h"

namespace grp {
namespace {

// Geom record layout (kG*), kSlot, kCamGrad, RasterArgs: ../common/raster.h.
constexpr int64_t kGaussBlock = 1024;        // fixed block size of the per-Gaussian backward
constexpr int kPrefetch = 8;                 // tile-list entries prefetched ahead

// Runs fn(i) for i in [0, n) on the ATen pool with dynamic scheduling (results never depend on
// which thread ran which i).
template <typename F>
void parallel_dynamic(int64_t n, const F& fn) {
  if (n <= 0) return;
  const int64_t nt = std::min<int64_t>(at::get_num_threads(), n);
  if (nt <= 1 || at::in_parallel_region()) {
    for (int64_t i = 0; i < n; ++i) fn(i);
    return;
  }
  std::atomic<int64_t> next{0};
  at::parallel_for(0, nt, 1, [&](int64_t, int64_t) {
    for (;;) {
      const int64_t i = next.fetch_add(1, std::memory_order_relaxed);
      if (i >= n) break;
      fn(i);
    }
  });
}

void check_tensor(const at::Tensor& t, const char* name, std::initializer_list<int64_t> shape) {
  check_float_tensor(t, name, shape, [](const at::Tensor& x, const char* n) {
    TORCH_CHECK(x.device().is_cpu(), n, " must be a CPU tensor, got ", x.device());
  });
}

void check_int_tensor(const at::Tensor& t, const char* name, at::ScalarType st) {
  TORCH_CHECK(t.defined() && t.device().is_cpu() && t.scalar_type() == st && t.is_contiguous(),
              name, " must be a contiguous CPU tensor of type ", st);
}

// ------------------------------------------------------------------------------------------------
// 1. Preprocess, over fixed chunks of Gaussians: the geom record, the radius and the tile
// footprint (rect, tile count, depth key) of every Gaussian; per chunk, the visible Gaussians and
// their tiles.
// ------------------------------------------------------------------------------------------------
struct ChunkCounts {
  int64_t visible = 0;  // Gaussians with radius > 0
  int64_t tiles = 0;    // their (tile, Gaussian) pairs
};

// Narrows the tile range [t0, t1) to the tiles holding a pixel of [0, npix) within `half` of
// `centre` (the alpha >= 1/255 box of the geom record, with the float arithmetic of box_range,
// which the tile loops apply); an empty range when none.
inline void clip_to_box(float centre, float half, int tile_px, int npix, int32_t& t0,
                        int32_t& t1) {
  if (!(half < INFINITY)) {  // NaN box: reaches no pixel; an infinite one: no narrowing
    if (!(half >= 0.f)) t1 = t0;
    return;
  }
  const double lo = std::max(0.0, std::ceil((double)(centre - half)));
  const double hi = std::min((double)(npix - 1), std::floor((double)(centre + half)));
  if (!(half >= 0.f) || lo > hi) {
    t1 = t0;
    return;
  }
  t0 = std::max(t0, (int32_t)(lo / tile_px));
  t1 = std::max(t0, std::min(t1, (int32_t)(hi / tile_px) + 1));
}

// Stores the preprocess result of Gaussian g (its record is at gd) and counts it. Its tile rect
// (the 3-sigma square of upstream, which the radius keeps) is narrowed to the tiles that its
// alpha >= 1/255 box reaches: the tile loops skip every pixel outside that box, so the lists
// lose only entries that update nothing (the images and gradients are the same bits) and a faint
// or elongated Gaussian is walked by fewer tiles.
inline void store_preprocessed(const RasterArgs& in, int64_t g, const PreprocessResult& r,
                               const float* gd, int32_t* radii, cpu::TileFootprint* footprints,
                               ChunkCounts& n) {
  radii[g] = r.radius;
  cpu::TileFootprint& f = footprints[g];
  for (int k = 0; k < 4; ++k) f.rect[k] = r.rect[k];
  if (r.radius > 0) {
    clip_to_box(gd[kGPx], gd[kGBoxX], kBlockX, in.W, f.rect[0], f.rect[2]);
    clip_to_box(gd[kGPy], gd[kGBoxY], kBlockY, in.H, f.rect[1], f.rect[3]);
  }
  const int64_t area = cpu::footprint_area(f);
  f.offset = area;
  std::memcpy(&f.depth_key, gd + kGZ, 4);
  if (area > 0) {
    ++n.visible;
    n.tiles += area;
  }
}

void preprocess(const RasterArgs& in, int nchunks, float* geom, int32_t* radii,
                cpu::TileFootprint* footprints, ChunkCounts* counts) {
  cpu::for_each_chunk(nchunks, [&](int c) {
    ChunkCounts n;
    const int64_t e = cpu::chunk_begin(in.P, c + 1, nchunks);
    int64_t g = cpu::chunk_begin(in.P, c, nchunks);
    if (in.cov3d == nullptr) {  // whole vectors of Gaussians (preprocess_simd.h)
      PreprocessResult res[cpu::kLanes];
      for (; g + cpu::kLanes <= e; g += cpu::kLanes) {
        cpu::preprocess_lanes(in, g, geom, res);
        for (int i = 0; i < cpu::kLanes; ++i)
          store_preprocessed(in, g + i, res[i], geom + kGStride * (g + i), radii, footprints, n);
      }
    }
    for (; g < e; ++g) {
      float* gd = geom + kGStride * g;
      const PreprocessResult r = preprocess_gaussian(in, g, in.viewmatrix, in.projmatrix, gd);
      store_preprocessed(in, g, r, gd, radii, footprints, n);
    }
    counts[c] = n;
  });
}

// The slot offsets (offsets[g + 1] = offsets[g] + tiles of g; also into each footprint) and the
// visible Gaussians in index order with their depth keys (keys / vals); returns their number.
int64_t compact_visible(int64_t P, int nchunks, const ChunkCounts* counts,
                        cpu::TileFootprint* footprints, int64_t* offsets, uint32_t* keys,
                        int32_t* vals) {
  std::vector<ChunkCounts> base(nchunks + 1);
  for (int c = 0; c < nchunks; ++c) {
    base[c + 1].visible = base[c].visible + counts[c].visible;
    base[c + 1].tiles = base[c].tiles + counts[c].tiles;
  }
  offsets[0] = 0;
  cpu::for_each_chunk(nchunks, [&](int c) {
    int64_t pos = base[c].visible, slot = base[c].tiles;
    const int64_t e = cpu::chunk_begin(P, c + 1, nchunks);
    for (int64_t g = cpu::chunk_begin(P, c, nchunks); g < e; ++g) {
      cpu::TileFootprint& f = footprints[g];
      const int64_t tiles = f.offset;
      f.offset = slot;
      slot += tiles;
      offsets[g + 1] = slot;
      if (tiles > 0) {
        keys[pos] = f.depth_key;
        vals[pos] = (int32_t)g;
        ++pos;
      }
    }
  });
  return base[nchunks].visible;
}

// Temporaries of the forward, kept by the calling thread between calls (cpu_support.h).
struct ForwardScratch {
  cpu::ScratchArray<cpu::TileFootprint> footprints, sorted;
  cpu::ScratchArray<uint32_t> keys, keys2;
  cpu::ScratchArray<int32_t> vals, vals2;
};

// ------------------------------------------------------------------------------------------------
// A tile row is kRowVecs vectors of the machine's width (simd.h).
// ------------------------------------------------------------------------------------------------
using cpu::kLanes;
using cpu::splat;
using cpu::splat_i;
using cpu::vexp_nonpos;
using cpu::vf;
using cpu::vi;
constexpr int kRowVecs = kBlockX / kLanes;
static_assert(kRowVecs * kLanes == kBlockX, "a tile row is a whole number of vectors");

// True when some lane of v[0..kRowVecs) is non-zero.
inline bool any_lane(const vi* v) {
  vi acc = v[0];
  for (int h = 1; h < kRowVecs; ++h) acc |= v[h];
  int32_t any = 0;
  for (int i = 0; i < kLanes; ++i) any |= acc[i];
  return any != 0;
}

// Bits r0..r1 (0 <= r0 <= r1 < 32) set.
inline uint32_t row_bits(int r0, int r1) {
  return (uint32_t)((((uint64_t)1 << (r1 + 1)) - 1) & ~(((uint64_t)1 << r0) - 1));
}

// Integer offsets [i0, i1] within [0, n) of origin + i that lie within `half` of `centre` (an
// alpha box's half extent, negative or NaN: nowhere); false when none.
inline bool box_range(float centre, float half, int origin, int n, int& i0, int& i1) {
  if (!(half >= 0.f)) return false;
  float flo = centre - half, fhi = centre + half;
  if (flo < (float)origin) flo = (float)origin;
  if (fhi > (float)(origin + n - 1)) fhi = (float)(origin + n - 1);
  if (!(flo <= fhi)) return false;
  i0 = (int)std::ceil(flo) - origin;
  i1 = (int)std::floor(fhi) - origin;
  return i0 <= i1;
}

// Rows [r0, r1] of the tile that Gaussian gd can reach (alpha >= 1/255); false when none.
inline bool row_range(const float* gd, int y0, int nrows, int& r0, int& r1) {
  return box_range(gd[kGPy], gd[kGBoxY], y0, nrows, r0, r1);
}

// Vectors [h0, h1] of a tile row holding the columns that Gaussian gd can reach; false when
// none. The other vectors' lanes all fail the alpha test, so skipping them is exact, as
// row_range's rows are.
inline bool vec_range(const float* gd, int x0, int ncols, int& h0, int& h1) {
  if (!box_range(gd[kGPx], gd[kGBoxX], x0, ncols, h0, h1)) return false;
  h0 /= kLanes;
  h1 /= kLanes;
  return true;
}

// One vector of a tile row of a Gaussian (upstream renderCUDA): power = -d^T conic d / 2 at its
// pixels (dx = px - x per lane, qx = conic.a dx^2, dy = py - y), G = exp(power), oG = o G and
// alpha = min(kAlphaMax, oG). Shared by the forward and the backward tile loops.
inline void row_alpha(const vf& qx, const vf& dx, float dy, float cB, float cC, float o, vf& power,
                      vf& G, vf& oG, vf& alpha) {
  power = -0.5f * (qx + cC * dy * dy) - cB * dx * dy;
  G = vexp_nonpos(power);
  oG = o * G;
  alpha = oG < splat(kAlphaMax) ? oG : splat(kAlphaMax);
}

// Pixel origin and size of tile `tile` (edge tiles are clipped to the image).
inline void tile_extent(const RasterArgs& in, int64_t tile, int& x0, int& y0, int& ncols,
                        int& nrows) {
  const int tx = (int)(tile % in.grid_x), ty = (int)(tile / in.grid_x);
  x0 = tx * kBlockX;
  y0 = ty * kBlockY;
  ncols = std::min(kBlockX, in.W - x0);
  nrows = std::min(kBlockY, in.H - y0);
}

// The x coordinates of the tile's columns, one vector per piece of a row.
inline void column_coords(int x0, vf* pixx) {
  for (int c = 0; c < kBlockX; ++c) pixx[c / kLanes][c % kLanes] = (float)(x0 + c);
}

// ------------------------------------------------------------------------------------------------
// 3. Forward render of one tile
// ------------------------------------------------------------------------------------------------
// Forward pixel state of one vector of a tile row.
struct FwdPix {
  vf T, C0, C1, C2, ID, DA;
  vi act, last;
};

// Blends Gaussian gd (list position jrel) into one vector of a row; returns the lanes that stop.
inline vi blend_vec(FwdPix& R, const vf& qx, const vf& dx, float dy, const float* gd, int32_t jrel) {
  vf power, G, oG, alpha;
  row_alpha(qx, dx, dy, gd[kGConB], gd[kGConC], gd[kGOpacity], power, G, oG, alpha);
  const vi valid = R.act & ~(power > splat(0.f)) & ~(alpha < splat(kAlphaMin));
  const vf Tc = R.T;
  const vf testT = Tc * (1.f - alpha);
  const vi stop = valid & (testT < splat(kTransmittanceMin));
  const vi contrib = valid & ~stop;
  const vf w = contrib ? alpha * Tc : splat(0.f);
  R.C0 += gd[kGR] * w;
  R.C1 += gd[kGG] * w;
  R.C2 += gd[kGB] * w;
  R.ID += gd[kGInvZ] * w;
  R.DA += gd[kGZ] * w;
  R.T = contrib ? testT : Tc;
  R.last = contrib ? splat_i(jrel) : R.last;
  R.act &= ~stop;
  return stop;
}

// Writes the tile's pixels (rows[r][h] holds columns h kLanes ..).
void store_tile(const RasterArgs& in, const FwdPix (*rows)[kRowVecs], int x0, int y0, int ncols,
                int nrows, const RenderOutputs& out) {
  const int64_t HW = (int64_t)in.H * in.W;
  for (int r = 0; r < nrows; ++r) {
    for (int c = 0; c < ncols; ++c) {
      const FwdPix& R = rows[r][c / kLanes];
      const int i = c % kLanes;
      const int64_t pix = (int64_t)(y0 + r) * in.W + (x0 + c);
      const float Tp = R.T[i];
      out.color[pix] = R.C0[i] + Tp * in.bg[0];
      out.color[HW + pix] = R.C1[i] + Tp * in.bg[1];
      out.color[2 * HW + pix] = R.C2[i] + Tp * in.bg[2];
      out.invdepth[pix] = R.ID[i];
      out.depth_acc[pix] = R.DA[i];
      out.alpha[pix] = 1.f - Tp;
      out.final_T[pix] = Tp;
      out.last[pix] = R.last[i];
    }
  }
}

void render_tile(const RasterArgs& in, int64_t tile, const float* geom, const int32_t* binning,
                 const int32_t* tile_ranges, const RenderOutputs& out) {
  int x0, y0, ncols, nrows;
  tile_extent(in, tile, x0, y0, ncols, nrows);
  FwdPix rows[kBlockY][kRowVecs];  // one record per vector of a row: a row's state together in L1
  vf pixx[kRowVecs];
  column_coords(x0, pixx);
  for (int r = 0; r < kBlockY; ++r)
    for (int h = 0; h < kRowVecs; ++h) {
      FwdPix& R = rows[r][h];
      for (int i = 0; i < kLanes; ++i) R.act[i] = (r < nrows && h * kLanes + i < ncols) ? -1 : 0;
      R.T = splat(1.f);
      R.C0 = R.C1 = R.C2 = R.ID = R.DA = splat(0.f);
      R.last = splat_i(-1);
    }
  // Rows with an active pixel: the tile is done when none is left, and the rows of a Gaussian
  // without one are skipped (exact: an inactive pixel's state never changes).
  uint32_t active_rows = ncols > 0 ? row_bits(0, nrows - 1) : 0u;
  const int32_t start = tile_ranges[tile], end = tile_ranges[tile + 1];
  for (int32_t j = start; j < end && active_rows != 0; ++j) {
    if (j + kPrefetch < end) __builtin_prefetch(geom + kGStride * (int64_t)binning[2 * (j + kPrefetch)]);
    const float* gd = geom + kGStride * (int64_t)binning[2 * j];
    int r0, r1, h0, h1;
    if (!row_range(gd, y0, nrows, r0, r1) || !vec_range(gd, x0, ncols, h0, h1)) continue;
    const uint32_t todo = active_rows & row_bits(r0, r1);
    if (todo == 0) continue;
    const float px = gd[kGPx], py = gd[kGPy], cA = gd[kGConA];
    vf dx[kRowVecs], qx[kRowVecs];
    for (int h = h0; h <= h1; ++h) {
      dx[h] = px - pixx[h];
      qx[h] = cA * dx[h] * dx[h];
    }
    vi stopped[kRowVecs] = {};
    for (uint32_t m = todo; m != 0; m &= m - 1) {
      const int r = __builtin_ctz(m);
      const float dy = py - (float)(y0 + r);
      for (int h = h0; h <= h1; ++h)
        stopped[h] |= blend_vec(rows[r][h], qx[h], dx[h], dy, gd, j - start);
    }
    if (!any_lane(stopped)) continue;
    for (uint32_t m = todo; m != 0; m &= m - 1) {
      const int r = __builtin_ctz(m);
      vi act[kRowVecs];
      for (int h = 0; h < kRowVecs; ++h) act[h] = rows[r][h].act;
      if (!any_lane(act)) active_rows &= ~(1u << r);
    }
  }
  store_tile(in, rows, x0, y0, ncols, nrows, out);
}

// ------------------------------------------------------------------------------------------------
// 4. Backward of one tile: the tile's background terms dbg_tile[3] and (unless slots == nullptr)
// the slot of every entry that reaches one of the tile's pixels, marked in live[slot] (the
// caller zeroes live); entries behind every pixel's last contributor, and those whose ellipse
// misses the tile, are not written (their slots would be zeros).
// kOpacitySlot / kColourSlot = false: slot 5 (opacity) / slots 6..8 (colour) are written as 0
// without being accumulated (for a caller that never reads them). The other slots come from the
// same statements in the same order in every variant (independent accumulators, explicit vector
// types: nothing for the vectoriser to regroup); tests/gaussian_renderer_pose/
// test_pose_only_backward.py checks that the camera gradient is the same bits in each.
// ------------------------------------------------------------------------------------------------
// Backward pixel state of one vector of a tile row (upstream renderCUDA backward, features = r,
// g, b, 1/z, z): T: transmittance, recovered back to front; lastA: alpha of the Gaussian behind;
// accdot = dL/dpixel . (features blended behind, accum_rec upstream); lfdot = dL/dpixel .
// (features of the Gaussian behind); dp = dL/dpixel per feature; kbg = T_final (dL/dalpha_out -
// bg . dL/dcolor), enters dL/dalpha_i as kbg / (1 - alpha_i).
struct BwdPix {
  vf T, lastA, kbg, accdot, lfdot;
  vf dp[kNumFeat];
  vi last;
};

// The per-lane sums of one entry's terms over the rows it reaches (slot order of kSlot).
struct SlotAcc {
  vf v[kSlot];
};

// Loads one tile's pixel state; returns each row's largest last contributor in row_last and adds
// the background terms to dbg.
void load_bwd_tile(const RasterArgs& in, const float* final_T, const int32_t* last_contrib,
                   const GradImages& gin, int x0, int y0, int ncols, int nrows,
                   BwdPix (*rows)[kRowVecs], int32_t* row_last, double* dbg) {
  const int64_t HW = (int64_t)in.H * in.W;
  for (int r = 0; r < kBlockY; ++r) {
    for (int h = 0; h < kRowVecs; ++h) {
      BwdPix& R = rows[r][h];
      R.T = R.lastA = R.kbg = R.accdot = R.lfdot = splat(0.f);
      R.last = splat_i(-1);
      for (int k = 0; k < kNumFeat; ++k) R.dp[k] = splat(0.f);
    }
    row_last[r] = -1;
    if (r >= nrows) continue;
    for (int c = 0; c < ncols; ++c) {
      BwdPix& R = rows[r][c / kLanes];
      const int i = c % kLanes;
      const int64_t pix = (int64_t)(y0 + r) * in.W + (x0 + c);
      const float Tf = final_T[pix];
      R.T[i] = Tf;
      R.last[i] = last_contrib[pix];
      row_last[r] = std::max(row_last[r], last_contrib[pix]);
      const float g0 = gin.color[pix], g1 = gin.color[HW + pix], g2 = gin.color[2 * HW + pix];
      R.dp[0][i] = g0;
      R.dp[1][i] = g1;
      R.dp[2][i] = g2;
      R.dp[3][i] = gin.invdepth[pix];
      R.dp[4][i] = gin.depth_acc[pix];
      const float bgdot = in.bg[0] * g0 + in.bg[1] * g1 + in.bg[2] * g2;
      R.kbg[i] = Tf * (gin.alpha[pix] - bgdot);
      dbg[0] += (double)Tf * (double)g0;
      dbg[1] += (double)Tf * (double)g1;
      dbg[2] += (double)Tf * (double)g2;
    }
  }
}

// Backward of Gaussian gd (list position jrel) through one vector of a row: updates the pixel
// state and adds the entry's terms to acc.
template <bool kOpacitySlot, bool kColourSlot>
inline void unblend_vec(BwdPix& R, const vf& qx, const vf& dx, float dy, const float* gd,
                        int32_t jrel, SlotAcc& acc) {
  const float cA = gd[kGConA], cB = gd[kGConB], cC = gd[kGConC], o = gd[kGOpacity];
  const float f[kNumFeat] = {gd[kGR], gd[kGG], gd[kGB], gd[kGInvZ], gd[kGZ]};
  vf power, G, oG, alpha;
  row_alpha(qx, dx, dy, cB, cC, o, power, G, oG, alpha);
  const vi valid = (splat_i(jrel) <= R.last) & ~(power > splat(0.f)) & ~(alpha < splat(kAlphaMin));
  const vf a = valid ? alpha : splat(0.f);
  const vf inv_1ma = 1.f / (1.f - a);
  const vf Tn = R.T * inv_1ma;  // unchanged where invalid (a = 0)
  const vf w = a * Tn;
  vf fdot = f[0] * R.dp[0];
  if (kColourSlot) acc.v[6] += w * R.dp[0];
  for (int k = 1; k < kNumFeat; ++k) {
    fdot += f[k] * R.dp[k];
    if (kColourSlot || k >= 3) acc.v[6 + k] += w * R.dp[k];
  }
  const vf la = R.lastA;
  const vf ndot = la * R.lfdot + (1.f - la) * R.accdot;
  const vf dLda = (fdot - ndot) * Tn + R.kbg * inv_1ma;
  R.T = Tn;
  R.accdot = valid ? ndot : R.accdot;
  R.lfdot = valid ? fdot : R.lfdot;
  R.lastA = valid ? alpha : la;
  // alpha = min(0.99, o G): no gradient to o G where the clamp is active
  const vi pass = valid & ~(oG > splat(kAlphaMax));
  const vf dLdG = pass ? o * dLda : splat(0.f);
  if (kOpacitySlot) acc.v[5] += pass ? G * dLda : splat(0.f);
  const vf gdx = G * dx, gdy = G * dy;
  acc.v[0] += dLdG * (-gdx * cA - gdy * cB);
  acc.v[1] += dLdG * (-gdy * cC - gdx * cB);
  acc.v[2] += -0.5f * gdx * dx * dLdG;
  acc.v[3] += -gdx * dy * dLdG;
  acc.v[4] += -0.5f * gdy * dy * dLdG;
}

template <bool kOpacitySlot, bool kColourSlot>
void backward_tile(const RasterArgs& in, int64_t tile, const float* geom, const int32_t* binning,
                   const int32_t* tile_ranges, const float* final_T, const int32_t* last_contrib,
                   const GradImages& gin, float* slots, uint8_t* live, double* dbg_tile) {
  int x0, y0, ncols, nrows;
  tile_extent(in, tile, x0, y0, ncols, nrows);
  BwdPix rows[kBlockY][kRowVecs];
  int32_t row_last[kBlockY];  // per row, the largest last contributor (-1: none)
  double dbg[3] = {0, 0, 0};
  load_bwd_tile(in, final_T, last_contrib, gin, x0, y0, ncols, nrows, rows, row_last, dbg);
  for (int k = 0; k < 3; ++k) dbg_tile[k] = dbg[k];
  if (slots == nullptr) return;
  int32_t maxlast = -1;
  for (int r = 0; r < nrows; ++r) maxlast = std::max(maxlast, row_last[r]);
  vf pixx[kRowVecs];
  column_coords(x0, pixx);
  const int32_t start = tile_ranges[tile];
  for (int32_t j = start + maxlast; j >= start; --j) {
    if (j - kPrefetch >= start) {
      __builtin_prefetch(geom + kGStride * (int64_t)binning[2 * (j - kPrefetch)]);
      __builtin_prefetch(slots + (int64_t)binning[2 * (j - kPrefetch) + 1] * kSlot, 1);
    }
    const float* gd = geom + kGStride * (int64_t)binning[2 * j];
    int r0, r1, h0, h1;
    if (!row_range(gd, y0, nrows, r0, r1) || !vec_range(gd, x0, ncols, h0, h1)) continue;
    // Rows with a pixel that entry j reaches (j at or before its last contributor); the others
    // would add zeros (exact to skip).
    uint32_t todo = 0;
    for (int r = r0; r <= r1; ++r)
      if (row_last[r] >= j - start) todo |= 1u << r;
    if (todo == 0) continue;
    const float px = gd[kGPx], py = gd[kGPy], cA = gd[kGConA];
    vf dx[kRowVecs], qx[kRowVecs];
    SlotAcc acc[kRowVecs];
    for (int h = h0; h <= h1; ++h) {
      dx[h] = px - pixx[h];
      qx[h] = cA * dx[h] * dx[h];
      for (int k = 0; k < kSlot; ++k) acc[h].v[k] = splat(0.f);
    }
    for (uint32_t m = todo; m != 0; m &= m - 1) {
      const int r = __builtin_ctz(m);
      const float dy = py - (float)(y0 + r);
      for (int h = h0; h <= h1; ++h)
        unblend_vec<kOpacitySlot, kColourSlot>(rows[r][h], qx[h], dx[h], dy, gd, j - start,
                                                acc[h]);
    }
    // Each slot: the row's vectors added lane-wise in order, then the lanes by a fixed tree (the
    // skipped vectors' lanes would add zeros).
    const int64_t slot_id = binning[2 * j + 1];
    float* slot = slots + slot_id * kSlot;
    for (int k = 0; k < kSlot; ++k) {
      vf t = acc[h0].v[k];
      for (int h = h0 + 1; h <= h1; ++h) t += acc[h].v[k];
      slot[k] = cpu::hsum(t);
    }
    live[slot_id] = 1;
  }
}

// ------------------------------------------------------------------------------------------------
// 5. Per-Gaussian backward of block `blk` (kGaussBlock Gaussians): sums each visible Gaussian's
// live slots in tile order and chains them through gaussian_backward_one (../common/raster.h),
// which writes gout (not when gout.means3D == nullptr: camera terms only); the camera terms go to
// cam[kCamGrad] (double, in Gaussian order) when cam != nullptr. A Gaussian without a live slot
// reaches no pixel: its gradients are zero and it is skipped. gout comes uninitialised (recycled
// blocks, rasterize_backward_cpu): the block's rows are zeroed here first, in parallel and in
// cache just before they are written, instead of a serial zero-fill of fresh pages.
// ------------------------------------------------------------------------------------------------
inline void zero_rows(float* t, int64_t width, int64_t g0, int64_t g1) {
  if (t != nullptr) std::memset(t + g0 * width, 0, (size_t)((g1 - g0) * width) * sizeof(float));
}

void gaussian_backward_block(const RasterArgs& in, int64_t blk, const int32_t* rad,
                             const int64_t* off, const float* slots, const uint8_t* live,
                             const GaussianGrads& gout, double* cam) {
  double* dV = cam;
  double* dP = cam ? cam + 16 : nullptr;
  double* dC = cam ? cam + 32 : nullptr;
  const Vec3 cpos = load3(in.campos);
  const int64_t g0 = blk * kGaussBlock, g1 = std::min(in.P, (blk + 1) * kGaussBlock);
  if (gout.means3D != nullptr) {
    zero_rows(gout.means3D, 3, g0, g1);
    zero_rows(gout.means2D, 3, g0, g1);
    zero_rows(gout.opac, 1, g0, g1);
    zero_rows(gout.shs, in.shs_rest != nullptr ? 3 : 3 * in.M, g0, g1);
    zero_rows(gout.shs_rest, 3 * (in.M - 1), g0, g1);
    zero_rows(gout.colors, 3, g0, g1);
    zero_rows(gout.scales, 3, g0, g1);
    zero_rows(gout.rots, 4, g0, g1);
    zero_rows(gout.cov3d, 6, g0, g1);
  }
  for (int64_t g = g0; g < g1; ++g) {
    if (rad[g] <= 0) continue;
    float s[kSlot] = {0};
    bool reached = false;
    for (int64_t e = off[g]; e < off[g + 1]; ++e) {
      if (!live[e]) continue;
      reached = true;
      const float* sl = slots + e * kSlot;
      for (int k = 0; k < kSlot; ++k) s[k] += sl[k];
    }
    if (!reached) continue;
    gaussian_backward_one(in, g, s, in.viewmatrix, in.projmatrix, cpos, gout, dV, dP, dC);
  }
}

}  // namespace

// ------------------------------------------------------------------------------------------------
// Forward
// ------------------------------------------------------------------------------------------------
ForwardOutputs rasterize_forward_cpu(const RasterInputs& args) {
  const RasterArgs in = fill_raster_args(check_tensor, args);
  cpu::PhaseTimer timer("forward", in.P, in.W, in.H);
  const int64_t P = in.P;
  const auto fopt = args.means3D.options();
  const auto iopt = fopt.dtype(at::kInt);
  const int64_t num_tiles = (int64_t)in.grid_x * in.grid_y;
  cpu::BlockCache& cache = cpu::BlockCache::instance();
  const auto cached_empty = [&cache](at::IntArrayRef sizes, const at::TensorOptions& o) {
    return cache.empty(sizes, o);
  };
  ForwardOutputs fw = allocate_forward_outputs(in, fopt, cached_empty);
  thread_local ForwardScratch scratch;
  cpu::TileFootprint* footprints = scratch.footprints.get(P);

  // 1. Preprocess, then the slot offsets and the visible Gaussians.
  const int nchunks = cpu::num_chunks(P, 4096);
  std::vector<ChunkCounts> counts(nchunks);
  preprocess(in, nchunks, fw.geom.data_ptr<float>(), fw.radii.data_ptr<int32_t>(), footprints,
             counts.data());
  timer.mark("preprocess");
  int64_t* off = fw.offsets.data_ptr<int64_t>();
  uint32_t* keys = scratch.keys.get(P);
  int32_t* vals = scratch.vals.get(P);
  const int64_t nvis = compact_visible(P, nchunks, counts.data(), footprints, off, keys, vals);
  const int64_t num_rendered = off[P];
  TORCH_CHECK(num_rendered < (int64_t)std::numeric_limits<int32_t>::max(),
              "too many (tile, Gaussian) pairs: ", num_rendered);
  timer.mark("compact");

  // 2. Binning: depth sort, then the per-tile lists (binning.h).
  const int32_t* order =
      cpu::radix_sort_by_key(keys, vals, scratch.keys2.get(nvis), scratch.vals2.get(nvis), nvis);
  timer.mark("sort");
  fw.tile_ranges = at::empty({num_tiles + 1}, iopt);
  fw.binning = cached_empty({num_rendered, 2}, iopt);
  const int32_t* bin = fw.binning.data_ptr<int32_t>();
  const int32_t* tr = fw.tile_ranges.data_ptr<int32_t>();
  cpu::fill_tile_lists(in.grid_x, num_tiles, order, nvis, footprints, scratch.sorted.get(nvis),
                       fw.tile_ranges.data_ptr<int32_t>(), fw.binning.data_ptr<int32_t>());
  timer.mark("tile_lists");

  // 3. Render.
  const RenderOutputs out = render_outputs(fw);
  const float* gm = fw.geom.data_ptr<float>();
  parallel_dynamic(num_tiles, [&](int64_t t) { render_tile(in, t, gm, bin, tr, out); });
  timer.mark("render");
  return fw;
}

namespace {

// Temporaries of the backward, kept by the calling thread between calls (cpu_support.h).
struct BackwardScratch {
  cpu::ScratchArray<float> slots;
  cpu::ScratchArray<uint8_t> live;
};

// 4. Per-tile backward into per-entry slots (every live slot is written by exactly one tile) and
// the background gradient. Without the Gaussians' gradients, the slots that cannot reach the
// camera are not accumulated: the opacity (it reaches it only through the antialiasing factor)
// and the colour (only through SH of degree > 0); with neither the camera nor the Gaussians
// (slots == nullptr), only the background terms are computed.
void backward_tiles(const RasterArgs& in, const BackwardInputs& b, float* slots, uint8_t* live,
                    float* grad_bg) {
  const int64_t num_tiles = (int64_t)in.grid_x * in.grid_y;
  const bool opacity_slot = b.compute_gaussian_grads || in.antialiasing;
  const bool colour_slot =
      b.compute_gaussian_grads || (in.colors == nullptr && in.sh_degree > 0);
  std::vector<double> dbg_tiles((size_t)num_tiles * 3);
  const float* gm = b.geom.data_ptr<float>();
  const int32_t* bin = b.binning.data_ptr<int32_t>();
  const int32_t* tr = b.tile_ranges.data_ptr<int32_t>();
  const GradImages gin{b.grad_color.data_ptr<float>(), b.grad_invdepth.data_ptr<float>(),
                       b.grad_depth_acc.data_ptr<float>(), b.grad_alpha.data_ptr<float>()};
  const float* fT = b.final_T.data_ptr<float>();
  const int32_t* lc = b.last_contrib.data_ptr<int32_t>();
  auto* tile_fn = opacity_slot
                      ? (colour_slot ? &backward_tile<true, true> : &backward_tile<true, false>)
                      : (colour_slot ? &backward_tile<false, true> : &backward_tile<false, false>);
  parallel_dynamic(num_tiles, [&](int64_t t) {
    tile_fn(in, t, gm, bin, tr, fT, lc, gin, slots, live, dbg_tiles.data() + 3 * t);
  });
  double sum[3] = {0, 0, 0};
  for (int64_t t = 0; t < num_tiles; ++t)
    for (int k = 0; k < 3; ++k) sum[k] += dbg_tiles[3 * t + k];
  for (int k = 0; k < 3; ++k) grad_bg[k] = (float)sum[k];
}

// 5. Per-Gaussian backward over fixed blocks; the camera gradient (when asked for) is summed per
// block in double, then over the blocks in order, into grads.
void backward_gaussians(const RasterArgs& in, const BackwardInputs& b, const float* slots,
                        const uint8_t* live, BackwardOutputs& grads) {
  const int64_t nblocks = (in.P + kGaussBlock - 1) / kGaussBlock;
  const bool camera = b.compute_camera_grad;
  std::vector<double> cam_blocks(camera ? (size_t)nblocks * kCamGrad : 0, 0.0);
  const int32_t* rad = b.radii.data_ptr<int32_t>();
  const int64_t* off = b.offsets.data_ptr<int64_t>();
  const GaussianGrads gout = gaussian_grad_ptrs(grads);
  at::parallel_for(0, nblocks, 1, [&](int64_t b0, int64_t b1) {
    for (int64_t blk = b0; blk < b1; ++blk) {
      double* cam = camera ? cam_blocks.data() + blk * kCamGrad : nullptr;
      gaussian_backward_block(in, blk, rad, off, slots, live, gout, cam);
    }
  });
  if (!camera) return;
  double sum[kCamGrad] = {0};
  for (int64_t blk = 0; blk < nblocks; ++blk)
    for (int k = 0; k < kCamGrad; ++k) sum[k] += cam_blocks[blk * kCamGrad + k];
  const auto fopt = b.means3D.options();
  grads.grad_viewmatrix = at::empty({4, 4}, fopt);
  grads.grad_projmatrix = at::empty({4, 4}, fopt);
  grads.grad_campos = at::empty({3}, fopt);
  float* dV = grads.grad_viewmatrix.data_ptr<float>();
  float* dP = grads.grad_projmatrix.data_ptr<float>();
  float* dC = grads.grad_campos.data_ptr<float>();
  for (int k = 0; k < 16; ++k) dV[k] = (float)sum[k];
  for (int k = 0; k < 16; ++k) dP[k] = (float)sum[16 + k];
  for (int k = 0; k < 3; ++k) dC[k] = (float)sum[32 + k];
}

}  // namespace

// ------------------------------------------------------------------------------------------------
// Backward
// ------------------------------------------------------------------------------------------------
BackwardOutputs rasterize_backward_cpu(const BackwardInputs& b) {
  const RasterArgs in = fill_raster_args(check_tensor, b);
  cpu::PhaseTimer timer("backward", in.P, in.W, in.H);
  const int64_t P = in.P;
  const int64_t num_tiles = (int64_t)in.grid_x * in.grid_y;
  check_backward_inputs(check_tensor, check_int_tensor, in, b);
  const int64_t num_rendered = b.offsets.data_ptr<int64_t>()[P];
  TORCH_CHECK(b.binning.dim() == 2 && b.binning.size(0) == num_rendered &&
                  b.binning.size(1) == 2 &&
                  b.tile_ranges.data_ptr<int32_t>()[num_tiles] == num_rendered,
              "saved binning state does not match the inputs");
  const auto fopt = b.means3D.options();
  cpu::BlockCache& cache = cpu::BlockCache::instance();
  BackwardOutputs grads = allocate_gaussian_grads(
      in, b.compute_gaussian_grads, fopt,
      [&cache](at::IntArrayRef sizes, const at::TensorOptions& o) { return cache.empty(sizes, o); });
  grads.grad_bg = at::empty({3}, fopt);
  const bool want_slots = b.compute_camera_grad || b.compute_gaussian_grads;
  thread_local BackwardScratch scratch;
  float* slots = want_slots ? scratch.slots.get((size_t)num_rendered * kSlot) : nullptr;
  uint8_t* live = want_slots ? scratch.live.get((size_t)num_rendered) : nullptr;
  if (live != nullptr) std::memset(live, 0, (size_t)num_rendered);
  timer.mark("alloc");
  backward_tiles(in, b, slots, live, grads.grad_bg.data_ptr<float>());
  timer.mark("tiles");
  if (want_slots) backward_gaussians(in, b, slots, live, grads);
  timer.mark("gaussians");
  return grads;
}

VisibilityOutputs mark_visible_cpu(const VisibilityInputs& args) {
  check_tensor(args.means3D, "means3D", {-1, 3});
  check_tensor(args.viewmatrix, "viewmatrix", {4, 4});
  check_tensor(args.projmatrix, "projmatrix", {4, 4});
  const int64_t P = args.means3D.size(0);
  VisibilityOutputs out;
  out.visible = at::empty({P}, args.means3D.options().dtype(at::kBool));
  const float* m = args.means3D.data_ptr<float>();
  const float* V = args.viewmatrix.data_ptr<float>();
  bool* o = out.visible.data_ptr<bool>();
  at::parallel_for(0, P, 4096, [&](int64_t b, int64_t e) {
    for (int64_t g = b; g < e; ++g) o[g] = transform_point_4x3(V, load3(m + 3 * g)).z > kNearPlane;
  });
  return out;
}

TORCH_LIBRARY_IMPL(grp, CPU, m) {
  m.impl(kForwardOp, boxed_kernel<&rasterize_forward_cpu>());
  m.impl(kBackwardOp, boxed_kernel<&rasterize_backward_cpu>());
  m.impl(kMarkVisibleOp, boxed_kernel<&mark_visible_cpu>());
}

}  // namespace grp
