"""Fit a 3DGS model on CPU with gaussian_renderer_pose (upstream 3DGS training, CPU schedule).

- `FitConfig`: every constant (learning rates, schedule, densification, budget).
- `Trainer` / `FitView`: the optimisation loop on in-memory posed images.
- `GaussianTrainState`: parameters + Adam + densification (clone / split / prune / opacity reset).
- `fit_scene`: dataset folder -> model folder (cfg_args, cameras.json, input.ply, point_cloud/...,
  metrics.json); `evaluate_model_folder`: train / test PSNR of a model folder on its dataset.
- `plane_sweep_points`: initial points of a posed capture without a point cloud.
Losses and PSNR count only valid pixels (`FitView.valid`, from `View.load_image`). The recipe
and its measurements: docs/FITTING.md.
"""
from .config import FitConfig
from .init import mean_knn_sq_dist, model_from_points, plane_sweep_points, random_cube_points
from .losses import photometric_loss, psnr, ssim
from .scene import (ModelFolderExistsError, SceneFitResult, evaluate_model_folder, fit_scene,
                    resolution_scale)
from .state import GaussianTrainState, expon_lr
from .trainer import FitResult, FitView, Trainer, render_state

__all__ = [
    "FitConfig", "FitResult", "FitView", "GaussianTrainState", "ModelFolderExistsError",
    "SceneFitResult", "Trainer", "evaluate_model_folder", "expon_lr", "fit_scene",
    "mean_knn_sq_dist", "model_from_points", "photometric_loss", "plane_sweep_points", "psnr",
    "random_cube_points", "render_state", "resolution_scale", "ssim",
]
