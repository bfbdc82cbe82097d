"""The options of a plan (`cell plan`'s flags), validated on construction."""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from core.errors import InputError
from planner.weld import CellLimits

if TYPE_CHECKING:  # an annotation only: a 3-axis plan does not load planner.five_axis (start-up time)
    from planner.five_axis import FiveAxisOptions


@dataclass(frozen=True)
class PlanOptions:
    width_mm: float
    layer_height_mm: float | None = None  # default: the bead height of the process model
    perimeters: int | str | None = 2  # None or "all": offset until the loops meet
    units: str = "mm"
    allow_outside: bool = False  # accept welding points outside the material's envelope
    infill_angle_deg: float = 0.0  # scan direction of layer 0; +90° every layer
    allow_underfill: bool = False  # features no legal bead fills, layers below min_coverage: warnings
    allow_overhang: bool = False  # steps out beyond the overhang rule: warnings
    min_coverage: float = 0.97  # every layer at least this share covered by beads
    workspace_mm: tuple[float, float, float] | None = None  # the cell's room: a larger part is refused
    five_axis: FiveAxisOptions | None = None  # tool axes per point (planner/five_axis.py)
    frame: str = "substrate"  # substrate: lowest point on z = 0; cad: keep the CAD coordinates (repair)
    cell_limits: CellLimits = CellLimits()  # speeds and source range of the cell (cell.yaml limits)
    machining_allowance_mm: float | None = None  # near-net stock per face; None: the material's, else 0
    feed_forward: bool = True  # per-segment speeds that level each layer's predicted top (planner/feedforward.py)
    feed_forward_pour: bool = False  # ...predicted as the world pours, on the stack (planner/level_pour.py; opt-in)

    def __post_init__(self) -> None:
        if isinstance(self.perimeters, str):  # "all" or "3", as on the command line
            p = self.perimeters.strip().lower()
            if p != "all" and not p.isdigit():
                raise InputError(f"--perimeters: '{self.perimeters}' is not a number of perimeters or 'all'")
            object.__setattr__(self, "perimeters", None if p == "all" else int(p))
        if not (self.width_mm > 0 and np.isfinite(self.width_mm)):
            raise InputError(f"--width: must be a positive number of mm, got {self.width_mm}")
        if self.layer_height_mm is not None and not (0 < self.layer_height_mm < self.width_mm * 5):
            raise InputError(f"--layer-height: must be > 0 mm and sensible for a {self.width_mm} mm bead, "
                             f"got {self.layer_height_mm}")
        if self.frame not in ("substrate", "cad"):
            raise InputError(f"--frame: '{self.frame}' is not substrate or cad")
        if not (0.0 <= self.min_coverage <= 1.0):
            raise InputError(f"--min-coverage: must be between 0 and 1, got {self.min_coverage}")
        a = self.machining_allowance_mm
        if a is not None and not (0.0 <= a <= 100.0):
            raise InputError(f"--machining-allowance: must be between 0 and 100 mm, got {a}")
        if isinstance(self.perimeters, int) and not (0 <= self.perimeters <= 1000):
            raise InputError(f"--perimeters: must be 0..1000 or 'all', got {self.perimeters}")
