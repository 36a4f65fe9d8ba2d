"""The candidate index on disk: rendered once per model and camera, loaded by every later call.

A single-photo call without a start pose would otherwise render and describe every candidate view
(about 160 on a real capture, tens of seconds on a CPU) each time. The index is stored as one file
per key in the ``candidates/`` folder of the cache folder (default ``~/.cache/icomma``;
``ICOMMA_CACHE_DIR`` or the Localizer's ``cache_dir`` move it; it is never written into the user's
model folder unless that folder is given as the cache folder).

The key is a hash of everything the renders' features depend on: the model's content (a hash of
its Gaussians), the candidate poses (the model's cameras, their names), the camera of the renders,
the candidate search's constants, the source photos (names, cameras, files) when they describe
cameras, the matcher and its settings, the background, the backend and the render settings, and
the file format. When any of them changes, the key changes and the index
is built again. Files are written atomically, and a lock file per key makes a second process that
asks for the same index at the same time wait for the first and load its result instead of
building it again.

The reduced models of the level of detail (``lod.reduce_model``, built by the Localizer for its
geometric stage and candidate renders) are stored beside the indices, as ``lod-<key>.pt``, keyed by
the model's fingerprint, the ``LodConfig``, the working camera and the poses they were built from
(:func:`lod_fields`), with the same atomic writes and locks.

The folder is kept under a size cap (``ICOMMA_CACHE_MAX_GB``, default 4; 0: none), as ccache
does: each load marks its file as used (its modification time), and after each write the least
recently used files are removed until the folder is under the cap again. A sweep over models or
settings leaves an index behind per key, and the keys of older settings, formats included, are
never asked for again; they are the first to go. Only the cache's own files are touched
(``<32 hex>.pt`` and ``lod-<32 hex>.pt``, their locks, and temporary files of a write a day old).
"""
from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import re
import time
from pathlib import Path
from typing import Any, Callable, Dict, List, Mapping, Optional, Tuple, TypeVar, Union

import numpy as np
import torch

from ..gaussians import GaussianModel
from ..io.atomic import atomic_path, file_lock
from .candidates import CandidateIndex

logger = logging.getLogger(__name__)

__all__ = [
    "CACHE_FORMAT",
    "CandidateCache",
    "default_cache_dir",
    "default_max_bytes",
    "lod_fields",
    "matcher_identity",
    "model_fingerprint",
]

#: Bump when the stored index changes meaning (old files are then never read: the key changes).
#: 2: a camera is described by a photo of its name only at the photo's pose.
CACHE_FORMAT = 2

PathLike = Union[str, os.PathLike]
T = TypeVar("T")

_MODEL_TENSORS = ("means", "sh_dc", "sh_rest", "opacity_logit", "scale_log", "quat")


def default_cache_dir() -> Path:
    """``$ICOMMA_CACHE_DIR``, else ``$XDG_CACHE_HOME/icomma`` or ``~/.cache/icomma``."""
    env = os.environ.get("ICOMMA_CACHE_DIR")
    if env:
        return Path(env).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or "~/.cache"
    return Path(base).expanduser() / "icomma"


#: The candidates folder's size cap unless ``ICOMMA_CACHE_MAX_GB`` says otherwise (an index of a
#: real capture's 160 cameras is 6-15 MB, a reduced model of a 1M model some 100 MB).
DEFAULT_MAX_GB = 4.0

#: The names of the cache's own files: an index, or a reduced model (``lod-``); group 1 the key.
_CACHE_FILE = re.compile(r"^(?:lod-)?([0-9a-f]{32})\.pt$")

#: A temporary file of a write older than this (seconds) is a crashed write's leftover.
_STALE_TMP_S = 86400.0


def default_max_bytes() -> Optional[int]:
    """The size cap in bytes: ``$ICOMMA_CACHE_MAX_GB`` in GiB, else 4 GiB.

    0 or less, or inf: None (no cap). A value that is not a number is reported and the default kept.
    """
    text = os.environ.get("ICOMMA_CACHE_MAX_GB")
    gb = DEFAULT_MAX_GB
    if text is not None and text.strip():
        try:
            gb = float(text)
        except ValueError:
            logger.warning("ICOMMA_CACHE_MAX_GB=%r is not a number of GiB: the cap stays %g GiB",
                           text, DEFAULT_MAX_GB)
        if math.isnan(gb):
            gb = DEFAULT_MAX_GB
    return None if gb <= 0 or math.isinf(gb) else int(gb * (1 << 30))


def model_fingerprint(model: GaussianModel) -> str:
    """A hash of the model's content (its Gaussians, bit for bit, and its SH degree)."""
    h = hashlib.blake2b(digest_size=16)
    h.update(str(model.sh_degree).encode())
    for name in _MODEL_TENSORS:
        t = getattr(model, name).detach().cpu().contiguous()
        h.update(name.encode() + str(tuple(t.shape)).encode() + str(t.dtype).encode())
        h.update(t.view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    return h.hexdigest()


def matcher_identity(matcher) -> Dict[str, Any]:
    """What a matcher's features depend on: its class, name and plain settings."""
    cls = type(matcher)
    settings = {k: v for k, v in sorted(vars(matcher).items())
                if not k.startswith("_") and isinstance(v, (bool, int, float, str, type(None)))}
    return {"class": f"{cls.__module__}.{cls.__qualname__}",
            "name": getattr(matcher, "name", None), "settings": settings}


def _hash_poses(c2ws) -> str:
    h = hashlib.blake2b(digest_size=16)
    for T in c2ws:
        h.update(np.ascontiguousarray(T, np.float64).tobytes())
    return h.hexdigest()


def index_fields(model_id: str, cameras_c2w, names, intrinsics, cfg, matcher,
                 render: Mapping[str, Any], photos: Optional[str] = None) -> Dict[str, Any]:
    """The key's fields (JSON): see the module docstring."""
    return {
        "format": CACHE_FORMAT,
        "model": model_id,
        "cameras": _hash_poses(cameras_c2w),
        "names": hashlib.blake2b("\n".join(names).encode(), digest_size=8).hexdigest(),
        "intrinsics": intrinsics.to_json(),
        "candidates": {"num_sampled": cfg.num_sampled, "rank_side": cfg.rank_side},
        "photos": photos,
        "matcher": matcher_identity(matcher),
        "render": dict(render),
    }


def lod_fields(model_id: str, lod: Mapping[str, Any], intrinsics, cameras_c2w,
               dtype: str) -> Dict[str, Any]:
    """The key's fields of a reduced model (JSON).

    The model, its ``LodConfig`` (as a dict), the working camera, the poses it was built from
    and the dtype.
    """
    return {"format": CACHE_FORMAT, "kind": "lod", "model": model_id, "lod": dict(lod),
            "intrinsics": intrinsics.to_json(), "cameras": _hash_poses(cameras_c2w),
            "dtype": dtype}


class CandidateCache:
    """Candidate indices stored under ``directory`` (``<key>.pt``, one per key).

    ``max_bytes``: the folder's size cap (module docstring); None: ``default_max_bytes()``, 0:
    no cap.
    """

    def __init__(self, directory: Optional[PathLike] = None, max_bytes: Optional[int] = None):
        self.directory = Path(directory).expanduser() if directory else (
            default_cache_dir() / "candidates")
        if max_bytes is not None and (isinstance(max_bytes, bool) or not isinstance(max_bytes, int)
                                      or max_bytes < 0):
            raise ValueError(f"max_bytes must be None or an int >= 0, got {max_bytes!r}")
        self.max_bytes = default_max_bytes() if max_bytes is None else (max_bytes or None)

    @staticmethod
    def key(fields: Mapping[str, Any]) -> str:
        """The file name stem of an index with these fields."""
        text = json.dumps(fields, sort_keys=True, default=str)
        return hashlib.blake2b(text.encode(), digest_size=16).hexdigest()

    def path(self, key: str) -> Path:
        """Where the index of ``key`` is stored."""
        return self.directory / f"{key}.pt"

    def load(self, key: str) -> Optional[CandidateIndex]:
        """The stored index of ``key``, or None (absent, or unreadable: it is then rebuilt)."""
        return self._load(self.path(key), "candidate cache",
                          lambda d: CandidateIndex.from_state(d["index"]))

    @staticmethod
    def _load(p: Path, what: str, decode: Callable[[Dict[str, Any]], Any]):
        """``decode`` of the stored file ``p``, or None (absent, another format, damaged)."""
        if not p.is_file():
            return None
        try:
            d = torch.load(p, map_location="cpu", weights_only=True)
            if d.get("format") != CACHE_FORMAT:
                return None
            value = decode(d)
        except Exception as e:  # noqa: BLE001 - a damaged cache file is rebuilt, never fatal
            logger.warning("%s %s unreadable (%s: %s): building it again", what, p,
                           type(e).__name__, e)
            return None
        try:  # used now: the last to go when the folder is over its cap
            os.utime(p)
        except OSError:
            pass  # (another user's file in a shared cache)
        return value

    def _save(self, p: Path, fields: Mapping[str, Any], payload: Dict[str, Any]) -> Path:
        """Store ``payload`` with the format and the key's fields, atomically; then ``prune``."""
        with atomic_path(p) as tmp:
            torch.save({"format": CACHE_FORMAT,
                        "fields": json.loads(json.dumps(fields, default=str)), **payload}, tmp)
        self.prune(keep=p)
        return p

    def prune(self, keep: Optional[Path] = None) -> List[Path]:
        """Remove the least recently used files until the folder is under ``max_bytes``.

        ``keep``: a file never removed (the one just written). Also removes the temporary files
        of writes that crashed a day or more ago. Returns the cache files removed.
        """
        entries, total, now = [], 0, time.time()
        try:
            names = list(self.directory.iterdir())
        except OSError:
            return []
        for p in names:
            try:
                st = p.stat()
            except OSError:
                continue  # removed meanwhile
            if p.name.startswith(".") and p.name.endswith(".tmp"):
                if now - st.st_mtime > _STALE_TMP_S:
                    _unlink(p)
                continue
            m = _CACHE_FILE.match(p.name)
            if m:
                entries.append((st.st_mtime, p.name, st.st_size, p, m.group(1)))
                total += st.st_size
        if self.max_bytes is None or total <= self.max_bytes:
            return []
        removed, freed = [], 0
        for _, _, size, p, key in sorted(entries):
            if total - freed <= self.max_bytes:
                break
            if keep is not None and p == Path(keep):
                continue
            if _unlink(p):
                removed.append(p)
                freed += size
                _unlink(self.directory / f"{key}.lock")
        if removed:
            logger.info("cache %s over %.1f GiB: removed the %d least recently used files "
                        "(%.0f MB)", self.directory, self.max_bytes / (1 << 30), len(removed),
                        freed / 1e6)
        return removed

    def save(self, key: str, fields: Mapping[str, Any], index: CandidateIndex) -> Path:
        """Store ``index`` atomically (a reader never sees half a file)."""
        return self._save(self.path(key), fields, {"index": index.to_state()})

    def get_or_build(self, fields: Mapping[str, Any], build: Callable[[], CandidateIndex]
                     ) -> Tuple[CandidateIndex, bool]:
        """(index, built now): the stored index of ``fields``, else ``build()`` stored.

        Under a lock per key: a second process asking at the same time waits and loads.
        """
        key = self.key(fields)
        return self._get_or_build(key, lambda: self.load(key),
                                  lambda index: self.save(key, fields, index), build)

    # ------------------------------------------------------------------ reduced models
    def reduced_path(self, key: str) -> Path:
        """Where the reduced model of ``key`` is stored."""
        return self.directory / f"lod-{key}.pt"

    def load_reduced(self, key: str) -> Optional[Tuple[GaussianModel, Dict[str, Any]]]:
        """(reduced model, its ``LodInfo`` as a dict) stored under ``key``, or None."""
        return self._load(self.reduced_path(key), "reduced model", lambda d: (
            GaussianModel(*(d["model"][n] for n in _MODEL_TENSORS), int(d["sh_degree"])),
            dict(d["info"])))

    def save_reduced(self, key: str, fields: Mapping[str, Any],
                     reduced: Tuple[GaussianModel, Dict[str, Any]]) -> Path:
        """Store ``(model, info dict)`` atomically."""
        model, info = reduced
        return self._save(self.reduced_path(key), fields, {
            "model": {n: getattr(model, n).detach().cpu().contiguous() for n in _MODEL_TENSORS},
            "sh_degree": int(model.sh_degree), "info": dict(info)})

    def get_or_build_reduced(
        self, fields: Mapping[str, Any],
        build: Callable[[], Tuple[GaussianModel, Dict[str, Any]]],
    ) -> Tuple[Tuple[GaussianModel, Dict[str, Any]], bool]:
        """((reduced model, info), built now): stored under ``fields``, else ``build()`` stored."""
        key = self.key(fields)
        return self._get_or_build(key, lambda: self.load_reduced(key),
                                  lambda r: self.save_reduced(key, fields, r), build)

    def _get_or_build(self, key: str, load: Callable[[], Optional[T]],
                      save: Callable[[T], Any], build: Callable[[], T]) -> Tuple[T, bool]:
        """(value, built now): ``load()``, else ``build()`` then ``save`` it, under a lock."""
        value = load()
        if value is not None:
            return value, False
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            logger.warning("cache folder %s not writable (%s): not cached", self.directory, e)
            return build(), True
        with file_lock(self.directory / f"{key}.lock"):
            value = load()
            if value is not None:
                return value, False
            value = build()
            try:
                save(value)
            except OSError as e:
                logger.warning("could not store %s in %s (%s)", key, self.directory, e)
            return value, True


def _unlink(p: Path) -> bool:
    """Remove ``p``; False when it was gone already or cannot be removed."""
    try:
        p.unlink()
        return True
    except OSError:
        return False
