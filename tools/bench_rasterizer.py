"""Time the rasterizer backends on synthetic scenes; prints a markdown table.

For each backend x scene (Gaussians x resolution) it measures, in ms (median of --repeats after a
warm-up run): the forward, the forward + backward (gradients for the Gaussians), the forward +
backward with the pose gradient too (viewmatrix / projmatrix / campos require grad), and the
forward + backward with ONLY the pose requiring grad (a localizer's fixed scene: the native
backward then skips the Gaussians' own gradients), plus the native/reference speed ratio and, per
backend, the fwd+bwd+pose / fwd+pose-only ratio, measured in the same run (the modes of a scene
are timed interleaved, one call of each in turn, so that a change of machine load hits them
alike). The reference (pure PyTorch) is only run up to
--reference-max-gaussians and --reference-max-pixels ("—" elsewhere).

The "cuda" backend (native CUDA kernel; scene copied to the GPU once, timings bracketed by
torch.cuda.synchronize) is added to the default backends when it is usable here; the table then
also gives the cpu/cuda speed ratio of the same run.

Examples:
    python tools/bench_rasterizer.py                       # full table
    python tools/bench_rasterizer.py --quick               # small, fast
    python tools/bench_rasterizer.py --backends cpu --threads 2 --json bench_out/raster.json
    python tools/bench_rasterizer.py --backends cuda,cpu --sizes 300000 --resolutions 800  # GPU
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path
from typing import Callable, Dict, List, Optional, Tuple

import torch

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

# the one home of synthetic scenes, and of atomic writes
from icomma_plugin.app.demo_scene import raster_bench_scene  # noqa: E402
from icomma_plugin.io.atomic import write_json_atomic  # noqa: E402

MODES = ("fwd", "fwd+bwd", "fwd+bwd+pose", "fwd+pose-only")
DEFAULT_SIZES = (10_000, 50_000, 200_000)
DEFAULT_RES = (200, 400, 800)


def log(msg: str) -> None:
    """Progress on stderr (stdout carries the table)."""
    print(msg, file=sys.stderr, flush=True)


# ----------------------------------------------------------------------------------------------
# Synthetic scene: P Gaussians in front of the camera, each a few pixels on screen.
# ----------------------------------------------------------------------------------------------
# ----------------------------------------------------------------------------------------------
# Backends: name -> (callable with the contract signature, None) or (None, reason unavailable).
# "cuda" runs the same native function on a copy of the scene on the GPU (BACKEND_DEVICE).
# ----------------------------------------------------------------------------------------------
BACKEND_DEVICE = {"reference": "cpu", "cpu": "cpu", "cuda": "cuda"}


def get_backend(name: str) -> Tuple[Optional[Callable], Optional[str]]:
    """(rasterize function, None) for a usable backend, else (None, why it is not usable)."""
    if name == "reference":
        from gaussian_renderer_pose.reference import rasterize_gaussians_reference

        return rasterize_gaussians_reference, None
    if name in ("cpu", "cuda"):
        from gaussian_renderer_pose import _backend

        ok, why = _backend.native_status(name)
        if not ok:
            return None, why
        from gaussian_renderer_pose._native import rasterize_gaussians_native

        return rasterize_gaussians_native, None
    return None, f"unknown backend {name!r} (known: reference, cpu, cuda)"


def default_backends() -> str:
    """cpu,reference, plus cuda first when the CUDA backend is usable here."""
    return "cuda,cpu,reference" if get_backend("cuda")[0] is not None else "cpu,reference"


def scene_to(scene: Dict[str, object], device: str) -> Dict[str, object]:
    """The scene with its tensors on ``device``."""
    return {k: (v.to(device) if isinstance(v, torch.Tensor) else v) for k, v in scene.items()}


def _sync(scene: Dict[str, object]) -> None:
    if scene["means3D"].device.type == "cuda":
        torch.cuda.synchronize(scene["means3D"].device)


GRAD_INPUTS = ("means3D", "means2D", "opacities", "shs", "scales", "rotations")
POSE_INPUTS = ("viewmatrix", "projmatrix", "campos")


def run_once(fn: Callable, scene: Dict[str, object], mode: str) -> float:
    """Milliseconds of one call of ``fn`` in ``mode`` (one of MODES)."""
    tensors = {k: v for k, v in scene.items() if k != "settings"}
    if mode != "fwd":
        names = {"fwd+bwd": GRAD_INPUTS, "fwd+bwd+pose": GRAD_INPUTS + POSE_INPUTS,
                 "fwd+pose-only": POSE_INPUTS}[mode]
        tensors = {
            k: (v.detach().clone().requires_grad_(True) if (k in names and v is not None) else v)
            for k, v in tensors.items()
        }
    _sync(scene)
    t0 = time.perf_counter()
    if mode == "fwd":
        with torch.no_grad():
            fn(**tensors, **scene["settings"])
    else:
        color, _radii, invdepth, _dacc, _alpha = fn(**tensors, **scene["settings"])
        loss = color.square().sum() + invdepth.sum()
        loss.backward()
    _sync(scene)
    return (time.perf_counter() - t0) * 1e3


def time_modes(fn: Callable, scene: Dict[str, object], modes: List[str], repeats: int,
               warmup: bool = True) -> Dict[str, float]:
    """Median ms per mode; the modes are run in turn, `repeats` rounds (after one warm-up round)."""
    if warmup:
        for mode in modes:
            run_once(fn, scene, mode)
    times: Dict[str, List[float]] = {mode: [] for mode in modes}
    for _ in range(repeats):
        for mode in modes:
            times[mode].append(run_once(fn, scene, mode))
    return {mode: statistics.median(t) for mode, t in times.items()}


def main(argv: Optional[List[str]] = None) -> int:
    """Command line entry point; returns the exit status."""
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--backends", default=None,
                    help="comma list of reference, cpu, cuda "
                         "(default: cpu,reference, and cuda when usable)")
    ap.add_argument("--sizes", default=",".join(map(str, DEFAULT_SIZES)),
                    help="numbers of Gaussians")
    ap.add_argument("--resolutions", default=",".join(map(str, DEFAULT_RES)),
                    help="square image sizes")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=None,
                    help="torch.set_num_threads (default: torch's)")
    ap.add_argument("--reference-max-gaussians", type=int, default=20_000)
    ap.add_argument("--reference-max-pixels", type=int, default=200 * 200)
    ap.add_argument("--json", type=Path, default=None, help="also write the results here (atomic)")
    ap.add_argument("--quick", action="store_true", help="small scenes, 2 repeats")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)

    if args.threads is not None:
        torch.set_num_threads(args.threads)
    sizes = [int(s) for s in args.sizes.split(",") if s]
    resolutions = [int(s) for s in args.resolutions.split(",") if s]
    repeats = args.repeats
    if args.quick:
        sizes, resolutions, repeats = [2_000, 10_000], [200], 2
        args.reference_max_gaussians = min(args.reference_max_gaussians, 2_000)
    # the target comparison: 20k Gaussians at 200x200 for the reference
    extra = [(args.reference_max_gaussians, 200)] if not args.quick else []
    scenes = sorted({(p, r) for p in sizes for r in resolutions} | set(extra))
    backends = [b.strip() for b in (args.backends or default_backends()).split(",") if b.strip()]
    fns = {}
    for b in backends:
        fn, why = get_backend(b)
        if fn is None:
            log(f"backend {b} unavailable: {why}")
        fns[b] = fn

    results = []
    for P, R in scenes:
        scene_cpu = raster_bench_scene(P, R, seed=args.seed)
        on_device = {"cpu": scene_cpu}
        row = {"gaussians": P, "resolution": R, "ms": {}}
        for b in backends:
            fn = fns[b]
            dev = BACKEND_DEVICE.get(b, "cpu")
            if fn is not None and dev not in on_device:
                on_device[dev] = scene_to(scene_cpu, dev)
            scene = on_device[dev]
            skip = fn is None or (b == "reference" and (P > args.reference_max_gaussians
                                                        or R * R > args.reference_max_pixels))
            if skip:
                row["ms"].update({f"{b}/{mode}": None for mode in MODES})
                continue
            log(f"[{P} x {R}^2] {b} {', '.join(MODES)} ...")
            # the reference is slow and has no JIT/caches to warm: one timed run
            is_ref = b == "reference"
            ms = time_modes(fn, scene, list(MODES), 1 if is_ref else repeats, warmup=not is_ref)
            row["ms"].update({f"{b}/{mode}": v for mode, v in ms.items()})
        results.append(row)

    # markdown table
    cols = [f"{b}/{m}" for b in backends for m in MODES]
    # (numerator, denominator, mode): reference/each native backend, and cpu/cuda
    ratio_cols = []
    if "reference" in backends:
        ratio_cols = [("reference", b, m) for b in backends if b != "reference" for m in MODES]
    if "cpu" in backends and "cuda" in backends:
        ratio_cols += [("cpu", "cuda", m) for m in MODES]
    # (backend, numerator mode, denominator mode): what skipping the Gaussians' gradients buys
    mode_ratio_cols = [(b, "fwd+bwd+pose", "fwd+pose-only") for b in backends if b != "reference"]
    short = {"reference": "ref"}
    header = (["Gaussians", "image"] + [f"{c} (ms)" for c in cols]
              + [f"{short.get(a, a)}/{b} {m}" for a, b, m in ratio_cols]
              + [f"{b} {n} / {d}" for b, n, d in mode_ratio_cols])
    gpu = f", GPU: {torch.cuda.get_device_name()}" if "cuda" in backends and fns.get("cuda") else ""
    print(f"threads: {torch.get_num_threads()}{gpu}, repeats: {repeats} (median, after a warm-up), "
          "reference: 1 timed run")
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for row in results:
        cells = [f"{row['gaussians']:,}", f"{row['resolution']}x{row['resolution']}"]
        for c in cols:
            v = row["ms"][c]
            cells.append("—" if v is None else f"{v:.1f}")
        for a, b, m in ratio_cols:
            r, n = row["ms"].get(f"{a}/{m}"), row["ms"].get(f"{b}/{m}")
            ratio = None if (r is None or n is None or n <= 0) else r / n
            row.setdefault("ratio", {})[f"{a}/{b}/{m}"] = ratio
            cells.append(
                "—" if ratio is None else (f"{ratio:.0f}x" if ratio >= 10 else f"{ratio:.1f}x")
            )
        for b, n, d in mode_ratio_cols:
            num, den = row["ms"].get(f"{b}/{n}"), row["ms"].get(f"{b}/{d}")
            ratio = None if (num is None or den is None or den <= 0) else num / den
            row.setdefault("ratio", {})[f"{b}/{n}/{d}"] = ratio
            cells.append("—" if ratio is None else f"{ratio:.2f}x")
        print("| " + " | ".join(cells) + " |")
    if args.json is not None:
        write_json_atomic(
            args.json,
            {"threads": torch.get_num_threads(), "repeats": repeats, "results": results},
        )
        log(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
