"""Cell I/O simulator: the remote I/O coupler of the cell on Modbus TCP (docs/contract.md §5).

Discrete inputs 0 door closed, 1 E-stop released, 2 gas pressure OK, 3 fume extraction
running; coils 0 gas valve, 1-3 beacon green / amber / red, 4 door lock; input registers 0 part
temperature (pyrometer, 0.1 °C), 1 gas flow (0.1 L/min). The pyrometer reads a lumped thermal
model of the part heated by η·U·I while the arc burns (the World's heat power) and cooling
toward ambient, in simulated time, so interpass waits behave like a real part.

Tests (and the fault spec: door_open@t=20s, estop@t=..., durations door_open=5s) open the door
or press E-stop at a chosen simulated time: `open_door(at=...)`, `press_estop(at=...)`.
"""
from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable

from sims.clock import SimClock
from sims.context import Served, SimContext, attach
from sims.faults import FaultSpec, parse_fault_spec
from sims.thermal import LumpedThermal
from sims.world import World
from wire.cellio_map import COILS, INPUTS, to_register
from wire.urls import parse_tcp_url

GAS_FLOW_L_MIN = 15.0
TICK_S = 0.010


class CellIOSim:
    """The coupler's state, the part's temperature and scheduled operator actions."""

    def __init__(self, *, clock: SimClock | None = None, world: World | None = None,
                 thermal: LumpedThermal | None = None, faults: FaultSpec | None = None) -> None:
        self.clock = clock or SimClock(1.0)
        self.world = world
        self.thermal = thermal or LumpedThermal()
        self.inputs = {k: True for k in INPUTS}
        self.coils = {k: False for k in COILS}
        self._t = self.clock.now()
        self._scheduled: list[tuple[float, str, bool]] = []   # (sim t, input, value)
        self._silent_until = 0.0
        self.log: list[dict[str, object]] = []
        self.reads = 0
        if faults is not None:
            for name, key in (("door_open", "door_closed"), ("estop", "estop_released")):
                dur = faults.value(name, None)
                for cond, v in faults.events(name):
                    if cond == "t":
                        self._scheduled.append((float(v), key, False))
                        if dur:
                            self._scheduled.append((float(v) + float(dur), key, True))
            sil = faults.value("silence", None)
            self._silence_events = [float(v) for c, v in faults.events("silence") if c == "t"]
            self._silence_dur: float | None = None if sil is None else float(sil)
        else:
            self._silence_events, self._silence_dur = [], None

    # -- operator actions (now, or at simulated time `at`) ------------------------------------
    def _set(self, key: str, value: bool, at: float | None) -> None:
        if at is not None and at > self.clock.now():
            self._scheduled.append((at, key, value))
            return
        if self.inputs[key] != value:
            self.inputs[key] = value
            self.log.append({"t": time.monotonic(), "t_sim": self.clock.now(), "input": key, "value": value})

    def open_door(self, at: float | None = None) -> None:
        self._set("door_closed", False, at)

    def close_door(self, at: float | None = None) -> None:
        self._set("door_closed", True, at)

    def press_estop(self, at: float | None = None) -> None:
        self._set("estop_released", False, at)

    def release_estop(self, at: float | None = None) -> None:
        self._set("estop_released", True, at)

    def set_gas_pressure(self, ok: bool, at: float | None = None) -> None:
        self._set("gas_ok", ok, at)

    def set_fume_extraction(self, running: bool, at: float | None = None) -> None:
        self._set("fume_ok", running, at)

    def inject(self, fault: str, *, duration_s: float | None = None) -> None:
        """An operator's action now (the seeded-fault names of sims/faults.py): `door_open` or
        `estop`, for `duration_s` wall seconds (None: until `door_close` / `estop_release`)."""
        acts = {"door_open": ("door_closed", False), "door_close": ("door_closed", True),
                "estop": ("estop_released", False), "estop_release": ("estop_released", True)}
        if fault not in acts:
            raise ValueError(f"the cell I/O takes {', '.join(acts)}, not {fault!r}")
        key, value = acts[fault]
        self._set(key, value, None)
        if duration_s is not None and not value:
            self._set(key, True, self.clock.now() + duration_s * self.clock.time_scale)

    def silence(self, duration_s: float | None = None) -> None:
        """Stop answering for `duration_s` wall seconds (None: for ever)."""
        self._silent_until = float("inf") if duration_s is None else time.monotonic() + duration_s

    def silent(self) -> bool:
        return time.monotonic() < self._silent_until

    # -- physics --------------------------------------------------------------------------------
    def tick(self) -> None:
        t = self.clock.now()
        due = sorted(x for x in self._scheduled if x[0] <= t)
        if due:
            self._scheduled = [x for x in self._scheduled if x[0] > t]
            for _, key, value in due:
                self._set(key, value, None)
        for ts in list(self._silence_events):
            if ts <= t:
                self._silence_events.remove(ts)
                self.silence(self._silence_dur)
        power = self.world.heat_power_w() if self.world is not None else 0.0
        self.thermal.step(power, t - self._t)
        self._t = t

    @property
    def part_temperature_c(self) -> float:
        return float(self.thermal.temperature_c)

    @property
    def gas_flow_l_min(self) -> float:
        return GAS_FLOW_L_MIN if self.coils["gas_valve"] and self.inputs["gas_ok"] else 0.0

    # -- Modbus view -------------------------------------------------------------------------------
    def read(self, fc: int, address: int, count: int) -> list[bool] | list[int] | None:
        self.tick()
        self.reads += 1
        vals: list[bool] | list[int]
        if fc == 2:
            vals = [self.inputs[k] for k in INPUTS]
        elif fc == 1:
            vals = [self.coils[k] for k in COILS]
        elif fc == 4:
            vals = [to_register(self.part_temperature_c), to_register(self.gas_flow_l_min)]
        else:
            return None
        if address < 0 or address + count > len(vals):
            return None
        return vals[address:address + count]

    def write(self, fc: int, address: int, values: list[int]) -> bool:
        if fc not in (5, 15) or address < 0 or address + len(values) > len(COILS):
            return False
        for i, v in enumerate(values):
            key = COILS[address + i]
            if self.coils[key] != bool(v):
                self.coils[key] = bool(v)
                self.log.append({"t": time.monotonic(), "t_sim": self.clock.now(), "coil": key, "value": bool(v)})
        return True

    async def run(self) -> None:
        while True:
            self.tick()
            await asyncio.sleep(TICK_S)


async def serve_modbus_tcp(sim: CellIOSim, host: str = "127.0.0.1", port: int = 0,
                           device_id: int = 1) -> tuple[str, Callable[[], Awaitable[None]]]:
    """Start the coupler on Modbus TCP and the model's ticking; returns (url, close)."""
    # lazy: sims.up imports every simulator module (a cycle at import time)
    from sims.modbus_server import serve_tcp
    return await serve_tcp(sim, host, port, device_id)


async def serve(ctx: SimContext) -> list[Served]:
    """`cell sim up`: the cell I/O coupler on cell.yaml's URL."""
    cfg = ctx.cell.devices.cellio
    th = ctx.sim.thermal
    thermal = LumpedThermal(th.ambient_c, th.heat_capacity_j_k, th.cooling_time_constant_s)
    sim = CellIOSim(clock=ctx.clock, world=ctx.world, thermal=thermal,
                    faults=parse_fault_spec(ctx.faults or ctx.sim.faults))
    phys = attach(ctx)
    if phys is not None:   # the bead height's temperature term reads the pyrometer's truth
        phys.set_temperature_source(lambda: sim.part_temperature_c)
    host, port = parse_tcp_url(cfg.url)
    url, close = await serve_modbus_tcp(sim, host, 0 if ctx.ephemeral else port, cfg.device_id)
    return [Served("cellio", url, close, sim=sim)]
