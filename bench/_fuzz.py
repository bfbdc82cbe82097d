"""Corrupted inputs for every subcommand of `cell` (issue 14): the seeds, the mutations and the
contract check, shared by tests/cli/test_fuzz_cli.py (hypothesis) and bench/fuzz_cli.py (long run)."""
from __future__ import annotations

import contextlib
import io
import json
import random
import shutil
import sqlite3
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

# a cell whose speed limit no job meets: `run`/`resume` of any fuzzed job that parses stop at
# the job check (exit 2) before any device is touched
TIGHT_CELL = (ROOT / "config" / "cell.yaml").read_text(encoding="utf-8").replace(
    "max_speed_mm_min: 6000", "max_speed_mm_min: 1")


def _job() -> dict:
    pts = [[0, 0, 1], [20, 0, 1], [20, 20, 1], [0, 20, 1], [0, 0.5, 1]]
    return {"schema": "cell-job/1", "source": {"file": "square.stl", "sha256": "0" * 64, "units": "mm"},
            "material": {"name": "inconel718-1.0mm"},
            "bead": {"width_mm": 5, "height_mm": 1, "step_over_mm": 3.69, "model": "tangent"},
            "layers": [{"index": 0, "z_mm": 1, "height_mm": 1, "interpass": {"max_temperature_c": 200, "dwell_s": 0},
                        "passes": [{"role": "perimeter", "width_mm": 5, "current_a": 120, "speed_mm_min": 600,
                                    "wfs_m_min": 5.5, "points": pts}]}], "summary": {}}


def _stl_ascii() -> bytes:
    # lazy: only this benchmark's path needs it
    import trimesh

    m = trimesh.creation.box(extents=(20, 20, 6))
    m.apply_translation((0, 0, 3))
    return m.export(file_type="stl_ascii").encode()


def _mesh(kind: str) -> bytes:
    # lazy: only this benchmark's path needs it
    import trimesh

    m = trimesh.creation.box(extents=(20, 20, 6))
    m.apply_translation((0, 0, 3))
    return m.export(file_type=kind) if kind != "obj" else m.export(file_type="obj").encode()


def seeds(tmp: Path) -> dict[str, bytes]:
    """One valid file of each kind the CLI reads."""
    # lazy: only this benchmark's path needs it
    from controller.job.identity import canonical_json, job_hash

    job = _job()
    j = tmp / "seed-journal.sqlite"
    db = sqlite3.connect(j)
    db.executescript(__import__("controller.journal.store", fromlist=["SCHEMA"]).SCHEMA)
    db.execute("INSERT INTO job (hash, name, platform, created, job_json) VALUES (?,?,?,?,?)",
               (job_hash(job), "square", "robot", 0.0, canonical_json(job)))
    db.execute("INSERT INTO passes (layer, pass, state, run, t) VALUES (0, 0, 'started', 1, 0)")
    db.commit()
    db.close()
    return {
        "stl": _mesh("stl"), "stl_ascii": _stl_ascii(), "obj": _mesh("obj"), "3mf": _mesh("3mf"),
        "cell_yaml": (ROOT / "config" / "cell.yaml").read_bytes(),
        "material_yaml": (ROOT / "config" / "materials" / "inconel718-1.0mm.yaml").read_bytes(),
        "job": json.dumps(job).encode(),
        "process_csv": b"current_a,speed_mm_min,width_mm,height_mm\n100,300,6.1,0.9\n130,300,7.2,1.0\n"
                       b"160,300,8.0,1.1\n100,500,5.2,0.7\n130,500,6.0,0.8\n160,500,6.9,0.85\n",
        "profile_csv": b"x_mm,y_mm\n" + b"".join(f"{x / 4:.3f},{max(0.0, 2 - (x / 4) ** 2 * 0.3):.4f}\n".encode()
                                                 for x in range(-14, 15)),
        "plane_csv": b"x,y,z\n0,0,0\n10,0,0.01\n0,10,0\n10,10,0.02\n5,5,0.01\n",
        "journal": j.read_bytes(),
    }


def mutate(data: bytes, rng: random.Random) -> bytes:
    """One to four corruptions: flip, insert, delete, duplicate, truncate, splice odd values."""
    b = bytearray(data)
    for _ in range(rng.randint(1, 4)):
        op = rng.randrange(8)
        n = len(b)
        if op == 0 and n:
            for _ in range(rng.randint(1, 8)):
                b[rng.randrange(n)] = rng.randrange(256)
        elif op == 1:
            b[rng.randint(0, n):rng.randint(0, n)] = bytes(rng.randrange(256) for _ in range(rng.randint(1, 64)))
        elif op == 2 and n:
            i = rng.randrange(n)
            del b[i:i + rng.randint(1, 256)]
        elif op == 3 and n:
            i = rng.randrange(n)
            b[i:i] = b[i:i + rng.randint(1, 512)] * rng.randint(1, 4)
        elif op == 4:
            del b[rng.randint(0, n):]
        elif op == 5:
            tok = rng.choice([b"nan", b"inf", b"-1e309", b"1e30", b"1e160", b"-0", b"99999", b"\xff\xfe", b"[[[[",
                              b"{{", b"!!python/object:os.system", b"&a [*a,*a]", b"\x00", b"tcp://[::1", b"\n\n"])
            i = rng.randint(0, n)
            b[i:i] = tok
        elif op == 6 and n:
            # replace a number-looking run with an odd number
            i = rng.randrange(n)
            b[i:i + rng.randint(1, 6)] = rng.choice([b"1e308", b"0", b"-5", b"1e-300", b"NaN", b"12345678901234567890"])
        else:
            b = bytearray(bytes(rng.randrange(256) for _ in range(rng.randint(0, 128)))) if rng.random() < 0.1 else b
    return bytes(b)


@dataclass(frozen=True)
class Case:
    name: str                          # the subcommand, for test ids
    kind: str                          # the seed the file comes from
    suffix: str                        # its file name suffix
    argv: Callable[[Path, Path], list[str]]   # (file, tmp dir) -> argv
    json_out: bool = True


def _tight(tmp: Path) -> str:
    p = tmp / "tight-cell.yaml"
    if not p.exists():
        p.write_text(TIGHT_CELL, encoding="utf-8")
    return str(p)


def _job_file(tmp: Path) -> str:
    p = tmp / "seed-job.json"
    if not p.exists():
        p.write_text(json.dumps(_job()), encoding="utf-8")
    return str(p)


def _fast_job_file(tmp: Path) -> str:
    """A job no cell config can run (1e9 mm/min): `run` of a fuzzed cell.yaml stops at the check."""
    p = tmp / "fast-job.json"
    if not p.exists():
        job = _job()
        job["layers"][0]["passes"][0]["speed_mm_min"] = 1e9
        p.write_text(json.dumps(job), encoding="utf-8")
    return str(p)


def _run_dir(f: Path, tmp: Path) -> str:
    d = tmp / f"run-{f.stem}"
    d.mkdir(exist_ok=True)
    shutil.copy(f, d / "journal.sqlite")
    return str(d)


CASES: list[Case] = [
    Case("plan", "stl", ".stl", lambda f, t: ["plan", str(f), "--width", "7", "--out", str(t / "o.json"), "--json"]),
    Case("plan", "stl_ascii", ".stl", lambda f, t: ["plan", str(f), "--width", "7", "--out", str(t / "o.json"), "--json"]),
    Case("plan", "obj", ".obj", lambda f, t: ["plan", str(f), "--width", "7", "--out", str(t / "o.json"), "--json"]),
    Case("plan", "3mf", ".3mf", lambda f, t: ["plan", str(f), "--width", "7", "--out", str(t / "o.json"), "--json"]),
    Case("run", "cell_yaml", ".yaml", lambda f, t: ["run", _fast_job_file(t), "--cell-config", str(f), "--runs", str(t / "runs"),
                                             "--json"]),
    Case("export", "cell_yaml", ".yaml", lambda f, t: ["export", _job_file(t), "--format", "gcode", "--cell-config", str(f),
                                             "--out", str(t / "o.nc"), "--json"]),
    Case("process", "material_yaml", ".yaml", lambda f, t: ["process", "inverse", "--width", "7", "--material", str(f),
                                                 "--allow-outside", "--json"]),
    Case("process", "material_yaml", ".yaml", lambda f, t: ["process", "forward", "--current", "120", "--speed", "400",
                                                 "--material", str(f), "--json"]),
    Case("run", "job", ".json", lambda f, t: ["run", str(f), "--cell-config", _tight(t), "--runs", str(t / "runs"),
                                       "--json"]),
    Case("export", "job", ".json", lambda f, t: ["export", str(f), "--format", "krl", "--out", str(t / "o.src"), "--json"]),
    Case("process", "process_csv", ".csv", lambda f, t: ["process", "fit", str(f), "--json"]),
    Case("bead", "profile_csv", ".csv", lambda f, t: ["bead", "fit", str(f), "--json"]),
    Case("align", "plane_csv", ".csv", lambda f, t: ["align", "plane", str(f), "--json"]),
    Case("align", "plane_csv", ".csv", lambda f, t: ["align", "transform", "--rotate", "z:45", "--json", str(f)]),
    Case("journal", "journal", ".sqlite", lambda f, t: ["journal", "check", _run_dir(f, t), "--json"]),
    Case("resume", "journal", ".sqlite", lambda f, t: ["resume", _run_dir(f, t), "--cell-config", _tight(t), "--json"]),
]


class ContractBroken(AssertionError):
    """The CLI broke its contract on an input."""


def run_case(case: Case, data: bytes, tmp: Path, time_limit_s: float = 30.0) -> tuple[int, str, str]:
    """Run one subcommand in-process on `data`; ContractBroken if it breaks the CLI contract."""
    # lazy: only this benchmark's path needs it
    from controller.cli.main import main

    f = tmp / f"input{case.suffix}"
    f.write_bytes(data)
    out, err = io.StringIO(), io.StringIO()
    t0 = time.monotonic()
    argv = case.argv(f, tmp)
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            rc = main(argv)
    except BaseException as exc:  # any escape is a broken contract
        raise ContractBroken(f"{argv}: {type(exc).__name__}: {exc}") from exc
    dt = time.monotonic() - t0
    o, e = out.getvalue(), err.getvalue()
    if rc not in (0, 1, 2):
        raise ContractBroken(f"{argv}: exit status {rc}")
    if "Traceback" in e:
        raise ContractBroken(f"{argv}: traceback on stderr: {e[-500:]}")
    if rc == 2 and "error: " not in e:
        raise ContractBroken(f"{argv}: exit 2 without an `error:` line: {e!r}")
    if dt > time_limit_s:
        raise ContractBroken(f"{argv}: took {dt:.1f} s")
    if case.json_out and rc in (0, 1) and o.strip():
        def _const(c: str) -> None:
            raise ContractBroken(f"{argv}: --json printed {c}")
        try:
            json.loads(o, parse_constant=_const)
        except ValueError as exc:
            raise ContractBroken(f"{argv}: --json stdout is not one JSON object: {exc}: {o[:300]!r}") from None
    return rc, o, e
