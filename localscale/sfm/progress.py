"""Progress bars of the long steps (tqdm on stderr)."""

from __future__ import annotations


def progress(items, desc: str, unit: str = "it", disable: bool = False, total=None):
    """``tqdm`` over ``items`` on stderr (plain iteration when disabled)."""
    from tqdm import tqdm

    return tqdm(items, desc=desc, unit=unit, disable=disable, total=total, leave=False, dynamic_ncols=True)
