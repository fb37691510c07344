"""Where the zoomed view lies in the wide one, from matches that did not verify.

A strong zoom matched at roughly the right scale and quarter turn, with the zoomed view shrunk,
often returns too few correct matches to verify, hidden among wrong ones. The correct ones agree
on one thing the wrong ones do not: once the scale and the turn are undone, they are related by a
translation only. :func:`locate_window` finds the translation most matches agree on (a vote in the
wide view's pixels) and returns the part of the wide view that the zoomed view shows under it, so
that this window can be enlarged and matched at full detail instead.
:func:`homography_window` gives the same window from a verified geometry.

A detector with its own size and orientation (SIFT) needs no hypothesis to vote: each match
alone gives a similarity, and :func:`locate_similarity` finds the one most matches agree on
(Lowe's Hough transform, Lowe 2004, Sec. 7), the scale, the turn and the window with it.
"""

from __future__ import annotations

import math
from typing import Optional

import numpy as np

from ...geometry import turn_matrix

#: defaults of :func:`locate_window` and :func:`locate_turn`: agreeing matches needed, how far an
#: agreeing offset may lie (share of the wide view's longer side), the window's margin on each side
#: (share of the zoomed view's outline) and its largest share of the wide view
MIN_VOTES, RADIUS, MARGIN, MAX_SHARE = 6, 0.04, 0.25, 0.5
#: bins of :func:`locate_similarity`'s vote: half an octave of scale, 30 degrees of rotation, and a
#: quarter of B's extent in A for where B's centre lies (Lowe's, with half his scale bin)
SCALE_BIN, ANGLE_BIN, PLACE_BIN = 0.5, 30.0, 0.25


def _stands_out(votes: int, chance: float, min_votes: int) -> bool:
    """Whether ``votes`` agreeing matches stand out of the ``chance`` count random matches give
    (and reach ``min_votes``)."""
    return votes >= max(min_votes, 1 + chance + 4 * math.sqrt(chance) + 2)


def _points(p) -> np.ndarray:
    return np.asarray(p, np.float64).reshape(-1, 2)


def translation_votes(offsets: np.ndarray, radius: float) -> tuple[np.ndarray, int]:
    """The offset (``2``) with the most offsets within ``radius`` of it, refined as their median,
    and that count. ``offsets``: ``N x 2``."""
    d2 = ((offsets[:, None, :] - offsets[None, :, :]) ** 2).sum(-1)
    near = d2 <= radius * radius
    counts = near.sum(1)
    best = int(np.argmax(counts))
    return np.median(offsets[near[best]], axis=0), int(counts[best])


def homography_window(H: np.ndarray, scale: float, shape_a: tuple, shape_b: tuple, margin: float, max_share: float):
    """``(image, x0, y0, x1, y1)``: the part of the image whose content is smaller (B if
    ``scale < 1``) that the other one covers under ``H``, or ``None`` (not small, or not in front)."""
    if not np.isfinite(H).all() or abs(np.linalg.det(H)) < 1e-12:
        return None
    wide, M, shape_wide, shape_other = (
        (1, H, shape_b, shape_a) if scale < 1 else (0, np.linalg.inv(H), shape_a, shape_b)
    )
    h, w = shape_other[:2]
    corners = np.array([[0.0, 0, 1], [w, 0, 1], [w, h, 1], [0, h, 1], [w / 2, h / 2, 1]]) @ M.T
    if not (np.isfinite(corners).all() and (corners[:4, 2] * corners[4, 2] > 0).all()):
        return None  # part of the other image is behind the camera: no bounded window
    xy = corners[:, :2] / corners[:, 2:]
    (x0, y0), (x1, y1) = xy.min(0), xy.max(0)
    mx, my = margin * (x1 - x0), margin * (y1 - y0)
    H_w, W_w = shape_wide[:2]
    x0, y0 = max(0, int(math.floor(x0 - mx))), max(0, int(math.floor(y0 - my)))
    x1, y1 = min(W_w, int(math.ceil(x1 + mx))), min(H_w, int(math.ceil(y1 + my)))
    if x1 - x0 < 16 or y1 - y0 < 16 or (x1 - x0) * (y1 - y0) > max_share * W_w * H_w:
        return None
    return (wide, x0, y0, x1, y1)


def _vote(pa: np.ndarray, pb: np.ndarray, scale: float, turn: int, shape_a: tuple, shape_b: tuple, radius: float):
    """The offset most matches agree on under ``(scale, turn)``, their count, the count expected by
    chance, and the frame: ``(shrink, zoomed width, height, wide width, height, B's turn matrix)``."""
    T = turn_matrix(turn, shape_b)
    qb = pb @ T[:2, :2].T + T[:2, 2]  # points of B in the turned B
    hb, wb = (shape_b[1], shape_b[0]) if turn % 2 else shape_b[:2]  # turned B's size
    if scale >= 1:  # B is the zoomed view: its points shrunk by S land in A
        wide, zoomed, shrink, zh, zw = pa, qb, 1.0 / scale, hb, wb
        wh, ww = shape_a[:2]
    else:  # A is the zoomed view: its points shrunk by 1 / S land in the turned B
        wide, zoomed, shrink, zh, zw = qb, pa, scale, shape_a[0], shape_a[1]
        wh, ww = hb, wb
    centre = np.array([(zw - 1) / 2, (zh - 1) / 2])
    offsets = wide - shrink * (zoomed - centre)
    r = radius * max(wh, ww)
    u, votes = translation_votes(offsets, r)
    chance = (len(offsets) - 1) * math.pi * r * r / (ww * wh)
    return u, votes, chance, (shrink, zw, zh, ww, wh, T)


def locate_window(
    points_a,
    points_b,
    scale: float,
    turn: int,
    shape_a: tuple,
    shape_b: tuple,
    min_votes: int = MIN_VOTES,
    radius: float = RADIUS,
    margin: float = MARGIN,
    max_share: float = MAX_SHARE,
) -> Optional[tuple[tuple, int]]:
    """The window of the wide view that the zoomed view shows, voted by matched points.

    Under the hypothesis ``S_{A->B} = scale`` with B turned by ``turn`` quarter turns (counter-
    clockwise), a correct match satisfies ``q = S (p_A - c) + u`` with ``q`` its point in the turned B
    (``S > 1``: B is the zoomed view) or ``p_A = (q - c') / S + u`` (``S < 1``: A is), ``c``/``c'``
    the zoomed view's centre and ``u`` the point of the wide view where that centre lies.

    Args:
        points_a, points_b: ``N x 2`` matched points in the pixels of A and of B as given.
        scale, turn: the hypothesis.
        shape_a, shape_b: ``(H, W)`` of A and B.
        min_votes: matches that must agree on ``u``; more when many matches could agree by
            chance (random offsets spread over the wide view).
        radius: how far (share of the wide view's longer side) an agreeing offset may lie.
        margin: the window is the zoomed view's outline grown by this share of its size on each side.
        max_share: a window larger than this share of the wide view is no window.
    Returns:
        ``(window, votes)``: ``window`` = ``(image, x0, y0, x1, y1)`` (``image`` 0: a window of A;
        1: of B before its turn; integer pixels), as :attr:`~.hypotheses.Hypothesis.window`, and the
        matches that agree on it; ``None`` without enough agreeing matches.
    """
    pa, pb = _points(points_a), _points(points_b)
    if len(pa) < min_votes or not (np.isfinite(scale) and scale > 0):
        return None
    return _window_of(
        _vote(pa, pb, scale, turn, shape_a, shape_b, radius), scale, shape_b, min_votes, margin, max_share
    )


def _window_of(vote: tuple, scale: float, shape_b: tuple, min_votes: int, margin: float, max_share: float):
    """:func:`locate_window`'s result from a :func:`_vote`."""
    u, votes, chance, (shrink, zw, zh, ww, wh, T) = vote
    # random matches spread their offsets over the wide view: the vote must stand out of that
    if not _stands_out(votes, chance, min_votes):
        return None
    half = shrink * np.array([zw, zh]) * (0.5 + margin)
    x0, y0 = np.maximum(0, np.floor(u - half)).astype(int)
    x1, y1 = np.minimum([ww, wh], np.ceil(u + half)).astype(int)
    if x1 - x0 < 16 or y1 - y0 < 16 or (x1 - x0) * (y1 - y0) > max_share * ww * wh:
        return None
    if scale >= 1:
        return (0, int(x0), int(y0), int(x1), int(y1)), votes
    # a window of the turned B: back to B as given
    Ti = np.linalg.inv(T)
    corners = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], np.float64) @ Ti[:2, :2].T + Ti[:2, 2]
    (bx0, by0), (bx1, by1) = np.floor(corners.min(0)), np.ceil(corners.max(0))
    window = (1, int(max(0, bx0)), int(max(0, by0)), int(min(shape_b[1], bx1 + 1)), int(min(shape_b[0], by1 + 1)))
    return window, votes


def locate_turn(
    points_a,
    points_b,
    scale: float,
    shape_a: tuple,
    shape_b: tuple,
    ratio: float = 1.5,
    min_votes: int = MIN_VOTES,
    radius: float = RADIUS,
    margin: float = MARGIN,
    max_share: float = MAX_SHARE,
) -> Optional[tuple[int, tuple, int]]:
    """The quarter turn of B under which the matches agree most on where the zoomed view lies,
    when it gathers at least ``ratio`` times the votes of any other turn: ``(turn, window,
    votes)`` (the other arguments as :func:`locate_window`'s), else ``None``. Matches of a scale- and
    rotation-invariant matcher on the images as they are vote for the turn as for the window."""
    pa, pb = _points(points_a), _points(points_b)
    if not len(pa) or not (np.isfinite(scale) and scale > 0):
        return None
    votes = [_vote(pa, pb, scale, k, shape_a, shape_b, radius) for k in range(4)]
    best = int(np.argmax([v[1] for v in votes]))
    if votes[best][1] < ratio * max(v[1] for k, v in enumerate(votes) if k != best):
        return None
    located = _window_of(votes[best], scale, shape_b, min_votes, margin, max_share)
    return None if located is None else (best, *located)


def similarity_votes(points_a, points_b, frames_a, frames_b, shape_b: tuple):
    """What each match says on its own: ``(log2 S_{A->B} (N), rotation from B to A in degrees
    [0, 360) (N), where B's centre lies in A (N x 2))``, from the sizes and orientations
    (:attr:`~localscale.features.Features.frames`, OpenCV's convention) of its two keypoints."""
    pa, pb = _points(points_a), _points(points_b)
    fa, fb = np.asarray(frames_a, np.float64).reshape(-1, 2), np.asarray(frames_b, np.float64).reshape(-1, 2)
    log_s = np.log2(np.maximum(fb[:, 0], 1e-6) / np.maximum(fa[:, 0], 1e-6))
    angle = np.mod(fa[:, 1] - fb[:, 1], 360.0)
    t = np.radians(angle)
    d = np.array([(shape_b[1] - 1) / 2, (shape_b[0] - 1) / 2]) - pb
    turned = np.stack([np.cos(t) * d[:, 0] - np.sin(t) * d[:, 1], np.sin(t) * d[:, 0] + np.cos(t) * d[:, 1]], 1)
    return log_s, angle, pa + turned / np.exp2(log_s)[:, None]


def _hough_bins(log_s: np.ndarray, angle: np.ndarray, centre: np.ndarray, extent_b: float):
    """Each vote in the two nearest bins of each dimension (16 bins): ``(bins 16N x 4, vote 16N)``."""
    n = len(log_s)
    s0 = np.floor(log_s / SCALE_BIN - 0.5)
    a0 = np.floor(angle / ANGLE_BIN - 0.5)
    rows, owners = [], []
    for ds in (0, 1):
        sb = s0 + ds
        place = PLACE_BIN * extent_b / np.exp2((sb + 0.5) * SCALE_BIN)  # at the bin's scale
        x0, y0 = np.floor(centre[:, 0] / place - 0.5), np.floor(centre[:, 1] / place - 0.5)
        for da in (0, 1):
            ab = np.mod(a0 + da, round(360 / ANGLE_BIN))
            for dx in (0, 1):
                for dy in (0, 1):
                    rows.append(np.stack([sb, ab, x0 + dx, y0 + dy], 1))
                    owners.append(np.arange(n))
    return np.concatenate(rows).astype(np.int64), np.concatenate(owners)


def locate_similarity(
    points_a,
    points_b,
    frames_a,
    frames_b,
    shape_a: tuple,
    shape_b: tuple,
    min_votes: int = MIN_VOTES,
    radius: float = RADIUS,
    candidates: int = 3,
) -> Optional[tuple[np.ndarray, int, np.ndarray]]:
    """The similarity between A and B that most matches agree on, from the keypoints' own sizes
    and orientations (Lowe's Hough transform): each match votes for its scale, rotation and the
    point of A where B's centre lies; the ``candidates`` fullest bins are each fitted with a
    similarity, and the one most matches agree with (within ``radius`` of the wide view's longer
    side, in its pixels) is returned if that count stands out of what random matches give.

    Args:
        points_a, points_b: ``N x 2`` matched points in the pixels of A and of B.
        frames_a, frames_b: ``N x 2`` ``(size, angle)`` of the matched keypoints
            (:attr:`~localscale.features.Features.frames`).
        shape_a, shape_b: ``(H, W)`` of A and B.
        min_votes, radius: as :func:`locate_window`'s.
        candidates: bins fitted, fullest first.
    Returns:
        ``(M, votes, inliers)``: ``M`` the ``3 x 3`` similarity from A's pixels to B's
        (``sqrt(det M)`` is ``S_{A->B}``), the matches that agree with it and their ``N`` mask;
        ``None`` without enough agreeing matches.
    """
    pa, pb = _points(points_a), _points(points_b)
    n = len(pa)
    if n < max(3, min_votes) or frames_a is None or frames_b is None:
        return None
    log_s, angle, centre = similarity_votes(pa, pb, frames_a, frames_b, shape_b)
    bins, owners = _hough_bins(log_s, angle, centre, float(max(shape_b[:2])))
    keys, inverse, counts = np.unique(bins, axis=0, return_inverse=True, return_counts=True)
    best = None
    for k in np.argsort(-counts, kind="stable")[:candidates]:
        members = owners[inverse.reshape(-1) == k]
        if len(members) < 3:
            break
        fitted = _fit_similarity(pa, pb, members, shape_a, shape_b, radius)
        if fitted is not None and (best is None or fitted[1].sum() > best[1].sum()):
            best = fitted
    if best is None:
        return None
    M, inliers = best
    votes = int(inliers.sum())
    wide = shape_a if np.linalg.det(M[:2, :2]) >= 1 else shape_b
    r = radius * max(wide[:2])
    chance = (n - 1) * math.pi * r * r / (wide[0] * wide[1])
    if not _stands_out(votes, chance, min_votes):
        return None
    return M, votes, inliers


def _fit_similarity(pa: np.ndarray, pb: np.ndarray, members: np.ndarray, shape_a, shape_b, radius: float):
    """A similarity (A -> B, ``3 x 3``) fitted to ``members``, refitted once to every match that agrees
    with it in the wide view, and that ``N`` mask; ``None`` if it cannot be fitted."""
    import cv2

    inliers = np.zeros(len(pa), bool)
    inliers[members] = True
    M = None
    for _ in range(2):
        A, _ = cv2.estimateAffinePartial2D(pa[inliers], pb[inliers], method=cv2.LMEDS)
        if A is None or not np.isfinite(A).all() or abs(np.linalg.det(A[:, :2])) < 1e-9:
            return None if M is None else (M, inliers)
        M = np.vstack([A, [0.0, 0.0, 1.0]])
        zoom_b = np.linalg.det(M[:2, :2]) >= 1  # B shows A's content bigger: A is the wide view
        if zoom_b:
            q = pb @ np.linalg.inv(M)[:2, :2].T + np.linalg.inv(M)[:2, 2]
            err, wide = np.linalg.norm(q - pa, axis=1), shape_a
        else:
            err, wide = np.linalg.norm(pa @ M[:2, :2].T + M[:2, 2] - pb, axis=1), shape_b
        agree = err <= radius * max(wide[:2])
        if agree.sum() < 3:
            return None
        inliers = agree
    return M, inliers
