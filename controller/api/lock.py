"""One controller per cell (docs/controller.md): the cell's lock, taken by every command that moves
a device (controller/runtime/cell_lock.py). Light on purpose: `early` runs before the heavy imports."""
from controller.runtime.cell_lock import CellInUse, CellLock, acquire, early

__all__ = ["CellInUse", "CellLock", "acquire", "early"]
