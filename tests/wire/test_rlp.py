"""RLP/1 frame codec: the exact bytes of docs/contract.md §5, CRC checking, sequence arithmetic."""
from __future__ import annotations

import zlib

import pytest
from hypothesis import given
from hypothesis import strategies as st

from wire import rlp


def test_design_example_frame_bytes():
    body = "002A MOVL 120.000 45.500 3.000 0 0 1 1500"
    assert rlp.move_body(0x2A, "MOVL", 120, 45.5, 3, 0, 0, 1, 1500) == body
    want = f"{zlib.crc32(body.encode()) & 0xFFFFFFFF:08X}"
    assert rlp.encode_move(0x2A, "MOVL", 120, 45.5, 3, 0, 0, 1, 1500) == f"{body} *{want}\n".encode()
    assert rlp.crc(body) == "10A993E9"


def test_decode_checks_crc_and_trailer():
    frame = rlp.encode("ACK 0007 12")
    assert rlp.decode(frame) == "ACK 0007 12"
    bad = bytearray(frame)
    bad[5] ^= 0x01  # one flipped bit in the body
    with pytest.raises(rlp.FrameError) as exc:
        rlp.decode(bytes(bad))
    assert exc.value.reason == "CRC"
    with pytest.raises(rlp.FrameError) as exc:
        rlp.decode(b"ACK 0007 12\n")
    assert exc.value.reason == "SYNTAX"
    with pytest.raises(rlp.FrameError) as exc:  # lower-case hex is not the format
        rlp.decode(f"ACK 0007 12 *{rlp.crc('ACK 0007 12').lower()}\n".encode())
    assert exc.value.reason == "SYNTAX"


def test_sequence_wraps_and_unwraps():
    assert rlp.seq_hex(0x1_0000 + 5) == "0005"
    assert rlp.seq_add(0xFFFF, 1) == 0
    assert rlp.seq_diff(0x0002, 0xFFFE) == 4
    assert rlp.seq_diff(0xFFFE, 0x0002) == -4
    # tickets past 65535 map back from their wire seq
    assert rlp.unwrap(0x0003, 0xFFFA) == 0x1_0003
    assert rlp.unwrap(0xFFFA, 0x1_0003) == 0xFFFA
    assert rlp.unwrap(0x0010, 5 * 65536 + 0x0008) == 5 * 65536 + 0x0010


def test_host_frames_parse():
    m = rlp.parse_host(rlp.move_body(7, "MOVJ", -1.25, 2, 3, 0, 0.6, 0.8, 1500.5))
    assert (m.seq, m.verb, m.target, m.axis, m.speed) == (7, "MOVJ", (-1.25, 2.0, 3.0), (0.0, 0.6, 0.8), 1500.5)
    assert rlp.parse_host("0009 MARK 12").mark == 12
    assert rlp.parse_host("000A WAIT").verb == "WAIT"
    assert rlp.parse_host("!HOLD") == "HOLD"
    for body in ("0009 MOVL 1 2 3 0 0 1", "zz01 WAIT", "0001 JUMP", "!FLY", "0001 MOVL 1 2 3 0 0 2 100",
                 "0001 MOVL 1 2 3 0 0 1 0"):
        with pytest.raises(rlp.FrameError):
            rlp.parse_host(body)


def test_robot_frames_parse():
    r = rlp.parse_reply(rlp.sta("HOLD", 0x1234, 0x1230, 60, (1.0, -2.5, 3.0)))
    assert (r.state, r.last_rx, r.last_exec, r.queue_free, r.pos) == ("HOLD", 0x1234, 0x1230, 60, (1.0, -2.5, 3.0))
    assert rlp.parse_reply("NAK 0010 CRC").reason == "CRC"
    assert rlp.parse_reply("ERR 10 target outside workspace").text == "target outside workspace"
    with pytest.raises(rlp.FrameError):
        rlp.parse_reply("NAK 0010 BECAUSE")


def test_move_arguments_are_checked():
    with pytest.raises(ValueError):
        rlp.move_body(1, "MOVL", 1, 2, 3)
    with pytest.raises(ValueError):
        rlp.move_body(1, "MOVL", 1, 2, 3, 0, 0, 1, -5)
    with pytest.raises(ValueError):
        rlp.move_body(1, "SPIN")


def test_splitter_reassembles_chunks():
    s = rlp.LineSplitter()
    data = rlp.encode("HB 1") + rlp.encode("HB 2")
    got = [line for i in range(len(data)) for line in s.feed(data[i:i + 1])]
    assert [rlp.decode(x) for x in got] == ["HB 1", "HB 2"]


@given(st.integers(0, 0xFFFF), st.sampled_from(["MOVJ", "MOVL"]),
       st.lists(st.floats(-2000, 2000, allow_nan=False), min_size=3, max_size=3),
       st.floats(0.1, 20000, allow_nan=False))
def test_move_roundtrip(seq, verb, xyz, v):
    frame = rlp.encode_move(seq, verb, *xyz, 0, 0, 1, v)
    m = rlp.parse_host(rlp.decode(frame))
    assert m.seq == seq and m.verb == verb
    assert all(abs(a - b) <= 0.0005 for a, b in zip(m.target, xyz))
    assert abs(m.speed - v) <= 0.0005
