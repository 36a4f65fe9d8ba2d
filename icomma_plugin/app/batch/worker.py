"""Running a batch: one worker per process, each with its own Localizer.

    setup = WorkerSetup(model_path=..., method=RobustConfig(), matcher={"_target_": ...}, ...)
    ledger = PosesLedger(out_dir, run=run_identity("batch", data, ...), total=len(plan.tasks))
    summary = run_batch(plan, setup, ledger, workers=2)

Each worker loads the model once and builds a :class:`~icomma_plugin.localization.localizer.
Localizer`, which keeps the candidate views per camera (and on disk) for every photo; a photo
whose own camera is among the model's cameras (same pose as its known truth) has that camera
left out, as a benchmark must. A photo that cannot be read, has the wrong size or no start pose
becomes a ``failed`` row whose ``error`` says why; the batch goes on.
"""

from __future__ import annotations

import contextlib
import json
import logging
import multiprocessing
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, List, Optional, Tuple

import numpy as np
import torch

from ...localization.localizer import Localizer, source_photos
from ...localization.types import LocalizationResult, Query
from ...matchers import matcher_from_config
from ...io.atomic import write_json_atomic
from ...pose.convert import cameras_extent
from ..focal import CAMERA_FOCAL_KEY, BatchFocalConfig, photo_focal_scale
from ..inputs import LensDistortion, ProblemError
from ..lens import (CAMERA_CENTRE_KEY, CAMERA_DISTORTION_KEY, LensConfig, centre_evidence,
                    centre_reading, principal_point_given)
from ..ledger import PosesLedger
from ..problem import Problem, read_query_image
from .planning import BatchPlan, PhotoTask
from .records import failure_row, result_row, safe_name

logger = logging.getLogger(__name__)

__all__ = ["BatchSummary", "BatchWorker", "WorkerSetup", "run_batch"]


@dataclass
class WorkerSetup:
    """Everything a worker process needs (picklable).

    method: RobustConfig or LocalizerConfig. matcher: the matcher group mapping. out_dir: the
    batch's output folder. folders: write each photo's folder of pictures (``photos/<name>/``)
    with ``output`` (an OutputOptions). thumbs: write ``thumbs/<name>.png`` for the contact
    sheet. config: the composed config, stored in each result.json. seed: torch / numpy seed of
    every photo (``seed + index``), so results do not depend on the worker a photo lands on.
    cache_dir: the Localizer's candidate cache (None: the default folder; False: none).
    photos: ``auto`` (the model's source photos as anchors, when found) or ``none``.
    verdict: the Localizer's verdict thresholds (``auto``: the model's calibration, when any).
    lod: the Localizer's level of detail (``auto``, ``off`` or ``LodConfig`` fields).
    distortion: the photo files' lens distortion (``inputs.LensDistortion``, removed before a
        photo is localized), or None.
    principal_point: the model's fit's principal point (``data.principal_point``: auto, dataset
        or centre; ``ModelFolder.with_principal_point``), for its source photos.
    dataset: the model's source dataset on this machine (``data.query.dataset``), where its
        photos are read from instead of cfg_args ``source_path``; None: cfg_args'.
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
    cache_dir: Any = None
    photos: str = "auto"
    verdict: Any = "auto"
    lod: Any = "auto"
    distortion: Any = None
    principal_point: Optional[str] = None
    dataset: Optional[str] = None


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
        from ...io.model_folder import load_model_folder

        self.setup = setup
        self.mf = model_folder if model_folder is not None else load_model_folder(
            setup.model_path, setup.iteration).with_principal_point(setup.principal_point)
        matcher = matcher if matcher is not None else matcher_from_config(setup.matcher)
        self.localizer = Localizer.from_model_folder(
            self.mf, matcher, setup.method, white_background=setup.white_background,
            backend=setup.backend, cache_dir=setup.cache_dir,
            photos=source_photos(self.mf, setup.white_background, setup.dataset)
            if setup.photos == "auto" else None, verdict=setup.verdict, lod=setup.lod)
        self.model, self.bg = self.localizer.model, self.localizer.background
        self.cameras = list(self.mf.cameras or [])
        self.scene_scale = cameras_extent([e.c2w for e in self.cameras]) if self.cameras else None
        self.out_dir = Path(setup.out_dir)

    def load_query(self, task: PhotoTask) -> Query:
        """The photo of ``task`` as a query, resized to the setup's ``resize``.

        Raises:
            ProblemError: the photo's size is not the one its intrinsics were planned for.
        """
        bg = self.bg.cpu().float()
        if task.view is not None:
            q = Query.from_view(task.view, bg)
            q = Query(q.rgb, q.intrinsics, q.alpha, q.valid, task.name)
        else:
            rgb, alpha = read_query_image(task.path, bg)
            W, H = int(rgb.shape[2]), int(rgb.shape[1])
            if (W, H) != (task.intrinsics.width, task.intrinsics.height):
                raise ProblemError(
                    f"the photo {task.path} is {W}x{H}, not the {task.intrinsics.width}x"
                    f"{task.intrinsics.height} its intrinsics were planned for"
                )
            valid = None
            lens = self.setup.distortion
            if lens is None and task.distortion is not None:  # adopted from the photos
                lens = LensDistortion(tuple(task.distortion))
            if lens is not None:
                rgb, alpha, valid = lens.undistort(rgb, alpha, task.intrinsics)
            q = Query(rgb, task.intrinsics, alpha, valid, task.name)
        return q.resized(self.setup.resize)

    def problem(self, task: PhotoTask, query: Query) -> Problem:
        """The localization problem of ``task``: this worker's model, the query, its poses."""
        return Problem(
            model=self.model, query=query, init_c2w=task.init_c2w, gt_c2w=task.gt_c2w,
            bg=self.bg, scene_scale=self.scene_scale, cameras=self.cameras,
            info={"model_path": self.setup.model_path, "iteration": self.mf.iteration,
                  "num_gaussians": self.model.num_gaussians, "batch_index": task.index},
        )

    def localize(self, problem: Problem, init_c2w: Optional[np.ndarray], progress=None
                 ) -> LocalizationResult:
        """Localize ``problem`` from ``init_c2w`` (None: no start pose)."""
        return self.localizer.localize(problem.query, init_c2w, problem.gt_c2w, progress)

    def write_pictures(self, problem: Problem, result: LocalizationResult, seconds: float
                       ) -> Tuple[Optional[str], Optional[str]]:
        """The photo's folder (when asked) and its thumbnail; (folder, thumb) relative paths."""
        from ..output import write_outputs

        folder = thumb = None
        safe = safe_name(problem.name)
        if self.setup.folders:
            folder = f"photos/{safe}"
            write_outputs(self.out_dir / folder, problem, result, matcher=self.localizer.matcher,
                          options=self.setup.output, backend=self.setup.backend,
                          config=self.setup.config, seconds_total=seconds)
        if self.setup.thumbs:
            try:
                from ...pictures import save_thumbnail

                rel = f"thumbs/{safe}.png"
                save_thumbnail(self.out_dir / rel, self.model, problem.query, result.c2w,
                               problem.bg, self.setup.thumb_side, backend=self.setup.backend)
                thumb = rel
            except Exception as e:  # noqa: BLE001 - a picture never fails a photo
                logger.warning("no thumbnail for %s: %s: %s", problem.name, type(e).__name__, e)
        return folder, thumb

    def run(self, task: PhotoTask) -> Dict[str, Any]:
        """Localize one photo; always returns a row (a failed one for bad input or a crash)."""
        t0 = time.perf_counter()
        if task.error:
            return _camera_of(failure_row(task, f"bad input: {task.error}", task.error), task)
        try:
            with _seeded(None if self.setup.seed is None else self.setup.seed + task.index):
                problem = self.problem(task, self.load_query(task))
                result = self.localize(problem, task.init_c2w)
            folder, thumb = self.write_pictures(problem, result, time.perf_counter() - t0)
            row = result_row(task, result, self.scene_scale, time.perf_counter() - t0, folder,
                             thumb)
            row["own_camera_left_out"] = len(self.localizer.own_cameras(task.gt_c2w, task.name))
        except (ValueError, FileNotFoundError) as e:
            msg = str(e).splitlines()[0] if str(e) else type(e).__name__
            row = failure_row(task, f"bad input: {msg}", msg, time.perf_counter() - t0)
        except Exception as e:  # noqa: BLE001 - one photo must not stop the batch
            logger.exception("photo %s failed", task.name)
            msg = f"internal error: {type(e).__name__}: {e}"
            row = failure_row(task, msg, msg, time.perf_counter() - t0)
        return _camera_of(row, task)


def _camera_of(row: Dict[str, Any], task: PhotoTask) -> Dict[str, Any]:
    """``row`` with the camera its photo was localized with.

    The focal length's share of the given one, and the adopted lens distortion and principal
    point when there are.
    """
    row[CAMERA_FOCAL_KEY] = task.focal_scale
    if task.distortion is not None:
        row[CAMERA_DISTORTION_KEY] = [float(v) for v in task.distortion]
    if task.centre is not None and task.intrinsics is not None:
        row[CAMERA_CENTRE_KEY] = [float(task.intrinsics.cx), float(task.intrinsics.cy)]
    return row


# ---------------------------------------------------------------------------------- processes

_WORKER: Optional[BatchWorker] = None


def _init_worker(setup: WorkerSetup, threads: int) -> None:
    """Initializer of a worker process (started by :func:`run_batch`).

    Its own thread count, its own model, matcher and Localizer.
    """
    global _WORKER
    torch.set_num_threads(max(1, int(threads)))
    _WORKER = BatchWorker(setup)


def _work(task: PhotoTask) -> Dict[str, Any]:
    assert _WORKER is not None, "worker not initialised"
    return _WORKER.run(task)


@dataclass
class BatchSummary:
    """What a :func:`run_batch` call did.

    ``done_now``: the photos it localized, each counted once (also when localized again with an
    adopted focal length: ``redone``); ``photos_per_minute`` counts them.
    """

    counts: Dict[str, int]
    done_now: int
    skipped: int
    todo: int
    seconds: float
    rows: List[Dict[str, Any]]
    focal_scale: float = 1.0  # the batch's focal length at the end, a share of the given one
    focal_adoptions: int = 0  # times this call adopted a focal length from the photos
    redone: int = 0  # photos localized again with an adopted focal length
    focal_passes: List[Dict[str, Any]] = field(default_factory=list)  # poses.focal.json's passes
    distortion: Optional[List[float]] = None  # k1, k2, p1, p2 adopted from the photos
    distortion_adoptions: int = 0  # times this call adopted them
    principal_point: Optional[List[float]] = None  # [cx, cy] adopted (the first photo's pixels)
    centre_evidence: Optional[Dict[str, Any]] = None  # the photos' principal point (lens.py)

    @property
    def photos_per_minute(self) -> Optional[float]:
        """Photos localized per minute of this call; None when it localized none."""
        return (
            None if self.done_now == 0 or self.seconds <= 0 else 60.0 * self.done_now / self.seconds
        )


def _same_lens(row: Dict[str, Any], k: Optional[Tuple[float, ...]]) -> bool:
    """Whether ``row``'s photo was undistorted with the adopted coefficients ``k`` (None: none)."""
    used = row.get(CAMERA_DISTORTION_KEY)
    if used is None or k is None:
        return used is None and k is None
    return all(abs(float(a) - float(b)) < 1e-12 for a, b in zip(used, k))


def _same_centre(row: Dict[str, Any], task: PhotoTask) -> bool:
    """Whether ``row``'s photo was localized with the principal point ``task`` adopted (or none)."""
    used = row.get(CAMERA_CENTRE_KEY)
    if task.intrinsics is None:  # a photo planned as failed: no camera
        return True
    if used is None or task.centre is None:
        return used is None and task.centre is None
    return all(abs(float(a) - float(b)) < 1e-6
               for a, b in zip(used, (task.intrinsics.cx, task.intrinsics.cy)))


def _todo(mine: List[PhotoTask], ledger: PosesLedger, retry_failed: bool, scale: float,
          lens: Optional[Tuple[float, ...]] = None, centre: Optional[Tuple[float, float]] = None
          ) -> Tuple[List[PhotoTask], int]:
    """(the photos of ``mine`` without a row at this camera, how many have one).

    The camera: the focal ``scale``, the adopted ``lens`` coefficients and principal point
    ``centre`` (``PhotoTask.with_centre``; None: none).
    """
    done = ledger.finished()
    if retry_failed:
        ledger.forget([t.name for t in mine if done.get(t.name, {}).get("status") == "failed"])
        done = ledger.finished()

    def held(t: PhotoTask) -> bool:
        row = done.get(t.name)
        return (row is not None and abs(float(row.get(CAMERA_FOCAL_KEY) or 1.0) - scale) < 1e-9
                and _same_lens(row, lens) and _same_centre(row, t.with_centre(centre)))

    todo = [t for t in mine if not held(t)]
    if len(mine) > len(todo):
        logger.info("resuming: %d of %d photos of this shard already done", len(mine) - len(todo),
                    len(mine))
    return todo, len(mine) - len(todo)


@contextlib.contextmanager
def _executor(setup: WorkerSetup, workers: int, threads_per_worker: int, most: int,
              model_folder, matcher) -> Iterator[Callable[[List[PhotoTask]], Iterator[dict]]]:
    """A function that localizes tasks (rows as they finish), kept for every pass of a batch.

    ``workers`` 1 (or a single photo): this process; more: a pool of at most ``most`` spawned
    processes, started at the first call that needs it.
    """
    held: Dict[str, Any] = {}

    def run(tasks: List[PhotoTask]) -> Iterator[dict]:
        if workers == 1 or (len(tasks) == 1 and "pool" not in held):
            if "worker" not in held:
                held["worker"] = BatchWorker(setup, model_folder, matcher)
            for t in tasks:
                yield held["worker"].run(t)
            return
        if "pool" not in held:
            ctx = multiprocessing.get_context("spawn")
            held["pool"] = ctx.Pool(min(workers, most), initializer=_init_worker,
                                    initargs=(setup, threads_per_worker))
        yield from held["pool"].imap_unordered(_work, tasks, chunksize=1)

    try:
        yield run
    finally:
        if "pool" in held:
            held["pool"].terminate()
            held["pool"].join()


def _focal_state_path(ledger: PosesLedger) -> Path:
    """The batch's adopted focal length (``poses.focal.json``; a shard's beside its part)."""
    j = ledger.journal_path
    return j.with_name(j.stem + ".focal.json")


def _read_focal_state(path: Path) -> Dict[str, Any]:
    """The camera a batch adopted from its photos (``poses.focal.json``; none yet: the given one).

    ``{"scale", "adoptions", "passes", "distortion", "distortion_adoptions", "centre"}``
    (``centre``: the principal point's move from the image centre, in focal lengths, or None).
    """
    try:
        state = json.loads(path.read_text())
        k, c = state.get("distortion"), state.get("centre")
        return {"scale": float(state["scale"]), "adoptions": int(state["adoptions"]),
                "passes": list(state.get("passes") or []),
                "distortion": None if k is None else [float(v) for v in k],
                "distortion_adoptions": int(state.get("distortion_adoptions") or 0),
                "centre": None if c is None else [float(v) for v in c]}
    except FileNotFoundError:
        return _given_camera()
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ProblemError(f"cannot read the batch's focal length {path} ({e}); move it away to "
                           "decide it again") from None


def _given_camera() -> Dict[str, Any]:
    """The camera state of a batch that adopted nothing from its photos."""
    return {"scale": 1.0, "adoptions": 0, "passes": [], "distortion": None,
            "distortion_adoptions": 0, "centre": None}


def _as_camera(task: PhotoTask, scale: float, lens: Optional[Tuple[float, ...]],
               centre: Optional[Tuple[float, float]], again: Optional[Dict[str, Any]]
               ) -> PhotoTask:
    """``task`` with the batch's camera.

    A photo localized again (``again``: its last row) starts from its last pose.
    """
    if scale == 1.0 and lens is None and centre is None and again is None:
        return task
    return replace(task.with_focal_scale(scale, _start_of(again, task)),
                   distortion=lens).with_centre(centre)


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
    focal: Optional[BatchFocalConfig] = None,
    lens: Optional[LensConfig] = None,
) -> BatchSummary:
    """Localize this shard's unfinished photos of ``plan``, recording each in ``ledger``.

    Args:
        plan: from ``planning.plan_batch``.
        setup: what each worker loads (from the tool's config).
        ledger: the output folder's record; photos it already holds are skipped.
        workers: 1 runs in this process (threads as the caller set them); more start that many
            worker processes (spawned), each with ``threads_per_worker`` torch threads (set in
            those processes only) and its own model and Localizer.
        threads_per_worker: torch threads of each worker process.
        retry_failed: redo photos recorded as failed.
        progress: called after each photo with ``{"row", "counts", "done", "todo"}``, and with
            ``row`` None when a pass starts (``todo``: its photos; ``focal_scale``).
        model_folder: reuse the caller's loaded model folder (``workers == 1`` only).
        matcher: reuse the caller's matcher (``workers == 1`` only).
        focal: the focal length from the photos (``focal.BatchFocalConfig``; None: off). Used
            for photo files given one camera; a dataset folder's views keep their own. The
            adopted one is kept in ``poses.focal.json`` for a resumed run.
        lens: the lens distortion from the photos (``lens.LensConfig``; None: off). For
            photo files given one camera and no distortion; decided before the focal length
            after each pass, kept in ``poses.focal.json`` too. Photos given no principal point
            have it adopted from their refits with the lens (``LensConfig.adopt_centre``).
    """
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers must be a positive int, got {workers!r}")
    mine = [t for t in plan.tasks if t.index % ledger.num_shards == ledger.shard]
    own_camera = bool(mine) and all(t.view is None for t in mine)  # files given one camera
    pool_focal = own_camera and focal is not None and focal.focal_from_photos
    pool_lens = (own_camera and lens is not None and lens.estimate
                 and setup.distortion is None)
    # no principal point given: the refits measure it with k1, k2 (the tangential terms would
    # stand for it), and it is adopted with them
    pool_centre = pool_lens and not all(principal_point_given(t.intrinsics) for t in mine
                                        if t.intrinsics is not None)
    pooling = pool_focal or pool_lens
    state_path = _focal_state_path(ledger)
    state = _read_focal_state(state_path) if pooling else _given_camera()
    t0 = time.perf_counter()
    rows: List[Dict[str, Any]] = []
    redone: set = set()
    skipped = None
    with _executor(setup, workers, threads_per_worker, len(mine), model_folder,
                   matcher) as localize:
        adopted_now = lens_now = 0
        evidence = None
        while True:
            scale, k, c = state["scale"], state["distortion"], state["centre"]
            k = None if k is None else tuple(float(v) for v in k)
            c = None if c is None or not pool_centre else tuple(float(v) for v in c)
            todo, held = _todo(mine, ledger, retry_failed and skipped is None, scale, k, c)
            skipped = held if skipped is None else skipped
            done = ledger.finished()
            # a photo localized again with a new camera starts from its last pose
            tasks = [_as_camera(t, scale, k, c, done.get(t.name)) for t in todo]
            if progress is not None:
                progress({"row": None, "counts": ledger.counts(), "done": 0, "todo": len(tasks),
                          "skipped": held, "focal_scale": scale})
            n = 0
            for row in localize(tasks):
                ledger.record(row)
                rows.append(row)
                n += 1
                if row["name"] in done:
                    redone.add(row["name"])
                if progress is not None:
                    progress({"row": row, "counts": ledger.counts(), "done": n,
                              "todo": len(tasks)})
            if not pooling:
                break
            finished = ledger.finished()
            now = [finished[t.name] for t in mine if t.name in finished]
            # the lens first: a distortion left in the photos pulls their focal refits
            new_k = None if not pool_lens or state["distortion_adoptions"] >= lens.rounds \
                else lens.adopt(now, state["distortion"])
            new_c = None
            if pool_centre and state["centre"] is None:
                measured = centre_evidence(now)
                evidence = measured or evidence
                new_c = lens.centre_agreed(measured)
            if new_c is not None:
                cx, cy = _centre_px(mine, new_c)
                logger.info("the photos' refits (%d) agree on a principal point (%.2f, %.2f) "
                            "px, %.2f px from the image centre at their working size: the batch "
                            "takes it, and localizes them again", evidence["views"], cx, cy,
                            evidence["shift_px"])
                state.update(centre=list(new_c))
            if new_k is not None:
                logger.info("the photos' refits (%d) agree on a lens distortion (k1, k2, p1, p2) "
                            "%s: the batch undistorts them with it, and localizes them again",
                            len(now), ", ".join(f"{v:.5f}" for v in new_k))
                state.update(distortion=list(new_k),
                             distortion_adoptions=state["distortion_adoptions"] + 1)
                lens_now += 1
            if new_c is not None or new_k is not None:
                write_json_atomic(state_path, state)
                continue
            new = None if not pool_focal or state["adoptions"] >= focal.focal_rounds \
                else focal.adopt(now, scale, state["adoptions"] > 0)
            if state["adoptions"] or new is not None:  # the record of the passes (focal.png)
                _record_pass(state, scale, now)
            if new is None:
                if state["adoptions"] or state["distortion_adoptions"] or state["centre"]:
                    write_json_atomic(state_path, state)
                break
            logger.info("the photos' refits (%d) agree on a focal length %.4f x the given one "
                        "(%.4f x the one used): the batch takes it, and localizes them again",
                        sum(photo_focal_scale(r) is not None for r in now), new, new / scale)
            state.update(scale=new, adoptions=state["adoptions"] + 1)
            write_json_atomic(state_path, state)
            adopted_now += 1
    ledger.flush()
    latest = list({r["name"]: r for r in rows}.values())  # a photo localized again: its last row
    if _centred_views(mine):
        evidence = _centred_views_reading(ledger, mine, lens)
    return BatchSummary(
        ledger.counts(), len(latest), skipped or 0, len(latest), time.perf_counter() - t0, latest,
        focal_scale=state["scale"], focal_adoptions=adopted_now, redone=len(redone),
        focal_passes=state["passes"], distortion=state["distortion"],
        distortion_adoptions=lens_now,
        principal_point=(None if state["centre"] is None or not pool_centre
                         else list(_centre_px(mine, state["centre"]))),
        centre_evidence=evidence,
    )


def _centred_views(tasks: List[PhotoTask]) -> bool:
    """Whether ``tasks`` are a dataset's views all taken at the image centre."""
    return bool(tasks) and all(t.view is not None and t.intrinsics is not None
                               and not principal_point_given(t.intrinsics) for t in tasks)


def _centred_views_reading(ledger: PosesLedger, tasks: List[PhotoTask],
                           lens: Optional[LensConfig]) -> Optional[Dict[str, Any]]:
    """Where the refits of a dataset's views taken at the image centre put the principal point.

    ``lens.centre_reading`` of their rows (``views_centred`` set); a warning when they agree on
    one off the centre (a dataset whose camera has one, read for a model said to be fitted with
    the image centre: every pose turned and still ``ok``; the views are not localized again).
    """
    finished = ledger.finished()
    ev = centre_reading([finished[t.name] for t in tasks if t.name in finished], lens)
    if ev is None:
        return None
    ev["views_centred"] = True
    if ev["off"]:
        logger.warning(
            "the views were taken at the image centre (their dataset gives none, or the model "
            "is taken as fitted with it: data.principal_point) and their refits agree on a "
            "principal point %.2f px from it (%d%% of %d the same way): if the model was fitted "
            "with the dataset's own, data.principal_point=dataset", ev["shift_px"],
            round(100 * ev["agree"]), ev["views"])
    return ev


def _centre_px(tasks: List[PhotoTask], centre) -> Tuple[float, float]:
    """The principal point ``centre`` (focal lengths from the image centre) in pixels.

    Those of the first photo with intrinsics (the batch's camera: all its photos share it).
    """
    t = next(t for t in tasks if t.intrinsics is not None).with_centre(tuple(centre))
    return float(t.intrinsics.cx), float(t.intrinsics.cy)


def _record_pass(state: Dict[str, Any], scale: float, rows: List[Dict[str, Any]]) -> None:
    """Add (or replace) the pass at focal ``scale`` in ``state["passes"]``: each photo's refit."""
    entry = {"used": scale, "estimates": {r["name"]: photo_focal_scale(r) for r in rows}}
    passes = state["passes"]
    if passes and abs(passes[-1]["used"] - scale) < 1e-12:
        passes[-1] = entry  # the same pass again (a resumed run that finished it)
    else:
        passes.append(entry)


def _start_of(row: Optional[Dict[str, Any]], task: PhotoTask) -> Optional[np.ndarray]:
    """Where a photo starts when localized again: its last pose, or its own start if it failed."""
    if row is None or row.get("status") == "failed" or row.get("c2w") is None:
        return task.init_c2w
    return np.asarray(row["c2w"], np.float64)
