"""Valid seed files for the reader fuzz tests, small enough to read hundreds of times a second.

PLY, cameras.json and cfg_args seeds come from the library's writers (PLY Gaussians:
tests/helpers/gaussians.py). COLMAP files come from the packers of tests/helpers/colmap.py,
which the dataset tests write with too; they also give the offset of every binary field.
"""
from __future__ import annotations

import io
import math
from typing import Dict, List, Optional, Tuple

from plyfile import PlyData

from icomma_plugin.io.cameras_json import CameraEntry
from icomma_plugin.pose.convert import look_at_c2w
from tests.helpers import colmap

CFG = {"data_device": "cuda", "eval": True, "images": "images", "model_path": "./output/x",
       "resolution": -1, "sh_degree": 1, "source_path": "/data/lego", "white_background": True}


def as_ascii(binary_ply: bytes) -> bytes:
    """The same PLY in ASCII format (plyfile's writer)."""
    ply = PlyData.read(io.BytesIO(binary_ply))
    ply.text = True
    out = io.BytesIO()
    ply.write(out)
    return out.getvalue()


def cameras(n: int) -> List[CameraEntry]:
    """``n`` cameras on a ring looking at the origin, 80x60 pixels."""
    out = []
    for i in range(n):
        a = 2 * math.pi * i / max(n, 1)
        c2w = look_at_c2w([4 * math.cos(a), 4 * math.sin(a), 1.0], [0, 0, 0], up=[0, 0, 1])
        out.append(CameraEntry(i, f"r_{i}", 80, 60, c2w, 111.1 + i, 110.5))
    return out


# ----------------------------------------------------------------------------- COLMAP

# The seed model (tests/helpers/colmap.py describes the tuples); images name files that exist.
COLMAP_CAMERAS = [(1, 1, 32, 24, [30.0, 28.0, 18.0, 11.0]),  # PINHOLE, off-centre
                  (2, 2, 20, 16, [22.0, 10.0, 8.0, 0.01])]   # SIMPLE_RADIAL (distorted)
COLMAP_IMAGES = [(10, (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 4.0), 1, "img_00.png",
                  [(1.0, 2.0, -1), (2.0, 2.0, -1)]),
                 (11, (0.9, 0.1, 0.3, 0.3), (0.5, -0.2, 3.0), 2, "img_01.png", []),
                 (12, (0.5, 0.5, -0.5, 0.5), (0.1, 0.2, 5.0), 1, "sub/img_02.png",
                  [(1.0, 2.0, -1)])]
COLMAP_POINTS = [(1, (0.1, 0.2, 0.3), (255, 128, 0), 0.5, [(1, 0), (1, 1)]),
                 (2, (1.0, -2.0, 3.0), (0, 0, 255), 0.1, []),
                 (3, (0.0, 0.0, 0.0), (7, 7, 7), 1.5, [(1, 0)])]


def colmap_binary() -> Tuple[Dict[str, bytes], Dict[str, List[Tuple[int, str]]]]:
    """The seed model as binary files and their fields (tests/helpers/colmap.py)."""
    return colmap.colmap_binary(COLMAP_CAMERAS, COLMAP_IMAGES, COLMAP_POINTS)


def colmap_text() -> Dict[str, Optional[bytes]]:
    """The seed model as COLMAP ``.txt`` bytes.

    The ``.bin`` names map to None (absent), so that the reader reads the text files.
    """
    files: Dict[str, Optional[bytes]] = dict(
        colmap.colmap_text(COLMAP_CAMERAS, COLMAP_IMAGES, COLMAP_POINTS))
    files.update({n.replace(".txt", ".bin"): None for n in list(files)})
    return files


def write_colmap_files(sparse, files, name=None, bad=None) -> None:
    """``files`` into ``sparse``, ``bad`` in place of ``name``; a None entry is removed."""
    for n, b in files.items():
        b = bad if n == name else b
        if b is None:
            (sparse / n).unlink(missing_ok=True)
        else:
            (sparse / n).write_bytes(b)


# ----------------------------------------------------------------------------- transforms.json

def _gl_look_at(centre):
    """OpenGL camera-to-world (x right, y up, z back) at ``centre`` looking at the origin."""
    c2w = look_at_c2w(centre, [0, 0, 0], up=[0, 0, 1])
    c2w[:3, 1:3] *= -1.0
    return c2w


def transforms(variant: int) -> dict:
    """A 3-frame ``transforms.json`` object (images ``images/f_<k>.png``, 8x6).

    0: nerfstudio, pinhole + OpenCV lens, points from ``points.ply``; 1: instant-ngp, field of
    view, one frame with its own fisheye camera; 2: one focal length only.
    """
    frames = [{"file_path": f"images/f_{k}" + (".png" if k % 2 else ""),
               "transform_matrix": _gl_look_at([4 * math.cos(k), 4 * math.sin(k), 1.0]).tolist()}
              for k in range(3)]
    if variant == 0:
        return {"camera_model": "OPENCV", "fl_x": 9.0, "fl_y": 9.5, "cx": 4.2, "cy": 3.1,
                "w": 8, "h": 6, "k1": 0.01, "k2": 0.0, "p1": 0.001, "p2": 0.0,
                "ply_file_path": "points.ply", "frames": frames}
    if variant == 1:
        frames[1].update({"camera_model": "OPENCV_FISHEYE", "k1": 0.02, "fl_x": 8.0})
        return {"camera_angle_x": 0.9, "frames": frames}
    return {"fl_x": 9.0, "w": 8, "h": 6, "frames": frames}
