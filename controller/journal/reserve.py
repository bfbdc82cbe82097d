"""The journal's reserve: disk space held beside the journal for the rows of its own fault.

A full disk is a fault like a lost link (docs/contract.md §6): the first write that fails trips the
cell. The rows that say what the trip did (the interrupted bead, where its deposit ended, the
alarm, the verified safe stop) come after that write, so on a disk that stays full they would be
lost too, and a resume would re-arc from the last progress row the disk took: up to a status period
of travel and the move it lay on too early on a CNC (issue 38). The journal therefore holds
`RESERVE_BYTES` in a file of zeros next to it (`journal.reserve`, written out, not sparse), frees it
at the first failed write and writes that row again; the fault stands (its message names the free
space before the release). The file is removed when the journal is closed cleanly.
"""
from __future__ import annotations

import os
from pathlib import Path

# the rows after a trip: about 20 commits of a few 4 kB WAL pages each (measured 0.2 MB), doubled
RESERVE_BYTES = 512 * 1024


class Reserve:
    """`nbytes` of disk held at `path` until `release()`."""

    def __init__(self, path: Path, nbytes: int) -> None:
        self.path, self.nbytes = path, nbytes
        self.held = False

    def make(self) -> None:
        """Write the reserve out (OSError when the disk cannot hold it: the free-space check said it could)."""
        if self.nbytes <= 0:
            return
        with open(self.path, "wb") as fh:
            fh.write(b"\0" * self.nbytes)
            fh.flush()
            os.fsync(fh.fileno())
        self.held = True

    def release(self) -> bool:
        """Free the space (True when there was some to free)."""
        if not self.held:
            return False
        self.held = False
        try:
            self.path.unlink()
        except FileNotFoundError:
            return False
        return True
