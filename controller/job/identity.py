"""A job's identity: its canonical JSON, the hash the journal and the run directory are keyed on,
its name, and the run directory under runs/."""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

from controller.job.read import JobJSON


def canonical_json(job: JobJSON) -> str:
    return json.dumps(job, sort_keys=True, separators=(",", ":"))


def job_hash(job: JobJSON) -> str:
    """sha256 of the job's canonical JSON: the journal and the run directory are keyed on it."""
    return hashlib.sha256(canonical_json(job).encode("utf-8")).hexdigest()


def job_name(job: JobJSON) -> str:
    name = job.get("name") or Path(str((job.get("source") or {}).get("file") or "job")).stem
    return "".join(c if c.isalnum() or c in "-_." else "-" for c in str(name)) or "job"


def run_dir_for(job: JobJSON, runs_dir: str | Path) -> Path:
    """runs/<job-name>-<hash8>/"""
    return Path(runs_dir) / f"{job_name(job)}-{job_hash(job)[:8]}"
