"""What matching two images returns (:class:`MatchResult`), and writing it to ``.npz``."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Union

import numpy as np

from ..core.errors import LocalScaleError
from .metrics import matching_accuracy


@dataclass
class MatchResult:
    """Matches between two images.

    Attributes:
        keypoints_a, keypoints_b: ``N_A x 2``, ``N_B x 2`` float32, full-image pixels.
        matches: ``K x 2`` int64 indices (A, B); distances: ``K`` match costs (lower is better).
        errors: ``K`` reprojection errors ``|H x_A - x_B|`` (pixels of B) when ``H`` was given, else ``None``.
        radii_a, radii_b: patch radii of all keypoints (``patches`` extractor; else ``None``).
        correction: the method used; H: the true homography when given.
        scale_a, scale_b: the (gated) maps / floats used, in the working frame, for inspection
            (``auto``: Local-ScaleNet's ungated maps, the hypotheses come from).
        meta: matcher name, feature counts, working scales, resize factors, passes.
        verification: :class:`~.verification.VerificationResult` of the matches (``refine=True``).
        refined_a, refined_b: :class:`~.verification.RefinedScale` of A and B (``refine=True``).
    """

    keypoints_a: np.ndarray
    keypoints_b: np.ndarray
    matches: np.ndarray
    distances: np.ndarray
    errors: Optional[np.ndarray]
    radii_a: Optional[np.ndarray]
    radii_b: Optional[np.ndarray]
    correction: str
    H: Optional[np.ndarray] = None
    scale_a: object = None
    scale_b: object = None
    meta: dict = field(default_factory=dict)
    verification: object = None
    refined_a: object = None
    refined_b: object = None

    @property
    def relative_pose(self):
        """``(R 3 x 3, t 3)`` with ``x_B = R x_A + t``, ``|t| = 1``, from the two-view geometry of a
        pair matched with both cameras; ``None`` otherwise."""
        g = getattr(self.verification, "two_view", None)
        return None if g is None or g.R is None else (g.R, g.t)

    def inliers(self, threshold: float = 5.0) -> np.ndarray:
        if self.errors is None:
            raise LocalScaleError("no homography was given, inliers are unknown")
        return self.errors < threshold

    def accuracy(self, threshold: float = 5.0) -> float:
        if self.errors is None:
            raise LocalScaleError("no homography was given, accuracy is unknown")
        return float(matching_accuracy(self.errors, [threshold])[0])


def save_matches(result: MatchResult, path: Union[str, Path]) -> None:
    """Write the result to ``.npz`` (keypoints_a/b, matches, distances, radii_a/b, correction,
    and errors / H when known)."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise LocalScaleError(f"cannot create folder {path.parent}: {e.strerror or e}") from None
    data = dict(
        keypoints_a=result.keypoints_a,
        keypoints_b=result.keypoints_b,
        matches=result.matches,
        distances=result.distances,
        correction=np.array(result.correction),
        matcher=np.array(str(result.meta.get("matcher", ""))),
    )
    if result.radii_a is not None:
        data.update(radii_a=result.radii_a, radii_b=result.radii_b)
    if result.errors is not None:
        data["errors"] = result.errors
    if result.H is not None:
        data["H"] = result.H
    from ..core.outputs import atomic_path

    with atomic_path(path) as tmp:  # complete file or none
        with open(tmp, "wb") as f:
            np.savez(f, **data)
