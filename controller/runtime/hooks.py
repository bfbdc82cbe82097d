"""Explicit seams of the build runner (controller/runtime/build.py): a process control attaches
through these instead of overriding the runner's methods or handing it a doctored container
(docs/closed-loop.md "The runner's seams").

- `LayerSource`: the layers the runner lays, `layer(i)` being layer i *as built* (a control's
  z offset and trim applied); the runner asks for a layer when it reaches it, never earlier, so a
  control may decide it from the layers laid before.
- `BuildHooks`: asked once before the first move, the devices ready (`before_motion`: a control
  whose sensing moves a device gets it ready there, e.g. the CNC homed before its first touch);
  told every arc-stable power-source sample with where the torch was
  (`arc_sample`), each bead's samples when it closes (`bead_closed`), and asked after each pass
  whether to go on, pause (a message) or lay other passes next (`after_pass`).

`PlannedLayers` and `NoHooks` are the open plan: the job's layers as they are, nothing told.
The layer control (controller/runtime/layer_control.py) implements both for the `open`,
`layer` and `path` modes; the path loop (path_control.py) is an `ArcSampleHook` it forwards to.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, Sequence

from controller.runtime.work import WorkItem
from planner.job import Layer

__all__ = ["AfterPass", "ArcSampleHook", "BuildHooks", "LayerSource", "NoHooks", "PlannedLayers"]


class LayerSource(Protocol):
    """The layers of a build: their count and pass counts as planned, each layer as built."""

    def layer_count(self) -> int:
        """How many layers the build lays now (a control may add or drop top layers)."""
        ...

    def passes_in(self, i: int) -> int:
        """How many passes layer i has (without building it)."""
        ...

    def layer(self, i: int) -> Layer:
        """Layer i as it is laid (asked when the runner reaches it)."""
        ...


class PlannedLayers:
    """The job's layers as planned."""

    def __init__(self, layers: Sequence[Layer]) -> None:
        self.layers = list(layers)

    def layer_count(self) -> int:
        return len(self.layers)

    def passes_in(self, i: int) -> int:
        return len(self.layers[i].passes)

    def layer(self, i: int) -> Layer:
        return self.layers[i]


@dataclass(frozen=True)
class AfterPass:
    """What the runner does after a pass: go on (the default), pause at the end of this bead with
    `pause` as the cause, and/or lay `rest` next instead of the remaining work (layers added or
    dropped)."""

    pause: str | None = None
    rest: list[WorkItem] | None = None


GO_ON = AfterPass()


class ArcSampleHook(Protocol):
    """Told every arc-stable power-source sample of a bead with where the torch was: `along_mm`,
    the length along the pass (its weld points) of the last point the motion device reported
    reaching (the robot's EXE, the CNC's status); `wfs_m_min` the wire feed the source reported
    with it (a current means a stick-out only at its own feed)."""

    def arc_sample(self, layer: int, pass_: int, along_mm: float, current_a: float,
                   wfs_m_min: float | None = None) -> None: ...


class BuildHooks(ArcSampleHook, Protocol):
    """A process control's hooks into a build."""

    async def before_motion(self) -> None:
        """Once per run (first run or resume), the devices ready, before the first move."""
        ...

    def bead_closed(self, layer: int, pass_: int, currents: Sequence[float], wfs_m_min: float) -> None:
        """A bead deposited to its end: the current of every arc-stable sample of it (a bead a
        trip cut is not told)."""
        ...

    async def after_pass(self, item: WorkItem, rest: Sequence[WorkItem]) -> AfterPass:
        """After pass `item` is done, `rest` the work still to run: go on, pause, or other work."""
        ...


class NoHooks:
    """The open plan's hooks: nothing told, always go on."""

    async def before_motion(self) -> None:
        return None

    def arc_sample(self, layer: int, pass_: int, along_mm: float, current_a: float,
                   wfs_m_min: float | None = None) -> None:
        return None

    def bead_closed(self, layer: int, pass_: int, currents: Sequence[float], wfs_m_min: float) -> None:
        return None

    async def after_pass(self, item: WorkItem, rest: Sequence[WorkItem]) -> AfterPass:
        return GO_ON
