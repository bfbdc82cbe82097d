"""Fits of the bead profiles (planner.profiles) to a measured cross-section, by least squares
(Ding 2015 fits its Table 2 the same way); each with its coefficient of determination.

Pure: no I/O, no clocks. scipy is imported on first use (`cell plan` never fits a profile).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from core.errors import InputError
from planner import fit_guards
from planner.profiles import SUBSTRATE_FRACTION, Arc, Cosine, Parabola




@dataclass(frozen=True, slots=True)
class ProfileFit:
    """A fitted profile and its coefficient of determination on the fitted points."""

    profile: Any
    r2: float
    n_points: int
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def width_mm(self) -> float:
        return float(self.profile.width_mm)

    @property
    def height_mm(self) -> float:
        return float(self.profile.height_mm)

    @property
    def area_mm2(self) -> float:
        return float(self.profile.area_mm2)

    def to_dict(self) -> dict[str, Any]:
        d = self.profile.to_dict()
        return {
            "width_mm": d["width_mm"],
            "height_mm": d["height_mm"],
            "area_mm2": d["area_mm2"],
            "r2": self.r2,
            "centre_mm": d["centre_mm"],
            "params": d["params"],
            "n_points": self.n_points,
        }


def least_squares(*args: Any, **kwargs: Any) -> Any:
    """scipy's least squares, imported on first use: `cell plan` never fits a profile."""
    from scipy.optimize import least_squares as ls  # lazy: `cell plan` never fits (start-up time)

    return ls(*args, **kwargs)


def _r2(y: np.ndarray, pred: np.ndarray) -> float:
    ss_res = float(np.sum((y - pred) ** 2))
    ss_tot = float(np.sum((y - y.mean()) ** 2))
    return 1.0 - ss_res / ss_tot if ss_tot > 0 else (1.0 if ss_res == 0 else 0.0)


def _prepare(x: Any, y: Any, min_height_mm: float | None) -> tuple[np.ndarray, np.ndarray]:
    xa = np.asarray(x, dtype=np.float64).reshape(-1)
    ya = np.asarray(y, dtype=np.float64).reshape(-1)
    if xa.shape != ya.shape:
        raise InputError(f"profile has {xa.size} x values but {ya.size} y values")
    if not (np.all(np.isfinite(xa)) and np.all(np.isfinite(ya))):
        raise InputError("profile contains a non-finite x or y value")
    if xa.size == 0 or float(ya.max(initial=0.0)) <= 0.0:
        raise InputError("profile has no point above the substrate (y > 0); nothing to fit")
    order = np.argsort(xa, kind="stable")
    xa, ya = xa[order], ya[order]
    thr = SUBSTRATE_FRACTION * float(ya.max()) if min_height_mm is None else float(min_height_mm)
    # The bead: the contiguous run of points above the threshold around the peak. Substrate
    # points (and noise spikes on the substrate) beyond the toes are not part of the profile.
    peak = int(np.argmax(ya))
    lo = peak
    while lo > 0 and ya[lo - 1] > thr:
        lo -= 1
    hi = peak
    while hi < ya.size - 1 and ya[hi + 1] > thr:
        hi += 1
    xa, ya = xa[lo : hi + 1], ya[lo : hi + 1]
    if xa.size < 5:
        raise InputError(
            f"profile has {xa.size} points on the bead (contiguous, y > {thr:.3g} mm); a fit needs at least 5"
        )
    if np.ptp(xa) <= 0.0:
        raise InputError("profile points on the bead all have the same x; nothing to fit")
    return xa, ya


def fit_parabola(x: Any, y: Any, *, min_height_mm: float | None = None) -> ProfileFit:
    """Least-squares y = a·(x − x0)² + c to the points above the substrate (linear in a, b, c)."""
    xa, ya = _prepare(x, y, min_height_mm)
    # Centre and scale x for conditioning, then A·u² + B·u + C.
    m, s = float(xa.mean()), float(np.ptp(xa)) or 1.0
    u = (xa - m) / s
    A, B, C = np.linalg.lstsq(np.column_stack([u * u, u, np.ones_like(u)]), ya, rcond=None)[0]
    if not A < 0.0:
        raise InputError("the measured profile is not convex upward (fitted parabola opens upward); not a bead")
    a = A / s**2
    u0 = -B / (2.0 * A)
    c = C - B * B / (4.0 * A)
    prof = Parabola(a=float(a), c=float(c), centre_mm=float(m + u0 * s))
    return ProfileFit(prof, _r2(ya, prof.raw(xa - prof.centre_mm)), int(xa.size))


def fit_cosine(x: Any, y: Any, *, min_height_mm: float | None = None) -> ProfileFit:
    """Least-squares y = a·cos(b·(x − x0)) to the points above the substrate."""
    xa, ya = _prepare(x, y, min_height_mm)
    p0 = fit_parabola(xa, ya, min_height_mm=-math.inf).profile
    span = float(np.ptp(xa))

    def res(p: np.ndarray) -> np.ndarray:
        return np.asarray(p[0] * np.cos(p[1] * (xa - p[2])) - ya)

    sol = least_squares(
        res,
        x0=[p0.height_mm, math.pi / p0.width_mm, p0.centre_mm],
        bounds=([1e-9, 1e-9, xa.min() - span], [np.inf, np.inf, xa.max() + span]),
        x_scale="jac",
        method="trf",
    )
    prof = Cosine(a=float(sol.x[0]), b=float(sol.x[1]), centre_mm=float(sol.x[2]))
    return ProfileFit(prof, _r2(ya, res(sol.x) + ya), int(xa.size))


def fit_arc(x: Any, y: Any, *, min_height_mm: float | None = None) -> ProfileFit:
    """Least-squares y = sqrt(a² − (x − x0)²) + b (b ≤ 0) to the points above the substrate."""
    xa, ya = _prepare(x, y, min_height_mm)
    # Algebraic (Kåsa) circle fit for the start: x² + y² + D·x + E·y + F = 0.
    M = np.column_stack([xa, ya, np.ones_like(xa)])
    D, E, F = np.linalg.lstsq(M, -(xa * xa + ya * ya), rcond=None)[0]
    x0, yc = -D / 2.0, -E / 2.0
    r2 = x0 * x0 + yc * yc - F
    half = float(np.max(np.abs(xa - x0)))
    r = math.sqrt(r2) if r2 > 0 and math.sqrt(r2) > half else half * 1.5
    b0 = min(float(yc), -1e-6)
    span = float(np.ptp(xa))

    def res(p: np.ndarray) -> np.ndarray:
        return np.asarray(np.sqrt(np.maximum(p[0] ** 2 - (xa - p[2]) ** 2, 0.0)) + p[1] - ya)

    sol = least_squares(
        res,
        x0=[max(r, -b0 + 1e-6), b0, float(x0)],
        bounds=([1e-9, -np.inf, xa.min() - span], [np.inf, 0.0, xa.max() + span]),
        x_scale="jac",
        method="trf",
    )
    a, b, xc = (float(v) for v in sol.x)
    if not -a < b:
        raise InputError("the measured profile does not fit a circle segment above the substrate")
    prof = Arc(a=a, b=b, centre_mm=xc)
    return ProfileFit(prof, _r2(ya, res(sol.x) + ya), int(xa.size))


def fit_profiles(x: Any, y: Any, *, min_height_mm: float | None = None) -> dict[str, ProfileFit]:
    """All three fits of one measured profile: {"parabola": …, "cosine": …, "arc": …}."""
    xa = fit_guards.finite_scaled(x, "profile x").reshape(-1)
    ya = fit_guards.finite_scaled(y, "profile y").reshape(-1)
    out = {
        "parabola": fit_parabola(xa, ya, min_height_mm=min_height_mm),
        "cosine": fit_cosine(xa, ya, min_height_mm=min_height_mm),
        "arc": fit_arc(xa, ya, min_height_mm=min_height_mm),
    }
    fit_guards.profile_not_flat(xa, ya)
    for name, f in out.items():
        fit_guards.plausible_profile(name, f.width_mm, f.height_mm, f.area_mm2, xa)
    return out
