"""Per-item results kept in a JSON-lines file as they are computed, so that an evaluation resumes.

Each line is ``{"run": FINGERPRINT, "key": KEY, "record": {...}}``; on reading, only the lines of
the same fingerprint (what makes the results comparable: the models' weights and their file
dates, the options) count, so a rerun with other weights computes everything again. A line cut
short by an interruption is skipped.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Optional


def weights_fingerprint(path: Optional[str]) -> str:
    """``"bundled"`` or ``path`` with its size and modification time (a rewritten checkpoint differs)."""
    if path is None:
        return "bundled"
    try:
        st = os.stat(path)
        return f"{Path(path).resolve()}:{st.st_size}:{int(st.st_mtime)}"
    except OSError:
        return str(path)


class RecordFile:
    """The records of one run (``fingerprint``) in ``path`` (None: kept in memory only)."""

    def __init__(self, path: Optional[Path], fingerprint: dict):
        self.path = Path(path) if path is not None else None
        self.run = json.loads(json.dumps(fingerprint, sort_keys=True))
        self.records: dict[str, dict] = {}
        if self.path is not None and self.path.exists():
            for line in self.path.read_text().splitlines():
                try:
                    row = json.loads(line)
                except json.JSONDecodeError:
                    continue
                if isinstance(row, dict) and row.get("run") == self.run and "key" in row:
                    self.records[row["key"]] = row.get("record")

    def get(self, key: str) -> Optional[dict]:
        return self.records.get(key)

    def add(self, key: str, record: dict) -> None:
        self.records[key] = record
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            with open(self.path, "a") as f:
                f.write(json.dumps({"run": self.run, "key": key, "record": record}) + "\n")
