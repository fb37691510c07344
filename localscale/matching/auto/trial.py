"""One run of the hypothesis loop: a hypothesis matched (:func:`run_hypothesis`: its window cut,
B turned, the matcher run, the keypoints taken back to the images' pixels) and verified
(:func:`verify_found`); what it found (:class:`Trial`) and what the loop returns (:class:`AutoResult`)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from ..verification import VerificationResult, verify_matches
from .hypotheses import Hypothesis
from .turns import match_turned


@dataclass
class Trial:
    """One hypothesis run: its verification's inlier count and ratio, whether it verified, seconds."""

    hypothesis: Hypothesis
    num_matches: int
    num_inliers: int
    inlier_ratio: float
    verified: bool
    seconds: float

    def to_dict(self) -> dict:
        h = self.hypothesis
        return {
            "source": h.source,
            "scale": round(float(h.scale), 5),
            "turn": int(h.turn),
            "window": None if h.window is None else [int(x) for x in h.window],
            "num_matches": int(self.num_matches),
            "num_inliers": int(self.num_inliers),
            "inlier_ratio": round(float(self.inlier_ratio), 4),
            "verified": bool(self.verified),
            "seconds": round(float(self.seconds), 3),
        }


@dataclass
class AutoResult:
    """What :func:`~.loop.try_hypotheses` returns: the chosen run's matches in original pixels, its
    verification, the chosen hypothesis, every trial in the order tried, the seconds of the whole
    loop, and Local-ScaleNet's ungated maps of A and B (``None`` when the networks did not run)."""

    matches: object
    verification: VerificationResult
    chosen: Hypothesis
    trials: list = field(default_factory=list)
    seconds: float = 0.0
    network_maps: Optional[tuple] = None

    def to_dict(self) -> dict:
        """JSON-ready: the chosen hypothesis, whether it verified, and every trial."""
        return {
            "chosen": self.chosen.describe(),
            "scale": round(float(self.chosen.scale), 5),
            "turn": int(self.chosen.turn),
            "verified": self.verified,
            "trials": [t.to_dict() for t in self.trials],
            "seconds": round(self.seconds, 3),
        }

    @property
    def verified(self) -> bool:
        return bool(self.verification.verified)


def run_hypothesis(
    matcher, a: np.ndarray, b: np.ndarray, h: Hypothesis, keys: tuple, vconf, cameras=(None, None), max_side=None
):
    """One hypothesis: crop its window, turn B, match with the hypothesis's maps or scale (the
    image whose content is smaller enlarged up to ``max_side``, None: the matcher's), map the
    keypoints back to the given images' pixels, verify."""
    keys = list(keys)
    offsets = [np.zeros(2, np.float32), np.zeros(2, np.float32)]
    images = [a, b]
    if h.window is not None:
        i, x0, y0, x1, y1 = h.window
        images[i] = np.ascontiguousarray(images[i][y0:y1, x0:x1])
        offsets[i] = np.array([x0, y0], np.float32)
        keys[i] = None if keys[i] is None else (keys[i], "window", tuple(h.window))
    sa, sb = h.maps if h.maps is not None else (h.scale, 1.0 / h.scale)
    found = match_turned(
        matcher, images[0], images[1], sa, sb, h.turn, tuple(keys), maps_turned=True, max_side=max_side
    )
    found = dataclasses.replace(
        found, keypoints_a=found.keypoints_a + offsets[0], keypoints_b=found.keypoints_b + offsets[1]
    )
    return found, verify_found(found, a, b, vconf, cameras)


def verify_found(found, a: np.ndarray, b: np.ndarray, vconf, cameras: tuple):
    """The matches of ``found`` (keypoints in the pixels of ``a`` and ``b``) verified by ``vconf``."""
    m = found.matches
    return verify_matches(
        found.keypoints_a[m[:, 0]], found.keypoints_b[m[:, 1]], a.shape[:2], b.shape[:2], None, vconf, *cameras
    )
