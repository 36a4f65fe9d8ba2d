// Torch-facing wrapper of the CUDA rasterizer: checks, allocations (PyTorch caching allocator),
// current stream, then the plain-pointer launchers of kernels.h. Compiled only in a CUDA build
// (setup.py CUDAExtension, -DGRP_WITH_CUDA). Same signatures, returns and saved-state meaning as
// the CPU functions of ../ops.h (rasterize_forward_cpu / rasterize_backward_cpu / mark_visible_cpu),
// so that _native.py routes CUDA tensors here unchanged.
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
#include "../ops.h"
#include "kernels.h"

namespace grp {
namespace {

void check_cuda_tensor(const at::Tensor& t, const char* name, std::initializer_list<int64_t> shape,
                       const at::Device& device) {
  TORCH_CHECK(t.defined(), name, " must be a tensor");
  TORCH_CHECK(t.device() == device, name, " must be on ", device, " (the device of means3D), got ",
              t.device());
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

void check_cuda_state(const at::Tensor& t, const char* name, at::ScalarType st,
                      const at::Device& device) {
  TORCH_CHECK(t.defined() && t.device() == device && t.scalar_type() == st && t.is_contiguous(),
              name, " must be a contiguous tensor of type ", st, " on ", device);
}

bool present(const std::optional<at::Tensor>& t) { return t.has_value() && t->defined(); }

cuda::SceneArgs check_inputs(const at::Tensor& means3D, const at::Tensor& opacities,
                             const std::optional<at::Tensor>& shs,
                             const std::optional<at::Tensor>& colors_precomp,
                             const std::optional<at::Tensor>& scales,
                             const std::optional<at::Tensor>& rotations,
                             const std::optional<at::Tensor>& cov3D_precomp, const at::Tensor& bg,
                             const at::Tensor& viewmatrix, const at::Tensor& projmatrix,
                             const at::Tensor& campos, int64_t H, int64_t W, double tanfovx,
                             double tanfovy, double scale_modifier, int64_t sh_degree,
                             bool antialiasing) {
  TORCH_CHECK(means3D.defined() && means3D.is_cuda(), "means3D must be a CUDA tensor");
  const at::Device dev = means3D.device();
  check_cuda_tensor(means3D, "means3D", {-1, 3}, dev);
  cuda::SceneArgs a;
  a.P = means3D.size(0);
  const int64_t P = a.P;
  TORCH_CHECK(P < (int64_t)std::numeric_limits<int32_t>::max(), "too many Gaussians: ", P);
  check_cuda_tensor(opacities, "opacities", {P, 1}, dev);
  check_cuda_tensor(bg, "bg", {3}, dev);
  check_cuda_tensor(viewmatrix, "viewmatrix", {4, 4}, dev);
  check_cuda_tensor(projmatrix, "projmatrix", {4, 4}, dev);
  check_cuda_tensor(campos, "campos", {3}, dev);
  TORCH_CHECK(H > 0 && W > 0 && H < (1 << 20) && W < (1 << 20), "image size must be positive, got ",
              H, "x", W);
  TORCH_CHECK(sh_degree >= 0 && sh_degree <= 3, "sh_degree must be in 0..3, got ", sh_degree);
  TORCH_CHECK(tanfovx > 0 && tanfovy > 0, "tanfovx/tanfovy must be positive");
  const bool has_colors = present(colors_precomp);
  TORCH_CHECK(has_colors || present(shs), "either shs or colors_precomp must be given");
  if (has_colors) {
    check_cuda_tensor(*colors_precomp, "colors_precomp", {P, 3}, dev);
    a.colors = colors_precomp->data_ptr<float>();
  } else {
    check_cuda_tensor(*shs, "shs", {P, -1, 3}, dev);
    a.M = shs->size(1);
    TORCH_CHECK(a.M >= (sh_degree + 1) * (sh_degree + 1), "shs has ", a.M,
                " coefficients, sh_degree ", sh_degree, " needs ", (sh_degree + 1) * (sh_degree + 1));
    a.shs = shs->data_ptr<float>();
  }
  if (present(cov3D_precomp)) {
    check_cuda_tensor(*cov3D_precomp, "cov3D_precomp", {P, 6}, dev);
    a.cov3d = cov3D_precomp->data_ptr<float>();
  } else {
    TORCH_CHECK(present(scales) && present(rotations),
                "either cov3D_precomp or scales and rotations must be given");
    check_cuda_tensor(*scales, "scales", {P, 3}, dev);
    check_cuda_tensor(*rotations, "rotations", {P, 4}, dev);
    a.scales = scales->data_ptr<float>();
    a.rots = rotations->data_ptr<float>();
  }
  a.H = (int)H;
  a.W = (int)W;
  a.grid_x = (a.W + kBlockX - 1) / kBlockX;
  a.grid_y = (a.H + kBlockY - 1) / kBlockY;
  a.tanfovx = (float)tanfovx;
  a.tanfovy = (float)tanfovy;
  a.focal_x = a.W / (2.0f * a.tanfovx);
  a.focal_y = a.H / (2.0f * a.tanfovy);
  a.scale_modifier = (float)scale_modifier;
  a.sh_degree = (int)sh_degree;
  a.antialiasing = antialiasing;
  a.means = means3D.data_ptr<float>();
  a.opac = opacities.data_ptr<float>();
  a.bg = bg.data_ptr<float>();
  a.viewmatrix = viewmatrix.data_ptr<float>();
  a.projmatrix = projmatrix.data_ptr<float>();
  a.campos = campos.data_ptr<float>();
  return a;
}

at::Tensor byte_buffer(size_t bytes, const at::TensorOptions& like) {
  return at::empty({(int64_t)(bytes > 0 ? bytes : 1)}, like.dtype(at::kByte));
}

uint64_t* as_u64(at::Tensor& t) { return reinterpret_cast<uint64_t*>(t.data_ptr<int64_t>()); }

}  // namespace

// ------------------------------------------------------------------------------------------------
// Forward
// ------------------------------------------------------------------------------------------------
std::vector<at::Tensor> rasterize_forward_cuda(
    const at::Tensor& means3D, const at::Tensor& opacities, const std::optional<at::Tensor>& shs,
    const std::optional<at::Tensor>& colors_precomp, const std::optional<at::Tensor>& scales,
    const std::optional<at::Tensor>& rotations, const std::optional<at::Tensor>& cov3D_precomp,
    const at::Tensor& bg, const at::Tensor& viewmatrix, const at::Tensor& projmatrix,
    const at::Tensor& campos, int64_t image_height, int64_t image_width, double tanfovx,
    double tanfovy, double scale_modifier, int64_t sh_degree, bool prefiltered, bool antialiasing) {
  (void)prefiltered;
  const cuda::SceneArgs a = check_inputs(means3D, opacities, shs, colors_precomp, scales, rotations,
                                         cov3D_precomp, bg, viewmatrix, projmatrix, campos,
                                         image_height, image_width, tanfovx, tanfovy,
                                         scale_modifier, sh_degree, antialiasing);
  const c10::cuda::CUDAGuard guard(means3D.device());
  const cudaStream_t stream = c10::cuda::getCurrentCUDAStream().stream();
  const int64_t P = a.P;
  const auto fopt = means3D.options();
  const auto iopt = fopt.dtype(at::kInt);
  const auto lopt = fopt.dtype(at::kLong);
  const int64_t num_tiles = (int64_t)a.grid_x * a.grid_y;

  at::Tensor color = at::empty({3, a.H, a.W}, fopt);
  at::Tensor invdepth = at::empty({1, a.H, a.W}, fopt);
  at::Tensor depth_acc = at::empty({1, a.H, a.W}, fopt);
  at::Tensor alpha = at::empty({1, a.H, a.W}, fopt);
  at::Tensor final_T = at::empty({a.H, a.W}, fopt);
  at::Tensor last_contrib = at::empty({a.H, a.W}, iopt);
  at::Tensor radii = at::empty({P}, iopt);
  at::Tensor geom = at::empty({P, cuda::kGStride}, fopt);
  at::Tensor offsets = at::empty({P + 1}, lopt);
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
  at::Tensor tile_ranges = at::zeros({num_tiles + 1}, iopt);
  at::Tensor binning = at::empty({num_rendered, 2}, iopt);
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
  const cuda::RenderOutputs out{color.data_ptr<float>(),   invdepth.data_ptr<float>(),
                                depth_acc.data_ptr<float>(), alpha.data_ptr<float>(),
                                final_T.data_ptr<float>(),   last_contrib.data_ptr<int32_t>()};
  C10_CUDA_CHECK(cuda::render(a, geom.data_ptr<float>(), binning.data_ptr<int32_t>(),
                              tile_ranges.data_ptr<int32_t>(), out, stream));

  return {color, radii, invdepth, depth_acc, alpha, geom, binning, tile_ranges, offsets, final_T,
          last_contrib};
}

// ------------------------------------------------------------------------------------------------
// Backward
// ------------------------------------------------------------------------------------------------
std::vector<at::Tensor> rasterize_backward_cuda(
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
  const cuda::SceneArgs a = check_inputs(means3D, opacities, shs, colors_precomp, scales, rotations,
                                         cov3D_precomp, bg, viewmatrix, projmatrix, campos,
                                         image_height, image_width, tanfovx, tanfovy,
                                         scale_modifier, sh_degree, antialiasing);
  const at::Device dev = means3D.device();
  const int64_t P = a.P;
  const int64_t num_tiles = (int64_t)a.grid_x * a.grid_y;
  check_cuda_tensor(grad_color, "grad_color", {3, a.H, a.W}, dev);
  check_cuda_tensor(grad_invdepth, "grad_invdepth", {1, a.H, a.W}, dev);
  check_cuda_tensor(grad_depth_acc, "grad_depth_acc", {1, a.H, a.W}, dev);
  check_cuda_tensor(grad_alpha, "grad_alpha", {1, a.H, a.W}, dev);
  check_cuda_tensor(geom, "geom", {P, cuda::kGStride}, dev);
  check_cuda_tensor(final_T, "final_T", {a.H, a.W}, dev);
  check_cuda_state(radii, "radii", at::kInt, dev);
  check_cuda_state(binning, "binning", at::kInt, dev);
  check_cuda_state(tile_ranges, "tile_ranges", at::kInt, dev);
  check_cuda_state(offsets, "offsets", at::kLong, dev);
  check_cuda_state(last_contrib, "last_contrib", at::kInt, dev);
  TORCH_CHECK(radii.numel() == P && offsets.numel() == P + 1 && tile_ranges.numel() == num_tiles + 1 &&
                  last_contrib.numel() == (int64_t)a.H * a.W,
              "saved forward state does not match the inputs");
  TORCH_CHECK(binning.dim() == 2 && binning.size(1) == 2, "saved binning state must be [R, 2], got ",
              binning.sizes());
  const int64_t num_rendered = binning.size(0);  // no host sync (the CPU also checks offsets[P])

  const c10::cuda::CUDAGuard guard(dev);
  const cudaStream_t stream = c10::cuda::getCurrentCUDAStream().stream();
  const auto fopt = means3D.options();
  const auto dopt = fopt.dtype(at::kDouble);
  at::Tensor dL_dmeans3D = at::zeros({P, 3}, fopt);
  at::Tensor dL_dmeans2D = at::zeros({P, 3}, fopt);
  at::Tensor dL_dopac = at::zeros({P, 1}, fopt);
  at::Tensor dL_dshs, dL_dcolors, dL_dscales, dL_drots, dL_dcov;
  if (a.colors != nullptr) dL_dcolors = at::zeros({P, 3}, fopt);
  else dL_dshs = at::zeros({P, a.M, 3}, fopt);
  if (a.cov3d != nullptr) {
    dL_dcov = at::zeros({P, 6}, fopt);
  } else {
    dL_dscales = at::zeros({P, 3}, fopt);
    dL_drots = at::zeros({P, 4}, fopt);
  }

  // 4. Per-tile backward into per-entry slots (zero-filled: unvisited entries contribute 0).
  at::Tensor slots = at::zeros({num_rendered * cuda::kSlot}, fopt);
  at::Tensor dbg_tiles = at::empty({num_tiles * 3}, dopt);
  const cuda::GradImages gin{grad_color.data_ptr<float>(), grad_invdepth.data_ptr<float>(),
                             grad_depth_acc.data_ptr<float>(), grad_alpha.data_ptr<float>()};
  C10_CUDA_CHECK(cuda::render_backward(a, geom.data_ptr<float>(), binning.data_ptr<int32_t>(),
                                       tile_ranges.data_ptr<int32_t>(), final_T.data_ptr<float>(),
                                       last_contrib.data_ptr<int32_t>(), gin,
                                       slots.data_ptr<float>(), dbg_tiles.data_ptr<double>(),
                                       stream));
  at::Tensor dL_dbg = at::empty({3}, fopt);
  C10_CUDA_CHECK(cuda::reduce_partials(dbg_tiles.data_ptr<double>(), num_tiles, 3, 3,
                                       dL_dbg.data_ptr<float>(), stream));

  // 5. Per-Gaussian backward (+ per-block camera terms, reduced in a fixed order).
  auto ptr = [](at::Tensor& t) { return t.defined() ? t.data_ptr<float>() : nullptr; };
  const cuda::GaussianGrads gout{ptr(dL_dmeans3D), ptr(dL_dmeans2D), ptr(dL_dopac), ptr(dL_dshs),
                                 ptr(dL_dcolors),  ptr(dL_dscales),  ptr(dL_drots), ptr(dL_dcov)};
  const int64_t nblocks = cuda::gaussian_backward_blocks(P);
  at::Tensor cam_partials;
  if (compute_camera_grad) cam_partials = at::empty({std::max<int64_t>(nblocks, 1) * cuda::kCamGrad}, dopt);
  C10_CUDA_CHECK(cuda::gaussian_backward(a, radii.data_ptr<int32_t>(), offsets.data_ptr<int64_t>(),
                                         slots.data_ptr<float>(), gout,
                                         compute_camera_grad ? cam_partials.data_ptr<double>() : nullptr,
                                         stream));
  at::Tensor dL_dV, dL_dP, dL_dcampos;
  if (compute_camera_grad) {
    // Rows of cam_partials: viewmatrix [0, 16), projmatrix [16, 32), campos [32, 35).
    dL_dV = at::empty({4, 4}, fopt);
    dL_dP = at::empty({4, 4}, fopt);
    dL_dcampos = at::empty({3}, fopt);
    const double* parts = cam_partials.data_ptr<double>();
    C10_CUDA_CHECK(cuda::reduce_partials(parts, nblocks, cuda::kCamGrad, 16, dL_dV.data_ptr<float>(),
                                         stream));
    C10_CUDA_CHECK(cuda::reduce_partials(parts + 16, nblocks, cuda::kCamGrad, 16,
                                         dL_dP.data_ptr<float>(), stream));
    C10_CUDA_CHECK(cuda::reduce_partials(parts + 32, nblocks, cuda::kCamGrad, 3,
                                         dL_dcampos.data_ptr<float>(), stream));
  }
  return {dL_dmeans3D, dL_dmeans2D, dL_dopac, dL_dshs, dL_dcolors, dL_dscales, dL_drots, dL_dcov,
          dL_dbg, dL_dV, dL_dP, dL_dcampos};
}

at::Tensor mark_visible_cuda(const at::Tensor& means3D, const at::Tensor& viewmatrix,
                             const at::Tensor& projmatrix) {
  TORCH_CHECK(means3D.defined() && means3D.is_cuda(), "means3D must be a CUDA tensor");
  const at::Device dev = means3D.device();
  check_cuda_tensor(means3D, "means3D", {-1, 3}, dev);
  check_cuda_tensor(viewmatrix, "viewmatrix", {4, 4}, dev);
  check_cuda_tensor(projmatrix, "projmatrix", {4, 4}, dev);
  const c10::cuda::CUDAGuard guard(dev);
  const int64_t P = means3D.size(0);
  at::Tensor out = at::empty({P}, means3D.options().dtype(at::kBool));
  C10_CUDA_CHECK(cuda::mark_visible(means3D.data_ptr<float>(), viewmatrix.data_ptr<float>(), P,
                                    out.data_ptr<bool>(), c10::cuda::getCurrentCUDAStream().stream()));
  return out;
}

}  // namespace grp
