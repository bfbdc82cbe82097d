"""Wire melting rate (burn-off) of GMAW: `WFS = α·I + β·L·I²` (Lesnewich 1958), pure functions.

Units: WFS in m/min, I in A, L (the electrode stick-out, taken as the contact-tip-to-work
distance, CTWD) in mm; α in (m/min)/A (arc heating), β in (m/min)/(A²·mm) (resistive heating
of the stick-out). At a fixed wire feed a longer stick-out melts more wire per ampere, so the
source's current falls: dI/dL = −β·I² / (α + 2·β·L·I).

The synergic line of a material (core.material.RibeiroCoefficients: Imin/Imax against WFSmin/
WFSmax) is measured at the nominal stick-out. `calibrate_on_line` turns it into α, β: at the
reference current (the line's middle by default) the resistive term is `resistive_share` of the
melting and the rest is the arc's. A straight synergic line and the quadratic relation agree only
at that reference point, so the *anchored* form `current_at` / `stick_out_at` scales the
relation by the synergic line: `I(W, L) = I_syn(W) · I_rel(W, L) / I_rel(W, L0)`. It is exact on
the synergic line at the nominal stick-out for every WFS, and has the relation's sensitivity to L.
The power-source simulator uses `current_at`; a controller inverts the measured current with
`stick_out_at` (docs/process-physics.md).

`fit_sweep` refits α, β from a stick-out sweep (rows of stick-out, WFS, current) by linear least
squares (the relation is linear in α and β). Everything here is pure: no I/O, no clocks.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from core.errors import InputError
from core.material import Material, RibeiroCoefficients

__all__ = [
    "MeltingRelation", "SweepFit", "wfs_for", "current_for", "stick_out_for", "calibrate",
    "calibrate_on_line", "relation_for", "synergic_current", "stick_out_factor", "current_at", "stick_out_at",
    "sensitivity_a_per_mm", "fit_sweep",
]


@dataclass(frozen=True, slots=True)
class MeltingRelation:
    """α, β of `WFS = α·I + β·L·I²` and the nominal stick-out the synergic line holds at."""

    alpha: float            # (m/min)/A
    beta: float             # (m/min)/(A²·mm)
    stick_out_mm: float     # nominal L0 (mm)

    def to_dict(self) -> dict[str, float]:
        return {"alpha": self.alpha, "beta": self.beta, "stick_out_mm": self.stick_out_mm}


@dataclass(frozen=True, slots=True)
class SweepFit:
    """`cell process stickout-fit`: α, β refit from a sweep, with the fit's quality."""

    alpha: float
    beta: float
    r2: float                 # of the wire feed predicted from (I, L)
    rms: float                # m/min, wire feed residual
    rms_stick_out_mm: float   # the stick-out read back from (WFS, I) against the sweep's
    n: int

    def to_dict(self) -> dict[str, float | int]:
        return {"alpha": self.alpha, "beta": self.beta, "r2": self.r2, "rms": self.rms,
                "rms_stick_out_mm": self.rms_stick_out_mm, "n": self.n}


# --- the relation --------------------------------------------------------------------------------


def wfs_for(alpha: float, beta: float, current_a: float, stick_out_mm: float) -> float:
    """Forward: the wire feed (m/min) a current melts at a stick-out."""
    return alpha * current_a + beta * stick_out_mm * current_a * current_a


def current_for(alpha: float, beta: float, wfs_m_min: float, stick_out_mm: float) -> float:
    """The current (A) that melts `wfs_m_min` at `stick_out_mm`: the positive root of the quadratic.

    Written as 2W / (α + √(α² + 4βLW)), which stays accurate when β·L is small.
    """
    if wfs_m_min <= 0.0:
        return 0.0
    bl = max(beta * stick_out_mm, 0.0)
    return 2.0 * wfs_m_min / (alpha + math.sqrt(alpha * alpha + 4.0 * bl * wfs_m_min))


def stick_out_for(alpha: float, beta: float, wfs_m_min: float, current_a: float) -> float:
    """Inverse: the stick-out (mm) at which `current_a` melts `wfs_m_min` (negative: no such L)."""
    if current_a <= 0.0 or beta <= 0.0:
        raise InputError(f"the stick-out needs a positive current and β (got {current_a} A, β {beta})")
    return (wfs_m_min - alpha * current_a) / (beta * current_a * current_a)


def calibrate(current_a: float, wfs_m_min: float, stick_out_mm: float, resistive_share: float) -> tuple[float, float]:
    """α, β such that (I, WFS) lies on the relation at L and the resistive term is that share of it."""
    if not (current_a > 0 and wfs_m_min > 0 and stick_out_mm > 0):
        raise InputError("calibrating the melting rate needs a positive current, wire feed and stick-out")
    if not 0.0 < resistive_share < 1.0:
        raise InputError(f"the resistive share must lie in (0, 1) (got {resistive_share})")
    alpha = (1.0 - resistive_share) * wfs_m_min / current_a
    beta = resistive_share * wfs_m_min / (stick_out_mm * current_a * current_a)
    return alpha, beta


def synergic_current(line: RibeiroCoefficients, wfs_m_min: float) -> float:
    """The synergic line's current (A) for a wire feed (m/min), extrapolated outside the envelope."""
    slope = (line.i_max_a - line.i_min_a) / (line.wfs_max_m_min - line.wfs_min_m_min)
    return line.i_min_a + slope * (wfs_m_min - line.wfs_min_m_min)


def calibrate_on_line(line: RibeiroCoefficients, stick_out_mm: float, resistive_share: float,
                      current_a: float | None = None) -> MeltingRelation:
    """α, β from the synergic line at the nominal stick-out (reference: the line's middle current)."""
    i_ref = 0.5 * (line.i_min_a + line.i_max_a) if current_a is None else current_a
    slope = (line.wfs_max_m_min - line.wfs_min_m_min) / (line.i_max_a - line.i_min_a)
    w_ref = line.wfs_min_m_min + slope * (i_ref - line.i_min_a)
    alpha, beta = calibrate(i_ref, w_ref, stick_out_mm, resistive_share)
    return MeltingRelation(alpha, beta, stick_out_mm)


def relation_for(material: Material, stick_out_mm: float | None = None,
                 resistive_share: float | None = None) -> MeltingRelation:
    """The material's relation: its `melting.alpha/beta` when given, else calibrated from its line.

    `stick_out_mm` / `resistive_share` override the material's (the simulator's hidden truth).
    """
    m = material.melting
    l0 = m.stick_out_mm if stick_out_mm is None else stick_out_mm
    if resistive_share is None and m.alpha is not None and m.beta is not None:
        return MeltingRelation(m.alpha, m.beta, l0)
    share = m.resistive_share if resistive_share is None else resistive_share
    return calibrate_on_line(material.ribeiro, l0, share, m.reference_current_a)


# --- anchored to the synergic line ----------------------------------------------------------------


def stick_out_factor(rel: MeltingRelation, wfs_m_min: float, stick_out_mm: float) -> float:
    """I(W, L) / I(W, L0) of the relation: 1.0 exactly at the nominal stick-out."""
    if wfs_m_min <= 0.0 or stick_out_mm == rel.stick_out_mm:
        return 1.0
    nominal = current_for(rel.alpha, rel.beta, wfs_m_min, rel.stick_out_mm)
    return current_for(rel.alpha, rel.beta, wfs_m_min, max(stick_out_mm, 0.0)) / nominal


def current_at(rel: MeltingRelation, line: RibeiroCoefficients, wfs_m_min: float, stick_out_mm: float) -> float:
    """The source's current (A) at a wire feed and an actual stick-out.

    The synergic line's current, scaled by the relation: exactly the line at the nominal stick-out.
    """
    i_syn = synergic_current(line, wfs_m_min)
    if wfs_m_min <= 0.0 or i_syn <= 0.0:
        return max(i_syn, 0.0)
    return i_syn * stick_out_factor(rel, wfs_m_min, stick_out_mm)


def stick_out_at(rel: MeltingRelation, line: RibeiroCoefficients, wfs_m_min: float, current_a: float) -> float:
    """Inverse of `current_at`: the stick-out (mm) a measured current means at a commanded wire feed."""
    i_syn = synergic_current(line, wfs_m_min)
    if wfs_m_min <= 0.0 or i_syn <= 0.0:
        raise InputError(f"no stick-out at wire feed {wfs_m_min} m/min: the synergic line gives no current there")
    nominal = current_for(rel.alpha, rel.beta, wfs_m_min, rel.stick_out_mm)
    return stick_out_for(rel.alpha, rel.beta, wfs_m_min, current_a * nominal / i_syn)


def sensitivity_a_per_mm(rel: MeltingRelation, line: RibeiroCoefficients, wfs_m_min: float) -> float:
    """dI/dL (A/mm, negative) of `current_at` at the nominal stick-out."""
    i = current_at(rel, line, wfs_m_min, rel.stick_out_mm)
    scale = i / current_for(rel.alpha, rel.beta, wfs_m_min, rel.stick_out_mm)
    i_rel = i / scale
    return -scale * rel.beta * i_rel * i_rel / (rel.alpha + 2.0 * rel.beta * rel.stick_out_mm * i_rel)


# --- refit from a sweep ---------------------------------------------------------------------------


def fit_sweep(stick_out_mm: Any, wfs_m_min: Any, current_a: Any) -> SweepFit:
    """Least-squares α, β from a stick-out sweep: WFS = α·I + β·(L·I²), no intercept.

    Needs at least 3 rows and at least two stick-outs (or currents) that tell α from β apart.
    """
    L = np.asarray(stick_out_mm, dtype=np.float64).reshape(-1)
    W = np.asarray(wfs_m_min, dtype=np.float64).reshape(-1)
    i = np.asarray(current_a, dtype=np.float64).reshape(-1)
    if not (len(L) == len(W) == len(i)):
        raise InputError("stick-out, wire feed and current columns differ in length")
    if len(L) < 3:
        raise InputError(f"a stick-out sweep needs at least 3 rows (got {len(L)})")
    if np.any(~np.isfinite(np.r_[L, W, i])) or np.any(L <= 0) or np.any(W <= 0) or np.any(i <= 0):
        raise InputError("every stick-out, wire feed and current of the sweep must be a positive number")
    X = np.column_stack([i, L * i * i])
    # scale the columns so the conditioning does not depend on the units
    norms = np.linalg.norm(X, axis=0)
    coef, _, rank, sv = np.linalg.lstsq(X / norms, W, rcond=None)
    if rank < 2 or sv[-1] < 1e-9 * sv[0]:
        raise InputError("the sweep cannot tell α from β apart: vary the stick-out (or the current) across its rows")
    alpha, beta = (float(c) for c in coef / norms)
    res = W - X @ np.array([alpha, beta])
    ss_tot = float(np.sum((W - W.mean()) ** 2))
    r2 = 1.0 - float(np.sum(res ** 2)) / ss_tot if ss_tot > 0 else 1.0
    back = (W - alpha * i) / (beta * i * i) if beta > 0 else np.full_like(L, np.nan)
    return SweepFit(alpha, beta, r2, float(np.sqrt(np.mean(res ** 2))),
                    float(np.sqrt(np.mean((back - L) ** 2))), len(L))
