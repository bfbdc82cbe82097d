"""Long fuzz run of the command line (issue 14): N corrupted inputs over every subcommand and
file kind (bench/_fuzz.py); prints a JSON summary and exits 1 if any broke the CLI contract.

    python -m bench.fuzz_cli [--n 10000] [--seed 0]
"""
from __future__ import annotations

import argparse
import json
import random
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

from bench._fuzz import CASES, ContractBroken, mutate, run_case, seeds


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--n", type=int, default=10_000)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    t0 = time.monotonic()
    broken: list[str] = []
    codes: Counter = Counter()
    slowest = 0.0
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        base = seeds(tmp)
        for i in range(a.n):
            case = CASES[i % len(CASES)]
            rng = random.Random(a.seed * 1_000_003 + i)
            work = tmp / f"w{i % 8}"
            work.mkdir(exist_ok=True)
            t = time.monotonic()
            try:
                rc, _, _ = run_case(case, mutate(base[case.kind], rng), work, time_limit_s=30.0)
                codes[f"{case.name}:{rc}"] += 1
            except ContractBroken as exc:
                broken.append(f"input {i} ({case.name}, {case.kind}): {exc}"[:600])
            slowest = max(slowest, time.monotonic() - t)
            if (i + 1) % 1000 == 0:
                sys.stderr.write(f"{i + 1} inputs, {len(broken)} broken, {time.monotonic() - t0:.0f} s\n")
    print(json.dumps({"inputs": a.n, "broken": len(broken), "examples": broken[:10],
                      "exit_codes": dict(sorted(codes.items())), "slowest_s": round(slowest, 2),
                      "wall_s": round(time.monotonic() - t0, 1)}, indent=1))
    return 1 if broken else 0


if __name__ == "__main__":
    raise SystemExit(main())
