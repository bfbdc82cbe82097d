"""A job without a cell session: read (once, typed), made from an object in memory, taken back
from a journal, checked against the cell, its run directory, the repair volume it fills, its
preview plots, the CAD meshes a repair job names (`cell run`, `cell plan`, `cell repair`, `cell
export`, `cell finish`, the demo, the TUI)."""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

from controller.job.model import CellJob
from controller.job.read import job_from_dict, read_job

if TYPE_CHECKING:
    import trimesh
    from core.config import CellConfig
    from controller.job.repair_volume import RepairVolume
    from planner.job import Job

__all__ = ["CellJob", "check_job_for_cell", "complete_in", "job_from_dict", "read_job", "repair_mesh",
           "repair_volume", "run_dir_for", "stored_job", "write_previews"]


def check_job_for_cell(job: CellJob, cfg: CellConfig, source: str) -> None:
    """The job checked against the cell (controller/job/check.py): a JobCheckError naming `source`
    and the first violation when it does not fit. The session's `open_job` finds it checked."""
    # lazy: the material tables load only when a job is checked
    from controller.job.check import check_job, job_material

    check_job(job, cfg, job_material(job, cfg), source)


def stored_job(meta: dict[str, Any], journal: Path) -> CellJob:
    """The job a journal holds (`RunJournal.job`), refused when it no longer matches the checksum
    stored beside it."""
    # lazy: the journal's reader loads only when a run is resumed
    from controller.job.read import stored_job as read_stored

    return read_stored(meta["job_json"], meta["hash"], journal)


def run_dir_for(job: CellJob, runs_dir: str | Path) -> Path:
    """The job's run directory: runs/<job-name>-<hash8>/."""
    # lazy: loaded with the job's identity only
    from controller.job.identity import run_dir_for as where

    return where(job, runs_dir)


def complete_in(run_dir: Path, job: CellJob) -> bool:
    """Whether the journal of `run_dir` says every pass of the job is done (a read-only look)."""
    # lazy: the journal loads only when a run directory is looked at
    from controller.journal.store import count_done_readonly

    total = job.passes_total
    return total > 0 and count_done_readonly(run_dir / "journal.sqlite") >= total


def repair_volume(cad: trimesh.Trimesh, stock: trimesh.Trimesh, allowance_mm: float = 0.0, *,
                  cad_name: str = "CAD", stock_name: str = "stock", overhang_mm: float = 0.0) -> RepairVolume:
    """CAD (swept up by the allowance) minus the stock (manifold3d): the volume a repair fills,
    carried `overhang_mm` beyond the CAD's free edges."""
    # lazy: manifold3d loads only when a repair is planned
    from controller.job.repair_volume import repair_volume as volume

    return volume(cad, stock, allowance_mm, cad_name=cad_name, stock_name=stock_name, overhang_mm=overhang_mm)


def repair_mesh(job: CellJob, job_path: Path | None, which: str = "cad") -> trimesh.Trimesh:
    """The CAD (or, `which="stock"`, the stock) mesh a repair job names; a relative path is looked
    up next to the job file."""
    # lazy: trimesh loads only when a mesh is read
    from controller.job.repair_volume import load_cad

    return load_cad(job, job_path, which)


def write_previews(job: Job, out_dir: str | Path) -> list[Path]:
    """layers.png and overview.png of a planned job in `out_dir` (`cell plan --preview`)."""
    # lazy: matplotlib loads only when previews are written
    from controller.job.preview import write_previews as write

    return write(job, out_dir)
