"""Pictures of a batch: each photo's thumbnail, and the contact sheet coloured by verdict."""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Dict, Mapping, Optional, Sequence

import numpy as np
import torch

from ..io.video import PathLike
from ..pose.convert import invert_rigid
from .images import VERDICT_COLOURS, save_image

logger = logging.getLogger(__name__)


__all__ = ["FLAG_COLOUR", "contact_sheet", "save_thumbnail"]


def save_thumbnail(
    path: PathLike, model, query, c2w, bg, side: int = 192, backend: str = "auto"
) -> Path:
    """Half-and-half blend of the render at ``c2w`` over the photo of ``query``.

    ``query`` is a localization ``Query``; the longer side is ``side`` px; written to ``path``.
    """
    from ..localization.types import resize_image
    from ..render import render

    intr = query.intrinsics
    s = intr.scale_to_side(side)
    small = intr.scaled(s) if s != 1.0 else intr
    photo = resize_image(query.rgb.float().cpu(), small.height, small.width).clamp(0, 1)
    w2c = torch.as_tensor(
        invert_rigid(np.asarray(c2w, np.float64)), dtype=model.dtype, device=model.device
    )
    with torch.no_grad():
        img = (
            render(
                model,
                small,
                w2c,
                torch.as_tensor(bg, dtype=model.dtype, device=model.device),
                backend=backend,
            )
            .color.clamp(0, 1)
            .float()
            .cpu()
        )
    return save_image(path, 0.5 * img + 0.5 * photo)


def _label(canvas: np.ndarray, text: str, xy, scale: float = 0.38, colour=(255, 255, 255)) -> None:
    import cv2

    x, y = xy
    cv2.putText(canvas, text, (x, y), cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(canvas, text, (x, y), cv2.FONT_HERSHEY_SIMPLEX, scale, colour, 1, cv2.LINE_AA)


def contact_sheet(
    path: PathLike,
    rows: Sequence[Dict[str, Any]],
    base_dir: PathLike,
    columns: int = 8,
    cell: int = 192,
    border: int = 5,
    max_photos: int = 400,
    flags: Optional[Mapping[str, str]] = None,
) -> Path:
    """One picture of a batch: each photo's thumbnail framed in its verdict's colour.

    Thumbnails are ``row["thumb"]``, relative to ``base_dir``; colours :data:`VERDICT_COLOURS`;
    each cell has the photo's name and, when the truth is known, its errors. Photos without a
    thumbnail get a grey cell. Rows after ``max_photos`` are left out (the sheet says so).
    ``flags`` (photo name -> a short word, e.g. an audit's flag): those cells get an inner
    magenta frame (:data:`FLAG_COLOUR`) and the word; the title counts them.
    """
    from PIL import Image

    if not rows:
        raise ValueError("rows is empty: no photo to put on a contact sheet")
    if isinstance(columns, bool) or not isinstance(columns, int) or columns < 1:
        raise ValueError(f"columns must be a positive int, got {columns!r}")
    shown = list(rows)[:max_photos]
    cols = min(columns, len(shown))
    nrows = (len(shown) + cols - 1) // cols
    pitch = cell + 2 * border
    header = 24
    canvas = np.full((header + nrows * pitch, cols * pitch, 3), 30, np.uint8)
    counts = {k: sum(1 for r in rows if r.get("status") == k) for k in VERDICT_COLOURS}
    flags = dict(flags or {})
    title = "  ".join(f"{k} {v}" for k, v in counts.items()) + (
        f"   flagged {sum(1 for r in rows if str(r.get('name')) in flags)}" if flags else ""
    ) + (f"   (first {len(shown)} of {len(rows)})" if len(rows) > len(shown) else "")
    _label(canvas, title, (6, 17), 0.5)
    base = Path(base_dir)
    for i, r in enumerate(shown):
        y0, x0 = header + (i // cols) * pitch, (i % cols) * pitch
        colour = VERDICT_COLOURS.get(r.get("status"), (128, 128, 128))
        canvas[y0 : y0 + pitch, x0 : x0 + pitch] = colour
        tile = np.full((cell, cell, 3), 70, np.uint8)
        thumb = r.get("thumb")
        if thumb and (base / thumb).is_file():
            im = Image.open(base / thumb).convert("RGB")
            f = cell / max(im.size)
            im = im.resize(
                (max(1, round(im.size[0] * f)), max(1, round(im.size[1] * f))), Image.BILINEAR
            )
            a = np.asarray(im)
            oy, ox = (cell - a.shape[0]) // 2, (cell - a.shape[1]) // 2
            tile[oy : oy + a.shape[0], ox : ox + a.shape[1]] = a
        canvas[y0 + border : y0 + border + cell, x0 + border : x0 + border + cell] = tile
        name = str(r.get("name", "?"))
        _label(
            canvas,
            name if len(name) <= 26 else "..." + name[-23:],
            (x0 + border + 3, y0 + border + 13),
        )
        err = r.get("rot_err_deg")
        line = str(r.get("status", "?"))
        if err is not None:
            t = r.get("trans_err_rel")
            line += f"  {err:.2f} deg" + ("" if t is None else f"  {100 * t:.2f}%")
        _label(canvas, line, (x0 + border + 3, y0 + border + cell - 6))
        if name in flags:
            _mark_flag(canvas, x0 + border, y0 + border, cell, str(flags[name]))
    return save_image(path, canvas)


#: The inner frame of a flagged cell (magenta: no verdict colour).
FLAG_COLOUR = (255, 0, 255)


def _mark_flag(canvas: np.ndarray, x0: int, y0: int, cell: int, word: str) -> None:
    """An inner magenta frame on the cell at (x0, y0) and ``FLAG <word>`` under its name."""
    w = max(2, cell // 40)
    canvas[y0 : y0 + w, x0 : x0 + cell] = FLAG_COLOUR
    canvas[y0 + cell - w : y0 + cell, x0 : x0 + cell] = FLAG_COLOUR
    canvas[y0 : y0 + cell, x0 : x0 + w] = FLAG_COLOUR
    canvas[y0 : y0 + cell, x0 + cell - w : x0 + cell] = FLAG_COLOUR
    _label(canvas, f"FLAG {word}"[:28], (x0 + w + 3, y0 + 30), colour=FLAG_COLOUR)

