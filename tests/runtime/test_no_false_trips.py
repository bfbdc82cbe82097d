"""No false trips (issue 12): builds against `cell sim up` in its own process, CPU hogs beside them.

The separate-process topology is the one real hardware has. Three builds of the 80 x 50 x 8 mm
block (6 mm beads, time scale 60), each against a fresh `cell sim up`, with a CPU-bound process
running beside them on this 2-core machine (one, not the benchmark's two: the other test worker
shares the machine): every build completes, no power-source watchdog drop, unless the host
witness saw a CPU of this machine stop longer than the limit that tripped. bench/false_trips.py
runs the 100-build version with two hogs and gives the reply-time figures.
"""
from __future__ import annotations

from pathlib import Path

import pytest

from bench.false_trips import block_job, host_explained, one_build, pct


# A soak: it owns the machine. Under `make test` the other worker runs a real-time cell of its own
# (simulators at SCHED_FIFO 30, a controller at 20) on the same two cores, which no cell has. Run it
# alone: `python -m bench.soak -k no_false_trips` (docs/testing.md says why CI does not).
@pytest.mark.slow
def test_three_builds_beside_a_cpu_hog_complete_without_a_false_trip(tmp_path: Path) -> None:
    job = block_job(tmp_path, 8.0)
    results = [one_build(job, tmp_path / f"b{i}", hog=True, hogs=1, timeout_s=300) for i in range(3)]
    for r in results:
        # a fault is only excused when the host witness saw a CPU of this machine stop for longer
        # than the limit that tripped (100 ms watchdog, 50 ms link budget): the device then did
        # what a real one does (bench/false_trips.host_explained; docs/false-trips.md)
        if host_explained(r):
            continue
        assert r["state"] == "complete" and not r["alarms"], (r["state"], r["exit"], r["alarms"], r["defects"],
                                                               r["error"], r["witness_max_gap_ms"])
        assert r["watchdog_drops"] == 0
        # A bead may be flagged, not tripped: at time scale 60 the robot's 64-move queue holds
        # 20-60 ms of a rounded corner's short moves, and a controller late by that much (beside
        # the hog) leaves it empty for a moment; the record says so (exit 3), the build goes on.
        # Anything else flagged is a failure (docs/false-trips.md).
        timing = ("motion queue ran empty", "torch stood still")
        assert r["exit"] in (0, 3) and all(any(t in d for t in timing) for d in r["defects"]), r["defects"]
    assert sum(r["state"] == "complete" for r in results) >= 2, [r["witness_max_gap_ms"] for r in results]
    # the independent client was answered all along (figures: bench/false_trips.py)
    for dev in ("power_source", "cellio"):
        times = [x for r in results for x in r["reply_ms"][dev]]
        assert len(times) > 100 and sum(r["probe_errors"][dev] for r in results) == 0
        assert pct(times, 50) < 20.0, (dev, pct(times, 50), pct(times, 99), max(times))
