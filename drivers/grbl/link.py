"""CncLink: the asyncio driver for a CNC speaking the grbl 1.1 serial interface (5 axes XYZAB).

Works unchanged against real grbl-interface firmware (plain grbl reports 3 axes: positions are
padded to 5 with 0.0) and against sims/cnc/. Talks bytes over any pyserial URL through
drivers/serial_async.py. Protocol details and choices: docs/protocols/grbl.md. The parts of this
package share one `LinkState` (state.py) through its public fields.

Flow control is grbl's character counting: the driver keeps the sum of the lengths of the
unacknowledged lines (each `len(line) + 1` for its `\\n`) at most `rx_buffer_bytes - 1`, the
usable size of grbl's RX ring, and sends the next line as soon as an `ok` / `error:N` frees
enough room, so the controller's buffer stays full. Real-time bytes (`?`, `!`, `~`, 0x18) are
not buffered by grbl and are sent at once. Status is polled in the background at
`status_hz` (at most 5 Hz, grbl's recommendation); no byte received for `link_timeout_s`
(grbl answers `?` even while moving, dwelling or homing) is a `LinkLost`.
"""
from __future__ import annotations

import asyncio
import concurrent.futures
import re
import time
from collections.abc import Callable, Iterable

from drivers.errors import DeviceError, DeviceTimeout, LinkLost
from drivers.grbl.errors import GrblAlarm, GrblError, GrblReset, ProbeError
from drivers.grbl.probe import Prober
from drivers.grbl.receive import GrblReceiver
from drivers.grbl.results import ProbeResult, SafeStopResult
from drivers.grbl.state import LinkState
from drivers.grbl.stop import SafeStop
from drivers.grbl.stream import StreamRun
from drivers.serial_async import SerialPort
from wire.grbl_protocol import RT_CYCLE_START, RT_FEED_HOLD, RT_SOFT_RESET, RT_STATUS, Error, GrblStatus, StreamResult

__all__ = ["CncLink"]

# States in which a connect may soft-reset the controller to get its banner (nothing moves).
_RESETTABLE = ("Idle", "Alarm", "Check", "Sleep")


class CncLink(GrblReceiver):
    """Driver for one grbl 1.1 controller.

    `CncLink(url, *, baud=115200, rx_buffer_bytes=128, status_hz=5.0)`; `await connect()`,
    `await close()`; `command(line)`, `stream(lines)`, `home()`, `unlock()`, `status()`,
    `feed_hold()`, `resume()`, `soft_reset()`, `wait_idle(timeout)`, `probe(target, feed)`.
    `latest_status` holds the newest background status report, `homed` whether `$H`
    succeeded since the position was last lost.
    """

    def __init__(self, url: str, *, baud: int = 115200, rx_buffer_bytes: int = 128, status_hz: float = 5.0,
                 link_timeout_s: float = 3.0, connect_timeout_s: float = 5.0, alarm_grace_s: float = 3.0,
                 ack_grace_s: float = 2.0, pace: bool = True, homing_timeout_s: float = 120.0,
                 stuck_after_s: float = 30.0, report_buffer: bool = True, hold_timeout_s: float = 10.0,
                 reset_timeout_s: float = 5.0, verify_timeout_s: float = 5.0, line_scale: float = 1.0) -> None:
        if not 0 < status_hz <= 5.0:
            raise ValueError("status_hz must be in (0, 5]: grbl recommends at most 5 status reports a second")
        if rx_buffer_bytes < 16:
            raise ValueError("rx_buffer_bytes must be at least 16")
        self.baud = baud
        self.status_period = 1.0 / status_hz
        self.link_timeout_s = link_timeout_s
        self.connect_timeout_s = connect_timeout_s
        # a simulated line at time scale k carries k times the bytes per wall second (docs/contract.md §6,
        # sims/transport.py): pace the writes to it as the robot link does (1 on hardware)
        self.line_scale = line_scale
        self._pace = pace
        port = SerialPort(url, baud=baud, name="cnc", pace=pace, pace_factor=0.98 * line_scale)
        # a ring of N bytes holds N - 1
        super().__init__(LinkState(url, rx_buffer_bytes - 1, port), alarm_grace_s=alarm_grace_s,
                         ack_grace_s=ack_grace_s, stuck_after_s=stuck_after_s)
        self.homing_timeout_s = homing_timeout_s
        self.report_buffer = report_buffer   # connect() turns on Bf: in the status report ($10 bit 1)
        # the safe stop's bounds (stop.py)
        self.hold_timeout_s = hold_timeout_s
        self.reset_timeout_s = reset_timeout_s
        self.verify_timeout_s = verify_timeout_s
        self._loop: asyncio.AbstractEventLoop | None = None
        self._jogging = False     # a `$J=` was sent and may still be running

    # -- properties ---------------------------------------------------------------------------

    @property
    def capacity(self) -> int:
        """Usable bytes of grbl's RX buffer: its size less one, at most what `$I` reports."""
        return self.shared.capacity

    @property
    def connected(self) -> bool:
        return bool(self.shared.tasks) and self.shared.lost is None

    # -- lifecycle ----------------------------------------------------------------------------
    async def connect(self) -> GrblStatus:
        """Open the port, wait for (or provoke) the banner and read the state.

        A controller that prints its banner on open (USB boards reset when the port opens) is
        taken as is. Otherwise `?` is sent until a status report arrives; a controller that is
        not moving (Idle, Alarm) is then soft-reset to get its banner and a clean parser; one in
        motion (Run, Hold, Home, Jog) is attached to without a reset."""
        sh = self.shared
        sh.closing = False
        sh.lost = None
        self.latest_status = None
        sh.banner.clear()
        sh.buf.clear()
        sh.port = SerialPort(self.url, baud=self.baud, name="cnc", pace=self._pace,
                             pace_factor=0.98 * self.line_scale)
        await sh.port.open()
        sh.last_rx = time.monotonic()
        self._loop = asyncio.get_running_loop()
        sh.tasks = [self._loop.create_task(self._read_loop())]
        try:
            await self._provoke_banner()
        except BaseException:
            await self.close()
            raise
        sh.tasks.append(self._loop.create_task(self._poll_loop()))
        st = await self.status()
        if st.state not in ("Run", "Hold", "Home", "Jog"):
            await self._read_build_info()
            if self.report_buffer and st.rx_free is None:
                st = await self._turn_on_buffer_report()
        return st

    async def _provoke_banner(self) -> None:
        deadline = time.monotonic() + self.connect_timeout_s
        sh = self.shared
        while time.monotonic() < deadline and not sh.banner.is_set() and self.latest_status is None:
            await sh.write(RT_STATUS)
            sh.last_q = time.monotonic()
            try:
                await asyncio.wait_for(sh.wait_changed(), 0.25)
            except asyncio.TimeoutError:
                pass
            sh.check_lost()
        if sh.banner.is_set():
            return
        if self.latest_status is None:
            raise DeviceTimeout(f"cnc at {self.url}: no answer to '?' within {self.connect_timeout_s:.1f} s; "
                                "check the cable, the URL and that the controller is powered")
        if self.latest_status.state in _RESETTABLE:
            for attempt in range(3):  # a banner garbled on the line: reset again
                try:
                    await self.soft_reset(timeout=1.5)
                    break
                except DeviceTimeout:
                    if attempt == 2:
                        raise

    async def _read_build_info(self) -> None:
        """`$I`: never fill grbl's RX ring beyond what the firmware says it has; planner size and
        axis letters (grblHAL's `[AXS:5:XYZAB]`)."""
        try:
            lines = await self.command("$I", timeout=5.0)
        except DeviceError:
            return
        for text in lines:
            m = re.match(r"\[OPT:[^,]*,(\d+),(\d+)", text)
            if m:
                self.planner_blocks_reported = int(m.group(1))
                self.rx_buffer_reported = int(m.group(2))
                self.shared.capacity = min(self.shared.capacity, self.rx_buffer_reported - 1)
            m = re.match(r"\[AXS:(\d+):([A-Z]+)\]", text)
            if m:
                self.axis_letters = m.group(2)

    async def _turn_on_buffer_report(self) -> GrblStatus:
        """Status reports without `Bf:` (grbl 1.1h's default `$10=1`): set `$10` bit 1 so every
        report shows the planner blocks and RX bytes free, which the safe stop and the
        acknowledgement watchdog judge by (the position type, bit 0, is kept)."""
        try:
            current = next((int(t.split("=", 1)[1]) for t in await self.command("$$", timeout=5.0)
                            if t.startswith("$10=")), 1)
            await self.command(f"$10={current | 2}", timeout=5.0)
        except (DeviceError, ValueError):
            pass
        return await self.status()

    async def close(self) -> None:
        """Stop polling and close the port (the controller keeps running what it has)."""
        sh = self.shared
        sh.closing = True
        for t in sh.tasks:
            t.cancel()
        for t in sh.tasks:
            try:
                await t
            except (asyncio.CancelledError, Exception):
                pass
        sh.tasks = []
        sh.port.close()
        sh.fail_pending(LinkLost(f"cnc at {self.url}: link closed"))

    async def __aenter__(self) -> "CncLink":
        await self.connect()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    # -- receiving ----------------------------------------------------------------------------
    async def _read_loop(self) -> None:
        try:
            while True:
                data = await self.shared.port.read()
                self._on_bytes(data)
        except LinkLost as exc:
            self._on_lost(exc)

    # -- sending (state.py: LinkState.write, send_line, room) --------------------------------
    async def command(self, line: str, timeout: float | None = None) -> list[str]:
        """Send one line and await its `ok`; returns the lines grbl printed before it
        (`[GC:…]`, `$N=V`, `[PRB:…]`, `[MSG:…]`). `error:N` → GrblError; an ALARM raised
        while the line was pending → GrblAlarm (ProbeError for ALARM:4/5); no answer within
        `timeout` seconds (None: wait, the link watchdog still applies) → DeviceTimeout."""
        sh = self.shared
        line = sh.check_line(line.strip())
        sh.check_lost()
        self._check_not_stopping(line)
        self._jogging = self._jogging or line.startswith("$J=")
        async with sh.send_lock:
            sh.stream_alarm = None
            await sh.room(len(line) + 1)
            p = await sh.send_line(line)
        try:
            r = await asyncio.wait_for(asyncio.shield(p.future), timeout)
        except asyncio.TimeoutError:
            raise DeviceTimeout(f"cnc at {self.url}: no answer to {line!r} within {timeout} s") from None
        if isinstance(r, Error):
            raise GrblError(r.code, line, url=self.url)
        if p.alarm is not None:
            cls = ProbeError if p.alarm.code in (4, 5) else GrblAlarm
            raise cls(p.alarm.code, line, self.url)
        return p.lines

    async def stream(self, lines: Iterable[str], progress: Callable[[int, int], None] | None = None) -> StreamResult:
        """Stream G-code with character counting, keeping grbl's RX buffer full
        (stream.py).

        Comments and blank lines are stripped before sending (line numbers still count every
        input line). At the first `error:N` it sends nothing more, runs `safe_stop` (so the
        lines already in grbl's buffer do not run and grbl is not left in Hold with lines
        queued) and raises GrblError naming that line's number and text, with the safe stop's
        result in `.safe_stop`. An ALARM stops the stream with GrblAlarm; a `safe_stop` called
        meanwhile (another task or thread) with GrblStopped. On success it sends `G4 P0` and
        returns once everything sent has executed. `progress(acked, sent)` is called as
        acknowledgements arrive."""
        self.shared.check_lost()
        self._check_not_stopping("a stream")
        return await StreamRun(self.shared, self, progress).run(lines)

    # -- the safe stop ------------------------------------------------------------------------
    @property
    def stopping(self) -> bool:
        """A safe stop is in progress: no line is sent meanwhile."""
        return self.shared.stopping

    def _check_not_stopping(self, what: str) -> None:
        if self.stopping:
            raise DeviceError(f"cnc at {self.url}: a safe stop is in progress; {what} was not sent")

    async def safe_stop(self, reason: str, *, hold_timeout_s: float | None = None, reset_timeout_s: float | None = None,
                        verify_timeout_s: float | None = None) -> SafeStopResult:
        """Stop the machine safely and verify it (stop.py): feed hold, process off
        (soft reset where anything is queued or held, else `M5`), then state, spindle, accessory
        state, queued blocks / bytes and position from fresh status reports, and `M5` from `$G`.

        Safe to call while a stream runs (the stream sends nothing more and raises GrblStopped)
        and more than once: a call during a stop waits for that stop's result. Every wait is
        bounded (`hold_timeout_s`, `reset_timeout_s`, `verify_timeout_s`; defaults from the
        constructor); an expired one is named in `SafeStopResult.timed_out`. Never raises for the
        machine's answers: check `.verified`. An alarm left by the stop is not cleared."""
        sh = self.shared
        sh.stop_gen += 1      # every stream stops sending now
        sh.pulse()
        if not sh.stopping:
            sh.stop_task = asyncio.get_running_loop().create_task(SafeStop(
                self, reason, hold_timeout_s=self.hold_timeout_s if hold_timeout_s is None else hold_timeout_s,
                reset_timeout_s=self.reset_timeout_s if reset_timeout_s is None else reset_timeout_s,
                verify_timeout_s=self.verify_timeout_s if verify_timeout_s is None else verify_timeout_s).run())
        assert sh.stop_task is not None
        return await asyncio.shield(sh.stop_task)

    async def safe_stop_result(self) -> SafeStopResult:
        """The result of the safe stop in progress or the last one (DeviceError if none ran)."""
        if self.shared.stop_task is None:
            raise DeviceError(f"cnc at {self.url}: no safe stop has run")
        return await asyncio.shield(self.shared.stop_task)

    def safe_stop_threadsafe(self, reason: str, timeout_s: float | None = None) -> SafeStopResult:
        """`safe_stop(reason)` from another thread (a signal handler's thread, a UI thread):
        runs on the link's event loop and waits at most `timeout_s` (default: the sum of the
        stop's bounds plus 2 s). Not from the link's own loop thread (it would deadlock)."""
        loop = self._loop
        if loop is None or loop.is_closed() or not self.shared.tasks:
            raise LinkLost(f"cnc at {self.url}: not connected; no safe stop possible")
        try:
            running = asyncio.get_running_loop()
        except RuntimeError:
            running = None
        if running is loop:
            raise RuntimeError("safe_stop_threadsafe() called on the link's own event loop: await safe_stop()")
        limit = timeout_s if timeout_s is not None else (
            self.hold_timeout_s + self.reset_timeout_s * 2 + self.verify_timeout_s * 2 + 2.0)
        fut = asyncio.run_coroutine_threadsafe(self.safe_stop(reason), loop)
        try:
            return fut.result(limit)
        except concurrent.futures.TimeoutError:
            raise DeviceTimeout(f"cnc at {self.url}: safe stop ({reason}) not finished within {limit:.1f} s") from None

    # -- real-time commands -------------------------------------------------------------------
    async def feed_hold(self) -> None:
        """`!`: decelerate to a stop (Hold:1, then Hold:0); queued lines are kept."""
        self.shared.check_lost()
        await self.shared.write(RT_FEED_HOLD)

    async def resume(self) -> None:
        """`~`: cycle start / resume after a feed hold."""
        self.shared.check_lost()
        await self.shared.write(RT_CYCLE_START)

    async def soft_reset(self, timeout: float = 5.0) -> None:
        """0x18: grbl stops at once, flushes its buffers and prints its banner again.

        Unacknowledged lines fail with GrblReset. Resetting while moving loses the position
        (grbl answers ALARM:3 and stays in Alarm)."""
        sh = self.shared
        sh.check_lost()
        sh.banner.clear()
        await sh.write(RT_SOFT_RESET)
        try:
            await asyncio.wait_for(sh.banner.wait(), timeout)
        except asyncio.TimeoutError:
            raise DeviceTimeout(f"cnc at {self.url}: no banner within {timeout} s after a soft reset") from None
        sh.fail_pending(GrblReset(f"cnc at {self.url}: soft reset flushed the unacknowledged lines"))

    # -- status -------------------------------------------------------------------------------

    async def _poll_loop(self) -> None:
        sh = self.shared
        while True:
            await asyncio.sleep(self.status_period / 2)
            now = time.monotonic()
            self._check_acks(now)
            if now - sh.last_rx > self.link_timeout_s and now >= sh.quiet_until:
                sh.port.close()
                self._on_lost(LinkLost(f"cnc at {self.url}: silent for {self.link_timeout_s:.1f} s "
                                       "(no answer to status requests); check the cable and the controller"))
                return
            if now - sh.last_q >= self.status_period * 0.999:
                sh.last_q = now
                try:
                    await sh.write(RT_STATUS)
                except LinkLost as exc:
                    self._on_lost(exc)
                    return

    async def status(self, timeout: float | None = None, *, at_once: bool = False) -> GrblStatus:
        """A fresh status report: the next one the ≤ 5 Hz poll brings in, or with `at_once` the
        answer to a `?` sent now (grbl answers `?` from its main loop within milliseconds; for a
        single check between moves, not for polling in a loop)."""
        sh = self.shared
        sh.check_lost()
        fut = asyncio.get_running_loop().create_future()
        sh.status_waiters.append(fut)
        now = time.monotonic()
        if at_once or now - sh.last_q >= self.status_period:
            sh.last_q = now
            await sh.write(RT_STATUS)
        try:
            return await asyncio.wait_for(fut, timeout or self.link_timeout_s + self.status_period)
        except asyncio.TimeoutError:
            raise DeviceTimeout(f"cnc at {self.url}: no status report; check the link") from None

    async def wait_idle(self, timeout: float = 60.0) -> GrblStatus:
        """Wait until all motion has finished and the controller is Idle (G4 P0, then status)."""
        deadline = time.monotonic() + timeout
        st = self.latest_status
        if st is not None and st.state == "Jog" or self._jogging:
            st = await self.status()   # grbl refuses G-code (error:9) while jogging: poll instead
        self._jogging = False
        if st is None or st.state not in ("Alarm", "Jog"):
            try:
                await self.command("G4 P0", timeout=max(deadline - time.monotonic(), 0.01))
            except DeviceTimeout:
                raise DeviceTimeout(f"cnc at {self.url}: not idle within {timeout} s "
                                    f"(state {self.latest_status.state if self.latest_status else '?'})") from None
        while True:
            st = await self.status()
            if st.state == "Idle":
                return st
            if st.state == "Jog":
                continue
            if st.state == "Alarm":
                raise GrblAlarm(self.alarms[-1] if self.alarms else 0, None, self.url, "; unlock ($X) or home ($H)")
            if time.monotonic() > deadline:
                raise DeviceTimeout(f"cnc at {self.url}: not idle within {timeout} s (state {st.state})")

    # -- machine commands ---------------------------------------------------------------------
    async def home(self, timeout: float | None = None) -> GrblStatus:
        """`$H`: run the homing cycle, answered once homing has finished. grbl answers nothing
        (not even `?`) meanwhile, so the link watchdog waits `timeout` (default
        `homing_timeout_s`, cell.yaml) instead of `link_timeout_s`."""
        limit = self.homing_timeout_s if timeout is None else timeout
        self.shared.quiet_until = time.monotonic() + limit
        try:
            await self.command("$H", timeout=limit)
        except DeviceTimeout:
            raise DeviceTimeout(f"cnc at {self.url}: homing ($H) not finished within {limit:.0f} s "
                                "(cnc.homing_timeout_s in cell.yaml); check the limit switches") from None
        finally:
            self.shared.quiet_until = 0.0
            self.shared.last_rx = time.monotonic()
        self.shared.homed = True
        self.reset_at = time.time()  # homing: an alignment probed before it no longer holds
        return await self.status()

    async def laser_mode(self, on: bool) -> None:
        """Set `$32` for the program about to stream and read it back: 1 for deposition (the process
        power drops on feed hold and rapids), 0 for machining (the spindle keeps turning on
        rapids). DeviceError when the controller does not keep it."""
        want = "1" if on else "0"
        if _setting(await self.command("$$"), 32) != want:
            await self.command(f"$32={want}")
            if _setting(await self.command("$$"), 32) != want:
                what = "laser mode ($32=1)" if on else "spindle mode ($32=0)"
                raise DeviceError(f"cnc at {self.url}: {what} did not stick; check the controller's settings "
                                  "before running a job")

    async def unlock(self) -> list[str]:
        """`$X`: clear the alarm lock ("[MSG:Caution: Unlocked]"); the position is not re-homed."""
        return await self.command("$X")

    async def probe(self, target: dict[str, float] | tuple[float, float, float], feed_mm_min: float, *,
                    mode: str = "G38.2", unlock_on_fail: bool = True) -> ProbeResult:
        """Probe toward `target` at `feed_mm_min` (probe.py): returns the trip
        position in machine coordinates and `contact`; ProbeError on ALARM:4/5 (then `$X`, Z
        retracted to where the probe started, unless `unlock_on_fail=False`)."""
        return await Prober(self).run(target, feed_mm_min, mode=mode, unlock_on_fail=unlock_on_fail)


def _setting(lines: list[str], n: int) -> str | None:
    """The value of `$n=` in a `$$` listing (None: not listed)."""
    for text in lines:
        if text.startswith(f"${n}="):
            return text.split("=", 1)[1].strip()
    return None
