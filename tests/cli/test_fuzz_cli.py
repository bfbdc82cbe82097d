"""Fuzz the command line (issue 14): every subcommand fed corrupted files of each kind it reads
(STL/OBJ/3MF, YAML, job JSON, CSV, journal) exits 0, 1 or 2, never with a traceback, in bounded
time, and its `--json` stdout is valid JSON (no NaN). In-process via main(argv) for speed, plus
a few subprocess cases; bench/fuzz_cli.py is the long run (>= 10,000 inputs)."""
from __future__ import annotations

import os
import random
import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bench._fuzz import CASES, ROOT, mutate, run_case, seeds

SEEDS: dict[str, bytes] = {}


@pytest.fixture(scope="module")
def seed_files(tmp_path_factory) -> dict[str, bytes]:
    if not SEEDS:
        SEEDS.update(seeds(tmp_path_factory.mktemp("seeds")))
    return SEEDS


@pytest.mark.parametrize("case", CASES, ids=lambda c: f"{c.name}-{c.kind}")
def test_the_unmutated_seed_keeps_the_contract(case, seed_files, tmp_path: Path) -> None:
    rc, _, _ = run_case(case, seed_files[case.kind], tmp_path)
    assert rc in (0, 1, 2)


@settings(max_examples=250, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)
@given(case_i=st.integers(0, len(CASES) - 1), seed=st.integers(0, 2**32 - 1))
def test_corrupted_inputs_keep_the_cli_contract(case_i: int, seed: int, seed_files, tmp_path_factory) -> None:
    case = CASES[case_i]
    data = mutate(seed_files[case.kind], random.Random(seed))
    run_case(case, data, tmp_path_factory.mktemp("fz"), time_limit_s=20.0)


@pytest.mark.parametrize("name, data, argv", [
    ("bad.csv", b"x,y,z\n\xff\xfe,1,2\n", ["align", "plane"]),
    ("deep.yaml", b"a: " + b"[" * 100_000 + b"]" * 100_000, ["process", "inverse", "--width", "7", "--material"]),
    ("job.json", b"\x89PNG\x00garbage", ["export", "--format", "gcode"]),
], ids=["non-utf8-csv", "deep-yaml", "garbage-job"])
def test_subprocess_bad_inputs_give_one_error_line(tmp_path: Path, name: str, data: bytes, argv: list[str]) -> None:
    f = tmp_path / name
    f.write_bytes(data)
    full = argv[:2] + [str(f)] + argv[2:] if argv[0] in ("align",) else argv + [str(f)]
    if argv[0] == "export":
        full = ["export", str(f), "--format", "gcode", "--out", str(tmp_path / "o.nc")]
    r = subprocess.run([sys.executable, "-m", "controller.cli.main", *full], capture_output=True, text=True, check=False,
                       timeout=60, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert r.returncode == 2, r.stderr
    assert r.stderr.startswith("error: ") and r.stderr.count("\n") == 1 and "Traceback" not in r.stderr
    assert str(f.name) in r.stderr
