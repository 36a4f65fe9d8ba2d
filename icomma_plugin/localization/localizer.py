"""One long-lived localizer per model, shared by every caller.

    localizer = Localizer.from_model_folder("output/lego", matcher=make_matcher("xfeat"))
    result = localizer.localize(query)                       # no start pose: candidate views
    result = localizer.localize(query, init_c2w=start_c2w)   # from a rough start
    result.c2w, result.verdict.status, result.verdict.reason

Like pixloc's ``Localizer`` and hloc's ``QueryLocalizer``, it is built once from the model, the
matcher, the method's config and the options (the model's cameras, its training side, backend,
background, cache folder), checks what does not change from query to query once, and owns what
every query reuses: the model's rasterizer inputs, the candidate index (built at the first query
that needs it, per camera, and kept on disk: ``candidate_cache.py``), the reduced models of the
level of detail for large models (``level_of_detail.py``: the geometric stage and the candidate
renders use them, the refinement and the verdict the full model) and the rule that leaves a
query's own camera out of its candidates. The tool, batches, tracking, the benchmark and the speed
benchmark all localize through it. Poses are camera-to-world (OpenCV axes) at this API.
"""
from __future__ import annotations

import dataclasses
import functools
import logging
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np
import torch
from gaussian_renderer_pose._dispatch import BACKENDS as _RASTER_BACKENDS

from ..camera import Intrinsics
from ..gaussians import GaussianModel
from ..pose.convert import as_rigid, invert_rigid
from ..render import model_for_backend, prepare_scene
from .candidate_cache import CandidateCache, index_fields, model_fingerprint
from ..pose.convert import same_pose
from .anchors import PhotoAnchors, SourcePhoto, name_stem
from .candidates import CandidateConfig, CandidateIndex, candidate_intrinsics, usable
from .level_of_detail import ReducedModels, lod_config
from .icomma import LocalizerConfig
from .robust import RobustConfig
from .state import LocalizationState, query_features, scaled_query
from .types import LocalizationResult, Query, TraceRecord
from .verify import can_match

logger = logging.getLogger(__name__)

__all__ = ["BACKENDS", "Localizer", "Method", "source_photos"]

#: The rasterizer backends a Localizer renders with (the rasterizer's own list).
BACKENDS = _RASTER_BACKENDS

#: A method's config: the default (``RobustConfig``) or the paper's (``LocalizerConfig``). A
#: method has ``name``, ``needs_start``, ``needs(matcher)``, ``at_model_side(...)`` and
#: ``run(state, init_w2c) -> MethodOutcome``.
Method = Union[RobustConfig, LocalizerConfig]


def _patch_search(cfg) -> Optional[Tuple[int, float, int, Optional[float]]]:
    """``(window, min NCC, Newton iterations, min margin)`` of a patch-searching method.

    None for one that does not. The iterations are the PnP's sub-pixel step's, which the patch
    search's matches stand in for.
    """
    window = getattr(cfg, "patch_search", None)
    return None if window is None else (window, cfg.patch_search_ncc,
                                        cfg.geometric.subpixel_iterations,
                                        cfg.patch_search_margin)


def _camera_parts(cameras) -> Tuple[List[np.ndarray], List[str], List[Optional[Intrinsics]]]:
    """(c2w, names, intrinsics) of ``cameras``: ``CameraEntry``s or ``[4, 4]`` c2w arrays."""
    from ..io.cameras_json import CameraEntry, entry_to_intrinsics

    c2ws, names, intrs = [], [], []
    for i, cam in enumerate(cameras):
        if isinstance(cam, CameraEntry):
            c2ws.append(as_rigid(cam.c2w, f"cameras[{i}].c2w"))
            names.append(str(cam.img_name))
            intrs.append(entry_to_intrinsics(cam))
        else:
            c2ws.append(as_rigid(cam, f"cameras[{i}]"))
            names.append(f"camera_{i}")
            intrs.append(None)
    return c2ws, names, intrs


@functools.lru_cache(maxsize=8)
def _photos_not_here(src: str) -> None:
    """Say once that the model's source photos are not on this machine."""
    logger.info("the model's source photos %s are not a folder here: the candidate views are "
                "ranked by their renders alone (data.query.dataset=<folder> says where they are)",
                src)


def source_photos(mf, white_background: bool, dataset=None) -> Optional[List[SourcePhoto]]:
    """The photos a model folder was fitted from: the train views of its ``source_path``.

    ``dataset``: that dataset's folder on this machine, when cfg_args' path is another machine's
    (a model trained elsewhere). None when neither names a folder that exists here (or it cannot
    be read: said in the log, the localizer then works with renders only).
    """
    from ..io.datasets import read_dataset

    src = dataset or mf.cfg.get("source_path")
    if not src or not Path(str(src)).expanduser().is_dir():
        if src:  # a model trained elsewhere names that machine's folder
            _photos_not_here(str(src))
        return None
    try:
        scene = read_dataset(Path(str(src)).expanduser(), white_background=white_background,
                             principal_point=mf.principal_point)
    except (ValueError, OSError) as e:
        logger.warning("the model's source photos at %s cannot be read (%s): renders only", src, e)
        return None
    return [SourcePhoto.of_view(v) for v in scene.train] or None


def _verdict_of(verdict, model: GaussianModel, cache_dir):
    """The verdict thresholds a Localizer uses (its ``verdict`` argument), or None."""
    from .calibration import load_calibration
    from .verify import VerdictConfig

    if verdict is None or isinstance(verdict, VerdictConfig):
        return verdict
    if isinstance(verdict, str) and verdict == "auto":
        if cache_dir is False:
            return None
        return load_calibration(model, None if cache_dir in (None, True) else cache_dir)
    if isinstance(verdict, (str, Path)):
        return load_calibration(model, path=verdict)
    raise ValueError("verdict must be a VerdictConfig, a calibration file, 'auto' or None, got "
                     f"{type(verdict).__name__}")


class Localizer:
    """Localize photos in one 3DGS model (module docstring).

    Args:
        model: the Gaussians (its device and dtype are used; nothing is moved).
        matcher: an ``icomma_plugin.matchers.Matcher``; None only for the paper's compare-only.
        method: :class:`RobustConfig` (the default, when None) or the paper's
            :class:`LocalizerConfig`.
        cameras: the model's cameras (``cameras.json`` entries, or c2w arrays): the candidate
            views of the default method. A query's own camera (at its true pose) is left out.
        backend: rasterizer backend, one of `BACKENDS`.
        background: background colour ``[3]`` (default black).
        model_side: the longer side [px] of the images the model was fitted on: the methods work
            at no more than this resolution (a sharper photo adds cost, not accuracy).
        cache_dir: the cache folder: the candidate index is kept in its ``candidates/`` and a
            calibration of the verdict is looked for in its ``calibration/``; None for the
            default (``candidate_cache.default_cache_dir()``, ``~/.cache/icomma``), False to keep
            the index in memory only (and read no calibration unless given).
        photos: the photos the model was fitted from (``SourcePhoto``s or dataset views; never
            held-out views): anchors of the candidate ranking and of the geometric stage
            (``anchors.py``). None: renders only.
        verdict: thresholds of the verdict for this model, replacing the method's: a
            ``VerdictConfig``, the path of a calibration file (``localization/calibration.py``,
            written by ``icomma-audit``), ``"auto"`` (the model's calibration in the cache folder
            when there is one) or None (the method's thresholds).
        lod: level of detail for the geometric stage and the candidate renders
            (``level_of_detail.py``): ``"auto"`` (a reduced model only for models of more than
            ``LOD_AUTO_GAUSSIANS`` Gaussians), ``"off"`` / None (the full model always), or a
            ``lod.LodConfig`` (or a mapping of its fields): always, with that config. Each
            result's ``details["lod"]`` says which model served which stage.

    Raises:
        ValueError: naming the argument: not a model, an unknown backend, a method that cannot
            run with this matcher, a bad background or camera pose, a bad ``lod``.
    """

    def __init__(
        self,
        model: GaussianModel,
        matcher=None,
        method: Optional[Method] = None,
        *,
        cameras: Sequence[Any] = (),
        backend: str = "auto",
        background: Optional[torch.Tensor] = None,
        model_side: Optional[int] = None,
        cache_dir: Union[str, Path, None, bool] = None,
        photos: Optional[Sequence[Any]] = None,
        verdict="auto",
        lod="auto",
    ):
        from ..checks import check_backend_here, check_int

        if not isinstance(model, GaussianModel):
            raise ValueError(f"model must be a GaussianModel, got {type(model).__name__}")
        self.method = RobustConfig() if method is None else method
        if not isinstance(self.method, (RobustConfig, LocalizerConfig)):
            raise ValueError("method must be a RobustConfig or a LocalizerConfig, got "
                             f"{type(self.method).__name__}")
        self._verdict = _verdict_of(verdict, model, cache_dir)
        if self._verdict is not None:
            self.method = dataclasses.replace(self.method, verdict=self._verdict)
        problem = self.method.needs(matcher)
        if problem:
            raise ValueError(problem)
        self.backend = check_backend_here(backend, "backend")
        self.model_side = check_int(model_side, "model_side", 1, optional=True)
        self.matcher = matcher
        self.model = model_for_backend(model, self.backend).without_zero_sh().detach()
        bg = torch.zeros(3) if background is None else torch.as_tensor(background)
        if bg.numel() != 3 or not bool(torch.isfinite(bg).all()):
            raise ValueError(f"background must be 3 finite values (RGB), got {background!r}")
        self.background = bg.reshape(3).to(self.model.device, self.model.dtype)
        # per camera: its pose, name, and intrinsics (None where a bare c2w gave none)
        self.cameras_c2w, self.camera_names, self.camera_intrinsics = _camera_parts(cameras)
        self.photos = None if not photos else PhotoAnchors(
            [p if isinstance(p, SourcePhoto) else SourcePhoto.of_view(p) for p in photos],
            self.background)
        root = None if cache_dir in (None, True) else cache_dir
        self.cache = None if cache_dir is False else CandidateCache(
            None if root is None else Path(str(root)).expanduser() / "candidates")
        self._scenes: Dict[Optional[int], Any] = {}
        self._indices: Dict[Any, CandidateIndex] = {}
        self._model_id: Optional[str] = None
        self.candidate_builds = 0  # candidate indices rendered by this localizer (not loaded)
        self.lod_mode, lod_cfg = lod_config(lod, self.model.num_gaussians)
        self.reduced = None if lod_cfg is None else ReducedModels(
            self.model, lod_cfg, self._lod_cameras(), self.cache, self._fingerprint)

    def _fingerprint(self) -> str:
        """The model's content hash (computed once)."""
        if self._model_id is None:
            self._model_id = model_fingerprint(self.model)
        return self._model_id

    def _lod_cameras(self) -> List[np.ndarray]:
        """Where the reduced models' footprints are taken from.

        The model's cameras, or views sampled around the scene when it has none.
        """
        if self.cameras_c2w:
            return list(self.cameras_c2w)
        from ..pose.views import sample_views, scene_frame

        centre, radius, up = scene_frame(self.model.means.detach().cpu().numpy(), [])
        return sample_views(centre, radius, up, CandidateConfig().num_sampled)

    def _reduced_scene(self, sh_degree: Optional[int]):
        """``state.reduced`` of a query: the reduced model's scene at a render's intrinsics."""
        if self.reduced is None:
            return None
        return functools.partial(self.reduced.scene_at, sh_degree=sh_degree)

    @classmethod
    def from_model_folder(cls, folder, matcher=None, method: Optional[Method] = None, *,
                          iteration: Optional[int] = None,
                          white_background: Optional[bool] = None, backend: str = "auto",
                          cache_dir: Union[str, Path, None, bool] = None,
                          photos: Union[str, Sequence[Any], None] = "auto",
                          verdict="auto", lod="auto") -> "Localizer":
        """A localizer for a 3DGS model folder (a ``ModelFolder`` or its path).

        Its cameras, training side and background (``cfg_args``, unless ``white_background`` is
        given) come from the folder; with ``backend="cuda"`` the model is moved to the GPU.
        ``photos="auto"``: the training photos of the dataset named by ``cfg_args``
        (``source_path``) when it is a folder here (:func:`source_photos`); None: none.
        """
        from ..io.model_folder import ModelFolder, load_model_folder

        mf = folder if isinstance(folder, ModelFolder) else load_model_folder(
            Path(str(folder)).expanduser(), iteration=iteration)
        white = mf.white_background if white_background is None else bool(white_background)
        if isinstance(photos, str):
            if photos != "auto":
                raise ValueError(f"photos must be 'auto', None or a list, got {photos!r}")
            photos = source_photos(mf, white)
        return cls(mf.model, matcher, method, cameras=mf.cameras, backend=backend,
                   background=torch.ones(3) if white else torch.zeros(3),
                   model_side=mf.training_side(), cache_dir=cache_dir, photos=photos,
                   verdict=verdict, lod=lod)

    # ------------------------------------------------------------------ localize
    def prepare(self, query: Query, method: Optional[Method] = None) -> Query:
        """Compute ahead what localizing ``query`` with ``method`` first matches against.

        The matcher's features of the query at the default method's working scale (and the
        geometric stage's coarse one), kept on the query (``Query.memo``): a localization of it
        then skips that extraction. Meant for a second thread while the previous photo is being
        localized (tracking's look-ahead, ``app.tracking``); it renders nothing. Returns ``query``.
        """
        if not isinstance(query, Query):
            raise ValueError(f"query must be a Query, got {type(query).__name__}")
        cfg = self._method(method).at_model_side(query.intrinsics, self.model_side)
        if not isinstance(cfg, RobustConfig) or not usable(self.matcher):
            return query
        scale = cfg.work_scale(query.intrinsics)
        with torch.no_grad():
            for s in {scale, cfg.geometric.first_scale(scale)}:
                query_features(query, scaled_query(query, s, self.model.device, self.model.dtype),
                               self.matcher)
        return query

    def localize(self, query: Query, init_c2w=None, gt_c2w=None,
                 progress: Optional[Callable[[TraceRecord], Any]] = None,
                 method: Optional[Method] = None) -> LocalizationResult:
        """Estimate the pose of ``query``.

        Args:
            query: the photo (:class:`~.types.Query`: image, intrinsics, masks, name).
            init_c2w: ``[4, 4]`` start pose (camera-to-world, OpenCV axes); None: no start (the
                default method searches the candidate views; the paper's method needs one).
            gt_c2w: the true pose, when known: used ONLY to report errors and to leave the
                query's own camera out of the candidates.
            progress: called with each trace record as it is made.
            method: another config of a method for this query only (e.g. tracking's cheaper
                one), sharing this localizer's model, candidate index and verdict.

        Raises:
            ValueError: a bad query or pose (naming it), or no start for the paper's method.
        """
        if not isinstance(query, Query):
            raise ValueError(f"query must be a Query, got {type(query).__name__}")
        given = self._method(method)
        cfg = given.at_model_side(query.intrinsics, self.model_side)
        init_w2c = None if init_c2w is None else invert_rigid(as_rigid(init_c2w, "init_c2w"))
        gt = None if gt_c2w is None else as_rigid(gt_c2w, "gt_c2w")
        if init_w2c is None and cfg.needs_start:
            raise ValueError(f"the paper's method (optimizer={cfg.name}) needs a start pose "
                             "(init_c2w); without one use the default method (optimizer=robust)")
        state = LocalizationState(
            self.model, query, self.background, backend=self.backend, matcher=self.matcher,
            mutual_nn=getattr(cfg, "mutual_nn", None), patch_search=_patch_search(cfg),
            sh_degree=cfg.sh_degree,
            antialiasing=cfg.antialiasing, gt_c2w=gt,
            progress=progress, record_trace=cfg.record_trace, scene=self._scene(cfg.sh_degree),
            reduced=self._reduced_scene(cfg.sh_degree))
        lod_events = 0 if self.reduced is None else len(self.reduced.events)
        state.candidates = functools.partial(self._candidates_for, state, gt, cfg)
        if self.photos is not None:
            own = self.photos.own(query.name, gt)
            state.anchors = functools.partial(self._anchors_for, own=own)
        init_rot, init_trans = (None, None) if init_w2c is None else state.errors(init_w2c)
        out = cfg.run(state, init_w2c)
        rot, trans = state.errors(out.w2c)
        score = out.score
        return LocalizationResult(
            name=query.name, c2w=invert_rigid(out.w2c), verdict=out.verdict, method=cfg.name,
            matcher=getattr(self.matcher, "name", None) if self._matches(cfg) else None,
            iterations=out.iterations, stop_reason=out.stop_reason, seconds=state.elapsed(),
            intrinsics=state.intrinsics_at(1.0),  # the query's, or its estimated focal length
            init_c2w=None if init_c2w is None else as_rigid(init_c2w, "init_c2w"), gt_c2w=gt,
            rot_err_deg=rot, trans_err=trans, init_rot_err_deg=init_rot,
            init_trans_err=init_trans, inliers=None if score is None else score.inliers,
            matches=None if score is None else score.matches,
            stage_seconds=state.stage_seconds(), stage_cpu_seconds=state.stage_seconds(cpu=True),
            details={**out.details, "lod": self._lod_details(state, lod_events),
                     **({"patch_search": dict(state.patch_searched)}
                        if state.patch_search is not None else {})},
            trace=state.trace,
            # What runs the same again: the working side resolved, pixel thresholds as given
            # (scaled again above the model's side, not twice).
            config=given.at_model_side(query.intrinsics, self.model_side,
                                       scale_pixels=False).to_dict(),
        )

    def _lod_details(self, state: LocalizationState, events_before: int) -> Dict[str, Any]:
        """``details["lod"]`` of a query (docs/LOCALIZATION.md, level of detail).

        The mode and config, the full model's size, per stage the Gaussian counts rendered
        (``state.rendered``), the reduced models made or loaded for this query and the seconds
        spent on them.
        """
        events = [] if self.reduced is None else self.reduced.events[events_before:]
        return {"mode": self.lod_mode,
                "config": None if self.reduced is None else self.reduced.identity(),
                "full_gaussians": self.model.num_gaussians,
                "stages": {k: {"gaussians": list(v["gaussians"]), "renders": v["renders"],
                               "reduced": v["reduced"]} for k, v in state.rendered.items()},
                "reduced_models": [dict(e) for e in events],
                "build_seconds": float(sum(e["seconds"] for e in events))}

    def _method(self, method: Optional[Method]) -> Method:
        """``method`` (checked, with this localizer's verdict), or the localizer's own."""
        if method is None:
            return self.method
        if not isinstance(method, (RobustConfig, LocalizerConfig)):
            raise ValueError("method must be a RobustConfig or a LocalizerConfig, got "
                             f"{type(method).__name__}")
        problem = method.needs(self.matcher)
        if problem:
            raise ValueError(problem)
        if self._verdict is not None:
            method = dataclasses.replace(method, verdict=self._verdict)
        return method

    def own_cameras(self, gt_c2w: Optional[np.ndarray], name: Optional[str] = None
                    ) -> List[str]:
        """Names of the model's cameras that are a query's own, left out of its candidates.

        At the pose ``gt_c2w`` (its truth), or named like the query (extension ignored).
        """
        stem = None if name is None else name_stem(name)
        return [n for n, c in zip(self.camera_names, self.cameras_c2w)
                if (gt_c2w is not None and same_pose(c, gt_c2w)) or name_stem(n) == stem]

    def _matches(self, cfg) -> bool:
        """Whether the method matched keypoints (compare-only runs do not)."""
        return can_match(self.matcher) and getattr(cfg, "use_matching", True)

    # ------------------------------------------------------------------ what queries share
    def _scene(self, sh_degree: Optional[int]):
        """The model's rasterizer inputs at ``sh_degree``, prepared once."""
        if sh_degree not in self._scenes:
            self._scenes[sh_degree] = prepare_scene(self.model, sh_degree)
        return self._scenes[sh_degree]

    def _candidates_for(self, state: LocalizationState, gt_c2w: Optional[np.ndarray], cfg
                        ) -> Optional[Tuple[CandidateIndex, frozenset]]:
        """(index, the query's own cameras to leave out) for ``state``'s query, or None."""
        if not usable(self.matcher) or not getattr(cfg, "use_candidates", False):
            return None
        index = self.candidate_index(state.query.intrinsics, cfg.candidates, state,
                                     sh_degree=cfg.sh_degree, antialiasing=cfg.antialiasing)
        return index, index.own_cameras(gt_c2w, state.query.name)

    def _anchors_for(self, state: LocalizationState, scale: float, c2w: np.ndarray, cfg,
                     own: frozenset, subpixel: bool = False):
        """The source photos' correspondences of ``state``'s query near ``c2w`` (``anchors``)."""
        return self.photos.correspondences(state, scale, c2w, cfg.anchor_photos, cfg, own,
                                           subpixel)

    def candidate_index(self, intrinsics: Intrinsics, cfg: Optional[CandidateConfig] = None,
                        state: Optional[LocalizationState] = None, *,
                        sh_degree: Optional[int] = None,
                        antialiasing: bool = False) -> CandidateIndex:
        """The candidate index for photos taken with ``intrinsics``.

        Built once per candidate camera (``candidates.candidate_intrinsics``: photos whose
        focal lengths differ a little share one), in memory and on disk; ``state`` (a query's)
        is charged the time of building it.
        """
        if not usable(self.matcher):
            raise ValueError("candidate views need a matcher that extracts features, got "
                             f"{self.matcher!r}")
        cfg = cfg or CandidateConfig()
        cams = [c for c in self.camera_intrinsics if c is not None]
        intr = candidate_intrinsics(intrinsics, cams, cfg.rank_side)
        memo = (intr, cfg.num_sampled, cfg.rank_side, sh_degree, antialiasing)
        if memo not in self._indices:
            if state is None:
                blank = torch.zeros(3, intrinsics.height, intrinsics.width)
                state = LocalizationState(self.model, Query(blank, intrinsics), self.background,
                                          backend=self.backend, matcher=self.matcher,
                                          sh_degree=sh_degree, antialiasing=antialiasing,
                                          scene=self._scene(sh_degree),
                                          reduced=self._reduced_scene(sh_degree))

            def build() -> CandidateIndex:
                self.candidate_builds += 1
                with state.serving("candidates", reduced=True):
                    return CandidateIndex.build(state, self.cameras_c2w, cfg, self.camera_names,
                                                intr, self.photos)

            with state.timed("candidates"):
                if self.cache is None:
                    index = build()
                else:
                    index, _ = self.cache.get_or_build(
                        self._index_fields(intr, cfg, sh_degree, antialiasing), build)
            self._indices[memo] = index
        return self._indices[memo]

    def _index_fields(self, intr: Intrinsics, cfg: CandidateConfig, sh_degree, antialiasing
                      ) -> Dict[str, Any]:
        render = {"background": [float(v) for v in self.background.cpu()],
                  "backend": f"{self.backend}:{self.model.device.type}", "sh_degree": sh_degree,
                  "antialiasing": antialiasing, "dtype": str(self.model.dtype)}
        if self.reduced is not None:  # rendered from a reduced model (absent: keys unchanged)
            render["lod"] = self.reduced.identity()
        photos = None if self.photos is None or not cfg.photos else self.photos.fingerprint()
        return index_fields(self._fingerprint(), self.cameras_c2w, self.camera_names, intr, cfg,
                            self.matcher, render, photos)
