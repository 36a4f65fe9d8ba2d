"""Many photos against one model.

Plan the photos (start pose, truth, intrinsics of each), run them in one process or in several
worker processes, record every result in ``poses.json`` / ``poses.csv`` (``ledger.py``),
resumable, shardable across cluster jobs.

    plan, mf = plan_batch(data)                       # the tool's data group (model_folder)
    setup = WorkerSetup(model_path=..., method=RobustConfig(), matcher={"name": "xfeat"}, ...)
    ledger = PosesLedger(out_dir, run=run_identity("batch", data), total=len(plan.tasks))
    summary = run_batch(plan, setup, ledger, workers=2)

Each worker loads the model once, builds the candidate views once per camera (intrinsics) and
reuses them for every photo (``CandidateSet.for_model``); a photo whose own camera is among the
model's cameras (same pose as its known truth) has that camera left out, as a benchmark must.
A photo that cannot be read, has the wrong size or no start pose becomes a ``failed`` row whose
``error`` says why; the batch goes on.
"""

from __future__ import annotations

import contextlib
import importlib
import logging
import multiprocessing
import os
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, List, Optional, Sequence, Tuple

import numpy as np
import torch

from ..camera import Intrinsics
from .inputs import PhotoMismatch, PoseTable, list_photos, photo_intrinsics, read_poses_file
from .ledger import PosesLedger
from .problem import (
    Problem,
    ProblemError,
    _init_group,
    _perturbed,
    load_c2w_file,
    open_model_folder,
    read_query_image,
)
from ..localization.types import LocalizationResult, Query

logger = logging.getLogger(__name__)

__all__ = [
    "BatchPlan",
    "BatchSummary",
    "BatchWorker",
    "PhotoTask",
    "WorkerSetup",
    "export_rows",
    "failure_row",
    "make_matcher_from_spec",
    "open_model_folder",
    "plan_batch",
    "resize_query",
    "result_row",
    "run_batch",
    "run_identity",
    "safe_name",
    "start_poses",
]

INIT_KEYS = ("camera", "c2w_file", "rot_deg", "poses_file", "cameras_json")


# ---------------------------------------------------------------------------------- planning


@dataclass
class PhotoTask:
    """One photo of a batch (picklable: it travels to the worker processes).

    intrinsics: at the image file's size (None when ``error`` is set). init_c2w: the start pose,
    or None (candidate views). gt_c2w: the truth when known (errors only). error: bad input
    found while planning: the photo is recorded as failed with this reason.
    """

    index: int
    name: str
    path: Optional[str]
    view: Any = None
    intrinsics: Optional[Intrinsics] = None
    init_c2w: Optional[np.ndarray] = None
    gt_c2w: Optional[np.ndarray] = None
    error: Optional[str] = None


@dataclass
class BatchPlan:
    """The photos of a batch (`plan_batch`) and the model they are localized in."""

    tasks: List[PhotoTask]
    model_path: str
    iteration: Optional[int]
    white_background: bool
    resize: Optional[int]
    init_mode: str  # none | constant | per_photo | perturbed
    source: Any = None


def _positive(d, key, default=None):
    v = d.get(key, default)
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, int) or v < 1:
        raise ProblemError(f"data.{key} must be a positive integer or null, got {v!r}")
    return v


def start_poses(
    ini_cfg, names: Sequence[str], gts: Sequence[Optional[np.ndarray]], mf
) -> Tuple[str, List[Optional[np.ndarray]], List[Optional[str]]]:
    """(mode, start c2w per photo, error per photo) from the ``data.init`` group.

    none (``data.init=none``): no start pose; constant: ``camera`` / ``c2w_file``; per_photo:
    ``poses_file`` / ``cameras_json`` looked up by name (``missing: none`` searches the candidate
    views for a photo the file lacks, ``fail`` records it as failed); perturbed: the truth turned
    by ``rot_deg`` (seed ``seed + index``).
    """
    from ..io.cameras_json import find_entry

    ini = _init_group(ini_cfg)
    n = len(names)
    if ini is None:
        return "none", [None] * n, [None] * n
    chosen = [k for k in INIT_KEYS if ini.get(k) is not None]
    if len(chosen) != 1:
        raise ProblemError(
            "choose exactly one start pose for the photos: data.init.poses_file, "
            "data.init.cameras_json, data.init.c2w_file, data.init.camera or data.init.rot_deg, or "
            f"none with data.init=none (got {chosen or 'none of them'})"
        )
    key = chosen[0]
    if key == "camera":
        if not mf.cameras:
            raise ProblemError(
                f"data.init.camera={ini['camera']!r}: the model folder has no cameras.json"
            )
        try:
            c2w = np.asarray(find_entry(mf.cameras, ini["camera"]).c2w, np.float64)
        except ValueError as e:
            raise ProblemError(f"data.init.camera: {e}") from None
        return "constant", [c2w] * n, [None] * n
    if key == "c2w_file":
        c2w = load_c2w_file(ini["c2w_file"], "data.init.c2w_file")
        return "constant", [c2w] * n, [None] * n
    if key == "rot_deg":
        out, errs = [], []
        for i, gt in enumerate(gts):
            if gt is None:
                out.append(None)
                errs.append(
                    "data.init.rot_deg perturbs the ground truth, which is unknown for this photo "
                    "(set data.gt.poses_file, or use a dataset folder as data.queries)"
                )
                continue
            sub = dict(ini, seed=int(ini.get("seed") or 0) + i)
            out.append(_perturbed(gt, sub, None, mf))
            errs.append(None)
        return "perturbed", out, errs
    missing = str(ini.get("missing") or "fail")
    if missing not in ("fail", "none"):
        raise ProblemError(f"data.init.missing must be fail or none, got {missing!r}")
    what = f"data.init.{key}"
    table = read_poses_file(ini[key], what)
    out, errs = [], []
    for name in names:
        c2w = table.get(name)
        out.append(c2w)
        errs.append(
            None
            if c2w is not None or missing == "none"
            else f"no start pose for {name!r} in {what} ({table.source}); add it, or set "
            "data.init.missing=none to search the candidate views"
        )
    return "per_photo", out, errs


def _truths(gt_cfg, names: Sequence[str], views) -> List[Optional[np.ndarray]]:
    g = gt_cfg or {}
    for k in ("camera", "c2w_file"):
        if g.get(k) is not None:
            raise ProblemError(
                f"data.gt.{k} is one pose for one photo; for a batch use data.gt.poses_file "
                "or data.gt.cameras_json (poses by name)"
            )
    table: Optional[PoseTable] = None
    for k in ("poses_file", "cameras_json"):
        if g.get(k) is not None:
            table = read_poses_file(g[k], f"data.gt.{k}")
    out = []
    for i, name in enumerate(names):
        gt = table.get(name) if table is not None else None
        if gt is None and views is not None:
            gt = np.asarray(views[i].c2w, np.float64)
        out.append(gt)
    return out


def select(items: Sequence[Any], every: Optional[int], limit: Optional[int]) -> List[int]:
    """Indices of every ``every``-th item, at most ``limit`` of them."""
    idx = list(range(0, len(items), every or 1))
    return idx[:limit] if limit else idx


def plan_batch(data: Dict[str, Any], mf=None) -> Tuple[BatchPlan, Any]:
    """The photos of ``data.queries`` with their start poses, truths and intrinsics.

    Returns:
        (plan, model folder). ``mf`` may be passed when the caller has loaded it already.

    Raises:
        ProblemError: naming the key (no photos found, an unreadable poses file, no
            intrinsics...).
    """
    from ..io.datasets.base import image_size

    if mf is None:
        mf, white = open_model_folder(data)
    else:
        white = (
            mf.white_background
            if data.get("white_background") is None
            else bool(data["white_background"])
        )
    every, limit = _positive(data, "every", 1), _positive(data, "limit")
    resize = _positive(data, "resize")
    photos = list_photos(
        data.get("queries"), "data.queries", str(data.get("queries_split") or "all"), white
    )
    keep = select(photos.names, every, limit)
    names = [photos.names[i] for i in keep]
    paths = [photos.paths[i] for i in keep]
    views = None if photos.views is None else [photos.views[i] for i in keep]
    gts = _truths(data.get("gt"), names, views)
    mode, inits, init_errs = start_poses(data.get("init"), names, gts, mf)
    it = data.get("intrinsics") or {}
    tasks = []
    for i, name in enumerate(names):
        err, intr = init_errs[i], None
        if views is not None:
            intr = views[i].intrinsics
        else:
            try:
                intr = photo_intrinsics(image_size(paths[i]), it, mf.cameras)
            except PhotoMismatch as e:  # this photo only
                err = err or str(e)
            except ProblemError:  # the config's, the same for every photo
                raise
            except Exception as e:  # noqa: BLE001 - an unreadable photo is a per-photo failure
                err = err or f"cannot read the image {paths[i]} ({type(e).__name__}: {e})"
        tasks.append(
            PhotoTask(
                i,
                name,
                str(paths[i]),
                None if views is None else views[i],
                intr,
                inits[i],
                gts[i],
                err,
            )
        )
    plan = BatchPlan(
        tasks, str(Path(mf.path).resolve()), mf.iteration, white, resize, mode, data.get("queries")
    )
    return plan, mf


def run_identity(kind: str, data: Dict[str, Any], model_path: str) -> Dict[str, Any]:
    """What a resumed run must share with the poses.json it continues."""

    def norm(v):
        return (
            [str(x) for x in v] if isinstance(v, (list, tuple)) else (None if v is None else str(v))
        )

    return {
        "kind": kind,
        "model_path": str(model_path),
        "queries": norm(data.get("queries")),
        "sequence": norm(data.get("sequence")),
    }


# ---------------------------------------------------------------------------------- the worker


def make_matcher_from_spec(spec: Optional[Dict[str, Any]]):
    """A matcher from a matcher group mapping; None for ``none``. No Hydra needed.

    The mapping has ``name`` and keyword arguments, optionally ``_target_``: a dotted path to a
    factory.
    """
    if not spec:
        return None
    d = dict(spec)
    target = d.pop("_target_", None)
    for k in ("_convert_", "_recursive_", "_partial_"):
        d.pop(k, None)
    if d.get("name") in (None, "none"):
        return None
    if target in (None, "icomma_plugin.matchers.make_matcher"):
        from ..matchers import make_matcher

        return make_matcher(d.pop("name"), **d)
    mod, _, attr = str(target).rpartition(".")
    return getattr(importlib.import_module(mod), attr)(**d)


@dataclass
class WorkerSetup:
    """Everything a worker process needs (picklable).

    method: RobustConfig or LocalizerConfig. matcher: the matcher group mapping. out_dir: the
    batch's output folder. folders: write each photo's folder of pictures (``photos/<name>/``)
    with ``output`` (an OutputOptions). thumbs: write ``thumbs/<name>.png`` for the contact
    sheet. config: the composed config, stored in each result.json. seed: torch / numpy seed of
    every photo (``seed + index``), so results do not depend on the worker a photo lands on.
    """

    model_path: str
    method: Any
    matcher: Optional[Dict[str, Any]]
    out_dir: str
    iteration: Optional[int] = None
    white_background: bool = False
    backend: str = "auto"
    resize: Optional[int] = None
    folders: bool = False
    output: Any = None
    thumbs: bool = True
    thumb_side: int = 192
    config: Dict[str, Any] = field(default_factory=dict)
    seed: Optional[int] = 0


def safe_name(name: str) -> str:
    """A file-system-safe folder name for a photo name (``a/b.jpg`` -> ``a__b.jpg``)."""
    s = name.replace("/", "__").replace("\\", "__")
    return re.sub(r"[^A-Za-z0-9._+-]", "_", s) or "photo"


def resize_query(q: Query, side: Optional[int]) -> Query:
    """``q`` resized so that its longer side is ``side`` px (intrinsics follow); as is for None."""
    from ..localization.state import resize_image

    W, H = q.intrinsics.width, q.intrinsics.height
    if not side or max(W, H) == side:
        return q
    intr = q.intrinsics.scaled(side / max(W, H))
    h, w = intr.height, intr.width
    rgb = resize_image(q.rgb, h, w).clamp(0, 1)
    alpha = None if q.alpha is None else resize_image(q.alpha, h, w).clamp(0, 1)
    valid = None if q.valid is None else (resize_image(q.valid, h, w) > 0.999).float()
    return Query(rgb.contiguous(), intr, alpha, valid, q.name)


def _intrinsics_json(intr: Intrinsics) -> Dict[str, Any]:
    return {
        "width": intr.width,
        "height": intr.height,
        "fx": intr.fx,
        "fy": intr.fy,
        "cx": intr.cx,
        "cy": intr.cy,
    }


def failure_row(
    task: PhotoTask, reason: str, error: Optional[str] = None, seconds: float = 0.0
) -> Dict[str, Any]:
    """The row of a photo that could not be localized at all."""
    return {
        "index": task.index,
        "name": task.name,
        "image": task.path,
        "status": "failed",
        "reason": reason,
        "error": error or reason,
        "c2w": None,
        "init_c2w": None if task.init_c2w is None else np.asarray(task.init_c2w).tolist(),
        "gt_c2w": None if task.gt_c2w is None else np.asarray(task.gt_c2w).tolist(),
        "rot_err_deg": None,
        "trans_err": None,
        "trans_err_rel": None,
        "initial_rot_err_deg": None,
        "seconds": seconds,
        "intrinsics": None if task.intrinsics is None else _intrinsics_json(task.intrinsics),
    }


def result_row(
    task: PhotoTask,
    problem: Problem,
    result: LocalizationResult,
    seconds: float,
    folder: Optional[str] = None,
    thumb: Optional[str] = None,
) -> Dict[str, Any]:
    """The poses.json row of one localized photo."""
    scale = problem.scene_scale
    te = result.final_translation_error
    v = result.verdict
    mc = result.match_counts or {}
    return {
        "index": task.index,
        "name": task.name,
        "image": task.path,
        "status": v.status if v is not None else "uncertain",
        "reason": v.reason if v is not None else "no verdict",
        "error": None,
        "c2w": result.c2w.tolist(),
        "init_c2w": None if problem.init_c2w is None else problem.init_c2w.tolist(),
        "gt_c2w": None if problem.gt_c2w is None else problem.gt_c2w.tolist(),
        "rot_err_deg": result.final_rotation_error_deg,
        "trans_err": te,
        "trans_err_rel": None if te is None or not scale else te / scale,
        "initial_rot_err_deg": result.initial_rotation_error_deg,
        "seconds": seconds,
        "localize_seconds": result.seconds,
        "iterations": result.iterations,
        "method": result.method,
        "inliers": mc.get("inliers"),
        "matches": mc.get("matches"),
        "intrinsics": _intrinsics_json(task.intrinsics),
        "work_size": [problem.query.intrinsics.width, problem.query.intrinsics.height],
        "folder": folder,
        "thumb": thumb,
        "worker": os.getpid(),
    }


@contextlib.contextmanager
def _seeded(seed: Optional[int]) -> Iterator[None]:
    """Seed torch and numpy inside the block and restore their states after it."""
    if seed is None:
        yield
        return
    state = np.random.get_state()
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        np.random.seed(seed % (2**32))
        try:
            yield
        finally:
            np.random.set_state(state)


class BatchWorker:
    """Localizes the photos of a batch, one at a time (one per process, or the caller's)."""

    def __init__(self, setup: WorkerSetup, model_folder=None, matcher=None):
        from ..io.model_folder import load_model_folder
        from ..pose.convert import cameras_extent

        self.setup = setup
        self.mf = (
            model_folder
            if model_folder is not None
            else load_model_folder(setup.model_path, setup.iteration)
        )
        self.model = self.mf.model
        if setup.backend == "cuda":
            self.model = self.model.to("cuda")
        self.bg = torch.ones(3) if setup.white_background else torch.zeros(3)
        self.matcher = matcher if matcher is not None else make_matcher_from_spec(setup.matcher)
        self.cameras = list(self.mf.cameras or [])
        self.scene_scale = cameras_extent([e.c2w for e in self.cameras]) if self.cameras else None
        self._candidates: Dict[Intrinsics, Any] = {}
        self.left_out = 0  # model cameras left out of the last photo's candidates (its own view)
        self.out_dir = Path(setup.out_dir)

    # ------------------------------------------------------------------ candidates
    def candidates(self, intr: Intrinsics):
        """The candidate set for photos with ``intr`` (built on first use, then reused)."""
        from ..localization.candidates import CandidateSet, usable
        from ..localization.robust import RobustConfig

        cfg = self.setup.method
        if not isinstance(cfg, RobustConfig) or not cfg.use_candidates or not usable(self.matcher):
            return None
        cs = self._candidates.get(intr)
        if cs is None:
            t = time.perf_counter()
            cs = CandidateSet.for_model(
                self.model,
                intr,
                self.matcher,
                self.bg,
                [e.c2w for e in self.cameras],
                cfg.candidates,
                self.setup.backend,
                [e.img_name for e in self.cameras],
            )
            logger.info(
                "candidate set for %dx%d: %d views in %.1f s",
                intr.width,
                intr.height,
                len(cs.c2w),
                time.perf_counter() - t,
            )
            self._candidates[intr] = cs
        return cs

    def candidates_without(self, intr: Intrinsics, gt_c2w: Optional[np.ndarray]):
        """:meth:`candidates` less the model's camera at ``gt_c2w`` (the photo's own view)."""
        from ..localization.candidates import CandidateSet

        cs = self.candidates(intr)
        self.left_out = 0
        if cs is None or gt_c2w is None:
            return cs
        n = len(self.cameras)
        drop = {i for i in range(n) if np.allclose(cs.c2w[i], gt_c2w, atol=1e-6)}
        self.left_out = len(drop)  # reported in the photo's row
        if not drop:
            return cs
        keep = [i for i in range(len(cs.c2w)) if i not in drop]
        return CandidateSet(
            [cs.c2w[i] for i in keep],
            [cs.source[i] for i in keep],
            cs.intrinsics,
            [cs.features[i] for i in keep],
        )

    # ------------------------------------------------------------------ one photo
    def load_query(self, task: PhotoTask) -> Query:
        """The photo of ``task`` as a query, resized to the setup's ``resize``.

        Raises:
            ProblemError: the photo's size is not the one its intrinsics were planned for.
        """
        if task.view is not None:
            im = task.view.load_image(background=self.bg)
            q = Query(im.rgb, task.view.intrinsics, im.alpha, im.valid, task.name)
        else:
            rgb, alpha = read_query_image(task.path, self.bg)
            W, H = int(rgb.shape[2]), int(rgb.shape[1])
            if (W, H) != (task.intrinsics.width, task.intrinsics.height):
                raise ProblemError(
                    f"the photo {task.path} is {W}x{H}, not the {task.intrinsics.width}x"
                    f"{task.intrinsics.height} its intrinsics were planned for"
                )
            q = Query(rgb, task.intrinsics, alpha, None, task.name)
        return resize_query(q, self.setup.resize)

    def problem(self, task: PhotoTask, query: Query) -> Problem:
        """The localization problem of ``task``: this worker's model, the query, its poses."""
        return Problem(
            model=self.model,
            query=query,
            init_c2w=task.init_c2w,
            gt_c2w=task.gt_c2w,
            bg=self.bg,
            scene_scale=self.scene_scale,
            cameras=self.cameras,
            info={
                "model_path": self.setup.model_path,
                "iteration": self.mf.iteration,
                "num_gaussians": self.model.num_gaussians,
                "batch_index": task.index,
            },
        )

    def localize(
        self, problem: Problem, init_c2w: Optional[np.ndarray], progress=None
    ) -> LocalizationResult:
        """Localize ``problem`` from ``init_c2w`` (None: no start pose).

        The candidate views leave out a model camera at the photo's known true pose.
        """
        from ..localize import localize

        q = problem.query
        init_w2c = None if init_c2w is None else np.linalg.inv(init_c2w)
        gt_w2c = None if problem.gt_c2w is None else np.linalg.inv(problem.gt_c2w)
        cs = self.candidates_without(q.intrinsics, problem.gt_c2w)
        return localize(
            self.model,
            q.rgb,
            q.intrinsics,
            init_w2c,
            self.matcher,
            self.setup.method,
            gt_w2c=gt_w2c,
            query_alpha=q.alpha,
            query_valid=q.valid,
            backend=self.setup.backend,
            bg=self.bg,
            progress=progress,
            cameras_c2w=problem.candidate_c2ws(),
            camera_names=None,
            candidate_set=cs,
            query_name=q.name,
            model_side=self.mf.training_side(),
        )

    def write_pictures(
        self, problem: Problem, result: LocalizationResult, seconds: float
    ) -> Tuple[Optional[str], Optional[str]]:
        """The photo's folder (when asked) and its thumbnail; (folder, thumb) relative paths."""
        from .output import write_outputs

        folder = thumb = None
        safe = safe_name(problem.name)
        if self.setup.folders:
            rel = f"photos/{safe}"
            write_outputs(
                self.out_dir / rel,
                problem,
                result,
                matcher=self.matcher,
                options=self.setup.output,
                backend=self.setup.backend,
                config=self.setup.config,
                seconds_total=seconds,
            )
            folder = rel
        if self.setup.thumbs:
            try:
                from ..pictures import save_thumbnail

                rel = f"thumbs/{safe}.png"
                save_thumbnail(
                    self.out_dir / rel,
                    self.model,
                    problem.query,
                    result.c2w,
                    problem.bg,
                    self.setup.thumb_side,
                    backend=self.setup.backend,
                )
                thumb = rel
            except Exception as e:  # noqa: BLE001 - a picture never fails a photo
                logger.warning("no thumbnail for %s: %s: %s", problem.name, type(e).__name__, e)
        return folder, thumb

    def run(self, task: PhotoTask) -> Dict[str, Any]:
        """Localize one photo; always returns a row (a failed one for bad input or a crash)."""
        t0 = time.perf_counter()
        if task.error:
            return failure_row(task, f"bad input: {task.error}", task.error)
        try:
            with _seeded(None if self.setup.seed is None else self.setup.seed + task.index):
                query = self.load_query(task)
                problem = self.problem(task, query)
                if task.init_c2w is None and not self._can_search():
                    raise ProblemError(
                        "no start pose for this photo, and the paper's method (optimizer=icomma) "
                        "needs one: use optimizer=robust or give data.init"
                    )
                result = self.localize(problem, task.init_c2w)
            folder, thumb = self.write_pictures(problem, result, time.perf_counter() - t0)
            row = result_row(task, problem, result, time.perf_counter() - t0, folder, thumb)
            row["own_camera_left_out"] = self.left_out
            return row
        except (ValueError, FileNotFoundError) as e:
            msg = str(e).splitlines()[0] if str(e) else type(e).__name__
            return failure_row(task, f"bad input: {msg}", msg, time.perf_counter() - t0)
        except Exception as e:  # noqa: BLE001 - one photo must not stop the batch
            logger.exception("photo %s failed", task.name)
            msg = f"internal error: {type(e).__name__}: {e}"
            return failure_row(task, msg, msg, time.perf_counter() - t0)

    def _can_search(self) -> bool:
        from ..localization.robust import RobustConfig

        return isinstance(self.setup.method, RobustConfig)


# ---------------------------------------------------------------------------------- processes

_WORKER: Optional[BatchWorker] = None


def _init_worker(setup: WorkerSetup, threads: int) -> None:
    """Initializer of a worker process (started by :func:`run_batch`).

    Its own thread count, its own model, matcher and candidate sets.
    """
    global _WORKER
    torch.set_num_threads(max(1, int(threads)))
    _WORKER = BatchWorker(setup)


def _work(task: PhotoTask) -> Dict[str, Any]:
    assert _WORKER is not None, "worker not initialised"
    return _WORKER.run(task)


@dataclass
class BatchSummary:
    """What a :func:`run_batch` call did. ``photos_per_minute`` counts the photos it localized."""

    counts: Dict[str, int]
    done_now: int
    skipped: int
    todo: int
    seconds: float
    rows: List[Dict[str, Any]]

    @property
    def photos_per_minute(self) -> Optional[float]:
        """Photos localized per minute of this call; None when it localized none."""
        return (
            None if self.done_now == 0 or self.seconds <= 0 else 60.0 * self.done_now / self.seconds
        )


def run_batch(
    plan: BatchPlan,
    setup: WorkerSetup,
    ledger: PosesLedger,
    *,
    workers: int = 1,
    threads_per_worker: int = 1,
    retry_failed: bool = False,
    progress: Optional[Callable[[Dict[str, Any]], Any]] = None,
    model_folder=None,
    matcher=None,
) -> BatchSummary:
    """Localize this shard's unfinished photos of ``plan``, recording each in ``ledger``.

    Args:
        plan: from :func:`plan_batch`.
        setup: what each worker loads (from the tool's config).
        ledger: the output folder's record; photos it already holds are skipped.
        workers: 1 runs in this process (threads as the caller set them); more start that many
            worker processes (spawned), each with ``threads_per_worker`` torch threads (set in
            those processes only) and its own model and candidate sets.
        threads_per_worker: torch threads of each worker process.
        retry_failed: redo photos recorded as failed.
        progress: called after each photo with ``{"row", "counts", "done", "todo"}``.
        model_folder: reuse the caller's loaded model folder (``workers == 1`` only).
        matcher: reuse the caller's matcher (``workers == 1`` only).
    """
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers must be a positive int, got {workers!r}")
    mine = [t for t in plan.tasks if t.index % ledger.num_shards == ledger.shard]
    done = ledger.finished()
    if retry_failed:
        again = [t.name for t in mine if done.get(t.name, {}).get("status") == "failed"]
        ledger.forget(again)
        done = ledger.finished()
    todo = [t for t in mine if t.name not in done]
    skipped = len(mine) - len(todo)
    if skipped:
        logger.info("resuming: %d of %d photos of this shard already done", skipped, len(mine))
    t0 = time.perf_counter()
    rows: List[Dict[str, Any]] = []
    if progress is not None:
        progress(
            {
                "row": None,
                "counts": ledger.counts(),
                "done": 0,
                "todo": len(todo),
                "skipped": skipped,
            }
        )

    def take(row):
        ledger.record(row)
        rows.append(row)
        if progress is not None:
            progress({"row": row, "counts": ledger.counts(), "done": len(rows), "todo": len(todo)})

    if todo:
        if workers == 1 or len(todo) == 1:
            w = BatchWorker(setup, model_folder, matcher)
            for t in todo:
                take(w.run(t))
        else:
            ctx = multiprocessing.get_context("spawn")
            with ctx.Pool(
                min(workers, len(todo)),
                initializer=_init_worker,
                initargs=(setup, threads_per_worker),
            ) as pool:
                for row in pool.imap_unordered(_work, todo, chunksize=1):
                    take(row)
    ledger.flush()
    return BatchSummary(
        ledger.counts(), len(rows), skipped, len(todo), time.perf_counter() - t0, rows
    )


# ---------------------------------------------------------------------------------- exports


def export_rows(
    out_dir,
    rows: Sequence[Dict[str, Any]],
    formats: Sequence[str],
    verdicts: Sequence[str] = ("ok", "uncertain"),
) -> Dict[str, List[str]]:
    """Write the estimated poses of ``rows`` in each of ``formats`` under ``out_dir/exports``.

    Only the rows with a verdict in ``verdicts`` are written; ``formats`` are among
    ``io.export.FORMATS``.

    Returns:
        Format -> the files written.

    Raises:
        ProblemError: an unknown format (naming ``output.export``), or a writer's error.
    """
    from ..io.export import FORMATS, NamedPose, export_poses

    bad = [f for f in formats if f not in FORMATS]
    if bad:
        raise ProblemError(f"output.export: unknown format(s) {bad}; choose from {sorted(FORMATS)}")
    poses = [
        NamedPose(r["name"], np.asarray(r["c2w"]), Intrinsics(**r["intrinsics"]))
        for r in rows
        if r.get("c2w") is not None and r.get("status") in verdicts and r.get("intrinsics")
    ]
    out: Dict[str, List[str]] = {}
    if not poses:
        logger.warning("no pose with a verdict in %s to export", list(verdicts))
        return out
    base = Path(out_dir) / "exports"
    base.mkdir(parents=True, exist_ok=True)
    errors = []
    for f in formats:
        # COLMAP: <exports>/colmap/sparse/0, so that <exports>/colmap/images makes a dataset folder
        target = base / "colmap" / "sparse" / "0" if f == "colmap" else base / FORMATS[f]
        try:
            out[f] = [str(p) for p in export_poses(target, poses, f)]
        except ValueError as e:
            errors.append(f"{f}: {e}")
    if errors:
        raise ProblemError("output.export: " + "; ".join(errors))
    return out
