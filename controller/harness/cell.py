"""One way to open a cell (docs/architecture.md "Opening a cell"): `open_cell(cfg, sim=...)`.

    async with open_cell(cfg, sim=load_sim(), log_dir=tmp / "log") as ctl:
        ctl.open_job(job)
        result = await ctl.start()

It yields the one API object (`controller.api.CellController`), connected unless `connect=False`
(a caller that installs its signal handlers first, or refuses something before any device), and
closes it after the body (devices released, journal closed). With `sim` the simulators start
first, in this process (`SimHarness`), or with `process=True` as `cell sim up` in a child of its
own (the demo's topology); the configuration the controller gets points at them, and
`ctl.simulators` reaches them (controller/api/simulated.py). Without `sim`, the devices of
cell.yaml (hardware, or `cell sim up` started elsewhere). The CLI, the TUI, the repair chain,
the tests and the benches all open a cell here.
"""
from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path

from controller.api import CellController
from controller.api.simulated import Simulators
from controller.defaults import sim_reply_timeout_ms
from controller.harness.sim import SimHarness
from controller.runtime.devices import with_urls as with_urls   # a cell's config pointed at URLs / a time scale
from controller.harness.sim_process import SimProcess
from controller.runtime.build import BuildOptions
from core.config import CellConfig, SimConfig, load_sim

__all__ = ["open_cell", "start_simulators", "with_urls"]


async def start_simulators(cfg: CellConfig, sim: SimConfig | bool | None, *, log_dir: str | Path | None = None,
                           faults: str = "", process: bool = False,
                           modules: list[str] | None = None, config_dir: Path | None = None,
                           start_timeout_s: float = 20.0, sim_config: str | Path | None = None,
                           ) -> tuple[CellConfig, SimHarness | SimProcess | None]:
    """The simulators `sim` asks for, started within `start_timeout_s` (None: none), and `cfg`
    pointing at them. With `process`, `cell sim up` on `sim_config` (default config/sim.yaml)."""
    if sim is None or sim is False:
        return cfg, None
    if process:   # `cell sim up` reads its sim.yaml itself
        if sim is not True:
            raise ValueError("open_cell(process=True) runs `cell sim up` on a sim.yaml file: give sim=True "
                             "(and sim_config=FILE)")
        proc = await asyncio.to_thread(SimProcess, cfg, Path(log_dir or "sim"),
                                       str(sim_config) if sim_config is not None else None, faults=faults)
        return proc.cfg, proc
    sim_cfg = load_sim() if sim is True else sim
    harness = SimHarness(cfg, sim_cfg, log_dir=log_dir, faults=faults, modules=modules, config_dir=config_dir)
    try:
        urls = await asyncio.to_thread(harness.start, start_timeout_s)
    except BaseException:
        harness.stop()
        raise
    return with_urls(cfg, urls), harness


@asynccontextmanager
async def open_cell(cfg: CellConfig, *, sim: SimConfig | bool | None = None, runs_dir: str | Path | None = None,
                    options: BuildOptions | None = None, log_dir: str | Path | None = None, faults: str = "",
                    process: bool = False, connect: bool = True, resume_ticket: int | None = None,
                    reply_timeout_ms: float | None = None, simulators: SimHarness | SimProcess | None = None,
                    modules: list[str] | None = None, config_dir: Path | None = None,
                    start_timeout_s: float = 20.0, sim_config: str | Path | None = None) -> AsyncIterator[CellController]:
    """The cell of `cfg` (on the simulators `sim`, in this process or with `process` in a child),
    its API object yielded connected (unless `connect=False`), closed and the simulators stopped
    after the body. `reply_timeout_ms`: the bus devices' reply timeout (default: the devices' own;
    in-process simulators: `controller.defaults.sim_reply_timeout_ms()`, they share this interpreter).
    `simulators`: ones already running (`start_simulators`, `cfg` pointing at them): the cell opens
    on them and leaves them running (a second controller on the same simulated cell, a reconnect).
    `modules`: only these simulators (sims/up.py SIM_MODULES names; `cell align run --sim`: the
    CNC's); `config_dir`: where the sim config's relative paths start; `start_timeout_s`: how long
    the in-process simulators may take to come up (a host running many cells at once); `sim_config`:
    the sim.yaml `cell sim up` reads with `process` (default config/sim.yaml)."""
    own = simulators is None
    if own:
        cfg, simulators = await start_simulators(cfg, sim, log_dir=log_dir, faults=faults, process=process,
                                                 modules=modules, config_dir=config_dir,
                                                 start_timeout_s=start_timeout_s, sim_config=sim_config)
    sims = simulators
    try:
        if reply_timeout_ms is None and isinstance(sims, SimHarness):
            reply_timeout_ms = sim_reply_timeout_ms()
        reach: Simulators | None = sims
        ctl = CellController(cfg, runs_dir=runs_dir, options=options, reply_timeout_ms=reply_timeout_ms,
                             simulators=reach)
        try:
            if connect:
                await ctl.connect(resume_ticket=resume_ticket)
            yield ctl
        finally:
            await ctl.close()
    finally:
        if own and sims is not None:
            await asyncio.to_thread(sims.stop)
