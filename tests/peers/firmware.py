"""Real CNC firmware as test peers: build grbl 1.1h (grbl-sim) and grblHAL's Simulator once into a
cache outside the repo and serve them on a pty through socat.

Sources come from /work/shared/peers (override: CELL_PEERS_DIR); they are copied into the cache
and patched there at build time (grbl: the kit's build.sh and patches), never into the repo.
Cache: ~/.cache/cell-peers (override: CELL_PEERS_CACHE); a build is redone only when its stamp
(the kit's commit files, patches and build options) changes.

    python -m tests.peers.firmware build          # builds both, prints the binaries and times
    python -m tests.peers.firmware serve grbl PTY # serves one on PTY until Ctrl-C
"""
from __future__ import annotations

import contextlib
import fcntl
import hashlib
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

PEERS = Path(os.environ.get("CELL_PEERS_DIR", "/work/shared/peers"))
CACHE = Path(os.environ.get("CELL_PEERS_CACHE", Path.home() / ".cache" / "cell-peers"))
GRBLHAL_AXES = 5
TOOLS = ("gcc", "make", "socat")
INSTALL_HINT = "apt-get install -y socat gcc make cmake"


class PeerUnavailable(RuntimeError):
    """The firmware cannot be built or served here (missing tool or sources)."""


def missing_tools(kind: str) -> list[str]:
    """Host tools needed for `kind` ('grbl' or 'grblhal') that are not on PATH."""
    need = TOOLS + (("cmake",) if kind == "grblhal" else ())
    return [t for t in need if shutil.which(t) is None]


def _stamp(paths: list[Path], extra: str) -> str:
    h = hashlib.sha256(extra.encode())
    for p in sorted(paths):
        h.update(p.name.encode())
        h.update(p.read_bytes())
    return h.hexdigest()[:16]


def _check(kind: str, src: Path) -> None:
    miss = missing_tools(kind)
    if miss:
        raise PeerUnavailable(f"{kind} firmware tests need {', '.join(miss)}: {INSTALL_HINT}")
    if not src.exists():
        raise PeerUnavailable(f"{kind} firmware sources not found at {src} (set CELL_PEERS_DIR)")


def build_grbl() -> Path:
    """grbl 1.1h + grbl-sim built by the kit's build.sh (patches applied in the cache copy)."""
    kit = PEERS / "grbl"
    _check("grbl", kit / "build.sh")
    out = CACHE / "grbl"
    stamp = _stamp([kit / "GRBL_COMMIT", kit / "GRBL_SIM_COMMIT", *(kit / "patches").glob("*.patch")], "v1")
    exe = out / "grbl_sim.exe"
    if exe.exists() and (out / "STAMP").exists() and (out / "STAMP").read_text() == stamp:
        return exe
    out.mkdir(parents=True, exist_ok=True)
    log = out / "build.log"
    with log.open("w") as f:
        r = subprocess.run(["bash", str(kit / "build.sh"), str(out)], stdout=f, stderr=subprocess.STDOUT)
    if r.returncode or not exe.exists():
        raise PeerUnavailable(f"grbl build failed (exit {r.returncode}); see {log}")
    (out / "STAMP").write_text(stamp)
    return exe


def build_grblhal(axes: int = GRBLHAL_AXES) -> Path:
    """grblHAL core + Simulator built with cmake, N_AXIS=`axes`, in the cache."""
    kit = PEERS / "grblhal"
    _check("grblhal", kit / "Simulator" / "CMakeLists.txt")
    out = CACHE / f"grblhal-{axes}ax"
    stamp = _stamp([kit / "CORE_COMMIT", kit / "SIMULATOR_COMMIT"], f"v1 N_AXIS={axes}")
    exe = out / "build" / "grblHAL_sim"
    if exe.exists() and (out / "STAMP").exists() and (out / "STAMP").read_text() == stamp:
        return exe
    shutil.rmtree(out, ignore_errors=True)
    src = out / "src"
    shutil.copytree(kit / "Simulator", src)
    shutil.rmtree(src / "src" / "grbl", ignore_errors=True)
    shutil.copytree(kit / "core", src / "src" / "grbl")     # the simulator expects core at src/grbl
    for p in src.rglob("*"):
        p.chmod(p.stat().st_mode | 0o200)
    (out / "build").mkdir()
    log = out / "build.log"
    with log.open("w") as f:
        for cmd in (["cmake", str(src), "-DCMAKE_BUILD_TYPE=Release", f"-DCMAKE_C_FLAGS=-DN_AXIS={axes}"],
                    ["make", f"-j{os.cpu_count() or 2}", "grblHAL_sim"]):
            r = subprocess.run(cmd, cwd=out / "build", stdout=f, stderr=subprocess.STDOUT)
            if r.returncode:
                raise PeerUnavailable(f"grblHAL build failed ({cmd[0]} exit {r.returncode}); see {log}")
    (out / "STAMP").write_text(stamp)
    return exe


def build(kind: str) -> Path:
    """Build (or take from the cache) the firmware `kind`: 'grbl' or 'grblhal'. One build at a time per
    kind across processes (test workers on a fresh machine all ask for it at once): the others wait
    for it and take it from the cache."""
    CACHE.mkdir(parents=True, exist_ok=True)
    with open(CACHE / f"{kind}.lock", "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        return build_grbl() if kind == "grbl" else build_grblhal()


def _children(pid: int) -> list[int]:
    """The direct children of a process (Linux /proc)."""
    try:
        return [int(x) for x in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except (OSError, ValueError):
        return []


# A fast machine: the simulators' defaults are 500 mm/min (or °/min) and 10 mm/s² on every axis, so
# a few rotary moves take seconds each in real time. A dialect check (every line answered ok, in
# order) does not depend on them; a real machine has settings of its own.
def fast_machine(axes: int) -> list[str]:
    """Max rates ($110…) and accelerations ($120…) of a fast machine, for each of `axes` axes."""
    return [f"${base + axis}={value}" for base, value in ((110, 20000), (120, 2000)) for axis in range(axes)]


async def stream_program(kind: str, lines: list[str], *, attempts: int = 2, link_timeout_s: float = 30.0,
                         stuck_after_s: float = 10.0, fast: bool = False) -> tuple[Any, int]:
    """Stream `lines` to a fresh firmware `kind` (unlocked if it powers up in Alarm); returns the
    StreamResult and the axis count the firmware reported. `fast`: the machine is set
    up as a fast one first (`fast_machine`, each setting answered ok). A firmware simulator that stops
    reading its input (GrblStuck: a hang of the simulator under CPU contention, not a verdict on
    the G-code) is started afresh, up to `attempts` times; anything else is raised."""
    from drivers.grbl import CncLink, GrblStuck

    for attempt in range(1, attempts + 1):
        with serve(kind) as pty:
            link = CncLink(pty, connect_timeout_s=link_timeout_s, link_timeout_s=link_timeout_s,
                           stuck_after_s=stuck_after_s)
            await link.connect()
            try:
                st = await link.status()
                if st.state.startswith("Alarm"):
                    await link.unlock()
                for setting in fast_machine(link.axes or 3) if fast else []:
                    await link.command(setting)
                return await link.stream(lines), link.axes   # GrblError names the first refused line
            except GrblStuck:
                if attempt == attempts:
                    raise
            finally:
                await link.close()
    raise AssertionError("unreachable")


@contextlib.contextmanager
def _a_core_of_its_own() -> Iterator[int]:
    """A CPU no other firmware peer of this test session runs on (an exclusive lock per CPU, shared by
    the test workers): a free one if there is one, else this worker's own, once it is free."""
    cpus = sorted(os.sched_getaffinity(0))
    locks = Path(os.environ.get("CELL_TEST_LOCKS", tempfile.gettempdir()))
    worker = int(os.environ.get("PYTEST_XDIST_WORKER", "gw0").lstrip("gw") or 0)
    order = cpus[worker % len(cpus):] + cpus[:worker % len(cpus)]
    with contextlib.ExitStack() as files:
        held = [files.enter_context(open(locks / f"firmware-cpu{cpu}", "a")) for cpu in order]
        for cpu, f in zip(order, held):
            try:
                fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                continue
            yield cpu
            return
        fcntl.flock(held[0], fcntl.LOCK_EX)
        yield order[0]


@contextlib.contextmanager
def serve(kind: str, env: dict[str, str] | None = None) -> Iterator[str]:
    """Serve firmware `kind` on a fresh pty (socat); yields the pty path as soon as it exists, stops
    the firmware by PID after. No fixed wait for the firmware to come up: grbl-sim reads nothing in
    its first simulated second, and the link's `connect()` sends `?` until a status report or the
    banner comes back (drivers/grbl/link.py), as with a board still booting (a contract test's set-up:
    1.45 s, against 1.65 s with the fixed 1.2 s wait it replaced)."""
    exe = build(kind)
    run = Path(tempfile.mkdtemp(prefix=f"cell-{kind}-"))
    pty = run / "tty"
    cmd = f"{exe} -n -b /dev/null -s /dev/null"
    with contextlib.ExitStack() as core:   # the core is free once its firmware is gone
        if shutil.which("taskset"):
            # grbl-sim shares its serial ring between two threads: one core keeps it stable (README).
            # So does grblHAL's Simulator (its SysTick and serial run on a thread of their own): on
            # two cores it was seen to hang now and then, reporting Idle but reading no more input.
            # Both spin a whole core even when idle, so two on one core starve: each takes a core of
            # its own across the test workers (there are more workers than cores)
            cmd = f"taskset -c {core.enter_context(_a_core_of_its_own())} {cmd}"
        penv = {**os.environ, "GRBLSIM_PINS": "1", **(env or {})}
        log = (run / "socat.log").open("w")
        proc = subprocess.Popen(["socat", f"PTY,link={pty},raw,echo=0", f"EXEC:{cmd},pty,raw,echo=0"],
                                cwd=run, env=penv, stdin=subprocess.DEVNULL, stdout=log, stderr=log,
                                start_new_session=True)
        try:
            deadline = time.monotonic() + 5
            while not pty.exists():
                if proc.poll() is not None or time.monotonic() > deadline:
                    raise PeerUnavailable(f"socat did not make {pty}; see {run / 'socat.log'}")
                time.sleep(0.02)
            yield str(pty)
        finally:
            # socat's EXEC with `pty` makes the firmware a session leader of its own, outside socat's
            # group: note it before socat goes, and end it by PID (else it spins on, orphaned)
            firmware_pids = _children(proc.pid)
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGTERM)
            for pid in firmware_pids:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)
            try:
                proc.wait(3)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
            log.close()
            shutil.rmtree(run, ignore_errors=True)


def main(argv: list[str]) -> int:
    """CLI: `build` or `serve KIND PTY`."""
    if argv[:1] == ["build"]:
        for kind in ("grbl", "grblhal"):
            t0 = time.monotonic()
            try:
                exe = build(kind)
            except PeerUnavailable as e:
                print(f"error: {e}", file=sys.stderr)
                return 2
            print(f"{kind}: {exe} ({time.monotonic() - t0:.1f} s)")
        return 0
    if argv[:1] == ["serve"] and len(argv) == 3:
        with serve(argv[1]) as pty:
            os.symlink(pty, argv[2])
            print(f"serving {argv[1]} on {argv[2]}; Ctrl-C stops", flush=True)
            try:
                signal.pause()
            except KeyboardInterrupt:
                pass
            finally:
                os.unlink(argv[2])
        return 0
    print("usage: python -m tests.peers.firmware build | serve grbl|grblhal PTY", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
