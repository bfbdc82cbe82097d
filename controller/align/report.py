"""Alignment report: JSON (the `cell align run` object) and a PNG of points, residuals and planes."""
from __future__ import annotations

import json
from pathlib import Path
import numpy as np

from controller.align.routine import AlignResult
from core.errors import InputError


def write_report(res: AlignResult, out_dir: str | Path, *, stem: str = "align") -> dict[str, Path]:
    """Write DIR/align.json and DIR/align.png; returns their paths."""
    d = Path(out_dir)
    try:
        d.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"{d}: cannot create the report directory ({exc.strerror or exc})") from None
    jp, pp = d / f"{stem}.json", d / f"{stem}.png"
    jp.write_text(json.dumps(res.to_json(), indent=1) + "\n", encoding="utf-8")
    plot(res, pp)
    return {"json": jp, "png": pp}


def plot(res: AlignResult, path: str | Path) -> None:
    """Three panels: the touches and fitted planes in 3-D, top residuals on the grid, side residuals."""
    # lazy: matplotlib loads only when this path runs (start-up time)
    import matplotlib

    matplotlib.use("Agg")
    # lazy: matplotlib loads only when this path runs (start-up time)
    import matplotlib.pyplot as plt

    top = res.points["top"]
    side = res.points["side"]
    ter = res.points["tertiary"]
    fig = plt.figure(figsize=(13, 4.5), dpi=100)
    ax = fig.add_subplot(1, 3, 1, projection="3d")
    ax.scatter(*top.T, c="tab:blue", s=18, label="top touches")
    ax.scatter(*side.T, c="tab:orange", s=18, label="side touches")
    ax.scatter(*ter.T, c="tab:green", s=18, label="third-face touch")
    out = list(res.top.outliers)
    if out:
        ax.scatter(*top[out].T, facecolors="none", edgecolors="red", s=80, label="rejected")
    # The fitted top plane over the probed area, and the side plane over the side touches.
    lo, hi = top[:, :2].min(axis=0), top[:, :2].max(axis=0)
    gx, gy = np.meshgrid(np.linspace(lo[0], hi[0], 2), np.linspace(lo[1], hi[1], 2))
    n, d = res.top.normal, res.top.offset
    ax.plot_surface(gx, gy, (d - n[0] * gx - n[1] * gy) / n[2], alpha=0.25, color="tab:blue")
    ns = res.side_normal
    ys = np.linspace(side[:, 1].min(), side[:, 1].max(), 2)
    zs = np.linspace(min(side[:, 2].min(), ter[:, 2].min()) - 3, res.top.point[2], 2)
    sy, sz = np.meshgrid(ys, zs)
    ds = ns @ res.side.point
    if abs(ns[0]) > 1e-9:
        ax.plot_surface((ds - ns[1] * sy - ns[2] * sz) / ns[0], sy, sz, alpha=0.25, color="tab:orange")
    ax.set_xlabel("x mm")
    ax.set_ylabel("y mm")
    ax.set_zlabel("z mm")
    ax.set_title(f"leveled: A {res.level_a_deg:.4f}°, B {res.level_b_deg:.4f}°")
    ax.legend(fontsize=7, loc="upper left")

    ax2 = fig.add_subplot(1, 3, 2)
    r_um = res.top.residuals * 1000
    sc = ax2.scatter(top[:, 0], top[:, 1], c=r_um, cmap="coolwarm", s=140, vmin=-max(abs(r_um).max(), 1e-3),
                     vmax=max(abs(r_um).max(), 1e-3))
    for (x, y), r in zip(top[:, :2], r_um):
        ax2.annotate(f"{r:+.1f}", (x, y), textcoords="offset points", xytext=(0, 9), ha="center", fontsize=7)
    fig.colorbar(sc, ax=ax2, label="residual µm")
    ax2.set_aspect("equal")
    ax2.set_title(f"top plane residuals\nrms {res.top.rms_mm * 1000:.2f} µm, max {res.top.max_residual_mm * 1000:.2f} µm")
    ax2.set_xlabel("x mm")
    ax2.set_ylabel("y mm")

    ax3 = fig.add_subplot(1, 3, 3)
    q = side - res.side.point
    along = q @ res.side.direction
    perp = q @ res.side_normal
    ax3.axhline(0, color="grey", lw=0.8)
    ax3.plot(along, perp * 1000, "o-", color="tab:orange")
    ax3.set_xlabel("along the side face, mm")
    ax3.set_ylabel("residual µm")
    ax3.set_title(f"side face: {res.face_angle_deg:.4f}° to CAD\nrms {res.side.rms_mm * 1000:.2f} µm")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
