"""Pictures of localizations, batches, sequences and benchmarks.

A run: overlays, match lines, convergence plots, an optimisation GIF or MP4 (``images``,
``plots``); a batch: thumbnails and a contact sheet coloured by verdict (``sheets``); a sequence:
the trajectory over the scene's cameras; a benchmark: the success curves beside the paper's
numbers (``plots``).

Images are ``[3, H, W]`` float tensors in [0, 1] (or ``[H, W, 3]`` uint8/float numpy arrays).
Every file is written atomically (``io.atomic.atomic_path``). matplotlib runs on the Agg backend
and is imported lazily, so importing this package is cheap. The core never imports it
(tests/test_layering.py).
"""
from ..io.video import to_uint8
from .images import (
    VERDICT_COLOURS,
    match_lines_image,
    overlay_panel,
    save_gif,
    save_image,
    save_match_lines,
    save_overlay,
    save_video,
)
from .plots import (
    plot_convergence,
    plot_curves_vs_paper,
    plot_focal_frames,
    plot_focal_passes,
    plot_trajectory,
    save_figure,
)
from .sheets import contact_sheet, save_thumbnail

__all__ = [
    "VERDICT_COLOURS",
    "contact_sheet",
    "match_lines_image",
    "overlay_panel",
    "plot_convergence",
    "plot_curves_vs_paper",
    "plot_focal_frames",
    "plot_focal_passes",
    "plot_trajectory",
    "save_figure",
    "save_gif",
    "save_image",
    "save_match_lines",
    "save_overlay",
    "save_thumbnail",
    "save_video",
    "to_uint8",
]
