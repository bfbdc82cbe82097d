"""`cell process …` and `cell bead …`: docs/contract.md §7 flags and JSON keys, and bad input as exit 2."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from controller.cli.main import main
from core.config import CONFIG_DIR, load_cell, load_material

DATA = Path(__file__).parents[1] / "data"
ROOT = Path(__file__).resolve().parents[2]


def run(argv, capsys):
    """Run `cell ARGV` in-process: (exit status, stdout, stderr)."""
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse usage errors
        code = exc.code
    out, err = capsys.readouterr()
    return code, out, err


def run_json(argv, capsys) -> dict:
    code, out, err = run(argv + ["--json"], capsys)
    assert code == 0, err
    assert err == ""
    lines = out.strip().splitlines()
    assert len(lines) == 1, "exactly one JSON object on stdout"
    obj = json.loads(lines[0])
    assert isinstance(obj, dict)
    return obj


def assert_one_line_error(code, out, err, *needles):
    assert code == 2
    assert out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert "Traceback" not in err
    for n in needles:
        assert n in lines[0], lines[0]


# --- process ---------------------------------------------------------------------------------


def test_process_inverse_json_keys_and_values(capsys):
    obj = run_json(["process", "inverse", "--width", "6"], capsys)
    assert {"width_mm", "height_mm", "current_a", "speed_mm_min", "wfs_m_min", "inside_envelope"} <= set(obj)
    assert obj["width_mm"] == 6.0 and obj["height_mm"] == pytest.approx(0.66)
    assert obj["current_a"] == pytest.approx(141.743, abs=1e-3)
    assert obj["speed_mm_min"] == pytest.approx(1366.48, abs=1e-2)
    assert obj["wfs_m_min"] == pytest.approx(6.445, abs=1e-3)
    assert obj["inside_envelope"] is True
    # Default material: cell.yaml's cell.material.
    assert obj["material"] == load_material(load_cell().cell.material).name


def test_process_inverse_with_height_and_material_file(capsys):
    obj = run_json(["process", "inverse", "--width", "8", "--height", "2.0", "--material", "er70s6-1.2mm"], capsys)
    assert obj["height_mm"] == 2.0 and obj["inside_envelope"] and obj["material"].startswith("ER70S-6")
    path = str(CONFIG_DIR / "materials" / "inconel718-1.0mm.yaml")
    obj = run_json(["process", "inverse", "--width", "6", "--material", path], capsys)
    assert obj["current_a"] == pytest.approx(141.743, abs=1e-3)


def test_process_inverse_outside_envelope(capsys):
    code, out, err = run(["process", "inverse", "--width", "10"], capsys)
    assert_one_line_error(code, out, err, "175.7 A", "Imax 160 A", "Inconel 718", "--allow-outside")
    obj = run_json(["process", "inverse", "--width", "10", "--allow-outside"], capsys)
    assert obj["inside_envelope"] is False and obj["current_a"] > 160


def test_process_inverse_human_table(capsys):
    code, out, err = run(["process", "inverse", "--width", "6"], capsys)
    assert code == 0 and err == ""
    assert "141.7 A" in out and "1366.5 mm/min" in out and "6.45 m/min" in out and "inside" in out
    assert not out.lstrip().startswith("{")


def test_process_forward(capsys):
    obj = run_json(["process", "forward", "--current", "140", "--speed", "1000"], capsys)
    assert {"width_mm", "height_mm"} <= set(obj)
    assert obj["width_mm"] == pytest.approx(6.7514, abs=1e-4)
    assert obj["height_mm"] == pytest.approx(0.79342, abs=1e-5)
    code, out, _ = run(["process", "forward", "--current", "140", "--speed", "1000"], capsys)
    assert code == 0 and "6.751 mm" in out


def test_process_fit(capsys):
    obj = run_json(["process", "fit", str(DATA / "ribeiro_beads.csv")], capsys)
    assert {"k1", "k2", "k3", "k4", "k5", "k6", "r2_width", "r2_height"} <= set(obj)
    assert obj["n_points"] == 24
    assert obj["r2_width"] > 0.98 and obj["r2_height"] > 0.98
    assert obj["k2"] == pytest.approx(0.968, abs=0.1) and obj["k3"] == pytest.approx(-0.416, abs=0.05)
    code, out, _ = run(["process", "fit", str(DATA / "ribeiro_beads.csv")], capsys)
    assert code == 0 and "k1:" in out and "R²" in out


# --- bead ------------------------------------------------------------------------------------


def test_bead_critical_distance(capsys):
    obj = run_json(["bead", "critical-distance"], capsys)
    assert obj["model"] == "parabola" and round(obj["ratio"], 3) == 0.738
    obj = run_json(["bead", "critical-distance", "--model", "cosine", "--width", "6"], capsys)
    assert obj["model"] == "cosine" and obj["step_over_mm"] == pytest.approx(6 * obj["ratio"])
    obj = run_json(["bead", "critical-distance", "--model", "arc", "--aspect", "0.2"], capsys)
    assert obj["aspect"] == 0.2 and 0.738 < obj["ratio"] < 1
    code, out, _ = run(["bead", "critical-distance"], capsys)
    assert code == 0 and "0.7378" in out


def test_bead_fit(capsys):
    obj = run_json(["bead", "fit", str(DATA / "bead_profile.csv")], capsys)
    assert set(obj) >= {"parabola", "cosine", "arc"}
    for name in ("parabola", "cosine", "arc"):
        assert {"width_mm", "height_mm", "area_mm2", "r2"} <= set(obj[name])
        assert obj[name]["r2"] > 0.975
    assert obj["parabola"]["width_mm"] == pytest.approx(8.83, rel=0.02)
    code, out, _ = run(["bead", "fit", str(DATA / "bead_profile.csv")], capsys)
    assert code == 0 and "parabola" in out and "cosine" in out and "arc" in out


# --- bad input: exit 2, one `error:` line, no traceback --------------------------------------


@pytest.mark.parametrize(
    "argv,needles",
    [
        (["process", "inverse", "--width", "abc"], ["--width", "abc"]),
        (["process", "inverse"], ["--width"]),
        (["process", "inverse", "--width", "-3"], ["width", "-3"]),
        (["process", "inverse", "--width", "nan"], ["width"]),
        (["process", "inverse", "--width", "6", "--height", "0"], ["height"]),
        (["process", "inverse", "--width", "6", "--material", "unobtainium"], ["unobtainium", "inconel718-1.0mm"]),
        (["process", "forward", "--current", "140"], ["--speed"]),
        (["process", "forward", "--current", "0", "--speed", "1000"], ["current"]),
        (["process", "fit", "/nonexistent/beads.csv"], ["/nonexistent/beads.csv", "cannot read"]),
        (["bead", "critical-distance", "--model", "gauss"], ["gauss"]),
        (["bead", "critical-distance", "--aspect", "0.2"], ["--aspect", "arc"]),
        (["bead", "critical-distance", "--model", "arc", "--aspect", "0.7"], ["0.7"]),
        (["bead", "critical-distance", "--width", "-1"], ["--width"]),
        (["process"], ["SUBCOMMAND"]),
    ],
)
def test_bad_arguments(argv, needles, capsys):
    assert_one_line_error(*run(argv, capsys), *needles)


@pytest.mark.parametrize(
    "text,needles",
    [
        ("current_a,speed_mm_min,width_mm\n120,500,7.7\n", ["line 1", "missing column 'height_mm'"]),
        ("120,500,7.7,1.1\n140,500,9,1.2\n", ["line 1", "missing column", "header"]),
        ("current_a,speed_mm_min,width_mm,height_mm\n120,500,7.7,1.1\n140,fast,9.0,1.2\n", ["line 3", "column 'speed_mm_min'", "'fast'"]),
        ("current_a,speed_mm_min,width_mm,height_mm\n120,500,7.7\n", ["line 2", "3 fields", "header has 4"]),
        ("# comment\n\ncurrent_a,speed_mm_min,width_mm,height_mm\n120,500,7.7,0\n", ["line 4", "column 'height_mm'", "positive"]),
        ("current_a,speed_mm_min,width_mm,height_mm\n", ["no data rows"]),
        ("", ["empty file"]),
        ("current_a,speed_mm_min,width_mm,height_mm\n120,500,7.7,1.1\n120,600,7.3,1.0\n", ["at least 4"]),
        ("current_a,speed_mm_min,width_mm,height_mm\n120,500,7.7,inf\n", ["line 2", "finite"]),
    ],
)
def test_process_fit_csv_errors_name_file_line_and_column(tmp_path, text, needles, capsys):
    f = tmp_path / "beads.csv"
    f.write_text(text)
    assert_one_line_error(*run(["process", "fit", str(f)], capsys), str(f), *needles)


@pytest.mark.parametrize(
    "text,needles",
    [
        ("x,y\n0,1\n", ["line 1", "missing column 'x_mm'"]),
        ("x_mm,y_mm\n0,0\n1,0\n2,0\n", ["no point above the substrate"]),
        ("x_mm,y_mm\n0,1\n1,2\n2,1\n", ["at least 5"]),
        ("x_mm,y_mm\n0,1\n1,two\n", ["line 3", "column 'y_mm'", "'two'"]),
    ],
)
def test_bead_fit_csv_errors(tmp_path, text, needles, capsys):
    f = tmp_path / "profile.csv"
    f.write_text(text)
    assert_one_line_error(*run(["bead", "fit", str(f)], capsys), str(f), *needles)


def test_no_traceback_from_the_real_entry_point(tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_bytes(b"\xff\xfe\x00garbage")
    for argv in (
        ["process", "inverse", "--width", "10"],
        ["process", "fit", str(bad)],
        ["bead", "fit", str(tmp_path / "missing.csv")],
    ):
        p = subprocess.run(
            [sys.executable, "-m", "controller.cli.main", *argv], cwd=ROOT, capture_output=True, text=True, timeout=60
        )
        assert p.returncode == 2, p.stderr
        assert p.stdout == "" and "Traceback" not in p.stderr
        assert len(p.stderr.strip().splitlines()) == 1 and p.stderr.startswith("error: ")
