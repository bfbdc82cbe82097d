"""Welding-parameter model of Ribeiro, Ogunbiyi and Norrish (1997).

Forward model (the paper's eqs. 14-15, I in A, S in mm/min, w and h in mm)::

    w = K1 · I^K2 · S^K3
    h = K4 · I^K5 · S^K6

Inverse (eqs. 23-25), with ``a = K2·K6 − K3·K5``::

    I = h^(−K3/a) · K4^(K3/a) · w^(K6/a) · K1^(−K6/a)
    S = h^(K2/a)  · K4^(−K2/a) · w^(−K5/a) · K1^(K5/a)

The height defaults to ``RATIO · w``. The wire feed speed follows the power source's synergic
straight line through ``(Imin, WFSmin)`` and ``(Imax, WFSmax)``. A point whose current lies
outside ``[Imin, Imax]`` or whose wire feed speed lies outside ``[WFSmin, WFSmax]`` is outside the
process envelope: an :class:`~core.errors.EnvelopeError` naming the limit, unless the caller
explicitly allows it (then ``inside_envelope`` is False and the synergic line is extrapolated).

Pure: no I/O, no clocks, no globals. Everything works in float64.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from core.errors import EnvelopeError, InputError

if TYPE_CHECKING:  # annotations only: `cell plan` passes a remembered material (core.config_cache) and
    # never imports pydantic
    from core.material import Material, RibeiroCoefficients

__all__ = [
    "ProcessPoint",
    "forward",
    "inverse",
    "wfs_for_current",
    "current_for_wfs",
    "envelope_violations",
    "ENVELOPE_RTOL",
]

# Relative slack on the envelope limits, so that a point computed exactly at Imax (e.g. by
# inverting forward(Imax, S)) is not rejected for a rounding error in the last bit.
ENVELOPE_RTOL = 1e-9


@dataclass(frozen=True, slots=True)
class ProcessPoint:
    """One bead's welding parameters (mm, mm/min, A, m/min)."""

    width_mm: float
    height_mm: float
    current_a: float
    speed_mm_min: float
    wfs_m_min: float
    inside_envelope: bool

    def to_dict(self) -> dict[str, Any]:
        """The JSON object of `cell process inverse --json` (same keys, same order)."""
        return asdict(self)


def _coeffs(material: Material | RibeiroCoefficients) -> RibeiroCoefficients:
    # by attribute, not isinstance: a remembered material (core.config_cache.Frozen) reads the same
    return cast("RibeiroCoefficients", getattr(material, "ribeiro", material))


def _name(material: Material | RibeiroCoefficients) -> str:
    return str(getattr(material, "name", "the given coefficients"))


def _positive(name: str, value: Any, unit: str) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.size == 0:
        raise InputError(f"{name} is empty; give at least one value in {unit}")
    bad = ~np.isfinite(arr) | (arr <= 0.0)
    if np.any(bad):
        first = arr.reshape(-1)[np.argmax(bad.reshape(-1))]
        raise InputError(f"{name} must be a positive, finite number of {unit} (got {_fmt(float(first))})")
    return arr


def _fmt(x: float) -> str:
    """Short human form of a number for messages: 10, 171.3, 0.0001234."""
    if not math.isfinite(x):
        return str(x)
    if x == int(x) and abs(x) < 1e15:
        return str(int(x))
    return f"{x:.4g}" if abs(x) < 0.1 else f"{x:.1f}" if abs(x) >= 100 else f"{x:.3g}"


def _out(arr: np.ndarray) -> float | np.ndarray:
    return float(arr) if arr.ndim == 0 else arr


def forward(
    material: Material | RibeiroCoefficients, current_a: Any, speed_mm_min: Any
) -> tuple[Any, Any]:
    """Bead (width_mm, height_mm) for a current (A) and a travel speed (mm/min).

    Vectorised: numpy arrays (broadcast together) give arrays; scalars give floats. No envelope
    check here: the forward model is also used to explore outside it.
    """
    k = _coeffs(material)
    i = _positive("current", current_a, "A")
    s = _positive("travel speed", speed_mm_min, "mm/min")
    w = k.k1 * np.power(i, k.k2) * np.power(s, k.k3)
    h = k.k4 * np.power(i, k.k5) * np.power(s, k.k6)
    return _out(np.asarray(w)), _out(np.asarray(h))


def inverse_arrays(k: RibeiroCoefficients, w: np.ndarray, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = k.k2 * k.k6 - k.k3 * k.k5
    # Evaluated in logarithms: the same formula, better conditioned for large exponents.
    lw, lh, lk1, lk4 = np.log(w), np.log(h), math.log(k.k1), math.log(k.k4)
    li = (-k.k3 * lh + k.k3 * lk4 + k.k6 * lw - k.k6 * lk1) / a
    ls = (k.k2 * lh - k.k2 * lk4 - k.k5 * lw + k.k5 * lk1) / a
    return np.exp(li), np.exp(ls)


def wfs_for_current(material: Material | RibeiroCoefficients, current_a: Any) -> Any:
    """Wire feed speed (m/min) on the synergic line through (Imin, WFSmin) and (Imax, WFSmax).

    Extrapolates linearly outside [Imin, Imax] (the envelope check is the caller's business).
    Vectorised like :func:`forward`.
    """
    k = _coeffs(material)
    i = np.asarray(current_a, dtype=np.float64)
    slope = (k.wfs_max_m_min - k.wfs_min_m_min) / (k.i_max_a - k.i_min_a)
    return _out(np.asarray(k.wfs_min_m_min + slope * (i - k.i_min_a)))


def current_for_wfs(material: Material | RibeiroCoefficients, wfs_m_min: Any) -> Any:
    """The synergic line read the other way: current (A) for a wire feed speed (m/min)."""
    k = _coeffs(material)
    v = np.asarray(wfs_m_min, dtype=np.float64)
    slope = (k.i_max_a - k.i_min_a) / (k.wfs_max_m_min - k.wfs_min_m_min)
    return _out(np.asarray(k.i_min_a + slope * (v - k.wfs_min_m_min)))


def envelope_violations(
    material: Material | RibeiroCoefficients, current_a: float, wfs_m_min: float
) -> list[str]:
    """Which envelope limits a (current, WFS) pair breaks, as short phrases; [] when inside."""
    k = _coeffs(material)
    out: list[str] = []
    tol_i = ENVELOPE_RTOL * k.i_max_a
    tol_v = ENVELOPE_RTOL * k.wfs_max_m_min
    if current_a > k.i_max_a + tol_i:
        out.append(f"{current_a:.1f} A, above Imax {_fmt(k.i_max_a)} A")
    elif current_a < k.i_min_a - tol_i:
        out.append(f"{current_a:.1f} A, below Imin {_fmt(k.i_min_a)} A")
    if wfs_m_min > k.wfs_max_m_min + tol_v:
        out.append(f"wire feed {wfs_m_min:.2f} m/min, above WFSmax {_fmt(k.wfs_max_m_min)} m/min")
    elif wfs_m_min < k.wfs_min_m_min - tol_v:
        out.append(f"wire feed {wfs_m_min:.2f} m/min, below WFSmin {_fmt(k.wfs_min_m_min)} m/min")
    return out


def inverse(
    material: Material,
    width_mm: float,
    height_mm: float | None = None,
    *,
    allow_outside: bool = False,
) -> ProcessPoint:
    """Current, travel speed and wire feed speed for a bead of this width (and height).

    ``height_mm`` defaults to the material's ``ratio × width``. Outside the process envelope
    (current outside [Imin, Imax] or WFS outside [WFSmin, WFSmax]) this raises
    :class:`EnvelopeError` naming the limit, unless ``allow_outside`` is True; then the point is
    returned with ``inside_envelope=False``.
    """
    k = _coeffs(material)
    w = float(_positive("bead width", width_mm, "mm"))
    h = k.ratio * w if height_mm is None else float(_positive("bead height", height_mm, "mm"))
    i_arr, s_arr = inverse_arrays(k, np.asarray(w), np.asarray(h))
    current, speed = float(i_arr), float(s_arr)
    if not (math.isfinite(current) and math.isfinite(speed)):
        raise InputError(
            f"width {_fmt(w)} mm, height {_fmt(h)} mm has no finite current/speed with the "
            f"coefficients of {_name(material)}; check the material's k1-k6"
        )
    wfs = float(wfs_for_current(k, current))
    broken = envelope_violations(k, current, wfs)
    if broken and not allow_outside:
        what = f"width {_fmt(w)} mm" if height_mm is None else f"width {_fmt(w)} mm and height {_fmt(h)} mm"
        high = current > k.i_max_a or wfs > k.wfs_max_m_min
        hint = "a narrower bead" if high else "a wider bead"
        if height_mm is not None:
            hint = "another width/height"
        extra = f" (and {'; '.join(broken[1:])})" if len(broken) > 1 else ""
        raise EnvelopeError(
            f"{what} needs {broken[0]} of {_name(material)}{extra}; "
            f"choose {hint} or --allow-outside"
        )
    return ProcessPoint(
        width_mm=w,
        height_mm=h,
        current_a=current,
        speed_mm_min=speed,
        wfs_m_min=wfs,
        inside_envelope=not broken,
    )
