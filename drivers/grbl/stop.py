"""The CNC's safe stop (docs/contract.md §6 "Every stop is safe"): feed hold, process off, nothing left
queued, each step verified from the firmware's own status reports.

Sequence (grbl 1.1h `protocol.c` / `motion_control.c`, and grblHAL, which does the same):
1. `!` feed hold at once (a real-time byte: never waits behind the RX buffer); the driver sends
   no further line from this moment (every stream breaks off).
2. Wait, at most `hold_timeout_s`, for a report showing `Hold:0` (deceleration complete) or a
   standing state (Idle, Alarm).
3. Process off. `M5` cannot go to a grbl in Hold with a move held: grbl syncs every spindle
   change with the planner (`spindle_sync` → `protocol_buffer_synchronize`), so the `M5` would
   wait, unanswered, for a cycle start that would run the queued weld moves. Hence:
   - Hold, anything queued (`Bf:`), any line of ours unanswered, or the hold not complete in
     time → soft reset 0x18: grbl's `mc_reset` turns spindle and coolant off and the reset
     flushes the planner and the RX buffer; reset at `Hold:0` keeps the position (no alarm),
     reset while still moving raises `ALARM:3` (position lost: re-home). Wait at most
     `reset_timeout_s` for the banner.
   - Idle with nothing queued → `M5` (answered at once), the reset only if it is not.
   - Alarm with the spindle off (grbl refuses G-code there, `error:9`) → nothing to send.
4. Verify, at most `verify_timeout_s`, from fresh status reports: state Idle or Alarm, `FS:`
   spindle 0, the accessory field showing the spindle off (`A:` without S/C; grbl 1.1h prints
   `A:` only in its `Ov:` reports and leaves it out when nothing is on), `Bf:` showing an empty
   planner and RX buffer, and the position unchanged between two reports. Then `$G` shows `M5`.
An alarm left by the stop is reported (`needs_unlock`, `needs_homing`), never cleared here.

The stop sends through the link's shared `LinkState` (state.py) and reads what was heard from the
link's receiving half (receive.py: alarms, status reports, buffer sizes).
"""
from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass

from drivers.errors import DeviceError, LinkLost
from drivers.grbl.receive import GrblReceiver
from drivers.grbl.results import SafeStopResult
from drivers.grbl.status import Pending
from wire.grbl_protocol import POSITION_LOST_ALARMS, RT_FEED_HOLD, RT_SOFT_RESET, RT_STATUS, Error, GrblStatus

__all__ = ["SafeStop"]

_STANDING = ("Idle", "Alarm")


@dataclass
class _Seen:
    """The checks as the reports so far tell them."""

    st: GrblStatus | None = None
    prev: GrblStatus | None = None
    spindle_off: bool | None = None
    spindle_off_at: float | None = None


class SafeStop:
    """One run of the sequence above for `link`; `run()` never raises for the machine's answers
    (a lost link, a timeout or a failed check is in the result), only for programming errors."""

    def __init__(self, link: GrblReceiver, reason: str, *, hold_timeout_s: float, reset_timeout_s: float,
                 verify_timeout_s: float, poll_s: float = 0.05) -> None:
        self.link = link
        self.sh = link.shared
        self.reason = reason
        self.hold_timeout_s = hold_timeout_s
        self.reset_timeout_s = reset_timeout_s
        self.verify_timeout_s = verify_timeout_s
        self.poll_s = poll_s
        self.t0 = time.monotonic()
        self.steps: list[str] = []
        self.timed_out: list[str] = []
        self.problems: list[str] = []
        self.held = self.m5_sent = self.reset = False
        self.hold_s: float | None = None
        self.alarms_before = len(link.alarms)
        self.unanswered = len(link.shared.pending)
        self.seen = _Seen()
        self.modal_m5: bool | None = None

    def _step(self, text: str) -> None:
        self.steps.append(f"{time.monotonic() - self.t0:.3f}s {text}")

    async def run(self) -> SafeStopResult:
        try:
            await self.sh.write(RT_FEED_HOLD)
            self._step("sent ! (feed hold)")
            st = await self._wait_hold()
            if self._reset_needed(st):
                await self._reset()
            elif st is not None and st.state == "Alarm":
                self._step("Alarm with the spindle off: grbl accepts no M5 there; verifying")
            else:
                await self._m5()
            await self._verify()
            await self._check_modal()
        except LinkLost as exc:
            self.problems.append(f"link lost: {exc}")
        return self._result()

    # -- the steps ----------------------------------------------------------------------------
    async def _report(self, timeout: float) -> GrblStatus | None:
        """The next status report, asking for it at once; None when none came within `timeout`."""
        sh = self.sh
        fut: asyncio.Future[GrblStatus] = asyncio.get_running_loop().create_future()
        sh.status_waiters.append(fut)
        sh.last_q = time.monotonic()
        await sh.write(RT_STATUS)
        try:
            st = await asyncio.wait_for(fut, max(timeout, 0.001))
        except asyncio.TimeoutError:
            return None
        self._note(st)
        return st

    def _note(self, st: GrblStatus) -> None:
        s = self.seen
        s.prev, s.st = s.st, st
        if st.spindle_on is not None:
            s.spindle_off = not st.spindle_on
        if s.spindle_off and st.spindle == 0 and s.spindle_off_at is None:
            s.spindle_off_at = time.monotonic()
        elif not s.spindle_off or st.spindle != 0:
            s.spindle_off_at = None

    async def _wait_hold(self) -> GrblStatus | None:
        deadline = time.monotonic() + self.hold_timeout_s
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                self.timed_out.append("hold")
                self._step(f"no Hold:0 within hold_timeout_s={self.hold_timeout_s:g}")
                return self.seen.st
            st = await self._report(min(left, 0.5))
            if st is not None and ((st.state == "Hold" and st.substate == 0) or st.state in _STANDING):
                self.held = st.state == "Hold"
                self.hold_s = time.monotonic() - self.t0
                self._step(f"{st.state}{'' if st.substate is None else ':' + str(st.substate)} seen")
                return st
            if st is None:
                await asyncio.sleep(self.poll_s)

    def _queued(self, st: GrblStatus) -> tuple[int | None, int | None]:
        """Planner blocks and RX bytes in use by this report's `Bf:` (None: not reported)."""
        link = self.link
        if st.planner_free is None or st.rx_free is None:
            return None, None
        return max(link.planner_blocks_empty - st.planner_free, 0), max(link.rx_free_empty - st.rx_free, 0)

    def _reset_needed(self, st: GrblStatus | None) -> bool:
        if st is None or st.state not in _STANDING or self.sh.pending:
            return True
        if st.state == "Alarm" and (st.spindle != 0 or st.spindle_on):
            return True
        blocks, rx = self._queued(st)
        return bool(blocks) or bool(rx)

    async def _reset(self) -> None:
        sh = self.sh
        sh.banner.clear()
        await sh.write(RT_SOFT_RESET)
        self.reset = True
        self._step("sent 0x18 (soft reset)")
        try:
            await asyncio.wait_for(sh.banner.wait(), self.reset_timeout_s)
        except asyncio.TimeoutError:
            self.timed_out.append("reset")
            self.problems.append(f"no banner within reset_timeout_s={self.reset_timeout_s:g} after the reset")
            return
        self._step("banner after the reset")
        sh.fail_pending(DeviceError(f"cnc at {sh.url}: safe stop ({self.reason}): the reset flushed this line"))
        self.seen = _Seen()   # only reports after the reset count

    async def _line(self, line: str, timeout: float) -> Pending | None:
        """Send one line outside the send lock (nothing else is sent during a stop); None when
        it is not answered within `timeout`."""
        p = await self.sh.send_line(line)
        try:
            await asyncio.wait_for(asyncio.shield(p.future), timeout)
        except asyncio.TimeoutError:
            return None
        except DeviceError:
            return None
        return p

    async def _m5(self) -> None:
        self.m5_sent = True
        p = await self._line("M5", min(self.reset_timeout_s, 2.0))
        if p is None or isinstance(p.future.result(), Error):
            self._step("M5 not acknowledged: soft reset instead")
            if p is None:
                self.timed_out.append("m5")
            await self._reset()
            return
        self._step("M5 acknowledged")
        self.seen = _Seen()

    def _open_checks(self) -> list[str]:
        """What the reports have not shown yet (empty: all verified)."""
        s, st = self.seen, self.seen.st
        if st is None:
            return ["no status report"]
        out = []
        if st.state not in _STANDING:
            out.append(f"state {st.state}")
        if st.spindle != 0:
            out.append(f"spindle S{st.spindle:g} in FS:")
        if s.spindle_off is not True:
            out.append("accessory field (A:) not showing the spindle off" if s.spindle_off is False
                       else "no report with the accessory state (Ov:/A:)")
        blocks, rx = self._queued(st)
        if blocks is None or rx is None:
            out.append("no Bf: field in the status report (set $10 to report buffers)")
        elif blocks or rx:
            out.append(f"{blocks} planner block(s) and {rx} RX byte(s) still queued")
        if s.prev is None or s.prev.mpos != st.mpos:
            out.append("position not yet seen unchanged in two reports")
        return out

    async def _verify(self) -> None:
        deadline = time.monotonic() + self.verify_timeout_s
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                self.timed_out.append("verify")
                self.problems.extend(self._open_checks())
                return
            st = await self._report(min(left, 0.5))
            if st is not None and st.state not in _STANDING and not self.reset:
                self._step(f"{st.state} after M5: soft reset")
                await self._reset()
                continue
            if not self._open_checks():
                self._step("verified from the status report")
                return
            await asyncio.sleep(self.poll_s)

    async def _check_modal(self) -> None:
        st = self.seen.st
        if st is None or st.state not in _STANDING:
            return
        p = await self._line("$G", max(self.verify_timeout_s / 2, 0.5))
        if p is None or isinstance(p.future.result(), Error):
            self.timed_out.append("modal")
            self.problems.append("$G not answered")
            return
        gc = next((t for t in p.lines if t.startswith("[GC:")), "")
        self.modal_m5 = "M5" in gc[4:-1].split()
        if not self.modal_m5:
            self.problems.append(f"$G does not show M5: {gc}")

    def _result(self) -> SafeStopResult:
        link, s = self.link, self.seen
        st = s.st or link.latest_status
        new_alarms = link.alarms[self.alarms_before:]
        blocks, rx = self._queued(st) if st is not None else (None, None)
        if not self.problems:
            self.problems.extend(self._open_checks())
        state = st.state if st is not None else "?"
        return SafeStopResult(
            reason=self.reason, verified=not self.problems, state=state,
            position=st.mpos if st is not None else (0.0, 0.0, 0.0, 0.0, 0.0),
            spindle=st.spindle if st is not None else -1.0, spindle_off=s.spindle_off,
            planner_queued=blocks, rx_queued=rx, settled=s.prev is not None and st is not None and s.prev.mpos == st.mpos,
            modal_m5=self.modal_m5, unanswered_lines=self.unanswered, held=self.held, m5_sent=self.m5_sent,
            reset=self.reset, alarm=new_alarms[-1] if new_alarms else None, needs_unlock=state == "Alarm",
            needs_homing=any(a in POSITION_LOST_ALARMS for a in new_alarms), hold_s=self.hold_s,
            spindle_off_s=None if s.spindle_off_at is None else s.spindle_off_at - self.t0,
            elapsed_s=time.monotonic() - self.t0, timed_out=tuple(self.timed_out), problems=tuple(self.problems),
            steps=tuple(self.steps))
