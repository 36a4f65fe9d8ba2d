// Host launchers of the CUDA rasterizer (pure CUDA: no torch/ATen). Implemented in kernels.cu,
// called by the torch-facing wrapper rasterize_cuda.cpp, which owns every allocation and the
// stream. All pointers are DEVICE pointers unless stated otherwise; every launcher is asynchronous
// on `stream` and returns the launch status (cudaGetLastError after the launch).
//
// The numerics are those of the CPU kernel (../cpu/rasterize_cpu.cpp) and docs/CONTRACTS.md
// "Forward numerics": both call the same per-Gaussian helpers of ../common/{math,sh}.h, and the
// saved state has the same meaning (see ../ops.h):
//   geom [P, 16] f32 (fields below), binning [R, 2] i32 = (gaussian id, slot id) in tile-major,
//   depth-minor order, tile_ranges [tiles + 1] i32, offsets [P + 1] i64, final_T [H, W] f32,
//   last_contrib [H, W] i32 (index in the tile's list of the last contributor, -1 if none).
// Slot of an entry = offsets[g] + (ty - rect_min_y) * rect_w + (tx - rect_min_x): the backward of
// tile (tx, ty) writes Gaussian g's partial gradient there, so the backward needs no atomics and
// is bitwise deterministic (fixed reduction orders everywhere, camera terms included).
#pragma once

#include <cuda_runtime_api.h>

#include <cstddef>
#include <cstdint>

#include "../common/raster.h"

namespace grp {
namespace cuda {

// Geom record layout (kG*), kNumFeat, kSlot, kCamGrad, RasterArgs (inputs of one rasterization,
// device pointers here) and GaussianGrads: ../common/raster.h, shared with the CPU kernel.
constexpr int kGaussThreads = 256;           // threads per block of the per-Gaussian kernels

// ---- forward ------------------------------------------------------------------------------------
// Cull, project, cov2D/conic, radius, tile rect, colour. Writes geom [P,16], radii [P] (0 = culled)
// and ntiles [P] (tiles touched, 0 when culled).
cudaError_t preprocess(const RasterArgs& a, float* geom, int32_t* radii, int64_t* ntiles,
                       cudaStream_t stream);

// offsets[0] = 0, offsets[1..P] = inclusive prefix sum of ntiles. `temp` of scan_temp_bytes(P).
size_t scan_temp_bytes(int64_t P);
cudaError_t scan_offsets(void* temp, size_t temp_bytes, const int64_t* ntiles, int64_t* offsets,
                         int64_t P, cudaStream_t stream);

// One (key, value) per (Gaussian, touched tile): key = tile << 32 | float bits of view depth,
// value = (gaussian id, slot id). keys [R], values [R, 2].
cudaError_t duplicate_with_keys(const RasterArgs& a, const float* geom, const int32_t* radii,
                                const int64_t* offsets, uint64_t* keys, int32_t* values,
                                cudaStream_t stream);

// Stable radix sort of the (key, value) pairs on the low sort_end_bit(num_tiles) bits.
int sort_end_bit(int64_t num_tiles);
size_t sort_temp_bytes(int64_t R, int end_bit);
cudaError_t sort_pairs(void* temp, size_t temp_bytes, const uint64_t* keys_in, uint64_t* keys_out,
                       const int32_t* values_in, int32_t* values_out, int64_t R, int end_bit,
                       cudaStream_t stream);

// tile_ranges [num_tiles + 1] from the sorted keys (entries of tile t: [ranges[t], ranges[t+1])).
// With R == 0 nothing is launched: the caller zero-fills `ranges`.
cudaError_t tile_ranges(const uint64_t* sorted_keys, int64_t R, int64_t num_tiles, int32_t* ranges,
                        cudaStream_t stream);

// RenderOutputs: ../common/raster.h.
// One 16x16 block per tile, front-to-back blending over shared-memory batches.
cudaError_t render(const RasterArgs& a, const float* geom, const int32_t* binning,
                   const int32_t* ranges, const RenderOutputs& out, cudaStream_t stream);

// view-space z > near plane (upstream markVisible); visible [P] (bool, 1 byte).
cudaError_t mark_visible(const float* means, const float* viewmatrix, int64_t P, bool* visible,
                         cudaStream_t stream);

// ---- backward -----------------------------------------------------------------------------------
// GradImages: ../common/raster.h.

// Per tile, reverse order from the last contributor: writes slots [R, kSlot] (the caller
// zero-fills them: entries behind every pixel's last contributor are not visited) and the per-tile
// background terms dbg_tiles [num_tiles, 3] (double).
cudaError_t render_backward(const RasterArgs& a, const float* geom, const int32_t* binning,
                            const int32_t* ranges, const float* final_T, const int32_t* last,
                            const GradImages& grad, float* slots, double* dbg_tiles,
                            cudaStream_t stream);

// GaussianGrads (../common/raster.h): outputs, zero-filled by the caller; nullptr where the input
// is absent.
// Number of blocks of the per-Gaussian backward (= rows of cam_partials).
int64_t gaussian_backward_blocks(int64_t P);
// Per Gaussian: sums its slots in order and chains through the per-Gaussian VJPs, writing `out`
// (all nullptr when the Gaussians' gradients are not wanted: `out` is then not touched). When
// cam_partials != nullptr, also reduces the camera terms of each block (in double) into
// cam_partials [gaussian_backward_blocks(P), kCamGrad]. Launches nothing when there is neither.
cudaError_t gaussian_backward(const RasterArgs& a, const int32_t* radii, const int64_t* offsets,
                              const float* slots, const GaussianGrads& out, double* cam_partials,
                              cudaStream_t stream);

// out[c] = (float) sum_i parts[i * stride + c] for c < ncomp, in a fixed order (deterministic).
cudaError_t reduce_partials(const double* parts, int64_t nparts, int stride, int ncomp, float* out,
                            cudaStream_t stream);

}  // namespace cuda
}  // namespace grp
