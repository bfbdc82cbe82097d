"""Device errors shared by every driver."""
from core.errors import CellError


class DeviceError(CellError):
    """A device refused a command or reported a fault; the message names the device and URL."""


class LinkLost(DeviceError):
    """A device went silent or its link dropped (timeouts, lost replies, closed port).

    `reason` is the cause alone (e.g. "socket disconnected"), without the device and URL the
    message names; a driver that drops its link on it words its own message around it.
    """

    def __init__(self, message: str, *, reason: str | None = None) -> None:
        super().__init__(message)
        self.reason = message if reason is None else reason


class DeviceTimeout(LinkLost):
    """A device did not answer within its timeout."""
