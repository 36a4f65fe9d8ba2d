r"""Time the CPU fitter's steps (the `Trainer` of tools/fit_scene.py) on a fitted model folder.

The fit starts from the folder's Gaussians, with the recipe ``tools/fit_scene.py`` would use for
its dataset (cfg_args ``source_path`` and ``resolution``), at step ``--at`` of the schedule (SH
degree at its maximum), so that a step costs what a late step of a real fit costs without fitting
for minutes first. After ``--warmup`` steps it times ``--steps`` steps and prints ms a step: the
whole step (wall and process CPU) and its parts (``Trainer.timings``: render, loss, backward,
densification statistics, densify, Adam, exposure).

``--checkouts OLD,NEW`` times the fitter of two (or more) checkouts in one run, each in its own
worker process: the rounds are interleaved (``--steps`` steps of each checkout in turn, the order
reversed every other round), so that a change of machine load hits them alike; the table gives the
median of the rounds and the ratios to the first checkout.

Examples:
    python tools/bench_fit.py -m ~/.cache/icomma/fits/goldcape --threads 2
    python tools/bench_fit.py -m ~/.cache/icomma/fits/goldcape --at 2000,5000 --rounds 4 \
        --checkouts ../old,.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path
from typing import Dict, List, Optional

import torch

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

PARTS = ("render", "loss", "backward", "stats", "densify", "adam", "exposure")


def log(msg: str) -> None:
    """Progress, on stderr (the table goes to stdout)."""
    print(msg, file=sys.stderr, flush=True)


def build_trainer(model: Path, at: int, seed: int = 0):
    """A `Trainer` on ``model``'s dataset, started from its Gaussians at schedule step ``at``."""
    from icomma_plugin.fit.config import FitConfig
    from icomma_plugin.fit.scene import describe_capture
    from icomma_plugin.fit.trainer import Trainer
    from icomma_plugin.fit.views import views_to_fit
    from icomma_plugin.io.datasets import read_dataset
    from icomma_plugin.io.model_folder import load_model_folder

    folder = load_model_folder(model)
    src = folder.cfg.get("source_path")
    if not src or not Path(src).is_dir():
        raise FileNotFoundError(f"--model: cfg_args source_path {src!r} of {model} is not a folder")
    white = bool(folder.cfg.get("white_background", False))
    res = folder.cfg.get("resolution", -1)
    capture = describe_capture(src, res, white_background=white)
    config = FitConfig.for_capture(capture.train_views, capture.width, capture.height,
                                   capture.object_render, seed=seed)
    if at >= config.iterations:
        raise ValueError(f"--at: {at} is past the recipe's {config.iterations} steps")
    scene = read_dataset(src, white_background=white)
    bg = (1.0, 1.0, 1.0) if white else (0.0, 0.0, 0.0)
    train = views_to_fit(scene.train, res, None, bg, keep_alpha=config.random_background)
    trainer = Trainer(folder.model, train, scene.scene_radius(), config, background=bg,
                      scene_centre=scene.scene_center(), exposure=not capture.object_render)
    trainer.state.active_sh_degree = trainer.state.max_sh_degree
    trainer.iteration = at
    return trainer


def time_steps(trainer, steps: int) -> Dict[str, float]:
    """Run ``steps`` steps; wall and CPU ms a step, the parts' ms a step, the Gaussian count."""
    trainer.timings = dict.fromkeys(trainer.timings, 0.0)
    c0, t0 = time.process_time(), time.perf_counter()
    for _ in range(steps):
        trainer.train_step()
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    parts = {k: 1e3 * trainer.timings.get(k, 0.0) / steps for k in PARTS}
    return {"ms": 1e3 * wall / steps, "cpu_ms": 1e3 * cpu / steps, "gaussians":
            trainer.state.num_gaussians, "step": trainer.iteration, **parts}


def worker_loop(root: Path) -> int:
    """Serve requests (JSON lines) with the fitter of ``root``.

    ``{"cmd": "setup", "model", "at", "threads", "warmup"}`` builds the trainer and runs the warm-up
    steps; ``{"cmd": "time", "steps"}`` -> `time_steps`; ``{"cmd": "quit"}``. A bad model folder or
    step is answered ``{"error": message}``.
    """
    sys.path.insert(0, str(root))
    import icomma_plugin

    print(json.dumps({"package": str(Path(icomma_plugin.__file__).resolve().parent)}), flush=True)
    trainer = None
    for line in sys.stdin:
        req = json.loads(line)
        if req["cmd"] == "quit":
            break
        try:
            if req["cmd"] == "setup":
                torch.set_num_threads(req["threads"])
                trainer = build_trainer(Path(req["model"]), req["at"])
                if req["warmup"]:
                    time_steps(trainer, req["warmup"])
                reply: Dict[str, object] = {}
            else:
                reply = time_steps(trainer, req["steps"])
        except (OSError, ValueError) as e:  # bad arguments: said by the parent, in one line
            reply = {"error": str(e)}
        print(json.dumps(reply), flush=True)
    return 0


def _median_row(samples: List[Dict[str, float]]) -> Dict[str, float]:
    keys = ("ms", "cpu_ms") + PARTS
    row = {k: statistics.median(s[k] for s in samples) for k in keys}
    row["gaussians"] = samples[-1]["gaussians"]
    return row


def _print_table(names: List[str], rows: List[Dict[str, object]]) -> None:
    cols = ("ms", "cpu_ms") + PARTS
    header = ["step", "checkout", "Gaussians", "wall ms", "CPU ms", *PARTS, "wall ratio",
              "CPU ratio"]
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for r in rows:
        base = r["rows"][0]
        for name, row in zip(names, r["rows"]):
            cells = [str(r["at"]), name, f"{row['gaussians']:,}"]
            cells += [f"{row[c]:.1f}" for c in cols]
            cells += [f"{base['ms'] / row['ms']:.2f}x" if row is not base else "1",
                      f"{base['cpu_ms'] / row['cpu_ms']:.2f}x" if row is not base else "1"]
            print("| " + " | ".join(cells) + " |")


def _schedule_steps(text: str) -> List[int]:
    """``--at``: a comma list of schedule steps, 0 or more (a usage error otherwise)."""
    try:
        steps = [int(a) for a in text.split(",") if a.strip()]
    except ValueError:
        steps = []
    if not steps or min(steps) < 0:
        raise argparse.ArgumentTypeError(
            f"must be a comma list of schedule steps (0 or more), got {text!r}")
    return steps


def run(args: argparse.Namespace) -> List[Dict[str, object]]:
    """Time every checkout at every ``--at``; prints the table, returns its rows."""
    from tools._common import CheckoutWorker

    roots = [Path(p).expanduser().resolve() for p in args.checkouts.split(",") if p.strip()]
    for r in roots:
        if not (r / "icomma_plugin" / "fit").is_dir():
            raise SystemExit(f"--checkouts: {r} is not a checkout with icomma_plugin/fit")
    rows: List[Dict[str, object]] = []
    for at in args.at:
        workers = [CheckoutWorker(r, Path(__file__), "--checkouts") for r in roots]
        try:
            for w in workers:
                reply = w.ask(cmd="setup", model=str(args.model), at=at, threads=args.threads,
                              warmup=args.warmup)
                if "error" in reply:
                    raise SystemExit(f"{w.name}: {reply['error']}")
            samples: List[List[Dict[str, float]]] = [[] for _ in workers]
            for rnd in range(args.rounds):
                order = list(range(len(workers)))[::(-1 if rnd % 2 else 1)]
                for i in order:
                    samples[i].append(workers[i].ask(cmd="time", steps=args.steps))
                done = ", ".join(f"{w.name} {s[-1]['ms']:.0f} ms" for w, s in zip(workers, samples))
                log(f"[step {at}] round {rnd + 1}/{args.rounds}: {done}")
            rows.append({"at": at, "rows": [_median_row(s) for s in samples],
                         "rounds": samples})
        finally:
            names = [w.name for w in workers]
            for w in workers:
                w.close()
    print(f"ms a step, median of {args.rounds} rounds of {args.steps} steps after {args.warmup} "
          f"warm-up steps, {args.threads} threads; ratios: {names[0]} / other")
    _print_table(names, rows)
    return rows


def main(argv: Optional[List[str]] = None) -> int:
    """Command line entry point; returns the exit status."""
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("-m", "--model", type=Path, help="a fitted model folder (its cfg_args "
                    "source_path must exist)")
    ap.add_argument("--at", type=_schedule_steps, default="5000",
                    help="comma list of schedule steps to start at")
    ap.add_argument("--steps", type=int, default=20, help="steps a round")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--warmup", type=int, default=5)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--checkouts", default=str(REPO),
                    help="comma list of repository roots (default: this one)")
    ap.add_argument("--json", type=Path, default=None, help="also write the results here (atomic)")
    ap.add_argument("--worker", type=Path, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker is not None:
        return worker_loop(args.worker.resolve())
    if args.model is None:
        ap.error("-m/--model is required")
    args.model = args.model.expanduser().resolve()
    if not args.model.is_dir():
        ap.error(f"-m/--model: not a folder: {args.model}")
    for name in ("steps", "rounds", "threads"):
        if getattr(args, name) < 1:
            ap.error(f"--{name} must be at least 1, got {getattr(args, name)}")
    if args.warmup < 0:
        ap.error(f"--warmup must be 0 or more, got {args.warmup}")
    rows = run(args)
    if args.json is not None:
        from icomma_plugin.io.atomic import write_json_atomic

        write_json_atomic(args.json, {"args": {k: str(v) for k, v in vars(args).items()},
                                      "results": rows})
        log(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
