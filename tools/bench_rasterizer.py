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

`--checkouts OLD,NEW` compares the native CPU backend of two (or more) checkouts of this
repository, each built in place, in ONE run: every checkout's kernel runs in its own worker
process (this script with `--worker ROOT`), the calls are interleaved (one call of each checkout in
turn, alternating which goes first), and the table gives, per scene, thread count and mode, the
wall ms, ns per Gaussian, process CPU ms and the ratios to the first checkout, and whether the
forward image and the pose-only camera gradient are the same bits.

Examples:
    python tools/bench_rasterizer.py                       # full table
    python tools/bench_rasterizer.py --quick               # small, fast
    python tools/bench_rasterizer.py --backends cpu --threads 2 --json bench_out/raster.json
    python tools/bench_rasterizer.py --backends cuda,cpu --sizes 300000 --resolutions 800  # GPU
    python tools/bench_rasterizer.py --checkouts ../old,. --sizes 300000,1000000 \
        --resolutions 200,800 --thread-counts 1,2 --repeats 7 --modes fwd,fwd+pose-only
"""
from __future__ import annotations

import argparse
import hashlib
import json
import statistics
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Dict, List, Optional, Tuple

import torch

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

if TYPE_CHECKING:
    from tools._common import CheckoutWorker

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


# ----------------------------------------------------------------------------------------------
# --checkouts: the native CPU kernels of several checkouts in one run, one worker process each,
# the calls interleaved.
# ----------------------------------------------------------------------------------------------
def _digest(fn: Callable, scene: Dict[str, object]) -> Dict[str, object]:
    """Hashes of the forward images and of the pose-only camera gradient of one call."""
    tensors = {k: v for k, v in scene.items() if k != "settings"}
    for k in POSE_INPUTS:
        tensors[k] = tensors[k].detach().clone().requires_grad_(True)
    color, radii, invdepth, depth_acc, alpha = fn(**tensors, **scene["settings"])
    (color.square().sum() + invdepth.sum()).backward()

    def sha(*ts: torch.Tensor) -> str:
        data = b"".join(t.detach().contiguous().numpy().tobytes() for t in ts)
        return hashlib.sha256(data).hexdigest()[:16]

    grads = [tensors[k].grad for k in POSE_INPUTS]
    from gaussian_renderer_pose import _ops

    settings = scene["settings"]
    with torch.no_grad():
        state = _ops.rasterize_forward(
            *(tensors[k].detach() if tensors[k] is not None else None for k in (
                "means3D", "opacities", "shs", "colors_precomp", "scales", "rotations",
                "cov3D_precomp", "bg", "viewmatrix", "projmatrix", "campos")),
            settings["image_height"], settings["image_width"], settings["tanfovx"],
            settings["tanfovy"], settings["scale_modifier"], settings["sh_degree"],
            settings["prefiltered"], settings["antialiasing"], None)[4:]
    return {"images": sha(color, invdepth, depth_acc, alpha, radii), "camera_grad": sha(*grads),
            "state": sha(*state),
            "color_sum": float(color.detach().double().sum()),
            "camera_grad_values": [float(v) for g in grads for v in g.flatten()]}


def worker_loop(root: Path) -> int:
    """Serve requests (JSON lines on stdin, replies on stdout) with the CPU kernel of ``root``.

    Requests: ``{"cmd": "scene", "gaussians", "resolution", "seed"}``, ``{"cmd": "time", "mode",
    "threads"}`` -> ``{"ms", "cpu_ms"}`` (wall and process CPU time of one call), ``{"cmd":
    "digest"}`` -> :func:`_digest`, ``{"cmd": "quit"}``.
    """
    sys.path.insert(0, str(root))
    import gaussian_renderer_pose
    from gaussian_renderer_pose._native import rasterize_gaussians_native
    try:  # the checkout compared may predate the app package
        from icomma_plugin.app.demo_scene import raster_bench_scene
    except ImportError:
        from icomma_plugin.demo_scene import raster_bench_scene

    where = Path(gaussian_renderer_pose.__file__).resolve().parent
    print(json.dumps({"package": str(where)}), flush=True)
    scene = None
    for line in sys.stdin:
        req = json.loads(line)
        if req["cmd"] == "quit":
            break
        if req["cmd"] == "scene":
            scene = raster_bench_scene(req["gaussians"], req["resolution"], seed=req["seed"])
            reply: Dict[str, object] = {}
        elif req["cmd"] == "time":
            torch.set_num_threads(req["threads"])
            cpu0 = time.process_time()
            ms = run_once(rasterize_gaussians_native, scene, req["mode"])
            reply = {"ms": ms, "cpu_ms": (time.process_time() - cpu0) * 1e3}
        else:
            reply = _digest(rasterize_gaussians_native, scene)
        print(json.dumps(reply), flush=True)
    return 0


def _time_interleaved(workers: List["CheckoutWorker"], modes: List[str], threads: int,
                      repeats: int) -> Dict[Tuple[int, str], Tuple[float, float]]:
    """(worker index, mode) -> median (wall ms, CPU ms) over ``repeats`` rounds after a warm-up.

    Each round calls every worker once per mode, the workers' order reversed every other round.
    """
    for w in workers:
        for mode in modes:
            w.ask(cmd="time", mode=mode, threads=threads)
    samples: Dict[Tuple[int, str], List[Tuple[float, float]]] = {
        (i, m): [] for i in range(len(workers)) for m in modes}
    for rnd in range(repeats):
        order = list(range(len(workers)))
        if rnd % 2:
            order.reverse()
        for mode in modes:
            for i in order:
                r = workers[i].ask(cmd="time", mode=mode, threads=threads)
                samples[(i, mode)].append((r["ms"], r["cpu_ms"]))
    return {key: (statistics.median(v[0] for v in vals), statistics.median(v[1] for v in vals))
            for key, vals in samples.items()}


def compare_checkouts(roots: List[Path], scenes: List[Tuple[int, int]], thread_counts: List[int],
                      modes: List[str], repeats: int, seed: int) -> List[Dict[str, object]]:
    """Time the CPU kernels of ``roots`` interleaved; prints a markdown table, returns its rows."""
    # imported here: a worker runs with the compared checkout's packages first on its path
    from tools._common import CheckoutWorker

    workers = [CheckoutWorker(r, Path(__file__), "--checkouts") for r in roots]
    rows: List[Dict[str, object]] = []
    try:
        for P, R in scenes:
            for w in workers:
                w.ask(cmd="scene", gaussians=P, resolution=R, seed=seed)
            digests = [w.ask(cmd="digest") for w in workers]
            for threads in thread_counts:
                log(f"[{P} x {R}^2, {threads} threads] {', '.join(modes)} ...")
                med = _time_interleaved(workers, modes, threads, repeats)
                for mode in modes:
                    rows.append({
                        "gaussians": P, "resolution": R, "threads": threads, "mode": mode,
                        "ms": [med[(i, mode)][0] for i in range(len(workers))],
                        "cpu_ms": [med[(i, mode)][1] for i in range(len(workers))],
                        "same_images": [d["images"] == digests[0]["images"] for d in digests],
                        "same_camera_grad": [d["camera_grad"] == digests[0]["camera_grad"]
                                             for d in digests],
                        "same_state": [d["state"] == digests[0]["state"] for d in digests],
                        "digests": digests,
                    })
    finally:
        for w in workers:
            w.close()
    _print_comparison([w.name for w in workers], rows, repeats)
    return rows


def _print_comparison(names: List[str], rows: List[Dict[str, object]], repeats: int) -> None:
    """The markdown table of :func:`compare_checkouts`."""
    print(f"median of {repeats} interleaved calls after a warm-up; ns/G = wall ns per Gaussian; "
          f"ratios: {names[0]} / other; 'same': images / pose-only camera gradient / saved "
          f"forward state (geom, binning, ...) bits equal to {names[0]}'s")
    header = ["Gaussians", "image", "threads", "mode"]
    for n in names:
        header += [f"{n} ms", f"{n} ns/G", f"{n} CPU ms"]
    for n in names[1:]:
        header += [f"wall ratio {n}", f"CPU ratio {n}", f"same {n}"]
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for r in rows:
        P = r["gaussians"]
        cells = [f"{P:,}", f"{r['resolution']}x{r['resolution']}", str(r["threads"]), r["mode"]]
        for ms, cpu in zip(r["ms"], r["cpu_ms"]):
            cells += [f"{ms:.1f}", f"{ms * 1e6 / P:.0f}", f"{cpu:.1f}"]
        for i in range(1, len(names)):
            same = " / ".join("yes" if r[k][i] else "NO"
                              for k in ("same_images", "same_camera_grad", "same_state"))
            cells += [f"{r['ms'][0] / r['ms'][i]:.2f}x", f"{r['cpu_ms'][0] / r['cpu_ms'][i]:.2f}x",
                      same]
        print("| " + " | ".join(cells) + " |")


def _run_comparison(args: argparse.Namespace) -> int:
    """The ``--checkouts`` mode of :func:`main`."""
    roots = [Path(p).resolve() for p in args.checkouts.split(",") if p.strip()]
    for r in roots:
        if not (r / "gaussian_renderer_pose").is_dir():
            raise SystemExit(f"--checkouts: {r} is not a checkout of this repository")
    modes = [m.strip() for m in args.modes.split(",") if m.strip()]
    bad = [m for m in modes if m not in MODES]
    if bad:
        raise SystemExit(f"--modes: unknown {bad}; known: {', '.join(MODES)}")
    default_threads = str(args.threads or torch.get_num_threads())
    thread_counts = [int(t) for t in (args.thread_counts or default_threads).split(",") if t]
    scenes = [(int(p), int(r)) for p in args.sizes.split(",") if p
              for r in args.resolutions.split(",") if r]
    rows = compare_checkouts(roots, scenes, thread_counts, modes, args.repeats, args.seed)
    if args.json is not None:
        write_json_atomic(args.json, {"checkouts": [str(r) for r in roots],
                                      "repeats": args.repeats, "results": rows})
        log(f"wrote {args.json}")
    return 0


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
    ap.add_argument("--checkouts", default=None,
                    help="comma list of repository roots (each built in place): compare their "
                         "native CPU kernels, interleaved, in one run (first = the baseline)")
    ap.add_argument("--thread-counts", default=None,
                    help="with --checkouts: comma list of thread counts (default: --threads, "
                         "else torch's)")
    ap.add_argument("--modes", default=",".join(MODES),
                    help=f"with --checkouts: comma list of modes out of {', '.join(MODES)}")
    ap.add_argument("--worker", type=Path, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker is not None:
        return worker_loop(args.worker.resolve())
    if args.checkouts is not None:
        return _run_comparison(args)

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
