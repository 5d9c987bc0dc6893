"""Figures of the study plots: built outside pyplot, saved as PNG."""
from __future__ import annotations

import os


def new_figure(figsize):
    """A matplotlib Figure outside pyplot (no global state; garbage-collected)."""
    from matplotlib.figure import Figure

    return Figure(figsize=figsize)


def save_figure(fig, out_png) -> str:
    """Save ``fig`` as a PNG (folders created) and return the path."""
    path = os.fspath(out_png)
    folder = os.path.dirname(path)
    if folder:
        os.makedirs(folder, exist_ok=True)
    fig.savefig(path, dpi=120, bbox_inches="tight")
    return path
