"""Guards of the fits (bead profile, process coefficients, plane/SVD): refuse data no fit can
answer sensibly (non-finite, absurdly scaled, flat), and answers no bead can have (issue 14)."""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from core.errors import InputError

MAX_ABS_MM = 1.0e6       # 1 km: beyond any cell; squares stay far from overflow in SVD/lstsq
MAX_ABS_VALUE = 1.0e9    # currents, speeds and the like


def finite_scaled(values: Any, what: str, limit: float = MAX_ABS_MM) -> np.ndarray:
    """The values as floats, refused when any is non-finite or larger in magnitude than `limit`."""
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"{what}: not numbers") from None
    if arr.size and not np.isfinite(arr.sum()):
        raise InputError(f"{what}: contains non-finite values (NaN or infinite)")
    if arr.size and float(np.max(np.abs(arr))) > limit:
        raise InputError(f"{what}: a value of {float(np.max(np.abs(arr))):.3g} is beyond ±{limit:g} "
                         "(absurdly scaled data: check the units)")
    return arr


def profile_not_flat(x: np.ndarray, y: np.ndarray) -> None:
    """A measured bead profile must rise above its base: a flat one has no width to fit."""
    if y.size and float(np.max(y)) > 0.0 and float(np.ptp(y)) <= 0.05 * float(np.max(np.abs(y))):
        raise InputError("profile is flat (its height varies by under 5 %): no bead to fit")


def plausible_profile(name: str, width_mm: float, height_mm: float, area_mm2: float, x: np.ndarray) -> None:
    """A fitted bead wider than three times the measured span (or not finite) is no answer."""
    span = float(np.ptp(x)) if x.size else 0.0
    vals = (width_mm, height_mm, area_mm2)
    if not all(math.isfinite(v) for v in vals) or width_mm <= 0.0 or width_mm > 3.0 * span:
        raise InputError(f"the {name} fit gives a {width_mm:.4g} mm wide bead for {span:.4g} mm of measured "
                         "profile: the profile does not look like a bead (refused)")


def finite_result(what: str, values: dict[str, float]) -> None:
    """Every number of a fit's answer finite, else the fit is refused naming the first bad one."""
    for k, v in values.items():
        if not math.isfinite(float(v)):
            raise InputError(f"{what}: the fit gives {k} = {v} (the data cannot be fitted: check the "
                             "measurements vary and are in the stated units)")
