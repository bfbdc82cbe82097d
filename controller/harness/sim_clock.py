"""Simulated time a separate `cell sim up` can be fed at (docs/controller.md, "Simulated time the host can feed").

Where the host cannot stream a CNC program at the configured time scale, the command lowers the
simulators' clock to the highest scale it can feed, over the clock line `cell sim up` serves
(wire/sim_clock.py; not a device protocol, real devices have no clock), says so before any motion
and journals it; after the build the configured scale is given back.
"""
from __future__ import annotations

import json
import socket
from pathlib import Path

from controller.job.model import CellJob
from controller.motion.cnc5 import limit_time_scale
from core.config import CellConfig
from core.errors import CellError, InputError
from core.runtime_dir import runtime_dir
from wire.sim_clock import Inject, ask, clock_file, parse_answer, parse_ok
from wire.urls import parse_tcp_url

TIMEOUT_S = 2.0


class SimClockLink:
    """The clock line of the `cell sim up` serving one CNC URL."""

    def __init__(self, url: str, cnc_url: str) -> None:
        self.url = url
        self.cnc_url = cnc_url

    @classmethod
    def find(cls, cnc_url: str, directory: Path | None = None) -> "SimClockLink | None":
        """The clock of the simulators serving `cnc_url`, if they name one and it answers."""
        path = clock_file(directory or runtime_dir(), cnc_url)
        try:
            url = str(json.loads(path.read_text())["url"])
        except (OSError, ValueError, KeyError, TypeError):
            return None
        link = cls(url, cnc_url)
        try:
            link.scale()
        except CellError:
            return None   # a stale file: those simulators are gone
        return link

    def _line(self, request: bytes) -> bytes:
        host, port = parse_tcp_url(self.url)
        try:
            with socket.create_connection((host, port), timeout=TIMEOUT_S) as s:
                s.sendall(request)
                return s.makefile("rb").readline()
        except OSError as exc:
            raise CellError(f"the simulators' clock at {self.url} (CNC {self.cnc_url}) did not answer ({exc})") from None

    def _ask(self, scale: float | None) -> float:
        line = self._line(ask(scale))
        try:
            return parse_answer(line)
        except ValueError as exc:
            raise CellError(f"the simulators' clock at {self.url} refused: {exc}") from None

    def inject(self, device: str, fault: str, duration_s: float | None = None) -> None:
        """A seeded fault now, by `device`'s simulator in that `cell sim up` (sims/inject.py)."""
        try:
            parse_ok(self._line(Inject(device, fault, duration_s).line()))
        except ValueError as exc:
            raise CellError(f"the simulators at {self.url} refused {fault} on the {device}: {exc}") from None

    def scale(self) -> float:
        return self._ask(None)

    def set(self, scale: float) -> float:
        got = self._ask(scale)
        if abs(got - scale) > 1e-9:
            raise CellError(f"the simulators' clock at {self.url} runs at {got:g}, not {scale:g}")
        return got


class FedScale:
    """The time scale of one command against `cell sim up`: lowered where the host cannot feed the
    job at cell.yaml's, and given back by `restore()`."""

    def __init__(self, cfg: CellConfig, note: str | None = None, clock: SimClockLink | None = None,
                 configured: float | None = None) -> None:
        self.cfg = cfg
        self.note = note
        self.clock = clock
        self.configured = configured if configured is not None else cfg.cell.time_scale

    @classmethod
    def lower(cls, cfg: CellConfig, job: CellJob, max_step_mm: float = 2.0) -> "FedScale":
        """Before any device: cfg at the scale the CNC link can feed `job`, the simulators' clock set
        to it (InputError when it must be lowered and no clock answers: real devices, or an older
        `cell sim up`)."""
        limited, note = limit_time_scale(cfg, job, max_step_mm, beside=True)   # `cell sim up`: a process of its own
        if note is None:
            return cls(cfg)
        clock = SimClockLink.find(cfg.devices.cnc.url)
        if clock is None:
            raise InputError(note.replace("; time scale limited to", "; run the simulators at time scale")
                             + " or less (cell.yaml cell.time_scale; restart `cell sim up` with it: the "
                               f"simulators serving {cfg.devices.cnc.url} name no clock to lower), or give --sim "
                               "to run them here at that scale")
        clock.set(limited.cell.time_scale)
        return cls(limited, note + f" (the simulators of `cell sim up` now run at {limited.cell.time_scale:g})",
                   clock, cfg.cell.time_scale)

    def set(self, scale: float) -> None:
        """The simulators at `scale` (a repair's probing at the cell's own, its build at the fed one)."""
        if self.clock is not None:
            self.clock.set(scale)

    def restore(self) -> None:
        """The simulators back at cell.yaml's time scale (best effort: they may be gone)."""
        if self.clock is not None:
            try:
                self.clock.set(self.configured)
            except CellError:
                pass
