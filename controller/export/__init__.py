"""Program export (`cell export`): the job as G-code, ABB RAPID or KUKA KRL, and back."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from controller.motion.kinematics import Trunnion
from controller.export.gcode import write_gcode
from controller.export.krl import program_name, write_krl
from controller.export.program import build_program
from controller.export.rapid import write_rapid
from controller.job.model import CellJob

FORMATS = ("gcode", "rapid", "krl")
SUFFIX = {"gcode": ".nc", "rapid": ".mod", "krl": ".src"}


@dataclass(frozen=True)
class Exported:
    """Files to write: name → lines (KRL gives a .src and a .dat)."""

    format: str
    files: dict[str, list[str]]
    passes: int

    @property
    def lines(self) -> int:
        return sum(len(v) for v in self.files.values())


def export_job(job: CellJob, fmt: str, *, name: str, out: Path, clearance_mm: float,
               travel_mm_min: float, power_s: int = 1000, trunnion: Trunnion | None = None,
               baud: int = 115200) -> Exported:
    """Render a job in one format; `out` is the main file (.dat beside a .src)."""
    prog = build_program(job, name=name)
    if fmt == "gcode":
        files = {str(out): write_gcode(prog, clearance_mm=clearance_mm, travel_mm_min=travel_mm_min,
                                       power_s=power_s, trunnion=trunnion, baud=baud)}
    elif fmt == "rapid":
        files = {str(out): write_rapid(prog, travel_mm_min=travel_mm_min, clearance_mm=clearance_mm)}
    elif fmt == "krl":
        # KRL wants the file name to be the program's name.
        src_path = out.with_name(program_name(name).lower() + ".src") if out.suffix != ".src" else out
        src, dat = write_krl(prog, travel_mm_min=travel_mm_min, clearance_mm=clearance_mm)
        files = {str(src_path): src, str(src_path.with_suffix(".dat")): dat}
    else:
        raise ValueError(fmt)
    return Exported(fmt, files, len(prog.passes))
