"""`cell sim up` as a subprocess: one JSON line per device, real URLs, logs, clean Ctrl-C."""
from __future__ import annotations

import asyncio
import json
import os
import select
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from drivers.robot import RobotLink

pytestmark = pytest.mark.realtime  # a cell on the wall clock (tests/conftest.py)

ROOT = Path(__file__).resolve().parent.parent


def free_ports(n: int) -> list[int]:
    socks = [socket.socket() for _ in range(n)]
    for s in socks:
        s.bind(("127.0.0.1", 0))
    ports = [s.getsockname()[1] for s in socks]
    for s in socks:
        s.close()
    return ports


def cell_yaml(tmp_path: Path) -> tuple[Path, dict]:
    cfg = yaml.safe_load((ROOT / "config" / "cell.yaml").read_text())
    p = free_ports(4)
    cfg["devices"]["robot"]["url"] = f"socket://127.0.0.1:{p[0]}"
    cfg["devices"]["cnc"]["url"] = f"socket://127.0.0.1:{p[1]}"
    cfg["devices"]["power_source"]["url"] = f"tcp://127.0.0.1:{p[2]}"
    cfg["devices"]["cellio"]["url"] = f"tcp://127.0.0.1:{p[3]}"
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path, cfg


def start(tmp_path: Path, *extra: str) -> subprocess.Popen:
    cfg_path, _ = cell_yaml(tmp_path)
    return subprocess.Popen([sys.executable, "-m", "controller.cli.main", "sim", "up", "--cell-config", str(cfg_path),
                             "--log", str(tmp_path / "logs"), *extra],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def read_devices(proc: subprocess.Popen, want: str = "robot", timeout: float = 30.0) -> dict[str, dict]:
    """The JSON lines printed at start-up, until `want` is among them and output pauses."""
    seen: dict[str, dict] = {}
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        ready, _, _ = select.select([proc.stdout], [], [], 0.5 if want in seen else 1.0)
        if not ready:
            if want in seen:
                return seen
            if proc.poll() is not None:
                break
            continue
        line = proc.stdout.readline()
        if not line:
            break
        obj = json.loads(line)
        seen[obj["device"]] = obj
    if want not in seen:
        proc.kill()
        raise AssertionError(f"no {want} line; stderr: {proc.stderr.read()}")
    return seen


async def drive(url: str, n: int) -> int:
    link = RobotLink(url)
    await link.connect()
    t = 0
    for i in range(n):
        t = await link.send_move("MOVL", float(i), 1.0, 2.0, 0, 0, 1, 3000)
    await link.wait_executed(t, timeout=30)
    await link.close()
    return t


def stop(proc: subprocess.Popen, sig: int = signal.SIGINT) -> tuple[int, str]:
    proc.send_signal(sig)
    try:
        _, err = proc.communicate(timeout=15)
    except subprocess.TimeoutExpired:
        proc.kill()
        raise AssertionError("cell sim up did not stop within 15 s") from None
    return proc.returncode, err


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
