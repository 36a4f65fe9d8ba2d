#!/usr/bin/env python
r"""Make an upstream-size model (300k, 1M Gaussians) from a fitted model folder, by splitting.

Every Gaussian is split into children sampled from its own Gaussian
(``icomma_plugin.lod.split_gaussians``) until ``--target`` Gaussians; as upstream's densification
is followed by more optimisation, the split model is then fitted for ``--distill-steps`` steps to
the original's renders from the model's cameras at ``--distill-side`` px
(``icomma_plugin.fit.distill``; the check cameras left out); the split model is rendered
beside the original from ``--check-cameras`` of the model's cameras at each ``--check-sides``
size, the PSNR of split vs original printed (after the fit, and by the rule alone), and the
folder written (upstream layout: ``cfg_args``, ``cameras.json``,
``point_cloud/iteration_<N>/point_cloud.ply``, plus ``split.json`` with the parameters and both
PSNR tables) only when every PSNR after the fit is at least
``--min-psnr`` (35 dB by default; exit status 1 otherwise).

    python tools/make_large_model.py -m ~/.cache/icomma/scenes/lego_200 -o /tmp/lego_300k \
        --target 300000
    python tools/make_large_model.py -m outputs/demo_scene -o /tmp/demo_100k --target 100000 \
        --mode upstream --min-psnr 0      # upstream's literal rule (does not keep the image)
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path
from typing import Dict, List, Sequence

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

import torch  # noqa: E402


#: The default size (longer side) of the renders the split model is fitted to: a model of
#: 1920x1080 photos is fitted at 800x450, as it is checked.
MAX_DISTILL_SIDE = 800


def parse_args(argv=None) -> argparse.Namespace:
    """The command line (module docstring)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("-m", "--model", required=True, type=Path, help="fitted 3DGS model folder")
    ap.add_argument("-o", "--out", required=True, type=Path, help="output model folder")
    ap.add_argument("--target", required=True, type=int, help="number of Gaussians wanted")
    ap.add_argument("--mode", default="preserve", choices=("preserve", "upstream"),
                    help="split rule (icomma_plugin.lod.split_gaussians)")
    ap.add_argument("--spread", type=float, default=0.3,
                    help="preserve mode: std of the children's offsets / the parent's scales")
    ap.add_argument("--opacity-power", type=float, default=None,
                    help="extra children in proportion to opacity ** this (default: 4 in "
                         "preserve mode, 0 in upstream mode)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--distill-steps", type=int, default=100,
                    help="steps fitting the split model to the original's renders (0 = none)")
    ap.add_argument("--distill-side", type=int, default=None,
                    help="image size (longer side) of those renders (default: the cameras', "
                         f"at most {MAX_DISTILL_SIDE})")
    ap.add_argument("--distill-cameras", type=int, default=100,
                    help="cameras rendered for the fit, evenly spaced (each render is held in "
                         "memory: 100 at 800x450 take 0.4 GB)")
    ap.add_argument("--check-cameras", type=int, default=4,
                    help="cameras of cameras.json rendered for the check (evenly spaced)")
    ap.add_argument("--check-sides", default="200,800", help="image sizes (longer side) checked")
    ap.add_argument("--min-psnr", type=float, default=35.0,
                    help="write only when every check PSNR [dB] is at least this")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--overwrite", action="store_true", help="replace an existing iteration")
    return ap.parse_args(argv)


def check_renders(original, split, cameras: Sequence, sides: Sequence[int],
                  white_background: bool = False) -> List[Dict]:
    """PSNR of ``split`` vs ``original`` rendered from each camera at each side."""
    from icomma_plugin.fit.losses import psnr
    from icomma_plugin.io.cameras_json import entry_to_intrinsics
    from icomma_plugin.render import prepare_scene, render

    full, reduced = prepare_scene(original), prepare_scene(split)
    bg = torch.ones(3) if white_background else torch.zeros(3)
    rows = []
    for side in sides:
        for e in cameras:
            intr = entry_to_intrinsics(e)
            intr = intr.scaled(side / max(intr.width, intr.height))
            w2c = torch.tensor(e.w2c, dtype=torch.float32)
            a = render(full, intr, w2c, bg).color.clamp(0.0, 1.0)
            b = render(reduced, intr, w2c, bg).color
            rows.append({"camera": e.img_name, "side": int(side), "psnr": psnr(b, a)})
    return rows


def distill_split(split, mf, check_cameras: Sequence, steps: int, side=None,
                  max_cameras: int = 100):
    """``split`` fitted to the original model's renders from the cameras not in the check.

    At most ``max_cameras`` of them (evenly spaced), at ``side`` px (None: their own size, at
    most `MAX_DISTILL_SIDE`).
    """
    from icomma_plugin.fit.distillation import distill
    from icomma_plugin.io.cameras_json import entry_to_intrinsics

    held = {e.img_name for e in check_cameras}
    entries = [e for e in mf.cameras if e.img_name not in held]
    if steps == 0 or not entries:
        return split
    entries = entries[::math.ceil(len(entries) / max_cameras)]
    pairs = []
    for e in entries:
        intr = entry_to_intrinsics(e)
        longer = max(intr.width, intr.height)
        target = side if side is not None else min(longer, MAX_DISTILL_SIDE)
        if target != longer:
            intr = intr.scaled(target / longer)
        pairs.append((intr, torch.tensor(e.w2c, dtype=torch.float32)))
    bg = (1.0, 1.0, 1.0) if mf.white_background else (0.0, 0.0, 0.0)

    def progress(it, total, info):
        if it % 50 == 0 or it == total:
            print(f"distillation {it}/{total}: loss {info['loss']:.4f}", flush=True)

    return distill(split, mf.model, pairs, steps, background=bg, progress=progress)


def main(argv=None) -> int:
    """Split, check, write (module docstring); returns the exit status."""
    a = parse_args(argv)
    torch.set_num_threads(max(1, a.threads))
    from icomma_plugin.io.atomic import write_json_atomic
    from icomma_plugin.io.model_folder import load_model_folder, write_model_folder
    from icomma_plugin.lod import split_gaussians

    mf = load_model_folder(a.model.expanduser())
    if not mf.cameras:
        print(f"error: {a.model} has no cameras.json (needed for the check)", file=sys.stderr)
        return 2
    if a.target < mf.model.num_gaussians:
        print(f"error: --target {a.target} is below the model's {mf.model.num_gaussians:,} "
              "Gaussians", file=sys.stderr)
        return 2
    if a.distill_steps < 0 or a.distill_cameras < 1 or (a.distill_side is not None
                                                         and a.distill_side < 8):
        print("error: --distill-steps must be >= 0, --distill-cameras >= 1 and --distill-side "
              ">= 8", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    split = split_gaussians(mf.model, target=a.target, mode=a.mode, spread=a.spread,
                            opacity_power=a.opacity_power,
                            generator=torch.Generator().manual_seed(a.seed))
    split_s = time.perf_counter() - t0
    step = max(1, len(mf.cameras) // max(1, a.check_cameras))
    cams = mf.cameras[::step][: a.check_cameras]
    sides = [int(s) for s in a.check_sides.split(",") if s.strip()]
    # the rule's own image first, so that the table shows what the fit bought
    before = (check_renders(mf.model, split, cams, sides, mf.white_background)
              if a.distill_steps > 0 else None)
    t0 = time.perf_counter()
    split = distill_split(split, mf, cams, a.distill_steps, a.distill_side, a.distill_cameras)
    distill_s = time.perf_counter() - t0
    rows = check_renders(mf.model, split, cams, sides, mf.white_background)
    print(f"{mf.model.num_gaussians:,} -> {split.num_gaussians:,} Gaussians ({a.mode}, "
          f"{split_s:.1f} s; {a.distill_steps} distillation steps, {distill_s:.1f} s); PSNR of "
          "split vs original (cameras not distilled on):")
    print("| camera | side | PSNR dB | split by the rule alone |\n|---|---|---|---|")
    for k, r in enumerate(rows):
        rule = f"{before[k]['psnr']:.2f}" if before else "-"
        print(f"| {r['camera']} | {r['side']} | {r['psnr']:.2f} | {rule} |")
    worst = min(r["psnr"] for r in rows)
    if not worst >= a.min_psnr:
        print(f"error: lowest PSNR {worst:.2f} dB < --min-psnr {a.min_psnr:g}; nothing written",
              file=sys.stderr)
        return 1
    out = a.out.expanduser()
    # the source's principal point said outright: the split has no metrics.json to tell it by
    cfg = dict(mf.cfg, model_path=str(out), principal_point=mf.principal_point)
    try:
        ply = write_model_folder(out, split, cfg, mf.cameras, mf.iteration, overwrite=a.overwrite)
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    write_json_atomic(out / "split.json", {
        "source": str(mf.path), "source_gaussians": mf.model.num_gaussians,
        "gaussians": split.num_gaussians, "mode": a.mode, "spread": a.spread,
        "opacity_power": a.opacity_power, "seed": a.seed, "distill_steps": a.distill_steps,
        "distill_side": a.distill_side, "distill_cameras": a.distill_cameras,
        "distill_seconds": round(distill_s, 1),
        "min_psnr_db": worst if math.isfinite(worst) else None, "checks": rows,
        "checks_before_distill": before})
    print(f"wrote {ply}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
