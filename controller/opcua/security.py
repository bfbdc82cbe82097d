"""Who may connect: loopback only, unless a certificate and users are configured (DESIGN.md §8)."""
from __future__ import annotations

import hashlib
import hmac
import ipaddress
import socket
from typing import Any
from urllib.parse import urlparse

from asyncua.crypto.permission_rules import User, UserRole
from asyncua.server.user_managers import UserManager

from core.errors import ConfigError


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


class PasswordUsers(UserManager):
    """Username/password users from cell.yaml (`opcua.users: {name: "sha256:…"}`); no anonymous."""

    def __init__(self, users: dict[str, str]) -> None:
        self._users = dict(users)

    def get_user(self, iserver: Any, username: str | None = None, password: str | None = None,
                 certificate: Any = None) -> User | None:
        if username is None or password is None or username not in self._users:
            return None
        if not hmac.compare_digest(password_hash(password), self._users[username]):
            return None
        return User(role=UserRole.User, name=username)
