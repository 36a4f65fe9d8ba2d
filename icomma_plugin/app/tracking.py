"""Ordered frames (a video file or a folder of frames) tracked one after the other.

Each frame starts from a constant-velocity prediction: the motion between the last two frames
that did not fail, applied again (``predict_c2w``). The first frame
starts from ``data.init`` (a pose, or none: the candidate views). A frame whose verdict is
``failed`` is localized again from the candidate views (no start pose), and the better of the two
results is kept. Every row is recorded in the ledger after its frame, so a killed run resumes at
the first frame it had not finished, with the same predictions.

One camera films the whole sequence, so its focal length is estimated from the frames together
(``TrackingConfig.focal_from_frames``): each frame's verdict refits its matches with the focal
length free (``signals.focal``), too weakly to be decided on one frame; when the frames since the
last adoption agree that it is off, the sequence adopts their median and the last
``focal_window`` frames are localized again with it (``focal.pooled_focal_scale``).

    source = FrameSource.open("walk.mp4", every=2)
    summary = track(worker, source, ledger, intrinsics_of=..., init_c2w=None)
"""

from __future__ import annotations

import dataclasses
import logging
import queue
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Dict, Iterable, Iterator, List, Optional, Sequence, Tuple

import numpy as np
import torch

from ..camera import Intrinsics
from ..io.poses_file import read_poses_file
from ..localization.types import Query
from ..pose.convert import invert_rigid
from ..pose.se3 import se3_exp, se3_log
from .batch import BatchWorker, PhotoTask, failure_row, result_row
from .focal import CAMERA_FOCAL_KEY, check_pooling, photo_focal_scale, pooled_focal_scale
from .inputs import LensDistortion, ProblemError, list_photos, start_poses
from .lens import (CAMERA_CENTRE_KEY, CAMERA_DISTORTION_KEY, TrackingLensConfig,
                   centre_evidence, moved_centre, photo_distortion, principal_point_given)
from .ledger import PosesLedger
from .problem import warn_if_rotated

logger = logging.getLogger(__name__)

__all__ = [
    "FrameSource",
    "TrackingConfig",
    "TrackingSummary",
    "first_frame_start",
    "predict_c2w",
    "prefetched",
    "sequence_pictures",
    "sequence_truths",
    "track",
    "write_tracking_video",
]

_RANK = {"ok": 2, "uncertain": 1, "failed": 0}


@dataclass
class TrackingConfig:
    """How a sequence is tracked.

    Attributes:
        velocity: predict with constant velocity (else start from the previous pose).
        relocalize: a failed frame is localized again from the candidate views.
        fast: tracking mode: from the prediction, first a cheap localization (``fast_rounds``
            geometric rounds that stop at a step below ``fast_stop_deg``, ``fast_refine``
            refinement steps, matching at ``fast_scale`` of the working resolution, no candidate
            search, renders matched by mutual nearest neighbours of the matcher's descriptors
            above ``fast_mutual_nn`` (None: by the matcher), or first by searching the frame's
            keypoints in the render within ``fast_patch_search`` pixels (NCC above
            ``fast_patch_ncc``, peak margin above ``fast_patch_margin``; None, the default:
            not. 0.8-0.95x the time a frame on the lego paths, but slower on photo collections
            and soft models, where it falls back; docs/SPEED.md),
            ``fast_subpixel_iterations`` Newton iterations of the PnP's sub-pixel step, and
            with no refinement step the
            verdict decided on the geometric stage's last render-and-match:
            ``RobustConfig.verify_geometric``); the full method only when its verdict is not
            ``ok``.
        prefetch: frames decoded ahead in a second thread (0: none).
        look_ahead: that thread also makes each frame's query and the matcher's features of it
            (``Localizer.prepare``) while the frame before is localized (needs ``prefetch``).
        focal_from_frames: estimate the camera's focal length from the frames together: when the
            frames' verdicts refit their matches best with a focal length whose median (over
            the frames since the last adoption, at least ``focal_window`` and at most
            ``focal_history`` of them) is more than ``focal_min_change`` (a share) off the one
            used, and at least ``focal_agree`` of them lie on its side, the sequence takes that
            median and localizes the last ``focal_window`` frames again with it, at most
            ``focal_rounds`` times in a row; once it has adopted one, a median more than
            ``focal_settle`` off suffices (a frame's refit finds most of the error, not all: its
            pose had taken up the rest). Every later frame is localized with the focal length
            adopted (``camera_focal_scale`` in its row, the share of the given one; the row's
            ``intrinsics`` are those its pose holds with). Off: every frame with the given
            intrinsics.
        lens: the camera's lens distortion from the first frames, when none was given
            (``lens.TrackingLensConfig``; ``tracking.lens.estimate``): decided once; adopted,
            those frames are localized again with it (a focal length adopted from them undone)
            and every later frame is undistorted with it (``camera_distortion`` in its row);
            frames given no principal point have theirs adopted with it
            (``camera_principal_point``).
    """

    velocity: bool = True
    relocalize: bool = True
    fast: bool = True
    fast_rounds: int = 3
    fast_stop_deg: float = 0.25
    fast_refine: int = 0
    fast_scale: float = 1.0
    fast_mutual_nn: Optional[float] = 0.82
    fast_patch_search: Optional[int] = None
    fast_patch_ncc: float = 0.8
    fast_patch_margin: Optional[float] = 0.1
    fast_subpixel_iterations: int = 0
    prefetch: int = 4
    look_ahead: bool = True
    focal_from_frames: bool = True
    focal_window: int = 10
    focal_min_change: float = 0.01
    focal_agree: float = 0.8
    focal_rounds: int = 3
    focal_settle: float = 0.005
    focal_history: int = 100
    lens: TrackingLensConfig = field(default_factory=TrackingLensConfig)

    def __post_init__(self):
        from ..checks import check_bool, check_int, check_real

        for name in ("velocity", "relocalize", "fast", "look_ahead", "focal_from_frames"):
            check_bool(getattr(self, name), f"tracking.{name}")
        check_int(self.fast_rounds, "tracking.fast_rounds", 1)
        check_real(self.fast_stop_deg, "tracking.fast_stop_deg", 0.0, lo_open=True)
        check_int(self.fast_refine, "tracking.fast_refine", 0)
        check_real(self.fast_scale, "tracking.fast_scale", 0.0, 1.0, lo_open=True)
        check_real(self.fast_mutual_nn, "tracking.fast_mutual_nn", 0.0, 1.0, lo_open=True,
                   hi_open=True, optional=True)
        check_int(self.fast_patch_search, "tracking.fast_patch_search", 1, optional=True)
        check_real(self.fast_patch_ncc, "tracking.fast_patch_ncc", -1.0, 1.0)
        check_real(self.fast_patch_margin, "tracking.fast_patch_margin", 0.0, optional=True)
        check_int(self.fast_subpixel_iterations, "tracking.fast_subpixel_iterations", 0)
        check_int(self.prefetch, "tracking.prefetch", 0)
        check_int(self.focal_window, "tracking.focal_window", 3)
        check_pooling(self, "tracking")
        check_int(self.focal_history, "tracking.focal_history", self.focal_window)

    def fast_method(self, method, side: int, matcher=None):
        """The cheap config of the default ``method`` for the tracking mode (None: not used).

        ``side``: the longer side of the full method's working resolution [px]; ``matcher``: the
        localizer's (mutual nearest neighbours only for one with descriptors).
        """
        from ..localization.robust import RobustConfig

        if not self.fast or not isinstance(method, RobustConfig):
            return None
        features = getattr(matcher, "supports_features", False)
        return dataclasses.replace(
            method,
            work_side=max(16, int(round(side * self.fast_scale))),
            use_candidates=False,
            verify_geometric=True,
            lens_check=False,
            mutual_nn=self.fast_mutual_nn if features else None,
            patch_search=self.fast_patch_search if features else None,
            patch_search_ncc=self.fast_patch_ncc,
            patch_search_margin=self.fast_patch_margin,
            geometric=dataclasses.replace(method.geometric, max_rounds=self.fast_rounds,
                                          subpixel_iterations=self.fast_subpixel_iterations,
                                          stop_rot_deg=self.fast_stop_deg,
                                          stop_trans_rel=self.fast_stop_deg * 0.02),
            refine=dataclasses.replace(method.refine, scales=(1.0,), blur=(0.0,),
                                       iterations=(self.fast_refine,)),
        )


def predict_c2w(
    history: Sequence[Tuple[int, np.ndarray]], index: int, velocity: bool = True
) -> Optional[np.ndarray]:
    """Start pose (c2w) of frame ``index``, or None.

    From the ``(frame index, c2w)`` of earlier frames that did not fail, oldest first: constant
    velocity from the last two (the motion between them, as a twist per frame, applied again:
    ``c2w_k = c2w_j @ exp((k - j) xi)`` with ``xi = log(inv(c2w_i) @ c2w_j) / (j - i)``), or the
    last one alone.
    """
    if not history:
        return None
    j, Cj = history[-1]
    Cj = np.asarray(Cj, np.float64)
    if not velocity or len(history) < 2:
        return Cj.copy()
    i, Ci = history[-2]
    if j <= i or index <= j:
        return Cj.copy()
    # the camera-frame motion from frame i to frame j, per frame
    delta = torch.as_tensor(invert_rigid(Ci) @ Cj, dtype=torch.float64)
    xi = se3_log(delta) / float(j - i)
    out = Cj @ se3_exp(xi * float(index - j)).numpy()
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


@dataclass
class FrameSource:
    """The frames of a video file or of an ordered folder (natural order of the file names).

    Frames are ``(index, name, [H, W, 3] uint8 RGB)``; ``index`` counts the source's frames (a
    video's frame number, a folder's position), so ``every`` leaves gaps the prediction spans.
    """

    spec: str
    every: int = 1
    limit: Optional[int] = None
    paths: Optional[List[Path]] = None  # a folder's frames
    names: Optional[List[str]] = None

    @classmethod
    def open(
        cls, spec, every: int = 1, limit: Optional[int] = None, what: str = "data.sequence"
    ) -> "FrameSource":
        """The frames of ``spec``: a video file or a folder of images.

        Every ``every``-th frame, at most ``limit``.

        Raises:
            ProblemError: ``spec`` is missing, unreadable or has no frames (naming ``what``).
        """
        from ..io.video import VIDEO_SUFFIXES, VideoError, video_info

        if spec is None or not str(spec).strip():
            raise ProblemError(f"{what} is empty: give a video file or a folder of frames")
        p = Path(str(spec)).expanduser()
        if p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES:
            try:
                video_info(p)
            except VideoError as e:
                raise ProblemError(f"{what}: {e}") from None
            return cls(str(p), every, limit)
        if p.is_file():
            raise ProblemError(
                f"{what}: {p} is not a video file ({', '.join(VIDEO_SUFFIXES)}) or a folder"
            )
        photos = list_photos(str(spec), what)
        return cls(str(p), every, limit, list(photos.paths), list(photos.names))

    @property
    def is_video(self) -> bool:
        """Whether the frames come from a video file (else from a folder)."""
        return self.paths is None

    def __iter__(self) -> Iterator[Tuple[int, str, np.ndarray]]:
        if self.is_video:
            from ..io.video import read_video_frames

            for i, rgb in read_video_frames(self.spec, every=self.every, limit=self.limit):
                yield i, f"frame_{i:06d}", rgb
            return
        from ..io.datasets import read_image_file

        idx = list(range(0, len(self.paths), self.every))
        if self.limit:
            idx = idx[: self.limit]
        for i in idx:
            warn_if_rotated(self.paths[i])
            img = read_image_file(self.paths[i])
            yield i, self.names[i], (np.clip(img[:, :, :3], 0, 1) * 255 + 0.5).astype(np.uint8)

    def count(self) -> Optional[int]:
        """Frames this source yields (a video's count is the container's, may be approximate)."""
        if self.is_video:
            from ..io.video import video_info

            n = video_info(self.spec)[2]
            if not n:
                return None
        else:
            n = len(self.paths)
        k = (n + self.every - 1) // self.every
        return min(k, self.limit) if self.limit else k


@dataclass
class TrackingSummary:
    """What a tracking call did: counts by verdict, frames done, skipped and relocalized."""

    counts: Dict[str, int]
    done_now: int
    skipped: int
    seconds: float
    relocalized: int
    rows: List[Dict[str, Any]] = field(default_factory=list)
    fast_ok: int = 0  # frames the tracking mode's cheap localization settled alone
    focal_scale: float = 1.0  # the sequence's focal length at the end, a share of the given one
    focal_adoptions: int = 0  # times this call adopted a focal length from its frames
    redone: int = 0  # frames localized again with an adopted focal length or lens
    distortion: Optional[List[float]] = None  # k1, k2, p1, p2 adopted from the frames
    distortion_adoptions: int = 0  # times this call adopted them
    principal_point: Optional[List[float]] = None  # [cx, cy] adopted from the frames [px]
    centre_evidence: Optional[Dict[str, Any]] = None  # the window's principal point (lens.py)

    @property
    def frames_per_second(self) -> Optional[float]:
        """Frames tracked per second of this call; None when it tracked none."""
        return None if self.done_now == 0 or self.seconds <= 0 else self.done_now / self.seconds


def prefetched(frames: Iterable, ahead: int, prepare: Optional[Callable[[Any], Any]] = None
               ) -> Iterator:
    """``frames``, decoded up to ``ahead`` items in advance in a second thread (0: as they are).

    Decoding (OpenCV, PIL) runs outside the GIL, beside the localization of the previous frame;
    so does ``prepare`` (item -> item) when given. An error of the reader is raised where the
    frame would have been.
    """
    if ahead <= 0:
        yield from frames if prepare is None else map(prepare, frames)
        return
    q: "queue.Queue" = queue.Queue(maxsize=ahead)
    done = object()
    stop = threading.Event()

    def read():
        try:
            for item in frames:
                if prepare is not None and not stop.is_set():
                    item = prepare(item)
                while not stop.is_set():
                    try:
                        q.put(("item", item), timeout=0.1)
                        break
                    except queue.Full:
                        continue
                if stop.is_set():
                    return
            q.put(("end", done))
        except BaseException as e:  # noqa: BLE001 - handed to the consumer
            q.put(("error", e))

    t = threading.Thread(target=read, name="frame-prefetch", daemon=True)
    t.start()
    try:
        while True:
            kind, item = q.get()
            if kind == "end":
                return
            if kind == "error":
                raise item
            yield item
    finally:
        stop.set()


def _query(rgb: np.ndarray, intr: Intrinsics, name: str, resize: Optional[int],
           distortion=None) -> Query:
    """A frame (``[H, W, 3]`` uint8) as a query: undistorted (``LensDistortion``), resized."""
    t = torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1).float() / 255.0
    valid = None
    if distortion is not None:
        t, _, valid = distortion.undistort(t, None, intr)
    return Query(t.contiguous(), intr, None, valid, name).resized(resize)


@dataclass
class _Held:
    """A frame of the focal length's (or the lens's) window: kept to be localized again."""

    index: int
    name: str
    rgb: np.ndarray
    row: Dict[str, Any]


class _Tracker:
    """One tracking run: the history of good poses, and each frame localized from it."""

    def __init__(self, worker: BatchWorker, source: FrameSource, ledger: PosesLedger,
                 intrinsics_of, init_c2w, gt_of, cfg: TrackingConfig):
        self.worker, self.source, self.ledger = worker, source, ledger
        self.intrinsics_of, self.init_c2w = intrinsics_of, init_c2w
        self.gt_of, self.cfg = gt_of, cfg
        self.done = ledger.finished()
        done = sorted(self.done.values(), key=lambda r: r.get("index", 0))
        self.history: List[Tuple[int, np.ndarray]] = [
            (int(r["index"]), np.asarray(r["c2w"], np.float64))
            for r in done if r.get("status") != "failed" and r.get("c2w") is not None
        ]
        # the sequence's focal length as a share of the given one (a resumed run: its last row's)
        scales = [r[CAMERA_FOCAL_KEY] for r in done if r.get(CAMERA_FOCAL_KEY)]
        self.focal_scale = float(scales[-1]) if scales and cfg.focal_from_frames else 1.0
        self.window: deque = deque(maxlen=cfg.focal_window)  # of _Held
        # the frames' focal scales since the last adoption (the next one is decided on them)
        self.since: deque = deque(maxlen=cfg.focal_history)
        self.focal_adoptions = 0
        # the lens (a resumed run: its last row's), decided once on the first frames
        lenses = [r[CAMERA_DISTORTION_KEY] for r in done if r.get(CAMERA_DISTORTION_KEY)]
        given = worker.setup.distortion is not None
        self.lens = tuple(float(v) for v in lenses[-1]) if lenses and not given else None
        self.lens_open = cfg.lens.estimate and not given and len(done) < cfg.lens.min_views
        self.lens_window: List[_Held] = []
        self.lens_adoptions = 0
        self.focal_before_lens = self.focal_scale  # what an adopted lens goes back to
        # the principal point adopted with the lens when none was given ([cx, cy] of the frames)
        centres = [r[CAMERA_CENTRE_KEY] for r in done if r.get(CAMERA_CENTRE_KEY)]
        self.centre_px = tuple(float(v) for v in centres[-1]) if centres else None
        self.centre_evidence: Optional[Dict[str, Any]] = None  # what the window's refits said
        self.redone = 0
        self.relocalized = 0
        self.fast_settled: set = set()  # names of the frames the cheap localization settled

    def _fast_method(self, query: Query):
        """The tracking mode's cheap config for ``query`` (None: not used)."""
        loc = self.worker.localizer
        side = loc.method.work_side or loc.model_side or max(query.size)
        fast = self.cfg.fast_method(loc.method, min(side, max(query.size)), loc.matcher)
        if fast is not None and self.lens_open:  # its refits decide the lens: sub-pixel ones
            fast = dataclasses.replace(fast, lens_check=True, geometric=dataclasses.replace(
                fast.geometric, subpixel_iterations=loc.method.geometric.subpixel_iterations))
        return fast

    def _intrinsics(self, rgb: np.ndarray) -> Intrinsics:
        """A frame's intrinsics: the given ones, with the sequence's focal length.

        And with its principal point, when one was adopted from the frames.
        """
        given = self.intrinsics_of((int(rgb.shape[1]), int(rgb.shape[0])))
        if self.centre_px is not None:
            given = dataclasses.replace(given, cx=self.centre_px[0], cy=self.centre_px[1])
        return given.with_focal_scale(self.focal_scale)

    def _distortion(self):
        """The lens the frames are undistorted with: the given one, or the adopted one, or None."""
        if self.lens is not None:
            return LensDistortion(self.lens)
        return self.worker.setup.distortion

    def _query(self, name: str, rgb: np.ndarray) -> Tuple[Intrinsics, Query]:
        intr = self._intrinsics(rgb)
        return intr, _query(rgb, intr, name, self.worker.setup.resize, self._distortion())

    def ahead(self, item: Tuple[int, str, np.ndarray]) -> Tuple[int, str, np.ndarray, Any]:
        """``(index, name, rgb)`` -> ``(index, name, rgb, (intrinsics, query) or None)``.

        In the prefetch thread: the frame's query with the matcher's features of it made ahead
        (``Localizer.prepare``), and the lens it was undistorted with. None for a frame already
        done, or a bad one (``frame`` reports it).
        """
        index, name, rgb = item
        if name in self.done:
            return index, name, rgb, None
        try:
            lens = self.lens
            intr, query = self._query(name, rgb)
            fast = self._fast_method(query)
            self.worker.localizer.prepare(query, fast)
            return index, name, rgb, (intr, query, lens)
        except Exception:  # noqa: BLE001 - the frame itself meets the error again and reports it
            return index, name, rgb, None

    def _localize(self, problem, start: Optional[np.ndarray]):
        """The frame's result from ``start``; a failed one relocalized from the candidates.

        In the tracking mode a cheap localization first; the full one when it is not ``ok``.
        """
        worker = self.worker
        result = None
        loc = worker.localizer
        fast = self._fast_method(problem.query)
        self.fast_settled.discard(problem.query.name)
        if fast is not None and start is not None:
            result = loc.localize(problem.query, start, problem.gt_c2w, method=fast)
            if result.verdict.status == "ok":
                self.fast_settled.add(problem.query.name)
        if result is None or result.verdict.status != "ok":
            result = worker.localize(problem, start)
        if (result.verdict.status == "failed" and start is not None and self.cfg.relocalize
                and not worker.localizer.method.needs_start):
            again = worker.localize(problem, None)
            if _RANK[again.verdict.status] > _RANK["failed"]:
                self.relocalized += 1
                return again, True
        return result, False

    def frame(self, index: int, name: str, rgb: np.ndarray, prepared=None,
              start: Optional[np.ndarray] = None) -> Dict[str, Any]:
        """Localize one frame and return its row (a failed row for bad input).

        ``prepared``: ``(intrinsics, query, lens)`` of the frame made ahead (``ahead``), or None.
        ``start``: the start pose (None: predicted from the history).
        """
        worker = self.worker
        t_frame = time.perf_counter()
        if start is None:
            start = predict_c2w(self.history, index, self.cfg.velocity)
            start = self.init_c2w if start is None else start
        gt = self.gt_of(name) if self.gt_of is not None else None
        path = self.source.spec if self.source.is_video else str(self.source.paths[index])
        task = PhotoTask(index, name, path, None, None, start, gt)
        try:
            if prepared is not None and (prepared[0] != self._intrinsics(rgb)
                                         or prepared[2] != self.lens):
                prepared = None  # made ahead before the sequence's camera changed
            task.intrinsics, query = prepared[:2] if prepared else self._query(name, rgb)
            problem = worker.problem(task, query)
            result, again = self._localize(problem, start)
            folder, thumb = worker.write_pictures(problem, result, time.perf_counter() - t_frame)
            row = result_row(task, result, worker.scene_scale, time.perf_counter() - t_frame,
                             folder, thumb)
            row["relocalized"] = again
            row["predicted_c2w"] = None if start is None else np.asarray(start).tolist()
        except (ValueError, FileNotFoundError) as e:
            msg = str(e).splitlines()[0] if str(e) else type(e).__name__
            row = failure_row(task, f"bad input: {msg}", msg, time.perf_counter() - t_frame)
        row[CAMERA_FOCAL_KEY] = self.focal_scale
        if self.lens is not None:
            row[CAMERA_DISTORTION_KEY] = list(self.lens)
        if self.centre_px is not None:
            row[CAMERA_CENTRE_KEY] = list(self.centre_px)
        again = bool(self.history) and self.history[-1][0] >= index
        if again:  # a frame localized again (``settle_focal``): its new pose replaces the old
            self.history = [h for h in self.history if h[0] != index]
        if row["status"] != "failed" and row["c2w"] is not None:
            self.history.append((index, np.asarray(row["c2w"], np.float64)))
            if again:
                self.history.sort(key=lambda h: h[0])
        return row

    def settle_lens(self, index: int, name: str, rgb: np.ndarray, row: Dict[str, Any]
                    ) -> List[Dict[str, Any]]:
        """Add a frame to the lens's first window; the rows of the frames localized again.

        Once ``lens.min_views`` frames are in, the lens their refits agree on
        (``LensConfig.adopt``) is adopted and they are localized again with it from their own
        poses, at most ``lens.rounds`` times; then the lens is decided for the sequence (the
        focal length's window starts again, on undistorted frames). Frames given no principal
        point have the one their refits agree on adopted with it (``LensConfig.adopt_centre``).
        """
        cfg = self.cfg.lens
        if not self.lens_open:
            return []
        if photo_distortion(row) is None and row.get("c2w") is not None:
            self.lens_open = False  # a method without the lens check: nothing to decide on
            self.lens_window = []
            return []
        self.lens_window.append(_Held(index, name, rgb, row))
        if len(self.lens_window) < cfg.min_views:
            return []
        given = self.intrinsics_of((int(rgb.shape[1]), int(rgb.shape[0])))
        self.centre_evidence = centre_evidence([h.row for h in self.lens_window])
        redone: Dict[str, Dict[str, Any]] = {}
        for round_ in range(cfg.rounds):
            rows = [h.row for h in self.lens_window]
            new = cfg.adopt(rows, self.lens)
            new_c = None
            if not principal_point_given(given) and self.centre_px is None:
                # the first round's rows are those measured above; later rounds' were redone
                ev = self.centre_evidence if round_ == 0 else centre_evidence(rows)
                new_c = cfg.centre_agreed(ev)
            if new is None and new_c is None:
                break
            if new_c is not None:
                moved = moved_centre(given, new_c)
                self.centre_px = (moved.cx, moved.cy)
                logger.info("%d frames agree on a principal point (%.2f, %.2f) px: the sequence "
                            "takes it, and localizes these again", len(rows), *self.centre_px)
            if new is not None:
                logger.info("%d frames agree on a lens distortion (k1, k2, p1, p2) %s: the "
                            "sequence undistorts its frames with it, and localizes these again",
                            len(rows), ", ".join(f"{v:.5f}" for v in new))
                self.lens = new
                self.lens_adoptions += 1
            # a focal length adopted from these distorted frames is undone (it made up for part
            # of the distortion: fox's 1.011); the undistorted frames to come estimate it again
            self.focal_scale = self.focal_before_lens
            for h in self.lens_window:
                if h.row.get("c2w") is None:  # failed when localized again: left as it is
                    continue
                h.row = self.frame(h.index, h.name, h.rgb, start=np.asarray(h.row["c2w"]))
                redone[h.name] = h.row
        self.lens_open = False
        self.lens_window = []
        if redone:  # the focal length's frames were distorted: its estimate starts again
            self.window.clear()
            self.since.clear()
        self.redone += len(redone)
        return list(redone.values())

    def settle_focal(self, index: int, name: str, rgb: np.ndarray, row: Dict[str, Any]
                     ) -> List[Dict[str, Any]]:
        """Add a frame to the focal length's window; the rows of the frames localized again.

        When the frames since the last adoption (at most ``focal_history``) agree that the
        focal length is off (``pooled_focal_scale``), the sequence adopts their median and
        localizes the last ``focal_window`` of them again from their own poses, until those
        agree it is right or ``focal_rounds`` adoptions were made. Deciding on every frame since
        the last adoption, not the last few, keeps a bias that changes along the path (goldcape's
        orbit: steps of 0.5-0.7 % between windows of 10 frames) from walking the estimate.
        """
        cfg = self.cfg
        scale = photo_focal_scale(row)
        if not cfg.focal_from_frames or scale is None:
            return []
        self.window.append(_Held(index, name, rgb, row))
        self.since.append(scale)
        if len(self.window) < cfg.focal_window:
            return []
        redone: Dict[str, Dict[str, Any]] = {}
        for _ in range(cfg.focal_rounds):
            # the first adoption asks for a larger change than the ones that refine it: the
            # refit finds most of the error, the frames localized again the rest
            scale = pooled_focal_scale(
                list(self.since), self.focal_scale,
                cfg.focal_settle if self.focal_adoptions else cfg.focal_min_change,
                cfg.focal_agree)
            if scale is None:
                break
            logger.info("%d frames agree on a focal length %.4f x the given one (%.4f x the "
                        "one used): the sequence takes it, and localizes the last %d again",
                        len(self.since), scale, scale / self.focal_scale, len(self.window))
            self.focal_scale = scale
            self.focal_adoptions += 1
            for h in self.window:
                if h.row.get("c2w") is None:  # failed when localized again: left as it is
                    continue
                h.row = self.frame(h.index, h.name, h.rgb, start=np.asarray(h.row["c2w"]))
                redone[h.name] = h.row
            # what the frames say now: the window's, localized with the focal length adopted
            self.since.clear()
            self.since.extend(photo_focal_scale(h.row) for h in self.window)
        self.redone += len(redone)
        return list(redone.values())


def track(
    worker: BatchWorker,
    source: FrameSource,
    ledger: PosesLedger,
    intrinsics_of: Callable[[Tuple[int, int]], Intrinsics],
    init_c2w: Optional[np.ndarray] = None,
    gt_of: Optional[Callable[[str], Optional[np.ndarray]]] = None,
    cfg: Optional[TrackingConfig] = None,
    progress: Optional[Callable[[Dict[str, Any]], Any]] = None,
) -> TrackingSummary:
    """Track the frames of ``source`` (module docstring), recording each in ``ledger``.

    Args:
        worker: model, matcher, method and Localizer (``batch.BatchWorker``).
        source: the frames.
        ledger: the output folder's record; frames it holds are skipped (resume), and their
            poses seed the prediction.
        intrinsics_of: ``(W, H)`` of a frame -> its intrinsics (``inputs.intrinsics_for_photos``).
        init_c2w: start pose of the first frame (None: candidate views).
        gt_of: frame name -> true c2w (errors only), or None.
        cfg: :class:`TrackingConfig`.
        progress: called after each frame with ``{"row", "counts", "done", "todo"}``.
    """
    tracker = _Tracker(worker, source, ledger, intrinsics_of, init_c2w, gt_of,
                       cfg or TrackingConfig())
    t0 = time.perf_counter()
    rows: Dict[str, Dict[str, Any]] = {}  # this call's, by name (a frame localized again: its last)
    skipped = 0
    total = source.count()
    if progress is not None:
        progress({"row": None, "counts": ledger.counts(), "done": 0, "skipped": len(tracker.done),
                  "todo": None if total is None else max(0, total - len(tracker.done))})
    ahead = tracker.ahead if tracker.cfg.look_ahead and tracker.cfg.prefetch > 0 else None
    for index, name, rgb, *prepared in prefetched(source, tracker.cfg.prefetch, ahead):
        if name in tracker.done:
            skipped += 1
            continue
        row = tracker.frame(index, name, rgb, prepared[0] if prepared else None)
        out = [row] + tracker.settle_lens(index, name, rgb, row)
        row = out[-1] if out[-1]["name"] == name else row  # this frame, localized again
        for r in out + tracker.settle_focal(index, name, rgb, row):
            ledger.record(r)
            rows[r["name"]] = r
        if progress is not None:
            progress({"row": rows[name], "counts": ledger.counts(), "done": len(rows),
                      "todo": total})
    ledger.flush()
    return TrackingSummary(ledger.counts(), len(rows), skipped, time.perf_counter() - t0,
                           tracker.relocalized, list(rows.values()), len(tracker.fast_settled),
                           tracker.focal_scale, tracker.focal_adoptions, tracker.redone,
                           None if tracker.lens is None else list(tracker.lens),
                           tracker.lens_adoptions,
                           None if tracker.centre_px is None else list(tracker.centre_px),
                           tracker.centre_evidence)


def write_tracking_video(
    path,
    worker: BatchWorker,
    source: FrameSource,
    rows: Sequence[Dict[str, Any]],
    intrinsics_of: Callable[[Tuple[int, int]], Intrinsics],
    fps: float = 10.0,
) -> Path:
    """render | frame | blend | difference of every tracked frame, as an MP4.

    Panels by ``pictures.overlay_panel``: the render at the frame's estimate (a frame without one
    shows black). A GIF when no MP4 encoder works.

    Returns:
        The path written.
    """
    from ..io.video import write_video
    from ..pictures import VERDICT_COLOURS, overlay_panel
    from ..render import render

    by_name = {r["name"]: r for r in rows}
    panels = []
    model = worker.model
    for _, name, rgb in source:
        r = by_name.get(name)
        if r is None:
            continue
        intr = intrinsics_of((int(rgb.shape[1]), int(rgb.shape[0])))
        if r.get("intrinsics"):  # those the pose holds with (a focal length estimated)
            intr = Intrinsics.from_json(r["intrinsics"])
        lens = worker.setup.distortion
        if r.get(CAMERA_DISTORTION_KEY):  # a lens adopted from the frames
            lens = LensDistortion(tuple(r[CAMERA_DISTORTION_KEY]))
        q = _query(rgb, intr, name, worker.setup.resize, lens)
        if r.get("c2w") is not None:
            w2c = torch.as_tensor(invert_rigid(np.asarray(r["c2w"], np.float64)),
                                  dtype=model.dtype, device=model.device)
            with torch.no_grad():
                img = render(model, q.intrinsics, w2c, worker.bg, backend=worker.setup.backend
                             ).color
            img = img.clamp(0, 1).float().cpu()
        else:
            img = torch.zeros_like(q.rgb)
        p = overlay_panel(img, q.rgb)
        p[:3] = VERDICT_COLOURS.get(r.get("status"), (128, 128, 128))  # a verdict stripe on top
        panels.append(p)
    return write_video(path, panels, fps=fps)


# ---------------------------------------------------------------------------------- the tool's run


def first_frame_start(data: Dict[str, Any], source: FrameSource, cameras, scene_centre,
                      gt_of) -> Optional[np.ndarray]:
    """The first frame's start pose (``data.init``; ProblemError when it cannot be had)."""
    first = "frame_000000" if source.is_video else source.names[0]
    _, inits, errs = start_poses(data.get("init"), [first],
                                 [None if gt_of is None else gt_of(first)], cameras, scene_centre)
    if errs[0]:
        raise ProblemError(errs[0])
    return inits[0]


def sequence_truths(data: Dict[str, Any]) -> Optional[Callable[[str], Optional[np.ndarray]]]:
    """Frame name -> true c2w from ``data.gt.poses_file`` / ``cameras_json``, or None."""
    g = data.get("gt") or {}
    for k in ("poses_file", "cameras_json"):
        if g.get(k) is not None:
            return read_poses_file(g[k], f"data.gt.{k}").get
    return None


def sequence_pictures(out: Path, worker: BatchWorker, source: FrameSource, rows, intrinsics_of,
                      options: Dict[str, Any], title: str) -> List[str]:
    """trajectory.png, tracking.mp4 and focal.png, as ``options`` (the tool's output group) ask.

    focal.png only when the sequence adopted a focal length from its frames.
    """
    files = []
    try:
        if options.get("focal_plot") and any(
                (r.get(CAMERA_FOCAL_KEY) or 1.0) != 1.0 for r in rows):
            from ..pictures import plot_focal_frames

            plot_focal_frames(out / "focal.png", [int(r.get("index", 0)) for r in rows],
                              [float(r.get(CAMERA_FOCAL_KEY) or 1.0) for r in rows],
                              [photo_focal_scale(r) for r in rows], title)
            files.append("focal.png")
        if options.get("trajectory_plot") and rows:
            from ..pictures import plot_trajectory

            plot_trajectory(
                out / "trajectory.png",
                [None if r.get("c2w") is None else np.asarray(r["c2w"]) for r in rows],
                [e.c2w for e in worker.cameras],
                [None if r.get("gt_c2w") is None else np.asarray(r["gt_c2w"]) for r in rows],
                [r["status"] for r in rows], title=title,
            )
            files.append("trajectory.png")
        if options.get("video") and rows:
            p = write_tracking_video(out / "tracking.mp4", worker, source, rows, intrinsics_of,
                                     float(options.get("video_fps") or 10))
            files.append(p.name)
    except Exception as e:  # noqa: BLE001 - a picture never fails the run
        logger.warning("could not draw every picture: %s: %s", type(e).__name__, e)
    return files
