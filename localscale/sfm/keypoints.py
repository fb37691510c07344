"""Keypoint sets of the matching step: every image's keypoints grown by the matches of every pair
(points within ``merge_px`` are one keypoint), and one match per keypoint."""

from __future__ import annotations

import numpy as np


class KeypointSet:
    """One image's keypoints (full-image pixels), grown by the matches of every pair: a point
    within ``merge_px`` of a keypoint already in the set is that keypoint (the nearest), any other
    point is appended. The first keypoints (``base``) keep their indices."""

    def __init__(self, base: np.ndarray, merge_px: float = 1.0):
        self.merge_px = float(merge_px)
        self._points: list = [tuple(p) for p in np.asarray(base, np.float64).reshape(-1, 2)]
        self.num_base = len(self._points)
        self._grid: dict = {}
        for i, p in enumerate(self._points):
            self._grid.setdefault(self._cell(p), []).append(i)

    def _cell(self, p) -> tuple:
        return int(np.floor(p[0] / self.merge_px)), int(np.floor(p[1] / self.merge_px))

    def __len__(self) -> int:
        return len(self._points)

    @property
    def keypoints(self) -> np.ndarray:
        return np.asarray(self._points, np.float32).reshape(-1, 2)

    def index(self, points: np.ndarray) -> np.ndarray:
        """The index of each point in the set (added when no keypoint is within ``merge_px``)."""
        out = np.empty(len(points), np.int64)
        r2 = self.merge_px**2
        for k, p in enumerate(np.asarray(points, np.float64).reshape(-1, 2)):
            cx, cy = self._cell(p)
            best, best_d = -1, r2
            for dx in (-1, 0, 1):
                for dy in (-1, 0, 1):
                    for i in self._grid.get((cx + dx, cy + dy), ()):
                        q = self._points[i]
                        d = (q[0] - p[0]) ** 2 + (q[1] - p[1]) ** 2
                        if d <= best_d:
                            best, best_d = i, d
            if best < 0:
                best = len(self._points)
                self._points.append((float(p[0]), float(p[1])))
                self._grid.setdefault((cx, cy), []).append(best)
            out[k] = best
        return out


def one_to_one(ia: np.ndarray, ib: np.ndarray, scores: np.ndarray):
    """Matches ``(ia, ib)`` with each index used once on either side (merged keypoints can repeat
    one): the best-scored match wins. Returns ``(K x 2, K scores)``."""
    order = np.argsort(-scores, kind="stable")
    used_a, used_b, keep = set(), set(), []
    for k in order:
        a, b = int(ia[k]), int(ib[k])
        if a in used_a or b in used_b:
            continue
        used_a.add(a)
        used_b.add(b)
        keep.append(k)
    keep = np.asarray(sorted(keep), np.int64)
    return np.stack([ia[keep], ib[keep]], 1).reshape(-1, 2).astype(np.int64), scores[keep].astype(np.float32)
