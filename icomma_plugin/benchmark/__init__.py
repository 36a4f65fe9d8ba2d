"""Benchmark of iComMa localisation against the paper's protocols (no Hydra, no printing).

    from icomma_plugin.benchmark import ProtocolSpec, run_protocol, synthetic_scene
    scene = synthetic_scene(num_queries=1)
    spec = ProtocolSpec.from_dict({...})            # as conf/benchmark_protocol/<name>.yaml
    records = run_protocol(scene, spec, LocalizerConfig(), matcher)
    summary = summarize(spec, records)

Modules: ``sampling`` (initial poses, perturbation about the world origin), ``metrics`` (success
curves, AUC, failure statistics), ``baselines`` (matcher + essential matrix), ``scene`` (model +
queries + translation scale), ``protocols`` (protocol specs and methods), ``runner``,
``report`` (summaries, markdown beside the paper, plots), ``results`` (results.json writer),
``paper`` (the paper's numbers with their sources). Tool: ``tools/benchmark.py``; docs:
docs/BENCHMARK.md.
"""
from .baselines import (
    essential_matrix_baseline,
    estimate_relative_pose,
    relative_pose_gt,
    rotation_angle_deg,
)
from .metrics import (
    failure_stats,
    pad_curves,
    pose_auc,
    success_curve,
    success_mask,
    time_to_success,
)
from .paper import NOT_FOUND, PAPER_NUMBERS, PaperValue, paper_value
from .protocols import KINDS, METHODS, Interval, ProtocolSpec, method_config
from .report import markdown, save_plots, summarize, table_rows
from .results import ResultsWriter, load_done
from .runner import record_key, run_protocol
from .sampling import InitialPose, pose_seed, sample_initial_pose
from .scene import BenchScene, Query, load_model_folder_scene, synthetic_scene

__all__ = [
    "BenchScene",
    "InitialPose",
    "Interval",
    "KINDS",
    "METHODS",
    "NOT_FOUND",
    "PAPER_NUMBERS",
    "PaperValue",
    "ProtocolSpec",
    "Query",
    "ResultsWriter",
    "essential_matrix_baseline",
    "estimate_relative_pose",
    "failure_stats",
    "load_done",
    "load_model_folder_scene",
    "markdown",
    "method_config",
    "pad_curves",
    "paper_value",
    "pose_auc",
    "pose_seed",
    "record_key",
    "relative_pose_gt",
    "rotation_angle_deg",
    "run_protocol",
    "sample_initial_pose",
    "save_plots",
    "success_curve",
    "success_mask",
    "summarize",
    "synthetic_scene",
    "table_rows",
    "time_to_success",
]
