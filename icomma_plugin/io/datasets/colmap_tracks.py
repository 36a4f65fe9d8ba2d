"""What a COLMAP model's tracks say about its own poses: each photo's record precision.

``colmap.py`` reads the cameras, poses and points a fit needs; this module asks it for the 2D
observations too (binary or text, COLMAP's layouts) and, for every registered photo of a
pinhole camera, the first-order precision of its recorded pose from the points it observes
(``icomma_plugin.pose.precision``): how far the record itself may be from the truth, so that the
audit and the benchmark can say when a localized pose is "off its record" by no more than the
record's own uncertainty (docs/AUDIT.md).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, Optional

import numpy as np

from icomma_plugin.pose.convert import cameras_extent, invert_rigid
from icomma_plugin.pose.precision import PosePrecision, bundle_precision, pose_precision

from .base import DatasetError, PathLike
from .colmap import (
    _pick,
    colmap_w2c,
    find_sparse_dir,
    read_cameras_binary,
    read_cameras_text,
    read_images_binary,
    read_images_text,
    read_points3D_binary,
    read_points3D_text,
)

logger = logging.getLogger(__name__)

__all__ = ["ImageTrack", "precision_of", "read_image_tracks", "record_precision"]

#: Observations a photo needs before its record's precision is estimated.
MIN_POINTS = 10


@dataclass
class ImageTrack:
    """One registered photo's pose and the 3D points it observes.

    w2c: its recorded world-to-camera pose (NaN where COLMAP has none); camera_id: its COLMAP
    camera; xy [N, 2]: where it observed the points, COLMAP's pixel convention; point_ids [N]:
    the points' ids.
    """

    name: str
    w2c: np.ndarray
    camera_id: int
    xy: np.ndarray
    point_ids: np.ndarray


def read_image_tracks(sparse_dir: PathLike):
    """(cameras, {image name: ImageTrack}, {point id: xyz}) of a COLMAP model folder.

    Raises:
        DatasetError: a missing or malformed file (the message names it).
    """
    sparse = Path(sparse_dir)
    cp, ip = _pick(sparse, "cameras"), _pick(sparse, "images")
    pp = _pick(sparse, "points3D")
    cams = read_cameras_binary(cp) if cp.suffix == ".bin" else read_cameras_text(cp)
    images = (read_images_binary(ip, with_points=True) if ip.suffix == ".bin"
              else read_images_text(ip, with_points=True))
    xyz, _, ids = (read_points3D_binary(pp, with_ids=True) if pp.suffix == ".bin"
                   else read_points3D_text(pp, with_ids=True))
    tracks = {}
    for im in images.values():
        seen = im.point3D_ids >= 0  # -1: an observation without a 3D point
        q = np.asarray(im.qvec, np.float64)
        posed = np.all(np.isfinite(q)) and np.linalg.norm(q) > 1e-8  # else no pose: NaN
        w2c = colmap_w2c(q, im.tvec) if posed else np.full((4, 4), np.nan)
        tracks[im.name] = ImageTrack(im.name, w2c, im.camera_id, im.xys[seen],
                                     im.point3D_ids[seen])
    return cams, tracks, {int(i): p for i, p in zip(ids, xyz)}


def _pinhole(cam) -> tuple:
    p = [float(v) for v in cam.params]
    return (p[0], p[0], p[1], p[2]) if cam.model == "SIMPLE_PINHOLE" else tuple(p)


def record_precision(root: PathLike, points: str = "free") -> Dict[str, Dict]:
    """Each registered photo's record precision, by image name (``PosePrecision.to_json()``).

    ``root``: a dataset folder with ``sparse/0`` (or ``sparse``), as ``read_colmap`` takes, LLFF
    folders with a COLMAP model beside included. ``points``: ``"free"`` (default): the whole
    reconstruction's uncertainty, its points estimated too (``bundle_precision``); ``"fixed"``:
    each photo from its own observations with the points held fixed (``pose_precision``, a lower
    bound: on bird 0.084 deg rms against 0.152 with the points free). ``"free"`` falls back to
    ``"fixed"`` (logged; the entries say ``points_free``) when a camera has a distortion model or
    the bundle has more than ``MAX_BUNDLE_PARAMS`` camera parameters. Each entry adds
    ``centre_std_rel``: the centre's precision in units of the records' camera extent
    (``cameras_extent``, the scene radius the benchmark and the audit use, and the same whatever
    similarity transform a reader applied). The focal length counts as a parameter when the photo
    has a camera of its own (COLMAP then estimated it per photo): one for SIMPLE_PINHOLE, two for
    PINHOLE; a camera shared by several photos counts as known. Photos of distorted camera models,
    or with fewer than ``MIN_POINTS`` observations, get no entry (logged).

    Returns ``{}`` when the folder has no COLMAP model or no points3D file.

    Raises:
        ValueError: ``points`` not "free" or "fixed".
    """
    if points not in ("free", "fixed"):
        raise ValueError(f"points must be 'free' or 'fixed', got {points!r}")
    try:
        sparse = find_sparse_dir(root)
    except DatasetError:  # not a COLMAP capture: nothing to say, nothing to log
        return {}
    if _pick(sparse, "points3D", required=False) is None:
        return {}
    try:
        cams, images, pts = read_image_tracks(sparse)
    except DatasetError as e:
        logger.info("no record precision for %s: %s", root, e)
        return {}
    users: Dict[int, int] = {}
    for im in images.values():
        users[im.camera_id] = users.get(im.camera_id, 0) + 1
    usable, skipped = {}, {"distorted camera model": 0, "too few points": 0, "degenerate": 0}
    posed = {n: im for n, im in images.items()  # (read_colmap skips the others too)
             if np.all(np.isfinite(im.w2c))}
    skipped["degenerate"] = len(images) - len(posed)
    for name, im in posed.items():
        cam = cams.get(im.camera_id)
        if cam is None or cam.model not in ("SIMPLE_PINHOLE", "PINHOLE"):
            skipped["distorted camera model"] += 1
            continue
        known = np.array([int(pid) in pts for pid in im.point_ids], bool)
        if known.sum() < MIN_POINTS:
            skipped["too few points"] += 1
            continue
        focal = "none" if users[im.camera_id] > 1 else (
            "shared" if cam.model == "SIMPLE_PINHOLE" else "separate")
        usable[name] = (im, _pinhole(cam), focal, known)
    extent = cameras_extent([invert_rigid(im.w2c) for im in posed.values()]) if posed else 1.0
    precisions = None
    if points == "free" and not skipped["distorted camera model"] and len(usable) >= 2:
        precisions = _bundle(usable, pts, root)
    out: Dict[str, Dict] = {}
    for name, (im, (fx, fy, cx, cy), focal, known) in usable.items():
        if precisions is not None:
            prec = precisions[name]
        else:
            xyz = np.stack([pts[int(pid)] for pid in im.point_ids[known]])
            try:
                prec = pose_precision(im.w2c, fx, fy, cx, cy, xyz, im.xy[known], focal)
            except ValueError:
                skipped["degenerate"] += 1
                continue
        out[name] = dict(prec.to_json(), centre_std_rel=prec.centre_std / extent)
    left = {k: v for k, v in skipped.items() if v}
    if left:
        logger.info("record precision of %s: photos left out: %s", root, left)
    return out


def _bundle(usable, pts, root) -> Optional[Dict[str, PosePrecision]]:
    """``bundle_precision`` of the usable photos, by name; None (logged) where it cannot run."""
    names = sorted(usable)
    ids = {pid: k for k, pid in enumerate(sorted(pts))}
    cam, pt, xy = [], [], []
    for c, name in enumerate(names):
        im, _, _, known = usable[name]
        cam.append(np.full(int(known.sum()), c))
        pt.append(np.array([ids[int(pid)] for pid in im.point_ids[known]], np.int64))
        xy.append(im.xy[known])
    try:
        res = bundle_precision(np.stack([usable[n][0].w2c for n in names]),
                               np.array([usable[n][1] for n in names]),
                               [usable[n][2] for n in names],
                               np.stack([pts[p] for p in sorted(pts)]),
                               np.concatenate(cam), np.concatenate(pt), np.concatenate(xy))
    except ValueError as e:
        logger.info("record precision of %s with the points held fixed: %s", root, e)
        return None
    return dict(zip(names, res))


def precision_of(table: Dict[str, Dict], name: str) -> Optional[Dict]:
    """``table``'s entry for a view ``name`` (exact, else by file name, else by stem)."""
    if name in table:
        return table[name]
    base = Path(name).name
    for key, value in table.items():
        if Path(key).name == base or Path(key).stem == Path(base).stem:
            return value
    return None
