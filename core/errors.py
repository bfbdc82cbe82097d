"""User-facing errors shared by every package: the CLI prints them as one `error:` line, exit 2."""


class CellError(Exception):
    """An error the user can act on; its message names the file, field or device and what to do."""


class ConfigError(CellError):
    """A configuration file is wrong: unknown/missing key, wrong type or unit, value out of range."""


class EnvelopeError(CellError):
    """A requested process point lies outside the material's process envelope."""


class MeshError(CellError):
    """A mesh cannot be planned: empty, open beyond repair, smaller than one bead."""


class InputError(CellError):
    """A data file or argument given on the command line is malformed."""


class Fault(CellError):
    """The cell stopped on a fault after it moved (a stall, a failed probe point, a build that
    stopped in Fault): exit 1, not the bad-input code. `state`: where the cell stood."""

    def __init__(self, message: str, *, state: str = "fault") -> None:
        super().__init__(message)
        self.state = state
