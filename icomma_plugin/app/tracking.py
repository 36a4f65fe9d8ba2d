"""Ordered frames (a video file or a folder of frames) tracked one after the other.

Each frame starts from a constant-velocity prediction: the motion between the last two frames
that did not fail, applied again (as a twist per frame: ``w2c_k = exp((k - j) xi) @ w2c_j`` with
``xi = log(w2c_j @ inv(w2c_i)) / (j - i)`` for the last good frames ``i < j``). The first frame
starts from ``data.init`` (a pose, or none: the candidate views). A frame whose verdict is
``failed`` is localized again from the candidate views (no start pose), and the better of the two
results is kept. Every row is recorded in the ledger after its frame, so a killed run resumes at
the first frame it had not finished, with the same predictions.

    source = FrameSource.open("walk.mp4", every=2)
    summary = track(worker, source, ledger, intrinsics_of=..., init_c2w=None)
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, List, Optional, Sequence, Tuple

import numpy as np
import torch

from ..camera import Intrinsics
from ..pose.se3 import se3_exp, se3_log
from .batch import BatchWorker, PhotoTask, failure_row, result_row, resize_query
from .inputs import list_photos
from .ledger import PosesLedger
from .problem import ProblemError
from ..localization.types import Query

logger = logging.getLogger(__name__)

__all__ = [
    "FrameSource",
    "TrackingConfig",
    "TrackingSummary",
    "predict_w2c",
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
    """

    velocity: bool = True
    relocalize: bool = True


def predict_w2c(
    history: Sequence[Tuple[int, np.ndarray]], index: int, velocity: bool = True
) -> Optional[np.ndarray]:
    """Start pose (w2c) of frame ``index``, or None.

    From the ``(frame index, w2c)`` of earlier frames that did not fail, oldest first: constant
    velocity from the last two, or the last one alone.
    """
    if not history:
        return None
    j, Tj = history[-1]
    Tj = np.asarray(Tj, np.float64)
    if not velocity or len(history) < 2:
        return Tj.copy()
    i, Ti = history[-2]
    if j <= i or index <= j:
        return Tj.copy()
    delta = torch.as_tensor(Tj @ np.linalg.inv(np.asarray(Ti, np.float64)), dtype=torch.float64)
    xi = se3_log(delta) / float(j - i)
    step = se3_exp(xi * float(index - j)).numpy()
    out = step @ Tj
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

    @property
    def frames_per_second(self) -> Optional[float]:
        """Frames tracked per second of this call; None when it tracked none."""
        return None if self.done_now == 0 or self.seconds <= 0 else self.done_now / self.seconds


def _query(rgb: np.ndarray, intr: Intrinsics, name: str, resize: Optional[int]) -> Query:
    t = torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1).float() / 255.0
    return resize_query(Query(t.contiguous(), intr, None, None, name), resize)


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
        worker: model, matcher, method and candidate views (``batch.BatchWorker``).
        source: the frames.
        ledger: the output folder's record; frames it holds are skipped (resume), and their
            poses seed the prediction.
        intrinsics_of: ``(W, H)`` of a frame -> its intrinsics (``inputs.photo_intrinsics``).
        init_c2w: start pose of the first frame (None: candidate views).
        gt_of: frame name -> true c2w (errors only), or None.
        cfg: :class:`TrackingConfig`.
        progress: called after each frame with ``{"row", "counts", "done", "todo"}``.
    """
    cfg = cfg or TrackingConfig()
    done = ledger.finished()
    history: List[Tuple[int, np.ndarray]] = []
    for r in sorted(done.values(), key=lambda r: r.get("index", 0)):
        if r.get("status") != "failed" and r.get("c2w") is not None:
            history.append((int(r["index"]), np.linalg.inv(np.asarray(r["c2w"], np.float64))))
    t0 = time.perf_counter()
    rows: List[Dict[str, Any]] = []
    skipped = relocs = 0
    total = source.count()
    if progress is not None:
        progress(
            {
                "row": None,
                "counts": ledger.counts(),
                "done": 0,
                "todo": None if total is None else max(0, total - len(done)),
                "skipped": len(done),
            }
        )
    intr_cache: Dict[Tuple[int, int], Intrinsics] = {}
    for index, name, rgb in source:
        if name in done:
            skipped += 1
            continue
        t_frame = time.perf_counter()
        size = (int(rgb.shape[1]), int(rgb.shape[0]))
        gt = gt_of(name) if gt_of is not None else None
        pred_w2c = predict_w2c(history, index, cfg.velocity)
        start = np.linalg.inv(pred_w2c) if pred_w2c is not None else init_c2w
        task = PhotoTask(
            index,
            name,
            source.spec if source.is_video else str(source.paths[index]),
            None,
            None,
            start,
            gt,
        )
        try:
            if size not in intr_cache:
                intr_cache[size] = intrinsics_of(size)
            task.intrinsics = intr_cache[size]
            problem = worker.problem(task, _query(rgb, task.intrinsics, name, worker.setup.resize))
            if start is None and not worker._can_search():
                raise ProblemError(
                    "the first frame has no start pose and the paper's method (optimizer=icomma) "
                    "needs one: give data.init, or use optimizer=robust"
                )
            result = worker.localize(problem, start)
            relocalized = False
            if (
                result.verdict is not None
                and result.verdict.status == "failed"
                and start is not None
                and cfg.relocalize
                and worker._can_search()
            ):
                again = worker.localize(problem, None)
                if again.verdict is not None and _RANK[again.verdict.status] > _RANK["failed"]:
                    result, relocalized = again, True
                    relocs += 1
            folder, thumb = worker.write_pictures(problem, result, time.perf_counter() - t_frame)
            row = result_row(task, problem, result, time.perf_counter() - t_frame, folder, thumb)
            row["relocalized"] = relocalized
            row["predicted_c2w"] = None if start is None else np.asarray(start).tolist()
        except (ValueError, FileNotFoundError) as e:
            msg = str(e).splitlines()[0] if str(e) else type(e).__name__
            row = failure_row(task, f"bad input: {msg}", msg, time.perf_counter() - t_frame)
        if row["status"] != "failed" and row["c2w"] is not None:
            history.append((index, np.linalg.inv(np.asarray(row["c2w"], np.float64))))
        ledger.record(row)
        rows.append(row)
        if progress is not None:
            progress({"row": row, "counts": ledger.counts(), "done": len(rows), "todo": total})
    ledger.flush()
    return TrackingSummary(
        ledger.counts(), len(rows), skipped, time.perf_counter() - t0, relocs, rows
    )


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
    from ..render import render
    from ..pictures import overlay_panel, VERDICT_COLOURS

    by_name = {r["name"]: r for r in rows}
    panels = []
    model = worker.model
    for index, name, rgb in source:
        r = by_name.get(name)
        if r is None:
            continue
        q = _query(
            rgb, intrinsics_of((int(rgb.shape[1]), int(rgb.shape[0]))), name, worker.setup.resize
        )
        if r.get("c2w") is not None:
            w2c = torch.as_tensor(
                np.linalg.inv(np.asarray(r["c2w"])), dtype=model.dtype, device=model.device
            )
            with torch.no_grad():
                img = render(
                    model,
                    q.intrinsics,
                    w2c,
                    worker.bg.to(model.dtype),
                    backend=worker.setup.backend,
                ).color
            img = img.clamp(0, 1).float().cpu()
        else:
            img = torch.zeros_like(q.rgb)
        p = overlay_panel(img, q.rgb)
        p[:3] = VERDICT_COLOURS.get(r.get("status"), (128, 128, 128))  # a verdict stripe on top
        panels.append(p)
    return write_video(path, panels, fps=fps)
