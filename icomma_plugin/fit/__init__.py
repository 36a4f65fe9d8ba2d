"""Fit a 3DGS model on CPU with gaussian_renderer_pose (upstream 3DGS training, CPU schedule).

- `FitConfig`: every constant (learning rates, schedule, densification, budget).
- `Trainer` / `FitView`: the optimisation loop on in-memory posed images.
- `GaussianTrainState`: parameters + Adam + densification (clone / split / prune / opacity reset).
- `fit_scene`: dataset folder -> model folder (cfg_args, cameras.json, input.ply, point_cloud/...,
  metrics.json).
"""
from .config import FitConfig
from .init import mean_knn_sq_dist, model_from_points, random_cube_points
from .losses import photometric_loss, psnr, ssim
from .scene import ModelFolderExistsError, SceneFitResult, fit_scene, resolution_scale
from .state import GaussianTrainState, expon_lr
from .trainer import FitResult, FitView, Trainer, render_state

__all__ = [
    "FitConfig", "FitResult", "FitView", "GaussianTrainState", "ModelFolderExistsError",
    "SceneFitResult", "Trainer", "expon_lr", "fit_scene", "mean_knn_sq_dist", "model_from_points",
    "photometric_loss", "psnr", "random_cube_points", "render_state", "resolution_scale", "ssim",
]
