"""What the API object tells of the simulators it was opened on (controller/harness/cell.py
`open_cell(cfg, sim=...)`): `CellController.simulators`, None on real devices.

Tests, benches and `cell run --fault name@layer=N` reach a simulated device through it (open the
door, inject an arc loss, read the simulated world); the controller itself never does.
"""
from __future__ import annotations

from pathlib import Path
from typing import Awaitable, Callable, Protocol, TypeVar

from core.config import SimConfig

__all__ = ["Simulators"]

T = TypeVar("T")


class Simulators(Protocol):
    """The simulators of a cell opened with `sim=`: in this process, or `cell sim up` in a child."""

    @property
    def sim_cfg(self) -> SimConfig:
        """The simulators' configuration (the workpiece, the stock's pose)."""
        ...

    @property
    def log_dir(self) -> Path | None:
        """Where the simulators write their own record (deposit.jsonl, robot.jsonl...)."""
        ...

    @property
    def in_process(self) -> bool:
        """True when they share this interpreter (their objects are reachable: `sim`, `call`)."""
        ...

    @property
    def process_id(self) -> int:
        """The process the simulators run in (this one, or `cell sim up`'s)."""
        ...

    def sim(self, device: str) -> object:
        """The simulator object of a device (in this process only): tests and benches read its state;
        the product reaches a simulator only through `inject` and `set_time_scale`."""
        ...

    def call(self, fn: Callable[..., T | Awaitable[T]], *args: object, **kwargs: object) -> T:
        """`fn(*args, **kwargs)` on the simulators' loop, its result (thread-safe; in this process only)."""
        ...

    def inject(self, device: str, fault: str, *, duration_s: float | None = None) -> None:
        """A seeded fault now, by the device's simulator (`cell run --fault`; docs/simulators.md)."""
        ...

    def set_time_scale(self, scale: float) -> None:
        """Process time / wall time of the simulated devices from now on (the machine idle)."""
        ...
