"""Pure parsing and formatting of the grbl 1.1 serial interface (no I/O).

Lines a grbl 1.1 controller sends, one per `\\r\\n`-terminated line:
`ok`, `error:N`, `ALARM:N`, status reports `<Idle|MPos:x,y,z,a,b|FS:f,s|Pn:P>`, probe results
`[PRB:x,y,z,a,b:1]`, feedback `[MSG:…]`, `[GC:…]`, `[VER:…]`, `[OPT:…]`, settings `$N=V`,
and the welcome banner `Grbl 1.1h ['$' for help]`. Machines with fewer axes (plain grbl: XYZ)
report fewer coordinates; positions are padded to the five axes x, y, z, a, b with 0.0.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field

AXES = ("x", "y", "z", "a", "b")
Pos5 = tuple[float, float, float, float, float]

# Real-time command bytes: picked out of the stream by grbl's serial ISR, never buffered.
RT_STATUS = b"?"
RT_FEED_HOLD = b"!"
RT_CYCLE_START = b"~"
RT_SOFT_RESET = b"\x18"

# grbl 1.1 error codes (doc/csv/error_codes_en_US.csv of the grbl repository).
ERRORS: dict[int, str] = {
    1: "G-code words consist of a letter and a value. Letter was not found.",
    2: "Numeric value format is not valid or missing an expected value.",
    3: "Grbl '$' system command was not recognized or supported.",
    4: "Negative value received for an expected positive value.",
    5: "Homing cycle is not enabled via settings.",
    6: "Minimum step pulse time must be greater than 3usec.",
    7: "EEPROM read failed. Reset and restored to default values.",
    8: "Grbl '$' command cannot be used unless Grbl is IDLE. Ensures smooth operation during a job.",
    9: "G-code locked out during alarm or jog state.",
    10: "Soft limits cannot be enabled without homing also enabled.",
    11: "Max characters per line exceeded. Line was not processed and executed.",
    12: "Grbl '$' setting value exceeds the maximum step rate supported.",
    13: "Safety door detected as opened and door state initiated.",
    14: "Build info or startup line exceeded EEPROM line length limit.",
    15: "Jog target exceeds machine travel. Command ignored.",
    16: "Jog command with no '=' or contains prohibited g-code.",
    17: "Laser mode requires PWM output.",
    20: "Unsupported or invalid g-code command found in block.",
    21: "More than one g-code command from same modal group found in block.",
    22: "Feed rate has not yet been set or is undefined.",
    23: "G-code command in block requires an integer value.",
    24: "Two G-code commands that both require the use of the XYZ axis words were detected in the block.",
    25: "A G-code word was repeated in the block.",
    26: "A G-code command implicitly or explicitly requires XYZ axis words in the block, but none were detected.",
    27: "N line number value is not within the valid range of 1 - 9,999,999.",
    28: "A G-code command was sent, but is missing some required P or L value words in the line.",
    29: "Grbl supports six work coordinate systems G54-G59. G59.1, G59.2, and G59.3 are not supported.",
    30: "The G53 G-code command requires either a G0 seek or G1 feed motion mode to be active.",
    31: "There are unused axis words in the block and G80 motion mode cancel is active.",
    32: "A G2 or G3 arc was commanded but there are no XYZ axis words in the selected plane to trace the arc.",
    33: "The motion command has an invalid target.",
    34: "A G2 or G3 arc, traced with the radius definition, had a mathematical error when computing the arc geometry.",
    35: "A G2 or G3 arc, traced with the offset definition, is missing the IJK offset word in the selected plane.",
    36: "There are unused, leftover G-code words that aren't used by any command in the block.",
    37: "The G43.1 dynamic tool length offset command cannot apply an offset to an axis other than its configured axis.",
    38: "Tool number greater than max supported value.",
}

# grbl 1.1 alarm codes (doc/csv/alarm_codes_en_US.csv).
ALARMS: dict[int, str] = {
    1: "Hard limit triggered. Machine position is likely lost due to sudden and immediate halt. Re-homing is highly recommended.",
    2: "G-code motion target exceeds machine travel. Machine position safely retained. Alarm may be unlocked.",
    3: "Reset while in motion. Grbl cannot guarantee position. Lost steps are likely. Re-homing is highly recommended.",
    4: "Probe fail. The probe is not in the expected initial state before starting probe cycle.",
    5: "Probe fail. Probe did not contact the workpiece within the programmed travel for G38.2 and G38.4.",
    6: "Homing fail. Reset during active homing cycle.",
    7: "Homing fail. Safety door was opened during active homing cycle.",
    8: "Homing fail. Cycle failed to clear limit switch when pulling off. Try increasing pull-off setting or check wiring.",
    9: "Homing fail. Could not find limit switch within search distance.",
    10: "Homing fail. On dual axis machines, could not find the second limit switch for self-squaring.",
}

# Alarms after which the machine position cannot be trusted (re-home).
POSITION_LOST_ALARMS = frozenset({1, 3, 6, 7, 8, 9, 10})

STATES = ("Idle", "Run", "Hold", "Jog", "Alarm", "Door", "Check", "Home", "Sleep")


def error_meaning(code: int) -> str:
    return ERRORS.get(code, "unknown error code")


def alarm_meaning(code: int) -> str:
    return ALARMS.get(code, "unknown alarm code")


@dataclass(frozen=True)
class GrblStatus:
    """One status report. `state` is the main state (Idle, Run, Hold, Alarm, …), `substate` the
    number after the colon (Hold:0 = hold complete, Hold:1 = decelerating), mpos machine
    coordinates x, y, z, a, b (mm, degrees), feed in mm/min, spindle (laser/process power S)."""

    state: str
    mpos: Pos5
    feed: float = 0.0
    spindle: float = 0.0
    probe_tripped: bool = False
    substate: int | None = None
    pins: str = ""
    planner_free: int | None = None   # Bf: field (free planner blocks), when $10 asks for it
    rx_free: int | None = None        # Bf: field (free bytes in the serial RX buffer)
    wco: Pos5 | None = None
    axes: int = 3                     # how many coordinates the position field carried
    # A: field (accessories on: S spindle CW, C spindle CCW, F flood, M mist). grbl 1.1h prints
    # it only in the reports that carry Ov: (every 10-20 reports, and the first after a reset),
    # and leaves it out when nothing is on; grblHAL prints an empty `A:`. So "" means the report
    # said nothing is on, None that this report does not tell.
    accessories: str | None = None

    @property
    def spindle_on(self) -> bool | None:
        """The spindle / laser enable output as this report tells it (None: it does not)."""
        if self.accessories is None:
            return None
        return "S" in self.accessories or "C" in self.accessories


@dataclass(frozen=True)
class Ok:
    pass


@dataclass(frozen=True)
class Error:
    code: int

    @property
    def meaning(self) -> str:
        return error_meaning(self.code)


@dataclass(frozen=True)
class Alarm:
    code: int

    @property
    def meaning(self) -> str:
        return alarm_meaning(self.code)


@dataclass(frozen=True)
class Probe:
    """`[PRB:x,y,z,a,b:1]`: the machine position where the probe tripped (or stopped) and success."""

    position: Pos5
    success: bool


@dataclass(frozen=True)
class Banner:
    version: str  # e.g. "1.1h"
    name: str = "Grbl"  # "Grbl" or "GrblHAL"


@dataclass(frozen=True)
class Message:
    """A bracketed feedback line: kind is MSG, GC, VER, OPT, AXS, G54, TLO, … and text the rest."""

    kind: str
    text: str


@dataclass(frozen=True)
class Setting:
    number: int
    value: str


@dataclass(frozen=True)
class Other:
    text: str


Reply = Ok | Error | Alarm | GrblStatus | Probe | Banner | Message | Setting | Other

_BANNER = re.compile(r"^(Grbl(?:HAL)?)\s+(\S+)\s*\[.*\]")
_SETTING = re.compile(r"^\$(\d+)=(\S*)")
_FLOATS = re.compile(r"^-?\d+(?:\.\d*)?(?:,-?\d+(?:\.\d*)?)*$")


def _pos(text: str) -> Pos5:
    vals = [float(v) for v in text.split(",")]
    vals = (vals + [0.0] * 5)[:5]
    return (vals[0], vals[1], vals[2], vals[3], vals[4])


@dataclass
class _StatusFields:
    """What the `|`-separated fields after the state of one status report carry."""

    mpos: Pos5 | None = None
    wpos: Pos5 | None = None
    feed: float = 0.0
    spindle: float = 0.0
    pins: str = ""
    bf_planner: int | None = None
    bf_rx: int | None = None
    new_wco: Pos5 | None = None
    axes: int = 3
    overrides: bool = False
    acc: str | None = None

    def take(self, key: str, val: str) -> None:
        """Read one `key:val` field (unknown keys are ignored)."""
        if key in ("MPos", "WPos"):
            self._take_position(key, val)
        elif key in ("FS", "F"):
            self._take_feed(key, val)
        elif key == "Pn":
            self.pins = val
        elif key == "Bf":
            a, _, b = val.partition(",")
            self.bf_planner, self.bf_rx = int(a), int(b)
        elif key == "WCO":
            self.new_wco = _pos(val)
        elif key == "Ov":
            self.overrides = True
        elif key == "A":
            self.acc = val

    def _take_position(self, key: str, val: str) -> None:
        if key == "MPos":
            self.mpos = _pos(val)
        else:
            self.wpos = _pos(val)
        self.axes = val.count(",") + 1

    def _take_feed(self, key: str, val: str) -> None:
        if key == "F":
            self.feed = float(val)
            return
        parts = val.split(",")
        self.feed = float(parts[0])
        self.spindle = float(parts[1]) if len(parts) > 1 else 0.0


def _status_mpos(f: _StatusFields, wco: Pos5 | None, line: str) -> Pos5:
    """The machine position of a report: its MPos, else its WPos plus the work offset."""
    if f.mpos is not None:
        return f.mpos
    if f.wpos is None:
        raise ValueError(f"status report without a position: {line!r}")
    use_wco = f.new_wco or wco
    off = use_wco or (0.0,) * 5
    return tuple(w + o for w, o in zip(f.wpos, off))  # type: ignore[return-value]


def parse_status(line: str, wco: Pos5 | None = None) -> GrblStatus:
    """Parse `<State[:n]|MPos:…|FS:f,s|Pn:…|Bf:b,r|WCO:…>`; WPos is turned into MPos with `wco`."""
    body = line.strip()
    if not (body.startswith("<") and body.endswith(">")):
        raise ValueError(f"not a status report: {line!r}")
    fields = body[1:-1].split("|")
    head = fields[0]
    state, _, sub = head.partition(":")
    substate = int(sub) if sub.isdigit() else None
    f = _StatusFields()
    for item in fields[1:]:
        key, _, val = item.partition(":")
        f.take(key, val)
    mpos = _status_mpos(f, wco, line)
    return GrblStatus(
        state=state, mpos=mpos, feed=f.feed, spindle=f.spindle, probe_tripped="P" in f.pins,
        substate=substate, pins=f.pins, planner_free=f.bf_planner, rx_free=f.bf_rx, wco=f.new_wco,
        axes=f.axes, accessories=f.acc if f.acc is not None else ("" if f.overrides else None),
    )


def parse_probe(line: str) -> Probe:
    """Parse `[PRB:x,y,z(,a,b):s]`."""
    body = line.strip()
    if not (body.startswith("[PRB:") and body.endswith("]")):
        raise ValueError(f"not a probe report: {line!r}")
    coords, _, flag = body[5:-1].rpartition(":")
    return Probe(_pos(coords), flag.strip() == "1")


def parse_line(line: str, wco: Pos5 | None = None) -> Reply:
    """Classify and parse one line received from grbl (without its line ending)."""
    s = line.strip()
    if s == "ok":
        return Ok()
    if s.startswith("error:"):
        try:
            return Error(int(s[6:]))
        except ValueError:
            return Other(s)
    if s.startswith("ALARM:"):
        try:
            return Alarm(int(s[6:]))
        except ValueError:
            return Other(s)
    if s.startswith("<") and s.endswith(">"):
        try:
            return parse_status(s, wco)
        except ValueError:
            return Other(s)
    if s.startswith("[PRB:"):
        try:
            return parse_probe(s)
        except ValueError:
            return Other(s)
    if s.startswith("[") and s.endswith("]"):
        kind, _, text = s[1:-1].partition(":")
        return Message(kind, text)
    m = _BANNER.match(s)
    if m:
        return Banner(m.group(2), m.group(1))
    m = _SETTING.match(s)
    if m:
        return Setting(int(m.group(1)), m.group(2))
    return Other(s)


def fmt(v: float) -> str:
    """A coordinate as grbl prints it and as we send it (3 decimals, no '-0.000')."""
    s = f"{v:.3f}"
    return "0.000" if s == "-0.000" else s


def format_status(st: GrblStatus, *, report_buffer: bool = False, rx_free: int = 0, planner_free: int = 0) -> str:
    """The status report line a grbl 1.1 controller prints for `st` (used by the simulator).

    When `st.accessories` is not None the report carries `Ov:100,100,100` and, when anything
    is on, `A:` (as grbl 1.1h prints them in its override reports)."""
    head = st.state if st.substate is None else f"{st.state}:{st.substate}"
    parts = [head, "MPos:" + ",".join(fmt(v) for v in st.mpos)]
    if report_buffer:
        parts.append(f"Bf:{planner_free},{rx_free}")
    parts.append(f"FS:{st.feed:.0f},{st.spindle:.0f}")
    if st.pins:
        parts.append("Pn:" + st.pins)
    if st.accessories is not None:
        parts.append("Ov:100,100,100")
        if st.accessories:
            parts.append("A:" + st.accessories)
    return "<" + "|".join(parts) + ">"


def format_probe(pos: Pos5, success: bool) -> str:
    return "[PRB:" + ",".join(fmt(v) for v in pos) + (":1]" if success else ":0]")


@dataclass
class StreamResult:
    """What `CncLink.stream` did: lines sent and acknowledged, bytes, time and buffer use.

    `mean_in_flight_bytes` is the time-weighted mean of unacknowledged bytes in grbl's RX
    buffer as counted by the driver while streaming (the buffer is "kept full" when it stays
    close to `capacity_bytes`)."""

    lines: int = 0
    acked: int = 0
    bytes_sent: int = 0
    elapsed_s: float = 0.0
    capacity_bytes: int = 0
    mean_in_flight_bytes: float = 0.0
    max_in_flight_bytes: int = 0
    messages: list[str] = field(default_factory=list)


def clean_line(line: str) -> str:
    """A G-code line as streamed: comments `( )` and `;…` removed, whitespace stripped.

    grbl strips them too; removing them on the host side saves RX-buffer bytes."""
    out = []
    depth = 0
    for ch in line:
        if ch == ";" and depth == 0:
            break
        if ch == "(":
            depth += 1
        elif ch == ")" and depth:
            depth -= 1
        elif depth == 0 and ch not in "\r\n":
            out.append(ch)
    return "".join(out).strip()
