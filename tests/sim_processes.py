"""`cell sim up` as a separate process for the tests: its configuration, start, device URLs, stop."""
from __future__ import annotations

import json
import select
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]


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


def stop(proc: subprocess.Popen, sig: int = signal.SIGINT) -> tuple[int, str]:
    proc.send_signal(sig)
    try:
        _, err = proc.communicate(timeout=15)
    except subprocess.TimeoutExpired:
        proc.kill()
        raise AssertionError("cell sim up did not stop within 15 s") from None
    return proc.returncode, err

