// CUDA kernels of the rasterizer: forward and full backward (incl. camera gradient). Pure CUDA: no
// torch/ATen (the wrapper rasterize_cuda.cpp allocates and passes plain pointers; see kernels.h).
//
// Every per-Gaussian formula comes from ../common/{math,sh,raster}.h (GRP_HD helpers shared with
// the CPU kernel ../cpu/rasterize_cpu.cpp; raster.h holds the whole per-Gaussian preprocess and
// backward bodies); the per-pixel blending and its backward are written out below
// as literal mirrors of the CPU kernel's loops (same expressions, same skip/stop rules, same
// exp_nonpos), so the two backends agree to float rounding.
//
// Pipeline (upstream diff-gaussian-rasterization design):
//   forward:  preprocess (1 thread / Gaussian) -> inclusive scan of the tiles touched -> duplicate
//             with (tile << 32 | depth bits) keys -> cub stable radix sort -> tile ranges ->
//             render (1 block of 16x16 threads / tile, shared-memory batches of 256 Gaussians).
//   backward: render_backward (1 block / tile, reverse order from the block's last contributor in
//             batches of 32; per Gaussian each warp reduces its 32 pixels with shuffles, the 8
//             warps are summed in a fixed order and the result is STORED in the entry's slot: no
//             atomics) -> gaussian_backward (1 thread / Gaussian: sums its slots in order, chains
//             the VJPs; camera terms reduced per block in double into a [blocks, 35] buffer; the
//             Gaussians' own gradients only when asked) ->
//             reduce_partials (fixed-order reduction of the per-block camera terms and of the
//             per-tile background terms). The backward is therefore bitwise deterministic.
#include <cub/cub.cuh>

#include <cstdint>

#include "common/config.h"
#include "common/math.h"
#include "common/raster.h"
#include "common/sh.h"
#include "kernels.h"

namespace grp {
namespace cuda {
namespace {

constexpr int kWarps = kBlockSize / 32;    // warps per tile block
constexpr int kBwdBatch = 32;              // Gaussians per shared-memory batch in the backward
constexpr unsigned kFullMask = 0xffffffffu;

static_assert(kBlockSize % 32 == 0, "tile blocks must be whole warps");
static_assert(kBlockX == 16, "a warp covers two 16-pixel rows of a tile");
static_assert(kGaussThreads % 32 == 0 && kGaussThreads >= kCamGrad, "per-Gaussian block size");
static_assert(kBwdBatch <= kBlockSize, "backward batch loaded by one thread per entry");

template <typename T>
__device__ __forceinline__ T warp_sum(T v) {
#pragma unroll
  for (int o = 16; o > 0; o >>= 1) v += __shfl_down_sync(kFullMask, v, o);
  return v;  // valid in lane 0
}

__device__ __forceinline__ int warp_max(int v) {
#pragma unroll
  for (int o = 16; o > 0; o >>= 1) {
    const int w = __shfl_down_sync(kFullMask, v, o);
    v = w > v ? w : v;
  }
  return v;  // valid in lane 0
}

inline unsigned grid_1d(int64_t n, int threads) { return (unsigned)((n + threads - 1) / threads); }

// ------------------------------------------------------------------------------------------------
// 1. Preprocess (body: preprocess_gaussian, ../common/raster.h, shared with the CPU kernel).
// ------------------------------------------------------------------------------------------------
__global__ void __launch_bounds__(kGaussThreads)
    preprocess_kernel(const RasterArgs a, float* __restrict__ geom, int32_t* __restrict__ radii,
                      int64_t* __restrict__ ntiles) {
  __shared__ float sV[16], sP[16];
  if (threadIdx.x < 16) {
    sV[threadIdx.x] = a.viewmatrix[threadIdx.x];
    sP[threadIdx.x] = a.projmatrix[threadIdx.x];
  }
  __syncthreads();
  const int64_t g = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
  if (g >= a.P) return;
  const PreprocessResult r = preprocess_gaussian(a, g, sV, sP, geom + (int64_t)kGStride * g);
  radii[g] = r.radius;
  ntiles[g] = r.area;
}

// ------------------------------------------------------------------------------------------------
// 2. Binning.
// ------------------------------------------------------------------------------------------------
__global__ void duplicate_kernel(int64_t P, int grid_x, int grid_y, const float* __restrict__ geom,
                                 const int32_t* __restrict__ radii,
                                 const int64_t* __restrict__ offsets, uint64_t* __restrict__ keys,
                                 int2* __restrict__ values) {
  const int64_t g = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
  if (g >= P || radii[g] <= 0) return;
  const float* gd = geom + (int64_t)kGStride * g;
  int minx, miny, maxx, maxy;
  get_rect({gd[kGPx], gd[kGPy]}, radii[g], grid_x, grid_y, minx, miny, maxx, maxy);
  const uint64_t zbits = (uint64_t)__float_as_uint(gd[kGZ]);  // t.z > 0.2: bit order = order
  int64_t e = offsets[g];
  for (int ty = miny; ty < maxy; ++ty) {
    for (int tx = minx; tx < maxx; ++tx, ++e) {
      keys[e] = ((uint64_t)((int64_t)ty * grid_x + tx) << 32) | zbits;
      values[e] = make_int2((int)g, (int)e);  // slot = offsets[g] + position in the rect
    }
  }
}

__global__ void tile_ranges_kernel(const uint64_t* __restrict__ keys, int64_t R, int64_t num_tiles,
                                   int32_t* __restrict__ ranges) {
  const int64_t i = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
  if (i >= R) return;
  const int64_t tile = (int64_t)(keys[i] >> 32);
  const int64_t prev = i == 0 ? -1 : (int64_t)(keys[i - 1] >> 32);
  for (int64_t t = prev + 1; t <= tile; ++t) ranges[t] = (int32_t)i;
  if (i == R - 1)
    for (int64_t t = tile + 1; t <= num_tiles; ++t) ranges[t] = (int32_t)R;
}

// ------------------------------------------------------------------------------------------------
// 3. Forward render (mirror of rasterize_cpu.cpp::render_tile, one thread per pixel).
// ------------------------------------------------------------------------------------------------
__global__ void __launch_bounds__(kBlockSize)
    render_kernel(const RasterArgs a, const float* __restrict__ geom,
                  const int32_t* __restrict__ binning, const int32_t* __restrict__ ranges,
                  const RenderOutputs out) {
  const int tile = blockIdx.y * a.grid_x + blockIdx.x;
  const int x = blockIdx.x * kBlockX + threadIdx.x;
  const int y = blockIdx.y * kBlockY + threadIdx.y;
  const int rank = threadIdx.y * kBlockX + threadIdx.x;
  const bool inside = x < a.W && y < a.H;
  const float fx = (float)x, fy = (float)y;
  const int start = ranges[tile], end = ranges[tile + 1];

  __shared__ float4 s_pc[kBlockSize];  // px, py, conic a, conic b
  __shared__ float4 s_co[kBlockSize];  // conic c, opacity, r, g
  __shared__ float4 s_fz[kBlockSize];  // b, 1/z, z, (box x)

  bool done = !inside;
  float T = 1.f, C0 = 0.f, C1 = 0.f, C2 = 0.f, ID = 0.f, DA = 0.f;
  int32_t last = -1;
  for (int base = start; base < end; base += kBlockSize) {
    // Also the barrier that protects the previous batch's shared data.
    if (__syncthreads_count(done) == kBlockSize) break;
    const int j = base + rank;
    if (j < end) {
      const float4* g4 = reinterpret_cast<const float4*>(geom + (int64_t)kGStride * binning[2 * j]);
      s_pc[rank] = g4[0];
      s_co[rank] = g4[1];
      s_fz[rank] = g4[2];
    }
    __syncthreads();
    const int n = min(kBlockSize, end - base);
    for (int k = 0; !done && k < n; ++k) {
      const float4 pc = s_pc[k];
      const float4 co = s_co[k];
      const float dx = pc.x - fx;
      const float dy = pc.y - fy;
      const float power = -0.5f * (pc.z * dx * dx + co.x * dy * dy) - pc.w * dx * dy;
      if (power > 0.f) continue;
      const float G = exp_nonpos(power);
      const float oG = co.y * G;
      const float alpha = oG < kAlphaMax ? oG : kAlphaMax;
      if (alpha < kAlphaMin) continue;
      const float testT = T * (1.f - alpha);
      if (testT < kTransmittanceMin) {  // stop: this Gaussian is excluded
        done = true;
        continue;
      }
      const float4 fz = s_fz[k];
      const float w = alpha * T;
      C0 += co.z * w;
      C1 += co.w * w;
      C2 += fz.x * w;
      ID += fz.y * w;
      DA += fz.z * w;
      T = testT;
      last = base - start + k;
    }
  }
  if (inside) {
    const int64_t HW = (int64_t)a.H * a.W;
    const int64_t pix = (int64_t)y * a.W + x;
    out.color[pix] = C0 + T * a.bg[0];
    out.color[HW + pix] = C1 + T * a.bg[1];
    out.color[2 * HW + pix] = C2 + T * a.bg[2];
    out.invdepth[pix] = ID;
    out.depth_acc[pix] = DA;
    out.alpha[pix] = 1.f - T;
    out.final_T[pix] = T;
    out.last[pix] = last;
  }
}

__global__ void mark_visible_kernel(const float* __restrict__ means,
                                    const float* __restrict__ viewmatrix, int64_t P,
                                    bool* __restrict__ visible) {
  const int64_t g = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
  if (g >= P) return;
  visible[g] = transform_point_4x3(viewmatrix, load3(means + 3 * g)).z > kNearPlane;
}

// ------------------------------------------------------------------------------------------------
// 4. Backward render (mirror of rasterize_cpu.cpp::backward_tile, one thread per pixel).
// ------------------------------------------------------------------------------------------------
__global__ void __launch_bounds__(kBlockSize)
    render_backward_kernel(const RasterArgs a, const float* __restrict__ geom,
                           const int32_t* __restrict__ binning, const int32_t* __restrict__ ranges,
                           const float* __restrict__ final_T, const int32_t* __restrict__ last_contrib,
                           const GradImages grad, float* __restrict__ slots,
                           double* __restrict__ dbg_tiles) {
  const int tile = blockIdx.y * a.grid_x + blockIdx.x;
  const int x = blockIdx.x * kBlockX + threadIdx.x;
  const int y = blockIdx.y * kBlockY + threadIdx.y;
  const int rank = threadIdx.y * kBlockX + threadIdx.x;
  const int lane = rank & 31, warp = rank >> 5;
  const bool inside = x < a.W && y < a.H;
  const float fx = (float)x, fy = (float)y;
  const int start = ranges[tile];  // entries after start + maxlast are never visited

  // Per-pixel state (pixels outside the image: last = -1, never valid).
  float T = 0.f, kbg = 0.f;
  float d0 = 0.f, d1 = 0.f, d2 = 0.f, d3 = 0.f, d4 = 0.f;
  int32_t last = -1;
  double b0 = 0.0, b1 = 0.0, b2 = 0.0;
  if (inside) {
    const int64_t HW = (int64_t)a.H * a.W;
    const int64_t pix = (int64_t)y * a.W + x;
    const float Tf = final_T[pix];
    T = Tf;
    last = last_contrib[pix];
    d0 = grad.color[pix];
    d1 = grad.color[HW + pix];
    d2 = grad.color[2 * HW + pix];
    d3 = grad.invdepth[pix];
    d4 = grad.depth_acc[pix];
    const float bgdot = a.bg[0] * d0 + a.bg[1] * d1 + a.bg[2] * d2;
    // dL/dalpha_i gets T_final / (1 - alpha_i) * (dL/dalpha_out - bg . dL/dpixel)
    kbg = Tf * (grad.alpha[pix] - bgdot);
    b0 = (double)Tf * (double)d0;
    b1 = (double)Tf * (double)d1;
    b2 = (double)Tf * (double)d2;
  }

  // Block reductions: background terms of the tile (double, fixed order) and the last contributor.
  __shared__ double s_dbg[kWarps][3];
  __shared__ int s_max[kWarps];
  {
    b0 = warp_sum(b0);
    b1 = warp_sum(b1);
    b2 = warp_sum(b2);
    const int ml = warp_max(last);
    if (lane == 0) {
      s_dbg[warp][0] = b0;
      s_dbg[warp][1] = b1;
      s_dbg[warp][2] = b2;
      s_max[warp] = ml;
    }
  }
  __syncthreads();
  if (rank == 0) {
    double s0 = 0.0, s1 = 0.0, s2 = 0.0;
    for (int w = 0; w < kWarps; ++w) {
      s0 += s_dbg[w][0];
      s1 += s_dbg[w][1];
      s2 += s_dbg[w][2];
    }
    dbg_tiles[3 * (int64_t)tile + 0] = s0;
    dbg_tiles[3 * (int64_t)tile + 1] = s1;
    dbg_tiles[3 * (int64_t)tile + 2] = s2;
  }
  int maxlast = s_max[0];
  for (int w = 1; w < kWarps; ++w) maxlast = s_max[w] > maxlast ? s_max[w] : maxlast;

  __shared__ int32_t s_slot[kBwdBatch];
  __shared__ float4 s_pc[kBwdBatch];
  __shared__ float4 s_co[kBwdBatch];
  __shared__ float4 s_fz[kBwdBatch];
  __shared__ float s_part[kBwdBatch][kWarps][kSlot];

  // Running back-to-front state (upstream: last_alpha, last_color, accum_rec).
  float la = 0.f;
  float l0 = 0.f, l1 = 0.f, l2 = 0.f, l3 = 0.f, l4 = 0.f;
  float a0 = 0.f, a1 = 0.f, a2 = 0.f, a3 = 0.f, a4 = 0.f;

  // Entries after start + maxlast are never visited: their slots stay zero (caller zero-fills).
  for (int bend = start + maxlast + 1; bend > start; bend -= kBwdBatch) {
    const int n = min(kBwdBatch, bend - start);
    __syncthreads();  // the previous batch's s_part / s_* are consumed
    if (rank < n) {
      const int j = bend - 1 - rank;  // reverse order inside the batch
      const int g = binning[2 * j];
      s_slot[rank] = binning[2 * j + 1];
      const float4* g4 = reinterpret_cast<const float4*>(geom + (int64_t)kGStride * g);
      s_pc[rank] = g4[0];
      s_co[rank] = g4[1];
      s_fz[rank] = g4[2];
    }
    __syncthreads();
    for (int k = 0; k < n; ++k) {
      const int jl = bend - 1 - k - start;
      const float4 pc = s_pc[k];
      const float4 co = s_co[k];
      const float cA = pc.z, cB = pc.w, cC = co.x, o = co.y;
      const float dx = pc.x - fx;
      const float dy = pc.y - fy;
      const float power = -0.5f * (cA * dx * dx + cC * dy * dy) - cB * dx * dy;
      const float G = exp_nonpos(power);
      const float oG = o * G;
      const float alpha = oG < kAlphaMax ? oG : kAlphaMax;
      const bool valid = jl <= last && !(power > 0.f) && !(alpha < kAlphaMin);
      float v[kSlot];
#pragma unroll
      for (int c = 0; c < kSlot; ++c) v[c] = 0.f;
      if (valid) {
        const float4 fz = s_fz[k];
        const float f0 = co.z, f1 = co.w, f2 = fz.x, f3 = fz.y, f4 = fz.z;
        const float one_m_a = 1.f - alpha;
        const float Tn = T / one_m_a;
        const float w = alpha * Tn;
        const float n0 = la * l0 + (1.f - la) * a0;
        const float n1 = la * l1 + (1.f - la) * a1;
        const float n2 = la * l2 + (1.f - la) * a2;
        const float n3 = la * l3 + (1.f - la) * a3;
        const float n4 = la * l4 + (1.f - la) * a4;
        float dLda = (f0 - n0) * d0 + (f1 - n1) * d1 + (f2 - n2) * d2 + (f3 - n3) * d3 +
                     (f4 - n4) * d4;
        dLda = dLda * Tn + kbg / one_m_a;
        T = Tn;
        a0 = n0;
        a1 = n1;
        a2 = n2;
        a3 = n3;
        a4 = n4;
        l0 = f0;
        l1 = f1;
        l2 = f2;
        l3 = f3;
        l4 = f4;
        la = alpha;
        v[6] = w * d0;
        v[7] = w * d1;
        v[8] = w * d2;
        v[9] = w * d3;
        v[10] = w * d4;
        // alpha = min(0.99, o G): no gradient to o G where the clamp is active
        const bool pass = !(oG > kAlphaMax);
        const float dLdG = pass ? o * dLda : 0.f;
        v[5] = pass ? G * dLda : 0.f;
        const float gdx = G * dx, gdy = G * dy;
        v[0] = dLdG * (-gdx * cA - gdy * cB);
        v[1] = dLdG * (-gdy * cC - gdx * cB);
        v[2] = -0.5f * gdx * dx * dLdG;
        v[3] = -gdx * dy * dLdG;
        v[4] = -0.5f * gdy * dy * dLdG;
      }
      if (__any_sync(kFullMask, valid)) {
#pragma unroll
        for (int c = 0; c < kSlot; ++c) v[c] = warp_sum(v[c]);
        if (lane == 0) {
#pragma unroll
          for (int c = 0; c < kSlot; ++c) s_part[k][warp][c] = v[c];
        }
      } else if (lane < kSlot) {
        s_part[k][warp][lane] = 0.f;
      }
    }
    __syncthreads();
    for (int idx = rank; idx < n * kSlot; idx += kBlockSize) {
      const int k = idx / kSlot, c = idx - k * kSlot;
      float s = 0.f;
#pragma unroll
      for (int w = 0; w < kWarps; ++w) s += s_part[k][w][c];
      slots[(int64_t)s_slot[k] * kSlot + c] = s;
    }
  }
}

// ------------------------------------------------------------------------------------------------
// 5. Per-Gaussian backward (mirror of the per-Gaussian loop of rasterize_backward_cpu).
// ------------------------------------------------------------------------------------------------
// kCam: reduce the camera terms per block. out.means3D == nullptr: the Gaussians' gradients are not
// written (camera terms only; a runtime test inside gaussian_backward_one, so that the camera terms
// are the same code either way).
template <bool kCam>
__global__ void __launch_bounds__(kGaussThreads)
    gaussian_backward_kernel(const RasterArgs a, const int32_t* __restrict__ radii,
                             const int64_t* __restrict__ offsets, const float* __restrict__ slots,
                             const GaussianGrads out, double* __restrict__ cam_partials) {
  __shared__ float sV[16], sP[16], sC[3];
  if (threadIdx.x < 16) {
    sV[threadIdx.x] = a.viewmatrix[threadIdx.x];
    sP[threadIdx.x] = a.projmatrix[threadIdx.x];
  }
  if (threadIdx.x < 3) sC[threadIdx.x] = a.campos[threadIdx.x];
  __syncthreads();
  const int64_t g = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;

  float cam[kCamGrad];
#pragma unroll
  for (int c = 0; c < kCamGrad; ++c) cam[c] = 0.f;
  float* dV = kCam ? cam : nullptr;
  float* dP = kCam ? cam + 16 : nullptr;
  float* dC = kCam ? cam + 32 : nullptr;

  if (g < a.P && radii[g] > 0) {
    float s[kSlot];
#pragma unroll
    for (int k = 0; k < kSlot; ++k) s[k] = 0.f;
    const int64_t e1 = offsets[g + 1];
    for (int64_t e = offsets[g]; e < e1; ++e) {
      const float* sl = slots + e * kSlot;
#pragma unroll
      for (int k = 0; k < kSlot; ++k) s[k] += sl[k];
    }
    gaussian_backward_one(a, g, s, sV, sP, Vec3{sC[0], sC[1], sC[2]}, out, dV, dP, dC);
  }

  if (kCam) {  // per-block reduction in double (fixed order), no atomics
    __shared__ double s_cam[kGaussThreads / 32][kCamGrad];
    const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5;
#pragma unroll
    for (int c = 0; c < kCamGrad; ++c) {
      const double v = warp_sum((double)cam[c]);
      if (lane == 0) s_cam[warp][c] = v;
    }
    __syncthreads();
    if (threadIdx.x < kCamGrad) {
      double s = 0.0;
      for (int w = 0; w < kGaussThreads / 32; ++w) s += s_cam[w][threadIdx.x];
      cam_partials[(int64_t)blockIdx.x * kCamGrad + threadIdx.x] = s;
    }
  }
}

// out[c] = sum over i of parts[i * stride + c]; one block per component, fixed order.
constexpr int kReduceThreads = 256;
__global__ void __launch_bounds__(kReduceThreads)
    reduce_partials_kernel(const double* __restrict__ parts, int64_t nparts, int stride,
                           float* __restrict__ out) {
  const int c = blockIdx.x;
  double s = 0.0;
  for (int64_t i = threadIdx.x; i < nparts; i += kReduceThreads) s += parts[i * stride + c];
  __shared__ double sh[kReduceThreads];
  sh[threadIdx.x] = s;
  __syncthreads();
  for (int w = kReduceThreads / 2; w > 0; w >>= 1) {
    if ((int)threadIdx.x < w) sh[threadIdx.x] += sh[threadIdx.x + w];
    __syncthreads();
  }
  if (threadIdx.x == 0) out[c] = (float)sh[0];
}

}  // namespace

// ------------------------------------------------------------------------------------------------
// Host launchers.
// ------------------------------------------------------------------------------------------------
cudaError_t preprocess(const RasterArgs& a, float* geom, int32_t* radii, int64_t* ntiles,
                       cudaStream_t stream) {
  if (a.P <= 0) return cudaSuccess;
  preprocess_kernel<<<grid_1d(a.P, kGaussThreads), kGaussThreads, 0, stream>>>(a, geom, radii, ntiles);
  return cudaGetLastError();
}

size_t scan_temp_bytes(int64_t P) {
  size_t bytes = 0;
  if (P <= 0) return 0;
  cub::DeviceScan::InclusiveSum(nullptr, bytes, static_cast<const int64_t*>(nullptr),
                                static_cast<int64_t*>(nullptr), (int)P);
  return bytes;
}

cudaError_t scan_offsets(void* temp, size_t temp_bytes, const int64_t* ntiles, int64_t* offsets,
                         int64_t P, cudaStream_t stream) {
  cudaError_t err = cudaMemsetAsync(offsets, 0, sizeof(int64_t), stream);
  if (err != cudaSuccess || P <= 0) return err;
  err = cub::DeviceScan::InclusiveSum(temp, temp_bytes, ntiles, offsets + 1, (int)P, stream);
  if (err != cudaSuccess) return err;
  return cudaGetLastError();
}

cudaError_t duplicate_with_keys(const RasterArgs& a, const float* geom, const int32_t* radii,
                                const int64_t* offsets, uint64_t* keys, int32_t* values,
                                cudaStream_t stream) {
  if (a.P <= 0) return cudaSuccess;
  duplicate_kernel<<<grid_1d(a.P, kGaussThreads), kGaussThreads, 0, stream>>>(
      a.P, a.grid_x, a.grid_y, geom, radii, offsets, keys, reinterpret_cast<int2*>(values));
  return cudaGetLastError();
}

int sort_end_bit(int64_t num_tiles) {
  int bits = 0;
  while (bits < 31 && (num_tiles >> bits) != 0) ++bits;
  return 32 + bits;
}

size_t sort_temp_bytes(int64_t R, int end_bit) {
  size_t bytes = 0;
  if (R <= 0) return 0;
  cub::DeviceRadixSort::SortPairs(nullptr, bytes, static_cast<const uint64_t*>(nullptr),
                                  static_cast<uint64_t*>(nullptr), static_cast<const int2*>(nullptr),
                                  static_cast<int2*>(nullptr), (int)R, 0, end_bit);
  return bytes;
}

cudaError_t sort_pairs(void* temp, size_t temp_bytes, const uint64_t* keys_in, uint64_t* keys_out,
                       const int32_t* values_in, int32_t* values_out, int64_t R, int end_bit,
                       cudaStream_t stream) {
  if (R <= 0) return cudaSuccess;
  cudaError_t err = cub::DeviceRadixSort::SortPairs(
      temp, temp_bytes, keys_in, keys_out, reinterpret_cast<const int2*>(values_in),
      reinterpret_cast<int2*>(values_out), (int)R, 0, end_bit, stream);
  if (err != cudaSuccess) return err;
  return cudaGetLastError();
}

cudaError_t tile_ranges(const uint64_t* sorted_keys, int64_t R, int64_t num_tiles, int32_t* ranges,
                        cudaStream_t stream) {
  if (R <= 0) return cudaSuccess;
  tile_ranges_kernel<<<grid_1d(R, 256), 256, 0, stream>>>(sorted_keys, R, num_tiles, ranges);
  return cudaGetLastError();
}

cudaError_t render(const RasterArgs& a, const float* geom, const int32_t* binning,
                   const int32_t* ranges, const RenderOutputs& out, cudaStream_t stream) {
  if (a.grid_x <= 0 || a.grid_y <= 0) return cudaSuccess;
  const dim3 grid(a.grid_x, a.grid_y), block(kBlockX, kBlockY);
  render_kernel<<<grid, block, 0, stream>>>(a, geom, binning, ranges, out);
  return cudaGetLastError();
}

cudaError_t mark_visible(const float* means, const float* viewmatrix, int64_t P, bool* visible,
                         cudaStream_t stream) {
  if (P <= 0) return cudaSuccess;
  mark_visible_kernel<<<grid_1d(P, 256), 256, 0, stream>>>(means, viewmatrix, P, visible);
  return cudaGetLastError();
}

cudaError_t render_backward(const RasterArgs& a, const float* geom, const int32_t* binning,
                            const int32_t* ranges, const float* final_T, const int32_t* last,
                            const GradImages& grad, float* slots, double* dbg_tiles,
                            cudaStream_t stream) {
  if (a.grid_x <= 0 || a.grid_y <= 0) return cudaSuccess;
  const dim3 grid(a.grid_x, a.grid_y), block(kBlockX, kBlockY);
  render_backward_kernel<<<grid, block, 0, stream>>>(a, geom, binning, ranges, final_T, last, grad,
                                                     slots, dbg_tiles);
  return cudaGetLastError();
}

int64_t gaussian_backward_blocks(int64_t P) { return P <= 0 ? 0 : (P + kGaussThreads - 1) / kGaussThreads; }

cudaError_t gaussian_backward(const RasterArgs& a, const int32_t* radii, const int64_t* offsets,
                              const float* slots, const GaussianGrads& out, double* cam_partials,
                              cudaStream_t stream) {
  const int64_t nb = gaussian_backward_blocks(a.P);
  if (nb == 0 || (out.means3D == nullptr && cam_partials == nullptr)) return cudaSuccess;
  if (cam_partials != nullptr)
    gaussian_backward_kernel<true><<<(unsigned)nb, kGaussThreads, 0, stream>>>(a, radii, offsets, slots,
                                                                              out, cam_partials);
  else
    gaussian_backward_kernel<false><<<(unsigned)nb, kGaussThreads, 0, stream>>>(a, radii, offsets,
                                                                               slots, out, nullptr);
  return cudaGetLastError();
}

cudaError_t reduce_partials(const double* parts, int64_t nparts, int stride, int ncomp, float* out,
                            cudaStream_t stream) {
  if (ncomp <= 0) return cudaSuccess;
  reduce_partials_kernel<<<ncomp, kReduceThreads, 0, stream>>>(parts, nparts, stride, out);
  return cudaGetLastError();
}

}  // namespace cuda
}  // namespace grp
