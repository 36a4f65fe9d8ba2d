"""A drop-in replacement for graphdeco-inria diff-gaussian-rasterization, with pose gradients.

The camera-pose gradients come through viewmatrix, projmatrix and campos.

Importing never compiles anything; the native extension is loaded lazily on first use.
See `gaussian_renderer_pose.rasterizer` and DESIGN.md for conventions and numerics.
"""
from ._dispatch import available_backends
from .camera import CameraMatrices, camera_matrices, projection_matrix
from .rasterizer import (
    GaussianRasterizationSettings,
    GaussianRasterizer,
    RasterOutput,
    rasterize_gaussians,
)

__all__ = [
    "GaussianRasterizationSettings",
    "GaussianRasterizer",
    "rasterize_gaussians",
    "RasterOutput",
    "camera_matrices",
    "CameraMatrices",
    "projection_matrix",
    "available_backends",
]
