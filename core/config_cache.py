"""Validated configuration remembered between commands, for a fast start (issue 28).

Validating YAML takes PyYAML and pydantic (about 0.2 s of imports and parsing) for a handful of
numbers. A command that only reads a configuration (`cell plan`) asks `remembered(...)` for
what it needs: the answer is stored as JSON under a key made of the files' bytes and of the
code that validates them (core/config.py, core/material.py, this file, pydantic's version), so an
edited file, an edited model or another pydantic is a miss, validated as always and stored again.
A miss that fails (a ConfigError) is not stored: the next command reports it again.

Light on purpose: stdlib only (no yaml, no pydantic); `core.config` imports CONFIG_DIR and
`material_path` from here. The cache is `$CELL_CACHE_DIR`, else `$XDG_CACHE_HOME/cell`, else
`~/.cache/cell`; one can delete it at any time. Nothing is stored when it cannot be written.
"""
from __future__ import annotations

import functools
import hashlib
import json
import os
import sys
from pathlib import Path
from typing import Any, Callable, Sequence

from core.errors import ConfigError

CONFIG_DIR = Path(__file__).resolve().parent.parent / "config"
_CODE = ("config.py", "material.py", "config_cache.py")  # the validating code: part of every key


def material_path(name_or_path: str) -> Path:
    """A material by name (config/materials/NAME.yaml) or by a path to a YAML file."""
    p = Path(name_or_path)
    if p.suffix in (".yaml", ".yml") or p.exists():
        return p
    cand = CONFIG_DIR / "materials" / f"{name_or_path}.yaml"
    if not cand.exists():
        known = ", ".join(sorted(x.stem for x in (CONFIG_DIR / "materials").glob("*.yaml")))
        raise ConfigError(f"material '{name_or_path}' not found; known materials: {known}")
    return cand


def cache_dir() -> Path:
    env = os.environ.get("CELL_CACHE_DIR")
    if env:
        return Path(env)
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "cell"


@functools.lru_cache(maxsize=1)
def _code_digest() -> bytes:
    h = hashlib.sha256()
    here = Path(__file__).resolve().parent
    for name in _CODE:
        h.update((here / name).read_bytes())
    # pydantic's version file (found without importing pydantic): its validation is part of the answer
    for entry in map(Path, sys.path):
        ver = entry / "pydantic" / "version.py"
        if ver.is_file():
            h.update(ver.read_bytes())
            break
    return h.digest()


def remembered(tag: str, files: Sequence[Path], compute: Callable[[], dict[str, Any]]) -> dict[str, Any]:
    """`compute()` (a JSON-able dict made from validating `files`), from the cache when `files`,
    the code and `tag` are what they were when it was stored. A file that cannot be read is
    part of the key as missing (compute() then says what is wrong, and nothing is stored)."""
    h = hashlib.sha256(_code_digest())
    h.update(tag.encode())
    for f in files:
        try:
            data = Path(f).read_bytes()
        except OSError:
            return compute()
        h.update(len(data).to_bytes(8, "little"))
        h.update(data)
    path = cache_dir() / f"{tag}-{h.hexdigest()[:32]}.json"
    try:
        value = json.loads(path.read_bytes())
        if isinstance(value, dict):
            return value
    except (OSError, ValueError):
        pass
    value = compute()
    _store(path, value)
    return value


def _store(path: Path, value: dict[str, Any]) -> None:
    """Write atomically (a reader never sees half a file); any failure only costs the next start."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{os.getpid()}")
        tmp.write_text(json.dumps(value, allow_nan=False), encoding="utf-8")
        os.replace(tmp, path)
    except (OSError, ValueError, TypeError):
        pass


class Frozen:
    """Read-only attributes over a validated model's JSON dump (nested mappings are Frozen too),
    with `model_dump(mode="json")` giving that dump back: a pydantic model as the planner reads
    it, without pydantic. `hidden` holds fields the model leaves out of its dump."""

    __slots__ = ("_dump", "_all")

    def __init__(self, dump: dict[str, Any], hidden: dict[str, Any] | None = None) -> None:
        object.__setattr__(self, "_dump", dump)
        both = {**dump, **(hidden or {})}
        object.__setattr__(self, "_all", {k: Frozen(v) if isinstance(v, dict) else v for k, v in both.items()})

    def __getattr__(self, name: str) -> Any:
        try:
            return self._all[name]
        except KeyError:
            raise AttributeError(name) from None

    def __setattr__(self, name: str, value: Any) -> None:
        raise AttributeError(f"{name}: a validated configuration is read-only")

    def model_dump(self, mode: str = "json") -> dict[str, Any]:
        if mode != "json":
            raise ValueError("only the JSON dump is remembered")
        out: dict[str, Any] = json.loads(json.dumps(self._dump))
        return out

    def __repr__(self) -> str:
        return f"Frozen({self._dump!r})"
