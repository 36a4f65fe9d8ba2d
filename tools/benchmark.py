#!/usr/bin/env python
r"""Benchmark localisation on a fitted 3DGS model against the paper's protocols.

    python tools/benchmark.py scene.model_path=~/.cache/icomma/scenes/lego_200 \
        benchmark_protocol=time_table
    python tools/benchmark.py scene.model_path=... benchmark_protocol=relative_pose quick=true
    python tools/benchmark.py -m scene.model_path=... quick=true \
        benchmark_protocol=curves_rotation,curves_translation,time_table,relative_pose,ablation
    python tools/benchmark.py -m hydra/launcher=joblib_local threads=1 scene.model_path=... \
        optimizer.lr=0.02,0.05                    # a parallel sweep of the paper's method
    python tools/benchmark.py scene.kind=synthetic benchmark_protocol=time_table \
        quick=true                                # no data needed

Methods (benchmark_protocol.methods): ``robust`` (the default localizer, config ``robust.*``),
``icomma`` (the paper's, config ``optimizer.*``), ``compare_only``, ``match_only``, ``essential``.

Outputs (Hydra's output folder, rewritten atomically after every run, so a partial run keeps its
numbers): results.json (all numbers, seeds, config, model path, timings, verdicts, errors),
results.md (our numbers beside the paper's, with the source and a Δ column), PNG plots. Resume an
interrupted run with ``resume=<old results.json>``. A run that raises is recorded with its error
and counted as a failure; the benchmark goes on. Returns the protocol's headline number (for
sweepers): the mean final success fraction of the first method over the intervals
(relative_pose: its AUC@10; ablation: its failure rate, to minimise).

Configuration: conf/benchmark.yaml + conf/benchmark_protocol/<name>.yaml (+ the matcher,
optimizer, renderer groups of tools/localize.py). Documentation: docs/BENCHMARK.md.
"""
from __future__ import annotations

import logging
import math
import sys
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
from hydra.core.hydra_config import HydraConfig  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402

from icomma_plugin.benchmark import (  # noqa: E402
    ProtocolSpec, ResultsWriter, load_done, load_model_folder_scene, run_protocol, synthetic_scene,
)
from icomma_plugin.io.datasets import PRINCIPAL_POINTS  # noqa: E402
from icomma_plugin.localize import LocalizerConfig, RobustConfig  # noqa: E402

log = logging.getLogger("benchmark")


def load_scene(cfg: DictConfig, spec: ProtocolSpec, backend: str):
    """The benchmark's scene from the ``scene`` group: synthetic or a fitted model folder.

    Raises:
        UserError: no or a missing ``scene.model_path``, or an unknown ``scene.kind``.
    """
    s = cfg.scene
    if s.kind == "synthetic":
        sy = s.synthetic
        return synthetic_scene(
            num_gaussians=int(sy.num_gaussians),
            width=int(sy.width),
            height=int(sy.height),
            num_queries=spec.num_queries,
            seed=int(sy.seed),
            translation_unit=str(s.translation_unit),
            backend=backend,
        )
    if s.kind == "model_folder":
        if OmegaConf.is_missing(s, "model_path") or not s.model_path:
            raise common.UserError(
                "scene.model_path is required with scene.kind=model_folder (fit one with "
                "`make scenes` or tools/fit_scene.py, or use scene.kind=synthetic)"
            )
        if not Path(str(s.model_path)).expanduser().is_dir():
            raise common.UserError(
                f"scene.model_path: model folder not found: {s.model_path} (fit one with "
                "`make scenes` or tools/fit_scene.py, or use scene.kind=synthetic)"
            )
        q = s.query
        idx = None if q.indices is None else [int(i) for i in q.indices]
        no_start = any(iv.no_start for iv in spec.intervals)
        pp = s.get("principal_point")
        if pp not in (None, "auto", *PRINCIPAL_POINTS):
            raise common.UserError(f"scene.principal_point must be auto, "
                                   f"{' or '.join(PRINCIPAL_POINTS)}, got {pp!r}")
        return load_model_folder_scene(
            s.model_path,
            dataset=q.dataset,
            num_queries=spec.num_queries,
            split=str(q.split),
            query_indices=idx,
            image_scale=None if q.image_scale is None else float(q.image_scale),
            white_background=None if s.white_background is None else bool(s.white_background),
            iteration=s.iteration,
            translation_unit=str(s.translation_unit),
            no_start_queries=spec.num_queries * spec.poses_per_query if no_start else 0,
            photos=str(s.get("photos") or "auto"),
            principal_point=pp,
        )
    raise common.UserError(f"scene.kind must be model_folder or synthetic, got {s.kind!r}")


def verdict_calibration(cfg: DictConfig, model):
    """(calibrated VerdictConfig or None, where it came from) of the ``calibration`` key.

    ``auto``: the model's stored calibration (docs/AUDIT.md) if it has one; ``none``; or a file.

    Raises:
        UserError: a calibration file that is missing, unreadable or for another model.
    """
    from icomma_plugin.localization.calibration import (
        calibration_path,
        load_calibration,
        model_key,
    )

    choice = cfg.get("calibration")
    if choice is None or str(choice).lower() in ("none", "false"):
        return None, None
    try:
        if str(choice).lower() == "auto":
            found = load_calibration(model)
            return found, None if found is None else str(calibration_path(model_key(model)))
        return load_calibration(model, path=str(choice)), str(choice)
    except ValueError as e:
        raise common.UserError(f"calibration: {e}") from None


def headline(spec: ProtocolSpec, summary: Dict[str, Any]) -> float:
    """The protocol's headline number for sweepers (module docstring); NaN without results."""
    first = spec.methods[0]
    cells = [c for c in summary["cells"] if c["method"] == first and c["n"]]
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


def count_run(counts: Dict[str, int], record: Dict[str, Any]) -> None:
    """Add a finished run to the progress bar's counts by verdict (``error``: it raised)."""
    if record.get("error"):
        counts["error"] += 1
    elif record.get("status") in counts:
        counts[record["status"]] += 1


def run(cfg: DictConfig, output_dir: Path) -> Dict[str, Any]:
    """Run the configured protocol into ``output_dir``, with the tool's thread count.

    Returns:
        The results document (as written to results.json).
    """
    with common.torch_threads(cfg.get("threads")):
        return _run(cfg, Path(output_dir))


def _run(cfg: DictConfig, output_dir: Path) -> Dict[str, Any]:
    seed = int(cfg.seed)
    common.seed_everything(seed)
    backend = common.check_backend(str(cfg.renderer.backend))
    spec = ProtocolSpec.from_dict(common.container(cfg.benchmark_protocol), quick=bool(cfg.quick))
    base = common.build_optimizer(cfg.optimizer)
    if not isinstance(base, LocalizerConfig):
        raise common.UserError(
            "optimizer must be the paper's group here (icomma or compare_only): it is the "
            "base of the icomma / compare_only / match_only methods; the default method's "
            "config is robust.*"
        )
    if cfg.get("robust") is not None:
        robust = common.build_optimizer(cfg.robust, "robust")
    else:
        robust = RobustConfig()
    needs = [m for m in spec.methods if m != "compare_only"]
    matcher, matcher_name = common.build_matcher(cfg.get("matcher")) if needs else (None, None)
    if needs and matcher is None:
        raise common.UserError(f"methods {needs} need a matcher: choose one, e.g. matcher=xfeat")
    scene = load_scene(cfg, spec, backend)
    if len(scene.queries) < spec.num_queries:
        log.warning(
            "only %d queries available (protocol asks for %d)", len(scene.queries), spec.num_queries
        )
    done = load_done(cfg.resume) if cfg.get("resume") else {}
    calibration, calibration_source = verdict_calibration(cfg, scene.model)
    info = scene.describe()
    writer = ResultsWriter(
        output_dir,
        spec,
        config=common.container(cfg),
        scene=info,
        matcher=matcher_name,
        localizer_config={"icomma": base.to_dict(), "robust": robust.to_dict()},
        seed=seed,
        plots=bool(cfg.output.plots),
        plot_every=int(cfg.output.plot_every),
        calibration=calibration,
        calibration_source=calibration_source,
    )
    log.info(
        "%s (%s): %d runs on %s, translation scale %.4g (%s); output %s",
        spec.name,
        "quick" if spec.quick else "full size",
        spec.num_runs,
        info.get("model_path", info.get("kind")),
        scene.translation_scale,
        scene.translation_unit,
        output_dir,
    )

    bar = None
    if cfg.output.progress:
        from tqdm import tqdm

        bar = tqdm(total=spec.num_runs, desc=spec.name, unit="run", dynamic_ncols=True)
    counts = {"ok": 0, "uncertain": 0, "failed": 0, "error": 0}

    def progress(ev):
        if bar is None:
            return
        if ev["event"] == "run_start":
            bar.set_description(
                f"{spec.name} {ev['interval']} {ev['method']} q{ev['query']} p{ev['pose']}"
            )
        elif ev["event"] == "run_end":
            count_run(counts, ev.get("record") or {})
            bar.set_postfix(counts, refresh=False)
            bar.update(1)

    try:
        records = run_protocol(
            scene,
            spec,
            base,
            matcher,
            robust_config=robust,
            backend=backend,
            on_record=writer.add,
            done=done,
            progress=progress,
            store_curves=bool(cfg.output.store_curves),
        )
    finally:
        if bar is not None:
            bar.close()
    writer.set_records(records)
    doc = writer.write(final=True, plots=bool(cfg.output.plots))
    errors = sum(1 for r in records if r.get("error"))
    if errors:
        log.warning(
            "%d of %d runs raised an error (recorded in results.json, counted as failures)",
            errors,
            len(records),
        )
    return doc


@hydra.main(version_base="1.3", config_path=CONFIG_DIR, config_name="benchmark")
def main(cfg: DictConfig) -> float:
    """Hydra entry point: run, print results.md, return the headline number (for sweepers)."""
    hc = HydraConfig.get()
    output_dir = Path(hc.runtime.output_dir)
    multirun = str(hc.mode) == "RunMode.MULTIRUN"
    doc = common.run_or_exit(lambda: run(cfg, output_dir), multirun, log)
    print((output_dir / "results.md").read_text())
    errors = sum(1 for r in doc["records"] if r.get("error"))
    if errors:
        print(f"{errors} of {len(doc['records'])} runs failed with an error (see results.json)")
    print(f"outputs in {output_dir}")
    proto = ProtocolSpec.from_dict(common.container(cfg.benchmark_protocol), quick=bool(cfg.quick))
    value = headline(proto, doc["summary"])
    return value if math.isfinite(value) else float("nan")


if __name__ == "__main__":
    main()
