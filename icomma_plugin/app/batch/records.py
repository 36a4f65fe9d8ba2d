"""The rows a batch records, and its exports.

Each photo gets one row of the one row schema (``localization.types.ROW_FIELDS``, the same as
result.json and the benchmark's records; docs/CONTRACTS.md), plus the batch's own fields:
``index`` (the photo's place in the input order), ``work_size``, ``folder`` and ``thumb`` (its
pictures), ``own_camera_left_out``, ``worker`` (the process) and ``localize_seconds``.
"""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence

import numpy as np

from ...camera import Intrinsics
from ...localization.types import LocalizationResult, blank_row
from ..inputs import ProblemError
from .planning import PhotoTask

logger = logging.getLogger(__name__)

__all__ = ["export_rows", "failure_row", "result_row", "safe_name"]


def safe_name(name: str) -> str:
    """A file-system-safe folder name for a photo name (``a/b.jpg`` -> ``a__b.jpg``)."""
    s = name.replace("/", "__").replace("\\", "__")
    return re.sub(r"[^A-Za-z0-9._+-]", "_", s) or "photo"


def _list(T) -> Optional[list]:
    return None if T is None else np.asarray(T).tolist()


def failure_row(
    task: PhotoTask, reason: str, error: Optional[str] = None, seconds: float = 0.0
) -> Dict[str, Any]:
    """The row of a photo that could not be localized at all."""
    return blank_row(
        index=task.index, name=task.name, image=task.path, status="failed", reason=reason,
        error=error or reason, init_c2w=_list(task.init_c2w), gt_c2w=_list(task.gt_c2w),
        seconds=seconds,
        intrinsics=None if task.intrinsics is None else task.intrinsics.to_json(),
    )


def result_row(task: PhotoTask, result: LocalizationResult, scene_scale: Optional[float],
               seconds: float, folder: Optional[str] = None, thumb: Optional[str] = None
               ) -> Dict[str, Any]:
    """The poses.json row of one localized photo (``seconds``: all its work, pictures too).

    Its ``intrinsics`` are those the pose holds with, at the photo file's size: the task's, with
    the focal length the method estimated when it did (``details["focal_scale"]``).
    """
    intr = result.intrinsics
    held = task.intrinsics
    focal = result.details.get("focal_scale")
    if held is not None and focal is not None:
        held = held.with_focal_scale(float(focal))
    return result.row(
        scene_scale, index=task.index, image=task.path, seconds=seconds,
        localize_seconds=result.seconds,
        intrinsics=None if held is None else held.to_json(),
        work_size=None if intr is None else [intr.width, intr.height], folder=folder,
        thumb=thumb, worker=os.getpid(),
    )


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
    from ...io.export import FORMATS, NamedPose, export_poses

    bad = [f for f in formats if f not in FORMATS]
    if bad:
        raise ProblemError(f"output.export: unknown format(s) {bad}; choose from {sorted(FORMATS)}")
    poses = [
        NamedPose(r["name"], np.asarray(r["c2w"]), Intrinsics.from_json(r["intrinsics"]))
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
