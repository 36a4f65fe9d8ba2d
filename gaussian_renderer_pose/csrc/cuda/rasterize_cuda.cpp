// Torch-facing wrapper of the CUDA rasterizer: checks, allocations (PyTorch caching allocator),
// current stream, then the plain-pointer launchers of kernels.h. Compiled only in a CUDA build
// (setup.py CUDAExtension, -DGRP_WITH_CUDA). Registers the CUDA kernels of the ops of ../ops.h
// (same arguments, returns and saved-state meaning as the CPU kernels), so that the dispatcher
// routes CUDA tensors here.
//
// One host synchronisation per forward (the number of (tile, Gaussian) entries, needed to size the
// sort buffers and the binning tensor), as upstream. The backward has none.
#include <ATen/ATen.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>  // (not ATen/cuda/CUDAContext.h: it pulls in cuBLAS/cuSPARSE)

#include <algorithm>
#include <cstdint>
#include <limits>
#include <optional>
#include <vector>

#include "../common/config.h"
#include "../common/raster.h"
#include "../common/raster_args_torch.h"
#include "../ops.h"
#include "kernels.h"

namespace grp {
namespace {

void check_cuda_tensor(const at::Tensor& t, const char* name, std::initializer_list<int64_t> shape,
                       const at::Device& device) {
  check_float_tensor(t, name, shape, [&device](const at::Tensor& x, const char* n) {
    TORCH_CHECK(x.device() == device, n, " must be on ", device, " (the device of means3D), got ",
                x.device());
  });
}

void check_cuda_state(const at::Tensor& t, const char* name, at::ScalarType st,
                      const at::Device& device) {
  TORCH_CHECK(t.defined() && t.device() == device && t.scalar_type() == st && t.is_contiguous(),
              name, " must be a contiguous tensor of type ", st, " on ", device);
}

// Tensor check of fill_raster_args: on the device of means3D (which must be a CUDA tensor).
struct CudaCheck {
  at::Device dev;
  explicit CudaCheck(const at::Tensor& means3D) : dev(cuda_device_of(means3D)) {}
  static at::Device cuda_device_of(const at::Tensor& means3D) {
    TORCH_CHECK(means3D.defined() && means3D.is_cuda(), "means3D must be a CUDA tensor");
    return means3D.device();
  }
  void operator()(const at::Tensor& t, const char* name, std::initializer_list<int64_t> shape) const {
    check_cuda_tensor(t, name, shape, dev);
  }
};

void check_gaussian_count(const RasterArgs& a) {
  TORCH_CHECK(a.P < (int64_t)std::numeric_limits<int32_t>::max(), "too many Gaussians: ", a.P);
}

at::Tensor byte_buffer(size_t bytes, const at::TensorOptions& like) {
  return at::empty({(int64_t)(bytes > 0 ? bytes : 1)}, like.dtype(at::kByte));
}

uint64_t* as_u64(at::Tensor& t) { return reinterpret_cast<uint64_t*>(t.data_ptr<int64_t>()); }

}  // namespace

// ------------------------------------------------------------------------------------------------
// Forward
// ------------------------------------------------------------------------------------------------
ForwardOutputs rasterize_forward_cuda(const RasterInputs& args) {
  const at::Tensor& means3D = args.means3D;
  const RasterArgs a = fill_raster_args(CudaCheck(means3D), args);
  check_gaussian_count(a);
  const c10::cuda::CUDAGuard guard(means3D.device());
  const cudaStream_t stream = c10::cuda::getCurrentCUDAStream().stream();
  const int64_t P = a.P;
  const auto fopt = means3D.options();
  const auto iopt = fopt.dtype(at::kInt);
  const auto lopt = fopt.dtype(at::kLong);
  const int64_t num_tiles = (int64_t)a.grid_x * a.grid_y;

  ForwardOutputs fw = allocate_forward_outputs(a, fopt);
  const at::Tensor& radii = fw.radii;
  const at::Tensor& geom = fw.geom;
  const at::Tensor& offsets = fw.offsets;
  at::Tensor ntiles = at::empty({P}, lopt);

  // 1. Preprocess + prefix sum of the tiles touched.
  C10_CUDA_CHECK(cuda::preprocess(a, geom.data_ptr<float>(), radii.data_ptr<int32_t>(),
                                  ntiles.data_ptr<int64_t>(), stream));
  {
    const size_t bytes = cuda::scan_temp_bytes(P);
    at::Tensor temp = byte_buffer(bytes, fopt);
    C10_CUDA_CHECK(cuda::scan_offsets(temp.data_ptr(), bytes, ntiles.data_ptr<int64_t>(),
                                      offsets.data_ptr<int64_t>(), P, stream));
  }
  const int64_t num_rendered = offsets.select(0, P).item<int64_t>();  // host sync
  TORCH_CHECK(num_rendered >= 0 && num_rendered < (int64_t)std::numeric_limits<int32_t>::max(),
              "too many (tile, Gaussian) pairs: ", num_rendered);

  // 2. Binning: duplicate with (tile | depth) keys, stable radix sort, tile ranges.
  fw.tile_ranges = at::zeros({num_tiles + 1}, iopt);
  fw.binning = at::empty({num_rendered, 2}, iopt);
  const at::Tensor& tile_ranges = fw.tile_ranges;
  const at::Tensor& binning = fw.binning;
  if (num_rendered > 0) {
    at::Tensor keys_in = at::empty({num_rendered}, lopt);
    at::Tensor keys_out = at::empty({num_rendered}, lopt);
    at::Tensor values_in = at::empty({num_rendered, 2}, iopt);
    C10_CUDA_CHECK(cuda::duplicate_with_keys(a, geom.data_ptr<float>(), radii.data_ptr<int32_t>(),
                                             offsets.data_ptr<int64_t>(), as_u64(keys_in),
                                             values_in.data_ptr<int32_t>(), stream));
    const int end_bit = cuda::sort_end_bit(num_tiles);
    const size_t bytes = cuda::sort_temp_bytes(num_rendered, end_bit);
    at::Tensor temp = byte_buffer(bytes, fopt);
    C10_CUDA_CHECK(cuda::sort_pairs(temp.data_ptr(), bytes, as_u64(keys_in), as_u64(keys_out),
                                    values_in.data_ptr<int32_t>(), binning.data_ptr<int32_t>(),
                                    num_rendered, end_bit, stream));
    C10_CUDA_CHECK(cuda::tile_ranges(as_u64(keys_out), num_rendered, num_tiles,
                                     tile_ranges.data_ptr<int32_t>(), stream));
  }

  // 3. Render.
  const RenderOutputs out = render_outputs(fw);
  C10_CUDA_CHECK(cuda::render(a, geom.data_ptr<float>(), binning.data_ptr<int32_t>(),
                              tile_ranges.data_ptr<int32_t>(), out, stream));

  return fw;
}

// ------------------------------------------------------------------------------------------------
// Backward
// ------------------------------------------------------------------------------------------------
BackwardOutputs rasterize_backward_cuda(const BackwardInputs& b) {
  const RasterArgs a = fill_raster_args(CudaCheck(b.means3D), b);
  check_gaussian_count(a);
  const at::Device dev = b.means3D.device();
  const int64_t P = a.P;
  const int64_t num_tiles = (int64_t)a.grid_x * a.grid_y;
  check_backward_inputs(
      [&dev](const at::Tensor& t, const char* name, std::initializer_list<int64_t> shape) {
        check_cuda_tensor(t, name, shape, dev);
      },
      [&dev](const at::Tensor& t, const char* name, at::ScalarType st) {
        check_cuda_state(t, name, st, dev);
      },
      a, b);
  TORCH_CHECK(b.binning.dim() == 2 && b.binning.size(1) == 2,
              "saved binning state must be [R, 2], got ", b.binning.sizes());
  const int64_t num_rendered = b.binning.size(0);  // no host sync (the CPU also checks offsets[P])

  const c10::cuda::CUDAGuard guard(dev);
  const cudaStream_t stream = c10::cuda::getCurrentCUDAStream().stream();
  const auto fopt = b.means3D.options();
  const auto dopt = fopt.dtype(at::kDouble);
  const bool compute_camera_grad = b.compute_camera_grad;
  const bool compute_gaussian_grads = b.compute_gaussian_grads;
  BackwardOutputs grads = zero_gaussian_grads(a, compute_gaussian_grads, fopt);

  // 4. Per-tile backward into per-entry slots (zero-filled: unvisited entries contribute 0).
  at::Tensor slots = at::zeros({num_rendered * kSlot}, fopt);
  at::Tensor dbg_tiles = at::empty({num_tiles * 3}, dopt);
  const GradImages gin{b.grad_color.data_ptr<float>(), b.grad_invdepth.data_ptr<float>(),
                       b.grad_depth_acc.data_ptr<float>(), b.grad_alpha.data_ptr<float>()};
  C10_CUDA_CHECK(cuda::render_backward(a, b.geom.data_ptr<float>(), b.binning.data_ptr<int32_t>(),
                                       b.tile_ranges.data_ptr<int32_t>(),
                                       b.final_T.data_ptr<float>(),
                                       b.last_contrib.data_ptr<int32_t>(), gin,
                                       slots.data_ptr<float>(), dbg_tiles.data_ptr<double>(),
                                       stream));
  grads.grad_bg = at::empty({3}, fopt);
  C10_CUDA_CHECK(cuda::reduce_partials(dbg_tiles.data_ptr<double>(), num_tiles, 3, 3,
                                       grads.grad_bg.data_ptr<float>(), stream));

  // 5. Per-Gaussian backward (+ per-block camera terms, reduced in a fixed order); only the camera
  // terms without compute_gaussian_grads, nothing with neither flag.
  const GaussianGrads gout = gaussian_grad_ptrs(grads);
  const int64_t nblocks = cuda::gaussian_backward_blocks(P);
  at::Tensor cam_partials;
  if (compute_camera_grad) cam_partials = at::empty({std::max<int64_t>(nblocks, 1) * kCamGrad}, dopt);
  double* cam = compute_camera_grad ? cam_partials.data_ptr<double>() : nullptr;
  C10_CUDA_CHECK(cuda::gaussian_backward(a, b.radii.data_ptr<int32_t>(),
                                         b.offsets.data_ptr<int64_t>(), slots.data_ptr<float>(),
                                         gout, cam, stream));
  if (compute_camera_grad) {
    // Rows of cam_partials: viewmatrix [0, 16), projmatrix [16, 32), campos [32, 35).
    grads.grad_viewmatrix = at::empty({4, 4}, fopt);
    grads.grad_projmatrix = at::empty({4, 4}, fopt);
    grads.grad_campos = at::empty({3}, fopt);
    const double* parts = cam_partials.data_ptr<double>();
    C10_CUDA_CHECK(cuda::reduce_partials(parts, nblocks, kCamGrad, 16,
                                         grads.grad_viewmatrix.data_ptr<float>(), stream));
    C10_CUDA_CHECK(cuda::reduce_partials(parts + 16, nblocks, kCamGrad, 16,
                                         grads.grad_projmatrix.data_ptr<float>(), stream));
    C10_CUDA_CHECK(cuda::reduce_partials(parts + 32, nblocks, kCamGrad, 3,
                                         grads.grad_campos.data_ptr<float>(), stream));
  }
  return grads;
}

VisibilityOutputs mark_visible_cuda(const VisibilityInputs& args) {
  const at::Tensor& means3D = args.means3D;
  TORCH_CHECK(means3D.defined() && means3D.is_cuda(), "means3D must be a CUDA tensor");
  const at::Device dev = means3D.device();
  check_cuda_tensor(means3D, "means3D", {-1, 3}, dev);
  check_cuda_tensor(args.viewmatrix, "viewmatrix", {4, 4}, dev);
  check_cuda_tensor(args.projmatrix, "projmatrix", {4, 4}, dev);
  const c10::cuda::CUDAGuard guard(dev);
  const int64_t P = means3D.size(0);
  VisibilityOutputs out;
  out.visible = at::empty({P}, means3D.options().dtype(at::kBool));
  C10_CUDA_CHECK(cuda::mark_visible(means3D.data_ptr<float>(), args.viewmatrix.data_ptr<float>(),
                                    P, out.visible.data_ptr<bool>(),
                                    c10::cuda::getCurrentCUDAStream().stream()));
  return out;
}

TORCH_LIBRARY_IMPL(grp, CUDA, m) {
  m.impl(kForwardOp, boxed_kernel<&rasterize_forward_cuda>());
  m.impl(kBackwardOp, boxed_kernel<&rasterize_backward_cuda>());
  m.impl(kMarkVisibleOp, boxed_kernel<&mark_visible_cuda>());
}

}  // namespace grp
