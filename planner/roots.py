"""A bracketing root finder in pure Python: `cell plan` needs one root (d*) and no scipy import."""
from __future__ import annotations

from typing import Any


def brentq(f: Any, a: float, b: float, xtol: float = 1e-15, rtol: float = 1e-15, maxiter: int = 200) -> float:
    """Root of f in [a, b] (f(a), f(b) of opposite signs) by the Illinois false position, with a
    bisection step whenever it stalls; pure Python, so `cell plan` does not import scipy.optimize."""
    fa, fb = f(a), f(b)
    if fa == 0.0:
        return a
    if fb == 0.0:
        return b
    side = 0
    for _ in range(maxiter):
        m = (a * fb - b * fa) / (fb - fa) if fb != fa else 0.5 * (a + b)
        if not (min(a, b) < m < max(a, b)):
            m = 0.5 * (a + b)
        fm = f(m)
        if fm == 0.0 or abs(b - a) < 2 * (xtol + rtol * abs(m)):
            return m
        if (fm > 0) == (fb > 0):
            b, fb = m, fm
            if side == -1:
                fa *= 0.5  # Illinois: the retained end's value halved, so it cannot stall
            side = -1
        else:
            a, fa = m, fm
            if side == 1:
                fb *= 0.5
            side = 1
        if abs(b - a) < 2 * (xtol + rtol * abs(m)):
            return 0.5 * (a + b)
    return 0.5 * (a + b)
