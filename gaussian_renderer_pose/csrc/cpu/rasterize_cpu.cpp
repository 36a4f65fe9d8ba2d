// Tile-based multi-threaded CPU rasterizer: forward and full backward (incl. camera gradient).
// Loops only: the per-Gaussian maths lives in ../common/{math,sh,raster}.h. See ../ops.h for the API.
//
// Pipeline (forward):
//   1. preprocess, parallel over Gaussians: cull, project, cov2D/conic, radius, tile rect, colour.
//   2. binning: visible Gaussians radix-sorted by view depth (stable -> ties by index), then
//      per-tile lists filled in that order (parallel over tile rows). Entry = (gaussian, slot);
//      the slot (offsets[g] + position in g's rect) is where the backward of that tile writes g's
//      partial gradient, so no two threads ever write the same memory.
//   3. render, parallel over tiles (dynamic): each tile walks its list front to back, and for each
//      Gaussian updates the 16-wide pixel rows that its alpha >= 1/255 ellipse can reach (one
//      16-lane vector per row, branch-free masked updates; exp by a vectorised polynomial);
//      stops when every pixel of the tile is done.
// Backward:
//   4. per tile, walk the list back to front from the last contributor (upstream renderCUDA bwd,
//      T recovered by division), reduce each Gaussian's per-pixel terms over the tile in a fixed
//      order and store them in its slot.
//   5. per Gaussian (parallel over fixed-size blocks): sum its slots in tile order, chain through
//      the per-Gaussian VJPs; camera terms summed per block in double, then blocks in order.
//      Without compute_gaussian_grads only the camera terms are computed (no Gaussian gradient
//      is allocated, zero-filled or written); with neither flag the step is skipped.
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
// 1. Preprocess
// ------------------------------------------------------------------------------------------------
void preprocess(const RasterArgs& in, float* geom, int32_t* radii, int32_t* rects,
                int64_t* ntiles) {
  at::parallel_for(0, in.P, 1024, [&](int64_t b, int64_t e) {
    for (int64_t g = b; g < e; ++g) {
      const PreprocessResult r =
          preprocess_gaussian(in, g, in.viewmatrix, in.projmatrix, geom + kGStride * g);
      radii[g] = r.radius;
      ntiles[g] = r.area;
      for (int k = 0; k < 4; ++k) rects[4 * g + k] = r.rect[k];
    }
  });
}

// Stable LSD radix sort of the visible Gaussians by depth (positive floats: bit order = order).
std::vector<int32_t> sort_by_depth(const float* geom, const int32_t* radii, int64_t P) {
  std::vector<int32_t> vals;
  vals.reserve(P);
  for (int64_t g = 0; g < P; ++g)
    if (radii[g] > 0) vals.push_back((int32_t)g);
  const size_t n = vals.size();
  std::vector<uint32_t> keys(n), keys2(n);
  std::vector<int32_t> vals2(n);
  for (size_t i = 0; i < n; ++i) std::memcpy(&keys[i], geom + kGStride * vals[i] + kGZ, 4);
  for (int pass = 0; pass < 4; ++pass) {
    const int shift = 8 * pass;
    size_t count[257] = {0};
    for (size_t i = 0; i < n; ++i) ++count[((keys[i] >> shift) & 255u) + 1];
    bool trivial = false;
    for (int b = 1; b <= 256; ++b)
      if (count[b] == n) trivial = true;
    if (trivial) continue;
    for (int b = 0; b < 256; ++b) count[b + 1] += count[b];
    for (size_t i = 0; i < n; ++i) {
      const size_t dst = count[(keys[i] >> shift) & 255u]++;
      keys2[dst] = keys[i];
      vals2[dst] = vals[i];
    }
    keys.swap(keys2);
    vals.swap(vals2);
  }
  return vals;
}

// ------------------------------------------------------------------------------------------------
// 16-lane vectors = one tile row (GCC/Clang vector extensions). The compiler lowers them to
// AVX-512, AVX2 or SSE depending on the target flags; every lane does the same IEEE maths.
// ------------------------------------------------------------------------------------------------
typedef float vf __attribute__((vector_size(4 * kBlockX)));
typedef int32_t vi __attribute__((vector_size(4 * kBlockX)));
static_assert(sizeof(vf) == sizeof(float) * kBlockX, "one vector per tile row");

inline vf splat(float v) {
  vf r;
  for (int i = 0; i < kBlockX; ++i) r[i] = v;
  return r;
}
inline vi splat_i(int32_t v) {
  vi r;
  for (int i = 0; i < kBlockX; ++i) r[i] = v;
  return r;
}

// Vector twin of exp_nonpos (common/math.h): same reduction and polynomial, lane-wise.
inline vf vexp_nonpos(vf x) {
  x = x < splat(-87.f) ? splat(-87.f) : x;
  x = x > splat(0.f) ? splat(0.f) : x;
  const vf v = x * 1.44269504088896341f;
  const vi n = __builtin_convertvector(v - 0.5f, vi);  // round to nearest for v <= 0
  const vf fn = __builtin_convertvector(n, vf);
  vf r = x - fn * 0.693359375f;
  r = r - fn * -2.12194440e-4f;
  vf p = splat(1.9875691500e-4f);
  p = p * r + 1.3981999507e-3f;
  p = p * r + 8.3334519073e-3f;
  p = p * r + 4.1665795894e-2f;
  p = p * r + 1.6666665459e-1f;
  p = p * r + 5.0000001201e-1f;
  const vf y = p * r * r + r + 1.0f;
  const vi bits = (n + 127) << 23;
  return y * (vf)bits;
}

// Rows [r0, r1] of the tile that Gaussian gd can reach (alpha >= 1/255); false when none.
inline bool row_range(const float* gd, int y0, int nrows, int& r0, int& r1) {
  const float by = gd[kGBoxY];
  if (!(by >= 0.f)) return false;
  const float py = gd[kGPy];
  float flo = py - by, fhi = py + by;
  if (flo < (float)y0) flo = (float)y0;
  if (fhi > (float)(y0 + nrows - 1)) fhi = (float)(y0 + nrows - 1);
  if (!(flo <= fhi)) return false;
  r0 = (int)std::ceil(flo) - y0;
  r1 = (int)std::floor(fhi) - y0;
  return r0 <= r1;
}

// One tile row of a Gaussian (upstream renderCUDA): power = -d^T conic d / 2 at the 16 pixels
// (dx = px - x per lane, qx = conic.a dx^2, dy = py - y), G = exp(power), oG = o G and
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

// ------------------------------------------------------------------------------------------------
// 3. Forward render of one tile
// ------------------------------------------------------------------------------------------------
void render_tile(const RasterArgs& in, int64_t tile, const float* geom, const int32_t* binning,
                 const int32_t* tile_ranges, const RenderOutputs& out) {
  int x0, y0, ncols, nrows;
  tile_extent(in, tile, x0, y0, ncols, nrows);
  // Pixel state, one record per tile row (keeps a row's vectors together in L1).
  struct Row {
    vf T, C0, C1, C2, ID, DA;
    vi act, last;
  };
  Row rows[kBlockY];
  vf pixx;
  vi colmask;
  for (int i = 0; i < kBlockX; ++i) {
    pixx[i] = (float)(x0 + i);
    colmask[i] = i < ncols ? -1 : 0;
  }
  for (int r = 0; r < kBlockY; ++r) {
    Row& R = rows[r];
    R.act = r < nrows ? colmask : splat_i(0);
    R.T = splat(1.f);
    R.C0 = R.C1 = R.C2 = R.ID = R.DA = splat(0.f);
    R.last = splat_i(-1);
  }
  int nact = ncols * nrows;
  const int32_t start = tile_ranges[tile], end = tile_ranges[tile + 1];
  for (int32_t j = start; j < end && nact > 0; ++j) {
    if (j + kPrefetch < end) __builtin_prefetch(geom + kGStride * (int64_t)binning[2 * (j + kPrefetch)]);
    const float* gd = geom + kGStride * (int64_t)binning[2 * j];
    int r0, r1;
    if (!row_range(gd, y0, nrows, r0, r1)) continue;
    const float px = gd[kGPx], py = gd[kGPy];
    const float cA = gd[kGConA], cB = gd[kGConB], cC = gd[kGConC], o = gd[kGOpacity];
    const float f0 = gd[kGR], f1 = gd[kGG], f2 = gd[kGB], fiz = gd[kGInvZ], fz = gd[kGZ];
    const vi jl = splat_i(j - start);
    const vf dx = px - pixx;
    const vf qx = cA * dx * dx;
    vi nstop = splat_i(0);
    for (int r = r0; r <= r1; ++r) {
      Row& R = rows[r];
      const float dy = py - (float)(y0 + r);
      vf power, G, oG, alpha;
      row_alpha(qx, dx, dy, cB, cC, o, power, G, oG, alpha);
      const vi valid = R.act & ~(power > splat(0.f)) & ~(alpha < splat(kAlphaMin));
      const vf Tc = R.T;
      const vf testT = Tc * (1.f - alpha);
      const vi stop = valid & (testT < splat(kTransmittanceMin));
      const vi contrib = valid & ~stop;
      const vf w = contrib ? alpha * Tc : splat(0.f);
      R.C0 += f0 * w;
      R.C1 += f1 * w;
      R.C2 += f2 * w;
      R.ID += fiz * w;
      R.DA += fz * w;
      R.T = contrib ? testT : Tc;
      R.last = contrib ? jl : R.last;
      R.act &= ~stop;
      nstop -= stop;
    }
    for (int i = 0; i < kBlockX; ++i) nact -= nstop[i];
  }
  const int64_t HW = (int64_t)in.H * in.W;
  for (int r = 0; r < nrows; ++r) {
    const Row& R = rows[r];
    for (int c = 0; c < ncols; ++c) {
      const int64_t pix = (int64_t)(y0 + r) * in.W + (x0 + c);
      const float Tp = R.T[c];
      out.color[pix] = R.C0[c] + Tp * in.bg[0];
      out.color[HW + pix] = R.C1[c] + Tp * in.bg[1];
      out.color[2 * HW + pix] = R.C2[c] + Tp * in.bg[2];
      out.invdepth[pix] = R.ID[c];
      out.depth_acc[pix] = R.DA[c];
      out.alpha[pix] = 1.f - Tp;
      out.final_T[pix] = Tp;
      out.last[pix] = R.last[c];
    }
  }
}

// ------------------------------------------------------------------------------------------------
// 4. Backward of one tile: writes the slot of every entry of the tile's list, and the tile's
// background terms dbg_tile[3] (only those when slots == nullptr).
// kOpacitySlot / kColourSlot = false: slot 5 (opacity) / slots 6..8 (colour) are written as 0
// without being accumulated (for a caller that never reads them). The other slots come from the
// same statements in the same order in every variant (independent accumulators, explicit vector
// types: nothing for the vectoriser to regroup); tests/renderer/test_pose_only_backward.py checks
// that the camera gradient is the same bits in each.
// ------------------------------------------------------------------------------------------------
template <bool kOpacitySlot, bool kColourSlot>
void backward_tile(const RasterArgs& in, int64_t tile, const float* geom, const int32_t* binning,
                   const int32_t* tile_ranges, const float* final_T, const int32_t* last_contrib,
                   const GradImages& gin, float* slots, double* dbg_tile) {
  int x0, y0, ncols, nrows;
  tile_extent(in, tile, x0, y0, ncols, nrows);
  const int64_t HW = (int64_t)in.H * in.W;
  // Per pixel (upstream renderCUDA backward, features = r, g, b, 1/z, z):
  //   T: transmittance, recovered back to front; lastA: alpha of the Gaussian behind;
  //   accdot = dL/dpixel . (features blended behind, accum_rec upstream);
  //   lfdot = dL/dpixel . (features of the Gaussian behind); dp = dL/dpixel per feature;
  //   kbg = T_final (dL/dalpha_out - bg . dL/dcolor), enters dL/dalpha_i as kbg / (1 - alpha_i).
  struct Row {
    vf T, lastA, kbg, accdot, lfdot;
    vf dp[kNumFeat];
    vi last;
  };
  Row rows[kBlockY];
  vf pixx;
  for (int i = 0; i < kBlockX; ++i) pixx[i] = (float)(x0 + i);
  int32_t maxlast = -1;
  double dbg[3] = {0, 0, 0};
  for (int r = 0; r < kBlockY; ++r) {
    Row& R = rows[r];
    R.T = R.lastA = R.kbg = R.accdot = R.lfdot = splat(0.f);
    R.last = splat_i(-1);
    for (int k = 0; k < kNumFeat; ++k) R.dp[k] = splat(0.f);
    if (r >= nrows) continue;
    for (int c = 0; c < ncols; ++c) {
      const int64_t pix = (int64_t)(y0 + r) * in.W + (x0 + c);
      const float Tf = final_T[pix];
      R.T[c] = Tf;
      R.last[c] = last_contrib[pix];
      maxlast = std::max(maxlast, last_contrib[pix]);
      const float g0 = gin.color[pix], g1 = gin.color[HW + pix], g2 = gin.color[2 * HW + pix];
      R.dp[0][c] = g0;
      R.dp[1][c] = g1;
      R.dp[2][c] = g2;
      R.dp[3][c] = gin.invdepth[pix];
      R.dp[4][c] = gin.depth_acc[pix];
      const float bgdot = in.bg[0] * g0 + in.bg[1] * g1 + in.bg[2] * g2;
      R.kbg[c] = Tf * (gin.alpha[pix] - bgdot);
      dbg[0] += (double)Tf * (double)g0;
      dbg[1] += (double)Tf * (double)g1;
      dbg[2] += (double)Tf * (double)g2;
    }
  }
  for (int k = 0; k < 3; ++k) dbg_tile[k] = dbg[k];
  if (slots == nullptr) return;
  const int32_t start = tile_ranges[tile], end = tile_ranges[tile + 1];
  // Entries behind every pixel's last contributor get zero slots.
  for (int32_t j = start + maxlast + 1; j < end; ++j) {
    float* s = slots + (int64_t)binning[2 * j + 1] * kSlot;
    for (int k = 0; k < kSlot; ++k) s[k] = 0.f;
  }
  for (int32_t j = start + maxlast; j >= start; --j) {
    if (j - kPrefetch >= start) {
      __builtin_prefetch(geom + kGStride * (int64_t)binning[2 * (j - kPrefetch)]);
      __builtin_prefetch(slots + (int64_t)binning[2 * (j - kPrefetch) + 1] * kSlot, 1);
    }
    float* slot = slots + (int64_t)binning[2 * j + 1] * kSlot;
    const float* gd = geom + kGStride * (int64_t)binning[2 * j];
    int r0, r1;
    if (!row_range(gd, y0, nrows, r0, r1)) {
      for (int k = 0; k < kSlot; ++k) slot[k] = 0.f;
      continue;
    }
    const float px = gd[kGPx], py = gd[kGPy];
    const float cA = gd[kGConA], cB = gd[kGConB], cC = gd[kGConC], o = gd[kGOpacity];
    const float f[kNumFeat] = {gd[kGR], gd[kGG], gd[kGB], gd[kGInvZ], gd[kGZ]};
    const vi jl = splat_i(j - start);
    const vf dx = px - pixx;
    const vf qx = cA * dx * dx;
    vf s_dx = splat(0.f), s_dy = s_dx, s_cA = s_dx, s_cB = s_dx, s_cC = s_dx, s_o = s_dx;
    vf s_f[kNumFeat];
    for (int k = 0; k < kNumFeat; ++k) s_f[k] = splat(0.f);
    for (int r = r0; r <= r1; ++r) {
      Row& R = rows[r];
      const float dy = py - (float)(y0 + r);
      vf power, G, oG, alpha;
      row_alpha(qx, dx, dy, cB, cC, o, power, G, oG, alpha);
      const vi valid = (jl <= R.last) & ~(power > splat(0.f)) & ~(alpha < splat(kAlphaMin));
      const vf a = valid ? alpha : splat(0.f);
      const vf inv_1ma = 1.f / (1.f - a);
      const vf Tn = R.T * inv_1ma;  // unchanged where invalid (a = 0)
      const vf w = a * Tn;
      vf fdot = f[0] * R.dp[0];
      if (kColourSlot) s_f[0] += w * R.dp[0];
      for (int k = 1; k < kNumFeat; ++k) {
        fdot += f[k] * R.dp[k];
        if (kColourSlot || k >= 3) s_f[k] += w * R.dp[k];
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
      if (kOpacitySlot) s_o += pass ? G * dLda : splat(0.f);
      const vf gdx = G * dx, gdy = G * dy;
      s_dx += dLdG * (-gdx * cA - gdy * cB);
      s_dy += dLdG * (-gdy * cC - gdx * cB);
      s_cA += -0.5f * gdx * dx * dLdG;
      s_cB += -gdx * dy * dLdG;
      s_cC += -0.5f * gdy * dy * dLdG;
    }
    float red[kSlot] = {0};
    for (int i = 0; i < kBlockX; ++i) {
      red[0] += s_dx[i];
      red[1] += s_dy[i];
      red[2] += s_cA[i];
      red[3] += s_cB[i];
      red[4] += s_cC[i];
      if (kOpacitySlot) red[5] += s_o[i];
      for (int k = 0; k < kNumFeat; ++k)
        if (kColourSlot || k >= 3) red[6 + k] += s_f[k][i];
    }
    for (int k = 0; k < kSlot; ++k) slot[k] = red[k];
  }
}

// ------------------------------------------------------------------------------------------------
// 5. Per-Gaussian backward of block `blk` (kGaussBlock Gaussians): sums each visible Gaussian's
// slots in tile order and chains them through gaussian_backward_one (../common/raster.h), which
// writes gout (not when gout.means3D == nullptr: camera terms only); the camera terms go to
// cam[kCamGrad] (double, in Gaussian order) when cam != nullptr.
// ------------------------------------------------------------------------------------------------
void gaussian_backward_block(const RasterArgs& in, int64_t blk, const int32_t* rad,
                             const int64_t* off, const float* slots, const GaussianGrads& gout,
                             double* cam) {
  double* dV = cam;
  double* dP = cam ? cam + 16 : nullptr;
  double* dC = cam ? cam + 32 : nullptr;
  const Vec3 cpos = load3(in.campos);
  const int64_t g1 = std::min(in.P, (blk + 1) * kGaussBlock);
  for (int64_t g = blk * kGaussBlock; g < g1; ++g) {
    if (rad[g] <= 0) continue;
    float s[kSlot] = {0};
    for (int64_t e = off[g]; e < off[g + 1]; ++e) {
      const float* sl = slots + e * kSlot;
      for (int k = 0; k < kSlot; ++k) s[k] += sl[k];
    }
    gaussian_backward_one(in, g, s, in.viewmatrix, in.projmatrix, cpos, gout, dV, dP, dC);
  }
}

}  // namespace

// ------------------------------------------------------------------------------------------------
// Forward
// ------------------------------------------------------------------------------------------------
ForwardOutputs rasterize_forward_cpu(const RasterInputs& args) {
  const RasterArgs in = fill_raster_args(check_tensor, args);
  const int64_t P = in.P;
  const auto fopt = args.means3D.options();
  const auto iopt = fopt.dtype(at::kInt);
  const int64_t num_tiles = (int64_t)in.grid_x * in.grid_y;

  ForwardOutputs fw = allocate_forward_outputs(in, fopt);
  std::vector<int32_t> rects(4 * P);

  int64_t* off = fw.offsets.data_ptr<int64_t>();
  preprocess(in, fw.geom.data_ptr<float>(), fw.radii.data_ptr<int32_t>(), rects.data(), off + 1);
  off[0] = 0;
  for (int64_t g = 0; g < P; ++g) off[g + 1] += off[g];
  const int64_t num_rendered = off[P];
  TORCH_CHECK(num_rendered < (int64_t)std::numeric_limits<int32_t>::max(),
              "too many (tile, Gaussian) pairs: ", num_rendered);

  // 2. Binning.
  const float* gm = fw.geom.data_ptr<float>();
  const std::vector<int32_t> order = sort_by_depth(gm, fw.radii.data_ptr<int32_t>(), P);
  fw.tile_ranges = at::zeros({num_tiles + 1}, iopt);
  fw.binning = at::empty({num_rendered, 2}, iopt);
  {
    int32_t* tr = fw.tile_ranges.data_ptr<int32_t>();
    int32_t* bin = fw.binning.data_ptr<int32_t>();
    const int gx = in.grid_x;
    std::vector<int32_t> counts(num_tiles, 0);
    at::parallel_for(0, in.grid_y, 1, [&](int64_t ty0, int64_t ty1) {
      for (int32_t g : order) {
        const int32_t* rc = rects.data() + 4 * g;
        const int lo = std::max<int>(rc[1], (int)ty0), hi = std::min<int>(rc[3], (int)ty1);
        for (int ty = lo; ty < hi; ++ty)
          for (int tx = rc[0]; tx < rc[2]; ++tx) ++counts[(int64_t)ty * gx + tx];
      }
    });
    tr[0] = 0;
    for (int64_t t = 0; t < num_tiles; ++t) tr[t + 1] = tr[t] + counts[t];
    std::vector<int32_t> cursor(tr, tr + num_tiles);
    at::parallel_for(0, in.grid_y, 1, [&](int64_t ty0, int64_t ty1) {
      for (int32_t g : order) {
        const int32_t* rc = rects.data() + 4 * g;
        const int lo = std::max<int>(rc[1], (int)ty0), hi = std::min<int>(rc[3], (int)ty1);
        const int w = rc[2] - rc[0];
        for (int ty = lo; ty < hi; ++ty)
          for (int tx = rc[0]; tx < rc[2]; ++tx) {
            const int32_t pos = cursor[(int64_t)ty * gx + tx]++;
            bin[2 * pos] = g;
            bin[2 * pos + 1] = (int32_t)(off[g] + (int64_t)(ty - rc[1]) * w + (tx - rc[0]));
          }
      }
    });
  }

  // 3. Render.
  const RenderOutputs out = render_outputs(fw);
  const int32_t* bin = fw.binning.data_ptr<int32_t>();
  const int32_t* tr = fw.tile_ranges.data_ptr<int32_t>();
  parallel_dynamic(num_tiles, [&](int64_t t) { render_tile(in, t, gm, bin, tr, out); });

  return fw;
}

// ------------------------------------------------------------------------------------------------
// Backward
// ------------------------------------------------------------------------------------------------
BackwardOutputs rasterize_backward_cpu(const BackwardInputs& b) {
  const RasterArgs in = fill_raster_args(check_tensor, b);
  const int64_t P = in.P;
  const int64_t num_tiles = (int64_t)in.grid_x * in.grid_y;
  check_backward_inputs(check_tensor, check_int_tensor, in, b);
  const int64_t num_rendered = b.offsets.data_ptr<int64_t>()[P];
  TORCH_CHECK(b.binning.dim() == 2 && b.binning.size(0) == num_rendered &&
                  b.binning.size(1) == 2 &&
                  b.tile_ranges.data_ptr<int32_t>()[num_tiles] == num_rendered,
              "saved binning state does not match the inputs");

  const auto fopt = b.means3D.options();
  const bool compute_camera_grad = b.compute_camera_grad;
  const bool compute_gaussian_grads = b.compute_gaussian_grads;
  BackwardOutputs grads = zero_gaussian_grads(in, compute_gaussian_grads, fopt);
  // 4. Per-tile backward into per-entry slots.
  // Every slot is written by exactly one tile (no zero-fill needed). Without the Gaussians'
  // gradients, the slots that cannot reach the camera are not accumulated: the opacity (it reaches
  // it only through the antialiasing factor) and the colour (only through SH of degree > 0); with
  // neither the camera nor the Gaussians, only the background terms are computed.
  const bool want_slots = compute_camera_grad || compute_gaussian_grads;
  const bool opacity_slot = compute_gaussian_grads || in.antialiasing;
  const bool colour_slot = compute_gaussian_grads || (in.colors == nullptr && in.sh_degree > 0);
  std::unique_ptr<float[]> slots(new float[(size_t)std::max<int64_t>(num_rendered, 1) * kSlot]);
  std::vector<double> dbg_tiles((size_t)num_tiles * 3);
  const float* gm = b.geom.data_ptr<float>();
  const int32_t* bin = b.binning.data_ptr<int32_t>();
  const int32_t* tr = b.tile_ranges.data_ptr<int32_t>();
  const GradImages gin{b.grad_color.data_ptr<float>(), b.grad_invdepth.data_ptr<float>(),
                       b.grad_depth_acc.data_ptr<float>(), b.grad_alpha.data_ptr<float>()};
  const float* fT = b.final_T.data_ptr<float>();
  const int32_t* lc = b.last_contrib.data_ptr<int32_t>();
  float* sl = want_slots ? slots.get() : nullptr;
  auto* tile_fn = opacity_slot
                      ? (colour_slot ? &backward_tile<true, true> : &backward_tile<true, false>)
                      : (colour_slot ? &backward_tile<false, true> : &backward_tile<false, false>);
  parallel_dynamic(num_tiles, [&](int64_t t) {
    tile_fn(in, t, gm, bin, tr, fT, lc, gin, sl, dbg_tiles.data() + 3 * t);
  });
  grads.grad_bg = at::empty({3}, fopt);
  {
    double s[3] = {0, 0, 0};
    for (int64_t t = 0; t < num_tiles; ++t)
      for (int k = 0; k < 3; ++k) s[k] += dbg_tiles[3 * t + k];
    for (int k = 0; k < 3; ++k) grads.grad_bg.data_ptr<float>()[k] = (float)s[k];
  }

  // 5. Per-Gaussian backward (nothing to do when neither the camera nor the Gaussians need it).
  const int64_t nblocks = (P + kGaussBlock - 1) / kGaussBlock;
  std::vector<double> cam_blocks(compute_camera_grad ? (size_t)nblocks * kCamGrad : 0, 0.0);
  const int32_t* rad = b.radii.data_ptr<int32_t>();
  const int64_t* off = b.offsets.data_ptr<int64_t>();
  const GaussianGrads gout = gaussian_grad_ptrs(grads);
  if (compute_camera_grad || compute_gaussian_grads) {
    at::parallel_for(0, nblocks, 1, [&](int64_t b0, int64_t b1) {
      for (int64_t blk = b0; blk < b1; ++blk) {
        double* cam = compute_camera_grad ? cam_blocks.data() + blk * kCamGrad : nullptr;
        gaussian_backward_block(in, blk, rad, off, slots.get(), gout, cam);
      }
    });
  }
  if (compute_camera_grad) {
    double sum[kCamGrad] = {0};
    for (int64_t blk = 0; blk < nblocks; ++blk)
      for (int k = 0; k < kCamGrad; ++k) sum[k] += cam_blocks[blk * kCamGrad + k];
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
