"""Deposit again where the stock probe found the deposit short (issue 36 item 2, docs/machining.md
"Deposit again"): the short spots become a small job on the repair's own frame and process."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from controller.cli.main import main
from controller.harness.repair_parts import make_parts
from controller.job.check import check_job
from controller.job.read import read_job
from controller.job.redeposit import redeposit_job
from core.config import load_cell, load_material
from planner.job import Job


def _pocket_job(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> Job:
    """The repair job of a 20 × 20 × 4 pocket at x, y 30…50, 4 mm beads, 0.5 mm allowance, as
    `cell repair plan` writes it."""
    cad, stock = make_parts(tmp_path)
    job_path = tmp_path / "job.json"
    assert main(["repair", "plan", str(cad), "--stock", str(stock), "--width", "4", "--allowance", "0.5",
                 "--out", str(job_path)]) == 0
    capsys.readouterr()
    return read_job(job_path)


def test_short_spots_become_short_passes_from_each_spot_inward_until_the_target(tmp_path: Path, capsys):
    job = _pocket_job(tmp_path, capsys)     # a 20 × 20 × 4 pocket at x, y 30…50
    # probed: a corner 0.6 below CAD, a spot beside it (one with it), one inside 0.3 below, one corner 0.1 below
    pts = np.array([[30.25, 30.25, -0.6], [31.0, 30.25, -0.5], [40.0, 42.0, -0.3], [49.75, 49.75, -0.1]])
    extra = redeposit_job(job, pts, pts[:, 2], 0.5)
    check_job(extra, load_cell(), load_material(load_cell().cell.material))   # a job the cell builds
    h = job.layers[-1].height_mm
    assert [len(L.passes) for L in extra.layers] == [3, 3, 1]       # 0.6 → 0.5 needs 3 layers, 0.3 two, 0.1 two
    zs = [L.z_mm for L in extra.layers]
    assert zs == pytest.approx([-0.1 + h, -0.1 + 2 * h, -0.1 + 3 * h])   # over the highest probed top
    first = extra.layers[0].passes
    top = job.layers[-1].passes[0]
    for p, spot in zip(first, ([30.25, 30.25], [40.0, 42.0], [49.75, 49.75])):
        a, b = p.points[0, :2], p.points[-1, :2]
        assert np.linalg.norm(b - a) == pytest.approx(4.0)                                  # a bead long
        assert np.linalg.norm(a + (b - a) / 4 - spot) == pytest.approx(0.0, abs=1e-3)       # its run-in before the spot
        assert np.linalg.norm(b - 40.0) <= np.linalg.norm(a - 40.0) + 1e-9                  # inward
        assert p.current_a == top.current_a and p.width_mm == top.width_mm
    assert extra.name.endswith("-redeposit1") and extra.hash != job.hash
    assert extra.repair is not None and extra.repair.cad == job.repair.cad


def test_a_deposit_short_all_over_gets_whole_layers_again_then_short_passes_where_still_short(tmp_path: Path, capsys):
    job = _pocket_job(tmp_path, capsys)     # a 20 × 20 × 4 pocket at x, y 30…50
    h = job.layers[-1].height_mm
    # the process laid less than planned: the deposit stands 0.1 mm over CAD in the middle (z 0.1), a corner 0.6 below
    pts = np.array([[40.0, 40.0, 0.1], [30.25, 30.25, -0.6]])
    extra = redeposit_job(job, pts, pts[:, 2], 0.3, typical=(0.1, 0.1))
    check_job(extra, load_cell(), load_material(load_cell().cell.material))
    whole, spots = extra.layers[0], extra.layers[1:]
    # one whole layer: the plan's second-highest layer again (the plan alternates), 0.1 + h high, every pass of it
    second = sorted(job.layers, key=lambda L: L.z_mm)[-2]
    assert whole.z_mm == pytest.approx(0.1 + h) and len(whole.passes) == len(second.passes)
    assert np.allclose(whole.passes[0].points[:, :2], second.passes[0].points[:, :2])
    # then the corner alone (-0.6 + h is still short), over the whole layer, until 0.3: two more layers
    assert [len(L.passes) for L in spots] == [1, 1]
    assert [L.z_mm for L in spots] == pytest.approx([0.1 + 2 * h, 0.1 + 3 * h])
    assert extra.job.summary["redeposit"]["whole_layers"] == 1
    # a deposit standing clear in the middle gets no whole layer: short passes only
    only = redeposit_job(job, pts[1:], pts[1:, 2], 0.3, typical=(0.5, 0.5))
    assert only.job.summary["redeposit"]["whole_layers"] == 0 and all(len(L.passes) == 1 for L in only.layers)
    # the corner's passes run over the deposit around it (z 0.5), not at the hole's own top (-0.6):
    # a torch there would stand 1.1 mm under the surroundings
    assert [L.z_mm for L in only.layers] == pytest.approx([0.5 + h, 0.5 + 2 * h, 0.5 + 3 * h])   # -0.6 to 0.3: 3 layers
