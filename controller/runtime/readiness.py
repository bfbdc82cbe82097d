"""Readiness before motion (docs/contract.md §6, issue 13): every device is checked before the first move.

After a fault, an abort or a crash the devices may still carry what happened: a power source
with an error latched (its watchdog after a crash), a robot with moves queued or in FAULT, a
CNC in alarm or with the process on. `ensure_ready` runs after the executor's `prepare()` (which
flushes the motion queue with `!ABORT` / `!RESET` or grbl's unlock) and before anything moves:

- power source: error number 0 and no process active. A latched error is cleared only by an
  explicit error-reset step (`cell resume`, `cell run --reset-errors`, or the operator's reset),
  which is journaled with the error it cleared; otherwise the run is refused with a message
  saying how.
- robot: state IDLE and the queue empty (queue_free equals the queue size).
- CNC: not in alarm (after the executor's unlock); the process is switched off (`M5`).

A refusal is a `NotReady` (a CellError): the build faults before any motion, and the alarm
names the device and what to do.
"""
from __future__ import annotations

import asyncio
import time
from typing import Callable

from controller.journal.store import Journal
from controller.ports import ArcControl, CncLinkPort, MotionExecutor, PowerSourcePort, RobotLinkPort
from core.errors import CellError
from drivers.power import PowerStatus

POWER_SETTLE_S = 2.0   # wall seconds for the source to report idle after an error reset


class NotReady(CellError):
    """A device is not ready for motion; the message names it and says what to do."""


async def _power_status(power: PowerSourcePort, timeout: float = 1.0) -> PowerStatus:
    st = power.status
    if st is None:
        st = await asyncio.wait_for(power.next_status(), timeout)
    return st


async def check_power(power: PowerSourcePort, journal: Journal | None, *, reset_errors: bool,
                      arc: ArcControl | None = None) -> None:
    """No latched error (cleared by a journaled error reset when allowed) and no process active."""
    st = await _power_status(power)
    err = int(st.error_number or 0)
    if err:
        where = power.url
        if not reset_errors:
            raise NotReady(f"power source at {where}: error {err} is latched from an earlier run; nothing "
                           "moved. Check the source, then clear it with `cell run JOB --reset-errors` "
                           "(or `cell resume`), which sends an error reset and journals it")
        if journal is not None:
            journal.event("info", f"readiness: error reset of the power source (error {err} latched)")
        if arc is not None:
            await arc.reset()
        else:
            power.drop_all()
            await power.error_reset()
        st = await _wait_power(power, lambda s: not s.error_number)
        err = int(st.error_number or 0)
        if err:
            raise NotReady(f"power source at {where}: error {err} is still latched after an error reset; "
                           "the source needs attention (see its display) before a build")
        if journal is not None:
            journal.event("info", "readiness: power source error cleared")
    st = await _wait_power(power, lambda s: not s.process_active and not s.arc_stable)
    if st.process_active or st.arc_stable:
        raise NotReady(f"power source at {power.url}: process still active "
                       f"{POWER_SETTLE_S:.0f} s after weld start was dropped; check the source")


async def _wait_power(power: PowerSourcePort, ok: Callable[[PowerStatus], bool],
                      timeout: float = POWER_SETTLE_S) -> PowerStatus:
    st = await _power_status(power)
    t0 = time.monotonic()
    while not ok(st) and time.monotonic() - t0 < timeout:
        st = await asyncio.wait_for(power.next_status(), 1.0)
    return st


async def check_robot(link: RobotLinkPort) -> None:
    """State IDLE, queue empty (every slot of the queue size learned at connect free), no latched protocol fault."""
    if link.protocol_fault:
        raise NotReady(f"robot at {link.url}: {link.fault}; reset the cell to clear it")
    st = await link.status()
    cap = link.queue_capacity
    if st.state != "IDLE" or (cap and st.queue_free != cap):
        raise NotReady(f"robot at {link.url}: state {st.state} with {st.queue_free} of {cap} queue slots free "
                       f"after the flush (expected IDLE, empty queue); check the robot controller")


async def check_cnc(link: CncLinkPort) -> None:
    """Not in alarm, the process off."""
    st = await link.status()
    if st.state.startswith("Alarm"):
        raise NotReady(f"CNC at {link.url}: in {st.state} after the unlock; home or reset it")
    # the process off whatever the CNC reports (grbl's FS speed is the programmed S, not the output)
    await link.command("M5")


async def ensure_ready(executor: MotionExecutor, power: PowerSourcePort, journal: Journal | None, *,
                       reset_errors: bool, arc: ArcControl | None = None) -> None:
    """Every device ready for motion, or NotReady. Journaled when it passes."""
    await check_power(power, journal, reset_errors=reset_errors, arc=arc)
    robot, cnc = executor.robot_link, executor.cnc_link
    if robot is not None:
        await check_robot(robot)
    if cnc is not None:
        await check_cnc(cnc)
    if journal is not None:
        journal.event("info", "readiness: every device ready before motion")
