"""Every stop is safe (issue 26): each stop path N times against `cell sim up` in its own process.

Per run: `cell run` of a small job as a subprocess, a stop at a random moment of a bead, then
`cell resume` to the end. Judged from the simulators' side, never from the controller's account:

- weld-start-drop latency: a second Modbus TCP client polls the power source's command register
  0xF001 every ~2 ms; the time from the signal (os.kill) to the first read with weld start (b0) 0;
- hold verified: the motion log (robot.jsonl / cnc.jsonl) executes nothing after the hold landed
  (robot: no EXE later than 0.5 s after the signal; CNC: the safe stop verified in the journal);
- CNC: status read from the simulator after the stop (`?`): state, spindle (FS) and Bf: queue;
- the cause in the journal (an alarm naming the signal / the journal path), never `complete`;
- path `journal`: the runs directory is a 16 MB tmpfs of its own (root), filled to ENOSPC mid-bead;
- resume: lost / twice mm from deposit.jsonl (bench/_coverage.py).

    .venv/bin/python -m bench.stops [--runs 5] [--paths sigint,sigterm,sighup,second,journal]
        [--platform robot|cnc] [--keep DIR]
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import random
import signal
import socket
import sqlite3
import struct
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import yaml

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench._coverage import coverage, read_segments  # noqa: E402

SIGNALS = {"sigint": signal.SIGINT, "sigterm": signal.SIGTERM, "sighup": signal.SIGHUP}


def free_port() -> int:
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


def job(n_layers: int = 2, speed: float = 600.0, side: float = 30.0) -> dict:
    """One square perimeter per layer: ~12 s of arc per layer at 600 mm/min."""
    layers = []
    for li in range(n_layers):
        z = 1.0 * (li + 1)
        pts = [[0, 0, z], [side, 0, z], [side, side, z], [0, side, z], [0, 0.5, z]]
        layers.append({"index": li, "z_mm": z, "height_mm": 1.0, "passes": [
            {"role": "perimeter", "width_mm": 5, "current_a": 120, "speed_mm_min": speed, "wfs_m_min": 5.5,
             "points": pts}]})
    return {"schema": "cell-job/1", "source": {"file": "stops.stl", "sha256": "0" * 64, "units": "mm"},
            "material": {"name": "inconel718-1.0mm"},
            "bead": {"width_mm": 5, "height_mm": 1, "step_over_mm": 3.69, "model": "tangent"},
            "layers": layers, "summary": {}}


class WeldStartWatch:
    """A second Modbus TCP client on the power source: when weld start (0xF001 b0) reads 0."""

    def __init__(self, url: str) -> None:
        host, port = url.split("://", 1)[1].rsplit(":", 1)
        self.addr = (host, int(port))
        self.samples: list[tuple[float, int]] = []   # (monotonic, register value)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        tid = 0
        while not self._stop.is_set():
            try:
                with socket.create_connection(self.addr, timeout=1.0) as s:
                    s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                    while not self._stop.is_set():
                        tid = (tid + 1) & 0xFFFF
                        s.sendall(struct.pack(">HHHBBHH", tid, 0, 6, 1, 3, 0xF001, 1))
                        head = _recv(s, 9)
                        body = _recv(s, head[8])
                        if head[7] == 3 and len(body) >= 2:
                            self.samples.append((time.monotonic(), struct.unpack(">H", body[:2])[0]))
                        time.sleep(0.002)
            except (OSError, IndexError):
                time.sleep(0.05)

    def drop_after(self, t0: float) -> float | None:
        """Seconds from t0 to the first read at or after t0 with weld start 0 (None: never)."""
        on_before = any(v & 1 for t, v in self.samples if t0 - 0.5 < t < t0)
        for t, v in self.samples:
            if t >= t0 and not v & 1:
                return (t - t0) if on_before else 0.0
        return None

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)


def _recv(s: socket.socket, n: int) -> bytes:
    buf = b""
    while len(buf) < n:
        chunk = s.recv(n - len(buf))
        if not chunk:
            raise OSError("closed")
        buf += chunk
    return buf


def cnc_status(url: str, timeout: float = 3.0) -> str | None:
    """One `?` status report read straight from the CNC simulator's socket."""
    host, port = url.split("://", 1)[1].rsplit(":", 1)
    try:
        with socket.create_connection((host, int(port)), timeout=timeout) as s:
            deadline = time.monotonic() + timeout
            buf = b""
            while time.monotonic() < deadline:
                s.sendall(b"?")
                s.settimeout(0.3)
                try:
                    buf += s.recv(4096)
                except socket.timeout:
                    continue
                for line in buf.decode("ascii", "replace").splitlines():
                    if line.startswith("<") and line.endswith(">"):
                        return line
    except OSError:
        return None
    return None


@dataclass
class SimCell:
    """`cell sim up` in its own process with a cell.yaml of free ports."""

    work: Path
    platform: str = "robot"
    time_scale: float = 1.0
    cfg_path: Path = field(init=False)
    cfg: dict = field(init=False)
    proc: subprocess.Popen | None = None

    def __post_init__(self) -> None:
        self.work.mkdir(parents=True, exist_ok=True)
        cfg = yaml.safe_load((ROOT / "config" / "cell.yaml").read_text())
        cfg["cell"]["platform"] = self.platform
        cfg["cell"]["time_scale"] = self.time_scale
        cfg["devices"]["robot"]["url"] = f"socket://127.0.0.1:{free_port()}"
        cfg["devices"]["cnc"]["url"] = f"socket://127.0.0.1:{free_port()}"
        cfg["devices"]["power_source"]["url"] = f"tcp://127.0.0.1:{free_port()}"
        cfg["devices"]["cellio"]["url"] = f"tcp://127.0.0.1:{free_port()}"
        self.cfg = cfg
        self.cfg_path = self.work / "cell.yaml"
        self.cfg_path.write_text(yaml.safe_dump(cfg))
        self.logs, self.runs = self.work / "simlog", self.work / "runs"

    def up(self) -> "SimCell":
        self.proc = cell("sim", "up", "--cell-config", str(self.cfg_path), "--log", str(self.logs),
                         stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
        for _ in range(4):
            if not self.proc.stdout.readline():  # type: ignore[union-attr]
                raise RuntimeError("cell sim up did not start")
        threading.Thread(target=lambda: [None for _ in self.proc.stdout], daemon=True).start()  # type: ignore[union-attr]
        time.sleep(0.3)
        return self

    def down(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()

    def url(self, device: str) -> str:
        return str(self.cfg["devices"][device]["url"])

    def run(self, *args: str, env: dict | None = None) -> subprocess.Popen:
        return cell(*args, "--cell-config", str(self.cfg_path), "--runs", str(self.runs), "--json",
                    "--max-step", "0.5", stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env)


def cell(*args: str, **kw) -> subprocess.Popen:
    env = kw.pop("env", None) or dict(os.environ)
    env.setdefault("PYTHONPATH", str(ROOT))
    return subprocess.Popen([sys.executable, "-m", "controller.cli.main", *args], cwd=ROOT, text=True,
                            env=env, **kw)


def wait_arc(proc: subprocess.Popen, timeout: float = 60.0) -> list[str]:
    """Read the controller's stderr until a bead is depositing; the lines read (a thread keeps reading)."""
    lines: list[str] = []
    ev = threading.Event()

    def pump() -> None:
        for line in proc.stderr:  # type: ignore[union-attr]
            lines.append(line)
            if "passes done" in line:   # the first progress line: travel, then the arc (~1 s)
                ev.set()
        ev.set()
    threading.Thread(target=pump, daemon=True).start()
    ev.wait(timeout)
    return lines


def journal_rows(run_dir: Path, sql: str) -> list[tuple]:
    db = sqlite3.connect(f"file:{run_dir / 'journal.sqlite'}?mode=ro", uri=True)
    try:
        return db.execute(sql).fetchall()
    finally:
        db.close()


def one_stop(c: SimCell, jobp: Path, path: str, rng: random.Random) -> dict:
    """One stop path on a fresh build of `jobp`, then `cell resume` to the end; the figures."""
    watch = WeldStartWatch(c.url("power_source"))
    p = c.run("run", str(jobp), "--new")
    lines = wait_arc(p)
    time.sleep(rng.uniform(2.5, 8.0))        # a random moment of the bead (arc on from ~1.5 s to ~13 s)
    sig = SIGNALS.get(path, signal.SIGTERM)
    t_sig = time.monotonic()
    if path == "journal":                    # the runs directory (a tmpfs of its own) fills up
        filler = fill(c.runs)
    else:
        os.kill(p.pid, sig)
    if path == "second":
        time.sleep(0.05)
        os.kill(p.pid, signal.SIGINT)        # noted, not obeyed
    out, err = p.communicate(timeout=120)
    t_exit = time.monotonic()
    lines.append(err)
    time.sleep(0.3)
    watch.close()
    res = json.loads(out.strip().splitlines()[-1]) if out.strip() else {}
    run_dir = Path(res.get("run_dir") or "")
    alarms = journal_rows(run_dir, "SELECT message FROM events WHERE kind='alarm'") if run_dir.is_dir() else []
    states = journal_rows(run_dir, "SELECT state FROM events WHERE kind='transition'") if run_dir.is_dir() else []
    fig = {"path": path, "exit": p.returncode, "state": res.get("state"),
           "weld_start_drop_ms": _ms(watch.drop_after(t_sig)), "exit_after_s": round(t_exit - t_sig, 2),
           "cause_journaled": any((signal.Signals(sig).name if path != "journal" else "a write failed") in m
                                  for (m,) in alarms + [(a["message"],) for a in res.get("alarms", [])]),
           "complete_journaled": any(s == "complete" for (s,) in states),
           "second_noted": any("noted, not obeyed" in ln for ln in lines) if path == "second" else None}
    if c.platform == "cnc":
        fig["cnc_status"] = cnc_status(c.url("cnc"))
        stops = journal_rows(run_dir, "SELECT message FROM events WHERE message LIKE 'cnc safe stop:%'")
        fig["cnc_safe_stop"] = stops[-1][0] if stops else None
    else:   # the held position comes from the robot's own STA in HOLD (interlocks._record)
        held = journal_rows(run_dir, "SELECT x FROM events WHERE kind='alarm' AND x IS NOT NULL")
        fig["robot_hold_confirmed"] = bool(held)
    if path == "journal":
        filler.unlink()                      # space freed: the operator's `cell resume`
    r = c.run("resume", str(run_dir))
    rout, rerr = r.communicate(timeout=600)
    fig["resume_exit"] = r.returncode
    fig["resume_state"] = (json.loads(rout.strip().splitlines()[-1]) if rout.strip() else {}).get("state")
    return fig


def fill(where: Path) -> Path:
    """Fill the file system of `where` to the last byte (ENOSPC)."""
    filler = where / "filler"
    with open(filler, "wb") as fh:
        try:
            while True:
                fh.write(b"\0" * (1 << 20))
                fh.flush()
        except OSError:
            pass
    with contextlib.suppress(OSError):
        os.sync()
    return filler


@contextlib.contextmanager
def small_fs(where: Path, size: str = "16m") -> Iterator[Path]:
    """A tmpfs of `size` mounted at `where` (root; RuntimeError where mounting is not allowed)."""
    where.mkdir(parents=True, exist_ok=True)
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(where)],
                       capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"cannot mount a tmpfs at {where}: {r.stderr.strip()}")
    try:
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], check=False)


def _ms(v: float | None) -> float | None:
    return None if v is None else round(v * 1000, 1)


def judge(c: SimCell, job_d: dict) -> dict:
    passes = [p["points"] for la in job_d["layers"] for p in la["passes"]]
    cov = coverage(passes, read_segments(c.logs / "deposit.jsonl"))
    return {"lost_mm": round(cov.missing_mm, 3), "twice_mm": round(cov.excess_mm, 3),
            "max_overlap_mm": round(max(cov.overlaps_mm, default=0.0), 3)}


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="bench.stops")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--paths", default="sigint,sigterm,sighup,second,journal")
    ap.add_argument("--platform", default="robot", choices=("robot", "cnc"))
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--keep", default=None, metavar="DIR")
    a = ap.parse_args(argv)
    rng = random.Random(a.seed)
    base = Path(a.keep) if a.keep else Path(tempfile.mkdtemp(prefix="stops-"))
    rows = []
    for path in a.paths.split(","):
        for k in range(a.runs):
            c = SimCell(base / f"{path}-{k}", platform=a.platform).up()
            try:
                jd = job(1)
                jobp = c.work / "job.json"
                jobp.write_text(json.dumps(jd))
                with (small_fs(c.runs) if path == "journal" else contextlib.nullcontext()):
                    fig = one_stop(c, jobp, path, rng)
                fig.update(judge(c, jd))
            finally:
                c.down()
            rows.append(fig)
            print(json.dumps(fig), flush=True)
    lat = [r["weld_start_drop_ms"] for r in rows if r["weld_start_drop_ms"] is not None]
    print(json.dumps({"runs": len(rows), "weld_start_drop_ms_max": max(lat, default=None),
                      "weld_start_drop_ms_mean": round(sum(lat) / len(lat), 1) if lat else None,
                      "never_complete": not any(r["complete_journaled"] for r in rows),
                      "cause_journaled": all(r["cause_journaled"] for r in rows),
                      "resumed_complete": all(r["resume_state"] == "complete" for r in rows),
                      "lost_mm_max": max(r["lost_mm"] for r in rows), "twice_mm_max": max(r["twice_mm"] for r in rows),
                      "dir": str(base)}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
