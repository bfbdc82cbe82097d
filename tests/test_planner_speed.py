"""Plan-time work that does not scale with the part is not done at plan time (issue 28 item 7)."""
from __future__ import annotations

import subprocess
import sys

import pytest

from planner.bead import SOLVED_RATIOS, _critical_ratio


@pytest.mark.parametrize("profile", sorted(SOLVED_RATIOS))
def test_the_kept_critical_ratios_are_the_solved_ones(profile):
    assert SOLVED_RATIOS[profile] == pytest.approx(_critical_ratio(profile, 0.25, solve=True), abs=1e-12)
    assert SOLVED_RATIOS["parabola"] == pytest.approx(0.738, abs=5e-4)  # Ding 2015: d* = 0.738 w


def test_planning_imports_no_scipy_trimesh_or_matplotlib():
    """A binary-STL plan loads none of the heavy optional libraries (start-up time)."""
    code = ("import sys; import planner.plan, planner.mesh, controller.cli.plan; "
            "print(sorted(m for m in ('scipy', 'trimesh', 'matplotlib', 'networkx') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
