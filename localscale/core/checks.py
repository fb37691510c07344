"""Checks of option values that raise a :class:`~localscale.core.errors.LocalScaleError` naming the value."""

from __future__ import annotations

import math

import numpy as np

from .errors import LocalScaleError


def check_int(value, name: str, low: int) -> None:
    """``value`` is an integer (not a bool) ``>= low``."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
        raise LocalScaleError(f"{name} must be an integer >= {low}, got {value!r}")


def check_number(value, name: str, low: float, high: float = math.inf, inclusive: bool = False) -> None:
    """``value`` is a finite number in ``(low, high]`` (``[low, high]`` with ``inclusive``)."""
    ok = (
        isinstance(value, (int, float, np.floating, np.integer))
        and not isinstance(value, bool)
        and math.isfinite(value)
        and (low <= value <= high if inclusive else low < value <= high)
    )
    if not ok:
        span = (
            f"in [{low:g}, {high:g}]"
            if inclusive
            else (f"in ({low:g}, {high:g}]" if math.isfinite(high) else f"a finite number > {low:g}")
        )
        raise LocalScaleError(f"{name} must be {span}, got {value!r}")


def check_choice(value, name: str, choices) -> None:
    """``value`` is one of ``choices``."""
    if value not in choices:
        raise LocalScaleError(f"{name} must be one of {tuple(choices)}, got {value!r}")
