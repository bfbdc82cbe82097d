"""Preview PNGs of a job: a few layers with beads drawn at their width, and a 3D overview."""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.axes import Axes  # noqa: E402
from matplotlib.collections import LineCollection  # noqa: E402

from planner.job import Job  # noqa: E402

ROLE_COLOURS = {"perimeter": "tab:blue", "infill": "tab:orange", "gap": "tab:green"}


def _pick_layers(job: Job, count: int) -> list[int]:
    n = len(job.layers)
    return sorted({int(round(x)) for x in np.linspace(0, n - 1, min(count, n))}) if n else []


def draw_layer(ax: Axes, job: Job, index: int) -> None:
    """Beads at their true width (in data units), arc starts as dots, travel as thin grey lines."""
    layer = job.layers[index]
    fig_scale = _points_per_mm(ax)
    prev = None
    for p in layer.passes:
        xy = p.points[:, :2]
        colour = ROLE_COLOURS.get(p.role, "k")
        ax.add_collection(LineCollection([xy], linewidths=max(p.width_mm * fig_scale, 0.5), colors=colour,
                                         alpha=0.35, capstyle="round", joinstyle="round"))
        ax.plot(xy[:, 0], xy[:, 1], color=colour, lw=0.6)
        ax.plot(*xy[0], "o", color="k", ms=2.5)
        if prev is not None:
            ax.plot([prev[0], xy[0, 0]], [prev[1], xy[0, 1]], color="0.6", lw=0.4, ls=":")
        prev = xy[-1]
    ax.set_title(f"layer {layer.index}  z {layer.z_mm:.2f} mm  {len(layer.passes)} beads", fontsize=8)
    ax.set_aspect("equal")


def _points_per_mm(ax: Axes) -> float:
    ax.figure.canvas.draw()
    x0, x1 = ax.get_xlim()
    bbox = ax.get_window_extent()
    return bbox.width * 72.0 / ax.figure.dpi / max(x1 - x0, 1e-9)


def write_previews(job: Job, out_dir: str | Path, count: int = 4) -> list[Path]:
    """Write layers.png (a few layers) and overview.png (3D) into out_dir; return the paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    pts = [p.points for L in job.layers for p in L.passes]
    allxy = np.vstack(pts)[:, :2] if pts else np.zeros((1, 2))
    w = job.bead.width_mm
    lo, hi = allxy.min(axis=0) - w, allxy.max(axis=0) + w
    picks = _pick_layers(job, count)
    fig, axes = plt.subplots(1, max(len(picks), 1), figsize=(4 * max(len(picks), 1), 4.2), squeeze=False)
    for ax, i in zip(axes[0], picks):
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        draw_layer(ax, job, i)
    fig.suptitle(f"{job.source.file}: bead {w:g} mm, step-over {job.bead.step_over_mm:.2f} mm", fontsize=9)
    fig.tight_layout()
    paths = [out / "layers.png"]
    fig.savefig(paths[0], dpi=110)
    plt.close(fig)
    fig = plt.figure(figsize=(6, 5))
    ax = fig.add_subplot(projection="3d")
    for L in job.layers:
        for p in L.passes:
            ax.plot(p.points[:, 0], p.points[:, 1], p.points[:, 2], lw=0.5,
                    color=ROLE_COLOURS.get(p.role, "k"))
    ax.set_xlabel("x mm")
    ax.set_ylabel("y mm")
    ax.set_zlabel("z mm")
    ax.set_title(f"{job.source.file}: {len(job.layers)} layers", fontsize=9)
    paths.append(out / "overview.png")
    fig.savefig(paths[1], dpi=110)
    plt.close(fig)
    return paths
