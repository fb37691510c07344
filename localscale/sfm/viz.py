"""Pictures of a reconstruction: the model from above and the pair graph (matplotlib, PNG).

:func:`plot_reconstruction` draws, side by side, (left) the 3D points and camera centres of the
largest model seen from above ("up" is the cameras' mean upward image direction, so it holds for
any orientation of the model), and (right) the pair graph: every image on a circle, each
matched pair an edge, green when its two-view geometry verified, red when it did not, registered
images filled. A camera far from the others (:func:`far_cameras`) is drawn as a mark at the edge of
the view from above, with its distance in spreads, so that the others stay readable. Written atomically.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from ..core.outputs import atomic_path


def _top_view_axes(rec) -> np.ndarray:
    """``3 x 2``: two world axes perpendicular to "up", taken as the cameras' mean upward image
    direction (photos are mostly taken upright); the first along the cameras' mean image x axis."""
    rots = []
    for im in rec.images.values():
        if im.has_pose:
            pose = im.cam_from_world() if callable(im.cam_from_world) else im.cam_from_world
            rots.append(np.asarray(pose.rotation.matrix()))
    if not rots:
        return np.eye(3)[:, :2]
    up = -np.mean([R[1] for R in rots], 0)  # image y points down: its world direction, negated
    up /= max(np.linalg.norm(up), 1e-12)
    x = np.mean([R[0] for R in rots], 0)
    x -= up * (x @ up)
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(up, [1.0, 0, 0]) if abs(up[0]) < 0.9 else np.cross(up, [0, 1.0, 0])
    x /= np.linalg.norm(x)
    y = np.cross(up, x)
    return np.stack([x, y], 1)


#: a camera this many times the median distance of the cameras to their median is drawn at the edge
FAR_CAMERA = 5.0


def far_cameras(c2) -> np.ndarray:
    """A mask of the cameras (N x 2, seen from above) farther than :data:`FAR_CAMERA` x the median
    distance of the cameras to their median point: drawn at the edge, so that one camera far off
    does not squeeze the others into a corner."""
    c2 = np.asarray(c2, np.float64).reshape(-1, 2)
    if len(c2) < 3:
        return np.zeros(len(c2), bool)
    d = np.linalg.norm(c2 - np.median(c2, 0), axis=1)
    scale = np.median(d)
    return d > FAR_CAMERA * scale if scale > 0 else np.zeros(len(c2), bool)


def _set_limits(ax, xy) -> None:
    """Equal axes around ``xy`` (the points and the near cameras) with a margin."""
    if not len(xy):
        return
    lo, hi = xy.min(0), xy.max(0)
    centre, half = (lo + hi) / 2, max(float((hi - lo).max()) / 2, 1e-9) * 1.1
    ax.set_xlim(centre[0] - half, centre[0] + half)
    ax.set_ylim(centre[1] - half, centre[1] + half)
    ax.set_aspect("equal", adjustable="box")


def _mark_far(ax, names: list, far_xy, near_xy) -> None:
    """Each far camera as an arrow at the edge of the picture, in its direction, with its name and distance."""
    if not len(names):
        return
    (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
    centre = np.array([(x0 + x1) / 2, (y0 + y1) / 2])
    half = (x1 - x0) / 2
    scale = max(float(np.median(np.linalg.norm(near_xy - np.median(near_xy, 0), axis=1))) if len(near_xy) else 0, 1e-12)
    for i, (n, xy) in enumerate(zip(names, far_xy)):
        v = xy - centre
        edge = centre + v / max(np.abs(v).max(), 1e-12) * half * 0.92
        label = "far camera (off the picture)" if i == 0 else None
        ax.scatter([edge[0]], [edge[1]], s=60, c="darkorange", marker="X", label=label, zorder=4)
        ax.annotate(f"{Path(n).stem} ({np.linalg.norm(v) / scale:.3g} x)", edge, fontsize=6, color="darkorange")


def plot_reconstruction(path, rec, image_names: list, pair_status: dict, title: str = "") -> Path:
    """Write the figure (module docstring) to ``path``.

    ``rec``: the largest ``pycolmap.Reconstruction`` (or None); ``image_names``: every image;
    ``pair_status``: ``{(a, b): True/False}`` verified or not.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .mapping import camera_centers

    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(12, 6))
    registered = set()
    if rec is not None and rec.num_reg_images():
        names, centres = camera_centers(rec)
        registered = set(names)
        pts = np.array([p.xyz for p in rec.points3D.values()]).reshape(-1, 3)
        cols = np.array([p.color for p in rec.points3D.values()]).reshape(-1, 3) / 255.0
        if len(pts):  # the points within the 1st..99th percentiles (a few far outliers would shrink the rest)
            lo, hi = np.percentile(pts, 1, axis=0), np.percentile(pts, 99, axis=0)
            keep = np.all((pts >= lo) & (pts <= hi), axis=1)
            pts, cols = pts[keep], cols[keep]
        axes = _top_view_axes(rec)
        mean = centres.mean(0) if len(centres) else 0
        p2 = (pts - mean) @ axes
        c2 = (centres - mean) @ axes
        ax0.scatter(p2[:, 0], p2[:, 1], s=1, c=cols if len(cols) else None)
        far = far_cameras(c2)
        near = ~far
        ax0.scatter(c2[near, 0], c2[near, 1], s=30, c="red", marker="^", label="cameras")
        for n, (x, y) in zip(np.array(names)[near], c2[near]):
            ax0.annotate(Path(n).stem, (x, y), fontsize=6)
        _set_limits(ax0, np.concatenate([p2, c2[near]]))
        _mark_far(ax0, [n for n, f in zip(names, far) if f], c2[far], c2[near])
        ax0.legend(loc="upper right", fontsize=7)
        ax0.set_title(f"from above: {len(names)} cameras, {rec.num_points3D()} points", fontsize=9)
    else:
        ax0.text(0.5, 0.5, "no model", ha="center", va="center")
        ax0.set_title("from above", fontsize=9)
    n = len(image_names)
    angle = {name: 2 * math.pi * i / max(1, n) for i, name in enumerate(image_names)}
    xy = {name: (math.cos(a), math.sin(a)) for name, a in angle.items()}
    for (a, b), ok in pair_status.items():
        if a in xy and b in xy:
            ax1.plot(
                [xy[a][0], xy[b][0]],
                [xy[a][1], xy[b][1]],
                color="tab:green" if ok else "tab:red",
                alpha=0.7 if ok else 0.35,
                lw=1.0,
            )
    for name, (x, y) in xy.items():
        ax1.scatter([x], [y], s=40, c="black" if name in registered else "white", edgecolors="black", zorder=3)
        ax1.annotate(Path(name).stem, (x * 1.08, y * 1.08), fontsize=6, ha="center", va="center")
    nv = sum(bool(v) for v in pair_status.values())
    ax1.set_title(f"pairs: {nv} verified (green), {len(pair_status) - nv} not (red); filled = registered", fontsize=9)
    ax1.set_aspect("equal")
    ax1.axis("off")
    if title:  # a folder name that is not UTF-8 shows its bytes as \xNN
        fig.suptitle(os.fsencode(title).decode("utf-8", "backslashreplace"), fontsize=10)
    fig.tight_layout()
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    return path
