"""Explicit seams of the build runner (controller/runtime/build.py) that a process control uses
instead of overriding the runner's private methods (docs/closed-loop.md "Along the path")."""
from __future__ import annotations

from typing import Protocol

__all__ = ["ArcSampleHook"]


class ArcSampleHook(Protocol):
    """Told every arc-stable power-source sample of a bead with where the torch was: `along_mm`,
    the length along the pass (its weld points) of the last point the motion device reported
    reaching (the robot's EXE, the CNC's status)."""

    def arc_sample(self, layer: int, pass_: int, along_mm: float, current_a: float) -> None: ...
