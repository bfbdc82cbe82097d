"""Issue 26: `kill -9` of `cell run` / `cell resume` mid-bead, then `cell resume`, against
`cell sim up` in its own process (the simulators outlive the controller). Judged from the
simulators' deposit.jsonl: at most 2 mm lost and at most 2 mm deposited twice per restart; a
robot that lost its record (power-cycled) makes the resume refuse, saying what it knows."""
from __future__ import annotations

import argparse
import json
import math
import os
import random
import signal
import subprocess
import time
from pathlib import Path

import pytest

from bench._coverage import read_segments
from bench.kill_resume import _cell, _deposited_mm, _setup, build_with_kills

pytestmark = pytest.mark.realtime  # a cell on the wall clock (tests/conftest.py)


def _args(**kw: object) -> argparse.Namespace:
    d = {"kills": 0, "layers": 2, "max_step": 2.0, "speed": 600.0, "time_scale": 10.0}
    d.update(kw)
    return argparse.Namespace(**d)


def test_two_kills_mid_bead_lose_and_repeat_at_most_2_mm_per_restart(tmp_path: Path) -> None:
    fig = build_with_kills(_args(), tmp_path, random.Random(1), [0.25, 0.6])
    assert fig["state"] == "complete" and fig["kills"] == 2, fig
    assert fig["rearcs"] == 2, fig                              # both kills cut a bead
    assert max(fig["lost_per_restart_mm"]) <= 2.0, fig
    assert max(fig["twice_per_restart_mm"]) <= 2.0, fig
    assert fig["missing_mm"] < 0.05 and fig["excess_per_restart_mm"] <= 2.0, fig
    assert fig["robot_seq_duplicates"] == 0, fig


def _sim_up(cfgp: Path, logs: Path) -> subprocess.Popen:
    sim = _cell("sim", "up", "--cell-config", str(cfgp), "--log", str(logs), stdout=subprocess.PIPE,
                stderr=subprocess.DEVNULL, text=True)
    for _ in range(4):  # one JSON line per simulator
        assert sim.stdout is not None and sim.stdout.readline(), "cell sim up did not start"
    time.sleep(0.3)
    return sim


def _stop(p: subprocess.Popen) -> None:
    try:
        os.killpg(p.pid, signal.SIGINT)
        p.wait(10)
    except Exception:
        os.killpg(p.pid, signal.SIGKILL)
        p.wait()


def test_a_robot_that_lost_its_record_makes_resume_refuse(tmp_path: Path) -> None:
    cfgp, jobp, job = _setup(_args(layers=1), tmp_path)
    logs, runs = tmp_path / "simlog", tmp_path / "runs"
    common = ["--cell-config", str(cfgp), "--runs", str(runs), "--json", "--max-step", "2"]
    planned = sum(math.dist(p, q) for la in job["layers"] for P in la["passes"]
                  for p, q in zip(P["points"], P["points"][1:]))
    sim = _sim_up(cfgp, logs)
    try:
        run = _cell("run", str(jobp), *common, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        t0 = time.monotonic()
        while run.poll() is None and _deposited_mm(logs / "deposit.jsonl") < 0.25 * planned:
            assert time.monotonic() - t0 < 60
            time.sleep(0.01)
        os.killpg(run.pid, signal.SIGKILL)
        run.wait()
        time.sleep(0.5)
        _stop(sim)          # the robot is power-cycled: it comes back with no record of its moves
        sim = _sim_up(cfgp, logs)
        before = _deposited_mm(logs / "deposit.jsonl")
        res = _cell("resume", *common, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        out, err = res.communicate(timeout=120)
    finally:
        _stop(sim)
    assert res.returncode == 1, (res.returncode, err[-800:])
    assert "resume refused" in err and "lost its record" in err and "layer 0 pass 0" in err, err[-800:]
    state = json.loads(out.strip().splitlines()[-1])
    assert state["state"] == "fault"
    # refused before any motion: nothing more was deposited
    assert abs(_deposited_mm(logs / "deposit.jsonl") - before) < 1e-9
    assert read_segments(logs / "deposit.jsonl")
