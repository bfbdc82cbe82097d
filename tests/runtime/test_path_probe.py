"""The path loop's touches along a pass (controller/runtime/path_probe.py) on the CNC simulator, over
the grbl wire protocol: one touch a point, the tops in the spots' order, visited from the near end."""
from __future__ import annotations

from pathlib import Path

import pytest

from controller.runtime.path_probe import TouchPlan, expected_tops, touch_tops
from core.config import load_sim
from sims.clock import SimClock
from sims.cnc import CncSim
from sims.workpiece import Workpiece
from tests.cnc_fixtures import cnc_link

pytestmark = pytest.mark.realtime  # a simulator on the wall clock (tests/conftest.py)


async def test_one_touch_a_point_reads_the_tilted_top_in_the_spots_order(tmp_path: Path) -> None:
    wp = load_sim().cnc.workpiece          # a 100 mm block, its top tilted 0.8° and -0.5°
    piece = Workpiece.from_config(wp, 0.0, seed=1)
    sim = CncSim(clock=SimClock(100.0), workpiece=piece, log_path=tmp_path / "cnc.jsonl")
    async with cnc_link(sim) as link:
        await link.connect()
        await link.home()
        await link.command("G90 G0 X40 Y0 Z30")     # the head near the pass's far end
        await link.wait_idle()                       # (as a layer's stream ends: its G4 P0 answered)
        spots = [(float(x), 0.0, 0.0) for x in range(-40, 41, 10)]   # planned top z 0 along x
        tops = await touch_tops(link, spots, TouchPlan())
        truth = []
        for x, y, _ in spots:
            hit = piece.probe((x, y, 10.0), (x, y, -10.0))
            assert hit is not None
            truth.append(hit[2])
        assert max(abs(t - u) for t, u in zip(tops, truth)) < 1e-3        # each top where it is, in order
        assert max(truth) - min(truth) > 0.5                              # (the tilt: ±0.6 mm over the pass)
        probes = [b for b in sim.executed if b.probe]
        assert len(probes) == len(spots) and all(b.contact and b.feed == 1800.0 for b in probes)
        assert probes[0].target is not None and probes[0].target[0] == pytest.approx(40.0)   # the near end first
        st = await link.wait_idle()
        assert st.mpos[2] == pytest.approx(max(truth[0], 0.0) + 1.5, abs=0.01)   # ends a hop above the top


def test_the_next_layer_is_expected_where_the_last_touches_stood_raised_by_the_commanded_rise() -> None:
    before = [(0.0, 0.0, 5.0), (10.0, 0.0, 5.0)]
    got = expected_tops(before, [4.6, 5.9], [(1.0, 0.0, 6.2), (9.0, 0.0, 6.2), (30.0, 0.0, 6.2)])
    assert got == pytest.approx([5.8, 7.1, 7.1])     # a high spot stays high: the travel must clear it
