"""`cell align plane` and `cell align transform` as a user types them (docs/contract.md §7)."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from controller.cli.main import main

pytestmark = pytest.mark.realtime  # a cell on the wall clock (tests/conftest.py)


def _json(capsys, argv):
    rc = main(argv)
    out, err = capsys.readouterr()
    assert rc == 0, err
    return json.loads(out)


def test_transform_reproduces_paper_table1(capsys):
    got = _json(capsys, ["align", "transform", "--rotate", "z:45", "--rotate", "y:45", "--pivot=1,1,5", "--json",
                         "--", "0,0,0", "0,1,0", "1,1,0", "1,0,0"])
    want = [[2.53553, 0.41421, -1.46447], [2.03553, 1.12132, -0.96447], [2.5355, 1.8284, -1.4645], [3.0355, 1.1213, -1.9645]]
    assert np.abs(np.array(got["points"]) - want).max() < 1e-4


def test_transform_negative_numbers_as_typed(capsys, tmp_path):
    a = _json(capsys, ["align", "transform", "--rotate", "x:-30", "--pivot=-1,-1,-5", "--json", "--", "-1,2,-3"])
    b = _json(capsys, ["align", "transform", "--rotate", "x:-30", "--pivot", "-1,-1,-5", "--json", "-1,2,-3"])
    assert a["points"] == b["points"]
    c, s = np.cos(np.radians(-30)), np.sin(np.radians(-30))
    q = np.array([-1, 2, -3.0]) + [-1, -1, -5]
    expect = np.array([q[0], c * q[1] - s * q[2], s * q[1] + c * q[2]]) - [-1, -1, -5]
    assert np.abs(np.array(a["points"][0]) - expect).max() < 1e-12
    # Points from a CSV file, mixed with words; order kept.
    f = tmp_path / "pts.csv"
    f.write_text("x,y,z\n0,0,0\n1,0,0\n")
    d = _json(capsys, ["align", "transform", "--rotate", "z:90", "--json", str(f), "--", "0,1,0"])
    assert np.allclose(d["points"], [[0, 0, 0], [0, 1, 0], [-1, 0, 0]], atol=1e-12)


def test_transform_bad_input_is_one_error_line(capsys):
    for argv in (["align", "transform", "--rotate", "w:45", "--", "0,0,0"],
                 ["align", "transform", "--rotate", "z:45", "--pivot=1,2", "--", "0,0,0"],
                 ["align", "transform", "--rotate", "z:45", "--", "0,0"]):
        assert main(argv) == 2
        out, err = capsys.readouterr()
        assert out == "" and err.count("\n") == 1 and err.startswith("error: ")


def test_plane_csv_keys_outlier_and_leveling(capsys, tmp_path):
    rng = np.random.default_rng(11)
    rows = ["x,y,z"]
    for i, (x, y) in enumerate([(x, y) for x in (-50, 0, 50) for y in (-50, 0, 50)]):
        z = 5 + 0.01 * x - 0.02 * y + rng.normal(0, 0.002) + (0.05 if i == 7 else 0.0)
        rows.append(f"{x},{y},{z:.6f}")
    f = tmp_path / "top.csv"
    f.write_text("\n".join(rows) + "\n")
    got = _json(capsys, ["align", "plane", str(f), "--json"])
    for key in ("normal", "point", "rms_mm", "max_residual_mm", "outliers", "level_a_deg", "level_b_deg"):
        assert key in got
    assert got["outliers"] == [7]
    n = np.array([-0.01, 0.02, 1.0]) / np.linalg.norm([-0.01, 0.02, 1.0])
    assert np.abs(np.array(got["normal"]) - n).max() < 1e-4
    assert got["rms_mm"] < 0.004
    # cell.yaml's AB table (A about x, B about y): A = atan2(ny, nz), B = atan2(-nx, …).
    assert got["level_a_deg"] == pytest.approx(np.degrees(np.arctan2(n[1], n[2])), abs=0.01)
    assert got["level_b_deg"] == pytest.approx(np.degrees(np.arctan2(-n[0], np.hypot(n[1], n[2]))), abs=0.01)


def test_plane_bad_csv_names_file_and_line(capsys, tmp_path):
    f = tmp_path / "bad.csv"
    f.write_text("x,y,z\n0,0,0\n1,0,zero\n0,1,0\n")
    assert main(["align", "plane", str(f)]) == 2
    err = capsys.readouterr().err
    assert "bad.csv" in err and "line 3" in err and err.count("\n") == 1
    g = tmp_path / "line.csv"
    g.write_text("0,0,0\n1,1,1\n2,2,2\n")
    assert main(["align", "plane", str(g), "--json"]) == 2
    assert "collinear" in capsys.readouterr().err


def test_cli_entry_point_with_negative_pivot():
    """The installed `cell` script, negative numbers as a shell user types them."""
    r = subprocess.run([sys.executable, "-m", "controller.cli.main", "align", "transform", "--rotate", "z:45",
                        "--rotate", "y:45", "--pivot=1,1,5", "--json", "--", "0,0,0"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert np.allclose(json.loads(r.stdout)["points"][0], [2.53553, 0.41421, -1.46447], atol=1e-5)


def test_run_without_a_device_or_with_a_bad_job_is_one_error_line(capsys, tmp_path):
    from core.config import CONFIG_DIR

    cell = tmp_path / "cell.yaml"
    cell.write_text((CONFIG_DIR / "cell.yaml").read_text().replace("socket://127.0.0.1:47602", "socket://127.0.0.1:1"))
    assert main(["align", "run", "--cell-config", str(cell), "--json"]) == 2
    out, err = capsys.readouterr()
    assert err.count("\n") == 1 and "socket://127.0.0.1:1" in err
    obj = json.loads(out)   # --json: one object on every exit path (issue 38)
    assert out.count("\n") == 1 and obj["state"] == "refused" and "socket://127.0.0.1:1" in obj["error"]
    bad = tmp_path / "job.json"
    bad.write_text('{"schema": "cell-job/1",\n "layers": [}\n')
    assert main(["align", "run", "--sim", "--job", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "job.json" in err and "line 2" in err and err.count("\n") == 1
