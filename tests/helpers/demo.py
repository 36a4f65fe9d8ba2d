"""Photos of the built-in demo scene taken at known poses (the truth of the tool tests)."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Dict, Tuple

import numpy as np
import torch

from icomma_plugin.app.demo_scene import DemoScene, build_demo_scene
from icomma_plugin.gaussians import GaussianModel
from icomma_plugin.io.model_folder import load_model_folder
from icomma_plugin.pose.convert import look_at_c2w
from icomma_plugin.render import render


def demo_model(folder: Path, size: int) -> Tuple[DemoScene, GaussianModel]:
    """A ``size`` x ``size`` demo model folder built at ``folder``, and its Gaussians."""
    scene = build_demo_scene(folder, seed=0, width=size, height=size)
    return scene, load_model_folder(scene.path).model


def photo(model, intrinsics, c2w: np.ndarray) -> np.ndarray:
    """uint8 [H, W, 3] render of ``model`` from camera-to-world ``c2w`` on black."""
    with torch.no_grad():
        img = render(
            model,
            intrinsics,
            torch.as_tensor(np.linalg.inv(c2w), dtype=torch.float32),
            torch.zeros(3),
        ).color.clamp(0, 1)
    return (img.permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8)


def orbit_c2w(azimuth: float, height: float, radius: float = 3.8) -> np.ndarray:
    """Camera-to-world on a circle around the demo model, looking at its middle."""
    eye = np.array([radius * np.cos(azimuth), radius * np.sin(azimuth), height])
    return look_at_c2w(eye, np.array([0.0, 0.0, 0.4]))


def save_photos(model, intrinsics, c2ws: Dict[str, np.ndarray], folder: Path,
                gt_path: Path) -> None:
    """Render ``model`` at each ``{file name: c2w}`` into ``folder``; their poses to ``gt_path``."""
    from PIL import Image

    folder.mkdir(parents=True, exist_ok=True)
    for name, c2w in c2ws.items():
        Image.fromarray(photo(model, intrinsics, c2w)).save(folder / name)
    gt_path.write_text(json.dumps({name: c2w.tolist() for name, c2w in c2ws.items()}))
