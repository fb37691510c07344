"""Quarter turns of an image: the pixel map of :func:`numpy.rot90`, the turn that undoes a
homography's rotation, and matching with one image turned (keypoints in the image as given).

Quarter turns are counter-clockwise, as :func:`numpy.rot90`.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ...geometry import homography_rotation_at, turn_matrix


def unturn_points(points, turn: int, shape: tuple) -> np.ndarray:
    """``N x 2`` pixel coordinates of ``np.rot90(image, turn)`` mapped back to those of the image
    (of ``shape`` ``(H, W)``), float32."""
    M = np.linalg.inv(turn_matrix(turn, shape))
    p = np.asarray(points, np.float64).reshape(-1, 2)
    return (p @ M[:2, :2].T + M[:2, 2]).astype(np.float32)


def nearest_turn(H: np.ndarray, point, shape_b: tuple) -> int:
    """The quarter turn of B (of ``shape_b``) after which the homography ``H`` (A -> B) rotates
    least at ``point`` of A."""
    return int(np.argmin([abs(homography_rotation_at(turn_matrix(k, shape_b) @ H, point)) for k in range(4)]))


def match_turned(
    matcher,
    image_a: np.ndarray,
    image_b: np.ndarray,
    scale_a=None,
    scale_b=None,
    turn: int = 0,
    keys: tuple = (None, None),
    maps_turned: bool = False,
    max_side=None,
):
    """``matcher.match`` with B turned by ``turn`` quarter turns; B's keypoints are returned in the
    pixels of B as given. ``scale_b``: a map of B as given (turned here), or of the turned B
    (``maps_turned``), or a float. ``max_side``: :meth:`~localscale.matching.Matcher.match`'s. B's
    ``frames_b`` are ``None`` when B was turned."""
    if turn % 4 == 0:
        return matcher.match(image_a, image_b, scale_a, scale_b, keys, max_side=max_side)
    bt = np.ascontiguousarray(np.rot90(image_b, turn))
    if isinstance(scale_b, np.ndarray) and scale_b.ndim == 2 and not maps_turned:
        scale_b = np.ascontiguousarray(np.rot90(scale_b, turn))
    key_b = None if keys[1] is None else (keys[1], "turn", turn % 4)
    found = matcher.match(image_a, bt, scale_a, scale_b, (keys[0], key_b), max_side=max_side)
    # the frames' angles are those of the turned B: dropped
    return dataclasses.replace(found, keypoints_b=unturn_points(found.keypoints_b, turn, image_b.shape), frames_b=None)
