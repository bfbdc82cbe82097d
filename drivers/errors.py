"""Device errors shared by every driver."""
from core.errors import CellError


class DeviceError(CellError):
    """A device refused a command or reported a fault; the message names the device and URL."""


class LinkLost(DeviceError):
    """A device went silent or its link dropped (timeouts, lost replies, closed port)."""


class DeviceTimeout(LinkLost):
    """A device did not answer within its timeout."""
