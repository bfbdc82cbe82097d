"""The multi-bead overlapping model of Ding et al. (2015); the bead profiles live in
planner.profiles and their fits in planner.bead_fit (re-exported here, the module's old home).

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
from functools import lru_cache

import numpy as np

from core.errors import InputError
from planner.bead_fit import ProfileFit, fit_arc, fit_cosine, fit_parabola, fit_profiles
from planner.profiles import (
    DING_ARC_ASPECT, PROFILES, Arc, Cosine, Parabola, Profile, profile_aspect, check_profile, area_factor,
    profile_from_width_height, wire_area_mm2,
)
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

OVERLAP_MODELS: tuple[str, ...] = ("tangent", "flat_top")


# --------------------------------------------------------------------------------------------
# Tangent overlapping model
# --------------------------------------------------------------------------------------------


def tangent_f(d_over_w: float, profile: str = "parabola", aspect: float | None = None) -> float:
    """f(d) = S_BEC − S_AED for two beads of width 1 and height ``aspect`` at centre distance d.

    Bead 1 is centred at 0, bead 2 at d. A = (x1, 0) is the left toe of bead 2 (x1 = d − 1/2),
    B = (x1, y1) the point of bead 1 above it, C = (x2, y2) the point where the line from B
    touches bead 2. The overlap AED cancels out of S_BEC − S_AED (the paper's eq. 6), leaving
    trapezoid ABCF − area under bead 1 over [x1, 1/2] − area under bead 2 over [x1, x2].
    Defined for 1/2 ≤ d < 1.
    """
    check_profile(profile)
    d = float(d_over_w)
    if not 0.5 <= d < 1.0:
        raise InputError(f"centre distance d/w must be in [0.5, 1) (got {d:g})")
    b1 = profile_from_width_height(profile, 1.0, profile_aspect(profile, aspect), 0.0)
    b2 = profile_from_width_height(profile, 1.0, profile_aspect(profile, aspect), d)
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


# The roots of the aspect-free profiles, solved by _critical_ratio once and kept (a test checks
# they still agree): a plan does no root finding before its first layer.
SOLVED_RATIOS: dict[str, float] = {"parabola": 0.7378432588978603, "cosine": 0.6885223764801173}


@lru_cache(maxsize=64)
def _critical_ratio(profile: str, aspect: float, solve: bool = False) -> float:
    if profile in SOLVED_RATIOS and not solve:
        return SOLVED_RATIOS[profile]
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
    check_profile(profile)
    asp = profile_aspect(profile, aspect) if profile == "arc" else 0.25
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
    check_profile(profile)
    aspect = None if height_mm is None else float(height_mm) / float(width_mm)
    if overlap_model == "tangent":
        return critical_ratio(profile, aspect) * float(width_mm)
    if overlap_model == "flat_top":
        return flat_top_ratio(profile, aspect) * float(width_mm)
    raise InputError(f"unknown overlap model '{overlap_model}'; choose one of {', '.join(OVERLAP_MODELS)}")
