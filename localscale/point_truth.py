"""Per-point truth of a pair from a COLMAP model: the scale at the 3D points both images see.

At each shared 3D point's observation in A, the truth is the median ratio of distances to its 8
nearest shared points in B and in A (:func:`localscale.training.real_pairs.point_log_scales`, the
real-pair labels of training).

Example::

    xy, truth = shared_point_truth("sparse/0", "a.jpg", "b.jpg")   # N x 2 pixels of A, N scales
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .core.errors import LocalScaleError

#: shared 3D points needed for a per-point truth
MIN_SHARED_POINTS = 9


def _find_image(rec, image, model_dir) -> object:
    name = Path(str(image)).name
    found = [im for im in rec.images.values() if im.name == str(image) or Path(im.name).name == name]
    if not found:
        raise LocalScaleError(f"--colmap-model {model_dir}: no image named {name} in the COLMAP model")
    if len(found) > 1:
        raise LocalScaleError(f"--colmap-model {model_dir}: {len(found)} images named {name} in the COLMAP model")
    return found[0]


def shared_point_truth(model_dir, image_a, image_b) -> tuple[np.ndarray, np.ndarray]:
    """``(xy N x 2, truth N)``: the observations in A of the 3D points A and B share (pixels of A's
    file, origin at the centre of the top-left pixel) and ``S_{A->B}`` at each (NaN where too few
    neighbours). Raises :class:`LocalScaleError` when the folder is not a COLMAP sparse model, an
    image is not in it, or the two share fewer than :data:`MIN_SHARED_POINTS` points."""
    import pycolmap

    from .training.real_pairs import point_log_scales

    d = Path(model_dir)
    if not d.is_dir() or not any((d / f"images.{ext}").is_file() for ext in ("bin", "txt")):
        raise LocalScaleError(
            f"--colmap-model {model_dir}: not a COLMAP sparse model folder (images.bin or images.txt)"
        )
    try:
        rec = pycolmap.Reconstruction(str(d))
    except Exception as e:  # pycolmap raises its own types for damaged files
        raise LocalScaleError(f"--colmap-model {model_dir}: cannot read the COLMAP model ({e})") from None
    obs = []
    for image in (image_a, image_b):
        im = _find_image(rec, image, model_dir)
        obs.append({int(p.point3D_id): np.asarray(p.xy, np.float64) for p in im.points2D if p.has_point3D()})
    shared = sorted(obs[0].keys() & obs[1].keys())
    if len(shared) < MIN_SHARED_POINTS:
        raise LocalScaleError(
            f"--colmap-model {model_dir}: the two images share {len(shared)} 3D points, {MIN_SHARED_POINTS} needed"
        )
    xy_a = np.array([obs[0][k] for k in shared]) - 0.5  # COLMAP: the top-left pixel's centre is 0.5
    xy_b = np.array([obs[1][k] for k in shared]) - 0.5
    return xy_a, np.exp(point_log_scales(xy_a, xy_b))
