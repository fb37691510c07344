"""Warnings, the JSON files and the table of a reconstruction.

:func:`warn` prints one ``warning: ...`` line to stderr and keeps it in the warnings that
:func:`collecting_warnings` gathers (the summary lists them), so a result that should not be
trusted is flagged both on the terminal and in ``summary.json``.
"""

from __future__ import annotations

import contextlib
import contextvars
import json
import math
import sys
import warnings
from pathlib import Path
from typing import Iterator

from ..core.outputs import write_text

_COLLECTED: contextvars.ContextVar = contextvars.ContextVar("sfm_warnings", default=None)


def warn(message: str) -> None:
    """Print ``warning: <message>`` (one line) to stderr and keep it for the summary."""
    line = " ".join(str(message).split())
    print(f"warning: {line}", file=sys.stderr, flush=True)
    kept = _COLLECTED.get()
    if kept is not None:
        kept.append(line)


@contextlib.contextmanager
def collecting_warnings() -> Iterator[list]:
    """Within the block, every :func:`warn` is also appended to the yielded list, and so is every
    Python ``UserWarning`` that localscale's code raises (a 16-bit image rescaled, an alpha channel
    dropped: printed as a ``warning:`` line, once per message); other warnings are shown as before."""
    kept: list = []
    token = _COLLECTED.set(kept)
    seen: set = set()
    package = str(Path(__file__).resolve().parent.parent)
    with warnings.catch_warnings():
        previous = warnings.showwarning

        def show(message, category, filename, lineno, file=None, line=None):
            if not (issubclass(category, UserWarning) and str(Path(filename).resolve()).startswith(package)):
                return previous(message, category, filename, lineno, file, line)
            text = " ".join(str(message).split())
            if text not in seen:
                seen.add(text)
                warn(text)

        warnings.showwarning = show
        try:
            yield kept
        finally:
            _COLLECTED.reset(token)


def no_model_reason(summary: dict) -> str:
    """Why a run made no model, from its summary's verified pairs."""
    v, p = summary["pairs_verified"], summary["pairs"]
    return f"{v} of {p} pairs verified, none with enough inliers at a wide enough angle" if v else "no pair verified"


def _jsonable(value):
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    if hasattr(value, "item") and getattr(value, "ndim", 1) == 0:  # numpy scalars
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def write_json(path, data: dict) -> Path:
    """``data`` as indented JSON, written atomically (non-finite floats as null)."""
    return write_text(path, json.dumps(_jsonable(data), indent=2) + "\n")


def read_json(path) -> dict:
    with open(path, encoding="utf-8") as f:
        return json.load(f)
