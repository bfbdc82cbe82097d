"""Figures for the build record: matplotlib's object API on the Agg canvas, fixed margins.

Half of a record's time went to pyplot and to `tight_layout`, which draws every figure once
more to measure its labels (2.7 s of a 1-bead record: 0.4 s importing pyplot and its figure
manager, ~1 s laying out). A record is written at the end of every build, before `cell run`
returns, so the figures are made without pyplot and with margins fixed in inches, wide enough
for the longest tick labels these plots carry (five digits and a sign) and their axis labels.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

DPI = 80
# margins in inches: y tick labels + y label on the left, x tick labels + x label below, a title above
LEFT_IN, RIGHT_IN, TOP_IN, BOTTOM_IN, GAP_IN = 1.0, 0.25, 0.55, 0.7, 0.25


def new_figure(rows: int, cols: int, figsize: tuple[float, float], *, sharex: bool = False) -> tuple[Any, Any]:
    """A figure of `rows` x `cols` axes (one Axes, or an array of them), margins fixed."""
    # lazy: matplotlib loads only when a record with plots is written (start-up time of the rest)
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize)
    ax = fig.subplots(rows, cols, sharex=sharex, squeeze=True)
    w, h = figsize
    fig.subplots_adjust(left=LEFT_IN / w, right=1.0 - RIGHT_IN / w, top=1.0 - TOP_IN / h, bottom=BOTTOM_IN / h,
                        hspace=GAP_IN * rows / max(h - TOP_IN - BOTTOM_IN, 1e-6))
    return fig, ax


def save(fig: Any, path: Path) -> Path:
    """Write the figure as a PNG (Agg) and free it."""
    fig.savefig(path, dpi=DPI)
    fig.clear()
    return path
