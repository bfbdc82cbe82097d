"""What a build runs and returns: the work items, the runner's options, its result.

Plain data shared by the layer sequencing (controller/runtime/build.py), the pass execution
(controller/runtime/pass_run.py), the process control's hooks (controller/runtime/hooks.py) and
the resume (controller/runtime/resume.py).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from controller.runtime.arc_out import RunOn
from core.errors import CellError
from core.material import ProcessTolerance

__all__ = ["BuildError", "BuildOptions", "BuildResult", "Interrupted", "WorkItem"]


class BuildError(CellError):
    """The build cannot go on (a device refused, the job does not fit)."""


class Interrupted(Exception):
    """The build was stopped by an interlock (the machine is already in Fault or EStop)."""


@dataclass(frozen=True)
class WorkItem:
    """One pass to deposit from point `start_idx` of its subdivided polyline."""

    layer: int
    pass_: int
    start_idx: int = 0


@dataclass
class BuildOptions:
    max_step_mm: float = 2.0            # weld moves are at most this long (re-arc overlap bound)
    clearance_mm: float = 5.0           # travel height above the start of a bead
    travel_speed_mm_min: float = 3000.0
    time_scale: float = 1.0             # process time / wall time (dwells, arc-loss timing)
    interpass_limit_c: float = 150.0
    interpass_dwell_s: float = 60.0     # process seconds, when the pyrometer gives no reading
    interpass_timeout_s: float = 3600.0  # process seconds before the wait becomes a fault
    arc_efficiency: float = 0.8
    sample_period_s: float = 0.1        # wall seconds between journal samples
    run_on: RunOn = RunOn()             # how long the arc burns on after a crash (resume estimate)
    tolerance: ProcessTolerance | None = None   # the material's bead tolerance (None: its defaults)
    reset_errors: bool = False          # readiness may clear a latched power-source error (journaled)
    progress_timeout_s: float | None = None  # process s standing with the arc on (None: from the job)

    def bead_tolerance(self) -> ProcessTolerance:
        """The tolerance a bead is judged against (the defaults when none was given)."""
        self.tolerance = self.tolerance or ProcessTolerance()
        return self.tolerance


@dataclass
class BuildResult:
    state: str
    layers_done: int
    passes_done: int
    arc_starts: int
    alarms: list[dict[str, Any]] = field(default_factory=list)
    defects: int = 0                    # beads of this job that were not deposited as planned
