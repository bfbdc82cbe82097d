"""`cell sim up` as a subprocess: one JSON line per device, real URLs, logs, clean Ctrl-C."""
from __future__ import annotations

import asyncio
import json
import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from drivers.robot import RobotLink
from tests.sim_processes import cell_yaml, start, read_devices, stop

pytestmark = pytest.mark.realtime  # a cell on the wall clock (tests/conftest.py)

ROOT = Path(__file__).resolve().parents[2]


async def drive(url: str, n: int) -> int:
    link = RobotLink(url)
    await link.connect()
    t = 0
    for i in range(n):
        t = await link.send_move("MOVL", float(i), 1.0, 2.0, 0, 0, 1, 3000)
    await link.wait_executed(t, timeout=30)
    await link.close()
    return t


def test_sim_up_serves_the_robot_on_loopback_tcp_and_logs_execution(tmp_path):
    proc = start(tmp_path)
    try:
        devices = read_devices(proc)
        robot = devices["robot"]
        assert robot["url"].startswith("socket://127.0.0.1:") and robot["url"] != "socket://127.0.0.1:0"
        assert asyncio.run(drive(robot["url"], 20)) == 20
    finally:
        rc, err = stop(proc)
    assert rc == 0 and "Traceback" not in err
    log = [json.loads(x) for x in (tmp_path / "logs" / "robot.jsonl").read_text().splitlines()]
    assert [e["seq"] for e in log] == list(range(1, 21))
    assert log[-1]["target"] == [19.0, 1.0, 2.0] and set(log[0]) == {"seq", "verb", "target", "t"}
    assert all(b["t"] > a["t"] for a, b in zip(log, log[1:]))


def test_sim_up_on_ptys_stops_on_sigterm(tmp_path):
    proc = start(tmp_path, "--pty")
    try:
        robot = read_devices(proc)["robot"]
        assert robot["url"].startswith("/dev/") and os.path.exists(robot["url"])
        assert asyncio.run(drive(robot["url"], 5)) == 5
    finally:
        rc, err = stop(proc, signal.SIGTERM)
    assert rc == 0 and "Traceback" not in err
    assert len((tmp_path / "logs" / "robot.jsonl").read_text().splitlines()) == 5


def test_sim_up_reports_a_busy_port_as_one_error_line(tmp_path):
    cfg_path, cfg = cell_yaml(tmp_path)
    port = int(cfg["devices"]["robot"]["url"].rsplit(":", 1)[1])
    with socket.socket() as s:
        s.bind(("127.0.0.1", port))
        s.listen()
        r = subprocess.run([sys.executable, "-m", "controller.cli.main", "sim", "up", "--cell-config", str(cfg_path)],
                           cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:") and str(port) in lines[0]
