"""COLMAP sparse models as files, written independently of the reader.

The layouts are those of COLMAP's ``scripts/python/read_write_model.py``; the dataset tests and
the fuzz seeds both write with these. A model is three lists:
- cameras: ``(id, model, width, height, params)``, the model a name (``"PINHOLE"``) or its id;
- images: ``(id, qvec (w, x, y, z), tvec, camera id, name, points2D [(x, y, point3D id)])``;
- points: ``(id, xyz, rgb, error, track [(image id, point2D index)])``.
"""
from __future__ import annotations

import struct
from pathlib import Path
from typing import Dict, List, Tuple

MODEL_IDS = {"SIMPLE_PINHOLE": 0, "PINHOLE": 1, "SIMPLE_RADIAL": 2, "RADIAL": 3, "OPENCV": 4,
             "OPENCV_FISHEYE": 5, "FULL_OPENCV": 6}
MODEL_NAMES = {v: k for k, v in MODEL_IDS.items()}

Slots = List[Tuple[int, str]]


def colmap_binary(cameras, images, points) -> Tuple[Dict[str, bytes], Dict[str, Slots]]:
    """The model as ``cameras/images/points3D.bin`` bytes, and where each field sits.

    Returns:
        ``(files, slots)``: the bytes per file name, and per file the ``(offset, struct fmt)``
        of every count, id and value field (where a fuzzer puts its values).
    """
    files, slots = {}, {}

    def put(buf, sl, fmt, *vals):
        sl.extend((len(buf) + struct.calcsize("<" + fmt[:k]), f) for k, f in enumerate(fmt))
        buf += struct.pack("<" + fmt, *vals)

    buf, sl = bytearray(), []
    put(buf, sl, "Q", len(cameras))
    for cid, model, w, h, params in cameras:
        put(buf, sl, "iiQQ", cid, MODEL_IDS[model] if isinstance(model, str) else model, w, h)
        put(buf, sl, "d" * len(params), *params)
    files["cameras.bin"], slots["cameras.bin"] = bytes(buf), sl

    buf, sl = bytearray(), []
    put(buf, sl, "Q", len(images))
    for iid, q, t, cid, name, pts in images:
        put(buf, sl, "idddddddi", iid, *q, *t, cid)
        buf += name.encode() + b"\x00"
        put(buf, sl, "Q", len(pts))
        for x, y, pid in pts:
            put(buf, sl, "ddq", x, y, pid)
    files["images.bin"], slots["images.bin"] = bytes(buf), sl

    buf, sl = bytearray(), []
    put(buf, sl, "Q", len(points))
    for pid, xyz, rgb, err, track in points:
        put(buf, sl, "QdddBBBd", pid, *xyz, *rgb, err)
        put(buf, sl, "Q", len(track))
        for iid, idx in track:
            put(buf, sl, "ii", iid, idx)
    files["points3D.bin"], slots["points3D.bin"] = bytes(buf), sl
    return files, slots


def colmap_text(cameras, images, points) -> Dict[str, bytes]:
    """The model as ``cameras/images/points3D.txt`` bytes (a comment line heads each file)."""
    cam = ["# Camera list with one line of data per camera:"]
    for cid, model, w, h, params in cameras:
        name = model if isinstance(model, str) else MODEL_NAMES[model]
        cam.append(" ".join([str(cid), name, str(w), str(h)] + [repr(float(p)) for p in params]))
    img = ["# Image list with two lines of data per image:"]
    for iid, q, t, cid, name, pts in images:
        img.append(" ".join([str(iid)] + [repr(float(v)) for v in (*q, *t)] + [str(cid), name]))
        img.append(" ".join(f"{x!r} {y!r} {pid}" for x, y, pid in pts))
    pts3d = ["# 3D point list with one line of data per point:"]
    for pid, xyz, rgb, err, track in points:
        pts3d.append(" ".join([str(pid)] + [repr(float(v)) for v in xyz]
                              + [str(int(c)) for c in rgb] + [repr(float(err))]
                              + [f"{a} {b}" for a, b in track]))
    return {"cameras.txt": ("\n".join(cam) + "\n").encode(),
            "images.txt": ("\n".join(img) + "\n").encode(),
            "points3D.txt": ("\n".join(pts3d) + "\n").encode()}


def write_colmap_bin(sparse: Path, cameras, images, points) -> None:
    """The model as COLMAP binary files in the folder ``sparse`` (created)."""
    sparse.mkdir(parents=True, exist_ok=True)
    for name, data in colmap_binary(cameras, images, points)[0].items():
        (sparse / name).write_bytes(data)


def write_colmap_txt(sparse: Path, cameras, images, points) -> None:
    """The model as COLMAP text files in the folder ``sparse`` (created)."""
    sparse.mkdir(parents=True, exist_ok=True)
    for name, data in colmap_text(cameras, images, points).items():
        (sparse / name).write_bytes(data)


def qvec_tvec(w2c) -> Tuple[List[float], List[float]]:
    """COLMAP's (qvec (w, x, y, z), tvec) of a world-to-camera ``[4, 4]``.

    The quaternion comes from the axis-angle of ``cv2.Rodrigues`` (not from the reader's own
    conversion), so a reader that mixes up the order or the sign is caught.
    """
    import cv2
    import numpy as np

    w2c = np.asarray(w2c, np.float64)
    rvec, _ = cv2.Rodrigues(w2c[:3, :3])
    angle = float(np.linalg.norm(rvec))
    axis = rvec.ravel() / angle if angle > 0 else np.zeros(3)
    q = [float(np.cos(angle / 2))] + [float(v) for v in np.sin(angle / 2) * axis]
    return q, [float(v) for v in w2c[:3, 3]]


def write_colmap_dataset(root: Path, photos) -> None:
    """A COLMAP dataset folder: ``images/<name>`` and ``sparse/0`` (binary, no points).

    ``photos``: ``(name, [H, W, 3] uint8 RGB, c2w, fx, fy[, cx, cy])``, each with its own PINHOLE
    camera (COLMAP's per-image intrinsics); the principal point in COLMAP's pixels (the image
    spans [0, W]), at the image centre unless given.
    """
    import numpy as np
    from PIL import Image

    (root / "images").mkdir(parents=True, exist_ok=True)
    cameras, images = [], []
    for i, (name, rgb, c2w, fx, fy, *pp) in enumerate(photos, 1):
        h, w = rgb.shape[:2]
        Image.fromarray(rgb).save(root / "images" / name)
        cx, cy = pp if pp else (w / 2.0, h / 2.0)
        cameras.append((i, "PINHOLE", w, h, [float(fx), float(fy), float(cx), float(cy)]))
        q, t = qvec_tvec(np.linalg.inv(np.asarray(c2w, np.float64)))
        images.append((i, q, t, i, name, []))
    write_colmap_bin(root / "sparse" / "0", cameras, images, [])
