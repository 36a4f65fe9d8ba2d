#!/usr/bin/env python
"""Benchmark iComMa localisation on a fitted 3DGS model against the paper's protocols.

    python tools/benchmark.py benchmark_protocol=time_table quick=true
    python tools/benchmark.py benchmark_protocol=relative_pose matcher=aliked_lightglue
    python tools/benchmark.py -m benchmark_protocol=curves_rotation,curves_translation,time_table,relative_pose,ablation quick=true
    python tools/benchmark.py -m hydra/launcher=joblib_local threads=1 optimizer.lr=0.02,0.05   # parallel sweep
    python tools/benchmark.py scene.kind=synthetic benchmark_protocol=time_table quick=true   # no data needed

Outputs (Hydra's output folder, rewritten atomically after every run, so a partial run keeps its
numbers): results.json (all numbers, seeds, config, model path, timings), results.md (our numbers
beside the paper's, with the source and a Δ column), PNG plots. Resume an interrupted run with
``resume=<old results.json>``. Returns the protocol's headline number (for sweepers): the mean
final success fraction of the `icomma` method over the intervals (relative_pose: its AUC@10;
ablation: its failure rate, to minimise).

Configuration: conf/benchmark.yaml + conf/benchmark_protocol/<name>.yaml (+ the matcher,
optimizer, renderer groups of tools/localize.py). Documentation: docs/BENCHMARK.md.
"""
from __future__ import annotations

import logging
import math
import random
import sys
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

from icomma_plugin.benchmark import (  # noqa: E402
    ProtocolSpec, ResultsWriter, load_done, load_model_folder_scene, run_protocol, synthetic_scene,
)
from icomma_plugin.localize import LocalizerConfig  # noqa: E402
from icomma_plugin.runtime import choose_threads, run_or_exit  # noqa: E402

log = logging.getLogger("benchmark")


class UserError(ValueError):
    """Bad input from the command line / config: reported as one line."""


def build_matcher(mcfg: Optional[DictConfig]):
    if mcfg is None:
        return None, None
    kw = OmegaConf.to_container(mcfg, resolve=True)
    name = kw.pop("name", None)
    if not name or name == "none":
        return None, None
    if name == "loftr":
        ck = kw.get("checkpoint")
        if not ck or not Path(str(ck)).expanduser().is_file():
            raise UserError("matcher=loftr needs a local checkpoint file: matcher.checkpoint=/path/to/outdoor_ds.ckpt "
                            "(LoFTR weights are never downloaded); or pick matcher=xfeat")
    from icomma_plugin.matchers import make_matcher

    return make_matcher(name, **kw), name


def load_scene(cfg: DictConfig, spec: ProtocolSpec, backend: str):
    s = cfg.scene
    if s.kind == "synthetic":
        sy = s.synthetic
        return synthetic_scene(num_gaussians=int(sy.num_gaussians), width=int(sy.width), height=int(sy.height),
                               num_queries=spec.num_queries, seed=int(sy.seed),
                               translation_unit=str(s.translation_unit), backend=backend)
    if s.kind == "model_folder":
        if not s.model_path:
            raise UserError("scene.model_path is required with scene.kind=model_folder")
        if not Path(str(s.model_path)).expanduser().is_dir():
            raise UserError(f"scene.model_path: model folder not found: {s.model_path} (fit one with "
                            "tools/fit_scene.py, or use scene.kind=synthetic)")
        idx = None if s.query_indices is None else [int(i) for i in s.query_indices]
        return load_model_folder_scene(
            s.model_path, dataset=s.dataset, num_queries=spec.num_queries, split=str(s.split), query_indices=idx,
            image_scale=None if s.image_scale is None else float(s.image_scale),
            white_background=None if s.white_background is None else bool(s.white_background),
            iteration=s.iteration, translation_unit=str(s.translation_unit))
    raise UserError(f"scene.kind must be model_folder or synthetic, got {s.kind!r}")


def headline(spec: ProtocolSpec, summary: Dict[str, Any]) -> float:
    cells = [c for c in summary["cells"] if c["method"] == "icomma" and c["n"]]
    if not cells:
        return float("nan")
    if spec.kind == "relative_pose":
        vals = [c.get("auc10") for c in cells]
    elif spec.kind == "ablation":
        vals = [c.get("failure_rate") for c in cells]
    else:
        a, b = spec.thresholds[-1]
        vals = [c.get(f"success_{a:g}deg_{b:g}") for c in cells]
    vals = [v for v in vals if v is not None]
    return float(np.mean(vals)) if vals else float("nan")


def run(cfg: DictConfig, output_dir: Path) -> Dict[str, Any]:
    output_dir = Path(output_dir)
    seed = int(cfg.seed)
    random.seed(seed)
    np.random.seed(seed % (2 ** 32))
    torch.manual_seed(seed)
    torch.set_num_threads(choose_threads(cfg.get("threads")))
    backend = str(cfg.renderer.backend)
    proto = OmegaConf.to_container(cfg.benchmark_protocol, resolve=True)
    spec = ProtocolSpec.from_dict(proto, quick=bool(cfg.quick))
    base = LocalizerConfig.from_dict(OmegaConf.to_container(cfg.optimizer, resolve=True))
    needs = [m for m in spec.methods if m != "compare_only"]
    matcher, matcher_name = build_matcher(cfg.get("matcher")) if needs else (None, None)
    if needs and matcher is None:
        raise UserError(f"methods {needs} need a matcher: choose one, e.g. matcher=xfeat")
    scene = load_scene(cfg, spec, backend)
    if len(scene.queries) < spec.num_queries:
        log.warning("only %d queries available (protocol asks for %d)", len(scene.queries), spec.num_queries)
    done = load_done(cfg.resume) if cfg.get("resume") else {}
    info = scene.describe()
    writer = ResultsWriter(output_dir, spec, config=OmegaConf.to_container(cfg, resolve=True), scene=info,
                           matcher=matcher_name, localizer_config=base.to_dict(), seed=seed,
                           plots=bool(cfg.output.plots), plot_every=int(cfg.output.plot_every))
    log.info("%s (%s): %d runs on %s, translation scale %.4g (%s); output %s", spec.name,
             "quick" if spec.quick else "full size", spec.num_runs, info.get("model_path", info.get("kind")),
             scene.translation_scale, scene.translation_unit, output_dir)

    bar = None
    if cfg.output.progress:
        from tqdm import tqdm

        bar = tqdm(total=spec.num_runs, desc=spec.name, unit="run", dynamic_ncols=True)

    def progress(ev):
        if bar is None:
            return
        if ev["event"] == "run_start":
            bar.set_description(f"{spec.name} {ev['interval']} {ev['method']} q{ev['query']} p{ev['pose']}")
        elif ev["event"] == "iteration":
            r = ev["record"]
            if r.get("rot_err_deg") is not None:
                bar.set_postfix({"it": r["iteration"], "rot": f"{r['rot_err_deg']:.2f}",
                                 "trans": f"{r['trans_err'] / scene.translation_scale:.3f}"}, refresh=True)
        elif ev["event"] == "run_end":
            bar.update(1)

    def on_record(rec):
        writer.add(rec)

    try:
        records = run_protocol(scene, spec, base, matcher, backend=backend, on_record=on_record, done=done,
                               progress=progress, store_curves=bool(cfg.output.store_curves))
    finally:
        if bar is not None:
            bar.close()
    writer.set_records(records)
    doc = writer.write(final=True, plots=bool(cfg.output.plots))
    return doc


@hydra.main(version_base="1.3", config_path="../conf", config_name="benchmark")
def main(cfg: DictConfig) -> float:
    hc = HydraConfig.get()
    output_dir = Path(hc.runtime.output_dir)
    multirun = str(hc.mode) == "RunMode.MULTIRUN"
    doc = run_or_exit(lambda: run(cfg, output_dir), multirun, log)
    print((output_dir / "results.md").read_text())
    print(f"outputs in {output_dir}")
    proto = ProtocolSpec.from_dict(OmegaConf.to_container(cfg.benchmark_protocol, resolve=True), quick=bool(cfg.quick))
    value = headline(proto, doc["summary"])
    return value if math.isfinite(value) else float("nan")


if __name__ == "__main__":
    main()
