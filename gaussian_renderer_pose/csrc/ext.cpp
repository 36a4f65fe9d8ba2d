// gaussian_renderer_pose._C: the schemas of the grp ops (generated from the argument lists of
// ops.h; the CPU and CUDA kernels are registered by the backends), and a small Python module for
// what is not an op: whether CUDA kernels were built, and the constants the fake kernels of
// _ops.py need.
#include <torch/extension.h>
#include <torch/library.h>

#include "common/config.h"
#include "common/raster.h"
#include "ops.h"

TORCH_LIBRARY(grp, m) {
  // Where torch.compile finds the fake (shape-only) kernels of these ops.
  m.set_python_module("gaussian_renderer_pose._ops");
  m.def(grp::op_schema<grp::RasterInputs, grp::ForwardOutputs>(grp::kForwardOp).c_str());
  m.def(grp::op_schema<grp::BackwardInputs, grp::BackwardOutputs>(grp::kBackwardOp).c_str());
  m.def(grp::op_schema<grp::VisibilityInputs, grp::VisibilityOutputs>(grp::kMarkVisibleOp).c_str());
}

// The ops are not differentiable themselves (_native.py wraps them in an autograd.Function that
// calls rasterize_backward): their outputs never require grad.
TORCH_LIBRARY_IMPL(grp, Autograd, m) {
  m.impl(grp::kForwardOp, torch::CppFunction::makeFallthrough());
  m.impl(grp::kBackwardOp, torch::CppFunction::makeFallthrough());
  m.impl(grp::kMarkVisibleOp, torch::CppFunction::makeFallthrough());
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.doc() = "gaussian_renderer_pose native rasterizer: ops torch.ops.grp.* (see csrc/ops.h)";
  static_assert(grp::kBlockX == grp::kBlockY, "square tiles");
  m.attr("TILE_SIZE") = grp::kBlockX;
  m.attr("GEOM_STRIDE") = static_cast<int>(grp::kGStride);
#if defined(GRP_WITH_CUDA)
  m.attr("WITH_CUDA") = true;
#else
  m.attr("WITH_CUDA") = false;
#endif
}
