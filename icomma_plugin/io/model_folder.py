"""A trained 3DGS model folder (graphdeco-inria ``train.py -m <model_path>`` output).

Layout::

    <model_path>/cfg_args                                  # str(Namespace(**ModelParams))
    <model_path>/cameras.json                              # only when trained from scratch
    <model_path>/input.ply                                 # initial point cloud (storePly)
    <model_path>/point_cloud/iteration_<N>/point_cloud.ply # Gaussians (see io/ply.py)

``cfg_args`` is read with :func:`parse_cfg_args` (``ast``, never ``eval``, unlike upstream
``get_combined_args``). By default the highest ``iteration_<N>`` is loaded, as upstream's
``searchForMaxIteration``.
"""
from __future__ import annotations

import ast
import dataclasses
import logging
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Union

from ..gaussians import GaussianModel
from .atomic import write_text_atomic
from .cameras_json import CameraEntry, read_cameras_json, write_cameras_json
from .datasets import PRINCIPAL_POINTS
from .ply import read_gaussian_ply, write_gaussian_ply, write_points_ply

log = logging.getLogger(__name__)

PathLike = Union[str, os.PathLike]

__all__ = ["ModelFolder", "parse_cfg_args", "format_cfg_args", "list_iterations",
           "load_model_folder", "write_model_folder"]

_ITER_RE = re.compile(r"iteration_(\d+)")


def training_scale(cfg: Optional[Dict[str, Any]], width: int) -> float:
    """The scale a model was fitted at, relative to source images ``width`` px wide.

    cfg_args ``resolution`` 1/2/4/8 divides; a larger value is a target width; otherwise (-1 /
    absent) upstream keeps images up to 1600 px wide: ``min(1, 1600 / width)``.
    """
    r = cfg.get("resolution") if cfg else None
    try:
        r = None if r is None else int(r)
    except (TypeError, ValueError):
        r = None
    if r in (1, 2, 4, 8):
        return 1.0 / r
    if r is not None and r > 8:
        return float(r) / float(width)
    return min(1.0, 1600.0 / float(width))


@dataclass
class ModelFolder:
    """A loaded model folder.

    Attributes:
        path: the folder.
        cfg: ``cfg_args`` as a dict (e.g. ``source_path``, ``white_background``, ``sh_degree``).
        iteration: the loaded ``iteration_<N>``.
        model: the Gaussians (float32, CPU).
        cameras: ``cameras.json`` entries, ``[]`` if the file is absent.
    """

    path: Path
    cfg: Dict[str, Any]
    iteration: int
    model: GaussianModel
    cameras: List[CameraEntry] = field(default_factory=list)

    def training_scale(self, width: int) -> float:
        """The scale the model was fitted at, relative to source images ``width`` px wide."""
        return training_scale(self.cfg, width)

    def training_side(self) -> Optional[int]:
        """The longer side [px] of the images the model was fitted on, or None without cameras.

        From its cameras and cfg_args.
        """
        if not self.cameras:
            return None
        e = self.cameras[0]
        return max(1, int(round(max(e.width, e.height) * self.training_scale(e.width))))

    @property
    def principal_point(self) -> str:
        """Where the model's fit put its views' principal point: ``"dataset"`` or ``"centre"``.

        cfg_args ``principal_point`` when it says (``icomma-fit`` writes it); else ``"dataset"``
        for a folder with ``metrics.json`` (``icomma-fit`` before it wrote the key, with the
        dataset's cx, cy) and ``"centre"`` for any other (upstream 3DGS ignores cx, cy: its
        cameras hold field-of-view angles alone).
        """
        said = self.cfg.get("principal_point")
        if said in PRINCIPAL_POINTS:
            return said
        return "dataset" if (self.path / "metrics.json").is_file() else "centre"

    @property
    def principal_point_assumed(self) -> bool:
        """Whether `principal_point` is upstream's by default: nothing in the folder says."""
        return (self.cfg.get("principal_point") not in PRINCIPAL_POINTS
                and not (self.path / "metrics.json").is_file())

    def with_principal_point(self, value: Optional[str]) -> "ModelFolder":
        """This folder with its fit's principal point said (``"dataset"`` / ``"centre"``).

        None or ``"auto"``: as it is (`principal_point` reads the folder).
        """
        if value is None or value == "auto":
            return self
        if value not in PRINCIPAL_POINTS:
            raise ValueError(f"principal_point must be auto, dataset or centre, got {value!r}")
        return dataclasses.replace(self, cfg={**self.cfg, "principal_point": value})

    @property
    def white_background(self) -> bool:
        """``cfg['white_background']`` (False when absent), the background 3DGS trained with."""
        return bool(self.cfg.get("white_background", False))


def parse_cfg_args(text: str, path: Optional[PathLike] = None) -> Dict[str, Any]:
    """Parse a ``cfg_args`` text ``Namespace(a=1, b='x', ...)`` into a dict, safely.

    Uses ``ast.parse(mode="eval")`` and ``ast.literal_eval`` on each keyword value: only Python
    literals (numbers, strings, bools, None, tuples/lists/dicts/sets of literals) are accepted,
    nothing is executed.

    Args:
        text: the file content.
        path: the file, only used in error messages.

    Returns:
        ``{key: value}`` in file order.

    Raises:
        ValueError: naming the file for syntax errors, a top level other than ``Namespace(...)``,
            positional or ``**`` arguments, duplicate keys, or non-literal values (named).
    """
    where = f"cfg_args {path}" if path is not None else "cfg_args"
    if not isinstance(text, str):
        raise ValueError(f"{where}: expected text, got {type(text).__name__}")
    try:
        tree = ast.parse(text.strip(), mode="eval")
    except (SyntaxError, ValueError) as e:  # ValueError: e.g. NUL bytes in the text
        raise ValueError(f"{where}: not a Namespace(...) expression ({e})") from e
    except (RecursionError, MemoryError) as e:
        raise ValueError(f"{where}: expression too deeply nested to parse") from e
    call = tree.body
    if not (isinstance(call, ast.Call) and isinstance(call.func, ast.Name)
            and call.func.id == "Namespace"):
        raise ValueError(f"{where}: expected 'Namespace(key=value, ...)', "
                         f"got {text.strip()[:80]!r}")
    if call.args:
        raise ValueError(f"{where}: Namespace(...) must only have keyword arguments")
    out: Dict[str, Any] = {}
    for kw in call.keywords:
        if kw.arg is None:
            raise ValueError(f"{where}: '**' arguments are not allowed in Namespace(...)")
        if kw.arg in out:
            raise ValueError(f"{where}: key {kw.arg!r} given twice")
        try:
            out[kw.arg] = ast.literal_eval(kw.value)
        except (ValueError, TypeError, SyntaxError, MemoryError, RecursionError) as e:
            seg = ast.get_source_segment(text.strip(), kw.value) or "?"
            raise ValueError(
                f"{where}: value of {kw.arg!r} is not a Python literal: {seg[:80]!r}"
            ) from e
    return out


def format_cfg_args(cfg: Dict[str, Any]) -> str:
    """``cfg`` as upstream writes it: ``Namespace(k1=repr(v1), ...)`` with sorted keys.

    Raises:
        ValueError: if a key is not an identifier or a value does not round-trip through
            :func:`parse_cfg_args` (only literals can be stored).
    """
    if not isinstance(cfg, dict):
        raise ValueError(f"cfg must be a dict, got {type(cfg).__name__}")
    parts = []
    for k in sorted(cfg):
        if not (isinstance(k, str) and k.isidentifier()):
            raise ValueError(f"cfg key {k!r} is not a Python identifier")
        v = cfg[k]
        r = repr(v)
        try:
            back = ast.literal_eval(r)
        except (ValueError, SyntaxError) as e:
            raise ValueError(f"cfg[{k!r}] = {r[:80]} is not a Python literal") from e
        if back != v and not (isinstance(v, float) and math.isnan(v)):
            raise ValueError(f"cfg[{k!r}] = {r[:80]} does not round-trip through its repr")
        parts.append(f"{k}={r}")
    return "Namespace(" + ", ".join(parts) + ")"


def list_iterations(path: PathLike) -> List[int]:
    """Sorted ``N`` of the ``point_cloud/iteration_<N>`` folders of a model folder ([] if none)."""
    pc = Path(path) / "point_cloud"
    if not pc.is_dir():
        return []
    its = []
    for p in pc.iterdir():
        m = _ITER_RE.fullmatch(p.name)
        if m and p.is_dir():
            its.append(int(m.group(1)))
    return sorted(its)


def load_model_folder(path: PathLike, iteration: Optional[int] = None) -> ModelFolder:
    """Load a 3DGS model folder.

    Args:
        path: the model folder (``-m`` of upstream train.py).
        iteration: ``N`` of ``point_cloud/iteration_<N>``; None (or -1, as upstream) = the largest.

    Returns:
        ModelFolder. A missing ``cameras.json`` gives ``cameras = []`` and a logged warning
        (upstream writes it only when training from scratch).

    Raises:
        ValueError: naming the path for: missing folder, missing ``cfg_args`` or a bad one (not
            UTF-8, not a ``Namespace(...)`` of literals, a non-bool ``white_background``), no
            ``point_cloud/`` or no ``iteration_*`` folder in it (lists what was found), a requested
            iteration that is absent (lists the available ones), missing/bad ``point_cloud.ply``
            or a bad ``cameras.json``.
    """
    root = Path(path)
    if not root.is_dir():
        raise ValueError(f"model folder {root}: not found (or not a directory)")
    cfg_path = root / "cfg_args"
    if not cfg_path.is_file():
        raise ValueError(f"model folder {root}: missing cfg_args (found {_listing(root)})")
    try:
        cfg_text = cfg_path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as e:
        raise ValueError(f"cfg_args {cfg_path}: not UTF-8 text ({e})") from e
    cfg = parse_cfg_args(cfg_text, cfg_path)
    wb = cfg.get("white_background", False)
    if not isinstance(wb, bool):  # bool('False') is True: refuse rather than guess
        raise ValueError(f"cfg_args {cfg_path}: field 'white_background' must be True or False, "
                         f"got {str(repr(wb))[:80]}")

    pc = root / "point_cloud"
    if not pc.is_dir():
        raise ValueError(f"model folder {root}: no point_cloud/ folder (found {_listing(root)})")
    its = list_iterations(root)
    if not its:
        raise ValueError(f"model folder {root}: no iteration_<N> folder in point_cloud/ "
                         f"(found {_listing(pc)})")
    if iteration is None or iteration == -1:
        iteration = its[-1]
    elif iteration not in its:
        raise ValueError(f"model folder {root}: iteration {iteration} not found "
                         f"(available: {its})")
    ply_path = pc / f"iteration_{iteration}" / "point_cloud.ply"
    if not ply_path.is_file():
        raise ValueError(f"model folder {root}: missing {ply_path.relative_to(root)} "
                         f"(found {_listing(ply_path.parent)})")
    model = read_gaussian_ply(ply_path)

    cam_path = root / "cameras.json"
    if cam_path.is_file():
        cameras = read_cameras_json(cam_path)
    else:
        log.warning("model folder %s: no cameras.json (upstream writes it only when training "
                    "from scratch); continuing without cameras", root)
        cameras = []

    if "sh_degree" in cfg and cfg["sh_degree"] != model.sh_degree:
        log.info("model folder %s: cfg_args sh_degree=%r but the PLY has degree %d; using the PLY",
                 root, cfg["sh_degree"], model.sh_degree)
    return ModelFolder(root, cfg, int(iteration), model, cameras)


def write_model_folder(
    path: PathLike,
    model: GaussianModel,
    cfg: Dict[str, Any],
    cameras: Sequence[CameraEntry],
    iteration: int,
    input_points=None,
    overwrite: bool = False,
) -> Path:
    """Write an upstream-compatible model folder; every file is written atomically.

    Writes ``cfg_args`` (:func:`format_cfg_args`), ``cameras.json``, ``input.ply`` (if
    ``input_points`` is given) and ``point_cloud/iteration_<iteration>/point_cloud.ply``. Other
    iterations already in the folder are kept (a warning is logged if a later one exists, since
    :func:`load_model_folder` loads the latest by default).

    Args:
        path: the folder (created).
        model: Gaussians to store.
        cfg: ``cfg_args`` content, literals only.
        cameras: entries for ``cameras.json``.
        iteration: non-negative int ``N``.
        input_points: None, ``xyz [N, 3]`` or a tuple ``(xyz, rgb)`` (see
            ``io.ply.write_points_ply``); None writes no ``input.ply``.
        overwrite: allow replacing an existing ``iteration_<N>/point_cloud.ply``.

    Returns:
        The path of the written ``point_cloud.ply``.

    Raises:
        ValueError: on a bad iteration/cfg, or if that iteration exists and ``overwrite`` is False.
    """
    if not isinstance(iteration, int) or isinstance(iteration, bool) or iteration < 0:
        raise ValueError(f"iteration must be a non-negative int, got {iteration!r}")
    root = Path(path)
    if root.exists() and not root.is_dir():
        raise ValueError(f"model folder {root}: exists and is not a directory")
    cfg_text = format_cfg_args(cfg)  # validate before writing anything
    ply_path = root / "point_cloud" / f"iteration_{iteration}" / "point_cloud.ply"
    if ply_path.exists() and not overwrite:
        raise ValueError(f"model folder {root}: iteration {iteration} already exists "
                         f"({ply_path}); pass overwrite=True to replace it")
    later = [i for i in list_iterations(root) if i > iteration]
    if later:
        log.warning("model folder %s: writing iteration %d but later iterations %s exist; "
                    "load_model_folder() picks the latest by default", root, iteration, later)

    write_gaussian_ply(model, ply_path)
    write_text_atomic(root / "cfg_args", cfg_text)
    write_cameras_json(root / "cameras.json", list(cameras))
    if input_points is not None:
        if isinstance(input_points, tuple):
            xyz, rgb = input_points
        else:
            xyz, rgb = input_points, None
        write_points_ply(root / "input.ply", xyz, rgb)
    return ply_path


def _listing(folder: Path, n: int = 12) -> str:
    try:
        names = sorted(p.name + ("/" if p.is_dir() else "") for p in folder.iterdir())
    except OSError:
        return "nothing readable"
    if not names:
        return "an empty folder"
    more = f", ... ({len(names)} in all)" if len(names) > n else ""
    return ", ".join(names[:n]) + more
