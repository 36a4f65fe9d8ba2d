"""Image files written for the readers, with PIL (independent of the readers' cv2 decode)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image


def write_png(path: Path, arr: np.ndarray) -> Path:
    """uint8 [H, W, 3|4] RGB(A) -> PNG at ``path`` (its folder created)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.ascontiguousarray(arr)).save(path)
    return path
