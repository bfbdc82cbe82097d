"""The job as the controller carries it after the one read (controller/job/read.py): typed.

`CellJob` holds the planner's typed `Job` (frozen dataclasses, numpy points: planner/job.py)
and what the cell adds around it, all checked when the file was read: the job's identity (the
hash of the file's canonical JSON, which the journal and the run directory are keyed on, the
canonical JSON itself, which the journal stores, the name and the file) and the top-level
sections the planner does not write: the alignment (`cell align run --job`, docs/contract.md §3) and
the repair (`cell repair plan`). Nothing after the read indexes the file's JSON.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from planner.job import Job, Layer


@dataclass(frozen=True, eq=False)
class Alignment:
    """The job's `alignment`: where the part sits on the machine (one per job)."""

    transform: np.ndarray | None      # 4×4 part → machine, finite (None: the section has no transform)
    table_a_deg: float | None         # the A/B leveling (`table_deg`, else `level_a_deg` / `level_b_deg`)
    table_b_deg: float | None
    probed_at: float | None           # Unix time of the probing (None: not a number in the file)
    no_level: bool                    # aligned with `--no-level`: the tilt is in the transform, no A/B move
    points_in_machine_frame: bool     # the points were already moved by the transform (old-style jobs)


@dataclass(frozen=True, eq=False)
class RepairInfo:
    """The job's `repair` section (`cell repair plan`): the CAD, the stock and the repaired region."""

    cad: str | None
    stock: str | None
    allowance_mm: float | None
    bounds_mm: np.ndarray | None      # (2, 3) lower / upper corner of the repair volume, CAD frame


@dataclass(frozen=True, eq=False)
class CellJob:
    """One job, read and checked once, with its identity."""

    job: Job                          # the plan: layers, passes (numpy points), material, bead, frame
    hash: str                         # sha256 of `json`: the journal and the run directory are keyed on it
    json: str                         # the file's object as canonical JSON (what the journal stores)
    name: str                         # the file's `name`, else its source's stem (file-name safe)
    path: Path | None = None          # the file it was read from (None: built in memory, from a journal)
    alignment: Alignment | None = None
    repair: RepairInfo | None = None

    @property
    def layers(self) -> tuple[Layer, ...]:
        return self.job.layers

    @property
    def frame(self) -> str:
        return self.job.frame

    @property
    def passes_total(self) -> int:
        return sum(len(la.passes) for la in self.job.layers)
