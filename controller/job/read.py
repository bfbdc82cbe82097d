"""Reading a job file (cell-job/1 JSON) from disk, with the user-facing errors."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, TypeAlias

from core.errors import InputError

JobJSON: TypeAlias = dict[str, Any]
"""A job file's JSON object (cell-job/1) as read, before it is checked: the values are JSON."""


def read_job(path: str | Path) -> JobJSON:
    """The JSON object of a job file; InputError naming the file if unreadable or not an object."""
    p = Path(path)
    try:
        job = json.loads(p.read_text(encoding="utf-8"))
    except UnicodeDecodeError as exc:
        raise InputError(f"{p}: not UTF-8 text (byte {exc.start}); not a cell-job/1 file") from None
    except RecursionError:
        raise InputError(f"{p}: nested too deeply; not a cell-job/1 file") from None
    except OSError as exc:
        raise InputError(f"{p}: cannot read the job ({exc.strerror or exc}); check the path") from None
    except json.JSONDecodeError as exc:
        raise InputError(f"{p}: line {exc.lineno}: not valid JSON ({exc.msg})") from None
    if not isinstance(job, dict):
        raise InputError(f"{p}: not a cell-job/1 file")
    return job
