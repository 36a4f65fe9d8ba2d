// Host-only (torch/ATen): checks of the input tensors and filling of RasterArgs (raster.h), shared
// by the CPU wrapper (../cpu/rasterize_cpu.cpp) and the CUDA wrapper (../cuda/rasterize_cuda.cpp).
// The backends differ only in the device check, passed in as a callable.
#pragma once

#include <ATen/ATen.h>

#include <cstdint>
#include <initializer_list>
#include <optional>
#include <vector>

#include "config.h"
#include "raster.h"

namespace grp {

inline bool present(const std::optional<at::Tensor>& t) { return t.has_value() && t->defined(); }

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

// Checks the forward's inputs with check(tensor, name, shape) and returns the RasterArgs pointing
// into them.
template <typename Check>
RasterArgs fill_raster_args(const Check& check, const at::Tensor& means3D,
                            const at::Tensor& opacities, const std::optional<at::Tensor>& shs,
                            const std::optional<at::Tensor>& colors_precomp,
                            const std::optional<at::Tensor>& scales,
                            const std::optional<at::Tensor>& rotations,
                            const std::optional<at::Tensor>& cov3D_precomp, const at::Tensor& bg,
                            const at::Tensor& viewmatrix, const at::Tensor& projmatrix,
                            const at::Tensor& campos, int64_t H, int64_t W, double tanfovx,
                            double tanfovy, double scale_modifier, int64_t sh_degree,
                            bool antialiasing) {
  check(means3D, "means3D", {-1, 3});
  RasterArgs a;
  a.P = means3D.size(0);
  const int64_t P = a.P;
  check(opacities, "opacities", {P, 1});
  check(bg, "bg", {3});
  check(viewmatrix, "viewmatrix", {4, 4});
  check(projmatrix, "projmatrix", {4, 4});
  check(campos, "campos", {3});
  TORCH_CHECK(H > 0 && W > 0 && H < (1 << 20) && W < (1 << 20), "image size must be positive, got ",
              H, "x", W);
  TORCH_CHECK(sh_degree >= 0 && sh_degree <= 3, "sh_degree must be in 0..3, got ", sh_degree);
  TORCH_CHECK(tanfovx > 0 && tanfovy > 0, "tanfovx/tanfovy must be positive");
  const bool has_colors = present(colors_precomp);
  TORCH_CHECK(has_colors || present(shs), "either shs or colors_precomp must be given");
  if (has_colors) {
    check(*colors_precomp, "colors_precomp", {P, 3});
    a.colors = colors_precomp->data_ptr<float>();
  } else {
    check(*shs, "shs", {P, -1, 3});
    a.M = shs->size(1);
    TORCH_CHECK(a.M >= (sh_degree + 1) * (sh_degree + 1), "shs has ", a.M,
                " coefficients, sh_degree ", sh_degree, " needs ", (sh_degree + 1) * (sh_degree + 1));
    a.shs = shs->data_ptr<float>();
  }
  if (present(cov3D_precomp)) {
    check(*cov3D_precomp, "cov3D_precomp", {P, 6});
    a.cov3d = cov3D_precomp->data_ptr<float>();
  } else {
    TORCH_CHECK(present(scales) && present(rotations),
                "either cov3D_precomp or scales and rotations must be given");
    check(*scales, "scales", {P, 3});
    check(*rotations, "rotations", {P, 4});
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

// Checks of the backward's output gradients and of the saved forward state shared by both
// backends: check(t, name, shape) for the float tensors, check_state(t, name, dtype) for the
// integer ones. The binning tensor's size is checked by the caller (the CPU reads offsets[P], the
// CUDA backend does not synchronise).
template <typename Check, typename CheckState>
void check_backward_inputs(const Check& check, const CheckState& check_state, const RasterArgs& a,
                           const at::Tensor& radii, const at::Tensor& geom,
                           const at::Tensor& binning, const at::Tensor& tile_ranges,
                           const at::Tensor& offsets, const at::Tensor& final_T,
                           const at::Tensor& last_contrib, const at::Tensor& grad_color,
                           const at::Tensor& grad_invdepth, const at::Tensor& grad_depth_acc,
                           const at::Tensor& grad_alpha) {
  const int64_t P = a.P;
  const int64_t num_tiles = (int64_t)a.grid_x * a.grid_y;
  check(grad_color, "grad_color", {3, a.H, a.W});
  check(grad_invdepth, "grad_invdepth", {1, a.H, a.W});
  check(grad_depth_acc, "grad_depth_acc", {1, a.H, a.W});
  check(grad_alpha, "grad_alpha", {1, a.H, a.W});
  check(geom, "geom", {P, kGStride});
  check(final_T, "final_T", {a.H, a.W});
  check_state(radii, "radii", at::kInt);
  check_state(binning, "binning", at::kInt);
  check_state(tile_ranges, "tile_ranges", at::kInt);
  check_state(offsets, "offsets", at::kLong);
  check_state(last_contrib, "last_contrib", at::kInt);
  TORCH_CHECK(radii.numel() == P && offsets.numel() == P + 1 && tile_ranges.numel() == num_tiles + 1 &&
                  last_contrib.numel() == (int64_t)a.H * a.W,
              "saved forward state does not match the inputs");
}

// Outputs and saved state of the forward (ops.h), allocated uninitialised; binning and
// tile_ranges are sized by the binning step and filled in by the backend.
struct ForwardTensors {
  at::Tensor color, radii, invdepth, depth_acc, alpha, geom, binning, tile_ranges, offsets,
      final_T, last_contrib;

  explicit ForwardTensors(const RasterArgs& a, const at::TensorOptions& fopt) {
    const auto iopt = fopt.dtype(at::kInt);
    color = at::empty({3, a.H, a.W}, fopt);
    invdepth = at::empty({1, a.H, a.W}, fopt);
    depth_acc = at::empty({1, a.H, a.W}, fopt);
    alpha = at::empty({1, a.H, a.W}, fopt);
    final_T = at::empty({a.H, a.W}, fopt);
    last_contrib = at::empty({a.H, a.W}, iopt);
    radii = at::empty({a.P}, iopt);
    geom = at::empty({a.P, kGStride}, fopt);
    offsets = at::empty({a.P + 1}, fopt.dtype(at::kLong));
  }

  RenderOutputs render_outputs() {
    return {color.data_ptr<float>(),   invdepth.data_ptr<float>(), depth_acc.data_ptr<float>(),
            alpha.data_ptr<float>(),   final_T.data_ptr<float>(),  last_contrib.data_ptr<int32_t>()};
  }

  // The 11 tensors returned by rasterize_forward_* (ops.h order).
  std::vector<at::Tensor> list() const {
    return {color, radii, invdepth, depth_acc, alpha, geom, binning, tile_ranges, offsets, final_T,
            last_contrib};
  }
};

// Zero-filled per-Gaussian gradient tensors (undefined where the input is absent).
struct GradTensors {
  at::Tensor means3D, means2D, opac, shs, colors, scales, rots, cov3d;

  GaussianGrads ptrs() {
    auto ptr = [](at::Tensor& t) { return t.defined() ? t.data_ptr<float>() : nullptr; };
    return {ptr(means3D), ptr(means2D), ptr(opac), ptr(shs),
            ptr(colors),  ptr(scales),  ptr(rots), ptr(cov3d)};
  }
};

inline GradTensors zero_gaussian_grads(const RasterArgs& a, const at::TensorOptions& fopt) {
  const int64_t P = a.P;
  GradTensors g;
  g.means3D = at::zeros({P, 3}, fopt);
  g.means2D = at::zeros({P, 3}, fopt);
  g.opac = at::zeros({P, 1}, fopt);
  if (a.colors != nullptr) g.colors = at::zeros({P, 3}, fopt);
  else g.shs = at::zeros({P, a.M, 3}, fopt);
  if (a.cov3d != nullptr) {
    g.cov3d = at::zeros({P, 6}, fopt);
  } else {
    g.scales = at::zeros({P, 3}, fopt);
    g.rots = at::zeros({P, 4}, fopt);
  }
  return g;
}

}  // namespace grp
