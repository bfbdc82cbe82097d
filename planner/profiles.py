"""Bead cross-section profiles of Ding et al. (2015), Table 1 (x across the bead, y above the
substrate, mm)::

    parabola  y = a·x² + c          h = c        w = 2·sqrt(−c/a)      A = (4c/3)·sqrt(−c/a)
    cosine    y = a·cos(b·x)        h = a        w = π/b               A = 2a/b
    arc       y = sqrt(a² − x²) + b h = a + b    w = 2·sqrt(a² − b²)   A = a²·acos(−b/a) + b·sqrt(a² − b²)

(The paper's Table 1 prints the arc height as ``a − b`` and the arc area without the ``a²``
and with the wrong sign on the second term; with its own Table 2 values — b < 0 — only the
forms above reproduce the fitted widths and the wire volume. See docs/process-models.md.)

Pure: no I/O, no clocks.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar, Protocol

import numpy as np

from core.errors import InputError

PROFILES: tuple[str, ...] = ("parabola", "cosine", "arc")
# A measured profile is fitted on the contiguous points above this fraction of its peak.
SUBSTRATE_FRACTION = 0.05


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
        v = np.where(inside, self.raw(np.clip(u, -half, half)), 0.0)  # type: ignore[attr-defined]
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

    def raw(self, u: np.ndarray) -> np.ndarray:
        return np.asarray(self.a * u * u + self.c)

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

    def raw(self, u: np.ndarray) -> np.ndarray:
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

    def raw(self, u: np.ndarray) -> np.ndarray:
        return np.asarray(np.sqrt(np.maximum(self.a**2 - u * u, 0.0)) + self.b)

    def slope(self, x: Any) -> Any:
        u = self._u(x)
        return -u / np.sqrt(np.maximum(self.a**2 - u * u, 1e-300))

    def _antideriv(self, u: float) -> float:
        u = min(max(u, -self.a), self.a)
        return 0.5 * (u * math.sqrt(max(self.a**2 - u * u, 0.0)) + self.a**2 * math.asin(u / self.a)) + self.b * u

    def params(self) -> dict[str, float]:
        return {"a": self.a, "b": self.b}


_CLASSES: dict[str, Any] = {"parabola": Parabola, "cosine": Cosine, "arc": Arc}

# Mean height/width of the arc fits of Ding 2015, Table 2 (h = a + b, w = 2·sqrt(a² − b²)):
# the arc's shape, unlike the parabola's and the cosine's, changes with its aspect ratio, so
# its critical distance needs one. Used when the caller gives none.
_DING_ARC_ROWS = (
    (7.010, -3.720), (6.216, -3.251), (5.715, -3.042), (5.220, -2.727),
    (4.941, -2.571), (4.866, -2.717), (4.299, -2.194), (4.052, -2.034),
)
DING_ARC_ASPECT: float = float(np.mean([(a + b) / (2.0 * math.sqrt(a * a - b * b)) for a, b in _DING_ARC_ROWS]))


def check_profile(profile: str) -> str:
    if profile not in _CLASSES:
        raise InputError(f"unknown bead profile '{profile}'; choose one of {', '.join(PROFILES)}")
    return profile


def profile_from_width_height(profile: str, width_mm: float, height_mm: float, centre_mm: float = 0.0) -> Profile:
    """The profile of this kind with this width and height (mm)."""
    check_profile(profile)
    for name, v in (("width", width_mm), ("height", height_mm)):
        if not (math.isfinite(v) and v > 0.0):
            raise InputError(f"bead {name} must be a positive, finite number of mm (got {v!r})")
    out: Profile = _CLASSES[profile].from_width_height(float(width_mm), float(height_mm), centre_mm)
    return out


def area_factor(profile: str = "parabola", aspect: float | None = None) -> float:
    """A / (w·h): 2/3 for the parabola, 2/π for the cosine, between 2/3 and π/4 for the arc."""
    check_profile(profile)
    asp = profile_aspect(profile, aspect)
    p = profile_from_width_height(profile, 1.0, asp)
    return p.area_mm2 / (p.width_mm * p.height_mm)


def wire_area_mm2(wire_diameter_mm: float, wfs_m_min: float, speed_mm_min: float) -> float:
    """Deposited cross-section from the wire volume, A = π·λ·D²/4 with λ = WFS / travel speed."""
    lam = wfs_m_min * 1000.0 / speed_mm_min
    return math.pi * lam * wire_diameter_mm**2 / 4.0


def profile_aspect(profile: str, aspect: float | None) -> float:
    """Height/width used for the normalised bead (irrelevant for the parabola and cosine)."""
    if profile != "arc":
        return 0.25 if aspect is None else float(aspect)
    asp = DING_ARC_ASPECT if aspect is None else float(aspect)
    if not (math.isfinite(asp) and 0.0 < asp <= 0.5):
        raise InputError(f"an arc bead needs 0 < height/width ≤ 0.5 (got {asp:g})")
    return asp
