#!/usr/bin/env python
"""Estimate the camera pose of a query image in a trained 3DGS model (iComMa).

    python tools/localize.py                                   # the built-in demo scene
    python tools/localize.py data=model_folder data.model_path=output/lego \\
        data.query.dataset=data/lego data.query.index=0 data.init.rot_deg=30 matcher=aliked_lightglue
    python tools/localize.py -m optimizer.lambda_match=0.2,0.5,0.8 optimizer.lr=0.02,0.05

Outputs go to Hydra's output folder (``hydra.run.dir``): result.json, trace.json / trace.csv,
overlay_initial.png, overlay_final.png, matches_initial.png, convergence.png (optimisation.gif
with ``output.gif=true``). ``main`` returns the final rotation error in degrees (the final loss
when no ground truth is known), so sweepers can minimise it.

Configuration: conf/localize.yaml (groups data, matcher, optimizer, renderer).
"""
from __future__ import annotations

import csv
import io
import logging
import os
import random
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, Optional

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

import hydra  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from hydra.core.hydra_config import HydraConfig  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402

from icomma_plugin.camera import Intrinsics  # noqa: E402
from icomma_plugin.localize import LocalizerConfig, localize  # noqa: E402
from icomma_plugin.pose.convert import perturb_pose  # noqa: E402
from icomma_plugin.runtime import run_or_exit, torch_threads  # noqa: E402

log = logging.getLogger("localize")


class UserError(ValueError):
    """Bad input from the command line / config: reported as one line, no traceback."""


@dataclass
class Problem:
    """Everything `localize` needs, plus what the report needs."""

    model: Any
    query: torch.Tensor  # [3, H, W]
    query_alpha: Optional[torch.Tensor]
    intrinsics: Intrinsics
    init_c2w: np.ndarray
    gt_c2w: Optional[np.ndarray]
    bg: torch.Tensor
    query_name: str
    scene_scale: Optional[float]
    info: Dict[str, Any] = field(default_factory=dict)


# ----------------------------------------------------------------------------------------------
# inputs
# ----------------------------------------------------------------------------------------------


def _rigid_ok(T: np.ndarray) -> bool:
    R = T[:3, :3]
    return (np.all(np.isfinite(T)) and np.allclose(R @ R.T, np.eye(3), atol=1e-4)
            and np.linalg.det(R) > 0 and np.allclose(T[3], [0, 0, 0, 1], atol=1e-6))


def load_c2w_file(path, what: str) -> np.ndarray:
    """A 4x4 (or 3x4) camera-to-world from a text or .npy file; UserError on anything else."""
    p = Path(str(path)).expanduser()
    if not p.is_file():
        raise UserError(f"{what}: file not found: {p}")
    try:
        arr = np.load(p) if p.suffix == ".npy" else np.loadtxt(p, ndmin=2)
    except Exception as e:  # noqa: BLE001 - any parse error is a user error here
        raise UserError(f"{what}: cannot read a 4x4 matrix from {p} ({type(e).__name__}: {e})") from None
    arr = np.asarray(arr, np.float64)
    if arr.size == 16:
        arr = arr.reshape(4, 4)
    elif arr.size == 12:
        arr = np.vstack([arr.reshape(3, 4), [0, 0, 0, 1]])
    else:
        raise UserError(f"{what}: {p} must hold a 4x4 (or 3x4) camera-to-world matrix, got {arr.size} numbers")
    if not _rigid_ok(arr):
        raise UserError(f"{what}: {p} is not a rigid camera-to-world matrix (rotation not orthonormal "
                        "with det +1, or last row not 0 0 0 1)")
    return arr


def _bg(white: bool) -> torch.Tensor:
    return torch.ones(3) if white else torch.zeros(3)


def _load_demo(d: DictConfig, backend: str) -> Problem:
    from icomma_plugin.demo_scene import build_demo_scene

    scene = build_demo_scene(
        d.path, seed=int(d.scene_seed), width=int(d.width), height=int(d.height),
        fov_deg=float(d.fov_deg), rot_range_deg=tuple(d.rot_range_deg), trans=float(d.trans),
        rebuild=bool(d.rebuild), backend=backend,
    )
    model = scene.load_model()
    init = scene.init_c2w
    if d.get("init_rot_deg") is not None:
        rng = np.random.default_rng(int(d.init_seed))
        init = perturb_pose(scene.gt_c2w, float(d.init_rot_deg), float(d.init_trans),
                            generator=rng, pivot=scene.scene_centre)
    return Problem(
        model=model, query=scene.load_query(), query_alpha=None, intrinsics=scene.intrinsics,
        init_c2w=init, gt_c2w=scene.gt_c2w, bg=_bg(scene.white_background), query_name="query",
        scene_scale=scene.scene_scale,
        info={"demo_path": str(scene.path), "num_gaussians": model.num_gaussians},
    )


def _read_image(path, bg: torch.Tensor):
    from icomma_plugin.io.datasets import read_image_file

    img = read_image_file(Path(str(path)).expanduser())
    t = torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1))).float()
    rgb, alpha = t[:3], (t[3:4] if t.shape[0] == 4 else None)
    if alpha is not None:
        rgb = rgb * alpha + bg.view(3, 1, 1) * (1 - alpha)
    return rgb.contiguous(), alpha


def _cameras_extent(cameras) -> Optional[float]:
    if not cameras:
        return None
    c = np.stack([e.c2w[:3, 3] for e in cameras])
    return 1.1 * float(np.max(np.linalg.norm(c - c.mean(0), axis=1))) or None


def _load_model_folder(d: DictConfig, seed: int) -> Problem:
    from icomma_plugin.io.cameras_json import entry_to_intrinsics, find_entry
    from icomma_plugin.io.datasets import read_dataset
    from icomma_plugin.io.model_folder import load_model_folder

    if OmegaConf.is_missing(d, "model_path") or not d.model_path:
        raise UserError("data.model_path is required with data=model_folder (a trained 3DGS output folder)")
    mp = Path(str(d.model_path)).expanduser()
    if not mp.is_dir():
        raise UserError(f"data.model_path: model folder not found: {mp}")
    mf = load_model_folder(mp, iteration=d.iteration)
    white = mf.white_background if d.white_background is None else bool(d.white_background)
    bg = _bg(white)
    q = d.query

    def entry(name, what):
        if not mf.cameras:
            raise UserError(f"{what}={name!r}: the model folder {mp} has no cameras.json")
        try:
            return find_entry(mf.cameras, name)
        except ValueError as e:
            raise UserError(f"{what}: {e}") from None

    def dataset(what):
        root = q.dataset or mf.cfg.get("source_path")
        if not root or not Path(str(root)).expanduser().is_dir():
            raise UserError(f"{what} needs the source images: set data.query.dataset (cfg_args source_path "
                            f"{mf.cfg.get('source_path')!r} is not a folder here) or data.query.image")
        kw = {"white_background": white}
        try:
            return read_dataset(Path(str(root)).expanduser(), **kw)
        except ValueError as e:
            if "does not take" in str(e):
                return read_dataset(Path(str(root)).expanduser())
            raise

    chosen = [k for k in ("image", "camera", "index") if q.get(k) is not None]
    if not chosen:
        raise UserError("choose the query: set data.query.image (a file), data.query.camera (a cameras.json "
                        "name/id) or data.query.index (a dataset view)")
    view = cam = None
    if q.camera is not None:
        cam = entry(q.camera, "data.query.camera")
    if q.image is not None:
        rgb, alpha = _read_image(q.image, bg)
        name = Path(str(q.image)).stem
    elif cam is not None:
        scene = dataset(f"data.query.camera={q.camera!r}")
        views = [v for v in scene.train + scene.test
                 if os.path.splitext(v.name)[0] == os.path.splitext(cam.img_name)[0]]
        if not views:
            raise UserError(f"data.query.camera={q.camera!r}: no view named {cam.img_name!r} in the dataset")
        view = views[0]
        rgb, alpha = view.load(background=bg)
        name = view.name
    else:
        scene = dataset(f"data.query.index={q.index}")
        if q.split not in ("train", "test"):
            raise UserError(f"data.query.split must be train or test, got {q.split!r}")
        views = getattr(scene, q.split)
        if not (0 <= int(q.index) < len(views)):
            raise UserError(f"data.query.index={q.index} out of range: split {q.split!r} has {len(views)} views")
        view = views[int(q.index)]
        rgb, alpha = view.load(background=bg)
        name = view.name
    H, W = int(rgb.shape[1]), int(rgb.shape[2])

    it = d.intrinsics
    if it.fx is not None:
        intr = Intrinsics(W, H, float(it.fx), float(it.fy if it.fy is not None else it.fx),
                          None if it.cx is None else float(it.cx), None if it.cy is None else float(it.cy))
    else:
        src = None
        if it.camera is not None:
            src = entry_to_intrinsics(entry(it.camera, "data.intrinsics.camera"))
        elif view is not None:
            src = view.intrinsics
        elif cam is not None:
            src = entry_to_intrinsics(cam)
        if src is None:
            raise UserError("query intrinsics unknown: set data.intrinsics.fx/fy or data.intrinsics.camera")
        if (src.width, src.height) != (W, H):
            src = Intrinsics(W, H, src.fx * W / src.width, src.fy * H / src.height)
        intr = src

    gt = None
    if d.gt.camera is not None:
        gt = entry(d.gt.camera, "data.gt.camera").c2w
    elif d.gt.c2w_file is not None:
        gt = load_c2w_file(d.gt.c2w_file, "data.gt.c2w_file")
    elif view is not None:
        gt = view.c2w
    elif cam is not None:
        gt = cam.c2w

    ini = d.init
    chosen = [k for k in ("camera", "c2w_file", "rot_deg") if ini.get(k) is not None]
    if len(chosen) != 1:
        raise UserError("choose exactly one initial pose: data.init.camera, data.init.c2w_file or "
                        f"data.init.rot_deg (got {chosen or 'none'})")
    if ini.camera is not None:
        init = entry(ini.camera, "data.init.camera").c2w
    elif ini.c2w_file is not None:
        init = load_c2w_file(ini.c2w_file, "data.init.c2w_file")
    else:
        if gt is None:
            raise UserError("data.init.rot_deg perturbs the ground truth, but no ground-truth pose is known "
                            "for this query (use data.query.camera / index, or data.gt.*)")
        rng = np.random.default_rng(int(ini.seed))
        if ini.pivot in ("camera", "origin", "scene_center"):
            pivot = (mf.model.means.double().median(0).values.numpy() if ini.pivot == "scene_center"
                     else str(ini.pivot))
            init = perturb_pose(gt, float(ini.rot_deg), float(ini.trans), rng, pivot=pivot)
        else:
            raise UserError(f"data.init.pivot must be scene_center, camera or origin, got {ini.pivot!r}")
    return Problem(
        model=mf.model, query=rgb, query_alpha=alpha, intrinsics=intr, init_c2w=np.asarray(init, np.float64),
        gt_c2w=None if gt is None else np.asarray(gt, np.float64), bg=bg, query_name=str(name),
        scene_scale=_cameras_extent(mf.cameras),
        info={"model_path": str(mp), "iteration": mf.iteration, "num_gaussians": mf.model.num_gaussians},
    )


def load_problem(cfg: DictConfig) -> Problem:
    kind = cfg.data.get("kind")
    if kind == "demo":
        return _load_demo(cfg.data, cfg.renderer.backend)
    if kind == "model_folder":
        return _load_model_folder(cfg.data, int(cfg.seed))
    raise UserError(f"data.kind must be demo or model_folder, got {kind!r}")


def build_matcher(mcfg: Optional[DictConfig]):
    """The matcher named by the matcher group (None for `none` / a removed group)."""
    if mcfg is None:
        return None
    kw = OmegaConf.to_container(mcfg, resolve=True)
    name = kw.pop("name", None)
    if not name or name == "none":
        return None
    if name == "loftr" and not kw.get("checkpoint"):
        raise UserError("matcher=loftr needs a local checkpoint file: set matcher.checkpoint=/path/to/"
                        "outdoor_ds.ckpt (LoFTR weights are not shipped or downloaded); or pick another "
                        "matcher, e.g. matcher=xfeat")
    if name == "loftr" and not Path(str(kw["checkpoint"])).expanduser().is_file():
        raise UserError(f"matcher.checkpoint: file not found: {kw['checkpoint']}")
    from icomma_plugin.matchers import make_matcher

    return make_matcher(name, **kw)


def build_localizer_config(ocfg: DictConfig) -> LocalizerConfig:
    return LocalizerConfig.from_dict(OmegaConf.to_container(ocfg, resolve=True))


# ----------------------------------------------------------------------------------------------
# run
# ----------------------------------------------------------------------------------------------


def _seed(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % (2 ** 32))
    torch.manual_seed(seed)


def _render(problem: Problem, c2w: np.ndarray, backend: str, scale: float = 1.0) -> torch.Tensor:
    from icomma_plugin.render import render

    intr = problem.intrinsics.scaled(scale) if scale != 1.0 else problem.intrinsics
    w2c = torch.as_tensor(np.linalg.inv(c2w), dtype=problem.model.dtype)
    with torch.no_grad():
        return render(problem.model, intr, w2c, problem.bg.to(problem.model.dtype), backend=backend).color


def _write_trace(out: Path, trace, fmt: str) -> list:
    from icomma_plugin.io.atomic import write_json_atomic, write_text_atomic

    written = []
    if fmt in ("json", "both"):
        write_json_atomic(out / "trace.json", trace)
        written.append("trace.json")
    if fmt in ("csv", "both"):
        keys = [k for k in (trace[0].keys() if trace else []) if k != "xi"]
        buf = io.StringIO()
        w = csv.DictWriter(buf, fieldnames=keys, extrasaction="ignore")
        w.writeheader()
        for r in trace:
            w.writerow({k: ("" if r.get(k) is None else r[k]) for k in keys})
        write_text_atomic(out / "trace.csv", buf.getvalue())
        written.append("trace.csv")
    return written


def run(cfg: DictConfig, output_dir: Path) -> Dict[str, Any]:
    """The body of the tool: load, localise, write the outputs into `output_dir`; returns result.json.
    `cfg.threads` applies for the duration of the call (torch's thread count is restored)."""
    with torch_threads(cfg.get("threads")):
        return _run(cfg, Path(output_dir))


def _run(cfg: DictConfig, output_dir: Path) -> Dict[str, Any]:
    from icomma_plugin import visualize as viz
    from icomma_plugin.io.atomic import write_json_atomic
    from icomma_plugin.io.cameras_json import CameraEntry

    output_dir.mkdir(parents=True, exist_ok=True)
    _seed(int(cfg.seed))
    backend = str(cfg.renderer.backend)
    lcfg = build_localizer_config(cfg.optimizer)
    matcher = build_matcher(cfg.get("matcher"))
    problem = load_problem(cfg)
    if backend == "cuda":  # the CUDA kernel renders CUDA tensors; library code never moves data
        if not torch.cuda.is_available():
            raise UserError("renderer=cuda: no CUDA device is available here (use renderer=auto or cpu)")
        problem.model = problem.model.to("cuda")
    ocfg = cfg.output
    init_w2c = np.linalg.inv(problem.init_c2w)
    gt_w2c = None if problem.gt_c2w is None else np.linalg.inv(problem.gt_c2w)
    work_scale = lcfg.image_scale

    # GIF frames / progress bar via the per-iteration hook.
    frames = []
    bar = None
    if ocfg.progress:
        from tqdm import tqdm

        bar = tqdm(total=lcfg.max_iterations, desc="localize", unit="it", dynamic_ncols=True, leave=False)
    from icomma_plugin.pose.se3 import se3_exp

    w2c0_t = torch.as_tensor(init_w2c, dtype=torch.float64)

    def hook(rec):
        if bar is not None:
            post = {"stage": rec["stage"], "loss": f"{rec['loss']:.3g}", "m": rec["matches_used"]}
            if rec.get("rot_err_deg") is not None:
                post["rot"] = f"{rec['rot_err_deg']:.3f}deg"
                post["trans"] = f"{rec['trans_err']:.4f}"
            bar.set_postfix(post, refresh=False)
            bar.update(1)
        if ocfg.gif and rec["iteration"] % max(1, int(ocfg.gif_every)) == 0 and rec.get("xi") is not None:
            w2c = (se3_exp(torch.tensor(rec["xi"], dtype=torch.float64)) @ w2c0_t).numpy()
            img = _render(problem, np.linalg.inv(w2c), backend, work_scale)
            frames.append(viz.overlay_panel(img, torch.nn.functional.interpolate(
                problem.query[None], size=img.shape[-2:], mode="bilinear", antialias=True)[0]))

    t0 = time.perf_counter()
    try:
        result = localize(problem.model, problem.query, problem.intrinsics, init_w2c, matcher, lcfg,
                          gt_w2c=gt_w2c, query_alpha=problem.query_alpha, backend=backend,
                          bg=problem.bg, progress=hook)
    finally:
        if bar is not None:
            bar.close()
    total_seconds = time.perf_counter() - t0

    est_c2w = result.c2w
    entry = CameraEntry(id=0, img_name=problem.query_name, width=problem.intrinsics.width,
                        height=problem.intrinsics.height, c2w=est_c2w, fx=float(problem.intrinsics.fx),
                        fy=float(problem.intrinsics.fy))
    scale = problem.scene_scale
    success = None
    if result.final_rotation_error_deg is not None:
        success = bool(result.final_rotation_error_deg < 0.5 and (
            scale is None or result.final_translation_error < 0.01 * scale))
    res = {
        "query": problem.query_name,
        "estimated_c2w": est_c2w.tolist(),
        "camera_entry": entry.to_json(),
        "initial_c2w": problem.init_c2w.tolist(),
        "ground_truth_c2w": None if problem.gt_c2w is None else problem.gt_c2w.tolist(),
        "initial_rotation_error_deg": result.initial_rotation_error_deg,
        "initial_translation_error": result.initial_translation_error,
        "final_rotation_error_deg": result.final_rotation_error_deg,
        "final_translation_error": result.final_translation_error,
        "scene_scale": scale,
        "final_translation_error_rel": (None if scale is None or result.final_translation_error is None
                                        else result.final_translation_error / scale),
        "success": success,
        "iterations": result.iterations,
        "switch_iteration": result.switch_iteration,
        "stop_reason": result.stop_reason,
        "match_counts": result.match_counts,
        "seconds": result.seconds,
        "seconds_total": total_seconds,
        "final_loss": result.final_loss,
        "gradient_mode": result.gradient_mode,
        "matcher": result.matcher,
        "backend": backend,
        "intrinsics": {"width": problem.intrinsics.width, "height": problem.intrinsics.height,
                       "fx": problem.intrinsics.fx, "fy": problem.intrinsics.fy,
                       "cx": problem.intrinsics.cx_px, "cy": problem.intrinsics.cy_px},
        "info": problem.info,
        "config": OmegaConf.to_container(cfg, resolve=True),
    }
    files = ["result.json"]
    files += _write_trace(output_dir, result.trace, str(ocfg.trace_format))

    q_small = problem.query
    if ocfg.overlays or ocfg.match_lines:
        init_img = _render(problem, problem.init_c2w, backend)
        final_img = _render(problem, est_c2w, backend)
        if ocfg.overlays:
            viz.save_overlay(output_dir / "overlay_initial.png", init_img, q_small)
            viz.save_overlay(output_dir / "overlay_final.png", final_img, q_small)
            files += ["overlay_initial.png", "overlay_final.png"]
        if ocfg.match_lines and matcher is not None:
            try:
                m = matcher.match(init_img.clamp(0, 1), q_small.to(init_img.dtype))
                viz.save_match_lines(output_dir / "matches_initial.png", init_img, q_small, m.kpts0, m.kpts1,
                                     m.confidence)
                files.append("matches_initial.png")
            except Exception as e:  # noqa: BLE001 - a picture must not fail the run
                log.warning("could not draw the match lines: %s", e)
    if ocfg.convergence_plot and result.trace:
        title = f"{result.matcher or 'compare only'} / {result.gradient_mode}: {result.stop_reason} " \
                f"after {result.iterations} it"
        viz.plot_convergence(output_dir / "convergence.png", result.trace, result.switch_iteration, title,
                             rot_target_deg=0.5, trans_target=None if scale is None else 0.01 * scale)
        files.append("convergence.png")
    if ocfg.gif and frames:
        viz.save_gif(output_dir / "optimisation.gif", frames)
        files.append("optimisation.gif")
    res["files"] = files
    write_json_atomic(output_dir / "result.json", res)
    return res


def summary(res: Dict[str, Any], output_dir: Path) -> str:
    def f(v, fmt):
        return "n/a" if v is None else format(v, fmt)

    lines = [
        "=" * 64,
        f"iComMa localisation of {res['query']!r}  ({res['matcher'] or 'compare only'}, "
        f"gradient {res['gradient_mode']}, backend {res['backend']})",
        f"  iterations   {res['iterations']}  ({res['stop_reason']}; stage switch at "
        f"{f(res['switch_iteration'], 'd')})   {res['seconds']:.1f} s",
        f"  matches      first {res['match_counts'].get('first')}  mean {f(res['match_counts'].get('mean'), '.1f')}"
        f"  compare-alone steps {res['match_counts'].get('compare_alone_steps')}",
    ]
    if res["final_rotation_error_deg"] is not None:
        rel = res.get("final_translation_error_rel")
        lines += [
            f"  rotation     {res['initial_rotation_error_deg']:8.3f} deg -> {res['final_rotation_error_deg']:.4f} deg",
            f"  translation  {res['initial_translation_error']:8.4f}     -> {res['final_translation_error']:.5f}"
            + ("" if rel is None else f"  ({100 * rel:.3f}% of the scene scale {res['scene_scale']:.3g})"),
            f"  success (< 0.5 deg, < 1% scale): {res['success']}",
        ]
    c = np.asarray(res["estimated_c2w"])
    lines.append("  estimated camera-to-world (OpenCV axes):")
    lines += ["    " + " ".join(f"{v:9.5f}" for v in row) for row in c[:3]]
    lines.append(f"  outputs in {output_dir}")
    lines.append("=" * 64)
    return "\n".join(lines)


@hydra.main(version_base="1.3", config_path="../conf", config_name="localize")
def main(cfg: DictConfig) -> float:
    hc = HydraConfig.get()
    output_dir = Path(hc.runtime.output_dir)
    multirun = str(hc.mode) == "RunMode.MULTIRUN"
    res = run_or_exit(lambda: run(cfg, output_dir), multirun, log)
    print(summary(res, output_dir))
    if res["final_rotation_error_deg"] is not None:
        return float(res["final_rotation_error_deg"])
    return float(res["final_loss"]) if res["final_loss"] is not None else float("nan")


if __name__ == "__main__":
    main()
