"""Did every CPU of this host run? A witness per CPU, for the link budget (docs/false-trips.md).

A device's reply is read by some CPU of this host (the loopback sender's, the network card's
interrupt CPU, the serial reader's). When one CPU stops running the guest (a virtual CPU taken
away by the hypervisor, measured here at up to ~190 ms while the other CPU ran on), a reply can
sit unread although the device answered and the controller's own timers fired on time. The link
budget (drivers/cyclic.py) must not count such a cycle against the device, as it already does not
count a cycle the controller itself did not run.

One tiny process per CPU, pinned to it at the highest SCHED_FIFO priority and importing nothing
of ours, wakes every 2 ms and writes its wake time and its recent gaps (a wake more than
`GAP_S` late) into shared memory (a seqlock per CPU); `stalled_s(t0, t1)` reads them.
The witness only runs where it gets real-time priority: a time-shared witness would see gaps
under any load and excuse a really silent device. Run as a script, it is the witness itself.
"""
from __future__ import annotations

import mmap
import os
import struct
import subprocess
import sys
import time

PERIOD_S = 0.002
GAP_S = 0.005          # a wake this much later than due is a stall of that CPU
RING = 32              # gaps kept per CPU
_HEAD = struct.Struct("<QQdQ")    # seq, realtime flag, last wake (monotonic), gaps written
_GAP = struct.Struct("<dd")       # start, end (monotonic)
SLOT = _HEAD.size + RING * _GAP.size


def _watch(fd: int, slot: int, cpu: int) -> None:
    """The witness loop (in its own process): runs until its parent is gone."""
    buf = mmap.mmap(fd, 0)
    base = slot * SLOT
    try:
        os.sched_setaffinity(0, {cpu})
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(os.sched_get_priority_max(os.SCHED_FIFO)))
        rt = 1
    except OSError:
        rt = 0
    parent = os.getppid()
    seq, gaps, n = 0, 0, 0
    last = time.monotonic()
    while True:
        time.sleep(PERIOD_S)
        now = time.monotonic()
        seq += 1
        struct.pack_into("<Q", buf, base, seq)          # odd: being written
        if now - last - PERIOD_S > GAP_S:
            _GAP.pack_into(buf, base + _HEAD.size + (gaps % RING) * _GAP.size, last + PERIOD_S, now)
            gaps += 1
        _HEAD.pack_into(buf, base, seq + 1, rt, now, gaps)
        seq += 1
        last = now
        n += 1
        if n % 500 == 0 and os.getppid() != parent:   # the controller is gone
            return


class HostWitness:
    """The witnesses of this host's CPUs, started with `start()` and ended with `close()`."""

    def __init__(self) -> None:
        self.cpus = sorted(os.sched_getaffinity(0))
        self._fd = -1
        self._buf: mmap.mmap | None = None
        self._procs: list[subprocess.Popen[bytes]] = []

    def start(self, timeout_s: float = 2.0) -> str:
        """Start one witness per CPU; one line for the log: what was obtained, or why not."""
        self._fd = os.memfd_create("cell-host-witness")
        os.ftruncate(self._fd, SLOT * len(self.cpus))
        self._buf = mmap.mmap(self._fd, 0)
        for slot, cpu in enumerate(self.cpus):
            # -S -I: the interpreter alone (no site, no project imports): starts in ~15 ms
            self._procs.append(subprocess.Popen(
                [sys.executable, "-S", "-I", __file__, str(self._fd), str(slot), str(cpu)],
                pass_fds=(self._fd,), stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL))
        deadline = time.monotonic() + timeout_s
        def all_realtime() -> bool:
            return all((h := self._read(s)) is not None and h[1] for s in range(len(self.cpus)))

        while time.monotonic() < deadline and not all_realtime():
            time.sleep(0.005)
        if not all_realtime():
            self.close()
            return ("host witness: not started (no real-time priority for it); a CPU of this host that "
                    "stalls may be taken for a silent device")
        return f"host witness: {len(self.cpus)} CPUs watched (SCHED_FIFO, {PERIOD_S * 1000:.0f} ms)"

    @property
    def pids(self) -> list[int]:
        """The witness processes, one per CPU in `cpus` order."""
        return [p.pid for p in self._procs]

    @property
    def running(self) -> bool:
        return self._buf is not None

    def _read(self, slot: int) -> tuple[float, int, list[tuple[float, float]]] | None:
        """(last wake, realtime flag, recent gaps) of one CPU, read consistently; None while its
        witness is caught in the middle of a write (it stopped running there: a stall)."""
        assert self._buf is not None
        base = slot * SLOT
        for _ in range(20):
            seq, rt, last, n = _HEAD.unpack_from(self._buf, base)
            if seq & 1:
                continue
            gaps = [_GAP.unpack_from(self._buf, base + _HEAD.size + (i % RING) * _GAP.size)
                    for i in range(max(0, n - RING), n)]
            if _HEAD.unpack_from(self._buf, base)[0] == seq:
                return last, rt, gaps
        return None

    def stalled_s(self, t0: float, t1: float) -> float:
        """How long some CPU of this host did not run between monotonic times t0 and t1 (the
        most over the CPUs of its recorded gaps, and of a gap still going on, within the span)."""
        if self._buf is None:
            return 0.0
        now = time.monotonic()
        worst = 0.0
        for slot in range(len(self.cpus)):
            head = self._read(slot)
            if head is None:   # caught mid-write: stalled now, since at least its period
                return max(0.0, min(t1, now) - max(t0, now - PERIOD_S))
            last, _rt, gaps = head
            if now - last > PERIOD_S + GAP_S:
                gaps = [*gaps, (last + PERIOD_S, now)]
            worst = max(worst, sum(max(0.0, min(e, t1) - max(s, t0)) for s, e in gaps))
        return worst

    def gaps(self) -> dict[int, list[tuple[float, float]]]:
        """The recent gaps (start, end) of each CPU (the last RING of them)."""
        if self._buf is None:
            return {}
        return {cpu: (h[2] if (h := self._read(slot)) is not None else []) for slot, cpu in enumerate(self.cpus)}

    def close(self) -> None:
        for p in self._procs:
            p.kill()
        for p in self._procs:
            p.wait(5)
        self._procs = []
        if self._buf is not None:
            self._buf.close()
            self._buf = None
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1


if __name__ == "__main__":
    _watch(int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]))
