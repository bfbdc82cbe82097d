"""Fault spec parsing and the fault channel: seeded corruption, drops, stalls, the 8N1 throttle."""
from __future__ import annotations

import asyncio
import time

import numpy as np
import pytest

from core.errors import ConfigError
from sims.faults import KEYS, FaultPipe, bytes_per_second, parse_fault_spec


def test_parses_the_issue_example_with_units():
    s = parse_fault_spec("seed=7,corrupt=0.01,drop=0.001,burst=32,latency=2ms,stall=5s,unplug@t=12s,"
                         "arc_loss@layer=3,door_open@t=20s")
    assert s.seed == 7
    assert s.value("corrupt") == 0.01 and s.value("drop") == 0.001 and s.value("burst") == 32
    assert s.value("latency") == pytest.approx(0.002) and s.value("stall") == 5.0
    assert s.events("unplug") == [("t", 12.0)]
    assert s.events("arc_loss") == [("layer", 3)]
    assert s.events("door_open") == [("t", 20.0)]
    assert s.value("ignition_fail", 0.0) == 0.0 and s.events("estop") == []


def test_device_fault_keys_are_in_the_table():
    for key in ("ignition_fail", "arc_loss", "wire_stick", "gas_fault", "wire_out", "silence", "door_open", "estop"):
        assert key in KEYS
    assert parse_fault_spec("ignition_fail=0.25").value("ignition_fail") == 0.25
    assert not parse_fault_spec("") and not parse_fault_spec(" , ")


@pytest.mark.parametrize("spec, key", [
    ("corupt=0.01", "corupt"),          # misspelt key
    ("corrupt=1.5", "corrupt"),         # probability above 1
    ("latency=2min", "latency"),        # unknown unit
    ("burst=0", "burst"),
    ("unplug@when=3s", "unplug"),        # unknown condition
    ("arc_loss@layer=x", "arc_loss@layer"),
    ("seed", "seed"),
])
def test_bad_entries_name_the_key(spec, key):
    with pytest.raises(ConfigError, match=f"'?{key}"):
        parse_fault_spec(spec)


def test_streams_are_seeded_and_independent():
    a, b = parse_fault_spec("seed=7"), parse_fault_spec("seed=7")
    assert np.array_equal(a.rng("robot.in").random(5), b.rng("robot.in").random(5))
    assert not np.array_equal(a.rng("robot.in").random(5), a.rng("robot.out").random(5))
    assert not np.array_equal(a.rng("x").random(5), parse_fault_spec("seed=8").rng("x").random(5))


async def _pump(spec: str, data: bytes, rate: float | None = None, seconds: float = 0.0) -> tuple[bytes, FaultPipe]:
    got = bytearray()
    pipe = FaultPipe(got.extend, parse_fault_spec(spec), stream="test", rate=rate)
    pipe.send(data)
    t0 = time.monotonic()
    while pipe.bytes_in - len(pipe._buf) < len(data) and time.monotonic() - t0 < 10:
        await asyncio.sleep(0.01)
    await asyncio.sleep(seconds + 0.02)
    pipe.close()
    return bytes(got), pipe


async def test_corruption_and_drops_match_the_spec_and_the_seed():
    data = bytes(range(256)) * 400  # 102,400 bytes
    got, pipe = await _pump("seed=3,corrupt=0.01", data)
    assert len(got) == len(data)
    flipped = np.frombuffer(got, np.uint8) ^ np.frombuffer(data, np.uint8)
    assert 0.008 < np.count_nonzero(flipped) / len(data) < 0.012
    assert all(bin(int(x)).count("1") == 1 for x in flipped[flipped != 0][:200])  # single bit flips
    again, _ = await _pump("seed=3,corrupt=0.01", data)
    assert again == got  # same seed, same damage
    got, pipe = await _pump("seed=3,drop=0.001", data)
    assert 50 < len(data) - len(got) < 160 and pipe.dropped == len(data) - len(got)


async def test_bursty_corruption_hits_consecutive_bytes():
    data = bytes(100_000)
    got, _ = await _pump("seed=5,corrupt=0.01,burst=32", data)
    hit = np.frombuffer(got, np.uint8) != 0
    assert 0.007 < hit.mean() < 0.013
    starts = np.count_nonzero(hit[1:] & ~hit[:-1])
    assert starts < hit.sum() / 10  # a few long bursts, not scattered bytes


async def test_throttle_carries_at_most_11520_bytes_per_second():
    assert bytes_per_second(115200) == 11520
    arrivals: list[tuple[float, int]] = []
    pipe = FaultPipe(lambda d: arrivals.append((time.monotonic(), len(d))), None, rate=11520)
    t0 = time.monotonic()
    pipe.send(bytes(5760))  # half a second of line time
    while sum(n for _, n in arrivals) < 5760 and time.monotonic() - t0 < 5:
        await asyncio.sleep(0.01)
    pipe.close()
    elapsed = arrivals[-1][0] - t0
    assert 0.47 < elapsed < 1.0
    # no window of 0.1 s carries more than 0.1 s of line time (plus one catch-up burst)
    for t, _ in arrivals:
        in_window = sum(n for u, n in arrivals if t <= u < t + 0.1)
        # (a catch-up chunk carries up to MAX_BURST_S + CHUNK_S of line time: the tick it was due in
        # plus what it caught up on; make test at load 13 saw 1,404 bytes against 1,383 without CHUNK_S)
        assert in_window <= 1152 + 11520 * (FaultPipe.MAX_BURST_S + FaultPipe.CHUNK_S) + 1


async def test_latency_and_stall_delay_but_keep_bytes():
    got, _ = await _pump("latency=50ms", b"abc", seconds=0.1)
    assert got == b"abc"
    arrivals = []
    pipe = FaultPipe(lambda d: arrivals.append(time.monotonic()), parse_fault_spec("stall=0.3s,stall@t=0s"))
    t0 = time.monotonic()
    pipe.send(b"held")
    await asyncio.sleep(0.5)
    pipe.close()
    assert arrivals and arrivals[0] - t0 >= 0.28
