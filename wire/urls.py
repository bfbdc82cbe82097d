"""Device URLs of cell.yaml, parsed once for the drivers and the simulators."""
from __future__ import annotations

from urllib.parse import urlsplit

from core.errors import ConfigError


def parse_tcp_url(url: str) -> tuple[str, int]:
    """`tcp://host:port` -> (host, port); anything else is a ConfigError naming the URL."""
    parts = urlsplit(url)
    if parts.scheme != "tcp" or not parts.hostname or parts.port is None:
        raise ConfigError(f"device URL '{url}' is not tcp://host:port")
    return parts.hostname, parts.port
