// Host-only (torch/ATen): checks of the op arguments (../ops.h structs), filling of RasterArgs
// (raster.h) and allocation of the op outputs, shared by the CPU wrapper (../cpu/rasterize_cpu.cpp)
// and the CUDA wrapper (../cuda/rasterize_cuda.cpp). The backends differ only in the device check,
// passed in as a callable.
#pragma once

#include <ATen/ATen.h>

#include <cstdint>
#include <initializer_list>

#include "../ops.h"
#include "config.h"
#include "raster.h"

namespace grp {

// float32, contiguous, given shape (-1 = any); device_check(t, name) checks the device.
template <typename DeviceCheck>
void check_float_tensor(const at::Tensor& t, const char* name, std::initializer_list<int64_t> shape,
                        const DeviceCheck& device_check) {
  TORCH_CHECK(t.defined(), name, " must be a tensor");
  device_check(t, name);
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

// Checks the rasterization inputs (the RasterInputs fields of ../ops.h, which BackwardInputs
// shares) with check(tensor, name, shape) and returns the RasterArgs pointing into them.
template <typename Check, typename Inputs>
RasterArgs fill_raster_args(const Check& check, const Inputs& in) {
  const at::Tensor& means3D = in.means3D;
  const int64_t H = in.image_height, W = in.image_width, sh_degree = in.sh_degree;
  check(means3D, "means3D", {-1, 3});
  RasterArgs a;
  a.P = means3D.size(0);
  const int64_t P = a.P;
  check(in.opacities, "opacities", {P, 1});
  check(in.bg, "bg", {3});
  check(in.viewmatrix, "viewmatrix", {4, 4});
  check(in.projmatrix, "projmatrix", {4, 4});
  check(in.campos, "campos", {3});
  TORCH_CHECK(H > 0 && W > 0 && H < (1 << 20) && W < (1 << 20), "image size must be positive, got ",
              H, "x", W);
  TORCH_CHECK(sh_degree >= 0 && sh_degree <= 3, "sh_degree must be in 0..3, got ", sh_degree);
  TORCH_CHECK(in.tanfovx > 0 && in.tanfovy > 0, "tanfovx/tanfovy must be positive");
  const bool has_colors = in.colors_precomp.defined();
  TORCH_CHECK(has_colors || in.shs.defined(), "either shs or colors_precomp must be given");
  if (has_colors) {
    check(in.colors_precomp, "colors_precomp", {P, 3});
    a.colors = in.colors_precomp.template data_ptr<float>();
  } else {
    if (in.shs_rest.defined()) {  // the first coefficient in shs, the others in shs_rest
      check(in.shs, "shs", {P, 1, 3});
      check(in.shs_rest, "shs_rest", {P, -1, 3});
      a.M = 1 + in.shs_rest.size(1);
      a.shs_rest = in.shs_rest.template data_ptr<float>();
    } else {
      check(in.shs, "shs", {P, -1, 3});
      a.M = in.shs.size(1);
    }
    TORCH_CHECK(a.M >= (sh_degree + 1) * (sh_degree + 1), "shs has ", a.M,
                " coefficients, sh_degree ", sh_degree, " needs ", (sh_degree + 1) * (sh_degree + 1));
    a.shs = in.shs.template data_ptr<float>();
  }
  if (in.cov3D_precomp.defined()) {
    check(in.cov3D_precomp, "cov3D_precomp", {P, 6});
    a.cov3d = in.cov3D_precomp.template data_ptr<float>();
  } else {
    TORCH_CHECK(in.scales.defined() && in.rotations.defined(),
                "either cov3D_precomp or scales and rotations must be given");
    check(in.scales, "scales", {P, 3});
    check(in.rotations, "rotations", {P, 4});
    a.scales = in.scales.template data_ptr<float>();
    a.rots = in.rotations.template data_ptr<float>();
  }
  a.H = (int)H;
  a.W = (int)W;
  a.grid_x = (a.W + kBlockX - 1) / kBlockX;
  a.grid_y = (a.H + kBlockY - 1) / kBlockY;
  a.tanfovx = (float)in.tanfovx;
  a.tanfovy = (float)in.tanfovy;
  a.focal_x = a.W / (2.0f * a.tanfovx);
  a.focal_y = a.H / (2.0f * a.tanfovy);
  a.scale_modifier = (float)in.scale_modifier;
  a.sh_degree = (int)sh_degree;
  a.antialiasing = in.antialiasing;
  a.means = means3D.template data_ptr<float>();
  a.opac = in.opacities.template data_ptr<float>();
  a.bg = in.bg.template data_ptr<float>();
  a.viewmatrix = in.viewmatrix.template data_ptr<float>();
  a.projmatrix = in.projmatrix.template data_ptr<float>();
  a.campos = in.campos.template data_ptr<float>();
  return a;
}

// Checks of the backward's output gradients and of the saved forward state shared by both
// backends: check(t, name, shape) for the float tensors, check_state(t, name, dtype) for the
// integer ones. The binning tensor's size is checked by the caller (the CPU reads offsets[P], the
// CUDA backend does not synchronise).
template <typename Check, typename CheckState>
void check_backward_inputs(const Check& check, const CheckState& check_state, const RasterArgs& a,
                           const BackwardInputs& b) {
  const int64_t P = a.P;
  const int64_t num_tiles = (int64_t)a.grid_x * a.grid_y;
  check(b.grad_color, "grad_color", {3, a.H, a.W});
  check(b.grad_invdepth, "grad_invdepth", {1, a.H, a.W});
  check(b.grad_depth_acc, "grad_depth_acc", {1, a.H, a.W});
  check(b.grad_alpha, "grad_alpha", {1, a.H, a.W});
  check(b.geom, "geom", {P, kGStride});
  check(b.final_T, "final_T", {a.H, a.W});
  check_state(b.radii, "radii", at::kInt);
  check_state(b.binning, "binning", at::kInt);
  check_state(b.tile_ranges, "tile_ranges", at::kInt);
  check_state(b.offsets, "offsets", at::kLong);
  check_state(b.last_contrib, "last_contrib", at::kInt);
  TORCH_CHECK(b.radii.numel() == P && b.offsets.numel() == P + 1 &&
                  b.tile_ranges.numel() == num_tiles + 1 &&
                  b.last_contrib.numel() == (int64_t)a.H * a.W,
              "saved forward state does not match the inputs");
}

// The forward's outputs and saved state (ops.h), allocated uninitialised by
// empty(sizes, options); binning and tile_ranges are sized by the binning step and filled in by
// the backend.
template <typename Empty>
ForwardOutputs allocate_forward_outputs(const RasterArgs& a, const at::TensorOptions& fopt,
                                        const Empty& empty) {
  const auto iopt = fopt.dtype(at::kInt);
  ForwardOutputs f;
  f.color = empty({3, a.H, a.W}, fopt);
  f.invdepth = empty({1, a.H, a.W}, fopt);
  f.depth_acc = empty({1, a.H, a.W}, fopt);
  f.alpha = empty({1, a.H, a.W}, fopt);
  f.final_T = empty({a.H, a.W}, fopt);
  f.last_contrib = empty({a.H, a.W}, iopt);
  f.radii = empty({a.P}, iopt);
  f.geom = empty({a.P, kGStride}, fopt);
  f.offsets = empty({a.P + 1}, fopt.dtype(at::kLong));
  return f;
}

inline ForwardOutputs allocate_forward_outputs(const RasterArgs& a, const at::TensorOptions& fopt) {
  return allocate_forward_outputs(
      a, fopt, [](at::IntArrayRef sizes, const at::TensorOptions& o) { return at::empty(sizes, o); });
}

inline RenderOutputs render_outputs(ForwardOutputs& f) {
  return {f.color.data_ptr<float>(), f.invdepth.data_ptr<float>(), f.depth_acc.data_ptr<float>(),
          f.alpha.data_ptr<float>(), f.final_T.data_ptr<float>(),
          f.last_contrib.data_ptr<int32_t>()};
}

// The backward's per-Gaussian gradients, allocated by make(sizes, options) (undefined where the
// input is absent, and all undefined unless gaussian_grads: compute_gaussian_grads of ../ops.h);
// grad_bg and the camera gradients are left to the backend.
template <typename Make>
BackwardOutputs allocate_gaussian_grads(const RasterArgs& a, bool gaussian_grads,
                                        const at::TensorOptions& fopt, const Make& make) {
  const int64_t P = a.P;
  BackwardOutputs g;
  if (!gaussian_grads) return g;
  g.grad_means3D = make({P, 3}, fopt);
  g.grad_means2D = make({P, 3}, fopt);
  g.grad_opacities = make({P, 1}, fopt);
  if (a.colors != nullptr) {
    g.grad_colors_precomp = make({P, 3}, fopt);
  } else if (a.shs_rest != nullptr) {
    g.grad_shs = make({P, 1, 3}, fopt);
    g.grad_shs_rest = make({P, a.M - 1, 3}, fopt);
  } else {
    g.grad_shs = make({P, a.M, 3}, fopt);
  }
  if (a.cov3d != nullptr) {
    g.grad_cov3D_precomp = make({P, 6}, fopt);
  } else {
    g.grad_scales = make({P, 3}, fopt);
    g.grad_rotations = make({P, 4}, fopt);
  }
  return g;
}

// allocate_gaussian_grads with zero-filled tensors.
inline BackwardOutputs zero_gaussian_grads(const RasterArgs& a, bool gaussian_grads,
                                           const at::TensorOptions& fopt) {
  return allocate_gaussian_grads(
      a, gaussian_grads, fopt,
      [](at::IntArrayRef sizes, const at::TensorOptions& o) { return at::zeros(sizes, o); });
}

inline GaussianGrads gaussian_grad_ptrs(BackwardOutputs& g) {
  auto ptr = [](at::Tensor& t) { return t.defined() ? t.data_ptr<float>() : nullptr; };
  return {ptr(g.grad_means3D),   ptr(g.grad_means2D),        ptr(g.grad_opacities),
          ptr(g.grad_shs),       ptr(g.grad_colors_precomp), ptr(g.grad_scales),
          ptr(g.grad_rotations), ptr(g.grad_cov3D_precomp), ptr(g.grad_shs_rest)};
}

}  // namespace grp
