// The native ops of gaussian_renderer_pose._C, registered with the dispatcher as
// grp::rasterize_forward, grp::rasterize_backward and grp::mark_visible. Their arguments and
// returns are stated once, as the lists below: ext.cpp turns them into the TORCH_LIBRARY schemas,
// and each backend receives them as the structs generated from the same lists
// (common/op_struct.h) in the kernels it registers with TORCH_LIBRARY_IMPL(grp, CPU | CUDA, m)
// (cpu/rasterize_cpu.cpp, cuda/rasterize_cuda.cpp). Python: _ops.py (torch.ops.grp, fake
// kernels), _native.py (the autograd.Function). To read a schema:
// print(torch.ops.grp.rasterize_forward.default._schema) after importing _ops.
//
// Forward numerics: docs/CONTRACTS.md "Forward numerics" (upstream diff-gaussian-rasterization,
// 2024 main with antialiasing). Gradients are exact derivatives of that forward, except where a
// clamp/threshold makes the forward piecewise constant (the gradient there is that of the branch
// taken), and the per-pixel transmittance of the backward is recovered back to front by
// T_i = T_{i+1} / (1 - alpha_i) as upstream (float32 rounding differs from a forward product).
//
// Tensors are float32 unless said otherwise, contiguous, all on the device of means3D (CPU or
// CUDA; the CUDA kernels queue work on its current stream). The forward synchronises with the host
// once on CUDA (to size the (tile, Gaussian) pair buffers); no backward does. Both backwards are
// bitwise deterministic (no atomics; fixed reduction orders independent of the thread count).
#pragma once

#include "common/op_struct.h"

namespace grp {

// Inputs of a rasterization: the forward's arguments, and the first arguments of the backward.
#define GRP_RASTER_INPUTS(X)                                                                \
  X(Tensor, means3D)           /* [P, 3] world-space means                               */ \
  X(Tensor, opacities)         /* [P, 1] activated opacities in [0, 1]                   */ \
  X(OptTensor, shs)            /* [P, M, 3] SH coefficients, M >= (sh_degree + 1)^2      */ \
                               /*        (with shs_rest: [P, 1, 3], the first only)      */ \
  X(OptTensor, colors_precomp) /* [P, 3] RGB used instead of SH when given               */ \
  X(OptTensor, scales)         /* [P, 3] activated scales (times scale_modifier)         */ \
  X(OptTensor, rotations)      /* [P, 4] quaternion (w, x, y, z), NOT normalised         */ \
  X(OptTensor, cov3D_precomp)  /* [P, 6] (xx, xy, xz, yy, yz, zz), instead of scales and  */ \
                               /*        rotations when given                            */ \
  X(Tensor, bg)                /* [3] background colour                                  */ \
  X(Tensor, viewmatrix)        /* [4, 4] w2c^T (3DGS world_view_transform), row-major    */ \
  X(Tensor, projmatrix)        /* [4, 4] (P w2c)^T (3DGS full_proj_transform), row-major */ \
  X(Tensor, campos)            /* [3] camera centre in world                             */ \
  X(Int, image_height)         /* H                                                      */ \
  X(Int, image_width)          /* W                                                      */ \
  X(Float, tanfovx)                                                                         \
  X(Float, tanfovy)                                                                         \
  X(Float, scale_modifier)                                                                  \
  X(Int, sh_degree)            /* 0..3                                                   */ \
  X(Bool, prefiltered)         /* accepted, no effect: culling is always done            */ \
  X(Bool, antialiasing)                                                                     \
  X(OptTensor, shs_rest)       /* [P, M - 1, 3] the SH coefficients after the first, or  */ \
                               /*        undefined (all of them in shs); last, as the    */ \
                               /*        backends' keyword argument                      */

// Output images of the forward.
#define GRP_RASTER_IMAGES(X)                                                                \
  X(Tensor, color)             /* [3, H, W] C = sum_i c_i a_i T_i + T_final bg           */ \
  X(Tensor, invdepth)          /* [1, H, W] sum_i a_i T_i / z_i                          */ \
  X(Tensor, depth_acc)         /* [1, H, W] sum_i a_i T_i z_i                            */ \
  X(Tensor, alpha)             /* [1, H, W] 1 - T_final                                  */

// What the forward returns after the images and the backward takes back (radii is also an output
// of the renderer; the rest is opaque).
#define GRP_SAVED_STATE(X)                                                                  \
  X(Tensor, radii)             /* [P] int32 screen radius in pixels, 0 when culled        */ \
  X(Tensor, geom)              /* [P, 16] per-Gaussian record (common/raster.h GeomField) */ \
  X(Tensor, binning)           /* [R, 2] int32 (gaussian id, slot id) per tile, in depth  */ \
                               /*        order; R = number of (tile, Gaussian) pairs      */ \
  X(Tensor, tile_ranges)       /* [tiles + 1] int32 start of each tile's list in binning  */ \
  X(Tensor, offsets)           /* [P + 1] int64 slot range of each Gaussian               */ \
  X(Tensor, final_T)           /* [H, W] transmittance after the last Gaussian            */ \
  X(Tensor, last_contrib)      /* [H, W] int32 index in the tile's list of the last       */ \
                               /*        contributor, -1 if none                          */

// Gradients of the loss w.r.t. the output images (shapes of GRP_RASTER_IMAGES).
#define GRP_IMAGE_GRADS(X)                                                                  \
  X(Tensor, grad_color)                                                                     \
  X(Tensor, grad_invdepth)                                                                  \
  X(Tensor, grad_depth_acc)                                                                 \
  X(Tensor, grad_alpha)

#define GRP_BACKWARD_INPUTS(X)                                                              \
  GRP_RASTER_INPUTS(X)                                                                      \
  GRP_SAVED_STATE(X)                                                                        \
  GRP_IMAGE_GRADS(X)                                                                        \
  X(Bool, compute_camera_grad)    /* false: no camera work, camera gradients None         */ \
  X(Bool, compute_gaussian_grads) /* false: none of the work that only the Gaussians'      */ \
                                  /* gradients need (grad_means3D .. grad_cov3D_precomp    */ \
                                  /* None); grad_bg and the camera gradient are unchanged   */

// Gradients w.r.t. the inputs: None where the input is absent (of shs and colors_precomp only the
// one used; of cov3D_precomp and scales/rotations likewise), for the camera unless
// compute_camera_grad, and for the Gaussians (means3D .. cov3D_precomp) unless
// compute_gaussian_grads. grad_bg is always returned.
#define GRP_BACKWARD_OUTPUTS(X)                                                             \
  X(OptTensor, grad_means3D)                                                                \
  X(OptTensor, grad_means2D)   /* [P, 3] d/d NDC (x, y) of the centre, z = 0 (upstream)   */ \
  X(OptTensor, grad_opacities)                                                              \
  X(OptTensor, grad_shs)                                                                    \
  X(OptTensor, grad_colors_precomp)                                                         \
  X(OptTensor, grad_scales)                                                                 \
  X(OptTensor, grad_rotations)                                                              \
  X(OptTensor, grad_cov3D_precomp)                                                          \
  X(Tensor, grad_bg)                                                                        \
  X(OptTensor, grad_viewmatrix)                                                             \
  X(OptTensor, grad_projmatrix)                                                             \
  X(OptTensor, grad_campos)                                                                 \
  X(OptTensor, grad_shs_rest)

#define GRP_FORWARD_OUTPUTS(X) GRP_RASTER_IMAGES(X) GRP_SAVED_STATE(X)

// mark_visible: bool [P], view-space z > near plane (upstream markVisible).
#define GRP_VISIBILITY_INPUTS(X) X(Tensor, means3D) X(Tensor, viewmatrix) X(Tensor, projmatrix)
#define GRP_VISIBILITY_OUTPUTS(X) X(Tensor, visible)

GRP_OP_STRUCT(RasterInputs, GRP_RASTER_INPUTS);
GRP_OP_STRUCT(ForwardOutputs, GRP_FORWARD_OUTPUTS);
GRP_OP_STRUCT(BackwardInputs, GRP_BACKWARD_INPUTS);
GRP_OP_STRUCT(BackwardOutputs, GRP_BACKWARD_OUTPUTS);
GRP_OP_STRUCT(VisibilityInputs, GRP_VISIBILITY_INPUTS);
GRP_OP_STRUCT(VisibilityOutputs, GRP_VISIBILITY_OUTPUTS);

// Each backend defines, for its device,
//   ForwardOutputs rasterize_forward_<dev>(const RasterInputs&);
//   BackwardOutputs rasterize_backward_<dev>(const BackwardInputs&);
//   VisibilityOutputs mark_visible_<dev>(const VisibilityInputs&);
// and registers them under the op names below with boxed_kernel (common/op_struct.h).
constexpr const char* kForwardOp = "rasterize_forward";
constexpr const char* kBackwardOp = "rasterize_backward";
constexpr const char* kMarkVisibleOp = "mark_visible";

}  // namespace grp
