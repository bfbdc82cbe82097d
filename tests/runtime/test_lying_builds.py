"""Builds against devices that flood, lie, garble, go mute or stay faulted (issue 13).

One run of each misbehaviour (bench/lying_devices.py runs ten): the build ends in a latched
fault within 5 s of the misbehaviour (or completes correctly), weld start dropped, motion held,
the journal intact, and the controller's deposited length (from measurements) equal to the
simulator's deposit log within 1 mm. Plus `cell sim up` in its own process with a lying robot,
and a power source whose error stays latched across restarts.
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from bench.lying_devices import one_run, small_job

pytestmark = pytest.mark.realtime  # a cell on the wall clock (tests/conftest.py)

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("mode", ["flood", "lie", "garble", "mute"])
def test_a_misbehaving_robot_ends_the_build_in_a_fault_with_the_account_right(tmp_path, mode):
    r = one_run(mode, 0, tmp_path)  # misbehaves from the 15th executed move (first layer)
    if r["alarm"] and "watchdog" in r["alarm"]:
        pytest.skip("the machine's load stalled the power-source cycle first (not the robot under test)")
    assert r["state"] == "fault", r
    assert r["latency_s"] is not None and r["latency_s"] < 5.0, r
    assert not r["weld_start"] and not r["moving"], r
    assert r["journal_ok"]
    # never more than the simulator deposited; equal within 1 mm where the robot can still say
    # where it stopped (flood, lie). A garbling / mute robot cannot: its last stretch is timed
    # from the last EXE (bench/lying_devices.py reports that difference)
    assert r["controller_mm"] <= r["sim_mm"] + 1.0, r
    if mode in ("flood", "lie"):
        assert abs(r["controller_mm"] - r["sim_mm"]) <= 1.0, r
    assert r["sim_mm"] < r["planned_mm"]  # it really stopped: nothing claims the whole job


def test_a_latched_power_source_error_moves_nothing_until_an_explicit_reset(tmp_path):
    r = one_run("latched", 0, tmp_path)
    assert r["state"] == "fault" and r["robot_moves"] == 0 and r["sim_mm"] == 0.0, r
    assert "error 50" in r["alarm"] and "--reset-errors" in r["alarm"]
    assert r["second_state"] == "complete" and abs(r["second_sim_mm"] - r["planned_mm"]) < 1.0


def _sim_up(tmp_path: Path, fault: str):
    from tests.sim_processes import cell_yaml, read_devices

    cfg_path, _ = cell_yaml(tmp_path)
    proc = subprocess.Popen([sys.executable, "-m", "controller.cli.main", "sim", "up", "--cell-config", str(cfg_path),
                             "--log", str(tmp_path / "logs"), "--fault", fault],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    read_devices(proc, want="robot", timeout=90.0)  # all lines come at once
    return proc, cfg_path


LOAD_SIGNS = ("no reply within", "watchdog")  # a loaded 2-core machine stalls the 10 ms bus cycles


def _cell_run(args: list[str], tmp_path: Path, tries: int = 3) -> tuple[subprocess.CompletedProcess, dict]:
    """`cell run ...` in its own process; retried (fresh runs dir) when the machine's load, not
    the device under test, tripped the cell (skipped if it always does)."""
    for k in range(tries):
        runs = tmp_path / f"runs{k}"
        # a retry after a load trip finds the source's watchdog error latched: clear it
        again = ["--reset-errors"] if k and "--reset-errors" not in args else []
        r = subprocess.run([sys.executable, "-m", "controller.cli.main", "run", *args, *again, "--json",
                            "--runs", str(runs)],
                           cwd=ROOT, capture_output=True, text=True, timeout=120)
        out = json.loads(r.stdout) if r.stdout.strip() else {"alarms": [], "error": r.stderr}
        text = r.stderr + " ".join(a["message"] for a in out.get("alarms", [])[:1])
        if not any(sign in text for sign in LOAD_SIGNS):
            return r, out
    pytest.skip(f"the machine's load tripped every attempt: {text[:200]}")


def test_cell_run_against_a_lying_robot_in_its_own_process(tmp_path):
    from tests.sim_processes import stop

    proc, cfg_path = _sim_up(tmp_path, "lie@move=20")
    try:
        job = tmp_path / "job.json"
        job.write_text(json.dumps(small_job(2)))
        r, out = _cell_run([str(job), "--cell-config", str(cfg_path)], tmp_path)
    finally:
        stop(proc)
    assert r.stdout, r.stderr
    assert r.returncode == 1 and out["state"] == "fault", (r.stdout, r.stderr)
    assert any("protocol fault" in a["message"] for a in out["alarms"]), out["alarms"]
    deposited = sum(1 for _ in (tmp_path / "logs" / "deposit.jsonl").open()) if (
        tmp_path / "logs" / "deposit.jsonl").exists() else 0
    assert out["passes_done"] < 4 and deposited > 0


def test_power_error_latched_across_sim_restarts_is_refused_before_motion(tmp_path):
    from tests.sim_processes import stop

    job = tmp_path / "job.json"
    job.write_text(json.dumps(small_job(1)))
    proc, cfg_path = _sim_up(tmp_path, "latched_error=50")
    stop(proc)  # restart: the error must survive it (kept in the log dir)
    proc, _ = _sim_up(tmp_path, "latched_error=0")
    try:
        # _sim_up wrote a new cell.yaml with new ports
        cfg_path = tmp_path / "cell.yaml"
        r, out = _cell_run([str(job), "--cell-config", str(cfg_path)], tmp_path)
        assert r.stdout, r.stderr
        robot_log = tmp_path / "logs" / "robot.jsonl"
        assert r.returncode == 1 and out["state"] == "fault"
        assert any("error 50" in a["message"] and "--reset-errors" in a["message"] for a in out["alarms"])
        assert not robot_log.exists() or robot_log.read_text() == ""   # no motion at all
        r2, out2 = _cell_run([str(job), "--reset-errors", "--cell-config", str(cfg_path)], tmp_path / "second")
        assert r2.returncode == 0 and out2["state"] == "complete", (r2.stdout, r2.stderr)
    finally:
        stop(proc)


def test_a_robot_whose_flush_leaves_moves_queued_is_refused_before_motion(tmp_path):
    """The robot says IDLE after `!ABORT` but two queue slots stay taken: the readiness check holds
    the flushed queue against the queue size learned at connect and refuses before any motion."""
    job = tmp_path / "job.json"
    job.write_text(json.dumps(small_job(1)))
    r, out = _cell_run([str(job), "--sim", "--fault", "phantom=2"], tmp_path)
    assert r.returncode == 1 and out["state"] == "fault", (r.stdout, r.stderr)
    msg = " ".join(a["message"] for a in out["alarms"])
    assert "robot at" in msg and "62 of 64 queue slots free" in msg, msg
    assert out["passes_done"] == 0 and out["arc_starts"] == 0, out
