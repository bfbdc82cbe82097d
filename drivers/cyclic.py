"""The plumbing shared by the cyclic device drivers (power source, cell I/O).

A `CyclicDevice` runs `_one_cycle()` every `cycle_ms` (wall time, never scaled) on the asyncio
loop, hands each cycle's reading to the subscribers and to the tasks waiting for the next cycle,
and stops on the first CellError (LinkLost, DeviceError), which it reports once to the
`on_error` callbacks and to every waiter. Subclasses implement the exchange and the lifecycle
(connect / close) around `_run()` and `_stop_cycle()`.
"""
from __future__ import annotations

import asyncio
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Awaitable, Callable, Generic, TypeVar

from drivers.errors import LinkLost
from drivers.loop_times import LoopClock, LoopSample, blame
from drivers.loop_times import device_thread as device_thread  # re-exported: the in-process simulators mark their thread
from core.errors import CellError

S = TypeVar("S")
T = TypeVar("T")

@dataclass
class CycleStats:
    """Link statistics of the cyclic exchange (docs/contract.md §5, "Link health"): the views, the
    report and the benchmark read them. A late reply is counted, never a fault."""

    cycles: int = 0
    late: int = 0               # replies that came after their cycle's period (still valid)
    bad: int = 0                # replies the device sent but that were not valid
    lost: int = 0               # link losses: `lost_after_cycles` cycles without a valid reply
    periods: list[float] = field(default_factory=list)   # wall seconds between cycle starts
    max_period_s: float = 0.0   # the longest wall time between two cycle starts
    host_stalls: int = 0        # reply timeouts that fired late: this process stalled, not the device
    # The longest period the controller is to blame for (docs/testing.md, "A loop that never
    # blocks"): one cycle plus the part of the loop's lateness that was its own work or the GIL held
    # by another thread of the controller (drivers/loop_times.py), never the OS's nor an
    # in-process simulator's. A device that answers late does not count here: the loop ran its
    # timers on time while it waited.
    max_own_period_s: float = 0.0
    os_delay_at_max_s: float = 0.0       # the OS's share of that period's lateness (run queue, a stopped CPU)
    device_delay_at_max_s: float = 0.0   # the in-process simulators' share (they held the GIL)
    keep: bool = False          # record periods (benchmark)
    # every cycle period in 0.1 ms bins up to 1 s (the last bin: longer): percentiles, bounded memory
    hist: list[int] = field(default_factory=lambda: [0] * 10_001)

    def restart_periods(self) -> None:
        """Count the periods from now on (a build's record: its own cycles, not the idle time
        before it, when a job was opened or planned)."""
        self.max_period_s = self.max_own_period_s = self.os_delay_at_max_s = self.device_delay_at_max_s = 0.0
        self.hist = [0] * len(self.hist)
        self.periods = []

    def add_period(self, seconds: float) -> None:
        self.hist[min(int(seconds * 10_000), 10_000)] += 1

    def period_percentile_ms(self, q: float) -> float | None:
        """The q-th percentile of the cycle periods, ms (None before two cycles)."""
        n = sum(self.hist)
        if n == 0:
            return None
        want, seen = q / 100.0 * n, 0
        for i, c in enumerate(self.hist):
            seen += c
            if seen >= want:
                return (i + 1) / 10.0
        return 1000.0


class CyclicDevice(ABC, Generic[S]):
    """A device read (and written) once per cycle; `S` is one cycle's reading."""

    device = "device"

    def __init__(self, url: str, *, cycle_ms: float = 10.0, timeout_ms: float | None = None,
                 lost_after_cycles: int = 3) -> None:
        self.url = url
        self.cycle_s = cycle_ms / 1000.0
        self.lost_after_cycles = lost_after_cycles
        # A fieldbus watchdog: the link is lost after `lost_after_cycles` cycles without a valid
        # reply. `timeout_ms` overrides it (in-process simulators share the controller's GIL).
        self.timeout_s = timeout_ms / 1000.0 if timeout_ms else lost_after_cycles * self.cycle_s
        self._task: asyncio.Task[None] | None = None
        self._error: CellError | None = None
        self._subs: list[Callable[[S], None]] = []
        self._err_subs: list[Callable[[CellError], None]] = []
        self._waiters: list[asyncio.Future[S]] = []
        self._closing = False
        self.stats = CycleStats()
        # how long (s) some CPU of this host did not run between two monotonic times: set by the
        # controller when it watches its CPUs (controller/runtime/host_witness.py), else never
        self.host_stalled_s: Callable[[float, float], float] | None = None
        self._kicked = False                       # cycle_now() asked for an exchange at once
        self._late_s = 0.0   # this cycle's lateness of the loop: timers that fired late, work after the exchange
        self._wake: asyncio.Future[bool] | None = None
        self._clock: LoopClock | None = None          # the cycle's thread clocks (while it runs)
        self._period_from: LoopSample | None = None   # restart_periods(): the period in progress starts here

    def where(self) -> str:
        return f"{self.device} at {self.url}"

    def restart_periods(self) -> None:
        """Count the cycle periods from now on (`CycleStats.restart_periods`), the one in progress
        too: from this moment, not from its cycle's start. Call it on the loop that cycles the
        device. Before 2026-11-28 the period in progress kept its start, so whatever the loop did
        before a build (a test's `open_job` on the loop: 31 ms) was the build's first period."""
        self.stats.restart_periods()
        if self._clock is not None:
            self._period_from = self._clock.sample()
            self._late_s = 0.0

    async def reply_within(self, aw: Awaitable[T]) -> T:
        """`aw`'s result within the link's reply budget; asyncio.TimeoutError when the device
        did not answer.

        The budget is counted in cycles this process really ran (docs/contract.md §5: lost after
        `lost_after_cycles` cycles without a valid reply): the wait goes in steps of one cycle,
        and a step whose timer fired more than half a cycle late (this process or its machine
        did not run: scheduling, a long interpreter-lock hold, a virtual CPU taken away) is a
        host stall, counted in the statistics and not against the device, which had no fair
        chance to be heard. So is the time another CPU of this host did not run meanwhile (the
        `host_stalled_s` witness): the reply may have waited on it. A hard limit of ten budgets
        (at least 1 s) still ends the wait on a host that never runs on time.
        """
        task = asyncio.ensure_future(aw)
        start = time.monotonic()
        hard = start + max(1.0, 10 * self.timeout_s)
        missed = 0.0
        try:
            while True:
                step = min(self.cycle_s, self.timeout_s - missed)
                t0 = time.monotonic()
                await asyncio.wait({task}, timeout=step)
                if not task.done():
                    # the reply may have been read in the very iteration whose timer fired (the
                    # reader callback runs first, the waiting task only on the next iteration)
                    for _ in range(3):
                        await asyncio.sleep(0)
                        if task.done():
                            break
                now = time.monotonic()
                self._late_s += max(0.0, now - t0 - step)   # the step's timer fired late (or the reply was read late)
                if task.done():
                    return task.result()
                if now - t0 - step > self.cycle_s / 2:
                    self.stats.host_stalls += 1
                else:
                    lost = self.host_stalled_s(t0, now) if self.host_stalled_s is not None else 0.0
                    if lost > 0.0:
                        self.stats.host_stalls += 1
                    missed += max(0.0, step - lost)
                if missed >= self.timeout_s - 1e-9 or now >= hard:
                    raise asyncio.TimeoutError()
        except BaseException:
            task.cancel()
            raise

    @abstractmethod
    async def _one_cycle(self) -> S:
        """One exchange on the wire; raise LinkLost / DeviceError, never retry."""

    @property
    def error(self) -> CellError | None:
        """The error that stopped the cycle (LinkLost, DeviceError), if any."""
        return self._error

    def subscribe(self, fn: Callable[[S], None]) -> Callable[[], None]:
        """Call `fn(reading)` every cycle, on the loop; returns an unsubscribe."""
        self._subs.append(fn)
        return lambda: self._subs.remove(fn) if fn in self._subs else None

    def on_error(self, fn: Callable[[CellError], None]) -> None:
        """Call `fn(error)` once when the cycle stops on LinkLost or DeviceError."""
        self._err_subs.append(fn)

    async def _next_cycle(self) -> S:
        """Wait for the next cycle's reading; the stopping error if the cycle has stopped."""
        if self._error is not None:
            raise self._error
        if self._task is None or self._task.done():
            raise LinkLost(f"{self.where()}: not connected")
        fut: asyncio.Future[S] = asyncio.get_running_loop().create_future()
        self._waiters.append(fut)
        return await fut

    async def _stop_cycle(self) -> bool:
        """Stop the cycle task; True if one was running."""
        # the flag ends the loop even if asyncio.wait_for swallows the cancel (Python 3.11)
        self._closing = True
        task, self._task = self._task, None
        if task is None:
            return False
        task.cancel()
        await asyncio.wait({task}, timeout=1.0)
        return True

    async def _run(self) -> None:
        period = self.cycle_s
        deadline = time.monotonic()
        last: LoopSample | None = None
        clock = self._clock = LoopClock()   # this thread's clocks: whose fault a late cycle is (drivers/loop_times.py)
        try:
            while not self._closing:
                sample = clock.sample()
                now = sample.t
                if self._period_from is not None:   # the periods were restarted within this one
                    last, self._period_from = self._period_from, None
                if last is not None:
                    self._note_period(last, sample)
                last = sample
                self._late_s = 0.0
                try:
                    st = await self._one_cycle()
                except CellError as exc:
                    if isinstance(exc, LinkLost):
                        self.stats.lost += 1
                    else:
                        self.stats.bad += 1
                    self._fail(exc)
                    return
                self.stats.cycles += 1
                done = time.monotonic()
                if done - now > period:
                    self.stats.late += 1    # valid, but after its cycle: counted, not a fault
                self._deliver(st)
                # absolute deadlines: no drift; after an overrun resynchronise instead of bursting
                deadline += period
                after = time.monotonic()
                self._late_s += after - done     # work on the device loop after the exchange
                if after - deadline > period:
                    deadline = after
                kicked = await self._sleep_until(deadline)
                self._late_s += max(0.0, time.monotonic() - max(deadline, after))   # woke late
                if kicked:
                    deadline -= period   # an extra exchange: the scheduled one still comes on time
        except asyncio.CancelledError:
            raise
        except Exception as exc:  # an unexpected transport error is still a lost link
            self._fail(LinkLost(f"{self.where()}: cycle stopped ({exc!r})"))
        finally:
            self._clock = None
            clock.close()

    def _note_period(self, a: LoopSample, b: LoopSample) -> None:
        """Count one period (from one cycle start's clocks to the next's) and the share of it the
        controller is to blame for (`max_own_period_s`; drivers/loop_times.py)."""
        st = self.stats
        gap = b.t - a.t
        st.max_period_s = max(st.max_period_s, gap)
        st.add_period(gap)
        if st.keep:
            st.periods.append(gap)
        if gap <= 1.5 * self.cycle_s:
            own, os_s, dev_s = gap, 0.0, 0.0
        else:
            stalled = self.host_stalled_s(a.t, b.t) if self.host_stalled_s is not None else 0.0
            share = blame(self._late_s, a, b, stalled, waited=gap - self.cycle_s - self._late_s)
            own, os_s, dev_s = min(gap, self.cycle_s + share.own), share.os, share.devices
        if own > st.max_own_period_s:
            st.max_own_period_s, st.os_delay_at_max_s, st.device_delay_at_max_s = own, os_s, dev_s

    def _deliver(self, st: S) -> None:
        """One cycle's reading to the subscribers and to the tasks waiting for it."""
        for fn in list(self._subs):
            try:
                fn(st)
            except Exception:  # a subscriber's bug must not stop the bus cycle
                pass
        waiters, self._waiters = self._waiters, []
        for fut in waiters:
            if not fut.done():
                fut.set_result(st)

    def cycle_now(self) -> None:
        """Exchange at once instead of at the next cycle (an interlock's drop goes out now); the
        cycle's schedule is kept. During an exchange: the next one follows it at once."""
        self._kicked = True
        if self._wake is not None and not self._wake.done():
            self._wake.set_result(True)

    async def _sleep_until(self, deadline: float) -> bool:
        """Sleep to `deadline` (time.monotonic()); True when cycle_now() cut the sleep short."""
        if self._kicked:
            self._kicked = False
            return True
        loop = asyncio.get_running_loop()
        fut: asyncio.Future[bool] = loop.create_future()
        self._wake = fut

        def due() -> None:
            if not fut.done():
                fut.set_result(False)

        timer = loop.call_later(max(0.0, deadline - time.monotonic()), due)
        try:
            kicked = await fut
        finally:
            timer.cancel()
            self._wake = None
        self._kicked = False
        return kicked

    def _fail(self, exc: CellError) -> None:
        self._error = exc
        self._task = None
        self._fail_waiters(exc)
        for fn in list(self._err_subs):
            try:
                fn(exc)
            except Exception:
                pass

    def _fail_waiters(self, exc: CellError) -> None:
        waiters, self._waiters = self._waiters, []
        for fut in waiters:
            if not fut.done():
                fut.set_exception(exc)
