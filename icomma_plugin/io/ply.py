"""3DGS ``point_cloud.ply`` (Gaussians) and ``input.ply`` (coloured points) reading and writing.

Reading parses the header here and reads only the ``vertex`` element, in one block for binary
files (plyfile, used for writing, reads row by row and allocates what a header's counts claim).

Layout of a Gaussian PLY (upstream ``GaussianModel.save_ply`` / ``load_ply``): one ``vertex``
element, every property ``float`` (f4), binary little-endian, in the order
``x, y, z, nx, ny, nz, f_dc_0..2, f_rest_0..(3K-1), opacity, scale_0..2, rot_0..3`` where
K = (D+1)^2 - 1 for SH degree D. ``f_rest`` is channel-major: ``f_rest_0..K-1`` are the R
coefficients 1..K, then G, then B. Normals are written as zeros and ignored on reading. The stored
values are raw (opacity logit, log-scale, unnormalised quaternion w,x,y,z), exactly
:class:`~icomma_plugin.gaussians.GaussianModel`'s fields.
"""
from __future__ import annotations

import functools
import logging
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Optional, Tuple, Union

import numpy as np
import torch
from plyfile import PlyData, PlyElement

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


# PLY scalar type names -> numpy codes (the PLY 1.0 names and their sized aliases).
_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2",
              "int16": "i2", "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4",
              "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4", "double": "f8",
              "float64": "f8"}
_FORMATS = {"ascii": "<", "binary_little_endian": "<", "binary_big_endian": ">"}
# A 3DGS header is ~1.5 KB; anything past this without 'end_header' is not a PLY header.
_MAX_HEADER = 1 << 20


@dataclass
class _Element:
    """One ``element`` of a PLY header.

    Its row count and ``(name, numpy code or None)`` properties, None marking a list property.
    """

    name: str
    count: int
    props: List[Tuple[str, Optional[str]]] = field(default_factory=list)


def _header_error(where: str, no: int, line: str, msg: str) -> ValueError:
    return ValueError(f"{where}: cannot parse PLY header line {no} {line[:80]!r}: {msg}")


def _parse_header(path: Path, what: str) -> Tuple[bool, str, List[_Element], int]:
    """``(is_ascii, byte order, elements, body offset)`` of a PLY file, checked line by line."""
    with open(path, "rb") as f:
        head = f.read(_MAX_HEADER)
    if head[:3] != b"ply":
        raise ValueError(f"{what} {path}: not a PLY file (it does not start with 'ply', "
                         f"got {head[:4]!r})")
    nl = next((n for n in (b"\r\n", b"\n", b"\r") if head[3:3 + len(n)] == n), None)
    if nl is None:
        raise ValueError(f"{what} {path}: cannot parse PLY header (no line break after 'ply')")
    end = head.find(nl + b"end_header" + nl)
    if end < 0:
        raise ValueError(f"{what} {path}: cannot parse PLY header (no 'end_header' line in the "
                         f"first {min(len(head), _MAX_HEADER)} bytes: truncated or not a PLY)")
    try:
        lines = head[3 + len(nl):end].decode("ascii").split(nl.decode("ascii"))
    except UnicodeDecodeError as e:
        raise ValueError(f"{what} {path}: cannot parse PLY header (not ASCII text: {e})") from e
    fmt = None
    elements: List[_Element] = []
    for no, line in enumerate(lines, start=2):
        words = line.split()
        bad = functools.partial(_header_error, f"{what} {path}", no, line)
        if not words or words[0] in ("comment", "obj_info"):
            continue
        key = words[0]
        if fmt is None:
            if key != "format" or len(words) != 3 or words[1] not in _FORMATS \
                    or words[2] != "1.0":
                raise bad(f"expected 'format <{'|'.join(_FORMATS)}> 1.0' first")
            fmt = words[1]
        elif key == "element":
            if len(words) != 3 or not words[2].isdigit() or len(words[2]) > 18:
                raise bad("expected 'element <name> <count>' with a count below 10^18")
            if any(e.name == words[1] for e in elements):
                raise bad(f"element {words[1]!r} declared twice")
            elements.append(_Element(words[1], int(words[2])))
        elif key == "property":
            if not elements:
                raise bad("property before any element")
            if len(words) == 5 and words[1] == "list":
                if words[2] not in _PLY_TYPES or words[3] not in _PLY_TYPES:
                    raise bad(f"unknown type (known: {', '.join(_PLY_TYPES)})")
                name, code = words[4], None
            elif len(words) == 3:
                if words[1] not in _PLY_TYPES:
                    raise bad(f"unknown type {words[1]!r} (known: {', '.join(_PLY_TYPES)})")
                name, code = words[2], _PLY_TYPES[words[1]]
            else:
                raise bad("expected 'property <type> <name>' or "
                          "'property list <count type> <type> <name>'")
            if any(n == name for n, _ in elements[-1].props):
                raise bad(f"property {name!r} declared twice")
            elements[-1].props.append((name, code))
        else:
            raise bad("expected 'element', 'property', 'comment' or 'obj_info'")
    if fmt is None:
        raise ValueError(f"{what} {path}: cannot parse PLY header (no 'format' line)")
    body = end + len(nl) * 2 + len(b"end_header")
    return fmt == "ascii", _FORMATS[fmt], elements, body


def _read_vertex(path: Path, what: str) -> np.ndarray:
    """The ``vertex`` element of a PLY file as a structured array (one field per property).

    Only the vertex element is read (elements after it are not). Every row count is checked
    against the bytes the file has before anything is allocated, so a corrupt count is an error,
    not a huge allocation.
    """
    if not path.exists():
        raise ValueError(f"{what} {path}: file not found")
    if not path.is_file():
        raise ValueError(f"{what} {path}: not a regular file")
    ascii_, order, elements, body = _parse_header(path, what)
    names = [e.name for e in elements]
    if "vertex" not in names:
        raise ValueError(f"{what} {path}: no 'vertex' element (elements found: {names})")
    k = names.index("vertex")
    vertex = elements[k]
    lists = [n for n, code in vertex.props if code is None]
    if lists:
        raise ValueError(f"{what} {path}: vertex properties {lists} are lists; expected scalars")
    if not vertex.props:
        raise ValueError(f"{what} {path}: the vertex element has no properties")
    dtype = np.dtype([(n, order + code) for n, code in vertex.props])
    if ascii_:
        return _read_ascii_rows(path, what, elements[:k], vertex, dtype, body)
    size = path.stat().st_size - body
    offset = 0
    for e in elements[:k]:
        if any(code is None for _, code in e.props):
            raise ValueError(f"{what} {path}: element {e.name!r} before 'vertex' has list "
                             f"properties; cannot locate the vertex data in a binary file")
        offset += e.count * sum(np.dtype(code).itemsize for _, code in e.props)
    need = offset + vertex.count * dtype.itemsize
    if need > size:
        raise ValueError(f"{what} {path}: early end-of-file: the header declares "
                         f"{vertex.count} vertices ({need} bytes with the elements before them) "
                         f"but only {max(size, 0)} bytes follow the header (truncated file or "
                         f"corrupt count)")
    with open(path, "rb") as f:
        f.seek(body + offset)
        buf = f.read(vertex.count * dtype.itemsize)
    return np.frombuffer(buf, dtype=dtype).copy()


def _read_ascii_rows(path: Path, what: str, before: List[_Element], vertex: _Element,
                     dtype: np.dtype, body: int) -> np.ndarray:
    """Vertex rows of an ASCII PLY (one row per line, after the rows of the elements before)."""
    with open(path, "rb") as f:
        f.seek(body)
        raw = f.read()
    try:
        text = raw.decode("ascii")
    except UnicodeDecodeError as e:
        raise ValueError(f"{what} {path}: ASCII PLY body is not ASCII text ({e})") from e
    lines = text.replace("\r\n", "\n").replace("\r", "\n").split("\n")
    start = sum(e.count for e in before)
    # Each row needs at least one character per property plus a separator or line break.
    if start + vertex.count > len(lines) or 2 * len(vertex.props) * vertex.count > len(raw):
        raise ValueError(f"{what} {path}: early end-of-file: the header declares "
                         f"{vertex.count} vertices after {start} other rows but the body has "
                         f"only {len(lines)} lines ({len(raw)} bytes)")
    rows = [ln.split() for ln in lines[start:start + vertex.count]]
    width = len(vertex.props)
    for i, r in enumerate(rows):
        if len(r) != width:
            raise ValueError(f"{what} {path}: vertex row {i} has {len(r)} values, expected "
                             f"{width} (one per property)")
    out = np.empty(vertex.count, dtype=dtype)
    for j, (name, code) in enumerate(vertex.props):
        col = [r[j] for r in rows]
        try:
            if code[0] == "f":
                with np.errstate(over="ignore"):  # out-of-range -> Inf, rejected by the callers
                    out[name] = np.array(col, dtype=np.float64)
            else:
                vals = [int(v) for v in col]
                info = np.iinfo(np.dtype(code))
                if any(v < info.min or v > info.max for v in vals):
                    raise ValueError(f"out of range for {np.dtype(code).name}")
                out[name] = vals
        except ValueError as e:
            raise ValueError(f"{what} {path}: vertex property {name!r}: malformed ASCII values "
                             f"({e})") from e
    return out


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
            truncated (also a vertex count larger than the file holds), no ``vertex`` element,
            missing properties (named), an ``f_rest`` count that matches no SH degree,
            non-float32 properties, NaN/Inf values (count and fields).
    """
    path = Path(path)
    what = "Gaussian PLY"
    data = _read_vertex(path, what)
    types = {n: data.dtype[n] for n in data.dtype.names}

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
        path: the ``.ply`` file to write.
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
        ``(xyz [N, 3] float64, rgb [N, 3] float64 in [0, 1] or None if no colour properties)``;
        colours are the stored 0..255 values divided by 255, as upstream.

    Raises:
        ValueError: naming the file for a missing/unparsable/truncated file, missing x, y, z,
            non-finite points or colours outside 0..255.
    """
    path = Path(path)
    what = "point PLY"
    d = _read_vertex(path, what)
    names = list(d.dtype.names)
    missing = [n for n in ("x", "y", "z") if n not in names]
    if missing:
        raise ValueError(f"{what} {path}: missing vertex properties {missing} (found {names})")
    xyz = np.stack([np.asarray(d[n], np.float64) for n in ("x", "y", "z")], 1).reshape(-1, 3)
    n_bad = int((~np.isfinite(xyz)).sum())
    if n_bad:
        raise ValueError(f"{what} {path}: {n_bad} non-finite (NaN/Inf) x/y/z values in "
                         f"{len(xyz)} points")
    rgb = None
    if all(n in names for n in ("red", "green", "blue")):
        rgb = np.stack([np.asarray(d[n], np.float64) for n in ("red", "green", "blue")],
                       1).reshape(-1, 3)
        out = ~((rgb >= 0) & (rgb <= 255))  # also NaN
        if out.any():
            raise ValueError(f"{what} {path}: {int(out.sum())} red/green/blue values outside "
                             f"0..255 (or NaN)")
        rgb = rgb / 255.0
    return xyz, rgb


def _np(x) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().numpy()
    return np.asarray(x)
