"""The simulators in this process (`--sim`, the demo, tests and benches): every device on a
background thread and event loop of its own, on loopback URLs the drivers open as real ones."""
from __future__ import annotations

import asyncio
import gc
import inspect
import os
import sys
import threading
from pathlib import Path
from typing import Any, Awaitable, Callable, TypeVar

from controller.runtime.devices import with_urls as with_urls  # re-exported: `cell run --sim` and the TUI take it from here
from core.config import CellConfig, SimConfig, load_material
from core.realtime import SIM_RT_PRIORITY, elevate
from drivers.cyclic import device_thread
from sims.clock import SimClock
from sims.faults import parse_fault_spec
from sims.loop import precise_loop
from sims.up import SimContext, close_all, serve_all
from sims.inject import inject
from sims.world import World
from core.errors import CellError

T = TypeVar("T")


class SimHarness:
    """Every simulator in this process, on a background thread and loop of its own."""

    in_process = True   # controller/api/simulated.py: its simulators' objects are reachable

    def __init__(self, cfg: CellConfig, sim: SimConfig, log_dir: str | Path | None = None,
                 faults: str = "", modules: list[str] | None = None, config_dir: Path | None = None) -> None:
        self.cfg, self.sim_cfg = cfg, sim
        self.log_dir = Path(log_dir) if log_dir else None
        self.faults = faults
        self.modules = modules
        self.config_dir = config_dir   # where the sim config's relative paths start (None: config/)
        self.loop = precise_loop()   # the simulators' timers on time (sims/loop.py)
        self.thread = threading.Thread(target=self._run, name="sims", daemon=True)
        self.served: dict[str, Any] = {}
        self.world: Any = None
        self.clock: Any = None

    def _run(self) -> None:
        # the simulated devices keep their own time: time-shared, this thread was preempted by
        # any CPU-bound process while it held the interpreter lock, and the controller's
        # real-time loop waited for it (the robot's heartbeat missed for 3 s under two CPU hogs)
        elevate("in-process simulators", SIM_RT_PRIORITY)
        asyncio.set_event_loop(self.loop)
        device_thread(threading.get_ident())   # its CPU time is the devices', not the controller's (docs/testing.md)
        try:
            self.loop.run_forever()
        finally:
            device_thread(threading.get_ident(), present=False)

    def start(self, timeout: float = 20.0) -> dict[str, str]:
        """Start the simulators; returns device -> URL."""
        # The simulated devices share this process (and its GIL) with the controller: switch
        # threads more often than the default 5 ms so a 10 ms bus cycle is answered in time.
        sys.setswitchinterval(0.0005)
        mat = load_material(self.cfg.cell.material)
        self.world = World(self.log_dir, arc_efficiency=mat.arc_efficiency)
        self.clock = SimClock(self.cfg.cell.time_scale)
        ctx = SimContext(cell=self.cfg, sim=self.sim_cfg, world=self.world, clock=self.clock,
                         log_dir=self.log_dir, ephemeral=True, faults=self.faults, config_dir=self.config_dir)
        self.thread.start()
        fut = asyncio.run_coroutine_threadsafe(serve_all(ctx, self.modules), self.loop)
        served = fut.result(timeout)
        self.served = {s.device: s for s in served}
        gc.freeze()  # full collections of the heap would stall the simulated devices (~100 ms)
        return {s.device: s.url for s in served}

    def sim(self, device: str) -> object:
        """The simulator object of a device (tests open the door, inject faults...)."""
        return self.served[device].sim

    def call(self, fn: Callable[..., T | Awaitable[T]], *args: object, **kwargs: object) -> T:
        """Run `fn(*args, **kwargs)` on the simulators' loop and return its result (thread-safe)."""
        async def _do() -> T:
            res = fn(*args, **kwargs)
            if inspect.isawaitable(res):
                return await res
            return res
        return asyncio.run_coroutine_threadsafe(_do(), self.loop).result(10)

    def inject(self, device: str, fault: str, *, duration_s: float | None = None) -> None:
        """A seeded fault now, by the device's simulator (sims/inject.py: the power source's faults, the
        cell I/O's door and E-stop)."""
        try:
            self.call(inject, {x.device: x.sim for x in self.served.values()}, device, fault, duration_s)
        except ValueError as exc:
            raise CellError(str(exc)) from None

    @property
    def process_id(self) -> int:
        return os.getpid()

    def set_time_scale(self, scale: float) -> None:
        """Process time / wall time of every simulated device from now on."""
        self.clock.set_scale(scale)

    def stop(self) -> None:
        if self.thread.is_alive():
            try:
                asyncio.run_coroutine_threadsafe(close_all(list(self.served.values())), self.loop).result(10)
            except Exception:
                pass
            self.loop.call_soon_threadsafe(self.loop.stop)
            self.thread.join(5)
        if self.world is not None:
            self.world.close()



def check_fault_spec(spec: str) -> None:
    """A ConfigError naming the bad key or value of a seeded fault spec (`--fault`)."""
    parse_fault_spec(spec)
