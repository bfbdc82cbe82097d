"""What the OPC UA server is told, without importing asyncua: who it is, where it listens and
whether that endpoint may serve (loopback only, unless a certificate and users are configured;
docs/contract.md §8). The controller's process imports only this; asyncua lives in the server's process.
"""
from __future__ import annotations

import hashlib
import ipaddress
import socket
from dataclasses import dataclass
from urllib.parse import urlparse

from core.config import OpcUaSettings
from core.errors import ConfigError

PUBLISH_PERIOD_S = 0.05   # process values at 20 Hz at least; any snapshot change wakes it sooner
# How long the server may take to come up (asyncua's address space built, the endpoint bound):
# seconds on a loaded host. One bound for the server's own thread and for the controller waiting
# on the child process that runs it (the child's was 15 s, under the controller's 30: under load
# the child gave up first, "did not start within 15 s", while the controller would have waited).
START_TIMEOUT_S = 30.0


@dataclass(frozen=True)
class Identification:
    manufacturer: str
    model: str
    serial_number: str
    software_revision: str


def endpoint_host(endpoint: str) -> tuple[str, int]:
    """(host, port) of an `opc.tcp://host:port/path` endpoint; ConfigError naming the key if malformed."""
    u = urlparse(endpoint)
    try:
        port = u.port or 4840
    except ValueError:
        raise ConfigError(f"opcua.endpoint {endpoint!r}: the port is not a number in 1…65535") from None
    if u.scheme != "opc.tcp" or not u.hostname:
        raise ConfigError(f"opcua.endpoint {endpoint!r}: expected opc.tcp://HOST:PORT/PATH")
    return u.hostname, port


def is_loopback(host: str) -> bool:
    """Whether every address the host name resolves to is a loopback address."""
    try:
        infos = socket.getaddrinfo(host, None)
    except OSError:
        return False
    return all(ipaddress.ip_address(i[4][0]).is_loopback for i in infos)


def password_hash(password: str) -> str:
    """The form users' passwords take in cell.yaml: `sha256:<hex>`."""
    return "sha256:" + hashlib.sha256(password.encode()).hexdigest()


def check_endpoint(opcua: OpcUaSettings) -> bool:
    """Whether the endpoint is secured; ConfigError when it leaves the host unsecured."""
    secured = bool(opcua.certificate and opcua.private_key and opcua.users)
    host, _port = endpoint_host(opcua.endpoint)
    if not secured and not is_loopback(host):
        raise ConfigError(f"opcua.endpoint {opcua.endpoint!r} leaves the host: serve it on 127.0.0.1, "
                          "or configure opcua.certificate, opcua.private_key and opcua.users")
    return secured
