"""RLP/1, the robot link protocol (docs/contract.md §5): a pure frame codec, no I/O.

A frame is one ASCII line `BODY *CCCCCCCC\\n`, CCCCCCCC the CRC-32 (zlib) of BODY as 8
upper-case hex digits. Host data frames are `SSSS VERB ARGS` (SSSS: 16-bit upper-case hex
sequence number, wrapping FFFF -> 0000); control frames start with `!`. Robot frames are
ACK, NAK, EXE, MRK, ERR, HB and STA; after `!PROTO 2` (RLP/2, docs/protocols/rlp.md §9) also
`SACK` and `PROTO`. Number formats (docs/protocols/rlp.md): mm with exactly
3 decimals, tool-axis components and speed as integers when integral, else up to 6 / 3
decimals.
"""
from __future__ import annotations

import re
import zlib
from dataclasses import dataclass
from typing import Callable

SEQ_MOD = 1 << 16
MOTION_VERBS = ("MOVJ", "MOVL")
QUEUE_VERBS = ("MOVJ", "MOVL", "WAIT", "MARK")
CONTROL_VERBS = ("HOLD", "GO", "ABORT", "RESET", "STATUS")
PROTOCOLS = (1, 2)   # RLP/1 (go-back-N) and RLP/2 (selective repeat), negotiated by `!PROTO n`
SACK_SPAN = 128     # a SACK's mask covers the frames last_rx + 2 .. last_rx + 1 + SACK_SPAN
STATES = ("IDLE", "RUN", "WAIT", "HOLD", "FAULT")
NAK_REASONS = ("CRC", "SEQ", "FULL", "SYNTAX")
MAX_LINE = 200  # a longer line is garbage (a lost newline merged frames): SYNTAX

_NUM = r"-?\d+(?:\.\d+)?"
_NUM_RE = re.compile(rf"^{_NUM}$")
_SEQ_RE = re.compile(r"^[0-9A-F]{4}$")
_CRC_RE = re.compile(rb"^(.*) \*([0-9A-F]{8})$")
_PROTO_RE = re.compile(r"^PROTO [1-9][0-9]{0,2}$")
_MASK_RE = re.compile(r"^[0-9A-F]{1,32}$")


class FrameError(ValueError):
    """A line is not a valid frame; `reason` is the NAK reason (CRC or SYNTAX)."""

    def __init__(self, reason: str, detail: str = "") -> None:
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason = reason


# -- framing ------------------------------------------------------------------------------------


def crc(body: str | bytes) -> str:
    """CRC-32 (zlib) of the ASCII body as 8 upper-case hex digits."""
    b = body.encode("ascii") if isinstance(body, str) else body
    return f"{zlib.crc32(b) & 0xFFFFFFFF:08X}"


def encode(body: str) -> bytes:
    """The wire bytes of one frame: `BODY *CCCCCCCC\\n`."""
    b = body.encode("ascii")
    return b + b" *" + crc(b).encode("ascii") + b"\n"


def decode(line: bytes) -> str:
    """The body of one received line (with or without its newline); FrameError if bad."""
    line = line.rstrip(b"\r\n")
    if len(line) > MAX_LINE:
        raise FrameError("SYNTAX", "line too long")
    m = _CRC_RE.match(line)
    if m is None:
        raise FrameError("SYNTAX", "no ' *CCCCCCCC' trailer")
    body = m.group(1)
    if crc(body) != m.group(2).decode("ascii"):
        raise FrameError("CRC", "checksum mismatch")
    try:
        text = body.decode("ascii")
    except UnicodeDecodeError:
        raise FrameError("SYNTAX", "non-ASCII body") from None
    if not text or not text.isprintable():
        raise FrameError("SYNTAX", "empty or unprintable body")
    return text


# -- sequence arithmetic ---------------------------------------------------------------------------


def seq_add(seq: int, n: int) -> int:
    return (seq + n) % SEQ_MOD


def seq_diff(a: int, b: int) -> int:
    """Signed distance a - b on the 16-bit circle, in [-32768, 32767]."""
    d = (a - b) % SEQ_MOD
    return d - SEQ_MOD if d >= SEQ_MOD // 2 else d


def unwrap(seq: int, ref_ticket: int) -> int:
    """The ticket (unwrapped int) with low 16 bits `seq` nearest to `ref_ticket`."""
    return ref_ticket + seq_diff(seq, ref_ticket % SEQ_MOD)


def seq_hex(seq: int) -> str:
    return f"{seq % SEQ_MOD:04X}"


# -- number formats ----------------------------------------------------------------------------


def fmt_mm(v: float) -> str:
    s = f"{v:.3f}"
    return "0.000" if s == "-0.000" else s


def _fmt_trim(v: float, places: int) -> str:
    s = f"{v:.{places}f}".rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s


def fmt_unit(v: float) -> str:
    return _fmt_trim(v, 6)


def fmt_speed(v: float) -> str:
    return _fmt_trim(v, 3)


# -- host frames --------------------------------------------------------------------------------


@dataclass(frozen=True)
class Move:
    """A queued host frame: MOVJ/MOVL with target, tool axis and speed; WAIT; MARK n."""

    seq: int
    verb: str
    target: tuple[float, float, float] | None = None
    axis: tuple[float, float, float] | None = None
    speed: float | None = None
    mark: int | None = None


def move_body(seq: int, verb: str, *args: float) -> str:
    """The body of a host data frame; raises ValueError for a wrong verb or argument count."""
    verb = verb.upper()
    if verb in MOTION_VERBS:
        if len(args) != 7:
            raise ValueError(f"{verb} takes x y z i j k v (7 numbers), got {len(args)}")
        x, y, z, i, j, k, v = (float(a) for a in args)
        if not v > 0:
            raise ValueError(f"{verb} speed must be positive, got {v}")
        parts = [fmt_mm(x), fmt_mm(y), fmt_mm(z), fmt_unit(i), fmt_unit(j), fmt_unit(k), fmt_speed(v)]
    elif verb == "WAIT":
        if args:
            raise ValueError("WAIT takes no arguments")
        parts = []
    elif verb == "MARK":
        if len(args) != 1 or int(args[0]) != args[0] or int(args[0]) < 0:
            raise ValueError("MARK takes one non-negative integer")
        parts = [str(int(args[0]))]
    else:
        raise ValueError(f"unknown verb {verb!r}; one of {', '.join(QUEUE_VERBS)}")
    return " ".join([seq_hex(seq), verb, *parts])


def encode_move(seq: int, verb: str, *args: float) -> bytes:
    return encode(move_body(seq, verb, *args))


def parse_host(body: str) -> Move | str:
    """A host body as a Move, or the control verb (`HOLD`, ...) of a `!` frame; FrameError(SYNTAX)."""
    if body.startswith("!"):
        verb = body[1:]
        if _PROTO_RE.match(verb):
            return verb  # "PROTO n": the host asks for protocol version n (RLP/2 §9)
        if verb not in CONTROL_VERBS:
            raise FrameError("SYNTAX", f"unknown control frame {body!r}")
        return verb
    tok = body.split(" ")
    if len(tok) < 2 or not _SEQ_RE.match(tok[0]):
        raise FrameError("SYNTAX", "expected 'SSSS VERB ...'")
    seq, verb, args = int(tok[0], 16), tok[1], tok[2:]
    if verb in MOTION_VERBS:
        if len(args) != 7 or not all(_NUM_RE.match(a) for a in args):
            raise FrameError("SYNTAX", f"{verb} takes 7 numbers")
        x, y, z, i, j, k, v = (float(a) for a in args)
        n = (i * i + j * j + k * k) ** 0.5
        if not v > 0 or abs(n - 1.0) > 1e-3:
            raise FrameError("SYNTAX", "speed must be > 0 and the tool axis a unit vector")
        return Move(seq, verb, (x, y, z), (i, j, k), v)
    if verb == "WAIT" and not args:
        return Move(seq, verb)
    if verb == "MARK" and len(args) == 1 and args[0].isdigit():
        return Move(seq, verb, mark=int(args[0]))
    raise FrameError("SYNTAX", f"bad verb or arguments {verb!r}")


# -- robot frames -------------------------------------------------------------------------------


@dataclass(frozen=True)
class Reply:
    """A robot frame: kind in ACK NAK EXE MRK ERR HB STA with its fields (unused ones None)."""

    kind: str
    seq: int | None = None
    credits: int | None = None
    reason: str | None = None
    n: int | None = None
    code: int | None = None
    text: str | None = None
    state: str | None = None
    last_rx: int | None = None
    last_exec: int | None = None
    queue_free: int | None = None
    pos: tuple[float, float, float] | None = None
    mask: int | None = None   # SACK: bit i set = frame seq + 2 + i is held


def ack(seq: int, credits: int) -> str:
    return f"ACK {seq_hex(seq)} {credits}"


def nak(seq: int, reason: str) -> str:
    return f"NAK {seq_hex(seq)} {reason}"


def sack(seq: int, credits: int, mask: int) -> str:
    """RLP/2: cumulative ACK of `seq` and the frames held beyond the gap after it: bit i of
    `mask` (upper-case hex, no leading zeros) is frame seq + 2 + i (seq + 1 is the one missing)."""
    return f"SACK {seq_hex(seq)} {credits} {mask & ((1 << SACK_SPAN) - 1):X}"


def proto(version: int) -> str:
    return f"PROTO {version}"


def exe(seq: int) -> str:
    return f"EXE {seq_hex(seq)}"


def sta(state: str, last_rx: int, last_exec: int, queue_free: int, pos: tuple[float, float, float]) -> str:
    return f"STA {state} {seq_hex(last_rx)} {seq_hex(last_exec)} {queue_free} " + " ".join(fmt_mm(p) for p in pos)


def _reply_ack(tok: list[str]) -> Reply | None:
    if len(tok) == 3 and _SEQ_RE.match(tok[1]):
        return Reply("ACK", seq=int(tok[1], 16), credits=int(tok[2]))
    return None


def _reply_sack(tok: list[str]) -> Reply | None:
    if len(tok) == 4 and _SEQ_RE.match(tok[1]) and _MASK_RE.match(tok[3]):
        return Reply("SACK", seq=int(tok[1], 16), credits=int(tok[2]), mask=int(tok[3], 16))
    return None


def _reply_proto(tok: list[str]) -> Reply | None:
    if len(tok) == 2 and tok[1].isdigit():
        return Reply("PROTO", n=int(tok[1]))
    return None


def _reply_nak(tok: list[str]) -> Reply | None:
    if len(tok) == 3 and _SEQ_RE.match(tok[1]) and tok[2] in NAK_REASONS:
        return Reply("NAK", seq=int(tok[1], 16), reason=tok[2])
    return None


def _reply_exe(tok: list[str]) -> Reply | None:
    if len(tok) == 2 and _SEQ_RE.match(tok[1]):
        return Reply("EXE", seq=int(tok[1], 16))
    return None


def _reply_count(tok: list[str]) -> Reply | None:
    """MRK n, HB n."""
    if len(tok) == 2:
        return Reply(tok[0], n=int(tok[1]))
    return None


def _reply_err(tok: list[str]) -> Reply | None:
    if len(tok) >= 2:
        return Reply("ERR", code=int(tok[1]), text=" ".join(tok[2:]))
    return None


def _reply_sta(tok: list[str]) -> Reply | None:
    if len(tok) == 8 and tok[1] in STATES and _SEQ_RE.match(tok[2]) and _SEQ_RE.match(tok[3]):
        return Reply("STA", state=tok[1], last_rx=int(tok[2], 16), last_exec=int(tok[3], 16),
                     queue_free=int(tok[4]), pos=(float(tok[5]), float(tok[6]), float(tok[7])))
    return None


# reply kind -> its parser (None: the tokens do not make that reply)
_REPLY_PARSERS: dict[str, Callable[[list[str]], Reply | None]] = {
    "ACK": _reply_ack, "NAK": _reply_nak, "EXE": _reply_exe, "MRK": _reply_count, "HB": _reply_count,
    "ERR": _reply_err, "STA": _reply_sta, "SACK": _reply_sack, "PROTO": _reply_proto,
}


def parse_reply(body: str) -> Reply:
    """A robot body as a Reply; FrameError(SYNTAX) if it is not one."""
    tok = body.split(" ")
    parse = _REPLY_PARSERS.get(tok[0])
    try:
        reply = parse(tok) if parse is not None else None
    except ValueError:
        reply = None
    if reply is None:
        raise FrameError("SYNTAX", f"not a robot frame: {body!r}")
    return reply


class LineSplitter:
    """Reassembles lines from arbitrary byte chunks; an overlong partial line is cut off."""

    def __init__(self, max_line: int = MAX_LINE) -> None:
        self._buf = bytearray()
        self._max = max_line

    def feed(self, data: bytes) -> list[bytes]:
        self._buf += data
        if b"\n" not in data:
            if len(self._buf) > self._max * 2:  # garbage without newline: keep the tail only
                del self._buf[: -self._max]
            return []
        *lines, rest = self._buf.split(b"\n")
        self._buf = bytearray(rest)
        return [bytes(x) for x in lines]
