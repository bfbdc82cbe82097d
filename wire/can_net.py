"""CAN buses that stay on this host unless cell.yaml allows the network (issue 13).

python-can's `udp_multicast` interface binds 0.0.0.0, joins its group on the default interface
and sends with a TTL of 1: weld commands would be reachable from (and sent to) the LAN. Unless
`devices.power_source.can.allow_network: true`, a udp_multicast bus is confined to loopback
(TTL 0, group joined and sent on 127.0.0.1 only, no other group's traffic), and interfaces that
can only reach another host (socketcand, remote) or a group that cannot be confined (IPv6)
are refused with an error naming the device and the key.
"""
from __future__ import annotations

import ipaddress
import socket
import struct
from typing import Any

from core.errors import ConfigError

KEY = "devices.power_source.can.allow_network"
NETWORK_ONLY = ("socketcand", "remote")   # python-can interfaces that talk to another host
IP_MULTICAST_ALL = 49                      # Linux: deliver only groups this socket joined


def check_channel(interface: str, channel: str, allow_network: bool, device: str = "power source") -> None:
    """ConfigError if this bus would leave the host and `allow_network` is not set."""
    if allow_network:
        return
    if interface in NETWORK_ONLY:
        raise ConfigError(f"{device}: CAN interface '{interface}' reaches another host; set {KEY}: true "
                          "in cell.yaml to allow weld commands on the network")
    if interface == "udp_multicast":
        try:
            group = ipaddress.ip_address(channel)
        except ValueError:
            raise ConfigError(f"{device}: CAN channel '{channel}' of udp_multicast is not a multicast "
                              f"group address; use e.g. 239.74.163.2 (or set {KEY}: true)") from None
        if group.version != 4 or not group.is_multicast:
            raise ConfigError(f"{device}: CAN channel '{channel}' cannot be kept on this host (an IPv4 "
                              f"multicast group can); set {KEY}: true in cell.yaml to allow the network")


def confine_to_loopback(bus: Any, channel: str) -> None:
    """Re-join a udp_multicast bus's group on loopback only, TTL 0 (never leaves the host)."""
    sock = getattr(getattr(bus, "_multicast", None), "_socket", None)
    if sock is None:
        raise ConfigError(f"CAN udp_multicast: cannot reach the bus's socket to keep it on loopback; set {KEY}")
    group = socket.inet_aton(channel)
    sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, struct.pack("@I", 0))
    sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton("127.0.0.1"))
    try:
        sock.setsockopt(socket.IPPROTO_IP, socket.IP_DROP_MEMBERSHIP, group + struct.pack("@I", socket.INADDR_ANY))
    except OSError:
        pass
    sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, group + socket.inet_aton("127.0.0.1"))
    try:
        sock.setsockopt(socket.IPPROTO_IP, IP_MULTICAST_ALL, 0)
    except OSError:
        pass


def open_bus(interface: str, channel: str, *, allow_network: bool = False, device: str = "power source",
             **kwargs: Any) -> Any:
    """A python-can Bus, refused or confined to this host unless the network is allowed."""
    # lazy: python-can loads only when this path runs (start-up time)
    import can

    check_channel(interface, channel, allow_network, device)
    if interface == "udp_multicast" and not allow_network:
        kwargs.setdefault("hop_limit", 0)
    bus = can.Bus(interface=interface, channel=channel, **kwargs)
    if interface == "udp_multicast" and not allow_network:
        try:
            confine_to_loopback(bus, channel)
        except BaseException:
            bus.shutdown()
            raise
    return bus


def socket_of(bus: Any) -> Any:
    """The UDP socket of a udp_multicast bus (tests read its options)."""
    return getattr(getattr(bus, "_multicast", None), "_socket", None)
