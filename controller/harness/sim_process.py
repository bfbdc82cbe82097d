"""The simulators in a process of their own (`cell sim up` as a child): the demo's topology.

Real hardware is a separate peer; so is `cell sim up`. In one interpreter the simulators and the
controller share the GIL, and on a loaded host that skews what the controller measures (the
robot's EXE times, hence the travel speed at time scale 120). `SimProcess` starts `cell sim up`
on free loopback ports with the given cell config, waits for its device lines, and stops it
with SIGINT.
"""
from __future__ import annotations

import json
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Awaitable, Callable, TypeVar

import yaml

from controller.runtime.devices import with_urls
from core.config import CellConfig, SimConfig, load_sim
from core.errors import CellError

T = TypeVar("T")

ROOT = Path(__file__).resolve().parent.parent.parent


def _free_ports(n: int) -> list[int]:
    socks = [socket.socket() for _ in range(n)]
    try:
        for s in socks:
            s.bind(("127.0.0.1", 0))
        return [s.getsockname()[1] for s in socks]
    finally:
        for s in socks:
            s.close()


class SimProcess:
    """`cell sim up` in a child process, on free loopback ports; `.cfg` points at it."""

    in_process = False                # controller/api/simulated.py: no simulator object to reach into

    def __init__(self, cfg: CellConfig, log_dir: Path, sim_config: str | None = None,
                 timeout_s: float = 60.0, faults: str = "") -> None:
        self.sim_cfg: SimConfig = load_sim(sim_config)
        self.log_dir: Path | None = log_dir
        p = _free_ports(4)
        urls = {"robot": f"socket://127.0.0.1:{p[0]}", "cnc": f"socket://127.0.0.1:{p[1]}",
                "power_source": f"tcp://127.0.0.1:{p[2]}", "cellio": f"tcp://127.0.0.1:{p[3]}"}
        self.cfg = with_urls(cfg, urls)
        log_dir.mkdir(parents=True, exist_ok=True)
        cfg_path = log_dir / "cell.yaml"
        cfg_path.write_text(yaml.safe_dump(self.cfg.model_dump(mode="json"), sort_keys=False), encoding="utf-8")
        self._err_path = log_dir / "sim_up.stderr"
        err = self._err_path.open("w", encoding="utf-8")
        cmd = [sys.executable, "-m", "controller.cli.main", "sim", "up", "--cell-config", str(cfg_path),
               "--log", str(log_dir)]
        if sim_config:
            cmd += ["--config", sim_config]
        if faults:
            cmd += ["--fault", faults]
        self.proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=err, text=True)
        err.close()
        self._wait_ready(timeout_s)

    def _wait_ready(self, timeout_s: float) -> None:
        out = self.proc.stdout
        assert out is not None
        seen: set[str] = set()
        deadline = time.monotonic() + timeout_s
        while len(seen) < 4:
            line = out.readline()
            if not line or time.monotonic() > deadline:
                self.close()
                raise CellError(f"`cell sim up` did not start: {self._stderr_tail() or 'no output'}")
            try:
                seen.add(json.loads(line)["device"])
            except (ValueError, KeyError):
                continue
        # keep draining stdout: a pipe nobody reads fills up and blocks the simulators
        threading.Thread(target=lambda: [None for _ in out], name="sim-up-stdout", daemon=True).start()

    def _stderr_tail(self) -> str:
        try:
            return self._err_path.read_text(encoding="utf-8", errors="replace").strip()[-500:]
        except OSError:
            return ""

    @property
    def process_id(self) -> int:
        return self.proc.pid

    def sim(self, device: str) -> object:
        raise CellError(f"the simulated {device} runs in `cell sim up` (pid {self.proc.pid}), not in this process")

    def call(self, fn: Callable[..., T | Awaitable[T]], *args: object, **kwargs: object) -> T:
        raise CellError(f"the simulators run in `cell sim up` (pid {self.proc.pid}), not in this process")

    def inject(self, device: str, fault: str, *, duration_s: float | None = None) -> None:
        """A seeded fault now, over `cell sim up`'s clock line (wire/sim_clock.py, INJECT)."""
        # lazy: the clock link loads the CNC's motion module (time-scale limits)
        from controller.harness.sim_clock import SimClockLink

        clock = SimClockLink.find(self.cfg.devices.cnc.url)
        if clock is None:
            raise CellError(f"`cell sim up` (pid {self.proc.pid}) names no clock line to inject {fault} through")
        clock.inject(device, fault, duration_s)

    def set_time_scale(self, scale: float) -> None:
        raise CellError(f"`cell sim up` (pid {self.proc.pid}) keeps the time scale it was started with")

    def stop(self) -> None:
        self.close()

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
