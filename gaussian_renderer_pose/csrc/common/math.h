// Per-Gaussian maths of the rasterizer: forward and hand-written VJP side by side.
//
// Conventions (docs/CONTRACTS.md "Forward numerics"):
//  * `viewmatrix` / `projmatrix` are the 3DGS row-major [4,4] buffers (= w2c^T, (P w2c)^T), so a
//    point transforms as a row vector: t = hom(m) @ viewmatrix.
//  * Rw = viewmatrix[:3,:3]^T (the w2c rotation), cov2D = J Rw Sigma Rw^T J^T.
//  * Quaternions are (w, x, y, z) and NOT normalised (the polynomial rotation formula is used as is,
//    and its exact derivative is returned).
//  * Symmetric 3x3 matrices are stored as 6 floats (xx, xy, xz, yy, yz, zz); their gradients are
//    w.r.t. those 6 independent values (off-diagonals counted once).
// Everything is GRP_HD so that a CUDA kernel can include this header unchanged. The helpers the
// per-Gaussian bodies of raster.h call are GRP_FORCE_INLINE (host_device.h): left to GCC's
// unit-growth heuristics, a larger translation unit put compute_cov2d / compute_cov3d / eval_sh_vjp
// out of line, which changed the forward's float rounding (FMA contraction across the call) and
// cost time.
#pragma once

#include <cmath>

#include "config.h"
#include "host_device.h"

namespace grp {

struct Vec2 {
  float x, y;
};
struct Vec3 {
  float x, y, z;
};
struct Vec4 {
  float x, y, z, w;
};
// Row-major 3x3 math matrix.
struct Mat3 {
  float m[3][3];
};
// Symmetric 3x3, 6 unique entries (xx, xy, xz, yy, yz, zz).
struct Sym3 {
  float v[6];
};
// Symmetric 2x2 [[a, b], [b, c]].
struct Sym2 {
  float a, b, c;
};

GRP_INLINE float clampf(float v, float lo, float hi) { return v < lo ? lo : (v > hi ? hi : v); }
GRP_INLINE float dot3(Vec3 a, Vec3 b) { return a.x * b.x + a.y * b.y + a.z * b.z; }

// ------------------------------------------------------------------------------------------------
// Affine transforms by the row-major [4,4] 3DGS matrices.
// ------------------------------------------------------------------------------------------------

// t_j = sum_k hom(p)_k M[4k + j], j = 0..2 (upstream transformPoint4x3).
GRP_INLINE Vec3 transform_point_4x3(const float* M, Vec3 p) {
  return {M[0] * p.x + M[4] * p.y + M[8] * p.z + M[12],
          M[1] * p.x + M[5] * p.y + M[9] * p.z + M[13],
          M[2] * p.x + M[6] * p.y + M[10] * p.z + M[14]};
}

// j = 0..3 (upstream transformPoint4x4).
GRP_INLINE Vec4 transform_point_4x4(const float* M, Vec3 p) {
  return {M[0] * p.x + M[4] * p.y + M[8] * p.z + M[12],
          M[1] * p.x + M[5] * p.y + M[9] * p.z + M[13],
          M[2] * p.x + M[6] * p.y + M[10] * p.z + M[14],
          M[3] * p.x + M[7] * p.y + M[11] * p.z + M[15]};
}

// VJP of transform_point_4x3: adds to dL_dp, and (when dL_dM != nullptr) to dL_dM[16].
template <typename Acc>
GRP_INLINE void transform_point_4x3_vjp(const float* M, Vec3 p, Vec3 dL_dt, Vec3& dL_dp,
                                        Acc* dL_dM) {
  dL_dp.x += M[0] * dL_dt.x + M[1] * dL_dt.y + M[2] * dL_dt.z;
  dL_dp.y += M[4] * dL_dt.x + M[5] * dL_dt.y + M[6] * dL_dt.z;
  dL_dp.z += M[8] * dL_dt.x + M[9] * dL_dt.y + M[10] * dL_dt.z;
  if (dL_dM != nullptr) {
    const float h[4] = {p.x, p.y, p.z, 1.0f};
    for (int k = 0; k < 4; ++k) {
      dL_dM[4 * k + 0] += h[k] * dL_dt.x;
      dL_dM[4 * k + 1] += h[k] * dL_dt.y;
      dL_dM[4 * k + 2] += h[k] * dL_dt.z;
    }
  }
}

// ------------------------------------------------------------------------------------------------
// Projection to pixels: ndc = p_hom.xyz / (p_hom.w + eps), pixel = ((ndc + 1) S - 1) / 2.
// ------------------------------------------------------------------------------------------------
GRP_INLINE float ndc2pix(float v, int S) { return ((v + 1.0f) * S - 1.0f) * 0.5f; }

// Given dL/d ndc.xy (upstream `dL_dmean2D` units), adds d/d mean and d/d projmatrix (optional).
template <typename Acc>
GRP_INLINE void project_vjp(const float* P, Vec3 m, Vec4 p_hom, Vec2 dL_dndc, Vec3& dL_dm,
                            Acc* dL_dP) {
  const float p_w = 1.0f / (p_hom.w + kProjEps);
  const float gx = dL_dndc.x * p_w;
  const float gy = dL_dndc.y * p_w;
  const float gw = -(dL_dndc.x * p_hom.x + dL_dndc.y * p_hom.y) * p_w * p_w;
  dL_dm.x += P[0] * gx + P[1] * gy + P[3] * gw;
  dL_dm.y += P[4] * gx + P[5] * gy + P[7] * gw;
  dL_dm.z += P[8] * gx + P[9] * gy + P[11] * gw;
  if (dL_dP != nullptr) {
    const float h[4] = {m.x, m.y, m.z, 1.0f};
    for (int k = 0; k < 4; ++k) {
      dL_dP[4 * k + 0] += h[k] * gx;
      dL_dP[4 * k + 1] += h[k] * gy;
      dL_dP[4 * k + 3] += h[k] * gw;
    }
  }
}

// ------------------------------------------------------------------------------------------------
// 3D covariance from scale and (unnormalised) quaternion: Sigma = R S^2 R^T, M = S R^T.
// ------------------------------------------------------------------------------------------------
GRP_INLINE Mat3 quat_to_rotmat(Vec4 q) {  // q = (w=r, x, y, z), stored as (x=r, y=x, z=y, w=z)
  const float r = q.x, x = q.y, y = q.z, z = q.w;
  Mat3 R;
  R.m[0][0] = 1.f - 2.f * (y * y + z * z);
  R.m[0][1] = 2.f * (x * y - r * z);
  R.m[0][2] = 2.f * (x * z + r * y);
  R.m[1][0] = 2.f * (x * y + r * z);
  R.m[1][1] = 1.f - 2.f * (x * x + z * z);
  R.m[1][2] = 2.f * (y * z - r * x);
  R.m[2][0] = 2.f * (x * z - r * y);
  R.m[2][1] = 2.f * (y * z + r * x);
  R.m[2][2] = 1.f - 2.f * (x * x + y * y);
  return R;
}

GRP_FORCE_INLINE Sym3 compute_cov3d(Vec3 scale, float mod, Vec4 q) {
  const Mat3 R = quat_to_rotmat(q);
  const float s[3] = {mod * scale.x, mod * scale.y, mod * scale.z};
  float Mm[3][3];  // M = S R^T: M[i][j] = s_i R[j][i]
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) Mm[i][j] = s[i] * R.m[j][i];
  float S[3][3];  // Sigma = M^T M
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) S[r][c] = Mm[0][r] * Mm[0][c] + Mm[1][r] * Mm[1][c] + Mm[2][r] * Mm[2][c];
  return {{S[0][0], S[0][1], S[0][2], S[1][1], S[1][2], S[2][2]}};
}

// dL_dcov: gradient w.r.t. the 6 stored values. Writes dL/dscale (already times mod) and dL/dq.
GRP_FORCE_INLINE void compute_cov3d_vjp(Vec3 scale, float mod, Vec4 q, const Sym3& dL_dcov,
                                        Vec3& dL_dscale, Vec4& dL_dq) {
  const Mat3 R = quat_to_rotmat(q);
  const float s[3] = {mod * scale.x, mod * scale.y, mod * scale.z};
  float Mm[3][3];
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) Mm[i][j] = s[i] * R.m[j][i];
  // Full symmetric gradient G: off-diagonal stored values appear twice in Sigma.
  const float G[3][3] = {{dL_dcov.v[0], 0.5f * dL_dcov.v[1], 0.5f * dL_dcov.v[2]},
                         {0.5f * dL_dcov.v[1], dL_dcov.v[3], 0.5f * dL_dcov.v[4]},
                         {0.5f * dL_dcov.v[2], 0.5f * dL_dcov.v[4], dL_dcov.v[5]}};
  float dM[3][3];  // dL/dM = 2 M G
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j)
      dM[i][j] = 2.f * (Mm[i][0] * G[0][j] + Mm[i][1] * G[1][j] + Mm[i][2] * G[2][j]);
  float ds[3];
  for (int i = 0; i < 3; ++i) ds[i] = dM[i][0] * R.m[0][i] + dM[i][1] * R.m[1][i] + dM[i][2] * R.m[2][i];
  dL_dscale = {mod * ds[0], mod * ds[1], mod * ds[2]};
  float dR[3][3];  // dL/dR[j][i] = dM[i][j] s_i
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) dR[j][i] = dM[i][j] * s[i];
  const float r = q.x, x = q.y, y = q.z, z = q.w;
  // d/dr
  const float gr = 2.f * (-z * dR[0][1] + y * dR[0][2] + z * dR[1][0] - x * dR[1][2] - y * dR[2][0] +
                          x * dR[2][1]);
  const float gx = 2.f * (y * dR[0][1] + z * dR[0][2] + y * dR[1][0] - 2.f * x * dR[1][1] -
                          r * dR[1][2] + z * dR[2][0] + r * dR[2][1] - 2.f * x * dR[2][2]);
  const float gy = 2.f * (-2.f * y * dR[0][0] + x * dR[0][1] + r * dR[0][2] + x * dR[1][0] +
                          z * dR[1][2] - r * dR[2][0] + z * dR[2][1] - 2.f * y * dR[2][2]);
  const float gz = 2.f * (-2.f * z * dR[0][0] - r * dR[0][1] + x * dR[0][2] + r * dR[1][0] -
                          2.f * z * dR[1][1] + y * dR[1][2] + x * dR[2][0] + y * dR[2][1]);
  dL_dq = {gr, gx, gy, gz};
}

// ------------------------------------------------------------------------------------------------
// EWA projection of the 3D covariance: cov2D = J Rw Sigma Rw^T J^T (undilated).
// ------------------------------------------------------------------------------------------------
struct Cov2DCtx {
  float J00, J02, J11, J12;  // the non-zero entries of J
  float T[2][3];             // T = J Rw
  float cx, cy;              // clamped tx/tz, ty/tz
  bool clamped_x, clamped_y;
};

GRP_FORCE_INLINE Sym2 compute_cov2d(Vec3 t, float focal_x, float focal_y, float tanfovx,
                                    float tanfovy, const Sym3& cov3d, const float* V,
                                    Cov2DCtx& ctx) {
  const float limx = kFrustumClamp * tanfovx;
  const float limy = kFrustumClamp * tanfovy;
  const float txtz = t.x / t.z;
  const float tytz = t.y / t.z;
  ctx.clamped_x = txtz < -limx || txtz > limx;
  ctx.clamped_y = tytz < -limy || tytz > limy;
  ctx.cx = clampf(txtz, -limx, limx);
  ctx.cy = clampf(tytz, -limy, limy);
  const float tx = ctx.cx * t.z;
  const float ty = ctx.cy * t.z;
  ctx.J00 = focal_x / t.z;
  ctx.J02 = -(focal_x * tx) / (t.z * t.z);
  ctx.J11 = focal_y / t.z;
  ctx.J12 = -(focal_y * ty) / (t.z * t.z);
  // Rw[r][c] = V[4c + r]; T[i][c] = sum_r J[i][r] Rw[r][c].
  for (int c = 0; c < 3; ++c) {
    ctx.T[0][c] = ctx.J00 * V[4 * c + 0] + ctx.J02 * V[4 * c + 2];
    ctx.T[1][c] = ctx.J11 * V[4 * c + 1] + ctx.J12 * V[4 * c + 2];
  }
  const float S[3][3] = {{cov3d.v[0], cov3d.v[1], cov3d.v[2]},
                         {cov3d.v[1], cov3d.v[3], cov3d.v[4]},
                         {cov3d.v[2], cov3d.v[4], cov3d.v[5]}};
  float U[2][3];  // U = T Sigma
  for (int i = 0; i < 2; ++i)
    for (int c = 0; c < 3; ++c)
      U[i][c] = ctx.T[i][0] * S[0][c] + ctx.T[i][1] * S[1][c] + ctx.T[i][2] * S[2][c];
  Sym2 out;
  out.a = U[0][0] * ctx.T[0][0] + U[0][1] * ctx.T[0][1] + U[0][2] * ctx.T[0][2];
  out.b = U[0][0] * ctx.T[1][0] + U[0][1] * ctx.T[1][1] + U[0][2] * ctx.T[1][2];
  out.c = U[1][0] * ctx.T[1][0] + U[1][1] * ctx.T[1][1] + U[1][2] * ctx.T[1][2];
  return out;
}

// VJP of compute_cov2d. dL_dcov2 = (d/da, d/db with b counted once, d/dc). Adds to dL_dt,
// writes *dL_dcov3d (6 stored values) when non-null, adds to dL_dV[16] (rotation block) when
// non-null.
template <typename Acc>
GRP_FORCE_INLINE void compute_cov2d_vjp(Vec3 t, float focal_x, float focal_y, const Sym3& cov3d,
                                        const float* V, const Cov2DCtx& ctx, Sym2 dL_dcov2,
                                        Vec3& dL_dt, Sym3* dL_dcov3d, Acc* dL_dV) {
  const float S[3][3] = {{cov3d.v[0], cov3d.v[1], cov3d.v[2]},
                         {cov3d.v[1], cov3d.v[3], cov3d.v[4]},
                         {cov3d.v[2], cov3d.v[4], cov3d.v[5]}};
  const float ga = dL_dcov2.a, gb = dL_dcov2.b, gc = dL_dcov2.c;
  float U[2][3];
  for (int i = 0; i < 2; ++i)
    for (int c = 0; c < 3; ++c)
      U[i][c] = ctx.T[i][0] * S[0][c] + ctx.T[i][1] * S[1][c] + ctx.T[i][2] * S[2][c];
  float dT[2][3];  // dL/dT = 2 G2 T Sigma, G2 = [[ga, gb/2], [gb/2, gc]]
  for (int c = 0; c < 3; ++c) {
    dT[0][c] = 2.f * ga * U[0][c] + gb * U[1][c];
    dT[1][c] = gb * U[0][c] + 2.f * gc * U[1][c];
  }
  if (dL_dcov3d != nullptr) {
    float Gf[3][3];  // dL/dSigma (full) = T^T G2 T
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 3; ++c)
        Gf[r][c] = ga * ctx.T[0][r] * ctx.T[0][c] +
                   0.5f * gb * (ctx.T[0][r] * ctx.T[1][c] + ctx.T[1][r] * ctx.T[0][c]) +
                   gc * ctx.T[1][r] * ctx.T[1][c];
    dL_dcov3d->v[0] = Gf[0][0];
    dL_dcov3d->v[1] = Gf[0][1] + Gf[1][0];
    dL_dcov3d->v[2] = Gf[0][2] + Gf[2][0];
    dL_dcov3d->v[3] = Gf[1][1];
    dL_dcov3d->v[4] = Gf[1][2] + Gf[2][1];
    dL_dcov3d->v[5] = Gf[2][2];
  }
  // dL/dJ[i][r] = sum_c dT[i][c] Rw[r][c], Rw[r][c] = V[4c + r]
  const float dJ00 = dT[0][0] * V[0] + dT[0][1] * V[4] + dT[0][2] * V[8];
  const float dJ02 = dT[0][0] * V[2] + dT[0][1] * V[6] + dT[0][2] * V[10];
  const float dJ11 = dT[1][0] * V[1] + dT[1][1] * V[5] + dT[1][2] * V[9];
  const float dJ12 = dT[1][0] * V[2] + dT[1][1] * V[6] + dT[1][2] * V[10];
  if (dL_dV != nullptr) {
    // dL/dRw[r][c] = sum_i J[i][r] dT[i][c]; J[0] = (J00, 0, J02), J[1] = (0, J11, J12)
    for (int c = 0; c < 3; ++c) {
      dL_dV[4 * c + 0] += ctx.J00 * dT[0][c];
      dL_dV[4 * c + 1] += ctx.J11 * dT[1][c];
      dL_dV[4 * c + 2] += ctx.J02 * dT[0][c] + ctx.J12 * dT[1][c];
    }
  }
  const float tz = t.z;
  const float itz = 1.f / tz;
  const float itz2 = itz * itz;
  const float tx = ctx.cx * tz;
  const float ty = ctx.cy * tz;
  // J00 = fx/tz, J02 = -fx tx/tz^2, J11 = fy/tz, J12 = -fy ty/tz^2 (tx, ty the clamped values)
  float dtz = -focal_x * itz2 * dJ00 - focal_y * itz2 * dJ11 + 2.f * focal_x * tx * itz2 * itz * dJ02 +
              2.f * focal_y * ty * itz2 * itz * dJ12;
  const float dtx = -focal_x * itz2 * dJ02;  // d/d(clamped tx)
  const float dty = -focal_y * itz2 * dJ12;
  float dtX = 0.f, dtY = 0.f;
  // tx = clamp(t.x/t.z) * t.z: unclamped -> d/dt.x = 1, d/dt.z = 0; clamped -> d/dt.z = +-lim.
  if (ctx.clamped_x) dtz += dtx * ctx.cx; else dtX = dtx;
  if (ctx.clamped_y) dtz += dty * ctx.cy; else dtY = dty;
  dL_dt.x += dtX;
  dL_dt.y += dtY;
  dL_dt.z += dtz;
}

// ------------------------------------------------------------------------------------------------
// Dilation, antialiasing factor and conic: cov' = cov + h I, conic = inv(cov').
// ------------------------------------------------------------------------------------------------
struct ConicResult {
  Sym2 conic;
  float det;   // det of the dilated covariance
  float coef;  // opacity scale (1 without antialiasing)
  Sym2 dilated;
};

GRP_FORCE_INLINE ConicResult dilate_and_invert(Sym2 cov, bool antialiasing) {
  ConicResult r;
  const float det0 = cov.a * cov.c - cov.b * cov.b;
  r.dilated = {cov.a + kDilation, cov.b, cov.c + kDilation};
  r.det = r.dilated.a * r.dilated.c - r.dilated.b * r.dilated.b;
  r.coef = 1.f;
  if (antialiasing) {
    const float ratio = det0 / r.det;
    r.coef = sqrtf(ratio > kAntialiasMinRatio ? ratio : kAntialiasMinRatio);
  }
  const float inv = r.det != 0.f ? 1.f / r.det : 0.f;
  r.conic = {r.dilated.c * inv, -r.dilated.b * inv, r.dilated.a * inv};
  return r;
}

// dL_dconic: true partials w.r.t. conic (a, b, c) entries (b counted once); dL_dcoef w.r.t. the
// antialiasing opacity scale. Returns dL/d undilated cov2D (a, b once, c).
GRP_FORCE_INLINE Sym2 dilate_and_invert_vjp(Sym2 cov, bool antialiasing, Sym2 dL_dconic,
                                             float dL_dcoef) {
  const float A = cov.a + kDilation, B = cov.b, C = cov.c + kDilation;
  const float det = A * C - B * B;
  const float inv = 1.f / det;
  const float inv2 = inv * inv;
  const float gA = dL_dconic.a, gB = dL_dconic.b, gC = dL_dconic.c;
  Sym2 d;
  d.a = (-C * C * gA + B * C * gB - B * B * gC) * inv2;
  d.c = (-B * B * gA + A * B * gB - A * A * gC) * inv2;
  d.b = (2.f * B * C * gA - (A * C + B * B) * gB + 2.f * A * B * gC) * inv2;
  if (antialiasing) {
    const float det0 = cov.a * cov.c - cov.b * cov.b;
    const float ratio = det0 / det;
    if (ratio >= kAntialiasMinRatio) {
      const float coef = sqrtf(ratio);
      const float gr = dL_dcoef * 0.5f / coef;
      d.a += gr * (cov.c * det - det0 * C) * inv2;
      d.c += gr * (cov.a * det - det0 * A) * inv2;
      d.b += gr * 2.f * B * (det0 - det) * inv2;
    }
  }
  return d;
}

// Screen-space radius: ceil(3 sqrt(lambda_max)) of the dilated covariance.
GRP_INLINE float screen_radius(Sym2 dilated, float det) {
  const float mid = 0.5f * (dilated.a + dilated.c);
  const float disc = mid * mid - det;
  const float sq = sqrtf(disc > kMinDiscriminant ? disc : kMinDiscriminant);
  const float lambda1 = mid + sq;
  const float lambda2 = mid - sq;
  return ceilf(kSigmaRadius * sqrtf(lambda1 > lambda2 ? lambda1 : lambda2));
}

// Tile rectangle (upstream getRect); rect_max exclusive.
GRP_INLINE void get_rect(Vec2 p, int max_radius, int grid_x, int grid_y, int& minx, int& miny,
                         int& maxx, int& maxy) {
  auto clampi = [](int v, int lo, int hi) { return v < lo ? lo : (v > hi ? hi : v); };
  minx = clampi((int)((p.x - max_radius) / kBlockX), 0, grid_x);
  miny = clampi((int)((p.y - max_radius) / kBlockY), 0, grid_y);
  maxx = clampi((int)((p.x + max_radius + kBlockX - 1) / kBlockX), 0, grid_x);
  maxy = clampi((int)((p.y + max_radius + kBlockY - 1) / kBlockY), 0, grid_y);
}

// exp(x) for x <= 0 (clamped below at -87): Cody-Waite reduction + Cephes polynomial (~1 ulp).
// Branch-free and written so that compilers vectorise it inside the per-tile pixel loops.
GRP_INLINE float exp_nonpos(float x) {
  x = x < -87.f ? -87.f : (x > 0.f ? 0.f : x);
  const float v = x * 1.44269504088896341f;
  const int n = (int)(v - 0.5f);  // round to nearest for v <= 0 (truncation toward zero)
  const float fn = (float)n;
  float r = x - fn * 0.693359375f;
  r = r - fn * -2.12194440e-4f;
  float p = 1.9875691500e-4f;
  p = p * r + 1.3981999507e-3f;
  p = p * r + 8.3334519073e-3f;
  p = p * r + 4.1665795894e-2f;
  p = p * r + 1.6666665459e-1f;
  p = p * r + 5.0000001201e-1f;
  const float y = p * r * r + r + 1.0f;
#if defined(__CUDA_ARCH__)
  return ldexpf(y, n);
#else
  union {
    int i;
    float f;
  } u;
  u.i = (n + 127) << 23;
  return y * u.f;
#endif
}

}  // namespace grp
