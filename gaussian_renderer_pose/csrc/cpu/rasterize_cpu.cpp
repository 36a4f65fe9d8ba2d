// Tile-based multi-threaded CPU rasterizer: forward and full backward (incl. camera gradient).
// Loops only: the per-Gaussian maths lives in ../common/{math,sh}.h. See ../ops.h for the API.
//
// Pipeline (forward):
//   1. preprocess, parallel over Gaussians: cull, project, cov2D/conic, radius, tile rect, colour.
//   2. binning: visible Gaussians radix-sorted by view depth (stable -> ties by index), then
//      per-tile lists filled in that order (parallel over tile rows). Entry = (gaussian, slot);
//      the slot (offsets[g] + position in g's rect) is where the backward of that tile writes g's
//      partial gradient, so no two threads ever write the same memory.
//   3. render, parallel over tiles (dynamic): each tile walks its list front to back, and for each
//      Gaussian updates the 16-wide pixel rows that its alpha >= 1/255 ellipse can reach
//      (branch-free masked updates that vectorise); stops when every pixel of the tile is done.
// Backward:
//   4. per tile, walk the list back to front from the last contributor (upstream renderCUDA bwd,
//      T recovered by division), reduce each Gaussian's per-pixel terms over the tile in a fixed
//      order and store them in its slot.
//   5. per Gaussian (parallel over fixed-size blocks): sum its slots in tile order, chain through
//      the per-Gaussian VJPs; camera terms summed per block in double, then blocks in order.
#include <ATen/ATen.h>
#include <ATen/Parallel.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <vector>

#include "../common/config.h"
#include "../common/math.h"
#include "../common/sh.h"
#include "../ops.h"

namespace grp {
namespace {

// Per-Gaussian record written by the preprocess (one cache line).
enum GeomField : int {
  kGPx = 0, kGPy, kGConA, kGConB, kGConC, kGOpacity, kGR, kGG, kGB, kGInvZ, kGZ, kGBoxX, kGBoxY,
  kGStride = 16
};
constexpr int kNumFeat = 5;                  // r, g, b, 1/z, z
constexpr int kSlot = 2 + 3 + 1 + kNumFeat;  // dL/dxy (pixels), dL/dconic, dL/dopacity_eff, dL/dfeat
constexpr int kCamGrad = 16 + 16 + 3;        // viewmatrix, projmatrix, campos
constexpr int64_t kGaussBlock = 1024;        // fixed block size of the per-Gaussian backward

#if defined(_OPENMP)
#define GRP_SIMD _Pragma("omp simd")
#define GRP_SIMD_RED(x) _Pragma(x)
#else
#define GRP_SIMD
#define GRP_SIMD_RED(x)
#endif

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
  TORCH_CHECK(t.defined(), name, " must be a tensor");
  TORCH_CHECK(t.device().is_cpu(), name, " must be a CPU tensor, got ", t.device());
  TORCH_CHECK(t.scalar_type() == at::kFloat, name, " must be float32, got ", t.scalar_type());
  TORCH_CHECK(t.is_contiguous(), name, " must be contiguous");
  TORCH_CHECK(t.dim() == (int64_t)shape.size(), name, " must have ", shape.size(),
              " dimensions, got shape ", t.sizes());
  int d = 0;
  for (int64_t s : shape) {
    TORCH_CHECK(s < 0 || t.size(d) == s, name, " has shape ", t.sizes(), ", expected dim ", d,
                " == ", s);
    ++d;
  }
}

void check_int_tensor(const at::Tensor& t, const char* name, at::ScalarType st) {
  TORCH_CHECK(t.defined() && t.device().is_cpu() && t.scalar_type() == st && t.is_contiguous(),
              name, " must be a contiguous CPU tensor of type ", st);
}

struct Inputs {
  int64_t P = 0;
  int H = 0, W = 0;
  int grid_x = 0, grid_y = 0;
  float tanfovx = 0, tanfovy = 0, focal_x = 0, focal_y = 0, scale_modifier = 1;
  int sh_degree = 0;
  int64_t M = 0;
  bool antialiasing = false;
  const float* means = nullptr;
  const float* opac = nullptr;
  const float* shs = nullptr;
  const float* colors = nullptr;
  const float* scales = nullptr;
  const float* rots = nullptr;
  const float* cov3d = nullptr;
  const float* bg = nullptr;
  const float* V = nullptr;
  const float* Pm = nullptr;
  const float* campos = nullptr;
};

Inputs check_inputs(const at::Tensor& means3D, const at::Tensor& opacities,
                    const std::optional<at::Tensor>& shs,
                    const std::optional<at::Tensor>& colors_precomp,
                    const std::optional<at::Tensor>& scales,
                    const std::optional<at::Tensor>& rotations,
                    const std::optional<at::Tensor>& cov3D_precomp, const at::Tensor& bg,
                    const at::Tensor& viewmatrix, const at::Tensor& projmatrix,
                    const at::Tensor& campos, int64_t H, int64_t W, double tanfovx, double tanfovy,
                    double scale_modifier, int64_t sh_degree, bool antialiasing) {
  check_tensor(means3D, "means3D", {-1, 3});
  Inputs in;
  in.P = means3D.size(0);
  const int64_t P = in.P;
  check_tensor(opacities, "opacities", {P, 1});
  check_tensor(bg, "bg", {3});
  check_tensor(viewmatrix, "viewmatrix", {4, 4});
  check_tensor(projmatrix, "projmatrix", {4, 4});
  check_tensor(campos, "campos", {3});
  TORCH_CHECK(H > 0 && W > 0 && H < (1 << 20) && W < (1 << 20), "image size must be positive, got ",
              H, "x", W);
  TORCH_CHECK(sh_degree >= 0 && sh_degree <= 3, "sh_degree must be in 0..3, got ", sh_degree);
  TORCH_CHECK(tanfovx > 0 && tanfovy > 0, "tanfovx/tanfovy must be positive");
  const bool has_colors = colors_precomp.has_value() && colors_precomp->defined();
  const bool has_shs = shs.has_value() && shs->defined();
  TORCH_CHECK(has_colors || has_shs, "either shs or colors_precomp must be given");
  if (has_colors) {
    check_tensor(*colors_precomp, "colors_precomp", {P, 3});
    in.colors = colors_precomp->data_ptr<float>();
  } else {
    check_tensor(*shs, "shs", {P, -1, 3});
    in.M = shs->size(1);
    TORCH_CHECK(in.M >= (sh_degree + 1) * (sh_degree + 1), "shs has ", in.M,
                " coefficients, sh_degree ", sh_degree, " needs ", (sh_degree + 1) * (sh_degree + 1));
    in.shs = shs->data_ptr<float>();
  }
  const bool has_cov = cov3D_precomp.has_value() && cov3D_precomp->defined();
  if (has_cov) {
    check_tensor(*cov3D_precomp, "cov3D_precomp", {P, 6});
    in.cov3d = cov3D_precomp->data_ptr<float>();
  } else {
    TORCH_CHECK(scales.has_value() && scales->defined() && rotations.has_value() &&
                    rotations->defined(),
                "either cov3D_precomp or scales and rotations must be given");
    check_tensor(*scales, "scales", {P, 3});
    check_tensor(*rotations, "rotations", {P, 4});
    in.scales = scales->data_ptr<float>();
    in.rots = rotations->data_ptr<float>();
  }
  in.H = (int)H;
  in.W = (int)W;
  in.grid_x = (in.W + kBlockX - 1) / kBlockX;
  in.grid_y = (in.H + kBlockY - 1) / kBlockY;
  in.tanfovx = (float)tanfovx;
  in.tanfovy = (float)tanfovy;
  in.focal_x = in.W / (2.0f * in.tanfovx);
  in.focal_y = in.H / (2.0f * in.tanfovy);
  in.scale_modifier = (float)scale_modifier;
  in.sh_degree = (int)sh_degree;
  in.antialiasing = antialiasing;
  in.means = means3D.data_ptr<float>();
  in.opac = opacities.data_ptr<float>();
  in.bg = bg.data_ptr<float>();
  in.V = viewmatrix.data_ptr<float>();
  in.Pm = projmatrix.data_ptr<float>();
  in.campos = campos.data_ptr<float>();
  return in;
}

inline Vec3 load3(const float* p) { return {p[0], p[1], p[2]}; }

inline Sym3 gaussian_cov3d(const Inputs& in, int64_t g) {
  if (in.cov3d != nullptr) {
    const float* c = in.cov3d + 6 * g;
    return {{c[0], c[1], c[2], c[3], c[4], c[5]}};
  }
  const float* q = in.rots + 4 * g;
  return compute_cov3d(load3(in.scales + 3 * g), in.scale_modifier, {q[0], q[1], q[2], q[3]});
}

// ------------------------------------------------------------------------------------------------
// 1. Preprocess
// ------------------------------------------------------------------------------------------------
void preprocess(const Inputs& in, float* geom, int32_t* radii, int32_t* rects, int64_t* ntiles) {
  at::parallel_for(0, in.P, 1024, [&](int64_t b, int64_t e) {
    for (int64_t g = b; g < e; ++g) {
      radii[g] = 0;
      ntiles[g] = 0;
      int32_t* rect = rects + 4 * g;
      rect[0] = rect[1] = rect[2] = rect[3] = 0;
      const Vec3 m = load3(in.means + 3 * g);
      const Vec3 t = transform_point_4x3(in.V, m);
      if (!(t.z > kNearPlane)) continue;  // also culls NaN
      const Vec4 ph = transform_point_4x4(in.Pm, m);
      const float p_w = 1.0f / (ph.w + kProjEps);
      const Vec3 ndc = {ph.x * p_w, ph.y * p_w, ph.z * p_w};
      const Sym3 cov3 = gaussian_cov3d(in, g);
      Cov2DCtx ctx;
      const Sym2 cov2 = compute_cov2d(t, in.focal_x, in.focal_y, in.tanfovx, in.tanfovy, cov3, in.V, ctx);
      const ConicResult cr = dilate_and_invert(cov2, in.antialiasing);
      if (cr.det == 0.0f) continue;
      const float radius = screen_radius(cr.dilated, cr.det);
      const Vec2 pix = {ndc2pix(ndc.x, in.W), ndc2pix(ndc.y, in.H)};
      if (!(radius >= 1.f) || !std::isfinite(pix.x) || !std::isfinite(pix.y) ||
          radius > 1e9f || std::fabs(pix.x) > 1e9f || std::fabs(pix.y) > 1e9f)
        continue;
      int minx, miny, maxx, maxy;
      get_rect(pix, (int)radius, in.grid_x, in.grid_y, minx, miny, maxx, maxy);
      const int64_t area = (int64_t)(maxx - minx) * (maxy - miny);
      if (area == 0) continue;
      Vec3 rgb;
      if (in.colors != nullptr) {
        rgb = load3(in.colors + 3 * g);
      } else {
        rgb = eval_sh(in.sh_degree, in.shs + g * in.M * 3, m, load3(in.campos));
        rgb = {rgb.x < 0.f ? 0.f : rgb.x, rgb.y < 0.f ? 0.f : rgb.y, rgb.z < 0.f ? 0.f : rgb.z};
      }
      const float o = in.opac[g] * cr.coef;
      float* gd = geom + kGStride * g;
      gd[kGPx] = pix.x;
      gd[kGPy] = pix.y;
      gd[kGConA] = cr.conic.a;
      gd[kGConB] = cr.conic.b;
      gd[kGConC] = cr.conic.c;
      gd[kGOpacity] = o;
      gd[kGR] = rgb.x;
      gd[kGG] = rgb.y;
      gd[kGB] = rgb.z;
      gd[kGZ] = t.z;
      gd[kGInvZ] = 1.0f / t.z;
      // Conservative half extents of {d : o exp(-d^T conic d / 2) >= 1/255}; pixels outside can
      // never pass the alpha test, so skipping them is exact. Negative = contributes nowhere.
      float bx, by;
      if (!(o >= kAlphaMin)) {
        bx = by = -1.f;
      } else if (cr.det > 0.f && cr.dilated.a > 0.f && cr.dilated.c > 0.f) {
        float k = logf(o / kAlphaMin);
        k = (k > 0.f ? k : 0.f) * 1.001f + 1e-3f;
        bx = sqrtf(2.f * k * cr.dilated.a) * 1.001f + 0.01f;
        by = sqrtf(2.f * k * cr.dilated.c) * 1.001f + 0.01f;
      } else {
        bx = by = std::numeric_limits<float>::infinity();
      }
      gd[kGBoxX] = bx;
      gd[kGBoxY] = by;
      radii[g] = (int32_t)radius;
      rect[0] = minx;
      rect[1] = miny;
      rect[2] = maxx;
      rect[3] = maxy;
      ntiles[g] = area;
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
// 3. Forward render of one tile
// ------------------------------------------------------------------------------------------------
struct RenderOut {
  float* color;      // [3, H, W]
  float* invdepth;   // [H, W]
  float* depth_acc;  // [H, W]
  float* alpha;      // [H, W]
  float* final_T;    // [H, W]
  int32_t* last;     // [H, W]
};

void render_tile(const Inputs& in, int64_t tile, const float* geom, const int32_t* binning,
                 const int32_t* tile_ranges, const RenderOut& out) {
  const int tx = (int)(tile % in.grid_x), ty = (int)(tile / in.grid_x);
  const int x0 = tx * kBlockX, y0 = ty * kBlockY;
  const int ncols = std::min(kBlockX, in.W - x0), nrows = std::min(kBlockY, in.H - y0);
  alignas(64) float T[kBlockSize], C0[kBlockSize], C1[kBlockSize], C2[kBlockSize];
  alignas(64) float ID[kBlockSize], DA[kBlockSize], act[kBlockSize];
  alignas(64) int32_t last[kBlockSize];
  alignas(64) float pixx[kBlockX];
  for (int i = 0; i < kBlockX; ++i) pixx[i] = (float)(x0 + i);
  int nact = 0;
  for (int p = 0; p < kBlockSize; ++p) {
    const bool inside = (p % kBlockX) < ncols && (p / kBlockX) < nrows;
    act[p] = inside ? 1.f : 0.f;
    nact += inside;
    T[p] = 1.f;
    C0[p] = C1[p] = C2[p] = ID[p] = DA[p] = 0.f;
    last[p] = -1;
  }
  const int32_t start = tile_ranges[tile], end = tile_ranges[tile + 1];
  for (int32_t j = start; j < end && nact > 0; ++j) {
    const float* gd = geom + kGStride * (int64_t)binning[2 * j];
    const float by = gd[kGBoxY];
    if (!(by >= 0.f)) continue;
    const float py = gd[kGPy];
    float flo = py - by, fhi = py + by;
    if (flo < (float)y0) flo = (float)y0;
    if (fhi > (float)(y0 + nrows - 1)) fhi = (float)(y0 + nrows - 1);
    if (!(flo <= fhi)) continue;
    const int r0 = (int)std::ceil(flo) - y0, r1 = (int)std::floor(fhi) - y0;
    const float px = gd[kGPx], cA = gd[kGConA], cB = gd[kGConB], cC = gd[kGConC];
    const float o = gd[kGOpacity];
    const float f0 = gd[kGR], f1 = gd[kGG], f2 = gd[kGB], fiz = gd[kGInvZ], fz = gd[kGZ];
    const int32_t jl = j - start;
    int nstop = 0;
    for (int r = r0; r <= r1; ++r) {
      const float dy = py - (float)(y0 + r);
      const int base = r * kBlockX;
      float* Tr = T + base;
      float* C0r = C0 + base;
      float* C1r = C1 + base;
      float* C2r = C2 + base;
      float* IDr = ID + base;
      float* DAr = DA + base;
      float* actr = act + base;
      int32_t* lastr = last + base;
      GRP_SIMD_RED("omp simd reduction(+ : nstop)")
      for (int i = 0; i < kBlockX; ++i) {
        const float dx = px - pixx[i];
        const float power = -0.5f * (cA * dx * dx + cC * dy * dy) - cB * dx * dy;
        const float G = exp_nonpos(power);
        const float oG = o * G;
        const float alpha = oG < kAlphaMax ? oG : kAlphaMax;
        const bool valid = actr[i] != 0.f && !(power > 0.f) && !(alpha < kAlphaMin);
        const float Tc = Tr[i];
        const float testT = Tc * (1.f - alpha);
        const bool stop = valid && testT < kTransmittanceMin;
        const bool contrib = valid && !stop;
        const float w = contrib ? alpha * Tc : 0.f;
        C0r[i] += f0 * w;
        C1r[i] += f1 * w;
        C2r[i] += f2 * w;
        IDr[i] += fiz * w;
        DAr[i] += fz * w;
        Tr[i] = contrib ? testT : Tc;
        lastr[i] = contrib ? jl : lastr[i];
        actr[i] = stop ? 0.f : actr[i];
        nstop += stop ? 1 : 0;
      }
    }
    nact -= nstop;
  }
  const int64_t HW = (int64_t)in.H * in.W;
  for (int r = 0; r < nrows; ++r) {
    for (int c = 0; c < ncols; ++c) {
      const int p = r * kBlockX + c;
      const int64_t pix = (int64_t)(y0 + r) * in.W + (x0 + c);
      out.color[pix] = C0[p] + T[p] * in.bg[0];
      out.color[HW + pix] = C1[p] + T[p] * in.bg[1];
      out.color[2 * HW + pix] = C2[p] + T[p] * in.bg[2];
      out.invdepth[pix] = ID[p];
      out.depth_acc[pix] = DA[p];
      out.alpha[pix] = 1.f - T[p];
      out.final_T[pix] = T[p];
      out.last[pix] = last[p];
    }
  }
}

// ------------------------------------------------------------------------------------------------
// 4. Backward of one tile: writes the slot of every entry of the tile's list.
// ------------------------------------------------------------------------------------------------
struct GradIn {
  const float* color;      // [3, H, W]
  const float* invdepth;   // [H, W]
  const float* depth_acc;  // [H, W]
  const float* alpha;      // [H, W]
};

void backward_tile(const Inputs& in, int64_t tile, const float* geom, const int32_t* binning,
                   const int32_t* tile_ranges, const float* final_T, const int32_t* last_contrib,
                   const GradIn& gin, float* slots, double* dbg_tile) {
  const int tx = (int)(tile % in.grid_x), ty = (int)(tile / in.grid_x);
  const int x0 = tx * kBlockX, y0 = ty * kBlockY;
  const int ncols = std::min(kBlockX, in.W - x0), nrows = std::min(kBlockY, in.H - y0);
  const int64_t HW = (int64_t)in.H * in.W;
  alignas(64) float T[kBlockSize], lastA[kBlockSize], kbg[kBlockSize];
  alignas(64) float acc[kNumFeat][kBlockSize], lf[kNumFeat][kBlockSize], dp[kNumFeat][kBlockSize];
  alignas(64) int32_t last[kBlockSize];
  alignas(64) float pixx[kBlockX];
  for (int i = 0; i < kBlockX; ++i) pixx[i] = (float)(x0 + i);
  int32_t maxlast = -1;
  double dbg[3] = {0, 0, 0};
  for (int p = 0; p < kBlockSize; ++p) {
    const int r = p / kBlockX, c = p % kBlockX;
    T[p] = 0.f;
    lastA[p] = 0.f;
    kbg[p] = 0.f;
    last[p] = -1;
    for (int k = 0; k < kNumFeat; ++k) acc[k][p] = lf[k][p] = dp[k][p] = 0.f;
    if (r >= nrows || c >= ncols) continue;
    const int64_t pix = (int64_t)(y0 + r) * in.W + (x0 + c);
    const float Tf = final_T[pix];
    T[p] = Tf;
    last[p] = last_contrib[pix];
    maxlast = std::max(maxlast, last[p]);
    dp[0][p] = gin.color[pix];
    dp[1][p] = gin.color[HW + pix];
    dp[2][p] = gin.color[2 * HW + pix];
    dp[3][p] = gin.invdepth[pix];
    dp[4][p] = gin.depth_acc[pix];
    const float bgdot = in.bg[0] * dp[0][p] + in.bg[1] * dp[1][p] + in.bg[2] * dp[2][p];
    // dL/dalpha_i gets T_final / (1 - alpha_i) * (dL/dalpha_out - bg . dL/dpixel)
    kbg[p] = Tf * (gin.alpha[pix] - bgdot);
    for (int k = 0; k < 3; ++k) dbg[k] += (double)Tf * (double)dp[k][p];
  }
  for (int k = 0; k < 3; ++k) dbg_tile[k] = dbg[k];
  const int32_t start = tile_ranges[tile], end = tile_ranges[tile + 1];
  // Entries behind every pixel's last contributor get zero slots.
  for (int32_t j = start + maxlast + 1; j < end; ++j) {
    float* s = slots + (int64_t)binning[2 * j + 1] * kSlot;
    for (int k = 0; k < kSlot; ++k) s[k] = 0.f;
  }
  for (int32_t j = start + maxlast; j >= start; --j) {
    float* slot = slots + (int64_t)binning[2 * j + 1] * kSlot;
    for (int k = 0; k < kSlot; ++k) slot[k] = 0.f;
    const float* gd = geom + kGStride * (int64_t)binning[2 * j];
    const float by = gd[kGBoxY];
    if (!(by >= 0.f)) continue;
    const float py = gd[kGPy];
    float flo = py - by, fhi = py + by;
    if (flo < (float)y0) flo = (float)y0;
    if (fhi > (float)(y0 + nrows - 1)) fhi = (float)(y0 + nrows - 1);
    if (!(flo <= fhi)) continue;
    const int r0 = (int)std::ceil(flo) - y0, r1 = (int)std::floor(fhi) - y0;
    const float px = gd[kGPx], cA = gd[kGConA], cB = gd[kGConB], cC = gd[kGConC];
    const float o = gd[kGOpacity];
    const float f[kNumFeat] = {gd[kGR], gd[kGG], gd[kGB], gd[kGInvZ], gd[kGZ]};
    const int32_t jl = j - start;
    alignas(64) float s_dx[kBlockX], s_dy[kBlockX], s_cA[kBlockX], s_cB[kBlockX], s_cC[kBlockX];
    alignas(64) float s_o[kBlockX], s_f[kNumFeat][kBlockX];
    for (int i = 0; i < kBlockX; ++i) {
      s_dx[i] = s_dy[i] = s_cA[i] = s_cB[i] = s_cC[i] = s_o[i] = 0.f;
      for (int k = 0; k < kNumFeat; ++k) s_f[k][i] = 0.f;
    }
    for (int r = r0; r <= r1; ++r) {
      const float dy = py - (float)(y0 + r);
      const int base = r * kBlockX;
      float* Tr = T + base;
      float* lAr = lastA + base;
      const float* kbgr = kbg + base;
      const int32_t* lastr = last + base;
      float* a0 = acc[0] + base; float* a1 = acc[1] + base; float* a2 = acc[2] + base;
      float* a3 = acc[3] + base; float* a4 = acc[4] + base;
      float* l0 = lf[0] + base; float* l1 = lf[1] + base; float* l2 = lf[2] + base;
      float* l3 = lf[3] + base; float* l4 = lf[4] + base;
      const float* d0 = dp[0] + base; const float* d1 = dp[1] + base; const float* d2 = dp[2] + base;
      const float* d3 = dp[3] + base; const float* d4 = dp[4] + base;
      GRP_SIMD
      for (int i = 0; i < kBlockX; ++i) {
        const float dx = px - pixx[i];
        const float power = -0.5f * (cA * dx * dx + cC * dy * dy) - cB * dx * dy;
        const float G = exp_nonpos(power);
        const float oG = o * G;
        const float alpha = oG < kAlphaMax ? oG : kAlphaMax;
        const bool valid = jl <= lastr[i] && !(power > 0.f) && !(alpha < kAlphaMin);
        const float a = valid ? alpha : 0.f;
        const float one_m_a = 1.f - a;
        const float Tn = Tr[i] / one_m_a;  // unchanged when invalid (a = 0)
        const float w = a * Tn;
        const float la = lAr[i];
        const float n0 = la * l0[i] + (1.f - la) * a0[i];
        const float n1 = la * l1[i] + (1.f - la) * a1[i];
        const float n2 = la * l2[i] + (1.f - la) * a2[i];
        const float n3 = la * l3[i] + (1.f - la) * a3[i];
        const float n4 = la * l4[i] + (1.f - la) * a4[i];
        float dLda = (f[0] - n0) * d0[i] + (f[1] - n1) * d1[i] + (f[2] - n2) * d2[i] +
                     (f[3] - n3) * d3[i] + (f[4] - n4) * d4[i];
        dLda = dLda * Tn + kbgr[i] / one_m_a;
        Tr[i] = Tn;
        a0[i] = valid ? n0 : a0[i];
        a1[i] = valid ? n1 : a1[i];
        a2[i] = valid ? n2 : a2[i];
        a3[i] = valid ? n3 : a3[i];
        a4[i] = valid ? n4 : a4[i];
        l0[i] = valid ? f[0] : l0[i];
        l1[i] = valid ? f[1] : l1[i];
        l2[i] = valid ? f[2] : l2[i];
        l3[i] = valid ? f[3] : l3[i];
        l4[i] = valid ? f[4] : l4[i];
        lAr[i] = valid ? alpha : la;
        s_f[0][i] += w * d0[i];
        s_f[1][i] += w * d1[i];
        s_f[2][i] += w * d2[i];
        s_f[3][i] += w * d3[i];
        s_f[4][i] += w * d4[i];
        // alpha = min(0.99, o G): no gradient to o G where the clamp is active
        const bool pass = valid && !(oG > kAlphaMax);
        const float dLdG = pass ? o * dLda : 0.f;
        s_o[i] += pass ? G * dLda : 0.f;
        const float gdx = G * dx, gdy = G * dy;
        s_dx[i] += dLdG * (-gdx * cA - gdy * cB);
        s_dy[i] += dLdG * (-gdy * cC - gdx * cB);
        s_cA[i] += -0.5f * gdx * dx * dLdG;
        s_cB[i] += -gdx * dy * dLdG;
        s_cC[i] += -0.5f * gdy * dy * dLdG;
      }
    }
    float red[kSlot] = {0};
    for (int i = 0; i < kBlockX; ++i) {
      red[0] += s_dx[i];
      red[1] += s_dy[i];
      red[2] += s_cA[i];
      red[3] += s_cB[i];
      red[4] += s_cC[i];
      red[5] += s_o[i];
      for (int k = 0; k < kNumFeat; ++k) red[6 + k] += s_f[k][i];
    }
    for (int k = 0; k < kSlot; ++k) slot[k] = red[k];
  }
}

}  // namespace

// ------------------------------------------------------------------------------------------------
// Forward
// ------------------------------------------------------------------------------------------------
std::vector<at::Tensor> rasterize_forward_cpu(
    const at::Tensor& means3D, const at::Tensor& opacities, const std::optional<at::Tensor>& shs,
    const std::optional<at::Tensor>& colors_precomp, const std::optional<at::Tensor>& scales,
    const std::optional<at::Tensor>& rotations, const std::optional<at::Tensor>& cov3D_precomp,
    const at::Tensor& bg, const at::Tensor& viewmatrix, const at::Tensor& projmatrix,
    const at::Tensor& campos, int64_t image_height, int64_t image_width, double tanfovx,
    double tanfovy, double scale_modifier, int64_t sh_degree, bool prefiltered, bool antialiasing) {
  (void)prefiltered;
  const Inputs in = check_inputs(means3D, opacities, shs, colors_precomp, scales, rotations,
                                 cov3D_precomp, bg, viewmatrix, projmatrix, campos, image_height,
                                 image_width, tanfovx, tanfovy, scale_modifier, sh_degree,
                                 antialiasing);
  const int64_t P = in.P;
  const auto fopt = means3D.options();
  const auto iopt = fopt.dtype(at::kInt);
  const int64_t num_tiles = (int64_t)in.grid_x * in.grid_y;

  at::Tensor color = at::empty({3, in.H, in.W}, fopt);
  at::Tensor invdepth = at::empty({1, in.H, in.W}, fopt);
  at::Tensor depth_acc = at::empty({1, in.H, in.W}, fopt);
  at::Tensor alpha = at::empty({1, in.H, in.W}, fopt);
  at::Tensor final_T = at::empty({in.H, in.W}, fopt);
  at::Tensor last_contrib = at::empty({in.H, in.W}, iopt);
  at::Tensor radii = at::empty({P}, iopt);
  at::Tensor geom = at::empty({P, kGStride}, fopt);
  at::Tensor offsets = at::empty({P + 1}, fopt.dtype(at::kLong));
  std::vector<int32_t> rects(4 * P);

  int64_t* off = offsets.data_ptr<int64_t>();
  preprocess(in, geom.data_ptr<float>(), radii.data_ptr<int32_t>(), rects.data(), off + 1);
  off[0] = 0;
  for (int64_t g = 0; g < P; ++g) off[g + 1] += off[g];
  const int64_t num_rendered = off[P];
  TORCH_CHECK(num_rendered < (int64_t)std::numeric_limits<int32_t>::max(),
              "too many (tile, Gaussian) pairs: ", num_rendered);

  // 2. Binning.
  const float* gm = geom.data_ptr<float>();
  const std::vector<int32_t> order = sort_by_depth(gm, radii.data_ptr<int32_t>(), P);
  at::Tensor tile_ranges = at::zeros({num_tiles + 1}, iopt);
  at::Tensor binning = at::empty({num_rendered, 2}, iopt);
  {
    int32_t* tr = tile_ranges.data_ptr<int32_t>();
    int32_t* bin = binning.data_ptr<int32_t>();
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
  RenderOut out{color.data_ptr<float>(), invdepth.data_ptr<float>(), depth_acc.data_ptr<float>(),
                alpha.data_ptr<float>(), final_T.data_ptr<float>(), last_contrib.data_ptr<int32_t>()};
  const int32_t* bin = binning.data_ptr<int32_t>();
  const int32_t* tr = tile_ranges.data_ptr<int32_t>();
  parallel_dynamic(num_tiles, [&](int64_t t) { render_tile(in, t, gm, bin, tr, out); });

  return {color, radii, invdepth, depth_acc, alpha, geom, binning, tile_ranges, offsets, final_T,
          last_contrib};
}

// ------------------------------------------------------------------------------------------------
// Backward
// ------------------------------------------------------------------------------------------------
std::vector<at::Tensor> rasterize_backward_cpu(
    const at::Tensor& means3D, const at::Tensor& opacities, const std::optional<at::Tensor>& shs,
    const std::optional<at::Tensor>& colors_precomp, const std::optional<at::Tensor>& scales,
    const std::optional<at::Tensor>& rotations, const std::optional<at::Tensor>& cov3D_precomp,
    const at::Tensor& bg, const at::Tensor& viewmatrix, const at::Tensor& projmatrix,
    const at::Tensor& campos, int64_t image_height, int64_t image_width, double tanfovx,
    double tanfovy, double scale_modifier, int64_t sh_degree, bool antialiasing,
    const at::Tensor& radii, const at::Tensor& geom, const at::Tensor& binning,
    const at::Tensor& tile_ranges, const at::Tensor& offsets, const at::Tensor& final_T,
    const at::Tensor& last_contrib, const at::Tensor& grad_color, const at::Tensor& grad_invdepth,
    const at::Tensor& grad_depth_acc, const at::Tensor& grad_alpha, bool compute_camera_grad) {
  const Inputs in = check_inputs(means3D, opacities, shs, colors_precomp, scales, rotations,
                                 cov3D_precomp, bg, viewmatrix, projmatrix, campos, image_height,
                                 image_width, tanfovx, tanfovy, scale_modifier, sh_degree,
                                 antialiasing);
  const int64_t P = in.P;
  const int64_t num_tiles = (int64_t)in.grid_x * in.grid_y;
  check_tensor(grad_color, "grad_color", {3, in.H, in.W});
  check_tensor(grad_invdepth, "grad_invdepth", {1, in.H, in.W});
  check_tensor(grad_depth_acc, "grad_depth_acc", {1, in.H, in.W});
  check_tensor(grad_alpha, "grad_alpha", {1, in.H, in.W});
  check_tensor(geom, "geom", {P, kGStride});
  check_tensor(final_T, "final_T", {in.H, in.W});
  check_int_tensor(radii, "radii", at::kInt);
  check_int_tensor(binning, "binning", at::kInt);
  check_int_tensor(tile_ranges, "tile_ranges", at::kInt);
  check_int_tensor(offsets, "offsets", at::kLong);
  check_int_tensor(last_contrib, "last_contrib", at::kInt);
  TORCH_CHECK(radii.numel() == P && offsets.numel() == P + 1 && tile_ranges.numel() == num_tiles + 1 &&
                  last_contrib.numel() == (int64_t)in.H * in.W,
              "saved forward state does not match the inputs");
  const int64_t num_rendered = offsets.data_ptr<int64_t>()[P];
  TORCH_CHECK(binning.dim() == 2 && binning.size(0) == num_rendered && binning.size(1) == 2 &&
                  tile_ranges.data_ptr<int32_t>()[num_tiles] == num_rendered,
              "saved binning state does not match the inputs");

  const auto fopt = means3D.options();
  at::Tensor dL_dmeans3D = at::zeros({P, 3}, fopt);
  at::Tensor dL_dmeans2D = at::zeros({P, 3}, fopt);
  at::Tensor dL_dopac = at::zeros({P, 1}, fopt);
  at::Tensor dL_dshs, dL_dcolors, dL_dscales, dL_drots, dL_dcov;
  if (in.colors != nullptr) dL_dcolors = at::zeros({P, 3}, fopt);
  else dL_dshs = at::zeros({P, in.M, 3}, fopt);
  if (in.cov3d != nullptr) {
    dL_dcov = at::zeros({P, 6}, fopt);
  } else {
    dL_dscales = at::zeros({P, 3}, fopt);
    dL_drots = at::zeros({P, 4}, fopt);
  }
  // 4. Per-tile backward into per-entry slots.
  std::vector<float> slots((size_t)num_rendered * kSlot);
  std::vector<double> dbg_tiles((size_t)num_tiles * 3);
  const float* gm = geom.data_ptr<float>();
  const int32_t* bin = binning.data_ptr<int32_t>();
  const int32_t* tr = tile_ranges.data_ptr<int32_t>();
  const GradIn gin{grad_color.data_ptr<float>(), grad_invdepth.data_ptr<float>(),
                   grad_depth_acc.data_ptr<float>(), grad_alpha.data_ptr<float>()};
  const float* fT = final_T.data_ptr<float>();
  const int32_t* lc = last_contrib.data_ptr<int32_t>();
  parallel_dynamic(num_tiles, [&](int64_t t) {
    backward_tile(in, t, gm, bin, tr, fT, lc, gin, slots.data(), dbg_tiles.data() + 3 * t);
  });
  at::Tensor dL_dbg = at::empty({3}, fopt);
  {
    double s[3] = {0, 0, 0};
    for (int64_t t = 0; t < num_tiles; ++t)
      for (int k = 0; k < 3; ++k) s[k] += dbg_tiles[3 * t + k];
    for (int k = 0; k < 3; ++k) dL_dbg.data_ptr<float>()[k] = (float)s[k];
  }

  // 5. Per-Gaussian backward.
  const int64_t nblocks = (P + kGaussBlock - 1) / kGaussBlock;
  std::vector<double> cam_blocks(compute_camera_grad ? (size_t)nblocks * kCamGrad : 0, 0.0);
  const int32_t* rad = radii.data_ptr<int32_t>();
  const int64_t* off = offsets.data_ptr<int64_t>();
  float* o_m3 = dL_dmeans3D.data_ptr<float>();
  float* o_m2 = dL_dmeans2D.data_ptr<float>();
  float* o_op = dL_dopac.data_ptr<float>();
  float* o_sh = dL_dshs.defined() ? dL_dshs.data_ptr<float>() : nullptr;
  float* o_col = dL_dcolors.defined() ? dL_dcolors.data_ptr<float>() : nullptr;
  float* o_sc = dL_dscales.defined() ? dL_dscales.data_ptr<float>() : nullptr;
  float* o_rot = dL_drots.defined() ? dL_drots.data_ptr<float>() : nullptr;
  float* o_cov = dL_dcov.defined() ? dL_dcov.data_ptr<float>() : nullptr;
  const Vec3 cpos = load3(in.campos);
  at::parallel_for(0, nblocks, 1, [&](int64_t b0, int64_t b1) {
    for (int64_t blk = b0; blk < b1; ++blk) {
      double* cam = compute_camera_grad ? cam_blocks.data() + blk * kCamGrad : nullptr;
      double* dV = cam;
      double* dP = cam ? cam + 16 : nullptr;
      double* dC = cam ? cam + 32 : nullptr;
      const int64_t g1 = std::min(P, (blk + 1) * kGaussBlock);
      for (int64_t g = blk * kGaussBlock; g < g1; ++g) {
        if (rad[g] <= 0) continue;
        float s[kSlot] = {0};
        for (int64_t e = off[g]; e < off[g + 1]; ++e) {
          const float* sl = slots.data() + e * kSlot;
          for (int k = 0; k < kSlot; ++k) s[k] += sl[k];
        }
        const Vec3 m = load3(in.means + 3 * g);
        const Vec3 t = transform_point_4x3(in.V, m);
        const Vec4 ph = transform_point_4x4(in.Pm, m);
        const Sym3 cov3 = gaussian_cov3d(in, g);
        Cov2DCtx ctx;
        const Sym2 cov2 = compute_cov2d(t, in.focal_x, in.focal_y, in.tanfovx, in.tanfovy, cov3, in.V, ctx);
        const ConicResult cr = dilate_and_invert(cov2, in.antialiasing);
        // opacity_eff = opacity * coef
        o_op[g] = s[5] * cr.coef;
        const float dcoef = s[5] * in.opac[g];
        const Sym2 dcov2 = dilate_and_invert_vjp(cov2, in.antialiasing, {s[2], s[3], s[4]}, dcoef);
        Vec3 dt = {0.f, 0.f, -s[9] / (t.z * t.z) + s[10]};  // features 1/z and z
        Sym3 dcov3;
        compute_cov2d_vjp(t, in.focal_x, in.focal_y, cov3, in.V, ctx, dcov2, dt, dcov3, dV);
        if (o_cov != nullptr) {
          for (int k = 0; k < 6; ++k) o_cov[6 * g + k] = dcov3.v[k];
        } else {
          const float* q = in.rots + 4 * g;
          Vec3 dsc;
          Vec4 dq;
          compute_cov3d_vjp(load3(in.scales + 3 * g), in.scale_modifier, {q[0], q[1], q[2], q[3]},
                            dcov3, dsc, dq);
          o_sc[3 * g + 0] = dsc.x;
          o_sc[3 * g + 1] = dsc.y;
          o_sc[3 * g + 2] = dsc.z;
          o_rot[4 * g + 0] = dq.x;
          o_rot[4 * g + 1] = dq.y;
          o_rot[4 * g + 2] = dq.z;
          o_rot[4 * g + 3] = dq.w;
        }
        const Vec2 dndc = {s[0] * 0.5f * in.W, s[1] * 0.5f * in.H};
        o_m2[3 * g + 0] = dndc.x;
        o_m2[3 * g + 1] = dndc.y;
        Vec3 dm = {0.f, 0.f, 0.f};
        project_vjp(in.Pm, m, ph, dndc, dm, dP);
        transform_point_4x3_vjp(in.V, m, dt, dm, dV);
        if (o_col != nullptr) {
          o_col[3 * g + 0] = s[6];
          o_col[3 * g + 1] = s[7];
          o_col[3 * g + 2] = s[8];
        } else {
          const Vec3 dv = eval_sh_vjp(in.sh_degree, in.shs + g * in.M * 3, m, cpos,
                                      {s[6], s[7], s[8]}, o_sh + g * in.M * 3);
          if (in.sh_degree > 0) {
            dm.x += dv.x;
            dm.y += dv.y;
            dm.z += dv.z;
            if (dC != nullptr) {
              dC[0] -= dv.x;
              dC[1] -= dv.y;
              dC[2] -= dv.z;
            }
          }
        }
        o_m3[3 * g + 0] = dm.x;
        o_m3[3 * g + 1] = dm.y;
        o_m3[3 * g + 2] = dm.z;
      }
    }
  });
  at::Tensor dL_dV, dL_dP, dL_dcampos;
  if (compute_camera_grad) {
    double sum[kCamGrad] = {0};
    for (int64_t b = 0; b < nblocks; ++b)
      for (int k = 0; k < kCamGrad; ++k) sum[k] += cam_blocks[b * kCamGrad + k];
    dL_dV = at::empty({4, 4}, fopt);
    dL_dP = at::empty({4, 4}, fopt);
    dL_dcampos = at::empty({3}, fopt);
    for (int k = 0; k < 16; ++k) dL_dV.data_ptr<float>()[k] = (float)sum[k];
    for (int k = 0; k < 16; ++k) dL_dP.data_ptr<float>()[k] = (float)sum[16 + k];
    for (int k = 0; k < 3; ++k) dL_dcampos.data_ptr<float>()[k] = (float)sum[32 + k];
  }
  return {dL_dmeans3D, dL_dmeans2D, dL_dopac, dL_dshs, dL_dcolors, dL_dscales, dL_drots, dL_dcov,
          dL_dbg, dL_dV, dL_dP, dL_dcampos};
}

at::Tensor mark_visible_cpu(const at::Tensor& means3D, const at::Tensor& viewmatrix,
                            const at::Tensor& projmatrix) {
  check_tensor(means3D, "means3D", {-1, 3});
  check_tensor(viewmatrix, "viewmatrix", {4, 4});
  check_tensor(projmatrix, "projmatrix", {4, 4});
  const int64_t P = means3D.size(0);
  at::Tensor out = at::empty({P}, means3D.options().dtype(at::kBool));
  const float* m = means3D.data_ptr<float>();
  const float* V = viewmatrix.data_ptr<float>();
  bool* o = out.data_ptr<bool>();
  at::parallel_for(0, P, 4096, [&](int64_t b, int64_t e) {
    for (int64_t g = b; g < e; ++g) o[g] = transform_point_4x3(V, load3(m + 3 * g)).z > kNearPlane;
  });
  return out;
}

}  // namespace grp
