"""Configuration loading: every error names the file, the key path and the line."""
from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import given, settings, strategies as st

from core.config import CONFIG_DIR, load_cell, load_material, load_sim, parse_model
from core.errors import ConfigError
from core.material import Material


def test_shipped_configs_load():
    cell = load_cell()
    assert cell.devices.robot.url.startswith("socket://")
    assert cell.cell.time_scale > 0
    m = load_material("inconel718-1.0mm")
    # The paper's CONST.INS values (Ribeiro 1997, Table 4).
    r = m.ribeiro
    assert (r.ratio, r.k1, r.k2, r.k3, r.k4, r.k5, r.k6) == (0.11, 1.0, 0.968322, -0.41625, 9.7266925, 0.335683, -0.60296)
    assert (r.i_min_a, r.i_max_a, r.wfs_min_m_min, r.wfs_max_m_min) == (95, 160, 4.0, 7.4)
    assert load_material("er70s6-1.2mm").wire_diameter_mm == 1.2
    assert load_sim().cnc.probe_noise_mm >= 0


def test_unknown_key_names_file_path_and_line(tmp_path: Path):
    text = (CONFIG_DIR / "cell.yaml").read_text().replace("    baud: 115200\n    heartbeat_s", "    baud: 115200\n    heartbeat_ms", 1)
    f = tmp_path / "cell.yaml"
    f.write_text(text)
    line = next(i + 1 for i, l in enumerate(text.splitlines()) if "heartbeat_ms" in l)
    with pytest.raises(ConfigError) as e:
        load_cell(f)
    msg = str(e.value)
    assert str(f) in msg and "devices.robot.heartbeat_ms" in msg and f"line {line}:" in msg


def test_out_of_range_value_and_missing_key(tmp_path: Path):
    text = (CONFIG_DIR / "materials" / "inconel718-1.0mm.yaml").read_text()
    f = tmp_path / "m.yaml"
    f.write_text(text.replace("i_max_a: 160", "i_max_a: -160"))
    with pytest.raises(ConfigError, match=r"m\.yaml: line \d+: key 'ribeiro\.i_max_a'"):
        load_material(str(f))
    f.write_text(text.replace("  k4: 9.7266925\n", ""))
    with pytest.raises(ConfigError, match=r"missing key 'ribeiro\.k4'"):
        load_material(str(f))


def test_unknown_material_lists_known_ones():
    with pytest.raises(ConfigError, match="inconel718-1.0mm"):
        load_material("unobtainium")


_MAT_TEXT = (CONFIG_DIR / "materials" / "inconel718-1.0mm.yaml").read_text().splitlines()
_VALUE_LINES = [i for i, l in enumerate(_MAT_TEXT) if ":" in l and not l.strip().startswith("#") and l.split(":", 1)[1].split("#")[0].strip()]


@settings(max_examples=150, deadline=None)
@given(st.sampled_from(_VALUE_LINES), st.sampled_from(["-1", "abc", "[1, 2]", "{a: 1}", "1e9", "null", "''"]), st.booleans())
def test_any_single_corrupted_key_is_a_clear_error(idx, bad, rename):
    lines = list(_MAT_TEXT)
    key, rest = lines[idx].split(":", 1)
    lines[idx] = f"{key}_x: {rest}" if rename else f"{key}: {bad}"
    try:
        parse_model("\n".join(lines), Material, "mat.yaml")
    except ConfigError as exc:
        msg = str(exc)
        assert msg.startswith("mat.yaml: line ") and "key" in msg
    # Some corruptions are still valid values (e.g. a free-text name); those must load.


def test_a_key_given_twice_is_an_error_naming_its_line(tmp_path: Path):
    # YAML lets the last duplicate win silently: an operator's edit of the first would be ignored
    text = (CONFIG_DIR / "cell.yaml").read_text()
    text = text.replace("    cycle_ms: 10\n", "    cycle_ms: 10\n    cycle_ms: 20\n", 1)
    bad = tmp_path / "cell.yaml"
    bad.write_text(text)
    line = text.splitlines().index("    cycle_ms: 20") + 1
    with pytest.raises(ConfigError) as e:
        load_cell(bad)
    assert f"line {line}" in str(e.value) and "'cycle_ms' is given twice" in str(e.value)


def test_tools_are_validated_like_the_rest_of_the_config(tmp_path: Path):
    cell = load_cell()
    name, ball = cell.tools.cutter(cell.machining.cutter)
    assert (name, ball.type, ball.diameter_mm) == ("ball6", "ball", 6.0) and ball.spindle_rpm <= ball.max_rpm
    assert cell.tools.deposition.number not in {c.number for c in cell.tools.cutters.values()}
    text = (CONFIG_DIR / "cell.yaml").read_text()
    f = tmp_path / "cell.yaml"
    for bad, match in (("max_depth_of_cut_mm: 1.0, max_stepover_mm: 2.0", r"tools\.cutters\.ball6.*deeper than the flutes"),
                       ("rpm: 12000,", r"tools\.cutters\.ball6.*rpm 30000 is above max_rpm"),
                       ("cutter: ball6 ", r"machining\.cutter 'ball9' is not in tools\.cutters"),
                       ("{number: 2, type: flat", r"tool number 1 is also ball6's")):
        good = {"max_depth_of_cut_mm: 1.0, max_stepover_mm: 2.0": "max_depth_of_cut_mm: 20, max_stepover_mm: 2.0",
                "rpm: 12000,": "rpm: 30000,", "cutter: ball6 ": "cutter: ball9 ",
                "{number: 2, type: flat": "{number: 1, type: flat"}[bad]
        f.write_text(text.replace(bad, good, 1))
        with pytest.raises(ConfigError, match=match) as e:
            load_cell(f)
        assert str(f) in str(e.value) and "line " in str(e.value)
