"""False trips under ordinary load (issue 12): builds against `cell sim up` in its own process.

    .venv/bin/python -m bench.false_trips                 # 100 builds, half with two CPU hogs
    .venv/bin/python -m bench.false_trips --builds 10     # a shorter run
    .venv/bin/python -m bench.false_trips --height 3      # a thinner block

A host witness (controller/runtime/host_witness.py: one SCHED_FIFO 99 process pinned to each CPU, as the
controller runs too) tells each reply over 20 ms apart: a CPU stopped running the guest meanwhile
(the machine), or not (ours).

Each build: a fresh `cell sim up` (cell.yaml at time scale 60, free ports), then `cell run` of a
planned 80 x 50 x 8 mm block (6 mm beads) in another process, as a new user would. With `--hog`
(every other build) two CPU-bound processes run beside them on this 2-core machine. Meanwhile an
independent Modbus client reads the power source and the cell I/O every 10 ms and records its
reply times. A build that ends anywhere but `complete`, or a power-source watchdog drop (error
50 in the simulator's log), is a false trip: no fault injection asks for one; unless the host
witness saw a CPU of this machine stop for longer than the limit that tripped (then it is counted
apart, as `host_stall_trips`: the device did what a real one would).
"""
from __future__ import annotations

import argparse
import asyncio
import json
import multiprocessing as mp
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import yaml

from bench._host_witness import WitnessRecord

ROOT = Path(__file__).resolve().parent.parent


def _spin(stop_at: float) -> None:
    x = 0
    while time.monotonic() < stop_at:
        x += 1


class CpuHogs:
    """`n` CPU-bound processes beside the cell, for as long as the context lasts."""

    def __init__(self, n: int = 2, max_s: float = 900.0) -> None:
        self.n, self.max_s = n, max_s
        self.procs: list[mp.Process] = []

    def __enter__(self) -> "CpuHogs":
        stop_at = time.monotonic() + self.max_s
        ctx = mp.get_context("spawn")
        self.procs = [ctx.Process(target=_spin, args=(stop_at,), daemon=True) for _ in range(self.n)]
        for p in self.procs:
            p.start()
        return self

    def __exit__(self, *exc: object) -> None:
        for p in self.procs:
            if p.pid is not None:
                p.kill()
        for p in self.procs:
            p.join(5)


def block_job(work: Path, height_mm: float = 8.0) -> Path:
    """Plan the 80 x 50 x `height_mm` block with 6 mm beads."""
    # lazy: only this benchmark's path needs it
    import trimesh

    stl = work / "block.stl"
    box = trimesh.creation.box(extents=(80.0, 50.0, height_mm))
    box.apply_translation((40.0, 25.0, height_mm / 2))
    box.export(stl)
    job = work / "block.job.json"
    r = subprocess.run([sys.executable, "-m", "controller.cli.main", "plan", str(stl), "--width", "6",
                        "--out", str(job)], cwd=ROOT, capture_output=True, text=True, timeout=300)
    if r.returncode != 0:
        raise RuntimeError(f"cell plan failed: {r.stderr}")
    return job


def cell_yaml(work: Path, opcua: bool = False) -> Path:
    """config/cell.yaml with free loopback ports (time scale as in the file: 60)."""
    # lazy: only this benchmark's path needs it
    import socket

    socks = [socket.socket() for _ in range(4)]
    for s in socks:
        s.bind(("127.0.0.1", 0))
    ports = [s.getsockname()[1] for s in socks]
    for s in socks:
        s.close()
    cfg = yaml.safe_load((ROOT / "config" / "cell.yaml").read_text())
    cfg["devices"]["robot"]["url"] = f"socket://127.0.0.1:{ports[0]}"
    cfg["devices"]["cnc"]["url"] = f"socket://127.0.0.1:{ports[1]}"
    cfg["devices"]["power_source"]["url"] = f"tcp://127.0.0.1:{ports[2]}"
    cfg["devices"]["cellio"]["url"] = f"tcp://127.0.0.1:{ports[3]}"
    if opcua:  # the factory interface on: does it cost the cycle anything? (issue 20)
        s = socket.socket()
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
        s.close()
        cfg["opcua"] = {"enabled": True, "endpoint": f"opc.tcp://127.0.0.1:{port}/cell"}
    path = work / "cell.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def sim_up(cfg_path: Path, log_dir: Path) -> subprocess.Popen:
    log_dir.mkdir(parents=True, exist_ok=True)
    # stderr to a file and stdout drained: a pipe nobody reads fills up and blocks the simulators
    err = (log_dir / "sim_up.stderr").open("w")
    proc = subprocess.Popen([sys.executable, "-m", "controller.cli.main", "sim", "up", "--cell-config", str(cfg_path),
                             "--log", str(log_dir)], cwd=ROOT, stdout=subprocess.PIPE, stderr=err, text=True)
    seen: set[str] = set()
    deadline = time.monotonic() + 90
    assert proc.stdout is not None
    while len(seen) < 4 and time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            raise RuntimeError(f"cell sim up exited: {(log_dir / 'sim_up.stderr').read_text()}")
        seen.add(json.loads(line)["device"])
    out = proc.stdout
    threading.Thread(target=lambda: [None for _ in out], daemon=True).start()
    return proc


def stop(proc: subprocess.Popen) -> None:
    # lazy: only this benchmark's path needs it
    import signal

    proc.send_signal(signal.SIGINT)
    try:
        proc.communicate(timeout=15)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.communicate()


SLOW_MS = 20.0   # the maximum reply time


class _LoopThread:
    """An asyncio loop on a thread of its own running `_run()` for as long as the context lasts;
    `_run()` ends when `_stop` is set."""

    def __init__(self) -> None:
        self._stop = threading.Event()
        self._thread = threading.Thread(target=lambda: asyncio.run(self._run()), daemon=True)

    def __enter__(self) -> "_LoopThread":
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(10)

    async def _run(self) -> None:
        raise NotImplementedError


class Prober(_LoopThread):
    """An independent Modbus client: reads the power source's and the cell I/O's status blocks
    every 10 ms on its own thread and keeps the reply times (ms)."""

    def __init__(self, urls: dict[str, str]) -> None:
        self.urls = urls
        self.times: dict[str, list[float]] = {k: [] for k in urls}
        self.errors: dict[str, int] = {k: 0 for k in urls}
        self.slow: list[tuple[str, float, float]] = []   # (device, monotonic start, ms) of replies > SLOW_MS
        super().__init__()

    async def _run(self) -> None:
        # lazy: only this benchmark's path needs it
        from pymodbus.client import AsyncModbusTcpClient

        # lazy: only this benchmark's path needs it
        from core.realtime import elevate

        # the measuring client must not be what is late: it gets the priority the cell gets
        elevate("false_trips prober")

        # lazy: only this benchmark's path needs it
        from wire.cellio_map import INPUTS
        from wire.power_registers import POWER_MAP
        from wire.urls import parse_tcp_url

        blocks = {"power_source": (POWER_MAP.status_start, POWER_MAP.status_count), "cellio": (0, len(INPUTS))}
        clients = {}
        for name, url in self.urls.items():
            host, port = parse_tcp_url(url)
            c = AsyncModbusTcpClient(host, port=port, timeout=1.0, retries=0)
            await c.connect()
            clients[name] = c
        try:
            while not self._stop.is_set():
                for name, c in clients.items():
                    addr, count = blocks[name]
                    t0 = time.perf_counter()
                    try:
                        if name == "cellio":   # the coupler's inputs are discrete inputs
                            rr = await c.read_discrete_inputs(addr, count=count, device_id=1)
                        else:
                            rr = await c.read_holding_registers(addr, count=count, device_id=1)
                        if rr.isError():
                            self.errors[name] += 1
                            continue
                    except Exception:
                        self.errors[name] += 1
                        continue
                    ms = (time.perf_counter() - t0) * 1000.0
                    self.times[name].append(ms)
                    if ms > SLOW_MS:
                        self.slow.append((name, time.monotonic() - ms / 1000.0, ms))
                await asyncio.sleep(0.01)
        finally:
            for c in clients.values():
                c.close()


class OpcClient(_LoopThread):
    """A factory client during the build: subscribes to the process values and the state at a
    20 ms publishing interval (as an MES dashboard would) and counts the notifications."""

    NODES = (("State",), ("Monitoring", "Process", "Current"), ("Monitoring", "Process", "Voltage"),
             ("Monitoring", "Process", "ArcOn"), ("JobManagement", "PassesDone"))

    def __init__(self, endpoint: str) -> None:
        self.endpoint = endpoint
        self.changes = 0
        self.connected = False
        super().__init__()

    def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
        self.changes += 1

    async def _run(self) -> None:
        # lazy: only this benchmark's path needs it
        import logging

        # lazy: only this benchmark's path needs it
        from asyncua import Client

        # the server goes away with `cell run` at the end of each build: the client's reconnect
        # chatter is not a finding
        logging.getLogger("asyncua").setLevel(logging.CRITICAL)
        while not self._stop.is_set():   # the server starts when `cell run` has connected
            client = Client(self.endpoint, timeout=2.0)
            try:
                await client.connect()
            except Exception:
                await asyncio.sleep(0.2)
                continue
            try:
                ns = await client.get_namespace_index("urn:cell-controller:machines")
                machines = await client.nodes.objects.get_child([f"{ns}:Machines"])
                machine = (await machines.get_children())[0]
                nodes = [await machine.get_child([f"{ns}:{p}" for p in path]) for path in self.NODES]
                sub = await client.create_subscription(20, self)
                await sub.subscribe_data_change(nodes)
                self.connected = True
                while not self._stop.is_set():
                    await asyncio.sleep(0.1)
            except Exception:
                await asyncio.sleep(0.2)   # the build ended and the server with it
            finally:
                try:
                    await client.disconnect()
                except Exception:
                    pass


def one_build(job: Path, work: Path, *, hog: bool, probe: Prober | None = None,
              timeout_s: float = 600.0, hogs: int = 2, opcua: bool = False) -> dict[str, Any]:
    """One build against a fresh `cell sim up`; the result, alarms and the source's watchdog drops."""
    work.mkdir(parents=True, exist_ok=True)
    cfg_path = cell_yaml(work, opcua)
    cfg = yaml.safe_load(cfg_path.read_text())
    logs = work / "logs"
    sim = sim_up(cfg_path, logs)
    hog_procs = CpuHogs(hogs) if hog else None
    prober = Prober({"power_source": cfg["devices"]["power_source"]["url"],
                     "cellio": cfg["devices"]["cellio"]["url"]}) if probe is None else probe
    client = OpcClient(cfg["opcua"]["endpoint"]) if opcua else None
    witness = WitnessRecord()
    t0 = time.monotonic()
    try:
        if hog_procs:
            hog_procs.__enter__()
        if client:
            client.__enter__()
        with witness, prober:
            r = subprocess.run([sys.executable, "-m", "controller.cli.main", "run", str(job), "--cell-config",
                                str(cfg_path), "--runs", str(work / "runs"), "--json"],
                               cwd=ROOT, capture_output=True, text=True, timeout=timeout_s)
    finally:
        stop(sim)  # first: a simulator left running (real-time priority) would load every later build
        if client:
            client.__exit__()
        if hog_procs:
            hog_procs.__exit__()
    out = json.loads(r.stdout) if r.stdout.strip() else {"state": "error", "alarms": [], "error": r.stderr[-500:]}
    return {"state": out.get("state"), "exit": r.returncode, "hog": hog, "wall_s": round(time.monotonic() - t0, 1),
            "links": _links(out),
            "alarms": [a.get("message") for a in out.get("alarms", [])][:3], "watchdog_drops": _watchdog_drops(out),
            "error": out.get("error"), "reply_ms": {k: list(v) for k, v in prober.times.items()},
            "probe_errors": dict(prober.errors), "slow_replies": _slow_replies(prober, witness),
            "defects": [str(d)[:200] for d in (out.get("defects") or [])][:5],
            "witness_max_gap_ms": witness.longest_ms(),
            "opcua_changes": client.changes if client else None}


def _watchdog_drops(out: dict[str, Any]) -> int:
    """The source latches error 50 when its watchdog drops the start; the controller reads it."""
    return sum(1 for a in out.get("alarms", []) if "error 50" in a.get("message", "")
               or "watchdog" in a.get("message", ""))


def _slow_replies(prober: Prober, witness: WitnessRecord) -> list[dict[str, Any]]:
    """Each reply over SLOW_MS: did a CPU stop running the guest meanwhile (the witness's gap)?"""
    return [{"device": d, "ms": round(ms, 1),
             "t": round(t, 3),
             "witness": [(cpu, round(g, 1)) for cpu, g in witness.overlapping(t, ms / 1000.0)]}
            for d, t, ms in prober.slow]


def _links(out: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """The controller's link statistics per device, from `cell run --json`."""
    return {x["device"]: {k: x.get(k) for k in ("late", "lost", "bad", "max_period_ms", "p99_period_ms")}
            for x in out.get("links", [])}


# A fault a stalled host explains: one CPU of this machine did not run for longer than the limit
# that tripped (the power source's 100 ms watchdog, the 50 ms link budget of config/cell.yaml).
# The device did what a real one would; no software on the machine could have prevented it.
WATCHDOG_MS, LINK_BUDGET_MS = 100.0, 50.0


def host_explained(r: dict[str, Any]) -> bool:
    """Whether a build that did not complete is explained by a witnessed CPU stall (see above)."""
    if r["state"] == "complete":
        return False
    longest = max(r["witness_max_gap_ms"].values(), default=0.0)
    limit = WATCHDOG_MS if r["watchdog_drops"] else LINK_BUDGET_MS
    return longest >= limit


def pct(xs: list[float], q: float) -> float:
    if not xs:
        return float("nan")
    xs = sorted(xs)
    return xs[min(len(xs) - 1, int(round(q / 100 * (len(xs) - 1))))]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--builds", type=int, default=100)
    ap.add_argument("--height", type=float, default=8.0, help="block height, mm (default 8)")
    ap.add_argument("--json", metavar="FILE")
    ap.add_argument("--work", metavar="DIR", help="keep every build's config and logs here (default: a temporary directory)")
    ap.add_argument("--opcua", action="store_true", help="serve OPC UA during the builds (its cost on the cycle)")
    a = ap.parse_args(argv)
    results = run_builds(a.builds, a.height, a.work, a.opcua)
    summary = summarise(results, a.opcua)
    print(json.dumps(summary, indent=1))
    if a.json:
        Path(a.json).write_text(json.dumps({"summary": summary, "builds": [
            {k: v for k, v in r.items() if k != "reply_ms"} for r in results]}, indent=1))
    return 0 if not summary["false_trips"] else 1


def run_builds(builds: int, height: float, work_dir: str | None, opcua: bool) -> list[dict[str, Any]]:
    """`builds` builds of the block, every other one with the CPU hogs."""
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(work_dir or tmp)
        work.mkdir(parents=True, exist_ok=True)
        job = block_job(work, height)
        for i in range(builds):
            res = one_build(job, work / f"b{i}", hog=bool(i % 2), opcua=opcua)
            results.append(res)
            print(f"build {i + 1}/{builds} hog={res['hog']}: {res['state']} in {res['wall_s']} s"
                  f"{' ' + str(res['alarms'][:1]) if res['state'] != 'complete' else ''}", flush=True)
    return results


def summarise(results: list[dict[str, Any]], opcua: bool) -> dict[str, Any]:
    """The figures of a run of builds: outcomes, link statistics, reply times, slow replies."""
    summary = _outcomes(results)
    for dev in ("power_source", "cellio", "robot"):
        summary[f"{dev}_controller_side"] = _link_summary([r["links"].get(dev, {}) for r in results])
    summary.update(_replies(results))
    summary["slow_replies"] = _slow_summary(results)
    summary["opcua"] = opcua
    if opcua:   # the client saw the build: data changes it was notified of, per build
        summary["opcua_changes_per_build"] = sorted(r["opcua_changes"] or 0 for r in results)
    return summary


def _outcomes(results: list[dict[str, Any]]) -> dict[str, Any]:
    """How the builds ended: complete, false trips, trips a host stall explains."""
    faults = [r for r in results if r["state"] != "complete"]
    false_trips = [r for r in faults if not host_explained(r)]
    return {"builds": len(results), "with_hogs": sum(r["hog"] for r in results),
            "complete": len(results) - len(faults),
            "false_trips": len(false_trips),
            "host_stall_trips": len(faults) - len(false_trips),
            "watchdog_drops": sum(r["watchdog_drops"] for r in results),
            "faults": [(r["hog"], r["alarms"][:1], r["witness_max_gap_ms"]) for r in faults]}


def _replies(results: list[dict[str, Any]]) -> dict[str, Any]:
    """Reply times of the power source and the cell I/O: over all builds, with and without hogs."""
    out: dict[str, Any] = {}
    for dev in ("power_source", "cellio"):
        for label, sel in (("all", results), ("hog", [r for r in results if r["hog"]]),
                           ("idle", [r for r in results if not r["hog"]])):
            out[f"{dev}_reply_ms_{label}"] = _reply_summary([x for r in sel for x in r["reply_ms"][dev]])
    return out


def _link_summary(ls: list[dict[str, Any]]) -> dict[str, Any]:
    """One device's controller-side link statistics over the builds."""
    return {
        "late": sum(x.get("late") or 0 for x in ls), "lost": sum(x.get("lost") or 0 for x in ls),
        "bad": sum(x.get("bad") or 0 for x in ls),
        "max_period_ms": max((x.get("max_period_ms") or 0 for x in ls), default=None),
        # the controller's cycle period: median over the builds of each build's p99
        "p99_period_ms_median": pct([x["p99_period_ms"] for x in ls if x.get("p99_period_ms")], 50)}


def _reply_summary(xs: list[float]) -> dict[str, Any]:
    return {"n": len(xs), "p50": round(pct(xs, 50), 2), "p99": round(pct(xs, 99), 2),
            "max": round(max(xs), 2) if xs else None}


def _slow_summary(results: list[dict[str, Any]]) -> dict[str, Any]:
    """Replies over SLOW_MS, told apart by the host witness: a CPU stalled meanwhile (the machine),
    or both CPUs ran the witness on time (the cell's own software)."""
    slow = [x for r in results for x in r["slow_replies"]]
    return {
        "n": len(slow), "with_cpu_stalled": sum(1 for x in slow if x["witness"]),
        "cpus_ran": sorted((x["device"], x["ms"]) for x in slow if not x["witness"])[-10:],
        "longest_witness_gap_ms": max((g for r in results for g in r["witness_max_gap_ms"].values()), default=0.0)}


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    sys.exit(main())
