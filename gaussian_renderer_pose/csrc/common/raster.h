// Glue shared by the CPU kernel (../cpu/rasterize_cpu.cpp) and the CUDA kernels (../cuda/kernels.cu):
// the argument struct of one rasterization, the layout of the saved per-Gaussian record and of the
// backward slots, and the per-Gaussian preprocess / backward bodies. Header-only and GRP_HD (no
// torch/ATen), so a .cu file includes it unchanged; the torch-side filling of RasterArgs from
// tensors is in raster_args_torch.h (host only).
#pragma once

#include <cmath>
#include <cstdint>

#include "config.h"
#include "host_device.h"
#include "math.h"
#include "sh.h"

namespace grp {

// Per-Gaussian record written by the preprocess (one cache line; saved as geom [P, 16]).
enum GeomField : int {
  kGPx = 0, kGPy, kGConA, kGConB, kGConC, kGOpacity, kGR, kGG, kGB, kGInvZ, kGZ, kGBoxX, kGBoxY,
  kGStride = 16
};
constexpr int kNumFeat = 5;                  // r, g, b, 1/z, z
constexpr int kSlot = 2 + 3 + 1 + kNumFeat;  // dL/dxy (pixels), dL/dconic, dL/dopacity_eff, dL/dfeat
constexpr int kCamGrad = 16 + 16 + 3;        // viewmatrix, projmatrix, campos

// Inputs of one rasterization (pointers into the backend's memory; optional ones are nullptr when
// absent).
struct RasterArgs {
  int64_t P = 0;
  int H = 0, W = 0;
  int grid_x = 0, grid_y = 0;
  float tanfovx = 0.f, tanfovy = 0.f, focal_x = 0.f, focal_y = 0.f, scale_modifier = 1.f;
  int sh_degree = 0;
  int64_t M = 0;  // SH coefficients per Gaussian (shs [P, M, 3])
  bool antialiasing = false;
  const float* means = nullptr;       // [P, 3]
  const float* opac = nullptr;        // [P, 1]
  const float* shs = nullptr;         // [P, M, 3]   (or nullptr); [P, 1, 3] with shs_rest
  const float* shs_rest = nullptr;    // [P, M - 1, 3] (or nullptr: every coefficient in shs)
  const float* colors = nullptr;      // [P, 3]      (or nullptr)
  const float* scales = nullptr;      // [P, 3]      (or nullptr)
  const float* rots = nullptr;        // [P, 4]      (or nullptr)
  const float* cov3d = nullptr;       // [P, 6]      (or nullptr)
  const float* bg = nullptr;          // [3]
  const float* viewmatrix = nullptr;  // [16]
  const float* projmatrix = nullptr;  // [16]
  const float* campos = nullptr;      // [3]
};

// Per-Gaussian gradient outputs (nullptr where the input is absent).
struct GaussianGrads {
  float* means3D;  // [P, 3]
  float* means2D;  // [P, 3] (d/d NDC xy; z stays 0)
  float* opac;     // [P, 1]
  float* shs;      // [P, M, 3]
  float* colors;   // [P, 3]
  float* scales;   // [P, 3]
  float* rots;     // [P, 4]
  float* cov3d;    // [P, 6]
  float* shs_rest; // [P, M - 1, 3] (SH in two tensors; shs is then [P, 1, 3])
};

// Output images of the forward render.
struct RenderOutputs {
  float* color;      // [3, H, W]
  float* invdepth;   // [H, W]
  float* depth_acc;  // [H, W]
  float* alpha;      // [H, W]
  float* final_T;    // [H, W]
  int32_t* last;     // [H, W]
};

// Gradients of the loss w.r.t. the output images (inputs of the backward render).
struct GradImages {
  const float* color;      // [3, H, W]
  const float* invdepth;   // [H, W]
  const float* depth_acc;  // [H, W]
  const float* alpha;      // [H, W]
};

GRP_FORCE_INLINE Vec3 load3(const float* p) { return {p[0], p[1], p[2]}; }

// World covariance of Gaussian g (precomputed, or from scale and rotation).
GRP_FORCE_INLINE Sym3 gaussian_cov3d(const RasterArgs& a, int64_t g) {
  if (a.cov3d != nullptr) {
    const float* c = a.cov3d + 6 * g;
    return {{c[0], c[1], c[2], c[3], c[4], c[5]}};
  }
  const float* q = a.rots + 4 * g;
  return compute_cov3d(load3(a.scales + 3 * g), a.scale_modifier, {q[0], q[1], q[2], q[3]});
}

// Result of preprocess_gaussian: radius 0 = culled (the record is all zeros).
struct PreprocessResult {
  int32_t radius;
  int64_t area;  // tiles touched
  int rect[4];   // minx, miny, maxx, maxy (tiles)
};

// The record of a culled Gaussian: all zeros.
GRP_FORCE_INLINE PreprocessResult culled_record(float* gd) {
  for (int k = 0; k < kGStride; ++k) gd[k] = 0.f;
  return {0, 0, {0, 0, 0, 0}};
}

// The screen-space culls of a projected Gaussian (radius below 1 or absurd, centre absurd, no tile
// touched); false when culled, else res gets the radius, the tile rect and its area.
GRP_FORCE_INLINE bool screen_footprint(const RasterArgs& a, Vec2 pix, float radius,
                                       PreprocessResult& res) {
  // !(|v| <= 1e9) also rejects NaN and +-inf.
  if (!(radius >= 1.f) || radius > 1e9f || !(fabsf(pix.x) <= 1e9f) || !(fabsf(pix.y) <= 1e9f))
    return false;
  int minx, miny, maxx, maxy;
  get_rect(pix, (int)radius, a.grid_x, a.grid_y, minx, miny, maxx, maxy);
  const int64_t area = (int64_t)(maxx - minx) * (maxy - miny);
  if (area == 0) return false;
  res.radius = (int32_t)radius;
  res.area = area;
  res.rect[0] = minx;
  res.rect[1] = miny;
  res.rect[2] = maxx;
  res.rect[3] = maxy;
  return true;
}

// Writes the geom record gd[kGStride] of visible Gaussian g: pixel centre, conic, effective
// opacity, colour rgb (clamped), depth tz, the alpha >= 1/255 box, zero padding.
GRP_FORCE_INLINE void write_geom_record(const RasterArgs& a, int64_t g, Vec2 pix,
                                        const ConicResult& cr, Vec3 rgb, float tz, float* gd) {
  const float o = a.opac[g] * cr.coef;
  gd[kGPx] = pix.x;
  gd[kGPy] = pix.y;
  gd[kGConA] = cr.conic.a;
  gd[kGConB] = cr.conic.b;
  gd[kGConC] = cr.conic.c;
  gd[kGOpacity] = o;
  gd[kGR] = rgb.x;
  gd[kGG] = rgb.y;
  gd[kGB] = rgb.z;
  gd[kGZ] = tz;
  gd[kGInvZ] = 1.0f / tz;
  // Conservative half extents of {d : o exp(-d^T conic d / 2) >= 1/255}; pixels outside can never
  // pass the alpha test, so skipping them is exact (the GPU evaluates every pixel of the tile, which
  // is exact as well). Negative = contributes nowhere.
  float bx, by;
  if (!(o >= kAlphaMin)) {
    bx = by = -1.f;
  } else if (cr.det > 0.f && cr.dilated.a > 0.f && cr.dilated.c > 0.f) {
    float k = logf(o / kAlphaMin);
    k = (k > 0.f ? k : 0.f) * 1.001f + 1e-3f;
    bx = sqrtf(2.f * k * cr.dilated.a) * 1.001f + 0.01f;
    by = sqrtf(2.f * k * cr.dilated.c) * 1.001f + 0.01f;
  } else {
    bx = by = INFINITY;
  }
  gd[kGBoxX] = bx;
  gd[kGBoxY] = by;
  for (int k = kGBoxY + 1; k < kGStride; ++k) gd[k] = 0.f;  // padding
}

// Most SH coefficients read (degree 3), 3 floats each.
constexpr int kMaxShFloats = 16 * 3;

// The SH coefficients of Gaussian g, 3 floats each: a pointer into shs, or, with the SH in two
// tensors (shs_rest), the (sh_degree + 1)^2 that are read, gathered into buf[kMaxShFloats]. The
// values are the same either way, so is every result computed from them.
GRP_FORCE_INLINE const float* gaussian_sh(const RasterArgs& a, int64_t g, float* buf) {
  if (a.shs_rest == nullptr) return a.shs + g * a.M * 3;
  const int n = (a.sh_degree + 1) * (a.sh_degree + 1);
  const float* rest = a.shs_rest + g * (a.M - 1) * 3;
  for (int c = 0; c < 3; ++c) buf[c] = a.shs[3 * g + c];
  for (int k = 3; k < 3 * n; ++k) buf[k] = rest[k - 3];
  return buf;
}

// The inverse of gaussian_sh's gather for a gradient, SH in two tensors: d[3 (sh_degree + 1)^2]
// to Gaussian g's rows of dshs [P, 1, 3] and dshs_rest [P, M - 1, 3] (the coefficients not read
// are left as they are).
GRP_FORCE_INLINE void scatter_sh_grad(const RasterArgs& a, int64_t g, const float* d, float* dshs,
                                      float* dshs_rest) {
  const int n = (a.sh_degree + 1) * (a.sh_degree + 1);
  float* rest = dshs_rest + g * (a.M - 1) * 3;
  for (int c = 0; c < 3; ++c) dshs[3 * g + c] = d[c];
  for (int k = 3; k < 3 * n; ++k) rest[k - 3] = d[k];
}

// The colour of Gaussian g seen from campos (precomputed, or SH clamped at 0).
GRP_FORCE_INLINE Vec3 gaussian_colour(const RasterArgs& a, int64_t g, Vec3 m) {
  if (a.colors != nullptr) return load3(a.colors + 3 * g);
  float buf[kMaxShFloats];
  const Vec3 rgb = eval_sh(a.sh_degree, gaussian_sh(a, g, buf), m, load3(a.campos));
  return {rgb.x < 0.f ? 0.f : rgb.x, rgb.y < 0.f ? 0.f : rgb.y, rgb.z < 0.f ? 0.f : rgb.z};
}

// Preprocess of Gaussian g (cull, project, cov2D/conic, radius, tile rect, colour) with V / Pm the
// view / projection matrices (a.viewmatrix / a.projmatrix or copies of them). Writes the whole geom
// record gd[kGStride], zeros where culled and in the padding, so that the saved state is a
// function of the inputs (never uninitialised memory). (The CPU kernel runs the same steps on
// vectors of Gaussians: cpu/preprocess_simd.h.)
GRP_FORCE_INLINE PreprocessResult preprocess_gaussian(const RasterArgs& a, int64_t g,
                                                      const float* V, const float* Pm, float* gd) {
  PreprocessResult res = {0, 0, {0, 0, 0, 0}};
  const Vec3 m = load3(a.means + 3 * g);
  const Vec3 t = transform_point_4x3(V, m);
  if (!(t.z > kNearPlane)) return culled_record(gd);  // also culls NaN
  const Vec4 ph = transform_point_4x4(Pm, m);
  const float p_w = 1.0f / (ph.w + kProjEps);
  const Vec3 ndc = {ph.x * p_w, ph.y * p_w, ph.z * p_w};
  const Sym3 cov3 = gaussian_cov3d(a, g);
  Cov2DCtx ctx;
  const Sym2 cov2 = compute_cov2d(t, a.focal_x, a.focal_y, a.tanfovx, a.tanfovy, cov3, V, ctx);
  const ConicResult cr = dilate_and_invert(cov2, a.antialiasing);
  if (cr.det == 0.0f) return culled_record(gd);
  const float radius = screen_radius(cr.dilated, cr.det);
  const Vec2 pix = {ndc2pix(ndc.x, a.W), ndc2pix(ndc.y, a.H)};
  if (!screen_footprint(a, pix, radius, res)) return culled_record(gd);
  write_geom_record(a, g, pix, cr, gaussian_colour(a, g, m), t.z, gd);
  return res;
}

// Backward of Gaussian g (visible in the forward) from s[kSlot], the sum of its slots: chains
// through the per-Gaussian VJPs and writes its rows of `out`. V / Pm / cpos: view / projection
// matrices and camera centre. Camera terms are accumulated into dV[16], dP[16], dC[3] (Acc = float
// or double) when non-null.
// out.means3D == nullptr: the Gaussians' gradients are not wanted (`out` is not written) and only
// the camera terms are computed (dV, dP, dC non-null). A runtime test, not a template argument:
// one compiled body serves both cases, so the camera terms are the same machine operations, hence
// the same bits, whether the Gaussians' gradients are wanted or not (two instantiations may
// contract a*b + c*d into different FMAs). Slots 5 (opacity) and 6..8 (colour) are read only where
// they reach the camera: with antialiasing, and with SH of degree > 0.
template <typename Acc>
GRP_FORCE_INLINE void gaussian_backward_one(const RasterArgs& a, int64_t g, const float* s,
                                            const float* V, const float* Pm, Vec3 cpos,
                                            const GaussianGrads& out, Acc* dV, Acc* dP, Acc* dC) {
  const bool gauss = out.means3D != nullptr;
  const Vec3 m = load3(a.means + 3 * g);
  const Vec3 t = transform_point_4x3(V, m);
  const Vec4 ph = transform_point_4x4(Pm, m);
  const Sym3 cov3 = gaussian_cov3d(a, g);
  Cov2DCtx ctx;
  const Sym2 cov2 = compute_cov2d(t, a.focal_x, a.focal_y, a.tanfovx, a.tanfovy, cov3, V, ctx);
  const ConicResult cr = dilate_and_invert(cov2, a.antialiasing);
  // opacity_eff = opacity * coef
  if (gauss) out.opac[g] = s[5] * cr.coef;
  const float dcoef = s[5] * a.opac[g];
  const Sym2 dcov2 = dilate_and_invert_vjp(cov2, a.antialiasing, {s[2], s[3], s[4]}, dcoef);
  Vec3 dt = {0.f, 0.f, -s[9] / (t.z * t.z) + s[10]};  // features 1/z and z
  Sym3 dcov3;
  compute_cov2d_vjp(t, a.focal_x, a.focal_y, cov3, V, ctx, dcov2, dt,
                    gauss ? &dcov3 : nullptr, dV);
  if (gauss) {
    if (out.cov3d != nullptr) {
      for (int k = 0; k < 6; ++k) out.cov3d[6 * g + k] = dcov3.v[k];
    } else {
      const float* q = a.rots + 4 * g;
      Vec3 dsc;
      Vec4 dq;
      compute_cov3d_vjp(load3(a.scales + 3 * g), a.scale_modifier, {q[0], q[1], q[2], q[3]},
                        dcov3, dsc, dq);
      out.scales[3 * g + 0] = dsc.x;
      out.scales[3 * g + 1] = dsc.y;
      out.scales[3 * g + 2] = dsc.z;
      out.rots[4 * g + 0] = dq.x;
      out.rots[4 * g + 1] = dq.y;
      out.rots[4 * g + 2] = dq.z;
      out.rots[4 * g + 3] = dq.w;
    }
  }
  const Vec2 dndc = {s[0] * 0.5f * a.W, s[1] * 0.5f * a.H};
  if (gauss) {
    out.means2D[3 * g + 0] = dndc.x;
    out.means2D[3 * g + 1] = dndc.y;
  }
  Vec3 dm = {0.f, 0.f, 0.f};
  project_vjp(Pm, m, ph, dndc, dm, dP);
  transform_point_4x3_vjp(V, m, dt, dm, dV);
  if (a.colors != nullptr) {
    if (gauss) {
      out.colors[3 * g + 0] = s[6];
      out.colors[3 * g + 1] = s[7];
      out.colors[3 * g + 2] = s[8];
    }
  } else if (gauss || a.sh_degree > 0) {  // at degree 0 the colour ignores the camera
    // With the SH in two tensors the gradient goes through dbuf, then to its two rows (the
    // coefficients not read keep the zeros the caller filled in).
    float buf[kMaxShFloats], dbuf[kMaxShFloats];
    float* dsh = !gauss ? nullptr : a.shs_rest != nullptr ? dbuf : out.shs + g * a.M * 3;
    const Vec3 dv = eval_sh_vjp(a.sh_degree, gaussian_sh(a, g, buf), m, cpos, {s[6], s[7], s[8]},
                                dsh);
    if (gauss && a.shs_rest != nullptr) scatter_sh_grad(a, g, dbuf, out.shs, out.shs_rest);
    if (a.sh_degree > 0) {
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
  if (gauss) {
    out.means3D[3 * g + 0] = dm.x;
    out.means3D[3 * g + 1] = dm.y;
    out.means3D[3 * g + 2] = dm.z;
  }
}

}  // namespace grp
