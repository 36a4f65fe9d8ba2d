"""Time whole localizations: wall time per pose and where it goes.

For the default method (``RobustConfig``) and the paper's (``LocalizerConfig``), on lego and the
built-in demo scene.

For each scene x method it runs localizations from sampled starts and reports medians of the
wall time, the process CPU time and the breakdown of ``LocalizationResult.stage_seconds``
(render, backward, matcher, pnp, verify, candidates, other, total), the final errors and the
success rate (< 5 deg and < 0.05 world units, the time table's), plus the paper/default time
ratio of the same run. It prints the thread count and the load average before and after each
block (the machine may be shared: compare ratios measured in the same run, not absolute times
of different runs).

Scenes: ``lego200``: the fitted model (``--model``, default ~/.cache/icomma/scenes/lego_200,
fitted at 200x200 from lego_400) with its test views at 200x200; ``lego400``: the SAME model
with the test views and intrinsics at full size (400x400 photos; the model was fitted at 200, and
both methods work at no more than the model's training resolution, as ``tools/localize.py``
does, so this times 400 px photos against a 200 px model, not a 400 px fit); ``demo``: the
built-in demo scene
(icomma_plugin/demo_scene.py) and its query.

Starts: as the benchmark (``icomma_plugin.benchmark.sampling.sample_initial_pose``: rotation
about the world origin by an angle uniform in ``--rot`` about a random axis, translation
+-``--trans`` per axis, world units), from seeds ``(--seed, 0, query index, pose index)``; the
default seed (1010) is held out from the benchmark's (0). Start k uses query ``k mod --queries``.
The paper's method runs the first ``--paper-starts`` starts (it costs ~35 s a start at 200 px),
so the ratio is also given paired over those starts.

Every start goes through the scene's ``Localizer`` (built once per scene and method, its
candidate index built before the timings). ``--render-repeats`` adds a per-render table (forward,
forward + pose backward) of a render as the localizer makes it and of the backend function alone
at a test pose (CPU ms).

Large models (issue 19): ``--model ~/.cache/icomma/large/lego_300k --scenes lego400
--query-scale 2 --work-side 800`` localizes 800 px queries at 800 px; ``--lod off|auto|N`` sets the
Localizer's level of detail (``N``: a ``LodConfig`` capped at N Gaussians); its reduced models are
built before the timings (``blocks/<scene>/lod_build_s``) and each record says which model served
which stage (``lod_stages``).

Examples:
    python tools/bench_localize.py --threads 1                              # everything
    python tools/bench_localize.py --quick --scenes demo --threads 1        # a quick look
    python tools/bench_localize.py --scenes lego200 --methods robust --threads 1
"""

from __future__ import annotations

import argparse
import collections
import datetime
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

if __package__:
    from ._common import apply_overrides, parse_overrides, thread_env, torch_threads  # noqa: E402
else:  # run as a script from a checkout
    from tools._common import apply_overrides, parse_overrides, thread_env, torch_threads  # noqa: E402

SCENES = ("lego200", "lego400", "demo")
METHODS = ("robust", "icomma")
STAGES = ("render", "backward", "matcher", "pnp", "verify", "candidates", "other", "total")
SUCCESS = (5.0, 0.05)  # deg, world units (the time table's threshold)
DEFAULT_MODEL = "~/.cache/icomma/scenes/lego_200"


def log(msg: str) -> None:
    """Progress line to stderr (stdout carries the results)."""
    print(msg, file=sys.stderr, flush=True)


def _pair(text: str, name: str) -> Tuple[float, float]:
    try:
        lo, hi = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{name} must be 'lo,hi' (two numbers), got {text!r}"
        ) from None
    if not (0 <= lo <= hi):
        raise argparse.ArgumentTypeError(f"{name} must satisfy 0 <= lo <= hi, got {text!r}")
    return lo, hi


def _names(text: str, known: Sequence[str], name: str) -> List[str]:
    out = [s.strip() for s in text.split(",") if s.strip()]
    bad = [s for s in out if s not in known]
    if bad or not out:
        raise argparse.ArgumentTypeError(
            f"{name} must be a comma list of {', '.join(known)}, got {text!r}"
        )
    return out


# ----------------------------------------------------------------------------------------------
# Machine
# ----------------------------------------------------------------------------------------------
def load_average() -> Optional[List[float]]:
    """The 1, 5 and 15 minute load averages (2 decimals); None where the OS has none."""
    try:
        return [round(v, 2) for v in os.getloadavg()]
    except OSError:
        return None


def load1() -> str:
    """The 1-minute load average as text ("?" where unknown)."""
    la = load_average()
    return "?" if la is None else f"{la[0]:.2f}"


def machine_info() -> Dict[str, Any]:
    """What the timings depend on: CPU model, cores, torch version and threads, git commit."""
    cpu = platform.processor() or None
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        commit = (
            subprocess.run(
                ["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"],
                capture_output=True,
                text=True,
                timeout=10,
            ).stdout.strip()
            or None
        )
    except (OSError, subprocess.SubprocessError):
        commit = None
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return {
        "cpu": cpu,
        "cores": cores,
        "torch_threads": torch.get_num_threads(),
        "thread_env": thread_env(),  # OMP_WAIT_POLICY=PASSIVE: 1.3-1.9x a lego pose
        "torch": torch.__version__,
        "python": platform.python_version(),
        "commit": commit,
    }


# ----------------------------------------------------------------------------------------------
# Scenes
# ----------------------------------------------------------------------------------------------
def load_scene(name: str, args) -> "Any":
    """A ``BenchScene`` for ``name`` (lego200, lego400 or demo)."""
    from icomma_plugin.benchmark.scene import BenchQuery, BenchScene, load_model_folder_scene

    if name in ("lego200", "lego400"):
        model = Path(args.model).expanduser()
        if not model.is_dir():
            raise FileNotFoundError(
                f"--model: model folder not found: {model} (fit one with tools/fit_scene.py)"
            )
        scale = None if name == "lego200" else 1.0  # None: the model's training scale (200 px)
        if args.query_scale is not None:
            scale = args.query_scale
        sc = load_model_folder_scene(
            model, dataset=args.dataset, num_queries=args.queries, image_scale=scale
        )
        want = 200 if name == "lego200" else 400
        want = want if args.query_scale is None else round(400 * args.query_scale)
        got = sc.queries[0].query.intrinsics.width
        if got != want:
            log(f"note: {name}: the queries are {got} px wide (dataset {sc.info['dataset']})")
        return sc
    from icomma_plugin.app.problem import load_problem

    p = load_problem(
        {"kind": "demo", "path": args.demo_path, "width": args.demo_size, "height": args.demo_size}
    )
    q = BenchQuery(p.query, np.asarray(p.gt_c2w, np.float64), 0)
    return BenchScene(
        model=p.model,
        queries=[q],
        bg=p.bg,
        translation_scale=1.0,
        translation_unit="world",
        scene_radius=float(p.scene_scale or 1.0),
        cameras_c2w=[e.c2w for e in p.cameras],
        info={"kind": "demo", **p.info},
    )


@dataclass
class Start:
    """One sampled start: the query, its seed and the initial pose (and how far it is off)."""

    index: int
    query: Any
    pose_index: int
    seed: Tuple[int, ...]
    init_c2w: np.ndarray
    rot_deg: float
    trans_world: float


def sample_starts(
    scene, n: int, seed: int, rot: Tuple[float, float], trans: Tuple[float, float]
) -> List[Start]:
    """``n`` starts, cycling over the scene's queries (module docstring: "Starts")."""
    from icomma_plugin.benchmark.sampling import pose_seed, sample_initial_pose

    out = []
    nq = len(scene.queries)
    for k in range(n):
        q = scene.queries[k % nq]
        s = pose_seed(seed, 0, q.index, k // nq)
        init = sample_initial_pose(
            q.gt_c2w,
            rot,
            trans,
            s,
            translation_scale=scene.translation_scale,
            translation_mode="per_axis",
            pivot="origin",
        )
        out.append(
            Start(
                k,
                q,
                k // nq,
                s,
                init.c2w,
                float(init.rot_deg),
                float(np.linalg.norm(init.c2w[:3, 3] - q.gt_c2w[:3, 3])),
            )
        )
    return out


# ----------------------------------------------------------------------------------------------
# One localization
# ----------------------------------------------------------------------------------------------
def method_config(method: str, args):
    """The config of ``method``: the default ``RobustConfig`` or the paper's."""
    from icomma_plugin.localize import LocalizerConfig, RobustConfig

    if method == "robust":
        return RobustConfig.from_dict(apply_overrides(
            RobustConfig(work_side=args.work_side).to_dict(), args.set or [],
            "the default method's config"))
    return LocalizerConfig(max_iterations=args.paper_max_iterations)


def run_start(scene, st: Start, method: str, cfg, matcher, args) -> Dict[str, Any]:
    """Localize from one start with ``method`` (its config ``cfg``) through the scene's Localizer.

    Returns:
        The record of the run: wall and CPU time, stage seconds, final errors, success and
        verdict (or the error it raised).
    """
    q = st.query
    localizer = scene.localizer(matcher, cfg, args.backend, cache_dir=False, lod=lod_arg(args))
    torch.manual_seed(int(np.random.SeedSequence(list(st.seed)).generate_state(1)[0]))
    rec: Dict[str, Any] = {
        "start": st.index,
        "name": q.name,
        "query_index": q.index,
        "pose_index": st.pose_index,
        "seed": list(st.seed),
        "init_rot_err_deg": st.rot_deg,
        "init_trans_err": st.trans_world,
        "method": method,
    }
    c0, t0 = time.process_time(), time.perf_counter()
    try:
        res = localizer.localize(q.query.fresh(), st.init_c2w, q.gt_c2w)  # timed as a first
    except Exception as e:  # a run that raises is a failed run (recorded), not the end of all
        log(f"start {st.index} ({method}) raised {type(e).__name__}: {e}")
        rec.update(error=f"{type(e).__name__}: {e}", success=False, status=None,
                   rot_err_deg=None, trans_err=None, iterations=None,
                   wall_s=time.perf_counter() - t0, cpu_s=time.process_time() - c0)
        return rec
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    rot, trans = res.rot_err_deg, res.trans_err
    return {
        **rec,
        "error": None,
        "wall_s": wall,
        "cpu_s": cpu,
        "stage_seconds": {k: float(res.stage_seconds.get(k, 0.0)) for k in STAGES},
        "stage_cpu_seconds": {k: float(res.stage_cpu_seconds.get(k, 0.0)) for k in STAGES},
        "iterations": res.iterations,
        "stop_reason": res.stop_reason,
        "status": res.verdict.status,
        "rot_err_deg": rot,
        "trans_err": trans,
        "success": bool(
            rot is not None and trans is not None and rot < SUCCESS[0] and trans < SUCCESS[1]
        ),
        "c2w": res.c2w.tolist(),
        "lod_stages": (res.details.get("lod") or {}).get("stages"),
        "verified_on": res.details.get("verified_on"),
        "trace_stages": trace_stages(res.trace),
    }


def profile_start(scene, st: Start, cfg, matcher, args, path: Path, rows: int = 40) -> None:
    """Localize from ``st`` under ``torch.profiler``; write its operator tables to ``path``.

    Sorted by self CPU time, and by self device time when the model is on a GPU (there a
    matcher of many small operations is bound by their launches: docs/GPU.md).
    """
    from torch.profiler import ProfilerActivity, profile

    localizer = scene.localizer(matcher, cfg, args.backend, cache_dir=False, lod=lod_arg(args))
    gpu = localizer.model.means.device.type == "cuda"
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if gpu else [])
    q = st.query
    with profile(activities=activities) as prof:
        res = localizer.localize(q.query.fresh(), st.init_c2w, q.gt_c2w)
    averages = prof.key_averages()
    ops = sum(e.count for e in averages if e.key.startswith("aten::"))
    text = [f"start {st.index}: {res.rot_err_deg:.4f} deg, {res.verdict.status}, "
            f"stages {json.dumps({k: round(v, 3) for k, v in res.stage_seconds.items()})}",
            f"aten operator calls: {ops}", "", "by self CPU time:",
            averages.table(sort_by="self_cpu_time_total", row_limit=rows)]
    if gpu:
        text += ["", "by self device time:",
                 averages.table(sort_by="self_device_time_total", row_limit=rows)]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(text) + "\n")


def trace_stages(trace) -> Dict[str, int]:
    """How many trace records each stage made (geometric rounds, refinement steps, ...)."""
    return dict(collections.Counter(r["stage_name"] for r in trace or []))


def lod_arg(args):
    """The Localizer's ``lod`` of ``--lod``: "off", "auto" or a LodConfig capped at N."""
    from icomma_plugin.lod import LodConfig

    text = str(args.lod).lower()
    return text if text in ("off", "auto") else LodConfig(max_gaussians=int(text))


def _lod_choice(text: str) -> str:
    if text.lower() in ("off", "auto") or (text.isdigit() and int(text) > 0):
        return text.lower()
    raise argparse.ArgumentTypeError(f"--lod must be off, auto or a positive int, got {text!r}")


# ----------------------------------------------------------------------------------------------
# Per-render timings (the two render paths at one pose)
# ----------------------------------------------------------------------------------------------
def render_timings(scene, repeats: int, backend: str) -> Dict[str, Any]:
    """Median CPU ms of a render at the first query's true pose.

    Forward (no grad) and forward + pose backward, as ``LocalizationState`` calls them on the
    prepared scene (``prepared``), and for the backend function alone on the same tensors
    (``kernel``: no camera matrices, no checks; the rest of a render's time is the Python around
    it).
    """
    import gaussian_renderer_pose as grp
    from gaussian_renderer_pose import _dispatch

    from icomma_plugin.localization.state import LocalizationState
    from icomma_plugin.pose.convert import invert_rigid
    from icomma_plugin.pose.se3 import se3_exp
    from icomma_plugin.render import prepare_scene

    q = scene.queries[0].query
    state = LocalizationState(scene.model, q, scene.bg, backend=backend)
    w2c = torch.as_tensor(invert_rigid(scene.queries[0].gt_c2w), dtype=torch.float64)
    out: Dict[str, Any] = {
        "gaussians": state.model.num_gaussians,
        "sh_degree": state.model.sh_degree,
        "image": [q.intrinsics.width, q.intrinsics.height],
    }
    ps = prepare_scene(state.model)
    intr, dt = q.intrinsics, ps.dtype
    mats = grp.camera_matrices(
        w2c.to(dt), intr.fx, intr.fy, intr.width, intr.height, intr.cx, intr.cy
    )
    kernel = _dispatch.select_backend(backend, ps.device, dt)
    settings = dict(
        image_height=intr.height,
        image_width=intr.width,
        tanfovx=mats.tanfovx,
        tanfovy=mats.tanfovy,
        scale_modifier=1.0,
        sh_degree=ps.sh_degree,
        prefiltered=False,
        antialiasing=False,
    )

    def kernel_call(grad: bool):
        cam = [
            t.detach().contiguous().requires_grad_(grad)
            for t in (mats.viewmatrix, mats.projmatrix, mats.campos)
        ]
        color = kernel(
            ps.means,
            None,
            ps.opacities,
            ps.shs,
            ps.colors,
            ps.scales,
            ps.rotations,
            None,
            state.bg,
            *cam,
            **settings,
        )[0]
        if grad:
            color.square().sum().backward()

    def fwd():
        with torch.no_grad():
            state.render(w2c)

    def fwd_bwd():
        xi = torch.zeros(6, dtype=torch.float64, requires_grad=True)
        o = state.render(se3_exp(xi) @ w2c)
        o.color.square().sum().backward()

    def kernel_fwd():
        with torch.no_grad():
            kernel_call(False)

    calls = {"fwd": fwd, "fwd+bwd": fwd_bwd}
    for path in ("prepared", "kernel", "prepared", "kernel"):  # interleaved
        for mode, fn in calls.items():
            if path == "kernel":
                fn = kernel_fwd if mode == "fwd" else (lambda: kernel_call(True))
            fn()  # warm-up (and the prepared scene's one-off preparation)
            ts = []
            for _ in range(repeats):
                c = time.process_time()
                fn()
                ts.append((time.process_time() - c) * 1e3)
            out.setdefault(f"{path}/{mode}", []).extend(ts)
    for k in [k for k in out if "/" in k]:
        out[k] = statistics.median(out[k])
    return out


# ----------------------------------------------------------------------------------------------
# Summary and report
# ----------------------------------------------------------------------------------------------
def _median(vals) -> Optional[float]:
    vals = [float(v) for v in vals if v is not None]
    return statistics.median(vals) if vals else None


def summarize(records: List[Dict[str, Any]]) -> List[Dict[str, Any]]:
    """One row per scene x method: medians of the finished runs, rates of all."""
    rows = []
    keys = sorted({(r["scene"], r["method"]) for r in records},
                  key=lambda k: (SCENES.index(k[0]), METHODS.index(k[1])))
    for scene, method in keys:
        every = [r for r in records if (r["scene"], r["method"]) == (scene, method)]
        rs = [r for r in every if not r.get("error")]  # timings: the runs that finished
        rows.append(
            {
                "scene": scene,
                "method": method,
                "n": len(every),
                "errors": len(every) - len(rs),
                "wall_s": _median(r["wall_s"] for r in rs),
                "cpu_s": _median(r["cpu_s"] for r in rs),
                "stages": {k: _median(r["stage_seconds"][k] for r in rs) for k in STAGES},
                "stages_cpu": {k: _median(r["stage_cpu_seconds"][k] for r in rs) for k in STAGES},
                "rot_err_deg": _median(r["rot_err_deg"] for r in rs),
                "trans_err": _median(r["trans_err"] for r in rs),
                "success": sum(r["success"] for r in every) / len(every),
                "ok": sum(r["status"] == "ok" for r in every) / len(every),
                "iterations": _median(r["iterations"] for r in rs),
            }
        )
    return rows


def _paired(records, scene, method_a, method_b, field="wall_s") -> Tuple[Optional[float], int]:
    """Median over the starts run by both methods of a / b, and how many."""
    def of(method):
        return {r["start"]: r[field] for r in records
                if (r["scene"], r["method"]) == (scene, method) and not r.get("error")}

    a, b = of(method_a), of(method_b)
    common = sorted(set(a) & set(b))
    return (_median(a[k] / b[k] for k in common if b[k] > 0), len(common))


def _ratio(a: Optional[float], b: Optional[float]) -> Optional[float]:
    return None if a is None or not b else a / b


def ratios(records: List[Dict[str, Any]], rows: List[Dict[str, Any]]) -> List[Dict[str, Any]]:
    """paper / default per scene (same run, paired over the same starts)."""
    out = []
    by = {(r["scene"], r["method"]): r for r in rows}
    for scene in SCENES:
        a, b = by.get((scene, "icomma")), by.get((scene, "robust"))
        if a and b:
            pr, n = _paired(records, scene, "icomma", "robust")
            pc, _ = _paired(records, scene, "icomma", "robust", "cpu_s")
            out.append({"scene": scene, "what": "paper / default",
                        "of_medians": _ratio(a["wall_s"], b["wall_s"]), "paired_median": pr,
                        "paired_n": n, "paired_cpu_median": pc})
    return out


# ----------------------------------------------------------------------------------------------
# Against other code (--compare-with)
# ----------------------------------------------------------------------------------------------
#: Options a reference run does not take: its own output, no nested reference, --quick (already
#: folded into --starts), per-render timings (not compared), and --set (the config under test).
_NOT_FORWARDED = ("help", "out", "compare_with", "quick", "render_repeats", "set", "matcher_set",
                  "profile")
#: Options always passed; the others only when they differ from their default, so that a
#: reference checkout older than an option still runs when the option is not used.
_ALWAYS_FORWARDED = ("scenes", "methods", "starts", "paper_starts", "seed", "queries", "model",
                     "matcher", "backend", "paper_max_iterations", "threads", "rot", "trans")


def reference_command(args, script: Path, out: Path) -> List[str]:
    """The command line of the reference run.

    Every option of this run that shapes the starts, the scenes and the method (all but
    ``_NOT_FORWARDED``).
    """
    cmd = [sys.executable, str(script), "--out", str(out)]
    for action in build_parser()._actions:
        name = action.dest
        if not action.option_strings or name in _NOT_FORWARDED:
            continue
        value = getattr(args, name)
        if value is None or (name not in _ALWAYS_FORWARDED and value == action.default):
            continue
        text = ",".join(map(str, value)) if isinstance(value, (list, tuple)) else str(value)
        cmd += [action.option_strings[0], text]
    return cmd


def run_reference(args, out: Path) -> Dict[str, Any]:
    """Run ``args.compare_with``'s bench_localize on the same starts; its results.json.

    In a subprocess with that checkout first on the path (its own native build), before this
    code's run, on the same machine.
    """
    ref = Path(args.compare_with).expanduser().resolve()
    script = ref / "tools" / "bench_localize.py"
    if not script.is_file():
        raise FileNotFoundError(f"--compare-with: no tools/bench_localize.py in {ref}")
    cmd = reference_command(args, script, out)
    env = dict(os.environ, PYTHONPATH=str(ref))
    log(f"reference run: {' '.join(cmd)} (PYTHONPATH={ref})")
    t = time.perf_counter()
    subprocess.run(cmd, cwd=str(ref), env=env, check=True, stdout=subprocess.DEVNULL)
    doc = json.loads((out / "results.json").read_text())
    doc["path"], doc["seconds"] = str(ref), time.perf_counter() - t
    return doc


def _reference_c2w(rec: Dict[str, Any]) -> Optional[np.ndarray]:
    """A reference record's estimate as c2w (older versions recorded w2c)."""
    from icomma_plugin.pose.convert import invert_rigid

    if rec.get("c2w") is not None:
        return np.asarray(rec["c2w"], np.float64)
    if rec.get("w2c") is not None:
        return invert_rigid(np.asarray(rec["w2c"], np.float64))
    return None


def versus_reference(records, reference) -> List[Dict[str, Any]]:
    """Per scene x method: this code / the reference, paired by start, and pose differences."""
    out = []
    ref = {(r["scene"], r["method"], r["start"]): r for r in reference
           if not r.get("error") and r.get("render_path", "prepared") == "prepared"}
    keys = sorted({(r["scene"], r["method"]) for r in records})
    for scene, method in keys:
        pairs = [(r, ref[(scene, method, r["start"])]) for r in records
                 if (r["scene"], r["method"]) == (scene, method) and not r.get("error")
                 and (scene, method, r["start"]) in ref]
        if not pairs:
            continue
        diffs = [float(np.abs(np.asarray(a["c2w"]) - _reference_c2w(b)).max()) for a, b in pairs]
        same_verdict = sum(a["status"] == b.get("status", b.get("verdict")) for a, b in pairs)
        out.append({
            "scene": scene, "method": method, "n": len(pairs),
            "wall": _median(a["wall_s"] / b["wall_s"] for a, b in pairs if b["wall_s"] > 0),
            "cpu": _median(a["cpu_s"] / b["cpu_s"] for a, b in pairs if b["cpu_s"] > 0),
            "max_pose_diff": max(diffs), "identical_poses": sum(d == 0.0 for d in diffs),
            "same_verdict": same_verdict,
            "reference_wall_s": _median(b["wall_s"] for _, b in pairs),
            "wall_s": _median(a["wall_s"] for a, _ in pairs),
        })
    return out


def _f(v, digits=2, unit="") -> str:
    return "—" if v is None else f"{v:.{digits}f}{unit}"


def _x(v: Optional[float]) -> str:
    return "—" if v is None else f"{v:.2f}x"


def _load(la) -> str:
    return "?" if not la else f"{la[0]:.2f}"


def markdown(result: Dict[str, Any]) -> str:
    """The result as markdown: machine line, per-run table, ratios and per-render timings."""
    m, a = result["machine"], result["args"]
    header = [
        "scene",
        "method",
        "n",
        "wall s",
        "CPU s",
        "errors",
        "final rot deg",
        "final trans",
        "success",
        "verdict ok",
        "iterations",
        "load before -> after",
    ]
    lines = [
        f"threads: {m['torch_threads']} (cores: {m['cores']}, {m['cpu']}), torch {m['torch']}, "
        f"commit {m['commit']}"
        + "".join(f", {k}={v}" for k, v in (m.get("thread_env") or {}).items())
        + f"; load average (1, 5, 15 min) before: {result['load_before']}, after: "
        f"{result['load_after']}",
        f"starts: rotation {a['rot']} deg about the origin, translation +-{a['trans']} per axis, "
        f"seed {a['seed']}; medians over n starts; success = < {SUCCESS[0]:g} deg and "
        f"< {SUCCESS[1]:g}",
        "",
        "| " + " | ".join(header) + " |",
        "|" + "---|" * len(header),
    ]

    def name(r):
        return "default (robust)" if r["method"] == "robust" else "paper (icomma)"

    for r in result["rows"]:
        blk = result["blocks"].get(f"{r['scene']}/{r['method']}", {})
        lines.append(
            "| "
            + " | ".join(
                [
                    r["scene"],
                    name(r),
                    str(r["n"]),
                    _f(r["wall_s"]),
                    _f(r["cpu_s"]),
                    str(r.get("errors", 0)),
                    _f(r["rot_err_deg"], 3),
                    _f(r["trans_err"], 4),
                    f"{100 * r['success']:.0f} %",
                    f"{100 * r['ok']:.0f} %",
                    _f(r["iterations"], 0),
                    f"{_load(blk.get('load_before'))} -> {_load(blk.get('load_after'))}",
                ]
            )
            + " |"
        )
    for key, title in (("stages_cpu", "CPU"), ("stages", "wall")):
        lines += [
            "",
            f"Breakdown by stage ({title} seconds, medians):",
            "",
            "| scene | method | " + " | ".join(STAGES) + " |",
            "|" + "---|" * (2 + len(STAGES)),
        ]
        for r in result["rows"]:
            lines.append(
                "| "
                + " | ".join(
                    [r["scene"], name(r), *[_f(r[key][k]) for k in STAGES]]
                )
                + " |"
            )
    if result["ratios"]:
        lines += [
            "",
            "| scene | ratio | of the medians (wall) | median of paired ratios (wall) | "
            "paired CPU | starts paired |",
            "|---|---|---|---|---|---|",
        ]
        for q in result["ratios"]:
            lines.append(
                "| "
                + " | ".join(
                    [
                        q["scene"],
                        q["what"],
                        _x(q["of_medians"]),
                        _x(q["paired_median"]),
                        _x(q.get("paired_cpu_median")),
                        str(q["paired_n"]),
                    ]
                )
                + " |"
            )
    if result.get("versus_reference"):
        lines += [
            "",
            f"Against {result['reference']['path']} (commit "
            f"{result['reference']['machine'].get('commit')}), the same starts run first by its "
            "own bench_localize:",
            "",
            "| scene | method | starts | wall s (ref -> this) | wall ratio (paired median) | "
            "CPU ratio | bit-identical poses | max pose difference | same verdict |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for v in result["versus_reference"]:
            lines.append(
                f"| {v['scene']} | {v['method']} | {v['n']} | {_f(v['reference_wall_s'])} -> "
                f"{_f(v['wall_s'])} | {_x(v['wall'])} | {_x(v['cpu'])} | "
                f"{v['identical_poses']}/{v['n']} | {v['max_pose_diff']:.1e} | "
                f"{v['same_verdict']}/{v['n']} |"
            )
    if result.get("render_timings"):
        lines += [
            "",
            "Per render at the first query's true pose (CPU ms, median), as LocalizationState "
            "calls it:",
            "",
            "| scene | Gaussians | SH degree | image | fwd | kernel fwd | fwd+bwd | "
            "kernel fwd+bwd |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for name, t in result["render_timings"].items():
            lines.append(
                "| "
                + " | ".join(
                    [
                        name,
                        f"{t['gaussians']:,}",
                        str(t["sh_degree"]),
                        f"{t['image'][0]}x{t['image'][1]}",
                        _f(t["prepared/fwd"], 1),
                        _f(t.get("kernel/fwd"), 1),
                        _f(t["prepared/fwd+bwd"], 1),
                        _f(t.get("kernel/fwd+bwd"), 1),
                    ]
                )
                + " |"
            )
    lines += [
        "",
        "Stage columns are medians, each on its own (medians need not add up to the total). "
        "Wall: `LocalizationResult.stage_seconds`; CPU: the process CPU time of the same timed "
        "blocks. A block nested in another counts as its own kind only (a render inside `verify` "
        "is render time). Timings and errors are over the runs that finished (`errors`: runs that "
        "raised, counted as failures in success and ok).",
    ]
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------------------------
# Main
# ----------------------------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    """The command line (module docstring)."""
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument(
        "--scenes",
        default="lego200,lego400,demo",
        type=lambda s: _names(s, SCENES, "--scenes"),
        help="comma list of lego200, lego400, demo",
    )
    ap.add_argument(
        "--methods",
        default="robust,icomma",
        type=lambda s: _names(s, METHODS, "--methods"),
        help="robust (the default, RobustConfig) and/or icomma (the paper's, LocalizerConfig)",
    )
    ap.add_argument(
        "--starts", type=int, default=20, help="starts per scene for the default method"
    )
    ap.add_argument(
        "--paper-starts",
        type=int,
        default=5,
        help="starts per scene for the paper's method (the first of the same starts; ~35 s each)",
    )
    ap.add_argument(
        "--quick", action="store_true", help="a quick look: 3 starts, 1 for the paper's method"
    )
    ap.add_argument(
        "--rot",
        type=lambda s: _pair(s, "--rot"),
        default=(20.0, 40.0),
        help="initial rotation error interval lo,hi [deg] (default 20,40)",
    )
    ap.add_argument(
        "--trans",
        type=lambda s: _pair(s, "--trans"),
        default=(0.0, 0.2),
        help="initial translation per axis lo,hi [world units] (default 0,0.2)",
    )
    ap.add_argument("--seed", type=int, default=1010, help="start seed (the benchmark uses 0)")
    ap.add_argument(
        "--queries", type=int, default=5, help="lego test views the starts cycle through"
    )
    ap.add_argument("--model", default=DEFAULT_MODEL, help="the lego model folder")
    ap.add_argument(
        "--dataset", default=None, help="lego dataset (default: the model's source_path)"
    )
    ap.add_argument(
        "--demo-path", default=None, help="demo scene folder (default ./outputs/demo_scene)"
    )
    ap.add_argument(
        "--demo-size", type=int, default=200, help="demo image side [px] (built if absent)"
    )
    ap.add_argument("--matcher", default="xfeat",
                    help="a built-in matcher name, with its class defaults (the tools' yamls)")
    ap.add_argument("--backend", default="auto")
    ap.add_argument("--paper-max-iterations", type=int, default=500)
    ap.add_argument(
        "--render-repeats",
        type=int,
        default=0,
        help="add per-render timings, this many repeats (0: none)",
    )
    ap.add_argument(
        "--threads",
        type=int,
        default=None,
        help="torch threads (default: automatic, the cores the load leaves free)",
    )
    ap.add_argument(
        "--lod",
        type=_lod_choice,
        default="auto",
        help="the Localizer's level of detail: off, auto (default) or N (a LodConfig capped at N "
        "Gaussians)",
    )
    ap.add_argument(
        "--work-side",
        type=int,
        default=None,
        help="the default method's working side [px] (default: the model's training side)",
    )
    ap.add_argument(
        "--set",
        action="append",
        metavar="KEY=VALUE",
        help="override the default method's config (RobustConfig), e.g. --set "
        "refine.hessian_scale=0.5 (repeatable; dotted keys, YAML values). Not passed to "
        "--compare-with: the reference runs its own defaults, so '--compare-with .' measures an "
        "override against the defaults on the same starts",
    )
    ap.add_argument(
        "--matcher-set",
        action="append",
        metavar="KEY=VALUE",
        help="a keyword argument of the matcher, e.g. --matcher-set max_keypoints=512 "
        "(repeatable; YAML values). Not passed to --compare-with, as --set",
    )
    ap.add_argument(
        "--query-scale",
        type=float,
        default=None,
        help="scale of the lego queries (default: lego200 the model's training scale, lego400 1)",
    )
    ap.add_argument(
        "--compare-with",
        type=Path,
        default=None,
        help="a checkout of other code (e.g. the last release, with its own native build): its "
        "bench_localize runs the same starts first, and the report gives paired time ratios and "
        "the largest pose difference",
    )
    ap.add_argument(
        "--out",
        type=Path,
        default=None,
        help="output folder for results.json / results.md (default outputs/bench_localize/<time>)",
    )
    ap.add_argument(
        "--profile",
        action="store_true",
        help="after the timed starts of each scene and method, localize the first start once more "
        "under torch.profiler (CUDA activities too when the model is on a GPU) and write the "
        "operator table, profile_<scene>_<method>.txt, into --out (not part of the timings)",
    )
    return ap


def main(argv: Optional[List[str]] = None) -> int:
    """Run the benchmark; write JSON and markdown. Returns the exit status."""
    args = build_parser().parse_args(argv)
    if args.quick:
        args.starts, args.paper_starts = min(args.starts, 3), min(args.paper_starts, 1)
    for name in ("starts", "paper_starts", "queries", "render_repeats"):
        if getattr(args, name) < (0 if name in ("paper_starts", "render_repeats") else 1):
            print(
                f"error: --{name.replace('_', '-')} must be a positive int, "
                f"got {getattr(args, name)}",
                file=sys.stderr,
            )
            return 2
    with torch_threads(args.threads):
        return _main(args)


def _main(args) -> int:
    from icomma_plugin.io.atomic import write_json_atomic, write_text_atomic
    from icomma_plugin.matchers import make_matcher

    out_dir = args.out or Path("outputs") / "bench_localize" / datetime.datetime.now().strftime(
        "%Y-%m-%d_%H-%M-%S"
    )
    args.out = out_dir  # where --profile writes too
    try:
        matcher = make_matcher(args.matcher, **dict(parse_overrides(args.matcher_set or [],
                                                                     "--matcher-set")))
    except (ValueError, TypeError) as e:  # an unknown or malformed argument: one line
        print(f"error: {'--matcher-set: ' if args.matcher_set else ''}{e}", file=sys.stderr)
        return 2
    result: Dict[str, Any] = {
        "machine": machine_info(),
        "load_before": load_average(),
        "records": [],
        "blocks": {},
        "render_timings": {},
        "args": {
            k: (list(v) if isinstance(v, tuple) else str(v) if isinstance(v, Path) else v)
            for k, v in vars(args).items() if k != "out"
        },
    }
    log(f"threads {torch.get_num_threads()}, load {result['load_before']}")

    def save():
        result["load_after"] = load_average()
        result["rows"] = summarize(result["records"])
        result["ratios"] = ratios(result["records"], result["rows"])
        if result.get("reference"):
            result["versus_reference"] = versus_reference(result["records"],
                                                          result["reference"]["records"])
        write_json_atomic(out_dir / "results.json", result)
        write_text_atomic(out_dir / "results.md", markdown(result))

    try:
        if args.compare_with is not None:
            result["reference"] = run_reference(args, out_dir / "reference")
        _run(args, result, matcher, save)
    except (ValueError, FileNotFoundError) as e:  # bad input: one line, no traceback
        print(f"error: {e}", file=sys.stderr)
        return 2
    finally:
        if result["records"] or result["render_timings"]:
            save()
            log(f"wrote {out_dir / 'results.json'} and results.md")
    print(markdown(result), end="")
    return 0


def _run(args, result: Dict[str, Any], matcher, save) -> None:
    """Run every scene x method x start of ``args`` into ``result["records"]``.

    ``save`` is called after each start.
    """
    for scene_name in args.scenes:
        t = time.perf_counter()
        scene = load_scene(scene_name, args)
        starts = sample_starts(scene, args.starts, args.seed, args.rot, args.trans)
        configs = {m: method_config(m, args) for m in args.methods}
        q0 = scene.queries[0].query
        if "robust" in args.methods:  # the candidate views: built once per scene, not timed
            tc = time.perf_counter()
            loc = scene.localizer(matcher, configs["robust"], args.backend, cache_dir=False,
                                  lod=lod_arg(args))
            loc.candidate_index(q0.intrinsics, configs["robust"].candidates)
            result["blocks"][f"{scene_name}/candidate_index_s"] = time.perf_counter() - tc
            if loc.reduced is not None:
                # the reduced models of the working resolution and of the refinement's levels (at
                # the model's side when the working side is larger: refine_model_side), not timed
                tc = time.perf_counter()
                eff = configs["robust"].at_model_side(q0.intrinsics, loc.model_side)
                scale = eff.work_scale(q0.intrinsics)
                for level in (1.0,) + eff.refine.scales:
                    loc.reduced.model_at(q0.intrinsics.scaled(scale * level))
                result["blocks"][f"{scene_name}/lod_build_s"] = time.perf_counter() - tc
                result["blocks"][f"{scene_name}/lod_models"] = [dict(e) for e in
                                                                loc.reduced.events]
        log(f"[{scene_name}] {scene.model.num_gaussians} Gaussians, {len(scene.queries)} queries "
            f"at {q0.intrinsics.width}x{q0.intrinsics.height} ({time.perf_counter() - t:.1f} s)")
        if args.render_repeats:
            result["render_timings"][scene_name] = render_timings(
                scene, args.render_repeats, args.backend
            )
        for method in args.methods:
            n = args.starts if method == "robust" else min(args.paper_starts, args.starts)
            block = {"load_before": load_average()}
            result["blocks"][f"{scene_name}/{method}"] = block
            for st in starts[:n]:
                rec = run_start(scene, st, method, configs[method], matcher, args)
                rec["scene"] = scene_name
                result["records"].append(rec)
                log(
                    f"[{scene_name}] {method:6s} start {st.index:2d} "
                    f"({st.rot_deg:4.1f} deg): {rec['wall_s']:6.2f} s, "
                    f"render {rec.get('stage_seconds', {}).get('render', 0.0):.2f} s, final "
                    f"{_f(rec['rot_err_deg'], 3)} deg, {rec['status']}, load {load1()}"
                )
                block["load_after"] = load_average()
                save()
            if args.profile and starts[:n]:
                path = args.out / f"profile_{scene_name}_{method}.txt"
                profile_start(scene, starts[0], configs[method], matcher, args, path)
                log(f"[{scene_name}] {method}: profile of start {starts[0].index} in {path}")


if __name__ == "__main__":
    raise SystemExit(main())
