"""A simulated cell and small jobs for the build tests (opened the one way, controller/harness/cell.py)."""
from __future__ import annotations

import asyncio
import time
from pathlib import Path
from typing import Any

from controller.api import CellController
from controller.defaults import SIM_REPLY_TIMEOUT_MS
from controller.harness.cell import open_cell
from controller.harness.sim import with_urls
from core.config import CellConfig, load_cell, load_sim
from tests.jobs import JobSpec, PassSpec, job_object, square


def small_job(n_layers: int = 3, side: float = 20.0, h: float = 1.0) -> dict[str, Any]:
    """The build tests' square, its file's object: per layer an outer loop of `side` mm and an inner
    10 mm loop, 5 mm beads at 120 A, 600 mm/min, 5.5 m/min (made by the planner's writer, tests/jobs.py)."""
    loops = [PassSpec(square(side)), PassSpec(square(10.0, 5.0, 5.0))]
    return job_object([loops] * n_layers, JobSpec(layer_height=h, name="square"))


def shorten(job: dict, layers: range) -> dict:
    """Make the given layers quick to build (one 10 mm bead each pass) to reach a later one fast."""
    for li in layers:
        for p in job["layers"][li]["passes"]:
            x, y, z = p["points"][0]
            p["points"] = [[x, y, z], [x + 10.0, y, z]]
    return job


def cnc_cell(time_scale: float) -> CellConfig:
    """The shipped cell on its CNC (platform cnc), wired to simulators at `time_scale`."""
    cfg = with_urls(load_cell(), {}, time_scale=time_scale)
    return cfg.model_copy(update={"cell": cfg.cell.model_copy(update={"platform": "cnc"})})


def on_the_cnc_block(job: dict) -> dict:
    """The job lifted onto the CNC simulator's substrate block (20 mm tall)."""
    for la in job["layers"]:
        for p in la["passes"]:
            p["points"] = [[x, y, z + 20.0] for x, y, z in p["points"]]
    return job


def planned(job: dict) -> list:
    return [p["points"] for la in job["layers"] for p in la["passes"]]


class Cell:
    """A simulated cell, opened the one way (controller/harness/cell.py `open_cell`): `ctl` the API
    object, `harness` its simulators, `log` their record."""

    def __init__(self, tmp: Path, scale: float, faults: str = "") -> None:
        self.log = tmp / "log"
        self._open = open_cell(with_urls(load_cell(), {}, time_scale=scale), sim=load_sim(), log_dir=self.log,
                               faults=faults, runs_dir=tmp / "runs", reply_timeout_ms=SIM_REPLY_TIMEOUT_MS)

    async def __aenter__(self) -> "Cell":
        self.ctl: CellController = await self._open.__aenter__()
        self.harness = self.ctl.simulators
        self.cfg = self.ctl.cfg
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self._open.__aexit__(*exc)

    async def wait_for(self, pred, timeout: float = 30.0) -> None:
        t0 = time.monotonic()
        while not pred(self.ctl.snapshot()):
            assert time.monotonic() - t0 < timeout, f"timed out; state {self.ctl.snapshot().state} {self.ctl.snapshot().alarms} {self.ctl.interlocks.trips}"
            await asyncio.sleep(0.002)

