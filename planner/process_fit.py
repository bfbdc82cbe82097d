"""Refit the Ribeiro (1997) coefficients K1–K6 from bead measurements, as the paper did.

Width and height are regressed separately on the logarithms (the paper's eqs. 2–5)::

    ln w = ln K1 + K2·ln I + K3·ln S
    ln h = ln K4 + K5·ln I + K6·ln S

by ordinary least squares. R² is the coefficient of determination of each regression, i.e.
in the logarithmic domain the regression works in (reported as r2_width / r2_height); the
R² of the back-transformed predictions in millimetres is reported too (r2_width_mm,
r2_height_mm). Pure: arrays in, a frozen dataclass out.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from core.errors import InputError
from planner import fit_guards

__all__ = ["ProcessFit", "fit_coefficients", "MIN_POINTS"]

MIN_POINTS = 4  # three coefficients per regression and at least one degree of freedom


@dataclass(frozen=True, slots=True)
class ProcessFit:
    k1: float
    k2: float
    k3: float
    k4: float
    k5: float
    k6: float
    r2_width: float
    r2_height: float
    r2_width_mm: float
    r2_height_mm: float
    n_points: int

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def coefficients(self) -> tuple[float, float, float, float, float, float]:
        return (self.k1, self.k2, self.k3, self.k4, self.k5, self.k6)


def _r2(y: np.ndarray, pred: np.ndarray) -> float:
    ss_res = float(np.sum((y - pred) ** 2))
    ss_tot = float(np.sum((y - y.mean()) ** 2))
    if ss_tot == 0.0:
        return 1.0 if ss_res == 0.0 else 0.0
    return 1.0 - ss_res / ss_tot


def _column(name: str, values: Any) -> np.ndarray:
    arr = fit_guards.finite_scaled(values, name, fit_guards.MAX_ABS_VALUE).reshape(-1)
    bad = ~np.isfinite(arr) | (arr <= 0.0)
    if np.any(bad):
        i = int(np.argmax(bad))
        raise InputError(f"{name}: row {i + 1} is {arr[i]!r}; every value must be positive and finite (logarithms)")
    return arr


def fit_coefficients(current_a: Any, speed_mm_min: Any, width_mm: Any, height_mm: Any) -> ProcessFit:
    """Least-squares K1–K6 on the logarithms of (I, S, w, h) measurements."""
    cols = {
        "current_a": _column("current_a", current_a),
        "speed_mm_min": _column("speed_mm_min", speed_mm_min),
        "width_mm": _column("width_mm", width_mm),
        "height_mm": _column("height_mm", height_mm),
    }
    sizes = {k: v.size for k, v in cols.items()}
    if len(set(sizes.values())) != 1:
        raise InputError(f"columns have different lengths: {sizes}")
    n = sizes["current_a"]
    if n < MIN_POINTS:
        raise InputError(f"{n} measurements; a fit of K1–K6 needs at least {MIN_POINTS}")
    li, ls = np.log(cols["current_a"]), np.log(cols["speed_mm_min"])
    X = np.column_stack([np.ones(n), li, ls])
    if np.ptp(li) == 0.0:
        raise InputError("every measurement has the same current; vary the current to fit K2 and K5")
    if np.ptp(ls) == 0.0:
        raise InputError("every measurement has the same speed; vary the speed to fit K3 and K6")
    if np.linalg.matrix_rank(X) < 3:
        raise InputError(
            "current and speed vary together (collinear in logarithms); "
            "measure at least two speeds per current"
        )
    lw, lh = np.log(cols["width_mm"]), np.log(cols["height_mm"])
    bw = np.linalg.lstsq(X, lw, rcond=None)[0]
    bh = np.linalg.lstsq(X, lh, rcond=None)[0]
    pw, ph = X @ bw, X @ bh
    fit_guards.finite_result("process fit", {"k1": float(np.exp(bw[0])), "k4": float(np.exp(bh[0])),
                                             "k2": bw[1], "k3": bw[2], "k5": bh[1], "k6": bh[2]})
    return ProcessFit(
        k1=float(np.exp(bw[0])),
        k2=float(bw[1]),
        k3=float(bw[2]),
        k4=float(np.exp(bh[0])),
        k5=float(bh[1]),
        k6=float(bh[2]),
        r2_width=_r2(lw, pw),
        r2_height=_r2(lh, ph),
        r2_width_mm=_r2(cols["width_mm"], np.exp(pw)),
        r2_height_mm=_r2(cols["height_mm"], np.exp(ph)),
        n_points=int(n),
    )
