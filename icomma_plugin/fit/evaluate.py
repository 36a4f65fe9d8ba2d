"""How well a fitted model explains photos: PSNR with and without exposure, and a picture grid.

PSNR is measured on valid pixels (`FitView.valid`), on the render clamped to [0, 1], as upstream.
Three figures per photo:
- ``full``: the render as it is (what localization compares a photo with);
- ``right``: the same, on the right half of the photo only;
- ``right_exposure``: upstream's `--train_test_exp` protocol for held-out photos: an affine
  colour transform fitted on the left half (least squares, `exposure.fit_affine_colour`),
  PSNR on the right half through it.
Training photos also get ``exposure``: PSNR through their own fitted exposure (exposure.json).
Held-out photos of a fit with exposures also get ``neighbour_exposure``: PSNR of the whole photo
through the exposure predicted from the nearest training photos (`exposure.NeighbourExposure`),
a render as the model would show that view without seeing its photo.
A render through an exposure is clamped to [0, 1] again before its PSNR, as upstream's.
"""
from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Callable, Dict, List, Mapping, Optional, Sequence, Union

import numpy as np
import torch

from .exposure import NeighbourExposure, apply_affine_colour, fit_affine_colour
from .losses import psnr

log = logging.getLogger(__name__)

PathLike = Union[str, os.PathLike]
RenderFn = Callable[[object], torch.Tensor]  # FitView -> colour [3, H, W]


def half_masks(view) -> tuple:
    """([1, H, W] left-half mask, right-half mask), each times the view's valid mask."""
    i = view.intrinsics
    left = torch.zeros(1, i.height, i.width, dtype=view.image.dtype, device=view.image.device)
    left[..., : i.width // 2] = 1.0
    right = 1.0 - left
    if view.valid is not None:
        left, right = left * view.valid, right * view.valid
    return left, right


def photo_psnrs(render: torch.Tensor, view, exposure: Optional[torch.Tensor] = None,
                predicted: Optional[torch.Tensor] = None) -> Dict[str, float]:
    """PSNRs (dB) of one render: "full", "right", "right_exposure" and the optional ones.

    "exposure" with ``exposure``, "neighbour_exposure" with ``predicted`` (module doc).

    exposure: the photo's own [3, 4] transform (a training photo), or None.
    predicted: a [3, 4] transform predicted for it from other photos, or None.
    """
    render = render.detach().to(view.image.device).clamp(0.0, 1.0)  # a GPU fit's render
    left, right = half_masks(view)

    def through(E):
        return apply_affine_colour(E.to(render.device, render.dtype), render).clamp(0.0, 1.0)

    out = {
        "full": psnr(render, view.image, view.valid),
        "right": psnr(render, view.image, right),
        "right_exposure": psnr(through(fit_affine_colour(render, view.image, left)), view.image,
                               right),
    }
    if exposure is not None:
        out["exposure"] = psnr(through(exposure), view.image, view.valid)
    if predicted is not None:
        out["neighbour_exposure"] = psnr(through(predicted), view.image, view.valid)
    return out


def evaluate_views(render_fn: RenderFn, views: Sequence, exposures: Optional[Mapping] = None,
                   keep: int = 0, predict_exposure: Optional[Callable] = None
                   ) -> Dict[str, object]:
    """Mean PSNRs over `views` (`photo_psnrs`), per view, and the first `keep` renders.

    Args:
        render_fn: FitView -> rendered colour [3, H, W].
        views: FitViews.
        exposures: {view name: [3, 4] tensor} of training photos, or None.
        keep: how many (evenly spaced) views' renders to return, for a picture grid.
        predict_exposure: w2c [4, 4] -> predicted [3, 4] transform (`NeighbourExposure`), for
            held-out photos; None: no ``neighbour_exposure`` figure.

    Returns:
        {"mean": {figure: dB}, "per_view": {name: {figure: dB}}, "renders": [(view, render)]}.
    """
    per_view: Dict[str, Dict[str, float]] = {}
    shown = set(np.linspace(0, len(views) - 1, keep).round().astype(int).tolist()) if keep else ()
    renders = []
    for k, v in enumerate(views):
        color = render_fn(v).detach().to(v.image.device)  # the photos' device (a GPU fit: CPU)
        E = None if exposures is None else exposures.get(v.name)
        P = None if predict_exposure is None else predict_exposure(v.w2c)
        per_view[v.name] = photo_psnrs(color, v, E, P)
        if k in shown:
            renders.append((v, color.detach().clamp(0.0, 1.0)))
    keys = sorted({f for d in per_view.values() for f in d})
    mean = {f: float(np.mean([d[f] for d in per_view.values() if f in d])) for f in keys}
    return {"mean": mean, "per_view": per_view, "renders": renders}


def write_grid(path: PathLike, pairs: Sequence, max_side: int = 320) -> Path:
    """A PNG with one row per view: photo | render | error (mean |difference| x 4, grey).

    Args:
        path: the PNG to write (its folder is created).
        pairs: (FitView, render [3, H, W]) pairs.
        max_side: each tile is resized so that its longer side is at most this.
    """
    import cv2

    if not pairs:
        raise ValueError("pairs must hold at least one (view, render) pair, got none")
    rows: List[np.ndarray] = []
    for view, render in pairs:
        photo = view.image.detach().cpu().float()
        err = (render.cpu().float() - photo).abs().mean(dim=0, keepdim=True)
        diff = (err * 4.0).clamp(0.0, 1.0).expand(3, -1, -1)
        tiles = [photo, render.cpu().float(), diff]
        h, w = photo.shape[1:]
        s = min(1.0, max_side / max(h, w))
        size = (max(1, round(w * s)), max(1, round(h * s)))
        row = [cv2.resize((t.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8), size,
                          interpolation=cv2.INTER_AREA) for t in tiles]
        rows.append(np.concatenate(row, axis=1))
    width = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0))) for r in rows]
    grid = np.concatenate(rows, axis=0)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.partial.png")
    if not cv2.imwrite(str(tmp), cv2.cvtColor(grid, cv2.COLOR_RGB2BGR)):
        raise OSError(f"could not write {path}")
    os.replace(tmp, path)
    return path


def neighbour_exposure(train_views: Sequence, exposures: Optional[Mapping]
                       ) -> Optional[NeighbourExposure]:
    """`NeighbourExposure` of the training views that have an exposure; None when none has."""
    if not exposures:
        return None
    have = [v for v in train_views if v.name in exposures]
    if not have:
        log.warning("exposure.json names none of the %d training photos: no neighbour exposure",
                    len(train_views))
        return None
    return NeighbourExposure([v.w2c for v in have], [exposures[v.name] for v in have])


def read_exposures(model_path: PathLike) -> Optional[Dict[str, torch.Tensor]]:
    """{image name: [3, 4] tensor} of a model folder's exposure.json, or None without one."""
    import json

    path = Path(model_path) / "exposure.json"
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text())
        out = {str(k): torch.tensor(v, dtype=torch.float32) for k, v in data.items()}
    except (ValueError, TypeError) as e:
        raise ValueError(f"{path}: expected {{image name: 3x4 list}}, cannot read it: {e}") from e
    bad = [k for k, t in out.items() if tuple(t.shape) != (3, 4)]
    if bad:
        raise ValueError(f"{path}: exposures must be 3x4, not so for {bad[:3]}")
    return out


def evaluate_model_folder(model_path: PathLike, source_path: Optional[PathLike] = None,
                          resolution: Optional[int] = None, backend: str = "auto",
                          iteration: Optional[int] = None, grid: Optional[PathLike] = None,
                          grid_views: int = 8) -> Dict:
    """Train and test PSNR of a model folder on its dataset, on valid pixels (as `fit_scene`).

    Args:
        model_path: a model folder (upstream layout).
        source_path: the dataset; None: `source_path` of its cfg_args.
        resolution: upstream `-r`; None: the cfg_args `resolution`.
        backend: rasterizer backend.
        iteration: the saved iteration (None: the last).
        grid: write a PNG here of `grid_views` held-out photos beside their renders
            (`write_grid`); None: no picture.
        grid_views: rows of that picture (evenly spaced test views).

    Returns:
        {"train_psnr", "test_psnr" (None without test views), "train_psnr_exposure" (through
        exposure.json; None without it), "test_psnr_right_half", "test_psnr_right_half_exposure",
        "test_psnr_neighbour_exposure" (None without exposure.json) (module doc), "train_views",
        "test_views", "iteration", "num_gaussians", "resolution" [W, H], "per_view" {name:
        full-image dB}, "grid" (the picture's path or None)}.
    """
    from ..checks import check_backend_here
    from ..io.datasets import read_dataset
    from ..io.model_folder import load_model_folder
    from ..render import model_for_backend, render
    from .views import tiny_resolution_message, views_to_fit

    check_backend_here(backend, "backend")
    folder = load_model_folder(model_path, iteration)
    src = source_path if source_path is not None else folder.cfg.get("source_path")
    if not src:
        raise ValueError(f"model folder {model_path}: cfg_args has no source_path; pass "
                         "source_path")
    res = folder.cfg.get("resolution", -1) if resolution is None else resolution
    white = bool(folder.cfg.get("white_background", False))
    scene = read_dataset(src, white_background=white, principal_point=folder.principal_point)
    if scene.train and tiny_resolution_message(res, None, scene.train[0].intrinsics):
        log.warning("%s", tiny_resolution_message(res, None, scene.train[0].intrinsics))
    bg = (1.0, 1.0, 1.0) if white else (0.0, 0.0, 0.0)
    bg_t = torch.tensor(bg)

    model = model_for_backend(folder.model, backend)

    def render_fn(fv):
        return render(model, fv.intrinsics, fv.w2c, bg_t, backend=backend).color

    exposures = read_exposures(model_path)
    with torch.no_grad():
        train_views = views_to_fit(scene.train, res, None, bg)
        tr = evaluate_views(render_fn, train_views, exposures)
        test_views = views_to_fit(scene.test, res, None, bg)
        te = evaluate_views(render_fn, test_views, keep=grid_views if grid else 0,
                            predict_exposure=neighbour_exposure(train_views, exposures))
    size = None
    if test_views or scene.train:
        i = (test_views[0] if test_views else views_to_fit(scene.train[:1], res, None, bg)[0])
        size = [i.intrinsics.width, i.intrinsics.height]
    grid_path = str(write_grid(grid, te["renders"])) if grid and te["renders"] else None
    per_view = {n: d["full"] for split in (tr, te) for n, d in split["per_view"].items()}
    return {
        "train_psnr": tr["mean"].get("full"),
        "test_psnr": te["mean"].get("full"),
        "train_psnr_exposure": tr["mean"].get("exposure"),
        "test_psnr_right_half": te["mean"].get("right"),
        "test_psnr_right_half_exposure": te["mean"].get("right_exposure"),
        "test_psnr_neighbour_exposure": te["mean"].get("neighbour_exposure"),
        "train_views": len(scene.train),
        "test_views": len(scene.test),
        "iteration": folder.iteration,
        "num_gaussians": folder.model.num_gaussians,
        "resolution": size,
        "per_view": per_view,
        "grid": grid_path,
    }
