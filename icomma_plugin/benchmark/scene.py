"""What a benchmark runs on.

A model, query images with ground-truth poses, and the scale that normalises translations.

- :func:`load_model_folder_scene`: a trained 3DGS model folder (e.g. lego fitted on its train
  split) plus a dataset whose split (``test``) provides the queries and their poses.
- :func:`synthetic_scene`: a small procedural model whose queries are rendered by the model itself
  (no data needed; tests and smoke runs).

Translation normalisation (docs/BENCHMARK.md): ``translation_unit="scene_radius"`` divides world
distances by the 3DGS scene radius (``getNerfppNorm``: 1.1 x the largest distance of a TRAIN
camera centre from their mean; ``SceneData.scene_radius()``); ``"world"`` keeps world units.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence

import numpy as np
import torch

from ..camera import Intrinsics
from ..gaussians import GaussianModel
from ..localization.localizer import Localizer
from ..localization.types import Query

logger = logging.getLogger(__name__)

__all__ = [
    "BenchQuery",
    "BenchScene",
    "TRANSLATION_UNITS",
    "shared_data_root",
    "default_lego_dataset",
    "select_indices",
    "training_scale",
    "load_model_folder_scene",
    "synthetic_scene",
    "camera_radius",
]

TRANSLATION_UNITS = ("scene_radius", "world")
REPO_ROOT = Path(__file__).resolve().parents[2]


@dataclass
class BenchQuery:
    """One query photo of a benchmark: the photo, its true pose and its index in its split."""

    query: Query
    gt_c2w: np.ndarray  # [4, 4] float64, OpenCV axes
    index: int
    # how precisely the capture's own tracks fix gt_c2w (colmap_tracks.record_precision's
    # entry: rot_std_deg, rot_cov, ...); None: no tracks
    record: Optional[Dict[str, Any]] = None

    @property
    def name(self) -> str:
        """The photo's name."""
        return self.query.name


@dataclass
class BenchScene:
    """A model, its queries and what the methods may use besides.

    That is the candidate views (``cameras_c2w``: the model's cameras, never a camera of the
    queries' split; ``cameras``: the same cameras as the model folder's ``CameraEntry``s, with
    their names and intrinsics, which the Localizer gets when they are known) and the scene
    centre (the ``scene_center`` pivot).
    """

    model: GaussianModel
    queries: List[BenchQuery]
    bg: torch.Tensor  # [3]
    translation_scale: float  # world units per normalised unit
    translation_unit: str
    scene_radius: float
    info: Dict[str, Any] = field(default_factory=dict)
    cameras_c2w: List[np.ndarray] = field(default_factory=list)
    cameras: Optional[List[Any]] = None
    scene_centre: Optional[np.ndarray] = None
    no_start_queries: List[BenchQuery] = field(default_factory=list)  # views for no-start runs
    model_side: Optional[int] = None  # longer side of the images the model was fitted on
    photos: Optional[List[Any]] = None  # the photos the model was fitted from (anchors)
    _localizers: Dict[Any, Any] = field(default_factory=dict)

    def localizer(self, matcher, method, backend: str = "auto", cache_dir=False,
                  lod="auto") -> Localizer:
        """The Localizer of ``method`` on this scene (made once per method and matcher).

        Its candidate views are the scene's cameras (never a camera of the queries' split). The
        candidate index is kept in memory only unless ``cache_dir`` says otherwise; ``lod``: the
        Localizer's level of detail.
        """
        key = (method.name, id(method), id(matcher), backend, repr(lod))
        if key not in self._localizers:
            self._localizers[key] = Localizer(
                self.model, matcher, method,
                cameras=self.cameras if self.cameras is not None else self.cameras_c2w,
                backend=backend,
                background=self.bg, model_side=self.model_side, cache_dir=cache_dir,
                photos=self.photos, lod=lod)
        return self._localizers[key]

    def describe(self) -> Dict[str, Any]:
        """The scene as results.json records it (model, queries, image size, units, ...)."""
        q = self.queries[0].query.intrinsics if self.queries else None
        return {
            **self.info,
            "num_gaussians": int(self.model.num_gaussians),
            "queries": [{"name": x.name, "index": x.index} for x in self.queries],
            "image_size": None if q is None else [q.width, q.height],
            "translation_unit": self.translation_unit,
            "translation_scale": self.translation_scale,
            "scene_radius": self.scene_radius,
            "background": [float(v) for v in self.bg],
        }


def shared_data_root() -> Path:
    """The shared data folder (``io.datasets.shared_data_root``)."""
    from ..io.datasets import shared_data_root as root

    return root()


def default_lego_dataset() -> Path:
    """The shared NeRF-synthetic lego at 400x400."""
    return shared_data_root() / "nerf_synthetic" / "lego_400"


def camera_radius(c2ws: Sequence[np.ndarray]) -> float:
    """3DGS ``getNerfppNorm`` radius of camera centres (``pose.convert.cameras_extent``)."""
    from ..pose.convert import cameras_extent

    return cameras_extent(c2ws)


def select_indices(n: int, num: int, indices: Optional[Sequence[int]] = None) -> List[int]:
    """Explicit ``indices`` (checked) or ``num`` evenly spaced indices over ``range(n)``."""
    if indices is not None:
        out = [int(i) for i in indices]
        bad = [i for i in out if not 0 <= i < n]
        if bad:
            raise ValueError(f"query indices {bad} out of range: the split has {n} views")
        return out
    if not isinstance(num, int) or num < 1:
        raise ValueError(f"num_queries must be a positive int, got {num!r}")
    if num > n:
        raise ValueError(f"num_queries={num} exceeds the {n} views of the split")
    return sorted({int(round(x)) for x in np.linspace(0, n - 1, num)})


def _scale_of(unit: str, radius: float) -> float:
    if unit not in TRANSLATION_UNITS:
        raise ValueError(f"translation_unit must be one of {TRANSLATION_UNITS}, got {unit!r}")
    return float(radius) if unit == "scene_radius" else 1.0


def training_scale(cfg: Dict[str, Any], cameras, width: int) -> float:
    """The image scale the model was trained at (``io.model_folder.training_scale``)."""
    from ..io.model_folder import training_scale as scale_of

    return scale_of(cfg, width)


def load_model_folder_scene(
    model_path, dataset=None, num_queries: int = 5, split: str = "test",
    query_indices: Optional[Sequence[int]] = None, image_scale: Optional[float] = None,
    white_background: Optional[bool] = None, iteration: Optional[int] = None,
    translation_unit: str = "world", no_start_queries: int = 0, photos: str = "none",
    principal_point: Optional[str] = None,
) -> BenchScene:
    """Model folder + the dataset's ``split`` views as queries.

    Args:
        model_path: trained 3DGS output folder (cfg_args, point_cloud/iteration_N/).
        dataset: dataset folder; None = cfg_args ``source_path`` when it exists here, else the
            shared lego_400 (``ICOMMA_SHARED_DATA``).
        num_queries: how many views of the split, evenly spaced (unless ``query_indices``).
        split: the split the queries come from: ``train``, ``test`` or ``val`` (Blender
            datasets only).
        query_indices: explicit view indices in the split instead of ``num_queries``.
        image_scale: query scale; None = the scale the model was trained at (cfg_args
            ``resolution``, see :func:`training_scale`).
        white_background: None = cfg_args ``white_background``.
        iteration: the model's iteration to load; None = the highest.
        translation_unit: ``world`` or ``scene_radius`` (module docstring).
        no_start_queries: also load this many evenly spaced views for the runs without a start
            pose (they have nothing random to vary, so each run takes another view).
        photos: ``auto``: the split's training views (the photos the model was fitted from)
            anchor the default method; ``none``: renders only.
        principal_point: the principal point the model was fitted with, which the views take
            (``dataset`` or ``centre``); None or ``auto``: as the folder says
            (``ModelFolder.principal_point``).
    """
    if photos not in ("auto", "none"):
        raise ValueError(f"photos must be auto or none, got {photos!r}")
    from ..io.datasets import detect_dataset_kind, read_dataset
    from ..io.datasets.colmap_tracks import precision_of, record_precision
    from ..io.model_folder import load_model_folder
    from ..pose.convert import same_as_any_mask
    from ..pose.views import scene_frame

    mp = Path(str(model_path)).expanduser()
    if not mp.is_dir():
        raise FileNotFoundError(f"model folder not found: {mp}")
    mf = load_model_folder(mp, iteration=iteration).with_principal_point(principal_point)
    white = mf.white_background if white_background is None else bool(white_background)
    if dataset is None:
        src = mf.cfg.get("source_path")
        dataset = src if src and Path(str(src)).is_dir() else default_lego_dataset()
    root = Path(str(dataset)).expanduser()
    if not root.is_dir():
        raise FileNotFoundError(
            f"dataset folder not found: {root} (set scene.query.dataset or ICOMMA_SHARED_DATA)"
        )
    if split not in ("train", "test", "val"):
        raise ValueError(f"split must be train, test or val (Blender datasets), got {split!r}")
    kw = {}
    if split == "val":  # NeRF-synthetic's third split: read it as the test split
        if detect_dataset_kind(root) != "blender":
            raise ValueError(
                f"split 'val' exists only for Blender / NeRF-synthetic datasets; {root} is "
                "another kind"
            )
        kw["test_split"] = "val"
    sd = read_dataset(root, white_background=white, principal_point=mf.principal_point, **kw)
    split_of_views = "test" if split == "val" else split
    views = getattr(sd, split_of_views)
    if not views:
        raise ValueError(f"the {split!r} split of {root} is empty")
    idx = select_indices(len(views), num_queries, query_indices)
    if image_scale is None:
        image_scale = training_scale(mf.cfg, mf.cameras, views[0].intrinsics.width)
    bg = torch.ones(3) if white else torch.zeros(3)
    records = record_precision(root)  # {} unless the capture has COLMAP tracks

    def load(i):
        return BenchQuery(Query.from_view(views[i], bg, float(image_scale)),
                          np.asarray(views[i].c2w, np.float64), i,
                          precision_of(records, views[i].name))

    queries = [load(i) for i in idx]
    by_index = {q.index: q for q in queries}
    extra = (
        [
            by_index.get(i) or load(i)
            for i in select_indices(len(views), min(len(views), no_start_queries))
        ]
        if no_start_queries > 0
        else []
    )
    radius = sd.scene_radius() if sd.train else camera_radius([v.c2w for v in views])
    # Candidate views: the model's cameras, never one at a pose of the queries' split (upstream's
    # cameras.json lists the test cameras too; a query must not find its own pose there).
    split_c2ws = [np.asarray(v.c2w, np.float64) for v in views]
    # The model's camera entries when it lists them: the Localizer then gets their names and
    # intrinsics as a user's does (one candidate index for COLMAP's per-image cameras; a camera
    # with a source photo described by that photo), not bare poses.
    entries = list(mf.cameras or [])
    cams = [np.asarray(e.c2w, np.float64) for e in entries] or [
        np.asarray(v.c2w, np.float64)
        for v in (sd.train if split_of_views == "test" else sd.test)
    ]
    keep = ~np.asarray(same_as_any_mask(cams, split_c2ws), bool)
    if split_of_views != "train" and sd.train:
        # Keep the cameras the model was fitted from (upstream's cameras.json lists the other
        # held-out views too, e.g. lego's 200 test cameras when the queries are its val views).
        train_c2ws = [np.asarray(v.c2w, np.float64) for v in sd.train]
        fitted = keep & np.asarray(same_as_any_mask(cams, train_c2ws), bool)
        keep = fitted if fitted.any() else keep
    cams = [c for c, k in zip(cams, keep) if k]
    entries = [e for e, k in zip(entries, keep) if k] if entries else None
    centre, _, _ = scene_frame(mf.model.means.numpy(), cams)
    return BenchScene(
        model=mf.model,
        queries=queries,
        bg=bg,
        translation_scale=_scale_of(translation_unit, radius),
        translation_unit=translation_unit,
        scene_radius=radius,
        cameras_c2w=cams,
        cameras=entries,
        scene_centre=centre,
        no_start_queries=extra,
        model_side=mf.training_side(),
        photos=list(sd.train) if photos == "auto" and split_of_views != "train" else None,
        info={
            "kind": "model_folder",
            "model_path": str(mp),
            "iteration": mf.iteration,
            "dataset": str(root),
            "split": split,
            "image_scale": float(image_scale),
            "white_background": white,
            "principal_point": mf.principal_point,  # the views' (the model's fit's)
            "candidate_cameras": len(cams),
            "records_with_precision": len(records),
        },
    )


def synthetic_scene(
    num_gaussians: int = 300, width: int = 64, height: int = 64, num_queries: int = 2,
    seed: int = 0, radius: float = 4.0, fov_deg: float = 40.0, translation_unit: str = "world",
    backend: str = "auto",
) -> BenchScene:
    """A procedural model around the origin, with ring cameras and queries rendered by the model.

    12 "train" cameras on a ring (for the scene radius) and ``num_queries`` query cameras between
    them.
    """
    from ..pose.convert import invert_rigid, look_at_c2w
    from ..render import render

    from ..app.demo_scene import blob_model

    model = blob_model(num_gaussians, seed)
    intr = Intrinsics.from_fov(int(width), int(height), math.radians(float(fov_deg)))

    def cam(az_deg, el_deg):
        az, el = math.radians(az_deg), math.radians(el_deg)
        eye = radius * np.array(
            [math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)]
        )
        return look_at_c2w(eye, np.zeros(3), up=(0.0, 0.0, 1.0))

    train = [cam(a, 30.0) for a in range(0, 360, 30)]
    r = camera_radius(train)
    bg = torch.zeros(3)
    queries = []
    for i in range(int(num_queries)):
        c2w = cam(15.0 + 360.0 * i / max(1, num_queries), 25.0 + 10.0 * (i % 2))
        with torch.no_grad():
            img = render(model, intr, torch.as_tensor(invert_rigid(c2w), dtype=torch.float32), bg,
                         backend=backend).color.clamp(0, 1)
        queries.append(BenchQuery(Query(img.contiguous(), intr, name=f"synthetic_{i}"), c2w, i))
    return BenchScene(
        model=model,
        queries=queries,
        bg=bg,
        translation_scale=_scale_of(translation_unit, r),
        translation_unit=translation_unit,
        scene_radius=r,
        cameras_c2w=train,
        scene_centre=np.zeros(3),
        info={"kind": "synthetic", "seed": int(seed), "num_gaussians": int(num_gaussians)},
    )
