"""The host witness for a benchmark: every gap of every CPU over a whole run (issue 12).

controller/runtime/host_witness.py keeps the last gaps of each CPU in shared memory; this records them
all (read every 50 ms) so that each late device reply can be told apart: a CPU stopped running
the guest meanwhile (the machine's stall), or both CPUs ran their witness on time (ours).

    .venv/bin/python -m bench._host_witness 60     # watch this machine for 60 s
"""
from __future__ import annotations

import sys
import threading
import time

from controller.runtime.host_witness import HostWitness


class WitnessRecord:
    """A HostWitness for as long as the context lasts, with every gap kept: `gaps[cpu]` is a list
    of (start, ms) in monotonic time."""

    def __init__(self) -> None:
        self.gaps: dict[int, list[tuple[float, float]]] = {}
        self._w = HostWitness()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._collect, daemon=True)
        self.line = ""

    def __enter__(self) -> "WitnessRecord":
        self.line = self._w.start()
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(5)
        self._w.close()

    def _collect(self) -> None:
        seen: dict[int, set[tuple[float, float]]] = {}
        while True:
            for cpu, gs in self._w.gaps().items():
                for g in gs:
                    if g not in seen.setdefault(cpu, set()):
                        seen[cpu].add(g)
                        self.gaps.setdefault(cpu, []).append((g[0], (g[1] - g[0]) * 1000.0))
            if self._stop.wait(0.05):
                return

    def overlapping(self, t: float, dur_s: float, slack_s: float = 0.005) -> list[tuple[int, float]]:
        """Gaps (cpu, ms) overlapping [t, t + dur_s] (monotonic)."""
        return [(cpu, ms) for cpu, gs in self.gaps.items() for (t0, ms) in gs
                if t0 - slack_s <= t + dur_s and t0 + ms / 1000.0 + slack_s >= t]

    @property
    def cpus(self) -> list[int]:
        return self._w.cpus

    def longest_ms(self) -> dict[int, float]:
        return {cpu: round(max((ms for _t, ms in gs), default=0.0), 1) for cpu, gs in self.gaps.items()}


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    seconds = float(args[0]) if args else 30.0
    with WitnessRecord() as w:
        print(w.line)
        time.sleep(seconds)
    for cpu in w.cpus:
        gs = w.gaps.get(cpu, [])
        big = sorted((ms for _t, ms in gs), reverse=True)[:5]
        print(f"cpu{cpu}: {len(gs)} stalls in {seconds:g} s; longest: " + ", ".join(f"{ms:.1f} ms" for ms in big))
    return 0


if __name__ == "__main__":
    sys.exit(main())
