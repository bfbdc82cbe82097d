"""Whose fault a late device cycle is: the loop's own work, the OS, or a thread holding the GIL
(docs/testing.md, "A loop that never blocks").

Between two cycle starts the thread that cycles the devices (the controller's asyncio loop) is in
one of three states, and Linux counts two of them for that one thread in
/proc/thread-self/schedstat:

- **on a CPU** (`cpu_s`): running the loop's callbacks, i.e. the controller's own work;
- **runnable, waiting for a CPU** (`wait_s`, the scheduler's run-queue delay): another process (or
  an in-process simulator at a higher priority) had the CPU: not the controller's doing;
- **asleep**: waiting for its timer or a device's reply (as it should), or, once its timer has
  fired, for the interpreter lock (GIL) another thread of the process holds.

The lateness of a cycle (the time the loop came late to it; drivers/cyclic.py measures it from
its own timers) is split in that order: the run-queue wait (and a CPU of the host witnessed
stopped) is the OS's, the loop's own CPU time is the controller's, and what is left was spent
asleep past a due timer: waiting for the GIL. That part is shared out over what the other threads
of the process did meanwhile, each share at most the time measured for it: CPU time of the
controller's other threads (the TUI's screen, work handed to a thread pool, the journal writer)
is the controller's, CPU time of the in-process simulators' threads (`device_thread`) the
devices', run-queue wait of any other thread (a holder of the lock preempted by another process)
the OS's, and what none of them explains (no thread of ours ran: a virtual CPU taken away) the
host's.

Reading a thread's schedstat is a `pread` of an open file (a few µs, the GIL held); the threads are listed
again every `RESCAN_S`. Where /proc is missing
the run-queue wait reads 0 and the CPU time comes from `time.thread_time()`.
"""
from __future__ import annotations

import ctypes
import os
import threading
import time
from dataclasses import dataclass

# Threads of this process that stand for devices (the in-process simulators of `--sim` and the
# tests): the CPU time they take is the devices', not the controller's.
_DEVICE_THREADS: set[int] = set()


def device_thread(ident: int, present: bool = True) -> None:
    """Count thread `ident` (threading.get_ident()) as a device's while `present`."""
    if present:
        _DEVICE_THREADS.add(ident)
    else:
        _DEVICE_THREADS.discard(ident)


def device_cpu_s() -> float:
    """CPU seconds the device threads of this process have run."""
    total = 0.0
    for ident in list(_DEVICE_THREADS):
        try:
            total += time.clock_gettime(time.pthread_getcpuclockid(ident))
        except (OSError, ValueError):
            _DEVICE_THREADS.discard(ident)   # that thread has ended
    return total


@dataclass(frozen=True)
class LoopSample:
    """The clocks of one cycle start, all in seconds."""

    t: float           # time.monotonic()
    loop_cpu: float    # the loop thread's CPU time
    loop_wait: float   # the loop thread's run-queue wait
    proc_cpu: float    # the whole process's CPU time
    dev_cpu: float     # the device threads' CPU time
    other_wait: float  # the run-queue wait of the process's other threads (one may hold the GIL)


@dataclass(frozen=True)
class Blame:
    """A cycle's lateness shared out, seconds: the controller's, the OS's (and the host's), the
    in-process devices'."""

    own: float
    os: float
    devices: float


# libc's pread called with the GIL held (ctypes.PyDLL): a few microseconds from /proc. `os.pread`
# releases the GIL around the call, and on the device loop every release is a wait to take it
# back behind the process's other threads (the TUI's screen, the simulators): sampled there at
# up to half of the loop's busy time, measured with a stack sampler on the TUI build.
_LIBC = ctypes.PyDLL(None)
_PREAD = _LIBC.pread
_PREAD.argtypes = (ctypes.c_int, ctypes.c_void_p, ctypes.c_size_t, ctypes.c_long)
_PREAD.restype = ctypes.c_ssize_t


def _schedstat(fd: int, buf: ctypes.Array[ctypes.c_char]) -> tuple[float, float]:
    """(CPU time, run-queue wait) in seconds from an open schedstat file, read into `buf` (the
    caller's own) without releasing the GIL."""
    n = _PREAD(fd, buf, len(buf) - 1, 0)
    if n <= 0:
        raise OSError("schedstat not readable")
    run_ns, wait_ns, _ = buf.raw[:n].split()
    return int(run_ns) / 1e9, int(wait_ns) / 1e9


class LoopClock:
    """The clocks of the calling thread (the one that cycles the devices) and of the process's other
    threads; open it on that thread."""

    RESCAN_S = 0.25   # the process's threads are listed again this often (they rarely change)

    def __init__(self) -> None:
        self._tid = threading.get_native_id()
        self._fd = self._open("/proc/thread-self/schedstat")
        self._others: dict[str, int] = {}   # thread id -> its open schedstat
        self._scanned = -1.0
        self._buf = ctypes.create_string_buffer(128)

    @staticmethod
    def _open(path: str) -> int:
        try:
            return os.open(path, os.O_RDONLY)
        except OSError:
            return -1

    def _rescan(self, now: float) -> None:
        self._scanned = now
        try:
            tids = set(os.listdir("/proc/self/task")) - {str(self._tid)}
        except OSError:
            return
        for tid in set(self._others) - tids:
            os.close(self._others.pop(tid))
        for tid in tids - set(self._others):
            if (fd := self._open(f"/proc/self/task/{tid}/schedstat")) >= 0:
                self._others[tid] = fd

    def _other_wait(self) -> float:
        total = 0.0
        for tid, fd in list(self._others.items()):
            try:
                total += _schedstat(fd, self._buf)[1]
            except (OSError, ValueError):   # that thread has ended
                os.close(self._others.pop(tid))
        return total

    def sample(self) -> LoopSample:
        now = time.monotonic()
        if now - self._scanned > self.RESCAN_S:
            self._rescan(now)
        cpu, wait = time.thread_time(), 0.0
        if self._fd >= 0:
            try:
                cpu, wait = _schedstat(self._fd, self._buf)
            except (OSError, ValueError):
                pass
        return LoopSample(now, cpu, wait, time.process_time(), device_cpu_s(), self._other_wait())

    def close(self) -> None:
        for fd in [self._fd, *self._others.values()]:
            if fd >= 0:
                os.close(fd)
        self._fd, self._others = -1, {}


def blame(late: float, a: LoopSample, b: LoopSample, stalled: float = 0.0, waited: float = 0.0) -> Blame:
    """Share out `late` seconds of a period from sample `a` to `b`; `stalled` is how long a CPU
    of the host was witnessed stopped meanwhile (controller/runtime/host_witness.py).

    `waited`: the rest of the period past its cycle, in which the loop ran its timers on time
    and waited for a device's reply. That is never the controller's; the in-process simulators'
    CPU time not already counted above is the devices' share of it (they answered late because
    they computed), so a late period's figures add up to its length."""
    late = max(0.0, late)
    os_s = min(late, max(0.0, b.loop_wait - a.loop_wait) + stalled)
    loop_cpu = max(0.0, b.loop_cpu - a.loop_cpu)
    own = min(late - os_s, loop_cpu)
    rest = late - os_s - own                         # asleep past a due timer: the GIL
    dev = max(0.0, b.dev_cpu - a.dev_cpu)
    others = max(0.0, (b.proc_cpu - a.proc_cpu) - loop_cpu - dev)   # the controller's other threads ran
    held = max(0.0, b.other_wait - a.other_wait)     # a thread that may hold the GIL waited for a CPU
    total = others + dev + held
    if rest <= 0.0 or total <= 0.0:
        # nobody of ours ran: the holder was off a CPU
        return Blame(own, os_s + rest, min(max(0.0, waited), dev))
    scale = min(1.0, rest / total)
    return Blame(own + others * scale, os_s + rest - (others + dev) * scale,
                 dev * scale + min(max(0.0, waited), dev * (1.0 - scale)))
