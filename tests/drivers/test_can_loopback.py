"""CAN over udp_multicast stays on this host unless cell.yaml allows the network (issue 13)."""
from __future__ import annotations

import socket
import struct

import pytest

from wire.can_net import KEY, check_channel, open_bus, socket_of
from drivers.power_can import CanPowerSource
from core.errors import ConfigError


def test_udp_multicast_bus_is_confined_to_loopback():
    bus = open_bus("udp_multicast", "239.74.163.77")
    try:
        s = socket_of(bus)
        assert struct.unpack("@I", s.getsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 4))[0] == 0
        assert s.getsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, 4) == socket.inet_aton("127.0.0.1")
    finally:
        bus.shutdown()


def test_two_confined_buses_still_talk_on_this_host():
    import can

    a, b = open_bus("udp_multicast", "239.74.163.78"), open_bus("udp_multicast", "239.74.163.78")
    try:
        a.send(can.Message(arbitration_id=0x201, data=b"\x01\x02", is_extended_id=False))
        got = None
        for _ in range(20):
            got = b.recv(0.1)
            if got is not None and got.arbitration_id == 0x201:
                break
        assert got is not None and bytes(got.data) == b"\x01\x02"
    finally:
        a.shutdown()
        b.shutdown()


@pytest.mark.parametrize("interface, channel", [("udp_multicast", "ff15:7079:7468:6f6e:6465:6d6f:6d63:6173"),
                                                ("socketcand", "can0"), ("udp_multicast", "not-a-group")])
def test_a_channel_that_leaves_the_host_is_refused_naming_device_and_key(interface, channel):
    with pytest.raises(ConfigError) as e:
        CanPowerSource(interface=interface, channel=channel, node=1)
    assert "power source" in str(e.value) and KEY in str(e.value)
    check_channel(interface, channel, True)  # allowed explicitly: no error
