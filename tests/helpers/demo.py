"""Photos of the built-in demo scene taken at known poses (the truth of the tool tests)."""
from __future__ import annotations

from pathlib import Path
from typing import Tuple

import numpy as np
import torch

from icomma_plugin.app.demo_scene import DemoScene, build_demo_scene
from icomma_plugin.gaussians import GaussianModel
from icomma_plugin.io.model_folder import load_model_folder
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
