// The CPU preprocess on vectors of kLanes consecutive Gaussians (simd.h): the steps of
// preprocess_gaussian (common/raster.h) up to the screen-space culls, lane-wise, with the same
// float operations in the same order (so the same contractions and the same bits:
// tests/gaussian_renderer_pose/test_native_misc.py compares the records with the scalar path),
// then the per-Gaussian tail of raster.h (screen_footprint, write_geom_record) lane by lane.
// Gaussians with a precomputed covariance, and a last partial block, take the scalar path.
#pragma once

#include <cstdint>

#include "../common/config.h"
#include "../common/math.h"
#include "../common/raster.h"
#include "../common/sh.h"
#include "simd.h"

namespace grp {
namespace cpu {

struct V3 {
  vf x, y, z;
};

// Lanes of field k of a [P, stride] array, rows g0 .. g0 + kLanes - 1.
inline vf load_lanes(const float* base, int64_t g0, int stride, int k) {
  vf r;
  for (int i = 0; i < kLanes; ++i) r[i] = base[(g0 + i) * stride + k];
  return r;
}

// transform_point_4x3 / transform_point_4x4 (row j of the transposed matrix M).
inline vf transform_row(const float* M, const V3& p, int j) {
  return M[j] * p.x + M[4 + j] * p.y + M[8 + j] * p.z + M[12 + j];
}

// compute_cov3d: Sigma = M^T M with M = S R^T (6 unique entries xx, xy, xz, yy, yz, zz).
inline void cov3d_lanes(const RasterArgs& a, int64_t g0, vf cov[6]) {
  const vf r = load_lanes(a.rots, g0, 4, 0), x = load_lanes(a.rots, g0, 4, 1);
  const vf y = load_lanes(a.rots, g0, 4, 2), z = load_lanes(a.rots, g0, 4, 3);
  vf R[3][3];
  R[0][0] = 1.f - 2.f * (y * y + z * z);
  R[0][1] = 2.f * (x * y - r * z);
  R[0][2] = 2.f * (x * z + r * y);
  R[1][0] = 2.f * (x * y + r * z);
  R[1][1] = 1.f - 2.f * (x * x + z * z);
  R[1][2] = 2.f * (y * z - r * x);
  R[2][0] = 2.f * (x * z - r * y);
  R[2][1] = 2.f * (y * z + r * x);
  R[2][2] = 1.f - 2.f * (x * x + y * y);
  const float mod = a.scale_modifier;
  const vf s[3] = {mod * load_lanes(a.scales, g0, 3, 0), mod * load_lanes(a.scales, g0, 3, 1),
                   mod * load_lanes(a.scales, g0, 3, 2)};
  vf Mm[3][3];
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) Mm[i][j] = s[i] * R[j][i];
  const int rc[6][2] = {{0, 0}, {0, 1}, {0, 2}, {1, 1}, {1, 2}, {2, 2}};
  for (int k = 0; k < 6; ++k) {
    const int r0 = rc[k][0], c0 = rc[k][1];
    cov[k] = Mm[0][r0] * Mm[0][c0] + Mm[1][r0] * Mm[1][c0] + Mm[2][r0] * Mm[2][c0];
  }
}

// compute_cov2d (forward only): cov2D = J Rw Sigma Rw^T J^T as (a, b, c).
inline void cov2d_lanes(const RasterArgs& a, const V3& t, const vf cov3[6], const float* V,
                        vf out[3]) {
  const float limx = kFrustumClamp * a.tanfovx;
  const float limy = kFrustumClamp * a.tanfovy;
  const vf txtz = t.x / t.z;
  const vf tytz = t.y / t.z;
  const vf cx = txtz < -limx ? splat(-limx) : (txtz > limx ? splat(limx) : txtz);
  const vf cy = tytz < -limy ? splat(-limy) : (tytz > limy ? splat(limy) : tytz);
  const vf tx = cx * t.z;
  const vf ty = cy * t.z;
  const vf J00 = a.focal_x / t.z;
  const vf J02 = -(a.focal_x * tx) / (t.z * t.z);
  const vf J11 = a.focal_y / t.z;
  const vf J12 = -(a.focal_y * ty) / (t.z * t.z);
  vf T[2][3];
  for (int c = 0; c < 3; ++c) {
    T[0][c] = J00 * V[4 * c + 0] + J02 * V[4 * c + 2];
    T[1][c] = J11 * V[4 * c + 1] + J12 * V[4 * c + 2];
  }
  const vf S[3][3] = {{cov3[0], cov3[1], cov3[2]},
                      {cov3[1], cov3[3], cov3[4]},
                      {cov3[2], cov3[4], cov3[5]}};
  vf U[2][3];
  for (int i = 0; i < 2; ++i)
    for (int c = 0; c < 3; ++c)
      U[i][c] = T[i][0] * S[0][c] + T[i][1] * S[1][c] + T[i][2] * S[2][c];
  out[0] = U[0][0] * T[0][0] + U[0][1] * T[0][1] + U[0][2] * T[0][2];
  out[1] = U[0][0] * T[1][0] + U[0][1] * T[1][1] + U[0][2] * T[1][2];
  out[2] = U[1][0] * T[1][0] + U[1][1] * T[1][1] + U[1][2] * T[1][2];
}

// dilate_and_invert + screen_radius on lanes.
struct ConicLanes {
  vf conic_a, conic_b, conic_c, det, coef, dil_a, dil_b, dil_c, radius;
};

inline ConicLanes conic_lanes(const vf cov[3], bool antialiasing) {
  ConicLanes r;
  r.dil_a = cov[0] + kDilation;
  r.dil_b = cov[1];
  r.dil_c = cov[2] + kDilation;
  r.det = r.dil_a * r.dil_c - r.dil_b * r.dil_b;
  r.coef = splat(1.f);
  if (antialiasing) {
    const vf det0 = cov[0] * cov[2] - cov[1] * cov[1];
    const vf ratio = det0 / r.det;
    r.coef = vsqrt(ratio > kAntialiasMinRatio ? ratio : splat(kAntialiasMinRatio));
  }
  const vf inv = r.det != 0.f ? 1.f / r.det : splat(0.f);
  r.conic_a = r.dil_c * inv;
  r.conic_b = -r.dil_b * inv;
  r.conic_c = r.dil_a * inv;
  const vf mid = 0.5f * (r.dil_a + r.dil_c);
  const vf disc = mid * mid - r.det;
  const vf sq = vsqrt(disc > kMinDiscriminant ? disc : splat(kMinDiscriminant));
  const vf lambda1 = mid + sq;
  const vf lambda2 = mid - sq;
  r.radius = vceil(kSigmaRadius * vsqrt(lambda1 > lambda2 ? lambda1 : lambda2));
  return r;
}

// eval_sh (before the clamp) on lanes: rgb + 0.5 of SH degree deg seen from campos.
inline V3 sh_lanes(const RasterArgs& a, int64_t g0, const V3& m) {
  const V3 v = {m.x - a.campos[0], m.y - a.campos[1], m.z - a.campos[2]};
  const vf norm = vsqrt(round_here(v.x * v.x) + round_here(v.y * v.y) + round_here(v.z * v.z));
  const vf inv = 1.f / norm;
  const vf x = v.x * inv, y = v.y * inv, z = v.z * inv;
  vf basis[16];
  basis[0] = splat(kShC0);
  int n = 1;
  if (a.sh_degree >= 1) {
    basis[1] = -kShC1 * y;
    basis[2] = kShC1 * z;
    basis[3] = -kShC1 * x;
    n = 4;
  }
  const vf xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
  if (a.sh_degree >= 2) {
    basis[4] = kShC2_0 * xy;
    basis[5] = kShC2_1 * yz;
    basis[6] = kShC2_2 * (2.f * zz - xx - yy);
    basis[7] = kShC2_3 * xz;
    basis[8] = kShC2_4 * (xx - yy);
    n = 9;
  }
  if (a.sh_degree >= 3) {
    basis[9] = kShC3_0 * y * (3.f * xx - yy);
    basis[10] = kShC3_1 * xy * z;
    basis[11] = kShC3_2 * y * (4.f * zz - xx - yy);
    basis[12] = kShC3_3 * z * (2.f * zz - 3.f * xx - 3.f * yy);
    basis[13] = kShC3_4 * x * (4.f * zz - xx - yy);
    basis[14] = kShC3_5 * z * (xx - yy);
    basis[15] = kShC3_6 * x * (xx - 3.f * yy);
    n = 16;
  }
  // As eval_sh: each product rounded, then summed in order of k. Coefficient k, channel c: in
  // shs, or (SH in two tensors, gaussian_sh) the first in shs and the others in shs_rest.
  const bool split = a.shs_rest != nullptr;
  const int stride = split ? 3 : (int)a.M * 3, rest_stride = (int)(a.M - 1) * 3;
  const auto coef = [&](int k, int c) {
    return split && k > 0 ? load_lanes(a.shs_rest, g0, rest_stride, 3 * (k - 1) + c)
                          : load_lanes(a.shs, g0, stride, 3 * k + c);
  };
  V3 rgb = {splat(0.f), splat(0.f), splat(0.f)};
  for (int k = 0; k < n; ++k) {
    rgb.x += round_here(basis[k] * coef(k, 0));
    rgb.y += round_here(basis[k] * coef(k, 1));
    rgb.z += round_here(basis[k] * coef(k, 2));
  }
  return {rgb.x + 0.5f, rgb.y + 0.5f, rgb.z + 0.5f};
}

// Preprocess of Gaussians g0 .. g0 + kLanes - 1 (a.cov3d == nullptr): as preprocess_gaussian for
// each, results in res[kLanes], records at geom + kGStride g.
inline void preprocess_lanes(const RasterArgs& a, int64_t g0, float* geom, PreprocessResult* res) {
  const float* V = a.viewmatrix;
  const float* Pm = a.projmatrix;
  const V3 m = {load_lanes(a.means, g0, 3, 0), load_lanes(a.means, g0, 3, 1),
                load_lanes(a.means, g0, 3, 2)};
  const V3 t = {transform_row(V, m, 0), transform_row(V, m, 1), transform_row(V, m, 2)};
  const vf phx = transform_row(Pm, m, 0), phy = transform_row(Pm, m, 1);
  const vf p_w = 1.0f / (transform_row(Pm, m, 3) + kProjEps);
  const vf ndcx = phx * p_w, ndcy = phy * p_w;
  vf cov3[6], cov2[3];
  cov3d_lanes(a, g0, cov3);
  cov2d_lanes(a, t, cov3, V, cov2);
  const ConicLanes cr = conic_lanes(cov2, a.antialiasing);
  const vf pixx = ((ndcx + 1.0f) * (float)a.W - 1.0f) * 0.5f;
  const vf pixy = ((ndcy + 1.0f) * (float)a.H - 1.0f) * 0.5f;
  V3 rgb = {splat(0.f), splat(0.f), splat(0.f)};
  if (a.colors == nullptr) rgb = sh_lanes(a, g0, m);
  for (int i = 0; i < kLanes; ++i) {
    const int64_t g = g0 + i;
    float* gd = geom + kGStride * g;
    res[i] = {0, 0, {0, 0, 0, 0}};
    if (!(t.z[i] > kNearPlane) || cr.det[i] == 0.0f) {
      res[i] = culled_record(gd);
      continue;
    }
    const Vec2 pix = {pixx[i], pixy[i]};
    if (!screen_footprint(a, pix, cr.radius[i], res[i])) {
      res[i] = culled_record(gd);
      continue;
    }
    Vec3 c;
    if (a.colors != nullptr) {
      c = load3(a.colors + 3 * g);
    } else {
      c = {rgb.x[i] < 0.f ? 0.f : rgb.x[i], rgb.y[i] < 0.f ? 0.f : rgb.y[i],
           rgb.z[i] < 0.f ? 0.f : rgb.z[i]};
    }
    ConicResult cri;
    cri.conic = {cr.conic_a[i], cr.conic_b[i], cr.conic_c[i]};
    cri.det = cr.det[i];
    cri.coef = cr.coef[i];
    cri.dilated = {cr.dil_a[i], cr.dil_b[i], cr.dil_c[i]};
    write_geom_record(a, g, pix, cri, c, t.z[i], gd);
  }
}

}  // namespace cpu
}  // namespace grp
