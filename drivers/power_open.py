"""`open_power_source` lives in drivers/registry.py now (one `open_*` per device kind); this
name stays until controller/cell.py calls the registry (issue 25)."""
from __future__ import annotations

from drivers.registry import open_power_source

__all__ = ["open_power_source"]
