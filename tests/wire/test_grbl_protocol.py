"""The grbl 1.1 line parser: what real firmware prints, parsed the way the driver needs it."""
from __future__ import annotations

import pytest

from wire.grbl_protocol import (
    Alarm, Banner, Error, GrblStatus, Message, Ok, Other, Probe, Setting, alarm_meaning, clean_line,
    error_meaning, format_probe, format_status, parse_line, parse_probe, parse_status,
)


def test_status_report_five_axes_with_probe_pin():
    st = parse_status("<Idle|MPos:12.500,-3.250,0.000,45.000,-10.000|FS:0,0|Pn:P>")
    assert st.state == "Idle"
    assert st.mpos == (12.5, -3.25, 0.0, 45.0, -10.0)
    assert st.probe_tripped is True
    assert (st.feed, st.spindle) == (0.0, 0.0)


def test_status_report_of_plain_three_axis_grbl_is_padded():
    # A stock grbl 1.1 board reports three axes; the driver must work with it unchanged.
    st = parse_status("<Run|MPos:1.000,2.000,3.000|FS:500,8000|Ov:100,100,100>")
    assert st.mpos == (1.0, 2.0, 3.0, 0.0, 0.0)
    assert st.state == "Run" and st.feed == 500.0 and st.spindle == 8000.0
    assert st.probe_tripped is False


def test_hold_substate_and_buffer_field():
    st = parse_status("<Hold:1|MPos:0.000,0.000,0.000,0.000,0.000|Bf:3,97|FS:1200,0>")
    assert (st.state, st.substate) == ("Hold", 1)
    assert (st.planner_free, st.rx_free) == (3, 97)
    assert parse_status("<Hold:0|MPos:0,0,0|FS:0,0>").substate == 0


def test_wpos_is_turned_into_machine_position_with_wco():
    st = parse_status("<Idle|WPos:1.000,1.000,1.000|FS:0,0|WCO:10.000,20.000,-5.000>")
    assert st.mpos == (11.0, 21.0, -4.0, 0.0, 0.0)
    later = parse_line("<Idle|WPos:0.000,0.000,0.000|FS:0,0>", wco=st.wco)
    assert isinstance(later, GrblStatus) and later.mpos == (10.0, 20.0, -5.0, 0.0, 0.0)


def test_probe_reports():
    ok = parse_probe("[PRB:10.000,20.000,-3.217,0.000,0.000:1]")
    assert ok.position == (10.0, 20.0, -3.217, 0.0, 0.0) and ok.success
    miss = parse_line("[PRB:0.000,0.000,-20.000:0]")
    assert isinstance(miss, Probe) and not miss.success and miss.position[2] == -20.0


@pytest.mark.parametrize("text, kind", [
    ("ok", Ok), ("error:9", Error), ("ALARM:5", Alarm), ("Grbl 1.1h ['$' for help]", Banner),
    ("[MSG:Caution: Unlocked]", Message), ("[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]", Message),
    ("$110=6000.000", Setting), ("garbage", Other), ("error:x", Other),
])
def test_line_classification(text, kind):
    assert isinstance(parse_line(text), kind)


def test_codes_carry_grbl_meanings():
    assert isinstance(parse_line("error:20"), Error) and parse_line("error:20").code == 20
    assert "locked out during alarm" in error_meaning(9)
    assert "Max characters per line" in error_meaning(11)
    assert "not in the expected initial state" in alarm_meaning(4)
    assert "did not contact the workpiece" in alarm_meaning(5)
    assert "Reset while in motion" in alarm_meaning(3)
    assert parse_line("Grbl 1.1h ['$' for help]").version == "1.1h"
    assert parse_line("[MSG:Caution: Unlocked]").text == "Caution: Unlocked"


def test_clean_line_strips_comments_and_whitespace():
    assert clean_line("G1 X10 (move) Y5 ; to the corner\r\n") == "G1 X10  Y5"
    assert clean_line("(only a comment)") == ""
    assert clean_line("  ; nothing  ") == ""


def test_simulator_formats_round_trip_through_the_parser():
    st = GrblStatus("Run", (1.5, -2.0, -0.0004, 90.0, 0.0), feed=1500, spindle=200, probe_tripped=True, pins="P")
    line = format_status(st, report_buffer=True, rx_free=100, planner_free=7)
    assert line == "<Run|MPos:1.500,-2.000,0.000,90.000,0.000|Bf:7,100|FS:1500,200|Pn:P>"
    back = parse_status(line)
    assert back.mpos == (1.5, -2.0, 0.0, 90.0, 0.0) and back.probe_tripped and back.rx_free == 100
    assert format_probe((1.0, 2.0, 3.0, 0.0, 0.0), True) == "[PRB:1.000,2.000,3.000,0.000,0.000:1]"
