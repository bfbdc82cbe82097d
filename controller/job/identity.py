"""A job's identity: its canonical JSON, the hash the journal and the run directory are keyed on,
its name, and the run directory under runs/.

The hash is of the file's own object (every key, every number as the file wrote it), computed
once when the file is read (controller/job/read.py) and carried with the typed job: never
recomputed from the typed job, whose numbers the planner's writer would round. A journal keyed
on it by an earlier version of the controller is the same job's journal now.
"""
from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # the typed job only annotates run_dir_for (model.py imports nothing of this module)
    from controller.job.model import CellJob


def canonical_json(obj: dict[str, Any]) -> str:
    """A job file's object as canonical JSON: sorted keys, compact separators."""
    return json.dumps(obj, sort_keys=True, separators=(",", ":"))


def text_hash(canonical: str) -> str:
    """sha256 (hex) of canonical JSON text."""
    return hashlib.sha256(canonical.encode("utf-8")).hexdigest()


def job_hash(obj: dict[str, Any]) -> str:
    """sha256 of a job file's canonical JSON: the journal and the run directory are keyed on it."""
    return text_hash(canonical_json(obj))


def job_name(obj: dict[str, Any]) -> str:
    """The file's `name`, else its source file's stem; only letters, digits and `-_.` kept."""
    name = obj.get("name") or Path(str((obj.get("source") or {}).get("file") or "job")).stem
    return "".join(c if c.isalnum() or c in "-_." else "-" for c in str(name)) or "job"


def run_dir_for(job: CellJob, runs_dir: str | Path) -> Path:
    """runs/<job-name>-<hash8>/"""
    return Path(runs_dir) / f"{job.name}-{job.hash[:8]}"
