// C++ entry points of gaussian_renderer_pose._C (declared once for the CPU and a future CUDA
// implementation). Python wrapper: gaussian_renderer_pose/_native.py.
//
// Forward numerics: docs/CONTRACTS.md "Forward numerics" (upstream diff-gaussian-rasterization,
// 2024 main with antialiasing). Gradients are exact derivatives of that forward, except where a
// clamp/threshold makes the forward piecewise constant (the gradient there is that of the branch
// taken), and the per-pixel transmittance of the backward is recovered back to front by
// T_i = T_{i+1} / (1 - alpha_i) as upstream (float32 rounding differs from a forward product).
//
// Args (all tensors float32, contiguous, on the CPU for the *_cpu functions):
//   means3D        [P, 3]    world-space means
//   opacities      [P, 1]    activated opacities in [0, 1]
//   shs            [P, M, 3] SH coefficients, M >= (sh_degree + 1)^2        (optional)
//   colors_precomp [P, 3]    RGB used instead of SH when given              (optional)
//   scales         [P, 3]    activated scales (multiplied by scale_modifier) (optional)
//   rotations      [P, 4]    quaternion (w, x, y, z), NOT normalised         (optional)
//   cov3D_precomp  [P, 6]    world covariance (xx, xy, xz, yy, yz, zz), used instead of
//                            scales/rotations when given                     (optional)
//   bg             [3]       background colour
//   viewmatrix     [4, 4]    w2c^T (3DGS world_view_transform), row-major
//   projmatrix     [4, 4]    (P w2c)^T (3DGS full_proj_transform), row-major
//   campos         [3]       camera centre in world
//   image_height, image_width (H, W), tanfovx, tanfovy, scale_modifier, sh_degree (0..3),
//   prefiltered (accepted, no effect: culling is always done), antialiasing.
//
// rasterize_forward_cpu returns 11 tensors:
//   [0] color      [3, H, W]  C = sum_i c_i a_i T_i + T_final bg
//   [1] radii      [P] int32  screen radius in pixels, 0 when culled
//   [2] invdepth   [1, H, W]  sum_i a_i T_i / z_i
//   [3] depth_acc  [1, H, W]  sum_i a_i T_i z_i
//   [4] alpha      [1, H, W]  1 - T_final
//   [5..10] saved state for the backward (opaque): geom [P, 16] f32, binning [R, 2] i32
//       (gaussian id, slot id) per tile in depth order, tile_ranges [tiles + 1] i32,
//       offsets [P + 1] i64 (slot range of each Gaussian), final_T [H, W] f32,
//       last_contrib [H, W] i32 (index in the tile list of the last contributor, -1 if none).
//
// rasterize_backward_cpu takes the forward's inputs, the 7 tensors radii + [5..10], the output
// gradients grad_color [3,H,W], grad_invdepth / grad_depth_acc / grad_alpha [1,H,W], and
// compute_camera_grad. It returns 12 tensors (undefined -> None where the input is absent):
//   dL_dmeans3D [P,3], dL_dmeans2D [P,3] (d/d NDC xy, z = 0; upstream units), dL_dopacities [P,1],
//   dL_dshs [P,M,3], dL_dcolors_precomp [P,3], dL_dscales [P,3], dL_drotations [P,4],
//   dL_dcov3D_precomp [P,6], dL_dbg [3], and, only when compute_camera_grad, dL_dviewmatrix
//   [4,4], dL_dprojmatrix [4,4], dL_dcampos [3] (undefined otherwise). The backward is bitwise
//   deterministic (no atomics; fixed reduction order independent of the thread count).
//
// mark_visible_cpu returns bool [P]: view-space z > near plane (upstream markVisible).
#pragma once

#include <ATen/ATen.h>

#include <optional>
#include <vector>

namespace grp {

std::vector<at::Tensor> rasterize_forward_cpu(
    const at::Tensor& means3D, const at::Tensor& opacities, const std::optional<at::Tensor>& shs,
    const std::optional<at::Tensor>& colors_precomp, const std::optional<at::Tensor>& scales,
    const std::optional<at::Tensor>& rotations, const std::optional<at::Tensor>& cov3D_precomp,
    const at::Tensor& bg, const at::Tensor& viewmatrix, const at::Tensor& projmatrix,
    const at::Tensor& campos, int64_t image_height, int64_t image_width, double tanfovx,
    double tanfovy, double scale_modifier, int64_t sh_degree, bool prefiltered, bool antialiasing);

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
    const at::Tensor& grad_depth_acc, const at::Tensor& grad_alpha, bool compute_camera_grad);

at::Tensor mark_visible_cpu(const at::Tensor& means3D, const at::Tensor& viewmatrix,
                            const at::Tensor& projmatrix);

// CUDA twins (csrc/cuda/rasterize_cuda.cpp + kernels.cu; defined and bound only in a build with
// GRP_WITH_CUDA): same arguments, returns and saved-state meaning as the *_cpu functions, on CUDA
// tensors that all live on the device of means3D (work is queued on its current stream). The
// forward synchronises with the host once (to size the (tile, Gaussian) pair buffers); the backward
// does not, and is bitwise deterministic as well (no atomics; fixed reduction orders).
std::vector<at::Tensor> rasterize_forward_cuda(
    const at::Tensor& means3D, const at::Tensor& opacities, const std::optional<at::Tensor>& shs,
    const std::optional<at::Tensor>& colors_precomp, const std::optional<at::Tensor>& scales,
    const std::optional<at::Tensor>& rotations, const std::optional<at::Tensor>& cov3D_precomp,
    const at::Tensor& bg, const at::Tensor& viewmatrix, const at::Tensor& projmatrix,
    const at::Tensor& campos, int64_t image_height, int64_t image_width, double tanfovx,
    double tanfovy, double scale_modifier, int64_t sh_degree, bool prefiltered, bool antialiasing);

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
    const at::Tensor& grad_depth_acc, const at::Tensor& grad_alpha, bool compute_camera_grad);

at::Tensor mark_visible_cuda(const at::Tensor& means3D, const at::Tensor& viewmatrix,
                             const at::Tensor& projmatrix);

}  // namespace grp
