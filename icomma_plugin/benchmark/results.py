"""Writes a protocol's outputs (results.json, results.md, PNGs) atomically, after every run.

results.json layout::

    {
      "schema": "icomma-benchmark/1",
      "status": "running" | "complete",
      "protocol": {...ProtocolSpec...}, "quick": bool, "size": "quick" | "full",
      "seed": int, "config": {...the composed Hydra config...},
      "scene": {...model path, dataset, queries, translation_unit, translation_scale...},
      "translation_normalisation": "...",
      "matcher": str, "localizer_config": {...},
      "timings": {"started": iso, "updated": iso, "wall_seconds": float},
      "summary": {...per (interval, method) cells...},
      "table": [...rows beside the paper...],
      "paper": {...paper.paper_summary() + the protocol's cells...},
      "records": [...one per run: seeds, initial pose, final errors, curves...],
      "files": [...]
    }
"""
from __future__ import annotations

import datetime as _dt
import json
import logging
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any, Dict, List, Optional

from ..io.atomic import write_json_atomic, write_text_atomic
from .paper import paper_rows, paper_summary
from .protocols import ProtocolSpec
from .report import markdown, save_plots, summarize, table_rows

logger = logging.getLogger(__name__)

__all__ = ["ResultsWriter", "load_done", "SCHEMA", "normalisation_text"]

SCHEMA = "icomma-benchmark/1"


def normalisation_text(unit: str, scale: float) -> str:
    """One sentence saying the translation unit of the results (and its scale)."""
    if unit == "scene_radius":
        return (
            "translations (perturbations and errors) are in units of the scene radius = "
            f"{scale:.6g} world units (3DGS getNerfppNorm: 1.1 x the largest distance of a train "
            "camera centre from their mean); world distance = normalised x scale"
        )
    return "translations are in world units (no normalisation; scale 1)"


def _now() -> str:
    return _dt.datetime.now().isoformat(timespec="seconds")


def load_done(path, retry_errors: bool = True) -> Dict[str, Dict[str, Any]]:
    """Records of a previous results.json keyed by their key (to resume a run).

    Runs that raised are left out when ``retry_errors`` (the default), so a resumed benchmark runs
    them again.
    """
    p = Path(str(path)).expanduser()
    if not p.is_file():
        raise FileNotFoundError(f"resume: no results.json at {p}")
    data = json.loads(p.read_text())
    if data.get("schema") != SCHEMA:
        raise ValueError(
            f"resume: {p} is not a benchmark results.json (schema {data.get('schema')!r})"
        )
    return {r["key"]: r for r in data.get("records", [])
            if "key" in r and not (retry_errors and r.get("error"))}


class ResultsWriter:
    """Accumulates records and rewrites the outputs after each (``add``) and at the end."""

    def __init__(
        self,
        out_dir,
        spec: ProtocolSpec,
        *,
        config: Dict[str, Any],
        scene: Dict[str, Any],
        matcher: Optional[str],
        localizer_config: Dict[str, Any],
        seed: int,
        plots: bool = True,
        plot_every: int = 1,
        calibration=None,
        calibration_source: Optional[str] = None,
    ):
        self.out_dir = Path(out_dir)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self.spec = spec
        self.config = config
        self.scene = scene
        self.matcher = matcher
        self.localizer_config = localizer_config
        self.seed = int(seed)
        self.plots = bool(plots)
        self.plot_every = max(1, int(plot_every))
        self.records: List[Dict[str, Any]] = []
        self.calibration = calibration  # a model's calibrated VerdictConfig (report.verdict_stats)
        self.calibration_source = calibration_source
        self.started = _now()
        self.t0 = time.perf_counter()
        self.files: List[str] = ["results.json", "results.md"]

    def header(self) -> Dict[str, Any]:
        """The lines above results.md's tables: model, queries, matcher, units, seed."""
        return {
            "model": self.scene.get("model_path", self.scene.get("kind")),
            "queries": ", ".join(
                q["name"] for q in self.scene.get("queries", [])[: self.spec.num_queries]
            ),
            "matcher": self.matcher or "none",
            "translation": normalisation_text(
                self.scene.get("translation_unit", "world"),
                float(self.scene.get("translation_scale", 1.0)),
            ),
            "seed": self.seed,
            **({"verdict calibration": f"{self.calibration_source} (rows *_calibrated)"}
               if self.calibration is not None else {}),
        }

    def add(self, record: Dict[str, Any]) -> None:
        """Add a finished run and rewrite the results (plots every ``plot_every`` runs)."""
        self.records.append(record)
        self.write(final=False, plots=self.plots and len(self.records) % self.plot_every == 0)

    def set_records(self, records: List[Dict[str, Any]]) -> None:
        """Replace the records (the protocol's final list, reused runs included)."""
        self.records = list(records)

    def write(self, final: bool = False, plots: Optional[bool] = None) -> Dict[str, Any]:
        """Write results.json and results.md atomically (and the plots, when asked).

        Args:
            final: mark the results complete (else running).
            plots: draw the plots; None: as the writer was configured.

        Returns:
            The results document (results.json's content).
        """
        summary = summarize(self.spec, self.records, self.calibration)
        if plots if plots is not None else self.plots:
            try:
                for f in save_plots(self.spec, summary, self.out_dir, self.matcher):
                    if f not in self.files:
                        self.files.append(f)
            except Exception as e:  # noqa: BLE001 - a plot must never lose the numbers
                logger.warning("could not draw the plots: %s", e)
        doc = {
            "schema": SCHEMA,
            "status": "complete" if final else "running",
            "protocol": self.spec.to_json(),
            "quick": self.spec.quick,
            "size": "quick" if self.spec.quick else "full",
            "seed": self.seed,
            "num_runs_done": len(self.records),
            "num_runs_planned": self.spec.num_runs,
            "scene": self.scene,
            "translation_normalisation": normalisation_text(
                self.scene.get("translation_unit", "world"),
                float(self.scene.get("translation_scale", 1.0)),
            ),
            "matcher": self.matcher,
            "localizer_config": self.localizer_config,
            "verdict_calibration": None if self.calibration is None else {
                "source": self.calibration_source, "verdict": asdict(self.calibration)},
            "config": self.config,
            "timings": {
                "started": self.started,
                "updated": _now(),
                "wall_seconds": time.perf_counter() - self.t0,
            },
            "summary": summary,
            "table": table_rows(self.spec, summary, self.matcher),
            "paper": {
                **paper_summary(),
                "dataset": self.spec.paper_dataset,
                "protocol_cells": paper_rows(self.spec.name, self.spec.paper_dataset),
            },
            "records": self.records,
            "files": list(self.files),
        }
        write_json_atomic(self.out_dir / "results.json", doc)
        status = (
            "complete" if final else f"partial: {len(self.records)} of {self.spec.num_runs} runs"
        )
        md = [f"# iComMa benchmark: {self.spec.name} ({status})", "",
              markdown(self.spec, summary, self.matcher, self.header())]
        md.append(
            f"Paper numbers: the {self.spec.paper_dataset} tables of the paper (source column; "
            "icomma_plugin/benchmark/paper.py). Our seconds are CPU seconds on this machine; the "
            "paper's are an RTX A6000 at 800x800."
        )
        write_text_atomic(self.out_dir / "results.md", "\n".join(md) + "\n")
        return doc
