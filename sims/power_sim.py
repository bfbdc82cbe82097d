"""Power-source simulator: a synergic MIG/MAG source on Modbus TCP, Modbus RTU and CAN.

The model (`PowerSourceSim`) is transport-free: each host cycle hands it the command (bits,
mode/job, WFS, trims, watchdog counter) and takes the status back (docs/contract.md §5). It runs

    idle -> pre-flow -> ignition -> current flow -> arc stable (motion release after 16 ms)
         -> burn-back (weld start dropped) -> post-flow -> idle

with synergic actuals (current from WFS along the material's synergic line, voltage from WFS
and arc-length trim along a configurable line), the watchdog (weld start dropped and an error
latched when the counter has not changed for 100 ms) and the faults: ignition failure, arc loss
for a time, wire stick, gas fault, wire out, collision, silence. A latched fault clears on a
rising edge of error reset.

Timing. Process phases (pre-flow, ignition delay, burn-back, post-flow) are process time: they
are divided by the time scale, with a floor of two bus cycles (20 ms) so each phase is still
seen on the bus. Link and supervision timing (the watchdog's 100 ms, the 16 ms arc-stable hold,
arc-loss durations given to `inject`) is wall time, never scaled. Fault-spec events `@t=` are in
simulated seconds (`clock.now()`), `@pass=N` on the N-th weld start.

Transports (sims/power_servers.py): `serve_modbus_tcp`, `serve_modbus_rtu` (a serial URL;
`socket://` listens on TCP with RTU framing) and `CanNode` on any python-can bus (`virtual`
in-process, `udp_multicast` between processes). `serve(ctx)` starts the one that cell.yaml's
`devices.power_source` names. Timing constants, error numbers, the synergic line and the
process times: sims/power_params.py.
"""
from __future__ import annotations

import asyncio
import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np

from core.material import Material
from sims.clock import SimClock
from sims.context import Served, SimContext, attach
from sims.faults import FaultSpec, parse_fault_spec
from sims.power_params import (
    ARC_HOLD_S, DEFAULT_LINE, DEFAULT_TIMES, ERR_COLLISION, ERR_GAS, ERR_NONE, ERR_WATCHDOG, ERR_WIRE_OUT, ERR_WIRE_STICK, ERROR_TEXT,
    MIN_PHASE_WALL_S, SELF_STALL_S, TICK_S, WATCHDOG_S, PowerStatus, ProcessTimes, SynergicLine, HostCommand,
)
from sims.power_servers import CanNode, serve_can, serve_modbus_rtu, serve_modbus_tcp
from sims.world import World
from wire.urls import parse_tcp_url
from core.errors import ConfigError
from wire.can_codec import dbc_path
from core.config import load_material
import json

# what tests, benchmarks and `cell sim up` import from here (their home modules: power_params, power_servers)
__all__ = ["ARC_HOLD_S", "ERROR_TEXT", "ERR_COLLISION", "ERR_GAS", "ERR_NONE", "ERR_WATCHDOG", "ERR_WIRE_OUT",
           "ERR_WIRE_STICK", "MIN_PHASE_WALL_S", "SELF_STALL_S", "TICK_S", "WATCHDOG_S", "CanNode",
           "PowerSourceSim", "PowerStatus", "ProcessTimes", "SynergicLine", "serve", "serve_can",
           "serve_modbus_rtu", "serve_modbus_tcp"]


@dataclass
class _SpecEvent:
    """A fault-spec event (`name@t=...` / `name@pass=N`) and whether it has fired."""

    cond: str
    at: float
    name: str
    duration: float | int | None
    done: bool = False


class PowerSourceSim:
    """The power source's behaviour; thread-unsafe, driven from one asyncio loop."""

    def __init__(self, material: Material, *, clock: SimClock | None = None, world: World | None = None,
                 line: SynergicLine = DEFAULT_LINE, times: ProcessTimes = DEFAULT_TIMES,
                 faults: FaultSpec | None = None, seed: int = 0, state_path: str | Path | None = None) -> None:
        self.material = material
        self.clock = clock or SimClock(1.0)
        self.world = world
        self.line = line
        self.times = times
        self.cmd = HostCommand()
        self._prev_reset = False
        self.phase = "idle"
        self._phase_t = time.monotonic()
        self._arc_since: float | None = None
        self.error = ERR_NONE
        self.flags = {"gas_fault": False, "wire_out": False, "wire_stick": False, "collision": False}
        self._counter_t = time.monotonic()
        self._last_tick = self._counter_t
        self.self_stalls = 0          # ticks that came late because this process did not run
        self._heartbeat = False
        self._arc_loss_until = 0.0
        self._silent_until = 0.0
        self._ignition_fail_next = 0
        self._stick_next_end = False
        self.starts = 0
        self.log: list[dict[str, object]] = []            # what the source really did (t wall, t_sim, event)
        self._last_world: tuple[bool, float, float, float] | None = None
        self._actuals = (0.0, 0.0, 0.0)
        self.stick_out_mm: float | None = None    # the last stick-out the current followed (truth)
        self.spec = faults
        self._rng = faults.rng("power_source") if faults is not None else np.random.default_rng(seed)
        self._ign_p = float(faults.value("ignition_fail", 0.0)) if faults is not None else 0.0
        self._events = self._spec_events(faults)
        self._pending_at: list[tuple[float, str, float | None, int]] = []   # (sim t, fault, duration_s, count) from inject(at=)
        self.cycles = 0
        self.history: deque[tuple[float, int, dict[str, bool]]] = deque(maxlen=5000)   # (wall t, counter, bits) of every host cycle
        self._echo_frozen: int | None = None
        # latched_error=N (issue 13): the error survives a restart of the source, kept in
        # `state_path` (the log dir's power_source.state.json) until an error reset clears it
        self._state_path = Path(state_path) if state_path is not None else None
        latched = faults.value("latched_error", None) if faults is not None else None
        if latched is not None:
            self.error = self._persisted() or int(latched)
            if self.error:
                self._log("fault", error=self.error, text="latched at power-up (" +
                          ERROR_TEXT.get(self.error, str(self.error)) + ")")
            self._persist()
        else:
            self._state_path = None

    def _persisted(self) -> int:
        if self._state_path is None or not self._state_path.exists():
            return ERR_NONE
        try:
            return int(json.loads(self._state_path.read_text(encoding="utf-8")).get("error", 0))
        except (ValueError, OSError):
            return ERR_NONE

    def _persist(self) -> None:
        if self._state_path is None:
            return
        self._state_path.parent.mkdir(parents=True, exist_ok=True)
        self._state_path.write_text(json.dumps({"error": self.error}) + "\n", encoding="utf-8")

    # -- faults -----------------------------------------------------------------------------
    @staticmethod
    def _spec_events(spec: FaultSpec | None) -> list[_SpecEvent]:
        out: list[_SpecEvent] = []
        if spec is None:
            return out
        for name in ("arc_loss", "wire_stick", "gas_fault", "wire_out", "silence"):
            dur = spec.value(name, None)
            for cond, v in spec.events(name):
                if cond in ("t", "pass"):
                    out.append(_SpecEvent(cond, float(v), name, dur))
        return out

    def inject(self, fault: str, *, duration_s: float | None = None, count: int = 1,
               at: float | None = None) -> None:
        """Inject a fault now (or at simulated time `at`).

        arc_loss (duration_s wall, default 0.5), ignition_fail (the next `count` starts),
        wire_stick (now while the arc burns, else at the next arc end), gas_fault, wire_out,
        collision (latched until error reset), silence (duration_s wall, None: for ever),
        freeze_echo (the watchdog echo stops following the counter; duration_s=0 ends it).
        """
        if at is not None and at > self.clock.now():
            self._pending_at.append((at, fault, duration_s, count))
            return
        now = time.monotonic()
        self._log("inject", fault=fault, duration_s=duration_s)
        if fault == "arc_loss":
            self._arc_loss_until = now + (0.5 if duration_s is None else duration_s)
        elif fault == "ignition_fail":
            self._ignition_fail_next += count
        elif fault == "wire_stick":
            if self.phase in ("arc", "stabilise"):
                self._latch(ERR_WIRE_STICK, "wire_stick")
            else:
                self._stick_next_end = True
        elif fault == "gas_fault":
            self._latch(ERR_GAS, "gas_fault")
        elif fault == "wire_out":
            self._latch(ERR_WIRE_OUT, "wire_out")
        elif fault == "collision":
            self._latch(ERR_COLLISION, "collision")
        elif fault == "freeze_echo":
            self._echo_frozen = max(self.cmd.counter, 0) if duration_s is None or duration_s > 0 else None
        elif fault == "silence":
            self._silent_until = math.inf if duration_s is None else now + duration_s
        else:
            raise ValueError(f"unknown power-source fault {fault!r}")

    def _latch(self, code: int, flag: str | None) -> None:
        if flag:
            self.flags[flag] = True
        if self.error == ERR_NONE:
            self.error = code
            self._persist()
        self._log("fault", error=code, text=ERROR_TEXT.get(code, str(code)))
        if self.phase != "idle":
            self._set_phase("idle")

    def silent(self) -> bool:
        self._poll_events()
        return time.monotonic() < self._silent_until

    def _poll_events(self) -> None:
        t = self.clock.now()
        if self._pending_at:
            due = [p for p in self._pending_at if p[0] <= t]
            self._pending_at = [p for p in self._pending_at if p[0] > t]
            for _, fault, duration_s, count in due:
                self.inject(fault, duration_s=duration_s, count=count)
        for ev in self._events:
            if ev.done:
                continue
            if (ev.cond == "t" and t >= ev.at) or (ev.cond == "pass" and self.starts >= ev.at and self.phase != "idle"):
                ev.done = True
                dur = ev.duration
                if ev.name == "arc_loss":
                    self.inject("arc_loss", duration_s=0.5 if dur is None else float(dur))
                elif ev.name == "silence":
                    self.inject("silence", duration_s=None if dur is None else float(dur))
                else:
                    self.inject(ev.name)

    # -- host cycle ---------------------------------------------------------------------------
    def command(self, bits: dict[str, bool], mode: int, job: int, wfs: float, arc_trim: float,
                dynamic_trim: float, counter: int) -> None:
        """Take one host cycle's command (already decoded)."""
        now = time.monotonic()
        if counter != self.cmd.counter:
            self._counter_t = now
        reset = bool(bits.get("error_reset"))
        if reset and not self._prev_reset:
            self._error_reset()
        self._prev_reset = reset
        self.cmd = HostCommand(dict(bits), mode, job, wfs, arc_trim, dynamic_trim, counter)
        self.history.append((now, counter, dict(bits)))
        self.cycles += 1
        self._heartbeat = not self._heartbeat
        self.tick(now)

    def _error_reset(self) -> None:
        if self.error or any(self.flags.values()):
            self._log("error_reset", error=self.error)
        self.error = ERR_NONE
        if self._state_path is not None and self._persisted():
            self._persist()
        for k in self.flags:
            self.flags[k] = False

    def status(self) -> PowerStatus:
        """The status of the last tick: echo, bits, error, voltage, current, wfs."""
        p = self.phase
        arc = p in ("arc", "burnback") and not self._arc_lost()
        flow = p in ("stabilise", "arc", "burnback") and not self._arc_lost()
        bits = {
            "heartbeat": self._heartbeat,
            "ready": self.cmd.bits.get("robot_ready", False) and self.error == ERR_NONE,
            "arc_stable": arc,
            "current_flow": flow,
            "main_current": p == "arc" and arc,
            "collision_ok": not self.flags["collision"],
            "gas_fault": self.flags["gas_fault"],
            "wire_out": self.flags["wire_out"],
            "process_active": p != "idle",
            "motion_release": p == "arc" and arc and self._arc_since is not None
            and time.monotonic() - self._arc_since >= ARC_HOLD_S,
            "wire_stick": self.flags["wire_stick"],
        }
        u, i, w = self._actuals
        echo = max(self.cmd.counter, 0) if self._echo_frozen is None else self._echo_frozen
        return {"echo": echo, "bits": bits, "error": self.error,
                "voltage": u, "current": i, "wfs": w}

    # -- the process model ---------------------------------------------------------------------
    def _wall(self, process_s: float) -> float:
        return max(process_s / self.clock.time_scale, MIN_PHASE_WALL_S)

    def _set_phase(self, phase: str) -> None:
        if phase == self.phase:
            return
        self._log("phase", frm=self.phase, to=phase)
        self.phase = phase
        self._phase_t = time.monotonic()
        self._arc_since = time.monotonic() if phase == "arc" else None

    def _arc_lost(self) -> bool:
        return time.monotonic() < self._arc_loss_until

    def _start_requested(self, now: float) -> bool:
        b = self.cmd.bits
        if not b.get("weld_start"):
            return False
        if now - self._counter_t > WATCHDOG_S:
            if self.error != ERR_WATCHDOG:
                self._latch(ERR_WATCHDOG, None)
            return False
        return self.error == ERR_NONE and b.get("robot_ready", False)

    def tick(self, now: float | None = None) -> None:
        """Advance the process to wall time `now` (monotonic)."""
        now = time.monotonic() if now is None else now
        gap = now - self._last_tick
        self._last_tick = max(self._last_tick, now)
        if gap > SELF_STALL_S:
            # the simulator itself did not run (its process was not scheduled): the host's
            # counter frames may be waiting in the socket. Its watchdog only times what it could
            # have heard; a real source does not stall, and a stall here is never the host's fault:
            # the last counter's age goes on from what it was at the last tick (plus one tick).
            # Before 2026-11-28 the age restarted at 15 ms after the last tick, so a stall of the
            # simulator's own longer than 115 ms dropped the start on its watchdog (error 50).
            self._counter_t = min(now, self._counter_t + gap - TICK_S)
            self.self_stalls += 1
            self._log("self_stall", gap_ms=round(gap * 1000, 1))
        self._poll_events()
        start = self._start_requested(now)
        step = self._PHASE_STEPS.get(self.phase)
        if step is not None:
            step(self, start, now - self._phase_t, now)
        self._update_actuals()

    # one step of the phase machine per phase: (start requested, seconds in the phase, wall now)
    def _step_idle(self, start: bool, dt: float, now: float) -> None:
        if start:
            self.starts += 1
            self._set_phase("preflow")
            self._poll_events()

    def _step_preflow(self, start: bool, dt: float, now: float) -> None:
        if not start:
            self._set_phase("postflow")
        elif dt >= self._wall(self.times.preflow_s):
            fail = self._ignition_fail_next > 0 or (self._ign_p > 0 and self._rng.random() < self._ign_p)
            if self._ignition_fail_next > 0:
                self._ignition_fail_next -= 1
            self._set_phase("ignition_failed" if fail else "ignition")

    def _step_ignition(self, start: bool, dt: float, now: float) -> None:
        if not start:
            self._set_phase("postflow")
        elif self.phase == "ignition" and dt >= self._wall(self.times.ignition_s):
            self._set_phase("stabilise")

    def _step_stabilise(self, start: bool, dt: float, now: float) -> None:
        if not start:
            self._set_phase("burnback")
        elif dt >= self._wall(self.times.stabilise_s):
            self._set_phase("arc")

    def _step_arc(self, start: bool, dt: float, now: float) -> None:
        if not start:
            self._set_phase("burnback")
        elif self._arc_lost():
            self._arc_since = None
        elif self._arc_since is None:
            self._arc_since = now

    def _step_burnback(self, start: bool, dt: float, now: float) -> None:
        if dt >= self._wall(self.times.burnback_s):
            if self._stick_next_end:
                self._stick_next_end = False
                self.flags["wire_stick"] = True
                self.error = self.error or ERR_WIRE_STICK
                self._persist()
                self._log("fault", error=ERR_WIRE_STICK, text="wire stick")
            self._set_phase("postflow")

    def _step_postflow(self, start: bool, dt: float, now: float) -> None:
        if start:
            self.starts += 1
            self._set_phase("preflow")
        elif dt >= self._wall(self.times.postflow_s):
            self._set_phase("idle")

    _PHASE_STEPS: ClassVar[dict[str, Callable[[PowerSourceSim, bool, float, float], None]]] = {
        "idle": _step_idle, "preflow": _step_preflow, "ignition": _step_ignition,
        "ignition_failed": _step_ignition, "stabilise": _step_stabilise, "arc": _step_arc,
        "burnback": _step_burnback, "postflow": _step_postflow,
    }

    def synergic(self, wfs: float, arc_trim: float) -> tuple[float, float]:
        """(voltage V, current A) on the synergic line for a wire feed and an arc-length trim."""
        r = self.material.ribeiro
        i = r.i_min_a + (wfs - r.wfs_min_m_min) * (r.i_max_a - r.i_min_a) / (r.wfs_max_m_min - r.wfs_min_m_min)
        u = self.line.u0_v + self.line.v_per_m_min * wfs + self.line.v_per_trim * arc_trim
        return max(u, 0.0), max(i, 0.0)

    def _update_actuals(self) -> None:
        p, c = self.phase, self.cmd
        lost = self._arc_lost()
        if p in ("stabilise", "arc") and not lost:
            u, i = self.synergic(c.wfs, c.arc_trim)
            i = self._melting_current(c.wfs, i)
            n, ni = self.line.noise, self.material.melting.current_noise_pct / 100.0
            if n or ni:
                u *= 1 + n * float(self._rng.standard_normal())
                i *= 1 + ni * float(self._rng.standard_normal())
            w = c.wfs
        elif p == "burnback" and not lost:
            u, i = self.synergic(c.wfs, c.arc_trim)
            u, i, w = u * 1.1, i * 0.3, 0.0
        elif p in ("preflow", "ignition", "ignition_failed", "stabilise", "arc"):
            u, i, w = 60.0 if p != "preflow" else 0.0, 0.0, (c.wfs * 0.3 if p.startswith("ignition") else 0.0)
        elif c.bits.get("wire_inch") and self.error == ERR_NONE:
            u, i, w = 0.0, 0.0, c.wfs or 1.0
        elif c.bits.get("wire_retract") and self.error == ERR_NONE:
            u, i, w = 0.0, 0.0, -(c.wfs or 1.0)
        else:
            u, i, w = 0.0, 0.0, 0.0
        self._actuals = (u, i, w)
        stable = p in ("arc", "burnback") and not lost
        key = (stable, round(u, 2), round(i, 1), round(w, 2))
        if self.world is not None and key != self._last_world:
            self.world.set_arc(stable, i, u, self.clock.now(), w)
        self._last_world = key

    def _melting_current(self, wfs: float, synergic_a: float) -> float:
        """The current at the torch's actual stick-out (the World's physics), else the synergic line's."""
        phys = self.world.physics if self.world is not None else None
        if phys is None:
            return synergic_a
        stick_out = self.world.stick_out_mm() if self.world is not None else None
        if stick_out is None:
            return synergic_a
        self.stick_out_mm = stick_out
        return max(phys.current_a(wfs, stick_out, synergic_a), 0.0)

    def _log(self, event: str, **kw: object) -> None:
        self.log.append({"t": time.monotonic(), "t_sim": self.clock.now(), "event": event, **kw})

    # -- background ticking (watchdog, phases) ------------------------------------------------
    async def run(self) -> None:
        """Advance the model every 5 ms even when no host cycle comes (watchdog, post-flow)."""
        while True:
            self.tick()
            await asyncio.sleep(TICK_S)


async def serve(ctx: SimContext) -> list[Served]:
    """`cell sim up`: the power source on the transport and URL of cell.yaml."""
    cfg = ctx.cell.devices.power_source
    material = load_material(ctx.cell.cell.material)
    spec = parse_fault_spec(ctx.faults or ctx.sim.faults)
    attach(ctx)
    sim = PowerSourceSim(material, clock=ctx.clock, world=ctx.world, faults=spec,
                         state_path=(Path(ctx.log_dir) / "power_source.state.json") if ctx.log_dir else None)
    extra: dict[str, object] = {"transport": cfg.transport}
    if cfg.transport == "modbus_tcp":
        host, port = parse_tcp_url(cfg.url)
        url, close = await serve_modbus_tcp(sim, host, 0 if ctx.ephemeral else port, cfg.device_id)
    elif cfg.transport == "modbus_rtu":
        u = cfg.url
        if u.startswith("tcp://"):
            raise ConfigError("devices.power_source.url: transport modbus_rtu needs a serial URL "
                              f"(socket://host:port, a port); got {u}")
        if ctx.ephemeral and u.startswith("socket://"):
            u = u.rsplit(":", 1)[0] + ":0"
        url, close = await serve_modbus_rtu(sim, u, cfg.device_id)
    else:
        dbc = dbc_path(cfg.can.dbc, ctx.config_dir)
        url, close = await serve_can(sim, cfg.can.interface, cfg.can.channel, dbc, cfg.can.node,
                                     allow_network=cfg.can.allow_network)
        extra.update({"interface": cfg.can.interface, "channel": cfg.can.channel, "node": cfg.can.node})
    return [Served("power_source", url, close, sim=sim, extra=extra)]
