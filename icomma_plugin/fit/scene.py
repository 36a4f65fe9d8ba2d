"""Fit a 3DGS model to a dataset folder and write the upstream model-folder layout.

    result = fit_scene("../shared/data/nerf_synthetic/lego_400", "out/lego_200",
                       FitConfig.scaled_schedule(5000), resolution=2)

Writes (icomma_plugin.io.model_folder.write_model_folder): cfg_args, cameras.json (test then
train, original sizes), input.ply (the init cloud), point_cloud/iteration_N/point_cloud.ply at
the configured save iterations and the last one, exposure.json when per-photo exposures were
fitted (upstream's file: {image name: 3x4}; renders never use it), plus metrics.json (train and
test PSNR with and without exposure, iterations, Gaussian count, seconds, resolution, init).
The folder is built in a hidden staging folder beside the target and renamed into place at the
end, so a model folder is never half-written, and an existing one is replaced only with
`overwrite=True`.

Resolution (upstream `-r`): -1 (auto: native size, widths above 1600 scaled to 1600), 1, 2, 4, 8
(divide the size), any other positive int (target width). `downscale` (a positive float factor)
is the alternative.
"""
from __future__ import annotations

import logging
import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Union

import numpy as np
import torch

from ..io.atomic import write_json_atomic
from .config import FitConfig
from .evaluate import evaluate_views, neighbour_exposure
from .init import (InitCloud, init_scale_limits, initial_points, is_object_render,
                   model_from_points)
from .trainer import FitResult, ProgressFn, Trainer, render_state
from .views import cfg_resolution_value, resolution_scale, tiny_resolution_message, views_to_fit

log = logging.getLogger(__name__)

PathLike = Union[str, os.PathLike]


class ModelFolderExistsError(ValueError, FileExistsError):
    """The target model folder exists and overwriting was not asked for."""


@dataclass
class SceneFitResult:
    """What `fit_scene` returns: the model folder written, the fit and its metrics.json."""

    model_path: Path
    fit: FitResult
    metrics: Dict


def _subset(n: int, k: int) -> List[int]:
    """k evenly spaced indices of range(n) (all when k == 0 or k >= n)."""
    if k <= 0 or k >= n:
        return list(range(n))
    return sorted(set(int(round(x)) for x in np.linspace(0, n - 1, k)))


def camera_entries(train, test) -> list:
    """cameras.json entries: test cameras first, then train (upstream), original sizes."""
    from ..io.cameras_json import CameraEntry

    entries = []
    for v in list(test) + list(train):
        i = v.intrinsics
        entries.append(
            CameraEntry(
                id=len(entries),
                img_name=v.name,
                width=i.width,
                height=i.height,
                c2w=np.asarray(v.c2w, dtype=np.float64),
                fx=float(i.fx),
                fy=float(i.fy),
            )
        )
    return entries


def _staging_path(final: Path) -> Path:
    return final.parent / f".{final.name}.partial"


def _check_source(source_path: PathLike) -> Path:
    """The dataset folder, resolved; ValueError naming the argument when it is not a folder."""
    if source_path is None or str(source_path) == "":
        raise ValueError("source_path must be a dataset folder, got an empty value")
    src = Path(source_path).expanduser().resolve()
    if not src.is_dir():
        raise ValueError(
            f"source_path must be an existing dataset folder, got {str(source_path)!r} "
            f"({'not a folder' if src.exists() else 'does not exist'})"
        )
    return src


def _check_paths(source_path: PathLike, model_path: PathLike, overwrite: bool):
    """(dataset folder, model folder) resolved; ValueError naming the bad argument."""
    src = _check_source(source_path)
    if model_path is None or str(model_path) == "":
        raise ValueError("model_path must be a folder path, got an empty value")
    final = Path(model_path).expanduser().resolve()
    if final.exists() and not overwrite:
        raise ModelFolderExistsError(
            f"model_path {str(final)!r} already exists; pass overwrite=True "
            "(--overwrite) to replace it"
        )
    return src, final


def _read_scene(src: Path, white_background: Optional[bool], dataset_kwargs: Optional[dict],
                principal_point: str = "dataset"):
    """The dataset, white for Blender scenes unless told (the NeRF convention)."""
    from ..io.datasets import detect_dataset_kind, read_dataset

    kind = detect_dataset_kind(src)
    if white_background is None:
        white_background = kind == "blender"
    kwargs = dict(dataset_kwargs or {})
    kwargs.setdefault("white_background", bool(white_background))
    scene = read_dataset(src, kind=kind, principal_point=principal_point, **kwargs)
    if not scene.train:
        raise ValueError(f"source_path {str(src)!r}: the dataset has no training views")
    return scene


@dataclass
class CaptureInfo:
    """What the recipe of a fit depends on (`describe_capture`)."""

    train_views: int
    width: int
    height: int
    object_render: bool


def describe_capture(source_path: PathLike, resolution: Optional[int] = -1,
                     downscale: Optional[float] = None,
                     white_background: Optional[bool] = None) -> CaptureInfo:
    """Training-view count, fitted image size and kind of a dataset, for the recipe.

    Reads the dataset's files (not its images) as `fit_scene` does; the result feeds
    `FitConfig.for_capture`.
    """
    scene = _read_scene(_check_source(source_path), white_background, None)
    intr = scene.train[0].intrinsics
    small = intr.scaled(resolution_scale(resolution, downscale, intr.width))
    return CaptureInfo(len(scene.train), small.width, small.height, is_object_render(scene))


def fit_scene(
    source_path: PathLike,
    model_path: PathLike,
    config: Optional[FitConfig] = None,
    *,
    resolution: Optional[int] = -1,
    downscale: Optional[float] = None,
    white_background: Optional[bool] = None,
    overwrite: bool = False,
    progress: Optional[ProgressFn] = None,
    progress_every: int = 10,
    device: Optional[Union[str, torch.device]] = None,
    dataset_kwargs: Optional[dict] = None,
) -> SceneFitResult:
    """Read the dataset at `source_path`, fit, and write the model folder `model_path`.

    white_background: None picks white for Blender/NeRF-synthetic scenes (the NeRF convention),
    black otherwise. The initial points are `init.initial_points`'; per-photo exposures are
    fitted when `config.exposure` says so (None: for photographed captures).
    """
    from ..checks import check_backend_here
    from ..io.model_folder import write_model_folder

    t_total = time.perf_counter()
    config = config or FitConfig()
    check_backend_here(config.backend, "FitConfig.backend")
    if torch.device(device if device is not None else "cpu").type == "cuda":
        check_backend_here("cuda", "device")
    src, final = _check_paths(source_path, model_path, overwrite)
    scene = _read_scene(src, white_background, dataset_kwargs, config.principal_point)
    bg = (1.0, 1.0, 1.0) if scene.white_background else (0.0, 0.0, 0.0)
    dev = torch.device(device) if device is not None else torch.device("cpu")
    train, test = _load_views(scene, config, resolution, downscale, bg, dev)
    w0 = scene.train[0].intrinsics.width
    t_init = time.perf_counter()
    cloud, init = _initial_model(scene, train, config, dev)
    seconds_init = time.perf_counter() - t_init
    extent = scene.scene_radius()
    log.info("init: %d points (%s, %d far field, %.1f s); scene extent %.3f", init.num_gaussians,
             cloud.source, cloud.far_points, seconds_init, extent)

    cfg = {
        "data_device": "cpu",
        "eval": True,
        "images": "images",
        "model_path": str(final),
        "principal_point": config.principal_point,
        "resolution": cfg_resolution_value(resolution, downscale, w0),
        "sh_degree": int(config.sh_degree),
        "source_path": str(src),
        "white_background": bool(scene.white_background),
    }
    cameras = camera_entries(scene.train, scene.test)
    staging = _staging_path(final)
    if staging.exists():
        shutil.rmtree(staging)

    def on_save(iteration, model):
        write_model_folder(staging, model, cfg, cameras, iteration,
                           input_points=(cloud.xyz, cloud.rgb))
        log.info("saved iteration %d (%d Gaussians)", iteration, model.num_gaussians)

    exposure = config.exposure if config.exposure is not None else not is_object_render(scene)
    trainer = Trainer(init, train, extent, config, background=bg, test=test, progress=progress,
                      on_save=on_save, progress_every=progress_every,
                      scene_centre=scene.scene_center(), exposure=exposure)
    result = trainer.run()
    metrics = _fit_metrics(trainer, result, train, test, cloud)
    metrics.update({
        "test_views_total": len(scene.test),
        "white_background": bool(scene.white_background),
        "scene_extent": extent,
        "backend": _backend_name(config.backend, dev),
        "seconds_init": round(seconds_init, 2),
        "config": config.to_dict(),
    })
    if trainer.exposure is not None:
        write_json_atomic(staging / "exposure.json",
                          trainer.exposure.to_json([v.name for v in train]))
    metrics["seconds_total"] = round(time.perf_counter() - t_total, 2)
    write_json_atomic(staging / "metrics.json", metrics)
    _publish(staging, final, overwrite)
    log.info("model folder written: %s", final)
    return SceneFitResult(model_path=final, fit=result, metrics=metrics)


def _load_views(scene, config: FitConfig, resolution, downscale, bg, dev):
    """(train, test) FitViews at the requested resolution; the resolution is checked first."""
    resolution_scale(resolution, downscale, scene.train[0].intrinsics.width)
    tiny = tiny_resolution_message(resolution, downscale, scene.train[0].intrinsics)
    if tiny:
        log.warning("%s", tiny)
    log.info("loading %d train views of %s", len(scene.train), scene.root)
    train = views_to_fit(
        scene.train, resolution, downscale, bg, device=dev, keep_alpha=config.random_background
    )
    test_idx = _subset(len(scene.test), config.eval_views)
    test = views_to_fit([scene.test[i] for i in test_idx], resolution, downscale, bg, device=dev)
    log.info("images at %dx%d; %d test views for evaluation", train[0].intrinsics.width,
             train[0].intrinsics.height, len(test))
    return train, test


def _initial_model(scene, train, config: FitConfig, dev):
    """(InitCloud, GaussianModel) of the start (`init.initial_points`, bounded scales)."""
    cloud = initial_points(scene, train, config)
    max_scale = None
    if config.init_max_pixels is not None:
        centres = np.stack([v.campos for v in scene.train])
        fx = float(np.mean([v.intrinsics.fx for v in train]))
        max_scale = init_scale_limits(cloud.xyz, centres, config.init_max_pixels / fx)
    init = model_from_points(cloud.xyz, cloud.rgb, config.sh_degree, config.init_opacity,
                             device=dev, max_scale=max_scale)
    return cloud, init


def _fit_metrics(trainer: Trainer, result: FitResult, train, test, cloud: InitCloud) -> Dict:
    """metrics.json's measurements: PSNRs (evaluate.py's figures), counts, seconds, init."""
    def render(v):
        return render_state(trainer.state, v, trainer.background, trainer.config.backend).color

    with torch.no_grad():
        exposures = None
        if trainer.exposure is not None:
            exposures = {v.name: trainer.exposure.matrix(i) for i, v in enumerate(train)}
        tr = evaluate_views(render, train, exposures)["mean"]
        te = evaluate_views(render, test, predict_exposure=neighbour_exposure(train, exposures)
                            )["mean"] if test else {}
    log.info("final: train PSNR %.2f dB (%s with exposure) over %d views", tr["full"],
             f"{tr['exposure']:.2f}" if "exposure" in tr else "-", len(train))
    if te:
        log.info("final: test PSNR %.2f dB%s; right halves %.2f dB, %.2f dB with the exposure of "
                 "the left half", te["full"],
                 f" ({te['neighbour_exposure']:.2f} with the nearest photos' exposure)"
                 if "neighbour_exposure" in te else "", te["right"], te["right_exposure"])
    return {
        "test_psnr": result.test_psnr,
        "test_psnr_right_half": te.get("right"),
        "test_psnr_right_half_exposure": te.get("right_exposure"),
        "test_psnr_neighbour_exposure": te.get("neighbour_exposure"),
        "train_psnr": tr["full"],
        "train_psnr_exposure": tr.get("exposure"),
        "train_views": len(train),
        "test_views": result.test_views,
        "iterations": result.iterations,
        "num_gaussians": result.num_gaussians,
        "seconds_train": round(result.seconds_train, 2),
        "seconds_cpu": None if result.seconds_cpu is None else round(result.seconds_cpu, 2),
        "seconds_per_step": round(result.seconds_train / max(result.iterations, 1), 4),
        "removed_non_finite": result.removed_non_finite,
        "replan": result.replan,
        "seconds_total": None,
        "resolution": [train[0].intrinsics.width, train[0].intrinsics.height],
        "init": {"source": cloud.source, "points": int(len(cloud.xyz)),
                 "far_field_points": cloud.far_points, "far_field_radius": cloud.radius},
        "exposure": trainer.exposure is not None,
        "threads": torch.get_num_threads(),
        "timings": {k: round(v, 2) for k, v in result.timings.items()},
        "history": result.history,
    }


def _backend_name(backend: str, device: torch.device) -> str:
    if backend != "auto":
        return backend
    try:
        from gaussian_renderer_pose import available_backends

        return device.type if available_backends().get(device.type) is None else "reference"
    except Exception:  # pragma: no cover
        return "auto"


def _publish(staging: Path, final: Path, overwrite: bool) -> None:
    """Move the finished staging folder to `final` (replacing an old one only if allowed)."""
    if final.exists():
        if not overwrite:
            raise ModelFolderExistsError(
                f"model_path {str(final)!r} appeared during the fit; the result "
                f"is kept in {str(staging)!r}"
            )
        old = final.parent / f".{final.name}.old"
        if old.exists():
            shutil.rmtree(old)
        os.replace(final, old)
        os.replace(staging, final)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(staging, final)


