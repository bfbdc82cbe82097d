"""The time scale the host can feed a 5-axis program at (issue 38, docs/controller.md "Simulated time
the host can feed"): the shipped grblHAL 5-axis cell feeds the tilted tube and the frustum at its own
time scale with the simulators beside (`cell sim up`), lowers it with them in this interpreter, and a
program the host cannot feed is still lowered, the message naming the line cost it assumed."""
from __future__ import annotations

from pathlib import Path

import pytest

from bench.five_axis import GRBLHAL5_CELL, plan5
from bench.parts5 import cone_frustum, tilted_tube
from controller.job.model import CellJob
from controller.job.read import job_from_dict
from controller.motion.cnc5 import limit_time_scale
from core.config import CellConfig, load_cell


def _cell(scale: float | None = None) -> CellConfig:
    cfg = load_cell(GRBLHAL5_CELL)
    if scale is not None:
        cfg = cfg.model_copy(update={"cell": cfg.cell.model_copy(update={"time_scale": scale})})
    return cfg


@pytest.fixture(scope="module")
def tube() -> CellJob:
    return job_from_dict(plan5(tilted_tube(height=1.2)))


def test_the_shipped_five_axis_cell_is_grblhal_with_its_ring() -> None:
    cfg = _cell()
    assert Path(GRBLHAL5_CELL).parent.name == "config"
    assert cfg.cell.platform == "cnc" and cfg.cell.time_scale == 10.0
    assert cfg.devices.cnc.rx_buffer_bytes == 1024   # grblHAL's ring: a 5-axis stream keeps ~30 lines in flight


def test_the_tube_is_fed_at_scale_10_beside_and_lowered_in_this_interpreter(tube: CellJob) -> None:
    beside, note = limit_time_scale(_cell(), tube, beside=True)
    assert note is None and beside.cell.time_scale == 10.0
    here, note = limit_time_scale(_cell(), tube)
    assert here.cell.time_scale == 5.0
    assert note is not None and note.startswith("cnc: at time scale 10 the link cannot feed"), note
    assert "2.0 ms on this host" in note and note.endswith("time scale limited to 5"), note


def test_the_frustum_is_fed_at_scale_10_beside() -> None:
    job = job_from_dict(plan5(cone_frustum(height=1.2)))
    cfg, note = limit_time_scale(_cell(), job, beside=True)
    assert note is None and cfg.cell.time_scale == 10.0


def test_a_program_the_host_cannot_feed_beside_is_still_lowered_and_said(tube: CellJob) -> None:
    cfg, note = limit_time_scale(_cell(20.0), tube, beside=True)
    assert cfg.cell.time_scale == 10.0
    assert note is not None and "at time scale 20 the link cannot feed" in note, note
    assert "1.0 ms on this host" in note and "torch would stand still" in note, note
