"""Level of detail inside the Localizer: a reduced model for the geometric stage and candidates.

The geometric stage (render, match, PnP) and the candidate renders only need the model as it
looks at their working resolution; a model of millions of Gaussians costs there what its
Gaussians cost, not what the image needs. :class:`ReducedModels` builds, once per working
resolution, a reduced model (``icomma_plugin.lod.reduce_model``: Gaussians that never reach a
pixel left out, those far below a pixel merged, a cap on the count) from the model's cameras (or
views sampled around the scene when it has none), keeps it in memory and, with a cache folder,
on disk beside the candidate index (``candidate_cache.py``). The photometric refinement and the
verdict render the full model.

``Localizer(lod=...)``: ``"auto"`` (the default) reduces models of more than
:data:`LOD_AUTO_GAUSSIANS` Gaussians with :data:`LOD_AUTO_CONFIG` (a smaller model renders
exactly as without a level of detail); ``None`` or ``"off"``: never; a :class:`~icomma_plugin.lod.
LodConfig` (or a mapping of its fields, e.g. a Hydra group): always, with that config.

Working resolutions are shared on a ladder: a render at focal length ``f`` uses the reduced model
built for the smallest rung ``2^(k/4) >= f`` (at most 19 % sharper than needed; sizes rounded up
to 16 px), so that photos whose cameras differ a little do not each build one.
"""
from __future__ import annotations

import dataclasses
import json
import math
import time
from typing import Any, Callable, Dict, List, Mapping, Optional, Tuple

import numpy as np

from ..camera import Intrinsics
from ..checks import config_from_dict
from ..gaussians import GaussianModel
from ..lod import LodConfig, reduce_model
from .candidate_cache import CandidateCache, lod_fields

__all__ = ["LOD_AUTO_CONFIG", "LOD_AUTO_GAUSSIANS", "LOD_MODES", "ReducedModels", "lod_config",
           "lod_intrinsics"]

#: ``lod="auto"`` reduces models with more Gaussians than this.
LOD_AUTO_GAUSSIANS = 200_000
#: ... with this config (a cap of 100k: lego 300k at 800 px renders 1.9x faster, 1M 4x;
#: docs/SPEED.md, issue 19).
LOD_AUTO_CONFIG = LodConfig(max_gaussians=100_000)
#: The modes of a Localizer's level of detail (``details["lod"]["mode"]``).
LOD_MODES = ("auto", "off", "config")

#: Rungs of the working-resolution ladder per doubling of the focal length.
_RUNGS_PER_OCTAVE = 4


def lod_config(lod: Any, num_gaussians: int) -> Tuple[str, Optional[LodConfig]]:
    """(mode, config or None) of a Localizer's ``lod`` argument for a model of that size.

    Raises:
        ValueError: ``lod`` is none of ``"auto"``, ``"off"``, None, a ``LodConfig`` or a mapping
            of its fields (the message names ``lod``).
    """
    if lod is None or (isinstance(lod, str) and lod.lower() in ("off", "none")):
        return "off", None
    if isinstance(lod, str) and lod.lower() == "auto":
        return "auto", LOD_AUTO_CONFIG if num_gaussians > LOD_AUTO_GAUSSIANS else None
    if isinstance(lod, LodConfig):
        return "config", lod
    if isinstance(lod, Mapping):
        try:
            return "config", config_from_dict(LodConfig, lod, "lod")
        except ValueError as e:
            raise ValueError(f"lod: {e}") from e
    raise ValueError("lod must be 'auto', 'off', None, a LodConfig or a mapping of its fields, "
                     f"got {lod!r}")


def lod_intrinsics(intrinsics: Intrinsics) -> Intrinsics:
    """The rung of the working-resolution ladder that serves renders at ``intrinsics``.

    The camera scaled so that its larger focal length is the smallest ``2^(k/4)`` at or above
    it (module docstring), its sizes rounded up to a multiple of 16 px and its principal point at
    the centre, so that cameras a few percent apart share a rung; a rung is its own rung.
    """
    focal = max(intrinsics.fx, intrinsics.fy)
    rung = 2.0 ** (math.ceil(_RUNGS_PER_OCTAVE * math.log2(focal) - 1e-6) / _RUNGS_PER_OCTAVE)
    s = rung / focal

    def side(n: int) -> int:
        return max(16, 16 * math.ceil(n * s / 16 - 1e-6))

    return Intrinsics(side(intrinsics.width), side(intrinsics.height),
                      rung * (intrinsics.fx / focal), rung * (intrinsics.fy / focal))


class ReducedModels:
    """The reduced models of one Localizer's model, one per working resolution (rung).

    Args:
        model: the full model (the Localizer's, after its SH simplification).
        config: what ``reduce_model`` may leave out and merge.
        cameras_c2w: poses the footprints are taken from (the model's cameras, or sampled views).
        cache: where they are kept on disk (None: in memory only).
        model_id: the model's fingerprint, or a callable that computes it (for the disk key).
    """

    def __init__(self, model: GaussianModel, config: LodConfig, cameras_c2w: List[np.ndarray],
                 cache: Optional[CandidateCache], model_id: Callable[[], str]):
        self.model, self.config, self.cameras_c2w = model, config, cameras_c2w
        self.cache, self._model_id = cache, model_id
        self._models: Dict[str, Tuple[GaussianModel, Dict[str, Any]]] = {}
        self._scenes: Dict[Tuple[str, Optional[int]], Any] = {}
        self.events: List[Dict[str, Any]] = []  # one per reduced model made or loaded
        self.builds = 0  # reduced models built here (not loaded from disk)

    def identity(self) -> Dict[str, Any]:
        """The config as a dict (in the candidate index's key, and in results)."""
        return dataclasses.asdict(self.config)

    def model_at(self, intrinsics: Intrinsics) -> Tuple[GaussianModel, Dict[str, Any]]:
        """(reduced model, its ``LodInfo`` as a dict) for renders at ``intrinsics`` (built once)."""
        rung = lod_intrinsics(intrinsics)
        key = json.dumps(rung.to_json(), sort_keys=True)
        if key not in self._models:
            t0 = time.perf_counter()
            if self.cache is None:
                value, built = self._build(rung), True
            else:
                fields = lod_fields(self._model_id(), self.identity(), rung, self.cameras_c2w,
                                    str(self.model.dtype))
                value, built = self.cache.get_or_build_reduced(fields, lambda: self._build(rung))
            self._models[key] = value
            self.events.append({"intrinsics": rung.to_json(), "gaussians":
                                value[0].num_gaussians, "source": "built" if built else "disk",
                                "seconds": time.perf_counter() - t0})
        return self._models[key]

    def scene_at(self, intrinsics: Intrinsics, sh_degree: Optional[int]):
        """The prepared scene (``render.prepare_scene``) of :meth:`model_at` at ``sh_degree``."""
        from ..render import prepare_scene

        key = (json.dumps(lod_intrinsics(intrinsics).to_json(), sort_keys=True), sh_degree)
        if key not in self._scenes:
            self._scenes[key] = prepare_scene(self.model_at(intrinsics)[0], sh_degree)
        return self._scenes[key]

    def _build(self, rung: Intrinsics) -> Tuple[GaussianModel, Dict[str, Any]]:
        self.builds += 1
        device = self.model.device
        reduced, info = reduce_model(self.model.to("cpu"), rung, self.cameras_c2w, self.config)
        return reduced.to(device), info.to_dict()
