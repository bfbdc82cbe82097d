"""Bead cross-section profiles and the multi-bead overlapping model of Ding et al. (2015).

Profiles (Table 1 of the paper, x across the bead, y above the substrate, mm)::

    parabola  y = a·x² + c          h = c        w = 2·sqrt(−c/a)      A = (4c/3)·sqrt(−c/a)
    cosine    y = a·cos(b·x)        h = a        w = π/b               A = 2a/b
    arc       y = sqrt(a² − x²) + b h = a + b    w = 2·sqrt(a² − b²)   A = a²·acos(−b/a) + b·sqrt(a² − b²)

(The paper's Table 1 prints the arc height as ``a − b`` and the arc area without the ``a²``
and with the wrong sign on the second term; with its own Table 2 values — b < 0 — only the
forms above reproduce the fitted widths and the wire volume. See docs/process-models.md.)

Overlap: the tangent overlapping model (TOM) gives a critical centre distance d* at which the
overlapping area AED equals the critical valley BEC, the root of ``f(d) = S_BEC − S_AED`` in
``(w/2, w)``; for a parabola ``d* = 0.7378·w`` (the paper's 0.738 w). It is solved here
numerically from the geometry (tangent line from B on bead 1 to bead 2, areas integrated in
closed form), which for the parabola reproduces the paper's closed-form f(d) (eq. 7) exactly.
The flat-top model (FOM) gives ``A/(w·h)·w``: 2/3·w for the parabola.

Pure: no I/O, no clocks; caches only deterministic results.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any, ClassVar, Protocol

import numpy as np

from core.errors import InputError
from planner import fit_guards
from planner.roots import brentq

__all__ = [
    "Parabola",
    "Cosine",
    "Arc",
    "Profile",
    "PROFILES",
    "OVERLAP_MODELS",
    "DING_ARC_ASPECT",
    "profile_from_width_height",
    "area_factor",
    "wire_area_mm2",
    "ProfileFit",
    "fit_parabola",
    "fit_cosine",
    "fit_arc",
    "fit_profiles",
    "tangent_f",
    "tangent_f_paper",
    "critical_ratio",
    "flat_top_ratio",
    "step_over",
]

PROFILES: tuple[str, ...] = ("parabola", "cosine", "arc")
# A measured profile is fitted on the contiguous points above this fraction of its peak.
SUBSTRATE_FRACTION = 0.05
OVERLAP_MODELS: tuple[str, ...] = ("tangent", "flat_top")


# --------------------------------------------------------------------------------------------
# Profiles
# --------------------------------------------------------------------------------------------


class Profile(Protocol):
    name: ClassVar[str]
    centre_mm: float

    @property
    def width_mm(self) -> float: ...
    @property
    def height_mm(self) -> float: ...
    @property
    def area_mm2(self) -> float: ...
    def y(self, x: Any) -> Any: ...
    def slope(self, x: Any) -> Any: ...
    def integral(self, lo: float, hi: float) -> float: ...
    def params(self) -> dict[str, float]: ...


class _Base:
    """Shared behaviour: clipping to the bead (zero outside the toes) and integration."""

    centre_mm: float

    def _u(self, x: Any) -> np.ndarray:
        return np.asarray(x, dtype=np.float64) - self.centre_mm

    def y(self, x: Any) -> Any:
        """Height above the substrate at x; 0 outside the bead's toes."""
        u = self._u(x)
        half = self.width_mm / 2.0  # type: ignore[attr-defined]
        inside = np.abs(u) <= half
        v = np.where(inside, self._raw(np.clip(u, -half, half)), 0.0)  # type: ignore[attr-defined]
        v = np.maximum(v, 0.0)
        return float(v) if v.ndim == 0 else v

    def integral(self, lo: float, hi: float) -> float:
        """∫ y dx over [lo, hi] (the bead clipped to its toes), in closed form."""
        half = self.width_mm / 2.0  # type: ignore[attr-defined]
        a = min(max(lo - self.centre_mm, -half), half)
        b = min(max(hi - self.centre_mm, -half), half)
        return float(self._antideriv(b) - self._antideriv(a))  # type: ignore[attr-defined]

    def to_dict(self) -> dict[str, Any]:
        return {
            "width_mm": self.width_mm,  # type: ignore[attr-defined]
            "height_mm": self.height_mm,  # type: ignore[attr-defined]
            "area_mm2": self.area_mm2,  # type: ignore[attr-defined]
            "centre_mm": self.centre_mm,
            "params": self.params(),  # type: ignore[attr-defined]
        }


@dataclass(frozen=True, slots=True)
class Parabola(_Base):
    """y = a·(x − x0)² + c, a < 0 < c."""

    a: float
    c: float
    centre_mm: float = 0.0
    name: ClassVar[str] = "parabola"

    def __post_init__(self) -> None:
        if not (math.isfinite(self.a) and math.isfinite(self.c) and self.a < 0.0 < self.c):
            raise InputError(f"parabola needs a < 0 < c (got a={self.a:g}, c={self.c:g}); not a bead shape")

    @classmethod
    def from_width_height(cls, width_mm: float, height_mm: float, centre_mm: float = 0.0) -> "Parabola":
        return cls(a=-4.0 * height_mm / width_mm**2, c=height_mm, centre_mm=centre_mm)

    @property
    def height_mm(self) -> float:
        return self.c

    @property
    def width_mm(self) -> float:
        return 2.0 * math.sqrt(-self.c / self.a)

    @property
    def area_mm2(self) -> float:
        return 4.0 * self.c / 3.0 * math.sqrt(-self.c / self.a)

    def _raw(self, u: np.ndarray) -> np.ndarray:
        return self.a * u * u + self.c

    def slope(self, x: Any) -> Any:
        return 2.0 * self.a * self._u(x)

    def _antideriv(self, u: float) -> float:
        return self.a * u**3 / 3.0 + self.c * u

    def params(self) -> dict[str, float]:
        return {"a": self.a, "c": self.c}


@dataclass(frozen=True, slots=True)
class Cosine(_Base):
    """y = a·cos(b·(x − x0)), a > 0, b > 0 (one arch: |b·(x − x0)| ≤ π/2)."""

    a: float
    b: float
    centre_mm: float = 0.0
    name: ClassVar[str] = "cosine"

    def __post_init__(self) -> None:
        if not (math.isfinite(self.a) and math.isfinite(self.b) and self.a > 0.0 and self.b > 0.0):
            raise InputError(f"cosine needs a > 0 and b > 0 (got a={self.a:g}, b={self.b:g}); not a bead shape")

    @classmethod
    def from_width_height(cls, width_mm: float, height_mm: float, centre_mm: float = 0.0) -> "Cosine":
        return cls(a=height_mm, b=math.pi / width_mm, centre_mm=centre_mm)

    @property
    def height_mm(self) -> float:
        return self.a

    @property
    def width_mm(self) -> float:
        return math.pi / self.b

    @property
    def area_mm2(self) -> float:
        return 2.0 * self.a / self.b

    def _raw(self, u: np.ndarray) -> np.ndarray:
        return self.a * np.cos(self.b * u)

    def slope(self, x: Any) -> Any:
        return -self.a * self.b * np.sin(self.b * self._u(x))

    def _antideriv(self, u: float) -> float:
        return self.a / self.b * math.sin(self.b * u)

    def params(self) -> dict[str, float]:
        return {"a": self.a, "b": self.b}


@dataclass(frozen=True, slots=True)
class Arc(_Base):
    """y = sqrt(a² − (x − x0)²) + b: a circle of radius a centred b below the substrate (b ≤ 0)."""

    a: float
    b: float
    centre_mm: float = 0.0
    name: ClassVar[str] = "arc"

    def __post_init__(self) -> None:
        if not (math.isfinite(self.a) and math.isfinite(self.b) and self.a > 0.0 and -self.a < self.b <= 0.0):
            raise InputError(
                f"arc needs a > 0 and −a < b ≤ 0 (got a={self.a:g}, b={self.b:g}); "
                "a bead taller than half its width is not a circle segment"
            )

    @classmethod
    def from_width_height(cls, width_mm: float, height_mm: float, centre_mm: float = 0.0) -> "Arc":
        if not 0.0 < height_mm <= width_mm / 2.0:
            raise InputError(
                f"an arc bead needs 0 < height ≤ width/2 (got width {width_mm:g} mm, height {height_mm:g} mm)"
            )
        r = (height_mm**2 + (width_mm / 2.0) ** 2) / (2.0 * height_mm)  # chord w, sagitta h
        return cls(a=r, b=min(height_mm - r, 0.0), centre_mm=centre_mm)

    @property
    def height_mm(self) -> float:
        return self.a + self.b

    @property
    def width_mm(self) -> float:
        return 2.0 * math.sqrt(self.a**2 - self.b**2)

    @property
    def area_mm2(self) -> float:
        return self.a**2 * math.acos(-self.b / self.a) + self.b * math.sqrt(self.a**2 - self.b**2)

    def _raw(self, u: np.ndarray) -> np.ndarray:
        return np.sqrt(np.maximum(self.a**2 - u * u, 0.0)) + self.b

    def slope(self, x: Any) -> Any:
        u = self._u(x)
        return -u / np.sqrt(np.maximum(self.a**2 - u * u, 1e-300))

    def _antideriv(self, u: float) -> float:
        u = min(max(u, -self.a), self.a)
        return 0.5 * (u * math.sqrt(max(self.a**2 - u * u, 0.0)) + self.a**2 * math.asin(u / self.a)) + self.b * u

    def params(self) -> dict[str, float]:
        return {"a": self.a, "b": self.b}


_CLASSES: dict[str, type] = {"parabola": Parabola, "cosine": Cosine, "arc": Arc}

# Mean height/width of the arc fits of Ding 2015, Table 2 (h = a + b, w = 2·sqrt(a² − b²)):
# the arc's shape, unlike the parabola's and the cosine's, changes with its aspect ratio, so
# its critical distance needs one. Used when the caller gives none.
_DING_ARC_ROWS = (
    (7.010, -3.720), (6.216, -3.251), (5.715, -3.042), (5.220, -2.727),
    (4.941, -2.571), (4.866, -2.717), (4.299, -2.194), (4.052, -2.034),
)
DING_ARC_ASPECT: float = float(np.mean([(a + b) / (2.0 * math.sqrt(a * a - b * b)) for a, b in _DING_ARC_ROWS]))


def _check_profile(profile: str) -> str:
    if profile not in _CLASSES:
        raise InputError(f"unknown bead profile '{profile}'; choose one of {', '.join(PROFILES)}")
    return profile


def profile_from_width_height(profile: str, width_mm: float, height_mm: float, centre_mm: float = 0.0) -> Profile:
    """The profile of this kind with this width and height (mm)."""
    _check_profile(profile)
    for name, v in (("width", width_mm), ("height", height_mm)):
        if not (math.isfinite(v) and v > 0.0):
            raise InputError(f"bead {name} must be a positive, finite number of mm (got {v!r})")
    return _CLASSES[profile].from_width_height(float(width_mm), float(height_mm), centre_mm)


def area_factor(profile: str = "parabola", aspect: float | None = None) -> float:
    """A / (w·h): 2/3 for the parabola, 2/π for the cosine, between 2/3 and π/4 for the arc."""
    _check_profile(profile)
    asp = _aspect(profile, aspect)
    p = profile_from_width_height(profile, 1.0, asp)
    return p.area_mm2 / (p.width_mm * p.height_mm)


def wire_area_mm2(wire_diameter_mm: float, wfs_m_min: float, speed_mm_min: float) -> float:
    """Deposited cross-section from the wire volume, A = π·λ·D²/4 with λ = WFS / travel speed."""
    lam = wfs_m_min * 1000.0 / speed_mm_min
    return math.pi * lam * wire_diameter_mm**2 / 4.0


# --------------------------------------------------------------------------------------------
# Fits to a measured profile
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class ProfileFit:
    """A fitted profile and its coefficient of determination on the fitted points."""

    profile: Any
    r2: float
    n_points: int
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def width_mm(self) -> float:
        return self.profile.width_mm

    @property
    def height_mm(self) -> float:
        return self.profile.height_mm

    @property
    def area_mm2(self) -> float:
        return self.profile.area_mm2

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
    from scipy.optimize import least_squares as ls

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
    return ProfileFit(prof, _r2(ya, prof._raw(xa - prof.centre_mm)), int(xa.size))


def fit_cosine(x: Any, y: Any, *, min_height_mm: float | None = None) -> ProfileFit:
    """Least-squares y = a·cos(b·(x − x0)) to the points above the substrate."""
    xa, ya = _prepare(x, y, min_height_mm)
    p0 = fit_parabola(xa, ya, min_height_mm=-math.inf).profile
    span = float(np.ptp(xa))

    def res(p: np.ndarray) -> np.ndarray:
        return p[0] * np.cos(p[1] * (xa - p[2])) - ya

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
        return np.sqrt(np.maximum(p[0] ** 2 - (xa - p[2]) ** 2, 0.0)) + p[1] - ya

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


# --------------------------------------------------------------------------------------------
# Tangent overlapping model
# --------------------------------------------------------------------------------------------


def _aspect(profile: str, aspect: float | None) -> float:
    """Height/width used for the normalised bead (irrelevant for the parabola and cosine)."""
    if profile != "arc":
        return 0.25 if aspect is None else float(aspect)
    asp = DING_ARC_ASPECT if aspect is None else float(aspect)
    if not (math.isfinite(asp) and 0.0 < asp <= 0.5):
        raise InputError(f"an arc bead needs 0 < height/width ≤ 0.5 (got {asp:g})")
    return asp


def tangent_f(d_over_w: float, profile: str = "parabola", aspect: float | None = None) -> float:
    """f(d) = S_BEC − S_AED for two beads of width 1 and height ``aspect`` at centre distance d.

    Bead 1 is centred at 0, bead 2 at d. A = (x1, 0) is the left toe of bead 2 (x1 = d − 1/2),
    B = (x1, y1) the point of bead 1 above it, C = (x2, y2) the point where the line from B
    touches bead 2. The overlap AED cancels out of S_BEC − S_AED (the paper's eq. 6), leaving
    trapezoid ABCF − area under bead 1 over [x1, 1/2] − area under bead 2 over [x1, x2].
    Defined for 1/2 ≤ d < 1.
    """
    _check_profile(profile)
    d = float(d_over_w)
    if not 0.5 <= d < 1.0:
        raise InputError(f"centre distance d/w must be in [0.5, 1) (got {d:g})")
    b1 = profile_from_width_height(profile, 1.0, _aspect(profile, aspect), 0.0)
    b2 = profile_from_width_height(profile, 1.0, _aspect(profile, aspect), d)
    x1 = d - 0.5
    y1 = float(b1.y(x1))

    def tangency(x2: float) -> float:
        return float(b2.slope(x2)) * (x2 - x1) - (float(b2.y(x2)) - y1)

    lo = x1 + 1e-12
    x2 = brentq(tangency, lo, d, xtol=1e-15, rtol=1e-15, maxiter=200) if tangency(lo) > 0.0 else lo
    y2 = float(b2.y(x2))
    trapezoid = 0.5 * (y1 + y2) * (x2 - x1)
    return trapezoid - b1.integral(x1, 0.5) - b2.integral(x1, x2)


def tangent_f_paper(d: float, w: float, a: float) -> float:
    """The paper's closed form for the parabola (eq. 7): f(d) = S_BEC − S_AED, a = −4h/w²."""
    return (
        a * d**3 / 3.0
        + a * w**3 / 6.0
        - a * w * d**2 / 2.0
        - a * d * (w - d) / 3.0 * math.sqrt(w * d - d * d)
    )


@lru_cache(maxsize=64)
def _critical_ratio(profile: str, aspect: float) -> float:
    grid = np.linspace(0.5 + 1e-6, 1.0 - 1e-6, 41)
    vals = [tangent_f(float(g), profile, aspect) for g in grid]
    for (g0, v0), (g1, v1) in zip(zip(grid, vals), zip(grid[1:], vals[1:])):
        if v0 < 0.0 <= v1:
            return float(brentq(lambda t: tangent_f(t, profile, aspect), float(g0), float(g1), xtol=1e-14, rtol=1e-14))
    raise InputError(f"no critical centre distance in (w/2, w) for the {profile} profile (aspect {aspect:g})")


def critical_ratio(profile: str = "parabola", aspect: float | None = None) -> float:
    """d*/w of the tangent overlapping model, the root of f(d) in (w/2, w); cached.

    Parabola 0.7378 (the paper's 0.738 w). The parabola's and the cosine's ratios do not depend
    on the bead's height/width (an affine stretch keeps tangency and area ratios); the arc's
    does, so ``aspect`` (h/w) applies to the arc only, by default :data:`DING_ARC_ASPECT`.
    """
    _check_profile(profile)
    asp = _aspect(profile, aspect) if profile == "arc" else 0.25
    return _critical_ratio(profile, round(asp, 12))


def flat_top_ratio(profile: str = "parabola", aspect: float | None = None) -> float:
    """d/w of the flat-top overlapping model: overlap = valley, i.e. d = A/h = area_factor·w."""
    return area_factor(profile, aspect)


def step_over(
    width_mm: float,
    overlap_model: str = "tangent",
    profile: str = "parabola",
    *,
    height_mm: float | None = None,
) -> float:
    """Centre distance (mm) between adjacent beads of this width.

    ``tangent``: d* = critical_ratio(profile)·w (0.738·w for the parabola);
    ``flat_top``: A/(w·h)·w (2/3·w for the parabola). ``height_mm`` matters for the arc only
    (its shape depends on h/w).
    """
    if not (isinstance(width_mm, (int, float)) and math.isfinite(width_mm) and width_mm > 0.0):
        raise InputError(f"bead width must be a positive, finite number of mm (got {width_mm!r})")
    _check_profile(profile)
    aspect = None if height_mm is None else float(height_mm) / float(width_mm)
    if overlap_model == "tangent":
        return critical_ratio(profile, aspect) * float(width_mm)
    if overlap_model == "flat_top":
        return flat_top_ratio(profile, aspect) * float(width_mm)
    raise InputError(f"unknown overlap model '{overlap_model}'; choose one of {', '.join(OVERLAP_MODELS)}")
