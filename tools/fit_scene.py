#!/usr/bin/env python
r"""Fit a 3DGS model to a posed image set on CPU (gaussian_renderer_pose) and write a model folder.

    python tools/fit_scene.py -s ../shared/data/nerf_synthetic/lego_400 -m OUT/lego_200 -r 2
    python tools/fit_scene.py -s ../shared/data/fox -m OUT/fox_270 -r 4 --threads 2
    python tools/fit_scene.py -s DATA -m OUT --iterations 3000 --eval-views 25 --eval-interval 1000
    python tools/fit_scene.py -s DATA -m OUT --set densify_grad_threshold=1e-4 \
        --set max_gaussians=80000
    python tools/fit_scene.py -m OUT/fox_270 --evaluate     # PSNRs + OUT/fox_270/eval_test_grid.png
    python tools/fit_scene.py -s DATA -m OUT --set principal_point=centre  # upstream's camera

Input: any folder `icomma_plugin.io.datasets.read_dataset` reads (COLMAP, Blender, instant-ngp /
nerfstudio transforms.json, LLFF). Distorted photos are undistorted and the pixels that fall
outside the photo are left out of the losses and of PSNR (validity masks). A capture without a
point cloud starts from a plane sweep over its training views (fit.init.initial_points).

Output (upstream 3DGS layout, loadable by icomma_plugin.io.model_folder.load_model_folder and by
upstream render.py): cfg_args, cameras.json, input.ply, point_cloud/iteration_N/point_cloud.ply,
plus metrics.json (train and test PSNR on valid pixels, iterations, Gaussian count, wall and CPU
seconds, resolution). An existing model folder is replaced only with --overwrite. cfg_args also
says which principal point the views were fitted with (`principal_point`: `dataset`, their files'
cx, cy, by default; `centre`, the image centre, as upstream 3DGS fits every capture, with --set
principal_point=centre), and the localizer takes the dataset's views at the same one.

Schedule (--recipe capture, the default): FitConfig.for_capture: the iterations from the photo
count and size unless --iterations is given, the densification / opacity-reset / SH schedule
scaled to them (densify from 4 % to 50 % of the run every 2 %, opacity reset every 30 %, SH
degree +1 every 10 %; upstream's learning rates), and, for photographed captures, coarse-to-fine,
bounded initial scales and a random background colour at every step. Photographed captures also
get a far-field shell and per-photo exposure (exposure.json). Any FitConfig field can be set with
--set name=value. The recipe, its comparison with upstream and measurements: docs/FITTING.md.
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

import torch  # noqa: E402

if __package__:
    from ._common import choose_threads, parse_overrides  # noqa: E402
else:  # run as a script from a checkout
    from tools._common import choose_threads, parse_overrides  # noqa: E402
from icomma_plugin.fit import FitConfig, fit_scene  # noqa: E402
from icomma_plugin.fit.config import auto_iterations, step_seconds  # noqa: E402

log = logging.getLogger("fit_scene")


def default_data_root() -> Path:
    """The shared data folder (``$ICOMMA_SHARED_DATA``, else ../shared/data)."""
    from icomma_plugin.io.datasets import shared_data_root

    return shared_data_root()


def parse_args(argv=None) -> argparse.Namespace:
    """The command line (module docstring)."""
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument(
        "-s",
        "--source",
        default=None,
        help="dataset folder (COLMAP / Blender / transforms.json / LLFF); default: "
        "$ICOMMA_SHARED_DATA/nerf_synthetic/lego_400",
    )
    p.add_argument("-m", "--model", required=True, help="model folder to write")
    p.add_argument(
        "--iterations",
        type=int,
        default=None,
        help="steps (default: FitConfig.for_capture's count from the photo count and size; "
        "with --recipe scaled, 5000)",
    )
    p.add_argument(
        "--minutes",
        type=float,
        default=None,
        help="a time budget instead of the recipe's own length: the steps that fit in it on "
        "this machine (a few steps of a synthetic fit timed first; the steps after "
        "densification planned again at the step time measured there), up to upstream's 30000 "
        "(goldcape 40 minutes: +1.8 dB held out, localized twice as close; docs/FITTING.md). "
        "Not with --iterations",
    )
    p.add_argument(
        "--recipe",
        choices=["capture", "scaled"],
        default="capture",
        help="capture (default): FitConfig.for_capture, what a photographed capture needs "
        "(object renders such as NeRF-synthetic get the scaled schedule alone); scaled: the "
        "schedule scaled to --iterations only (the fitter before issue 18, plus its new "
        "defaults: far field, exposure; see docs/FITTING.md)",
    )
    g = p.add_mutually_exclusive_group()
    g.add_argument(
        "-r",
        "--resolution",
        type=int,
        default=-1,
        help="upstream -r: 1/2/4/8 divide the size, other values are a target width, -1 native",
    )
    g.add_argument(
        "--downscale", type=float, default=None, help="divide the image size by this factor"
    )
    b = p.add_mutually_exclusive_group()
    b.add_argument(
        "--white-background", dest="white_background", action="store_true", default=None
    )
    b.add_argument("--black-background", dest="white_background", action="store_false")
    p.add_argument(
        "--eval-views", type=int, default=0, help="test views to evaluate (0: all, evenly spaced)"
    )
    p.add_argument(
        "--eval-interval",
        type=int,
        default=0,
        help="evaluate test PSNR every N iterations (0: end only)",
    )
    p.add_argument(
        "--save-iterations", type=int, nargs="*", default=[], help="also save these iterations"
    )
    p.add_argument(
        "--num-random-points", type=int, default=None, help="random init points (no point cloud)"
    )
    p.add_argument("--max-gaussians", type=int, default=None, help="cap on the Gaussian count")
    p.add_argument("--backend", default="auto", choices=["auto", "cpu", "reference", "cuda"])
    p.add_argument("--device", default="cpu")
    p.add_argument(
        "--threads",
        type=int,
        default=0,
        help="torch threads; 0 (default): the cores other work leaves free "
        "(tools/_common.choose_threads; contended threads run ~10x slower)",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="override any FitConfig field, repeatable (YAML values, or a Python literal "
        "such as (0.25, 0.5); the syntax of every tool's --set)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing model folder")
    p.add_argument("--no-progress", action="store_true",
                   help="no tqdm progress bar (a log line every minute instead, with the time "
                   "left, unless --log-every)")
    p.add_argument(
        "--log-every",
        type=int,
        default=0,
        help="also log loss / PSNR / count every N iterations",
    )
    p.add_argument("--log-level", default="INFO")
    p.add_argument(
        "--evaluate",
        action="store_true",
        help="fit nothing: print train / test PSNR (valid pixels; with and without exposure) of "
        "the model folder -m on its dataset (-s, default: its cfg_args source_path; -r "
        "likewise) and write a grid of held-out photos beside their renders (--grid)",
    )
    p.add_argument(
        "--grid",
        default=None,
        help="--evaluate: the PNG of held-out photos | renders | differences (default: "
        "MODEL/eval_test_grid.png; 'none': no picture)",
    )
    return p.parse_args(argv)


def timed_step_factor() -> float:
    """This machine's fitter step over the machine `step_seconds` models (a few steps timed)."""
    from icomma_plugin.fit import timing

    factor = timing.step_time_factor()
    log.info("--minutes: a fitter step here takes %.2fx the reference machine's (timed on a "
             "synthetic fit; torch threads: %d); the budget is counted at that rate", factor,
             torch.get_num_threads())
    return factor


def build_config(args: argparse.Namespace, capture=None) -> FitConfig:
    """The FitConfig of the command line: the recipe plus the flags and ``--set``s.

    Args:
        args: the parsed command line.
        capture: `icomma_plugin.fit.scene.CaptureInfo` of the dataset (for --recipe capture);
            None: the scaled schedule of --iterations (default 5000).

    Raises:
        ValueError: a ``--set`` that is not FIELD=VALUE or names no FitConfig field.
    """
    over = {
        "eval_views": args.eval_views,
        "eval_interval": args.eval_interval,
        "save_iterations": tuple(args.save_iterations),
        "backend": args.backend,
        "seed": args.seed,
    }
    if args.num_random_points is not None:
        over["num_random_points"] = args.num_random_points
    if args.max_gaussians is not None:
        over["max_gaussians"] = args.max_gaussians
    names = set(FitConfig.field_names())
    for k, v in parse_overrides(args.set):
        if k not in names:
            raise ValueError(f"--set: unknown FitConfig field {k!r}; fields: {sorted(names)}")
        over[k] = v
    seconds = None
    if args.minutes is not None:
        if args.iterations is not None:
            raise ValueError("--minutes and --iterations both set the run's length: give one")
        if not args.minutes > 0:
            raise ValueError(f"--minutes must be > 0, got {args.minutes}")
        if capture is None:
            raise ValueError("--minutes needs the capture's photos to time a step")
        factor = timed_step_factor()
        seconds = 60.0 * args.minutes / factor
        # ... and the run's tail planned again at the step time measured when densification ends
        over.setdefault("time_budget", 60.0 * args.minutes)
    if args.recipe == "capture" and capture is not None:
        cfg = FitConfig.for_capture(capture.train_views, capture.width, capture.height,
                                    capture.object_render, args.iterations, seconds, **over)
    elif seconds is not None:
        cfg = FitConfig.scaled_schedule(
            auto_iterations(capture.train_views, capture.width * capture.height, seconds), **over)
    else:
        cfg = FitConfig.scaled_schedule(args.iterations or 5000, **over)
    if seconds is not None:  # what the budget bought (at least MIN_ITERATIONS, at most 30000)
        log.info("--minutes %g: %d steps, about %.0f minutes of steps here", args.minutes,
                 cfg.iterations,
                 cfg.iterations * step_seconds(capture.width * capture.height) * factor / 60.0)
    return cfg


def evaluate(args: argparse.Namespace) -> int:
    """--evaluate: PSNR of an existing model folder, printed as JSON."""
    from icomma_plugin.fit import evaluate_model_folder

    grid = args.grid if args.grid is not None else str(Path(args.model) / "eval_test_grid.png")
    try:
        res = evaluate_model_folder(
            args.model,
            args.source,
            None if args.resolution == -1 else args.resolution,
            backend=args.backend,
            grid=None if grid.lower() == "none" else grid,
        )
    except ValueError as e:
        log.error("%s", e)
        return 2
    print(json.dumps(res, indent=2))
    return 0


#: Without a bar or ``--log-every``, a log line this often [s]: an hour's fit in a job's log
#: (``--no-progress``) still says how far it is.
LOG_SECONDS = 60.0


def make_progress(bar, log_every: int, log_seconds: float = LOG_SECONDS, clock=time.perf_counter):
    """The fit's progress callback: a tqdm bar (or None) and a log line every `log_every`.

    With neither, a log line every `log_seconds` of `clock`, with the time left at the rate
    since the last line (a step's cost grows through a run: coarse-to-fine, densification).
    """
    t_start = clock()
    last = [t_start, 0]  # the time and the iteration of the last line

    def progress(it, total, info):
        if bar is not None:
            bar.n = it
            post = {
                "loss": f"{info.get('loss', float('nan')):.4f}",
                "N": int(info.get("num_gaussians", 0)),
            }
            if "psnr" in info:
                post["psnr"] = f"{info['psnr']:.2f}"
            bar.set_postfix(post, refresh=False)
            bar.refresh()
        if log_every and (it % log_every == 0 or it == total):
            log.info(
                "iteration %d/%d: loss %.4f, train-view PSNR %.2f dB, %d Gaussians, %.0f s",
                it, total, info.get("loss", float("nan")), info.get("psnr", float("nan")),
                int(info.get("num_gaussians", 0)), clock() - t_start,
            )
        elif bar is None and not log_every:
            now = clock()
            if now - last[0] >= log_seconds or it == total:
                rate = (now - last[0]) / max(it - last[1], 1)
                last[:] = [now, it]
                spent = now - t_start
                left = rate * (total - it)
                log.info("iteration %d/%d (%.0f %%): loss %.4f, %d Gaussians, %.0f s, about "
                         "%.0f s left", it, total, 100.0 * it / max(total, 1),
                         info.get("loss", float("nan")), int(info.get("num_gaussians", 0)),
                         spent, left)

    return progress


def main(argv=None) -> int:
    """Fit (or with --evaluate, measure) a model folder. Returns the exit status."""
    args = parse_args(argv)
    logging.basicConfig(
        level=getattr(logging, args.log_level.upper(), logging.INFO),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    torch.set_num_threads(choose_threads(args.threads or None))
    log.info("torch threads: %d", torch.get_num_threads())
    if args.evaluate:
        return evaluate(args)
    source = args.source or default_data_root() / "nerf_synthetic" / "lego_400"
    try:
        capture = None
        if args.recipe == "capture":
            from icomma_plugin.fit.scene import describe_capture

            capture = describe_capture(source, None if args.downscale else args.resolution,
                                       args.downscale, args.white_background)
        config = build_config(args, capture)
    except ValueError as e:
        log.error("%s", e)
        return 2

    bar = None
    if not args.no_progress:
        from tqdm import tqdm

        bar = tqdm(total=config.iterations, dynamic_ncols=True, mininterval=1.0)
    log.info("recipe %s: %d iterations, coarse-to-fine %s, initial scales <= %s px",
             args.recipe, config.iterations, list(config.coarse_to_fine), config.init_max_pixels)
    progress = make_progress(bar, args.log_every)
    t0 = time.perf_counter()
    try:
        res = fit_scene(
            source,
            args.model,
            config,
            resolution=None if args.downscale else args.resolution,
            downscale=args.downscale,
            white_background=args.white_background,
            overwrite=args.overwrite,
            progress=progress,
            device=args.device,
        )
    except ValueError as e:  # bad user input (dataset, resolution, existing folder...)
        if bar is not None:
            bar.close()
        log.error("%s", e)
        return 2
    if bar is not None:
        bar.close()
    m = res.metrics
    keys = ("test_psnr", "train_psnr", "test_psnr_right_half", "test_psnr_right_half_exposure",
            "test_psnr_neighbour_exposure",
            "train_psnr_exposure", "test_views", "iterations", "num_gaussians", "seconds_train",
            "seconds_cpu", "seconds_per_step", "seconds_total", "resolution", "backend",
            "threads")
    summary = {k: m[k] for k in keys}
    summary["model_path"] = str(res.model_path)
    summary["wall_seconds"] = round(time.perf_counter() - t0, 1)
    print(json.dumps(summary, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
