"""A planned bead in the layer plane before it gets its z, welding parameters and order."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False)
class Path2D:
    role: str  # perimeter | infill | gap
    points: np.ndarray  # (n, 2); a closed loop repeats its first point at the end
    width_mm: float
    closed: bool = False
    share_mm: float = 0.0  # width of the strip this bead fills (step-over, or its width if alone)
    lone: bool = False  # no overlapping neighbour: it fills its profile area, not a strip

    @property
    def length(self) -> float:
        return float(np.linalg.norm(np.diff(self.points, axis=0), axis=1).sum())

    def reversed(self) -> "Path2D":
        return Path2D(self.role, self.points[::-1].copy(), self.width_mm, self.closed, self.share_mm, self.lone)
