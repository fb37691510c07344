"""Output names of a ``predict --pairs`` run; the pairs file itself is read by :mod:`localscale.pairs_file`."""

from __future__ import annotations

from ..outputs import resolved_path
from .common import image_labels, short_name


def pairs_output_names(pairs: list[tuple]) -> list[str]:
    """``<index:05d>_<A>_<B>`` per pair: the index is the pair's position in the list (so it does
    not depend on which pairs fail) and the names come from :func:`image_labels` over all images."""
    labels = image_labels([p for pair in pairs for p in pair])
    return [
        short_name(f"{i:05d}_{labels[resolved_path(a)]}_{labels[resolved_path(b)]}") for i, (a, b) in enumerate(pairs)
    ]
