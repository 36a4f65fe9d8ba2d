"""Fit a 3DGS model on CPU with gaussian_renderer_pose (upstream 3DGS training, CPU schedule).

- `FitConfig`: every constant (learning rates, schedule, densification, budget).
- `Trainer` / `FitView`: the optimisation loop on in-memory posed images.
- `GaussianTrainState`: parameters + Adam + densification (clone / split / prune / opacity reset).
- `fit_scene`: dataset folder -> model folder (cfg_args, cameras.json, input.ply, point_cloud/...,
  metrics.json); `evaluate_model_folder`: train / test PSNR of a model folder on its dataset.
- `initial_points`: the start: the capture's cloud, else `plane_sweep_points`, plus
  `far_field_points` (a shell beyond the cameras) for photographed captures.
- `ExposureState`: per-photo affine colour transforms (upstream `--train_test_exp`);
  `NeighbourExposure`: a new view's, predicted from the nearest training photos'.
- `evaluate_views` / `write_grid`: PSNR with and without exposure, photos beside renders.
- `distill`: one model fitted to another's renders (a split model back to its parent's image).
Losses and PSNR count only valid pixels (`FitView.valid`, from `View.load_image`). The recipe
and its measurements: docs/FITTING.md.
"""
from .config import FitConfig
from .distillation import DISTILL_CONFIG, distill
from .init import mean_knn_sq_dist, model_from_points, plane_sweep_points, random_cube_points
from .losses import photometric_loss, psnr, ssim
from .evaluate import evaluate_model_folder, evaluate_views, write_grid
from .exposure import ExposureState, NeighbourExposure, fit_affine_colour
from .init import InitCloud, far_field_points, initial_points
from .scene import ModelFolderExistsError, SceneFitResult, fit_scene
from .views import resolution_scale
from .state import GaussianTrainState, expon_lr
from .trainer import FitResult, FitView, Trainer, render_state

__all__ = [
    "DISTILL_CONFIG", "ExposureState", "FitConfig", "FitResult", "FitView", "GaussianTrainState",
    "InitCloud",
    "ModelFolderExistsError", "NeighbourExposure", "SceneFitResult", "Trainer",
    "evaluate_model_folder",
    "distill", "evaluate_views", "expon_lr", "far_field_points", "fit_affine_colour", "fit_scene",
    "initial_points", "mean_knn_sq_dist", "model_from_points", "photometric_loss",
    "plane_sweep_points", "psnr", "random_cube_points", "render_state", "resolution_scale",
    "ssim", "write_grid",
]
