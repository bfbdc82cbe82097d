"""Fits of probed points: plane (SVD, χ², iterative outlier rejection), line, point, 3-2-1 frame.

Pure functions: numpy arrays in, frozen dataclasses out. Lengths in mm.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import stats

from core.errors import InputError

F = NDArray[np.float64]

# Significance for the per-set outlier test and the χ² check. Per set, not per point: with
# Bonferroni's correction the chance of rejecting a good point anywhere in the set is ≤ ALPHA.
ALPHA = 0.01
CHI2_ALPHA = 0.001
MAX_ABS_MM = 1.0e6   # 1 km: beyond any cell


def _points(points: ArrayLike, what: str, minimum: int) -> F:
    p = np.asarray(points, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3:
        raise InputError(f"{what}: expected (n, 3) points, got shape {p.shape}")
    if len(p) < minimum:
        raise InputError(f"{what}: needs at least {minimum} points, got {len(p)}")
    if not np.isfinite(p.sum()):  # one reduction instead of an (n, 3) boolean array
        raise InputError(f"{what}: points contain NaN or infinite values")
    if float(np.abs(p).max()) > MAX_ABS_MM:  # 1e160 squared overflows and the SVD never converges
        raise InputError(f"{what}: a coordinate of {float(np.abs(p).max()):.3g} mm is beyond ±{MAX_ABS_MM:g} mm "
                         "(absurdly scaled: check the units)")
    return p


@dataclass(frozen=True)
class PlaneFit:
    normal: F                    # unit normal, oriented toward the probe
    point: F                     # centroid of the inliers (a point on the plane)
    rms_mm: float                # RMS of the inliers' residuals
    max_residual_mm: float       # largest |residual| among the inliers
    residuals: F                 # signed distance of every input point (outliers included)
    outliers: tuple[int, ...]    # indices of rejected points, in the order they were rejected
    n_points: int
    chi2: float                  # Σ r²/σ² over the inliers (nan without a noise figure)
    dof: int                     # inliers − 3
    chi2_p: float                # P(χ²_dof ≥ chi2): small means the residuals exceed the noise
    chi2_ok: bool                # chi2_p ≥ CHI2_ALPHA (True when no noise figure was given)

    @property
    def inliers(self) -> F:
        mask = np.ones(self.n_points, dtype=bool)
        mask[list(self.outliers)] = False
        return mask

    @property
    def offset(self) -> float:
        """d in n·x = d."""
        return float(self.normal @ self.point)


def _plane_core(p: F) -> tuple[F, F]:
    """Least-squares plane (orthogonal distances): centroid and unit normal, via SVD of the scatter."""
    n = len(p)
    c = (np.ones(n) @ p) / n  # BLAS; several times faster than p.mean(axis=0)
    # The 3×3 scatter matrix has the same right singular vectors as the centred points, and is
    # far cheaper than an SVD of an (n, 3) array for 10⁵ points.
    if n < 20_000:
        q = p - c
        s = q.T @ q
    else:
        # Σppᵀ − n·ccᵀ skips an (n, 3) temporary; shifting by the first point first keeps the
        # cancellation small (coordinates of hundreds of mm, residuals of µm).
        p0 = p[0]
        g = p.T @ p - np.outer(p0, c * n) - np.outer(c * n, p0) + n * np.outer(p0, p0)
        d = c - p0
        s = g - n * np.outer(d, d)
    _, _, vt = np.linalg.svd(s)
    return c, vt[2]


def fit_plane(points: ArrayLike, *, toward: ArrayLike = (0.0, 0.0, 1.0), noise_mm: float | None = None,
              reject: bool = True, alpha: float = ALPHA, max_outliers: int | None = None) -> PlaneFit:
    """Fit a plane; normal oriented toward the probe (`toward` = the direction the probe came from).

    Outliers are rejected one at a time: fit, take the point with the largest |residual|, drop
    it if it exceeds the per-set threshold (the two-sided normal quantile at alpha/n, in units
    of σ√(1 − leverage)), refit, repeat. σ is `noise_mm` when given (the probe's configured
    noise); without it the test is the externally studentised residual against Student's t.
    At least 4 points are kept.
    """
    p = _points(points, "plane fit", 3)
    n = len(p)
    toward_v = np.asarray(toward, dtype=float)
    keep = np.ones(n, dtype=bool)
    outliers: list[int] = []
    limit = max(0, n - 4) if max_outliers is None else min(max_outliers, max(0, n - 4))
    while True:
        c, nrm = _plane_core(p[keep] if outliers else p)
        res_all = p @ nrm - c @ nrm
        if not reject or len(outliers) >= limit:
            break
        idx = np.flatnonzero(keep) if outliers else np.arange(n)
        r = res_all[idx] if outliers else res_all  # no fancy-index copy in the common case
        m = len(r)
        # Standardise by the residual's own variance σ²(1 − h_ii): few points, high leverage.
        if m < 2000:
            q = p[idx] - c
            _, sv, vt = np.linalg.svd(q, full_matrices=False)
            u = q @ vt[:2].T / np.where(sv[:2] > 0, sv[:2], 1.0)
            lev = np.clip(1.0 / m + np.sum(u * u, axis=1), 0.0, 1.0 - 1e-6)
            score = np.abs(r) / np.sqrt(1.0 - lev)
        else:
            lev = np.zeros(m)  # h ~ 3/m: negligible
            score = np.abs(r)
        worst = int(np.argmax(score))
        if noise_mm is not None and noise_mm > 0:
            z = score[worst] / float(noise_mm)
            thresh = float(stats.norm.isf(alpha / (2.0 * m)))
        else:
            # No noise figure: externally studentised residual. σ comes from the fit without
            # the candidate (an outlier must not inflate its own yardstick); t with m − 4 dof.
            if m - 4 < 2:
                break
            others = np.delete(np.arange(m), worst)
            c2, n2 = _plane_core(p[idx[others]])
            r2 = (p[idx[others]] - c2) @ n2
            s2 = float(np.sqrt(np.sum(r2**2) / (m - 4)))
            d = float((p[idx[worst]] - c2) @ n2)
            if s2 <= 0:
                break
            z = abs(d) * np.sqrt(1.0 - lev[worst]) / s2  # var of a deleted residual: σ²/(1 − h)
            thresh = float(stats.t.isf(alpha / (2.0 * m), m - 4))
        if z <= thresh:
            break
        keep[idx[worst]] = False
        outliers.append(int(idx[worst]))
    if nrm @ toward_v < 0:
        nrm = -nrm
        res_all = -res_all
    r_in = res_all[keep] if outliers else res_all
    dof = int(keep.sum()) - 3
    if noise_mm is not None and noise_mm > 0 and dof > 0:
        chi2 = float(np.sum((r_in / noise_mm) ** 2))
        chi2_p = float(stats.chi2.sf(chi2, dof))
        ok = chi2_p >= CHI2_ALPHA
    else:
        chi2, chi2_p, ok = float("nan"), float("nan"), True
    return PlaneFit(normal=nrm, point=c, rms_mm=float(np.sqrt(np.mean(r_in**2))),
                    max_residual_mm=float(np.max(np.abs(r_in))), residuals=res_all,
                    outliers=tuple(outliers), n_points=n, chi2=chi2, dof=dof, chi2_p=chi2_p, chi2_ok=ok)


@dataclass(frozen=True)
class LineFit:
    direction: F                 # unit direction (sign: along the order of the points)
    point: F                     # centroid
    rms_mm: float                # RMS of the perpendicular distances
    max_residual_mm: float


def fit_line(points: ArrayLike) -> LineFit:
    """Least-squares 3-D line through the points (principal direction of the centred points)."""
    p = _points(points, "line fit", 2)
    c = p.mean(axis=0)
    q = p - c
    _, _, vt = np.linalg.svd(q, full_matrices=False)
    d = vt[0]
    if d @ (p[-1] - p[0]) < 0:
        d = -d
    perp = q - np.outer(q @ d, d)
    dist = np.linalg.norm(perp, axis=1)
    return LineFit(direction=d, point=c, rms_mm=float(np.sqrt(np.mean(dist**2))), max_residual_mm=float(dist.max()))


@dataclass(frozen=True)
class PointFit:
    point: F                     # mean of the samples
    spread_mm: float             # largest distance between two samples
    std_mm: float                # RMS distance from the mean


def fit_point(samples: ArrayLike) -> PointFit:
    """One touch point from repeated samples."""
    p = _points(samples, "point fit", 1)
    c = p.mean(axis=0)
    diff = p[:, None, :] - p[None, :, :]
    spread = float(np.sqrt((diff**2).sum(-1)).max()) if len(p) > 1 else 0.0
    return PointFit(point=c, spread_mm=spread, std_mm=float(np.sqrt(np.mean(np.sum((p - c) ** 2, axis=1)))))


@dataclass(frozen=True)
class Frame321:
    """Part frame from 3-2-1 alignment: z normal of the primary, x along the secondary line."""

    rotation: F                  # 3×3, columns = part x, y, z axes in machine coordinates
    origin: F                    # corner where the three datum planes meet
    matrix: F                    # 4×4 part → machine


def frame_321(primary: ArrayLike, secondary: ArrayLike, tertiary: ArrayLike, *,
              primary_toward: ArrayLike = (0.0, 0.0, 1.0)) -> Frame321:
    """3-2-1: ≥3 points on the primary face, ≥2 on the secondary, ≥1 on the tertiary.

    The primary normal is the part z axis; the secondary line, projected on the primary plane,
    the part x axis; the origin is where the primary, the secondary (through the line,
    perpendicular to the primary) and the tertiary (through the point, perpendicular to both)
    planes meet.
    """
    pl = fit_plane(primary, toward=primary_toward, reject=False)
    sec = _points(secondary, "3-2-1 secondary", 2)
    ter = _points(np.atleast_2d(tertiary), "3-2-1 tertiary", 1)
    z = pl.normal
    ln = fit_line(sec)
    x = ln.direction - z * (ln.direction @ z)
    nx = np.linalg.norm(x)
    if nx < 1e-9:
        raise InputError("3-2-1: the secondary points lie along the primary normal; probe them along the face")
    x /= nx
    y = np.cross(z, x)
    tp = ter.mean(axis=0)
    # Solve for the corner o: z·o = z·c_primary, y·o = y·c_line, x·o = x·tertiary.
    a = np.vstack([z, y, x])
    b = np.array([z @ pl.point, y @ ln.point, x @ tp])
    o = np.linalg.solve(a, b)
    r = np.column_stack([x, y, z])
    m = np.eye(4)
    m[:3, :3] = r
    m[:3, 3] = o
    return Frame321(rotation=r, origin=o, matrix=m)


def grid_points(center: ArrayLike, size: ArrayLike, counts: tuple[int, int]) -> F:
    """A rectangular grid of (x, y) probe positions around a centre (used by the probe cycles)."""
    cx, cy = np.asarray(center, dtype=float)[:2]
    sx, sy = np.asarray(size, dtype=float)[:2]
    nx, ny = counts
    xs = np.linspace(cx - sx / 2, cx + sx / 2, nx) if nx > 1 else np.array([cx])
    ys = np.linspace(cy - sy / 2, cy + sy / 2, ny) if ny > 1 else np.array([cy])
    gx, gy = np.meshgrid(xs, ys, indexing="xy")
    return np.column_stack([gx.ravel(), gy.ravel()])


@dataclass(frozen=True)
class Datum:
    """A CAD datum face: its outward unit normal and a point on it, in CAD coordinates."""

    normal: tuple[float, float, float]
    point: tuple[float, float, float]


def cad_transform_321(top_normal: ArrayLike, top_point: ArrayLike, side_normal: ArrayLike, side_point: ArrayLike,
                      tertiary_point: ArrayLike, *, cad_top: Datum, cad_side: Datum, cad_tertiary: Datum) -> F:
    """4×4 CAD → machine from a 3-2-1 set: the fitted top plane, the side face, one tertiary touch.

    Rotation: the CAD (top normal, side normal ⊥ top) frame onto the measured one (the side
    normal is made exactly perpendicular to the top, which the top defines best). Translation:
    each CAD datum face must pass through its measured point.
    """
    def frame(z_in: ArrayLike, x_in: ArrayLike) -> F:
        z: F = np.asarray(z_in, dtype=float)
        z = z / np.linalg.norm(z)
        x: F = np.asarray(x_in, dtype=float)
        x = x - z * (x @ z)
        nx = np.linalg.norm(x)
        if nx < 1e-9:
            raise InputError("3-2-1: the side face is parallel to the top face; probe a face at an angle to it")
        x = x / nx
        return np.column_stack([x, np.cross(z, x), z])

    r = frame(top_normal, side_normal) @ frame(cad_top.normal, cad_side.normal).T
    rows, rhs = [], []
    for datum, q in ((cad_top, top_point), (cad_side, side_point), (cad_tertiary, tertiary_point)):
        n = r @ np.asarray(datum.normal, dtype=float)
        rows.append(n)
        rhs.append(n @ (np.asarray(q, dtype=float) - r @ np.asarray(datum.point, dtype=float)))
    a = np.vstack(rows)
    if abs(np.linalg.det(a)) < 1e-9:
        raise InputError("3-2-1: the three datum faces do not fix the position (two are parallel)")
    t = np.linalg.solve(a, np.array(rhs))
    m = np.eye(4)
    m[:3, :3] = r
    m[:3, 3] = t
    return m
