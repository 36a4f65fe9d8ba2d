"""3DGS ``point_cloud.ply`` (Gaussians) and ``input.ply`` (coloured points) reading and writing.

Layout of a Gaussian PLY (upstream ``GaussianModel.save_ply`` / ``load_ply``): one ``vertex``
element, every property ``float`` (f4), binary little-endian, in the order
``x, y, z, nx, ny, nz, f_dc_0..2, f_rest_0..(3K-1), opacity, scale_0..2, rot_0..3`` where
K = (D+1)^2 - 1 for SH degree D. ``f_rest`` is channel-major: ``f_rest_0..K-1`` are the R
coefficients 1..K, then G, then B. Normals are written as zeros and ignored on reading. The stored
values are raw (opacity logit, log-scale, unnormalised quaternion w,x,y,z), exactly
:class:`~icomma_plugin.gaussians.GaussianModel`'s fields.
"""
from __future__ import annotations

import logging
import os
import re
from pathlib import Path
from typing import Optional, Tuple, Union

import numpy as np
import torch
from plyfile import PlyData, PlyElement, PlyListProperty, PlyParseError

from ..gaussians import GaussianModel, num_sh_coeffs
from .atomic import atomic_path

log = logging.getLogger(__name__)

PathLike = Union[str, os.PathLike]

__all__ = ["read_gaussian_ply", "write_gaussian_ply", "read_points_ply", "write_points_ply"]

# f_rest count -> SH degree (3 * ((D+1)^2 - 1)).
_REST_TO_DEGREE = {3 * (num_sh_coeffs(d) - 1): d for d in range(4)}
_FIXED = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
          "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]


def _attribute_names(sh_degree: int) -> list:
    """Upstream ``construct_list_of_attributes`` order."""
    n_rest = 3 * (num_sh_coeffs(sh_degree) - 1)
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
            + [f"f_rest_{i}" for i in range(n_rest)]
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def _read_ply(path: Path, what: str) -> PlyData:
    if not path.exists():
        raise ValueError(f"{what} {path}: file not found")
    if not path.is_file():
        raise ValueError(f"{what} {path}: not a regular file")
    with open(path, "rb") as f:
        magic = f.read(4)
    if magic[:3] != b"ply":
        raise ValueError(f"{what} {path}: not a PLY file (it does not start with 'ply', "
                         f"got {magic!r})")
    try:
        return PlyData.read(str(path), mmap=False)
    except (PlyParseError, ValueError, EOFError, IndexError, TypeError) as e:
        # plyfile reports truncation as "early end-of-file" and header problems with the line.
        raise ValueError(f"{what} {path}: cannot parse PLY ({type(e).__name__}: {e})") from e


def _vertex(ply: PlyData, path: Path, what: str):
    names = [el.name for el in ply.elements]
    if "vertex" not in names:
        raise ValueError(f"{what} {path}: no 'vertex' element (elements found: {names})")
    el = ply["vertex"]
    lists = [p.name for p in el.properties if isinstance(p, PlyListProperty)]
    if lists:
        raise ValueError(f"{what} {path}: vertex properties {lists} are lists; expected scalars")
    return el


def read_gaussian_ply(path: PathLike) -> GaussianModel:
    """Read a 3DGS ``point_cloud.ply`` into a float32 CPU :class:`GaussianModel`.

    The SH degree is inferred from the number of ``f_rest_*`` properties (0, 9, 24, 45 -> 0..3);
    ``f_rest`` names are sorted numerically as upstream does. Extra properties are ignored (logged).
    A file with zero Gaussians is accepted with a warning.

    Args:
        path: the PLY file.

    Returns:
        GaussianModel with raw (trainable-form) parameters.

    Raises:
        ValueError: naming the file and the problem: missing file, not a PLY / unparsable or
            truncated, no ``vertex`` element, missing properties (named), an ``f_rest`` count that
            matches no SH degree, non-float32 properties, NaN/Inf values (count and fields).
    """
    path = Path(path)
    what = "Gaussian PLY"
    el = _vertex(_read_ply(path, what), path, what)
    types = {p.name: np.dtype(p.val_dtype) for p in el.properties}

    missing = [n for n in _FIXED if n not in types]
    if missing:
        raise ValueError(f"{what} {path}: missing vertex properties {missing} "
                         f"(found {list(types)}); is this a 3DGS point_cloud.ply?")

    rest = [n for n in types if n.startswith("f_rest_")]
    bad_rest = [n for n in rest if not re.fullmatch(r"f_rest_\d+", n)]
    if bad_rest:
        raise ValueError(f"{what} {path}: malformed SH property names {bad_rest}")
    rest = sorted(rest, key=lambda n: int(n.split("_")[-1]))
    if len(rest) not in _REST_TO_DEGREE:
        raise ValueError(f"{what} {path}: {len(rest)} f_rest_* properties match no SH degree "
                         f"(expected one of {sorted(_REST_TO_DEGREE)} for degrees 0..3)")
    expected_rest = [f"f_rest_{i}" for i in range(len(rest))]
    if rest != expected_rest:
        gaps = sorted(set(expected_rest) - set(rest), key=lambda n: int(n.split("_")[-1]))
        raise ValueError(f"{what} {path}: f_rest_* properties are not numbered 0..{len(rest) - 1} "
                         f"(missing {gaps})")
    degree = _REST_TO_DEGREE[len(rest)]

    used = _FIXED + rest
    f4 = (np.dtype("<f4"), np.dtype(">f4"))
    wrong = {n: types[n] for n in used if types[n] not in f4}
    if wrong:
        desc = ", ".join(f"{n}: {t.name}" for n, t in wrong.items())
        raise ValueError(f"{what} {path}: properties must be float32 ('float'/'f4') as 3DGS writes "
                         f"them, got {desc}")
    extra = [n for n in types if n not in used and n not in ("nx", "ny", "nz")]
    if extra:
        log.info("%s %s: ignoring extra vertex properties %s", what, path, extra)

    data = el.data
    P = len(data)
    cols = {n: np.asarray(data[n], dtype=np.float32) for n in used}
    bad = {n: int((~np.isfinite(v)).sum()) for n, v in cols.items()}
    bad = {n: c for n, c in bad.items() if c}
    if bad:
        total = int(sum(c for c in bad.values()))
        raise ValueError(f"{what} {path}: {total} non-finite (NaN/Inf) values in {P} Gaussians; "
                         f"per property: {bad}")
    if P == 0:
        log.warning("%s %s: contains zero Gaussians", what, path)

    def stack(names):
        if not names:
            return torch.zeros(P, 0)
        return torch.from_numpy(np.stack([cols[n] for n in names], axis=1).reshape(P, len(names)))

    K = num_sh_coeffs(degree) - 1
    # Channel-major on disk: [P, 3*K] -> [P, 3, K] -> [P, K, 3] (upstream load_ply).
    sh_rest = stack(rest).reshape(P, 3, K).transpose(1, 2).contiguous()
    return GaussianModel(
        means=stack(["x", "y", "z"]),
        sh_dc=stack(["f_dc_0", "f_dc_1", "f_dc_2"]).reshape(P, 1, 3),
        sh_rest=sh_rest,
        opacity_logit=stack(["opacity"]),
        scale_log=stack(["scale_0", "scale_1", "scale_2"]),
        quat=stack(["rot_0", "rot_1", "rot_2", "rot_3"]),
        sh_degree=degree,
    )


def write_gaussian_ply(model: GaussianModel, path: PathLike) -> None:
    """Write ``model`` as an upstream-compatible ``point_cloud.ply`` (atomically).

    Binary little-endian, all properties f4, upstream attribute order, zero normals, SH
    channel-major. Parent folders are created.

    Raises:
        ValueError: if ``model`` is not a GaussianModel or holds NaN/Inf (the file would not load).
    """
    if not isinstance(model, GaussianModel):
        raise ValueError(f"model must be a GaussianModel, got {type(model).__name__}")
    path = Path(path)
    m = model.detach().to(device="cpu", dtype=torch.float32)
    P = m.num_gaussians
    K = num_sh_coeffs(m.sh_degree) - 1
    parts = [
        m.means,
        torch.zeros(P, 3),
        m.sh_dc.reshape(P, 3),
        m.sh_rest.transpose(1, 2).reshape(P, 3 * K),  # channel-major, as upstream save_ply
        m.opacity_logit,
        m.scale_log,
        m.quat,
    ]
    values = torch.cat(parts, dim=1).numpy()
    names = _attribute_names(m.sh_degree)
    n_bad = int((~np.isfinite(values)).sum())
    if n_bad:
        cols = [names[j] for j in np.nonzero(~np.isfinite(values).all(0))[0]]
        raise ValueError(f"write_gaussian_ply {path}: model has {n_bad} non-finite values "
                         f"(properties {cols})")
    arr = np.empty(P, dtype=[(n, "<f4") for n in names])
    for j, n in enumerate(names):
        arr[n] = values[:, j]
    ply = PlyData([PlyElement.describe(arr, "vertex")], text=False, byte_order="<")
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            ply.write(f)


def write_points_ply(path: PathLike, xyz, rgb=None) -> None:
    """Write a coloured point cloud as upstream ``storePly`` (the model folder's ``input.ply``).

    Properties ``x, y, z, nx, ny, nz`` (f4, zero normals) and ``red, green, blue`` (u1), binary
    little-endian, written atomically.

    Args:
        xyz: ``[N, 3]`` points (numpy or torch).
        rgb: ``[N, 3]`` colours, uint8 0..255 or floats in [0, 1]; None -> black.

    Raises:
        ValueError: on bad shapes or non-finite points.
    """
    path = Path(path)
    xyz = _np(xyz)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError(f"xyz must have shape [N, 3], got {list(xyz.shape)}")
    if not np.all(np.isfinite(xyz)):
        raise ValueError(f"xyz has {int((~np.isfinite(xyz)).sum())} non-finite values")
    N = xyz.shape[0]
    if rgb is None:
        cols = np.zeros((N, 3), np.uint8)
    else:
        rgb = _np(rgb)
        if rgb.shape != (N, 3):
            raise ValueError(f"rgb must have shape [{N}, 3] like xyz, got {list(rgb.shape)}")
        if np.issubdtype(rgb.dtype, np.floating):
            cols = np.clip(np.round(rgb * 255.0), 0, 255).astype(np.uint8)
        else:
            cols = np.clip(rgb, 0, 255).astype(np.uint8)
    dtype = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("nx", "<f4"), ("ny", "<f4"),
             ("nz", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")]
    arr = np.zeros(N, dtype=dtype)
    arr["x"], arr["y"], arr["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    arr["red"], arr["green"], arr["blue"] = cols[:, 0], cols[:, 1], cols[:, 2]
    ply = PlyData([PlyElement.describe(arr, "vertex")], text=False, byte_order="<")
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            ply.write(f)


def read_points_ply(path: PathLike) -> Tuple[np.ndarray, Optional[np.ndarray]]:
    """Read a point cloud PLY (e.g. ``input.ply``/``points3d.ply``) as upstream ``fetchPly``.

    Returns:
        ``(xyz [N, 3] float64, rgb [N, 3] float64 in [0, 1] or None if no colour properties)``.

    Raises:
        ValueError: naming the file for a missing/unparsable file or missing x, y, z.
    """
    path = Path(path)
    what = "point PLY"
    el = _vertex(_read_ply(path, what), path, what)
    names = [p.name for p in el.properties]
    missing = [n for n in ("x", "y", "z") if n not in names]
    if missing:
        raise ValueError(f"{what} {path}: missing vertex properties {missing} (found {names})")
    d = el.data
    xyz = np.stack([np.asarray(d[n], np.float64) for n in ("x", "y", "z")], 1).reshape(-1, 3)
    rgb = None
    if all(n in names for n in ("red", "green", "blue")):
        rgb = np.stack([np.asarray(d[n], np.float64) for n in ("red", "green", "blue")], 1) / 255.0
    return xyz, rgb


def _np(x) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().numpy()
    return np.asarray(x)
