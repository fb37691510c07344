"""Decoder messages kept off the terminal: OpenCV's log silenced and what the C decoders
(libjpeg, libpng) print on stderr captured while a file is decoded or written."""

from __future__ import annotations

import os
import tempfile
import threading
from contextlib import contextmanager
from typing import Iterator

import cv2

_quiet_lock = threading.Lock()
_quiet_depth = 0
_quiet_saved: dict = {}


@contextmanager
def quiet_decoder() -> Iterator[list]:
    """Silence OpenCV's log and send what the C decoders print on stderr (fd 2) to a temporary
    file while a decode runs; yields a list that receives the captured lines afterwards.

    Nested and concurrent uses share one redirection (the first to enter sets it up, the last
    to leave restores stderr), so decodes in several threads stay concurrent."""
    global _quiet_depth
    captured: list = []
    with _quiet_lock:
        if _quiet_depth == 0:
            _quiet_saved.clear()
            try:
                _quiet_saved["level"] = cv2.utils.logging.getLogLevel()
                cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
            except Exception:  # pragma: no cover - OpenCV without the logging module
                pass
            try:
                sink = tempfile.TemporaryFile()
                _quiet_saved["fd"] = os.dup(2)
                _quiet_saved["sink"] = sink
                os.dup2(sink.fileno(), 2)
            except OSError:  # no usable fd 2: leave stderr alone
                _quiet_saved.pop("fd", None)
        _quiet_depth += 1
    try:
        yield captured
    finally:
        with _quiet_lock:
            _quiet_depth -= 1
            sink = _quiet_saved.get("sink")
            if _quiet_depth == 0:
                if "fd" in _quiet_saved:
                    os.dup2(_quiet_saved["fd"], 2)
                    os.close(_quiet_saved["fd"])
                if "level" in _quiet_saved:
                    cv2.utils.logging.setLogLevel(_quiet_saved["level"])
                _quiet_saved.clear()
            if sink is not None:
                try:
                    sink.seek(0)
                    captured.extend(
                        line for line in sink.read().decode("utf-8", "replace").splitlines() if line.strip()
                    )
                except (OSError, ValueError):  # pragma: no cover
                    pass
                if _quiet_depth == 0:
                    sink.close()
