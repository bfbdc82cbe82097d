"""Ground-truth check of a build: the simulators' deposit log against the planned passes.

Every planned pass polyline is sampled every `step` mm; a sample is covered by a deposited
segment that passes within `tol` of it running along the path (|cos| > 0.98, so a crossing
bead does not count). Missing = planned length not covered; excess = deposited length beyond
the planned length (double deposits, re-arc overlaps).
"""
from __future__ import annotations

import json
import math
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np


@dataclass(frozen=True)
class Coverage:
    planned_mm: float
    deposited_mm: float
    missing_mm: float
    excess_mm: float
    samples: int
    uncovered: list[tuple[float, float, float]]
    overlaps_mm: list[float]      # lengths of the stretches deposited more than once


    def as_dict(self) -> dict:
        return {"planned_mm": round(self.planned_mm, 2), "deposited_mm": round(self.deposited_mm, 2),
                "missing_mm": round(self.missing_mm, 3), "excess_mm": round(self.excess_mm, 3),
                "samples": self.samples, "uncovered_first": self.uncovered[:5],
                "overlaps": len(self.overlaps_mm),
                "max_overlap_mm": round(max(self.overlaps_mm, default=0.0), 3)}


def read_segments(path: str | Path) -> list[dict]:
    out = []
    p = Path(path)
    if not p.exists():
        return out
    for line in p.read_text(encoding="utf-8").splitlines():
        line = line.strip()
        if line:
            try:
                out.append(json.loads(line))
            except json.JSONDecodeError:
                pass  # a line torn by a kill of the simulator's process
    return out


def coverage(passes: Iterable[Sequence[Sequence[float]]], segments: list[dict], *, step: float = 0.25,
             tol: float = 0.05) -> Coverage:
    seg_a = np.array([s["from"] for s in segments], float).reshape(-1, 3)
    seg_b = np.array([s["to"] for s in segments], float).reshape(-1, 3)
    by_z: dict[int, list[int]] = defaultdict(list)
    for k in range(len(seg_a)):
        for zk in {round(seg_a[k, 2] * 10), round(seg_b[k, 2] * 10)}:
            by_z[zk].append(k)
    deposited = float(np.linalg.norm(seg_b - seg_a, axis=1).sum()) if len(seg_a) else 0.0
    planned = 0.0
    missing = 0.0
    n = 0
    uncovered: list[tuple[float, float, float]] = []
    overlaps: list[float] = []
    for pts in passes:
        run = 0.0  # length of the current stretch covered twice or more
        P = np.asarray(pts, float)[:, :3]
        for i in range(len(P) - 1):
            a, b = P[i], P[i + 1]
            L = float(np.linalg.norm(b - a))
            if L < 1e-9:
                continue
            planned += L
            d = (b - a) / L
            idx = by_z.get(round(a[2] * 10), [])
            if not idx:
                missing += L
                n += 1
                if run > 0:
                    overlaps.append(run)
                    run = 0.0
                continue
            A, B = seg_a[idx], seg_b[idx]
            D = B - A
            Ls = np.linalg.norm(D, axis=1)
            ok = Ls > 1e-9
            U = np.where(ok[:, None], D / np.maximum(Ls, 1e-12)[:, None], 0.0)
            par = np.abs(U @ d) > 0.98
            m = max(1, math.ceil(L / step))
            ts = (np.arange(m) + 0.5) / m
            S = a + ts[:, None] * (b - a)
            for s in S:
                n += 1
                w = s - A
                tt = np.clip(np.einsum("ij,ij->i", w, D) / np.maximum(Ls ** 2, 1e-12), 0, 1)
                dist = np.linalg.norm(A + tt[:, None] * D - s, axis=1)
                near = (dist < tol) & par
                hits = int(np.count_nonzero(near))
                # two segments meeting at the sample (one move ending, the next starting) are not
                # a double deposit: count only those that run past it by more than `tol`
                inner = int(np.count_nonzero(near & (tt * Ls > tol) & ((1 - tt) * Ls > tol)))
                hits = min(hits, 1) if inner + (hits - inner) / 2 < 2 else 2  # multiplicity of the deposit
                if hits == 0:
                    missing += L / m
                    if len(uncovered) < 50:
                        uncovered.append(tuple(round(float(v), 3) for v in s))
                if hits >= 2:
                    run += L / m
                elif run > 0:
                    overlaps.append(run)
                    run = 0.0
        if run > 0:
            overlaps.append(run)
    return Coverage(planned, deposited, missing, max(0.0, deposited - (planned - missing)), n, uncovered, overlaps)


def exec_log_duplicates(path: str | Path) -> int:
    """How many queue entries of robot.jsonl repeat a sequence number already executed."""
    seen: set[int] = set()
    dup = 0
    for rec in read_segments(path):
        s = rec.get("seq")
        if s in seen:
            dup += 1
        seen.add(s)
    return dup
