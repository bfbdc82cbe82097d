"""Programs a machine runs itself, from a job (`cell export`, `cell finish plan`): G-code, RAPID
and KRL of the deposition, and the milling program of a near-net build's top faces."""
from __future__ import annotations

from pathlib import Path

from controller.export import SUFFIX, Exported, export_job
from controller.export.milling import TopFinish, finish_top, milling_program
from controller.export.program import alignment_matrix, points_in_machine_frame
from controller.job.model import CellJob
from controller.motion.kinematics import Trunnion
from core.config import CellConfig

__all__ = ["SUFFIX", "Exported", "TopFinish", "alignment_matrix", "export_program", "finish_top", "milling_program",
           "points_in_machine_frame"]


def export_program(job: CellJob, fmt: str, *, name: str, out: Path, cfg: CellConfig) -> Exported:
    """The job as a `fmt` program (gcode, rapid, krl) for the machine of `cfg`: its clearance, travel
    speed, trunnion and CNC baud rate; `out` is the main file (.dat beside a .src)."""
    return export_job(job, fmt, name=name, out=out, clearance_mm=cfg.limits.clearance_mm,
                      travel_mm_min=cfg.limits.travel_speed_mm_min, trunnion=Trunnion.from_config(cfg.kinematics),
                      baud=cfg.devices.cnc.baud)
