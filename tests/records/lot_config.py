"""A cell.yaml with a records: section of the test's choosing."""
from __future__ import annotations

from pathlib import Path

import yaml

from core.config import CONFIG_DIR


def cell_yaml(tmp: Path, **records: object) -> Path:
    cfg = yaml.safe_load((CONFIG_DIR / "cell.yaml").read_text())
    cfg["records"] = {**(cfg.get("records") or {}), **records}
    p = tmp / "cell.yaml"
    p.write_text(yaml.safe_dump(cfg))
    return p

