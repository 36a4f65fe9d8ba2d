// Python bindings of gaussian_renderer_pose._C (see ops.h for the arguments and shapes).
#include <torch/extension.h>

#include "ops.h"

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.doc() = "gaussian_renderer_pose native rasterizer (CPU; CUDA when built with GRP_WITH_CUDA)";
  m.def("forward", &grp::rasterize_forward_cpu,
        "rasterize_forward_cpu(means3D, opacities, shs, colors_precomp, scales, rotations, "
        "cov3D_precomp, bg, viewmatrix, projmatrix, campos, image_height, image_width, tanfovx, "
        "tanfovy, scale_modifier, sh_degree, prefiltered, antialiasing) -> list of 11 tensors",
        py::arg("means3D"), py::arg("opacities"), py::arg("shs"), py::arg("colors_precomp"),
        py::arg("scales"), py::arg("rotations"), py::arg("cov3D_precomp"), py::arg("bg"),
        py::arg("viewmatrix"), py::arg("projmatrix"), py::arg("campos"), py::arg("image_height"),
        py::arg("image_width"), py::arg("tanfovx"), py::arg("tanfovy"), py::arg("scale_modifier"),
        py::arg("sh_degree"), py::arg("prefiltered"), py::arg("antialiasing"),
        py::call_guard<py::gil_scoped_release>());
  m.def("backward", &grp::rasterize_backward_cpu,
        "rasterize_backward_cpu(<forward inputs without prefiltered>, radii, geom, binning, "
        "tile_ranges, offsets, final_T, last_contrib, grad_color, grad_invdepth, grad_depth_acc, "
        "grad_alpha, compute_camera_grad) -> list of 12 tensors (None where not applicable)",
        py::call_guard<py::gil_scoped_release>());
  m.def("mark_visible", &grp::mark_visible_cpu, "mark_visible(means3D, viewmatrix, projmatrix) -> bool[P]",
        py::arg("means3D"), py::arg("viewmatrix"), py::arg("projmatrix"),
        py::call_guard<py::gil_scoped_release>());
#if defined(GRP_WITH_CUDA)
  // CUDA twins: same arguments and returns, CUDA tensors (_native.py routes by device).
  m.def("forward_cuda", &grp::rasterize_forward_cuda,
        "rasterize_forward_cuda(<as forward>) -> list of 11 CUDA tensors",
        py::arg("means3D"), py::arg("opacities"), py::arg("shs"), py::arg("colors_precomp"),
        py::arg("scales"), py::arg("rotations"), py::arg("cov3D_precomp"), py::arg("bg"),
        py::arg("viewmatrix"), py::arg("projmatrix"), py::arg("campos"), py::arg("image_height"),
        py::arg("image_width"), py::arg("tanfovx"), py::arg("tanfovy"), py::arg("scale_modifier"),
        py::arg("sh_degree"), py::arg("prefiltered"), py::arg("antialiasing"),
        py::call_guard<py::gil_scoped_release>());
  m.def("backward_cuda", &grp::rasterize_backward_cuda,
        "rasterize_backward_cuda(<as backward>) -> list of 12 CUDA tensors (None where not applicable)",
        py::call_guard<py::gil_scoped_release>());
  m.def("mark_visible_cuda", &grp::mark_visible_cuda,
        "mark_visible_cuda(means3D, viewmatrix, projmatrix) -> bool[P] (CUDA)", py::arg("means3D"),
        py::arg("viewmatrix"), py::arg("projmatrix"), py::call_guard<py::gil_scoped_release>());
  m.attr("WITH_CUDA") = true;
#else
  m.attr("WITH_CUDA") = false;
#endif
}
