"""Robot link (RLP/1) benchmark: throughput, noisy-link integrity, hold latency, link loss, replug.

    .venv/bin/python -m bench.link            # full figures (a few minutes)
    .venv/bin/python -m bench.link --quick    # shorter layers and fewer trials
    .venv/bin/python -m bench.link --soak [--frames 1000000] [--baud 1000000]

Everything runs against sims/robot_sim.py over loopback TCP through the fault channel, with
the 8N1 throttle at the given baud (115200: 11,520 bytes/s). Throughput is the bytes of unique
move frames the robot accepted per second, first send to last ACK. Integrity is checked
against the simulator's execution log: the executed sequence equals the plan (nothing lost,
repeated or reordered).
"""
from __future__ import annotations

import argparse
import asyncio
import json
import statistics
import tempfile
import time
from pathlib import Path

from wire import rlp
from drivers.errors import LinkLost
from drivers.robot import RobotLink
from sims.clock import SimClock
from sims.faults import bytes_per_second, parse_fault_spec
from sims.robot_sim import RobotSim
from sims.transport import SerialServer

NOISY = "seed=1,corrupt=0.01,drop=0.001"            # "1e-2": 1 % of bytes corrupted, 0.1 % dropped
NOISY_1E3 = "seed=1,corrupt=0.001,drop=0.0001"      # "1e-3": the same mix, ten times rarer
NOISY_BURST = "seed=1,corrupt=0.01,drop=0.001,burst=32"
SPEED = 1500.0  # mm/min


class Rig:
    """A robot simulator behind the fault channel and a RobotLink connected to it."""

    def __init__(self, spec: str = "", *, time_scale: float = 1000.0, baud: int = 115200,
                 max_inflight: int | None = None, log_path: Path | None = None, record: bool = True,
                 protocol: int = 2) -> None:
        self.sim = RobotSim(clock=SimClock(time_scale), log_path=log_path, record=record)
        self.server = SerialServer(self.sim, name="robot", spec=parse_fault_spec(spec), baud=baud)
        self.baud, self.max_inflight, self.protocol = baud, max_inflight, protocol

    async def __aenter__(self) -> "Rig":
        self.sim.start()
        url = await self.server.start(None, ephemeral=True)
        self.link = RobotLink(url, baud=self.baud or 115200, pace=bool(self.baud), max_inflight=self.max_inflight,
                              max_protocol=self.protocol)
        await self.link.connect()
        return self

    async def __aexit__(self, *exc) -> None:
        await self.link.close()
        await self.server.close()
        await self.sim.close()


def layer(n: int) -> list[tuple]:
    """n moves of 1 mm: a zigzag of 1 mm steps along x, 1 mm rows in y."""
    out = []
    for i in range(n):
        row, col = divmod(i, 100)
        x = float(col + 1 if row % 2 == 0 else 99 - col)
        out.append(("MOVL", x, float(row % 200), 5.0, 0, 0, 1, SPEED))
    return out


def frame_bytes(moves: list[tuple]) -> int:
    return sum(len(rlp.encode_move(i + 1, *m)) for i, m in enumerate(moves))


async def stream(rig: Rig, moves: list[tuple]) -> dict:
    link = rig.link
    t0 = time.monotonic()
    last = 0
    for m in moves:
        last = await link.send_move(*m)
    await link.wait_acked(last, timeout=3600)
    t_ack = time.monotonic()
    await link.wait_executed(last, timeout=3600)
    nbytes = frame_bytes(moves)
    first = last - len(moves) + 1
    ok = rig.sim.executed == [t & 0xFFFF for t in range(first, last + 1)]
    return {"moves": len(moves), "seconds": round(t_ack - t0, 3), "bytes_per_s": round(nbytes / (t_ack - t0), 1),
            "line_fraction": round(nbytes / (t_ack - t0) / bytes_per_second(rig.baud), 4),
            "exactly_once_in_order": ok, "underruns_before_end": rig.sim.underruns - 1,
            "frames_sent": link.stats.frames_sent, "resends": link.stats.resends, "naks": link.stats.naks,
            "robot_crc_errors": rig.sim.crc_errors, "host_crc_errors": link.stats.crc_errors,
            "timeouts": link.stats.timeouts, "rtt_ms_mean": round(link.stats.rtt_ms_mean, 2),
            "rtt_ms_p99": round(link.stats.rtt_ms_p99, 2), "protocol": link.protocol,
            "robot_duplicates": rig.sim.duplicates, "sacks": link.stats.sacks, "rto_ms_end": round(1000 * link.rto_s, 1)}


async def throughput(n: int) -> dict:
    moves = layer(n)
    frame_s = frame_bytes(moves) / n / bytes_per_second(115200)
    # robot speed such that it consumes 90 % of the line: the link must keep its queue fed
    matched_scale = (60.0 / SPEED) / (frame_s / 0.90)
    out = {"frame_bytes_mean": round(frame_bytes(moves) / n, 2)}
    async with Rig(time_scale=1000.0) as rig:
        out["clean_link_limited"] = await stream(rig, moves)
    async with Rig(time_scale=matched_scale) as rig:
        out["clean_robot_at_90pct"] = await stream(rig, moves)
        out["clean_robot_at_90pct"]["time_scale"] = round(matched_scale, 3)
    async with Rig(time_scale=matched_scale, max_inflight=1) as rig:
        out["send_and_wait_robot_at_90pct"] = await stream(rig, moves)
    async with Rig(time_scale=1000.0, max_inflight=1) as rig:
        out["send_and_wait_link_limited"] = await stream(rig, moves)
    return out


NOISY_CASES = (("1e-3", NOISY_1E3, 2), ("1e-2", NOISY, 2), ("1e-2_burst32", NOISY_BURST, 2),
               ("1e-3_rlp1", NOISY_1E3, 1), ("1e-2_rlp1", NOISY, 1))


async def noisy(n: int, clean_bps: float, cases: tuple[tuple[str, str, int], ...] = NOISY_CASES) -> dict:
    """Each case: (name, fault spec, the protocol the host asks for: 2 selective repeat, 1 go-back-N)."""
    out = {}
    for name, spec, proto in cases:
        with tempfile.TemporaryDirectory() as d:
            log = Path(d) / "robot.jsonl"
            moves = layer(n)
            async with Rig(spec, time_scale=1000.0, log_path=log, protocol=proto) as rig:
                r = await stream(rig, moves)
            entries = [json.loads(x) for x in log.read_text().splitlines()]
            r["log_equals_plan"] = ([(e["seq"], tuple(e["target"])) for e in entries]
                                    == [((i + 1) & 0xFFFF, m[1:4]) for i, m in enumerate(moves)])
            r["spec"] = spec
            r["fraction_of_clean"] = round(r["bytes_per_s"] / clean_bps, 4)
            out[name] = r
    return out


async def hold_latency(trials: int) -> dict:
    lat, queued = [], []
    async with Rig(time_scale=1.0) as rig:  # real time: simulated ms = wall ms
        link = rig.link
        for _ in range(trials):
            while link.next_ticket - 1 - link.last_exec_ticket < 64:
                await link.send_move("MOVL", float(link.next_ticket % 100), 0, 0, 0, 0, 1, 60)
            await link.drain(timeout=30)
            await asyncio.sleep(0.05)
            queued.append(len(rig.sim.queue))
            t0 = time.monotonic()
            st = await link.hold()
            lat.append(time.monotonic() - t0)
            assert st.state == "HOLD"
            await link.go()
            await asyncio.sleep(0.05)
        await link.abort()
    lat_ms = sorted(1000 * x for x in lat)
    return {"trials": trials, "queue_len_min": min(queued), "queue_slots": 64, "hold_ack_ms_mean": round(statistics.mean(lat_ms), 2),
            "hold_ack_ms_max": round(lat_ms[-1], 2), "time_scale": 1.0}


async def link_loss(trials: int) -> dict:
    det = []
    async with Rig(time_scale=1.0) as rig:
        rig.link.auto_reconnect = False
        for _ in range(trials):
            if not rig.link.connected:
                await rig.link.connect()
            t = await rig.link.send_move("MOVL", 10, 0, 0, 0, 0, 1, 60)
            rig.server.stall(4.0)
            t0 = time.monotonic()
            try:
                await rig.link.wait_executed(t, timeout=30)
            except LinkLost:
                det.append(time.monotonic() - t0)
            await asyncio.sleep(4.2 - (time.monotonic() - t0))
    return {"trials": trials, "detected": len(det), "detect_s_mean": round(statistics.mean(det), 3),
            "detect_s_max": round(max(det), 3), "link_timeout_s": 3.0}


async def replug(trials: int) -> dict:
    moves = layer(200 * trials)
    resumed_ok = 0
    checks = []
    async with Rig(time_scale=200.0) as rig:
        link = rig.link
        lost = asyncio.Event()
        restored: list = []
        link.on_event(lambda e: lost.set() if e.kind == "link_lost" else
                      (restored.append((e.value, rig.sim.last_rx, rig.sim.last_exec)) if e.kind == "link_restored" else None))
        sent = 0
        for k in range(trials):
            while sent < 200 * (k + 1) - 100:
                try:
                    await link.send_move(*moves[sent])
                    sent += 1
                except LinkLost:
                    await link.wait_connected(timeout=30)
            lost.clear()
            rig.server.unplug()
            await asyncio.wait_for(lost.wait(), 10)
            await link.wait_connected(timeout=30)
            st, _, _ = restored[-1]
            # the driver's numbering resumes from what the robot reports it received / executed
            ok = (link.last_ack_ticket == st.last_rx_ticket and st.last_rx_ticket & 0xFFFF == st.last_rx
                  and st.last_exec_ticket & 0xFFFF == st.last_exec and link.last_exec_ticket >= st.last_exec_ticket)
            checks.append(ok)
            resumed_ok += ok
            if (await link.status()).state == "HOLD":
                await link.go()
            while sent < 200 * (k + 1):
                await link.send_move(*moves[sent])
                sent += 1
        await link.wait_executed(sent, timeout=60)
        exact = rig.sim.executed == [(i + 1) & 0xFFFF for i in range(sent)]
    return {"trials": trials, "resumed_from_robot_seq": resumed_ok, "moves": sent, "exactly_once_in_order": exact,
            "reconnects": link.stats.reconnects}


async def soak(frames: int, baud: int, spec: str) -> dict:
    with tempfile.TemporaryDirectory() as d:
        log = Path(d) / "robot.jsonl"
        async with Rig(spec, time_scale=1000.0, baud=baud, log_path=log) as rig:
            link = rig.link
            t0 = time.monotonic()
            n = 0
            last = 0
            report = t0
            while link.stats.frames_sent < frames:
                last = await link.send_move("MOVL", float(n % 100), float((n // 100) % 100), 5.0, 0, 0, 1, SPEED)
                n += 1
                if time.monotonic() - report > 60:
                    report = time.monotonic()
                    print(f"  soak: {link.stats.frames_sent} frames, {n} moves, {report - t0:.0f} s", flush=True)
            await link.wait_executed(last, timeout=600)
            dt = time.monotonic() - t0
            stats = link.stats.as_dict()
            exact = rig.sim.executed == [(i + 1) & 0xFFFF for i in range(n)]
            sim_counts = {"robot_crc_errors": rig.sim.crc_errors, "robot_syntax_errors": rig.sim.syntax_errors,
                          "robot_duplicates": rig.sim.duplicates}
        lines = 0
        ok_log = True
        with open(log) as fh:
            for i, line in enumerate(fh):
                e = json.loads(line)
                ok_log &= e["seq"] == (i + 1) & 0xFFFF and e["target"][0] == float(i % 100)
                lines += 1
        ok_log &= lines == n
    return {"spec": spec, "baud": baud, "frames_sent": stats["frames_sent"], "moves": n, "seconds": round(dt, 1),
            "exactly_once_in_order": exact, "log_equals_plan": ok_log, "resends": stats["resends"],
            "naks": stats["naks"], "timeouts": stats["timeouts"], **sim_counts}


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="bench.link", description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="shorter layers, fewer trials")
    ap.add_argument("--soak", action="store_true", help="only the long integrity soak")
    ap.add_argument("--frames", type=int, default=1_000_000, help="soak length in frames sent")
    ap.add_argument("--baud", type=int, default=1_000_000, help="soak line rate (0: unthrottled)")
    ap.add_argument("--spec", default=NOISY, help="soak fault spec")
    ap.add_argument("--noisy-only", action="store_true", help="the clean link-limited run and the noisy cases only")
    args = ap.parse_args(argv)

    async def run() -> dict:
        if args.soak:
            return {"soak": await soak(args.frames, args.baud, args.spec)}
        n = 2000 if args.quick else 10_000
        res: dict = {"layer_moves": n}
        if args.noisy_only:
            async with Rig(time_scale=1000.0) as rig:
                clean = await stream(rig, layer(n))
            res["clean_link_limited"] = clean
            res["noisy"] = await noisy(n, clean["bytes_per_s"])
            return res
        res["throughput"] = await throughput(n)
        print(json.dumps({"throughput": res["throughput"]}), flush=True)
        clean = res["throughput"]["clean_link_limited"]["bytes_per_s"]
        res["noisy"] = await noisy(n // 2 if args.quick else n, clean)
        print(json.dumps({"noisy": res["noisy"]}), flush=True)
        res["hold"] = await hold_latency(5 if args.quick else 20)
        res["link_loss"] = await link_loss(1 if args.quick else 3)
        res["replug"] = await replug(5 if args.quick else 20)
        return res

    res = asyncio.run(run())
    print(json.dumps(res, indent=1))
    for k, v in res.get("noisy", {}).items():
        print(f"noisy {k} (RLP/{v['protocol']}): {v['fraction_of_clean']:.1%} of clean, resends {v['resends']}, "
              f"exactly once: {v['exactly_once_in_order']}, log = plan: {v['log_equals_plan']}")
    t = res.get("throughput")
    if t:
        print(f"clean link, link-limited: {t['clean_link_limited']['line_fraction']:.1%} of 11,520 B/s; "
              f"robot at 90 %: {t['clean_robot_at_90pct']['line_fraction']:.1%}, underruns "
              f"{t['clean_robot_at_90pct']['underruns_before_end']}; send-and-wait: "
              f"{t['send_and_wait_link_limited']['line_fraction']:.1%} (link-limited), "
              f"{t['send_and_wait_robot_at_90pct']['line_fraction']:.1%} (robot at 90 %)")
        print(f"hold ack: mean {res['hold']['hold_ack_ms_mean']} ms, max {res['hold']['hold_ack_ms_max']} ms; "
              f"link loss detected in {res['link_loss']['detect_s_max']} s (max); replug "
              f"{res['replug']['resumed_from_robot_seq']}/{res['replug']['trials']} resumed, exactly once: "
              f"{res['replug']['exactly_once_in_order']}")
    return 0


if __name__ == "__main__":
    import sys

    raise SystemExit(main(sys.argv[1:]))
