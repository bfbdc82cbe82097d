"""5-axis post-processing at the executor (Kerschbaumer's "calculation mode 1"): (point, axis) → X Y Z A B|C.

Pure: numpy in, arrays and G-code text out. The convention is docs/kinematics.md (the Trunnion of
controller/motion/kinematics.py). Continuity: of every inverse-kinematics candidate inside the
axis limits (each angle also ±360°) the one closest to the previous point's angles is taken, so a
pass never flips 180°/360°; where the inner axis is free (tool axis along it: the singularity) the
previous inner angle is kept. Feed: inverse time (G93), F = planned speed / part-frame length of
the move, so the tool tip moves at the planned speed whatever the table does.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from controller.motion.kinematics import Trunnion, signed_angle, apply_transform, rotation_matrix, unit
from core.errors import InputError

Z = np.array([0.0, 0.0, 1.0])
# Within 0.5° of the inner axis (the singularity) the inner angle is held and only the outer one
# follows: the tool axis is then off by at most 0.5°, and the table does not spin to follow the
# azimuth of an almost vertical axis.
_SINGULAR = float(np.sin(np.radians(0.5)))


def weld_axes(points: Sequence[Sequence[float]], axes: Sequence[Sequence[float]] | None,
              max_step_mm: float) -> list[tuple[float, float, float]]:
    """Tool axes at the points of build.weld_points (same subdivision), normalised linear blend."""
    if axes is None:
        return [(0.0, 0.0, 1.0)] * _count(points, max_step_mm)
    out = [tuple(unit(axes[0]))]
    a_pt = np.asarray(points[0][:3], dtype=float)
    a_ax = np.asarray(axes[0], dtype=float)
    for p, ax in zip(points[1:], axes[1:]):
        q, qa = np.asarray(p[:3], dtype=float), np.asarray(ax, dtype=float)
        d = math.dist(a_pt, q)
        if d < 1e-9:
            continue
        n = max(1, math.ceil(d / max_step_mm - 1e-9))
        for k in range(1, n + 1):
            out.append(tuple(unit(a_ax + (qa - a_ax) * (k / n))))
        a_pt, a_ax = q, qa
    return out


def _count(points: Sequence[Sequence[float]], max_step_mm: float) -> int:
    n, a = 1, points[0]
    for p in points[1:]:
        d = math.dist(a[:3], p[:3])
        if d < 1e-9:
            continue
        n += max(1, math.ceil(d / max_step_mm - 1e-9))
        a = p
    return n


@dataclass(frozen=True)
class Post5:
    """The configured table and, optionally, the job's alignment (part → table frame at zero)."""

    trunnion: Trunnion
    alignment: np.ndarray | None = None   # 4×4 part → table frame; None: identity

    def _solutions(self, axes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Both Paden–Kahan solutions (a, second) for every axis at once: (n, 2, 2) and validity (n, 2)."""
        t = self.trunnion
        u1, u2 = t.axes()
        v = axes / np.linalg.norm(axes, axis=1, keepdims=True)
        d = float(u1 @ u2)
        w = np.cross(u1, u2)
        ww = float(w @ w)
        if ww < 1e-18:
            raise InputError("the two table axes are parallel; check kinematics.axis_a / axis_second")
        s1, s2 = v @ u1, float(u2 @ Z)
        det = 1.0 - d * d
        alpha, beta = (s1 - d * s2) / det, (s2 - d * s1) / det
        g2 = (1.0 - alpha * alpha - beta * beta - 2.0 * alpha * beta * d) / ww
        ok = g2 >= -1e-12
        g = np.sqrt(np.clip(g2, 0.0, None))
        out = np.zeros((len(v), 2, 2))
        for k, sg in enumerate((1.0, -1.0)):
            c = alpha[:, None] * u1 + beta[:, None] * u2 + (sg * g)[:, None] * w
            t1 = _angles(v, c, u1)
            t2 = _angles(c, np.broadcast_to(Z, c.shape), u2)
            out[:, k] = np.column_stack([t1, t2]) if t.table == "AB" else np.column_stack([t2, t1])
        return out, np.column_stack([ok, ok])

    def _held(self, axis: np.ndarray, prev: tuple[float, float]) -> tuple[float, float]:
        """At the singularity: the inner angle held, the outer one solved."""
        t = self.trunnion
        u1, u2 = t.axes()
        inner = prev[0] if t.table == "AB" else prev[1]
        v = rotation_matrix(u1, inner) @ axis
        outer = float(np.degrees(signed_angle(v, Z, u2)))
        return (inner, outer) if t.table == "AB" else (outer, inner)

    def angles(self, axes: np.ndarray, prev: tuple[float, float] | None = None) -> np.ndarray:
        """(n, 2) table angles (a, second) along a pass, continuous, shifted by whole turns into the limits.

        Raises InputError naming the first point the limits cannot reach.
        """
        t = self.trunnion
        axes = np.asarray(axes, dtype=float)
        first = prev
        sols, ok = self._solutions(axes)
        u1 = t.axes()[0]
        near = np.linalg.norm(np.cross(axes / np.linalg.norm(axes, axis=1, keepdims=True), u1), axis=1) < _SINGULAR
        out = np.zeros((len(axes), 2))
        for i in range(len(axes)):
            cands = [(float(a), float(s)) for (a, s), good in zip(sols[i], ok[i]) if good]
            if prev is not None and near[i]:
                cands = [self._held(unit(axes[i]), prev)]
            if not cands:
                raise InputError(f"point {i}: no table angles bring tool axis {np.round(axes[i], 4).tolist()} to +Z")
            if prev is None:
                best = min(cands, key=lambda c: (not t.within_limits(*c), max(abs(c[0]), abs(c[1]))))
            else:
                pv = prev
                cands = [(a, s + 360.0 * round((pv[1] - s) / 360.0)) for a, s in cands]
                best = min(cands, key=lambda c: (max(abs(c[0] - pv[0]), abs(c[1] - pv[1])), abs(c[0]) + abs(c[1])))
            out[i] = best
            prev = best
        return self._into_limits(out, axes, first)

    def _into_limits(self, ang: np.ndarray, axes: np.ndarray, first: tuple[float, float] | None) -> np.ndarray:
        lo, hi = self.trunnion.second_limits_deg
        shifts = [0.0] if first is not None else sorted((360.0 * k for k in range(-3, 4)), key=abs)
        for sh in shifts:
            s = ang[:, 1] + sh
            if s.min() >= lo - 1e-9 and s.max() <= hi + 1e-9:
                ang = np.column_stack([ang[:, 0], s])
                break
        bad = [i for i, (a, s) in enumerate(ang) if not self.trunnion.within_limits(a, s)]
        if bad:
            i = bad[0]
            raise InputError(f"point {i}: tool axis {np.round(axes[i], 4).tolist()} needs table angles "
                             f"({ang[i, 0]:.2f}, {ang[i, 1]:.2f})° outside the kinematics limits (a "
                             f"{list(self.trunnion.a_limits_deg)}, second {list(self.trunnion.second_limits_deg)}) "
                             "in cell.yaml")
        return ang

    def machine(self, points: np.ndarray, axes: np.ndarray,
                prev: tuple[float, float] | None = None) -> np.ndarray:
        """(n, 5) machine positions X Y Z A S for part points and tool axes in the part frame."""
        pts = np.asarray(points, dtype=float)
        ax = np.asarray(axes, dtype=float)
        if self.alignment is not None:
            pts = apply_transform(self.alignment, pts)
            ax = ax @ np.asarray(self.alignment, dtype=float)[:3, :3].T
        ang = self.angles(ax, prev)
        t = self.trunnion
        u1, u2 = t.axes()
        inner, outer = (ang[:, 0], ang[:, 1]) if t.table == "AB" else (ang[:, 1], ang[:, 0])
        c2 = -np.asarray(t.pivot, dtype=float)
        c1 = c2 + np.asarray(t.offset, dtype=float)
        # M = T(c2)·R_outer·T(−c2)·T(c1)·R_inner·T(−c1) (docs/kinematics.md), for every point at once
        q = np.einsum("nij,nj->ni", rotations(u1, inner), pts - c1) + c1
        xyz = np.einsum("nij,nj->ni", rotations(u2, outer), q - c2) + c2
        return np.column_stack([xyz, ang])


def _angles(v: np.ndarray, w: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """Signed angles (deg) turning each v into w about axis (rows projected on its normal plane)."""
    vp = v - np.outer(v @ axis, axis)
    wp = w - np.outer(w @ axis, axis)
    out: np.ndarray = np.degrees(np.arctan2(np.cross(vp, wp) @ axis, np.einsum("ij,ij->i", vp, wp)))
    return out


def rotations(axis: np.ndarray, deg: np.ndarray) -> np.ndarray:
    """(n, 3, 3) right-handed rotations about one unit axis (Rodrigues, vectorised)."""
    k = np.asarray(axis, dtype=float)
    t = np.radians(np.asarray(deg, dtype=float))
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    out: np.ndarray = np.eye(3) + np.sin(t)[:, None, None] * kx + (1.0 - np.cos(t))[:, None, None] * (kx @ kx)
    return out


def inverse_time(points: np.ndarray, speed_mm_min: float | np.ndarray) -> np.ndarray:
    """G93 F per move (1/min): planned speed (one, or one per move) over the part-frame length of each move."""
    seg = np.linalg.norm(np.diff(np.asarray(points, dtype=float), axis=0), axis=1)
    out: np.ndarray = speed_mm_min / np.maximum(seg, 1e-6)
    return out


def _g(v: float) -> str:
    s = f"{v:.3f}"
    return "0.000" if s == "-0.000" else s


def move_line(m: Sequence[float] | np.ndarray, letters: str, feed: float | None = None, verb: str = "G1") -> str:
    """One G-code motion line with the machine's letters (XYZAB or XYZAC)."""
    words = " ".join(f"{c}{_g(v)}" for c, v in zip(letters, m))
    return f"{verb} {words}" + (f" F{feed_word(feed)}" if feed is not None else "")


def feed_word(f: float) -> str:
    """A feed word grbl reads: 5 significant digits, never in exponent form (F1e+05 is F1)."""
    digits = max(0, 4 - int(math.floor(math.log10(abs(f))))) if f > 0 else 0
    return f"{f:.{digits}f}"


# --- where the tool tip is along a machine-linear move (lines5.py fits the lines) ---------------------

_CHECK = (0.25, 0.5, 0.75)   # where a machine-linear move is checked against the planned segment


def tip_path(trunnion: Trunnion, m0: np.ndarray, m1: np.ndarray, ts: Sequence[float] = _CHECK) -> np.ndarray:
    """Where the tool tip is on the part at fractions `ts` of a machine-linear move m0 → m1.

    The machine interpolates every axis linearly; the part point under the tool at machine
    position (x, y, z, a, s) is M(a, s)⁻¹·(x, y, z) (forward kinematics).
    """
    out = np.empty((len(ts), 3))
    for i, t in enumerate(ts):
        m = m0 + (m1 - m0) * t
        mat = trunnion.matrix(float(m[3]), float(m[4]))
        out[i] = mat[:3, :3].T @ (m[:3] - mat[:3, 3])
    return out
