#!/usr/bin/env python
"""Estimate the camera pose of a query image in a trained 3DGS model.

    python tools/localize.py                                   # the built-in demo scene
    python tools/localize.py data=model_folder data.model_path=output/lego \\
        data.query.dataset=data/lego data.query.index=0 data.init.rot_deg=30
    python tools/localize.py data=model_folder data.model_path=output/lego \\
        data.query.image=photo.png data.intrinsics.fx=1111 data.init=none   # no start pose at all
    python tools/localize.py optimizer=icomma                  # the paper's method, as published
    python tools/localize.py -m optimizer=icomma optimizer.lambda_match=0.2,0.5,0.8

Outputs go to Hydra's output folder (``hydra.run.dir``): result.json (pose, verdict, errors when
the truth is known), trace.json / trace.csv, overlay_initial.png, overlay_final.png,
matches_initial.png, convergence.png (optimisation.gif with ``output.gif=true``). ``main`` returns
the final rotation error in degrees (the final loss when no ground truth is known), so sweepers
can minimise it.

Configuration: conf/localize.yaml (groups data, matcher, optimizer, renderer).
"""
from __future__ import annotations

import logging
import sys
import time
from pathlib import Path
from typing import Any, Dict

if __package__:
    from . import _common as common
    from ._paths import CONFIG_DIR
else:  # run as a script from a checkout
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from tools import _common as common
    from tools._paths import CONFIG_DIR

import hydra  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from hydra.core.hydra_config import HydraConfig  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

log = logging.getLogger("localize")


def run(cfg: DictConfig, output_dir: Path) -> Dict[str, Any]:
    """The body of the tool: load, localise, write the outputs into ``output_dir``; returns
    result.json. ``cfg.threads`` applies for the duration of the call."""
    with common.torch_threads(cfg.get("threads")):
        return _run(cfg, Path(output_dir))


def _run(cfg: DictConfig, output_dir: Path) -> Dict[str, Any]:
    from icomma_plugin.localization.output import OutputOptions, write_outputs
    from icomma_plugin.localization.problem import load_problem
    from icomma_plugin.localize import LocalizerConfig, localize

    output_dir.mkdir(parents=True, exist_ok=True)
    common.seed_everything(int(cfg.seed))
    backend = str(cfg.renderer.backend)
    method_cfg = common.build_optimizer(cfg.optimizer)
    matcher, _ = common.build_matcher(cfg.get("matcher"))
    problem = load_problem(common.container(cfg.data), backend)
    if backend == "cuda":  # the CUDA kernel renders CUDA tensors; library code never moves data
        if not torch.cuda.is_available():
            raise common.UserError("renderer=cuda: no CUDA device is available here (use renderer=auto or cpu)")
        problem.model = problem.model.to("cuda")
    paper = isinstance(method_cfg, LocalizerConfig)
    if paper and problem.init_c2w is None:
        raise common.UserError("data.init=none needs the default optimizer (optimizer=robust): the paper's "
                               "method starts from a given pose")
    opts = OutputOptions.from_dict(common.container(cfg.output))

    bar = None
    if cfg.output.progress:
        from tqdm import tqdm

        bar = tqdm(total=method_cfg.max_iterations if paper else None, desc="localize", unit="step",
                   dynamic_ncols=True, leave=False)

    def hook(rec):
        if bar is None:
            return
        post = {"stage": rec.stage.name.lower()}
        if rec.loss is not None:
            post["loss"] = f"{rec.loss:.3g}"
        if rec.inliers is not None:
            post["inliers"] = rec.inliers
        if rec.rot_err_deg is not None:
            post["rot"] = f"{rec.rot_err_deg:.3f}deg"
        bar.set_postfix(post, refresh=False)
        bar.update(1)

    init_w2c = None if problem.init_c2w is None else np.linalg.inv(problem.init_c2w)
    gt_w2c = None if problem.gt_c2w is None else np.linalg.inv(problem.gt_c2w)
    t0 = time.perf_counter()
    try:
        result = localize(problem.model, problem.query.rgb, problem.query.intrinsics, init_w2c, matcher,
                          method_cfg, gt_w2c=gt_w2c, query_alpha=problem.query.alpha,
                          query_valid=problem.query.valid, backend=backend, bg=problem.bg, progress=hook,
                          cameras_c2w=problem.candidate_c2ws(), query_name=problem.name)
    finally:
        if bar is not None:
            bar.close()
    return write_outputs(output_dir, problem, result, matcher=matcher, options=opts, backend=backend,
                         config=common.container(cfg), seconds_total=time.perf_counter() - t0)


def summary(res: Dict[str, Any], output_dir: Path) -> str:
    def f(v, fmt):
        return "n/a" if v is None else format(v, fmt)

    v = res.get("verdict") or {}
    lines = [
        "=" * 72,
        f"localisation of {res['query']!r}: {res['method']} ({res['matcher'] or 'compare only'}, "
        f"backend {res['backend']})",
        f"  verdict      {str(v.get('status', 'n/a')).upper()}: {v.get('reason', '')}",
        f"  steps        {res['iterations']}  ({res['stop_reason']})   {res['seconds']:.2f} s",
    ]
    if res["final_rotation_error_deg"] is not None:
        rel = res.get("final_translation_error_rel")
        init_r = res.get("initial_rotation_error_deg")
        init_t = res.get("initial_translation_error")
        lines += [
            f"  rotation     {f(init_r, '8.3f')} deg -> {res['final_rotation_error_deg']:.4f} deg",
            f"  translation  {f(init_t, '8.4f')}     -> {res['final_translation_error']:.5f}"
            + ("" if rel is None else f"  ({100 * rel:.3f}% of the scene scale {res['scene_scale']:.3g})"),
            f"  success (< 0.5 deg, < 1% scale): {res['success']}",
        ]
    c = np.asarray(res["estimated_c2w"])
    lines.append("  estimated camera-to-world (OpenCV axes):")
    lines += ["    " + " ".join(f"{x:9.5f}" for x in row) for row in c[:3]]
    lines.append(f"  outputs in {output_dir}")
    lines.append("=" * 72)
    return "\n".join(lines)


@hydra.main(version_base="1.3", config_path=CONFIG_DIR, config_name="localize")
def main(cfg: DictConfig) -> float:
    hc = HydraConfig.get()
    output_dir = Path(hc.runtime.output_dir)
    multirun = str(hc.mode) == "RunMode.MULTIRUN"
    res = common.run_or_exit(lambda: run(cfg, output_dir), multirun, log)
    print(summary(res, output_dir))
    if res["final_rotation_error_deg"] is not None:
        return float(res["final_rotation_error_deg"])
    return float(res["final_loss"]) if res["final_loss"] is not None else float("nan")


if __name__ == "__main__":
    main()
