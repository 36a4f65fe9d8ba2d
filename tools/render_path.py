#!/usr/bin/env python
r"""Render a smooth camera path through a 3DGS model to a video, with its true poses.

The video is test input for tracking (``tools/localize.py data.sequence=...``):

    python tools/render_path.py -m ~/.cache/icomma/scenes/lego_200 -o /tmp/lego_path --frames 100
    python tools/localize.py data=model_folder data.model_path=~/.cache/icomma/scenes/lego_200 \
        data.sequence=/tmp/lego_path/path.mp4 data.intrinsics.camera=0 data.init=none \
        data.gt.poses_file=/tmp/lego_path/poses.json output.dir=/tmp/lego_path/track

The path orbits the scene centre (the point the model's cameras look at, ``scene_frame``) at the
cameras' median distance: ``--arc`` degrees of azimuth over the frames, the elevation swinging
``--swing`` degrees about ``--elevation`` and the distance breathing by ``--breathe`` (relative)
once along the way, the aim wandering ``--wander`` of the radius about the centre. Writes
``path.mp4`` (``--png``: also ``frames/``), ``poses.json`` (frame name -> true c2w, OpenCV axes;
names ``frame_000000`` as the tracker names a video's frames, and the PNG names) and
``path.json`` (the parameters and intrinsics).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

import numpy as np  # noqa: E402
import torch  # noqa: E402


def path_poses(
    centre, radius, up, n, arc_deg, elevation_deg, swing_deg, breathe, wander, start_deg
):
    """``n`` c2w poses along the orbit described in the module docstring."""
    from icomma_plugin.pose.convert import look_at_c2w

    z = np.asarray(up, np.float64) / np.linalg.norm(up)
    x = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    out = []
    for k in range(n):
        s = k / max(1, n - 1)
        az = math.radians(start_deg + arc_deg * s)
        el = math.radians(elevation_deg + swing_deg * math.sin(2 * math.pi * s))
        r = radius * (1.0 + breathe * math.sin(math.pi * s))
        d = math.cos(el) * (math.cos(az) * x + math.sin(az) * y) + math.sin(el) * z
        aim = centre + wander * radius * (
            math.sin(3 * math.pi * s) * x + 0.5 * math.cos(2 * math.pi * s) * y
        )
        out.append(look_at_c2w(centre + r * d, aim, z))
    return out


def main(argv=None) -> int:
    """Render the path (module docstring). Returns the exit status."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("-m", "--model", required=True, help="3DGS model folder")
    ap.add_argument("-o", "--out", required=True, help="output folder")
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--fps", type=float, default=25.0)
    ap.add_argument(
        "--camera",
        default=None,
        help="cameras.json entry (id or name) for the intrinsics (default: the first)",
    )
    ap.add_argument(
        "--size",
        type=int,
        default=None,
        help="longer image side [px] (default: the model's training resolution, cfg_args)",
    )
    ap.add_argument("--arc", type=float, default=60.0, help="azimuth covered [deg]")
    ap.add_argument(
        "--start",
        type=float,
        default=None,
        help="first azimuth [deg] (default: the first camera's)",
    )
    ap.add_argument(
        "--elevation", type=float, default=None, help="[deg] (default: the cameras' median)"
    )
    ap.add_argument("--swing", type=float, default=8.0, help="elevation swing [deg]")
    ap.add_argument("--breathe", type=float, default=0.05, help="relative change of the distance")
    ap.add_argument(
        "--wander", type=float, default=0.03, help="aim wander, relative to the distance"
    )
    ap.add_argument("--png", action="store_true", help="also write frames/frame_000000.png ...")
    ap.add_argument("--threads", type=int, default=1)
    a = ap.parse_args(argv)
    torch.set_num_threads(max(1, a.threads))

    from icomma_plugin.io.cameras_json import entry_to_intrinsics, find_entry
    from icomma_plugin.io.model_folder import load_model_folder
    from icomma_plugin.io.video import write_video
    from icomma_plugin.pose.convert import invert_rigid
    from icomma_plugin.pose.views import scene_frame
    from icomma_plugin.render import render
    from icomma_plugin.pictures import save_image, to_uint8

    mf = load_model_folder(Path(a.model).expanduser())
    if not mf.cameras:
        print(
            f"error: {a.model} has no cameras.json (needed for the intrinsics and the orbit)",
            file=sys.stderr,
        )
        return 2
    cam = int(a.camera) if a.camera is not None and a.camera.isdigit() else a.camera
    entry = find_entry(mf.cameras, cam) if cam is not None else mf.cameras[0]
    intr = entry_to_intrinsics(entry)
    res = int(mf.cfg.get("resolution", -1) or -1)
    side = a.size or (
        max(intr.width, intr.height) // res if res in (1, 2, 4, 8) else max(intr.width, intr.height)
    )
    intr = intr.scaled(side / max(intr.width, intr.height))
    cams = [np.asarray(e.c2w, np.float64) for e in mf.cameras]
    centre, radius, up = scene_frame(mf.model.means.numpy(), cams)
    rel = np.stack([c[:3, 3] - centre for c in cams])
    ups = rel @ up
    flat = rel - np.outer(ups, up)
    elev = (
        a.elevation
        if a.elevation is not None
        else float(np.degrees(np.median(np.arctan2(ups, np.linalg.norm(flat, axis=1)))))
    )
    zax = up / np.linalg.norm(up)
    xax = np.cross(zax, [1.0, 0.0, 0.0] if abs(zax[0]) < 0.9 else [0.0, 1.0, 0.0])
    xax /= np.linalg.norm(xax)
    yax = np.cross(zax, xax)
    start = (
        a.start
        if a.start is not None
        else float(np.degrees(np.arctan2(flat[0] @ yax, flat[0] @ xax)))
    )
    poses = path_poses(
        centre, radius, up, a.frames, a.arc, elev, a.swing, a.breathe, a.wander, start
    )
    bg = torch.ones(3) if mf.white_background else torch.zeros(3)
    out = Path(a.out).expanduser()
    (
        (out / "frames").mkdir(parents=True, exist_ok=True)
        if a.png
        else out.mkdir(parents=True, exist_ok=True)
    )
    frames, truth = [], {}
    for k, c2w in enumerate(poses):
        with torch.no_grad():
            img = render(
                mf.model, intr, torch.as_tensor(invert_rigid(c2w), dtype=mf.model.dtype), bg
            ).color
        frames.append(to_uint8(img.clamp(0, 1)))
        truth[f"frame_{k:06d}"] = c2w.tolist()
        if a.png:
            save_image(out / "frames" / f"frame_{k:06d}.png", frames[-1])
            truth[f"frame_{k:06d}.png"] = c2w.tolist()
    video = write_video(out / "path.mp4", frames, fps=a.fps)
    (out / "poses.json").write_text(json.dumps(truth))
    steps = [np.linalg.norm(poses[k + 1][:3, 3] - poses[k][:3, 3]) for k in range(len(poses) - 1)]
    (out / "path.json").write_text(
        json.dumps(
            {
                "model": str(mf.path),
                "frames": a.frames,
                "fps": a.fps,
                "video": video.name,
                "intrinsics": {
                    "width": intr.width,
                    "height": intr.height,
                    "fx": intr.fx,
                    "fy": intr.fy,
                },
                "camera": entry.img_name,
                "camera_id": entry.id,  # names may repeat (lego's train and test r_0): the id won't
                "centre": centre.tolist(),
                "radius": radius,
                "up": up.tolist(),
                "arc_deg": a.arc,
                "start_deg": start,
                "elevation_deg": elev,
                "swing_deg": a.swing,
                "breathe": a.breathe,
                "wander": a.wander,
                "mean_step": float(np.mean(steps)) if steps else 0.0,
            },
            indent=2,
        )
    )
    print(
        f"{len(frames)} frames {intr.width}x{intr.height} -> {video}; "
        f"true poses in {out / 'poses.json'}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
