"""Scale maps refined by a verified geometry, and matching that refines them between passes.

* :func:`refine_scale_map`: the network map replaced, where a verified geometry explains the
  inliers, by the geometry's scale: the analytic map ``sqrt|det J_H(x)|`` of the homography
  over its support (co-visible region of A under ``H`` and the dilated inlier hull), or per-inlier
  scales of local affine fits interpolated between the inliers (fundamental-matrix case, where
  the network map is first shifted to the inliers' median level);
  blended with the network map in ``log2`` with a weight that decays with the distance to the
  support. Unverified: the network map unchanged, source all 0. ``source_layer`` labels each
  pixel by where its scale comes from (0 network, 1 homography, 2 matches).
* :func:`matches_scale_map`: the dense map of a match set alone (local affine fits, interpolated).
* :func:`refine_passes`: match, verify, refine the maps of both images, re-cut the patches
  with the refined maps and match again, until the inlier count stops growing; the pass with
  the most inliers is returned. When the first pass is not verified, an optional *seed* match
  set (e.g. OpenCV SIFT on a DoG scale space, :func:`sift_seed_points`, which finds matches under
  zoom where a single-scale detector does not) is verified with the same thresholds and, if it
  passes, gives the geometry of the refined maps for the second pass.

Example::

    v = verify_matches(pts_a, pts_b, a.shape[:2], b.shape[:2], scale_map=net_a)
    ref = refine_scale_map(net_a, v, a.shape[:2], b.shape[:2])
    ref.scale, ref.source, ref.verified
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Optional

import cv2
import numpy as np

from ..core.errors import LocalScaleError
from ..geometry import covisible_mask, homography_scale_map, orient_homography
from .nearest_neighbour import match_descriptors, ratio_mutual_matches
from .verification import VerificationConfig, VerificationResult, verify_matches

#: labels of :attr:`RefinedScale.source_layer`: the source each pixel's scale comes from
SOURCE_NETWORK, SOURCE_HOMOGRAPHY, SOURCE_MATCHES = 0, 1, 2
SOURCE_NAMES = {SOURCE_NETWORK: "network", SOURCE_HOMOGRAPHY: "homography", SOURCE_MATCHES: "matches"}


@dataclass
class RefinedScale:
    """A refined scale map of one image.

    Attributes:
        scale: ``H x W`` float32 refined ``S_{this->other}``.
        source: ``H x W`` float32 weight of the geometry in ``log2`` (0 = network map, 1 = geometry).
        verification: the :class:`VerificationResult` it came from (seen from this image).
        verified: whether a verified geometry was used.
        source_layer: ``H x W`` uint8, where each pixel's scale comes from: :data:`SOURCE_NETWORK`
            (0, the network's map), :data:`SOURCE_HOMOGRAPHY` (1, the verified homography's analytic
            map) or :data:`SOURCE_MATCHES` (2, local affine fits of the verified matches of a
            fundamental or essential matrix); a pixel is labelled by the geometry where its
            weight ``source`` is at least 0.5.
    """

    scale: np.ndarray
    source: np.ndarray
    verification: VerificationResult
    verified: bool
    source_layer: Optional[np.ndarray] = None

    def __post_init__(self):
        if self.source_layer is None:
            label = SOURCE_HOMOGRAPHY if self.verification.model == "homography" else SOURCE_MATCHES
            geo = (self.source >= 0.5) if self.verified else np.zeros(self.source.shape, bool)
            self.source_layer = np.where(geo, label, SOURCE_NETWORK).astype(np.uint8)

    @property
    def H(self):
        return self.verification.H

    @property
    def F(self):
        return self.verification.F

    @property
    def inliers(self):
        return self.verification.inliers


def _network_log2(scale_map, shape) -> np.ndarray:
    if scale_map is None:
        return np.zeros(shape, np.float64)
    if np.isscalar(scale_map):
        return np.full(shape, math.log2(float(scale_map)))
    m = np.asarray(scale_map, np.float64)
    if m.shape != tuple(shape):
        raise LocalScaleError(f"scale map is {m.shape[1]}x{m.shape[0]}, image is {shape[1]}x{shape[0]}")
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.log2(m)


def _anchored_to(net: np.ndarray, points: np.ndarray, log2_scales: np.ndarray) -> np.ndarray:
    """The network's ``log2`` map shifted so that its median at ``points`` is that of the geometry's
    ``log2_scales`` there: away from the matches, the map keeps its shape and takes the verified level."""
    if not len(points):
        return net
    h, w = net.shape
    pi = np.clip(np.round(points).astype(int), 0, [w - 1, h - 1])
    d = log2_scales - net[pi[:, 1], pi[:, 0]]
    d = d[np.isfinite(d)]
    return net + float(np.median(d)) if len(d) else net


def _hull_mask(points: np.ndarray, shape, margin_px: float) -> np.ndarray:
    mask = np.zeros(shape, np.uint8)
    pts = np.round(np.asarray(points, np.float64)).astype(np.int32).reshape(-1, 2)
    if len(pts) >= 3:
        cv2.fillConvexPoly(mask, cv2.convexHull(pts), 1)
    else:
        for x, y in pts:
            mask[np.clip(y, 0, shape[0] - 1), np.clip(x, 0, shape[1] - 1)] = 1
    if margin_px >= 1 and mask.any():
        r = int(round(margin_px))
        mask = cv2.dilate(mask, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))
    return mask.astype(bool)


def _distance_to(mask: np.ndarray) -> np.ndarray:
    """Euclidean distance (pixels) of every pixel to the nearest ``True`` pixel of ``mask``."""
    if not mask.any():
        return np.full(mask.shape, np.inf, np.float32)
    return cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, 5)


def _interpolate_log_scales(points: np.ndarray, log_scales: np.ndarray, shape, neighbours: int, stride: int):
    """Inverse-distance interpolation of per-point ``log2`` scales over an image; returns
    ``(log2 map H x W, distance to the nearest point H x W)``."""
    h, w = shape
    gh, gw = math.ceil(h / stride), math.ceil(w / stride)
    gx, gy = np.meshgrid(np.arange(gw) * stride + (stride - 1) / 2, np.arange(gh) * stride + (stride - 1) / 2)
    g = np.stack([gx.ravel(), gy.ravel()], 1)
    d = np.linalg.norm(g[:, None] - points[None], axis=-1)
    n = min(neighbours, len(points))
    nn = np.argpartition(d, n - 1, axis=1)[:, :n] if n < len(points) else np.tile(np.arange(len(points)), (len(g), 1))
    dn = np.take_along_axis(d, nn, 1)
    wts = 1.0 / np.maximum(dn, 1.0) ** 2
    val = (wts * log_scales[nn]).sum(1) / wts.sum(1)
    grid = val.reshape(gh, gw).astype(np.float32)
    full = cv2.resize(grid, (gw * stride, gh * stride), interpolation=cv2.INTER_LINEAR)[:h, :w]
    mask = np.zeros((h, w), bool)
    pi = np.clip(np.round(points).astype(int), 0, [w - 1, h - 1])
    mask[pi[:, 1], pi[:, 0]] = True
    return full.astype(np.float64), _distance_to(mask)


def _matches_log2_map(points: np.ndarray, log2_scales: np.ndarray, shape, config: VerificationConfig):
    """``log2`` scales of points interpolated over an image (NaN without points) and the mask of
    the points' pixels (the support of the map)."""
    support = np.zeros(shape, bool)
    if not len(points):
        return np.full(shape, np.nan), support
    geo, _ = _interpolate_log_scales(points, log2_scales, shape, config.interp_neighbours, config.grid_stride)
    pi = np.clip(np.round(points).astype(int), 0, [shape[1] - 1, shape[0] - 1])
    support[pi[:, 1], pi[:, 0]] = True
    return geo, support


def matches_scale_map(
    points_a: np.ndarray, points_b: np.ndarray, shape: tuple, config: VerificationConfig = VerificationConfig()
) -> tuple[np.ndarray, np.ndarray]:
    """A dense ``S_{A->B}`` from matches alone: a least-squares affine map fitted to each match and
    its ``config.affine_neighbours - 1`` nearest matches in A (scale ``sqrt|det|``, kept where the
    fit's residuals are within ``config.affine_threshold`` px), interpolated over A in ``log2``
    (inverse distance to the ``config.interp_neighbours`` nearest fits).

    Returns ``(scale H x W float32, NaN where no fit exists; distance H x W to the nearest fit, px)``.
    """
    from .verification import local_affine_scales

    pa, pb = np.asarray(points_a, np.float64).reshape(-1, 2), np.asarray(points_b, np.float64).reshape(-1, 2)
    s, ok = local_affine_scales(pa, pb, config.affine_neighbours, config.affine_threshold)
    geo, support = _matches_log2_map(pa[ok], np.log2(s[ok]), tuple(shape)[:2], config)
    return np.exp2(geo).astype(np.float32), _distance_to(support)


def refine_scale_map(
    scale_map,
    verification: VerificationResult,
    shape: Optional[tuple] = None,
    config: VerificationConfig = VerificationConfig(),
) -> RefinedScale:
    """The network's map refined by a verified geometry (module docstring).

    Args:
        scale_map: the network's ``S_{A->B}`` (``H_A x W_A``), a float, or ``None`` (= 1).
        verification: :class:`VerificationResult` of matches A -> B.
        shape: ``(height, width)`` of A (default: ``verification.shape_a``).
        config: support, decay and interpolation settings.
    Returns:
        :class:`RefinedScale` (``H_A x W_A`` scale and source weight).
    """
    config.check()
    shape = tuple(shape or verification.shape_a)[:2]
    net = _network_log2(scale_map, shape)
    if not verification.verified or verification.model == "none":
        base = np.exp2(net).astype(np.float32) if scale_map is not None else np.ones(shape, np.float32)
        return RefinedScale(base, np.zeros(shape, np.float32), verification, False)
    diag = math.hypot(*shape)
    inl_a = verification.points_a[verification.inliers]
    if verification.model == "homography":
        H = orient_homography(verification.H, shape)
        geo = np.log2(homography_scale_map(H, *shape))
        support = _hull_mask(inl_a, shape, config.hull_margin * diag)
        if config.support == "covisible" and verification.shape_b:
            support |= covisible_mask(H, shape, verification.shape_b)
        support &= np.isfinite(geo)
    else:
        ls = np.log2(verification.local_scales[verification.inliers])
        known = np.isfinite(ls)  # inliers without a consistent local affine fit have no scale
        geo, _ = _matches_log2_map(inl_a[known], ls[known], shape, config)
        support = _hull_mask(inl_a[known], shape, config.hull_margin * diag)
        net = _anchored_to(net, inl_a[known], ls[known])
    dist = _distance_to(support)
    weight = np.exp(-dist / (config.decay * diag)).astype(np.float64)
    ok = np.isfinite(geo)
    weight[~ok] = 0.0
    net_ok = np.isfinite(net)
    out = np.where(net_ok, net, 0.0) * (1 - weight) + np.where(ok, geo, 0.0) * weight
    out = np.where(net_ok | (weight > 0), out, net)
    return RefinedScale(np.exp2(out).astype(np.float32), weight.astype(np.float32), verification, True)


def refine_pair_maps(
    scale_a, scale_b, verification: VerificationResult, config: VerificationConfig = VerificationConfig()
) -> tuple[RefinedScale, RefinedScale]:
    """Refined maps of both images: A's from ``verification``, B's from its swapped view."""
    return (
        refine_scale_map(scale_a, verification, verification.shape_a, config),
        refine_scale_map(scale_b, verification.swapped(), verification.shape_b, config),
    )


# ---------------------------------------------------------------- second pass


@dataclass
class RefinedMatching:
    """Outcome of :func:`refine_passes`.

    Attributes:
        keypoints_a, keypoints_b: ``N_A x 2``, ``N_B x 2``; matches: ``K x 2`` int64; distances: ``K``.
        verification: :class:`VerificationResult` of these matches.
        refined_a, refined_b: :class:`RefinedScale` of A and B from the returned pass's geometry.
        passes: matching passes run; inlier_counts: inliers after each pass;
        best_pass: index of the returned pass (0 = the first, with the initial maps).
        seed: verification of the seed match set when it was tried, else ``None``.
    """

    keypoints_a: np.ndarray
    keypoints_b: np.ndarray
    matches: np.ndarray
    distances: np.ndarray
    verification: VerificationResult
    refined_a: RefinedScale
    refined_b: RefinedScale
    passes: int
    inlier_counts: list = field(default_factory=list)
    best_pass: int = 0
    seed: Optional[VerificationResult] = None


def refine_passes(
    match: Callable,
    shape_a: tuple,
    shape_b: tuple,
    first_a=None,
    first_b=None,
    prior_a=None,
    prior_b=None,
    config: VerificationConfig = VerificationConfig(),
    max_passes: int = 2,
    seed: Optional[Callable] = None,
) -> RefinedMatching:
    """Match, verify, refine both maps and match again with them while the inlier count grows.

    Args:
        match: ``f(map_a, map_b) -> (keypoints_a N_A x 2, keypoints_b N_B x 2, matches K x 2, costs K)``,
            the pair matched with these scale maps (``None`` = no correction), e.g.
            :meth:`localscale.matching.Matcher.match` or :func:`describe_and_match`.
        shape_a, shape_b: ``(height, width)``.
        first_a, first_b: maps of the first matching pass (e.g. the gated network maps).
        prior_a, prior_b: network maps the refined maps start from (default: ``first_*``).
        config: :class:`VerificationConfig`.
        max_passes: matching passes at most (1 = no second pass); passes stop early when the
            inlier count does not grow or verification fails.
        seed: ``f() -> (points_a K x 2, points_b K x 2)``, another match set of the pair, verified
            (same thresholds) when the first pass is not; its geometry then refines the maps.
    Returns:
        :class:`RefinedMatching`: the matches of the pass with the most inliers (the earliest on
        ties); the refined maps of the last verified geometry of a pass that grew the inlier count
        (or of the seed), else the priors unchanged.
    """
    if max_passes < 1:
        raise LocalScaleError(f"max_passes must be >= 1, got {max_passes}")
    prior_a = first_a if prior_a is None else prior_a
    prior_b = first_b if prior_b is None else prior_b
    maps = (first_a, first_b)
    best, counts, geometry, seeded = None, [], None, None
    for i in range(max_passes):
        ka, kb, m, dist = match(maps[0], maps[1])
        m = np.asarray(m, np.int64).reshape(-1, 2)
        ka, kb, dist = np.asarray(ka), np.asarray(kb), np.asarray(dist)
        v = verify_matches(ka[m[:, 0]], kb[m[:, 1]], shape_a, shape_b, prior_a, config)
        counts.append(v.num_inliers)
        grew = best is None or v.num_inliers > best.verification.num_inliers
        if grew:
            best = RefinedMatching(ka, kb, m, dist, v, None, None, i + 1, counts, i)
        if grew and v.verified:
            geometry = v
        elif i == 0 and seed is not None:
            pa, pb = seed()
            seeded = verify_matches(pa, pb, shape_a, shape_b, prior_a, config)
            geometry = seeded if seeded.verified else None
        else:
            break
        if geometry is None:
            break
        ra, rb = refine_pair_maps(prior_a, prior_b, geometry, config)
        maps = (ra.scale, rb.scale)
        best.refined_a, best.refined_b = ra, rb
    if best.refined_a is None:
        best.refined_a, best.refined_b = (
            refine_pair_maps(prior_a, prior_b, best.verification, config)
            if geometry is None
            else refine_pair_maps(prior_a, prior_b, geometry, config)
        )
    best.passes, best.inlier_counts, best.seed = len(counts), counts, seeded
    return best


def describe_and_match(describe_a: Callable, describe_b: Callable, ratio: Optional[float] = None) -> Callable:
    """The ``match`` of :func:`refine_passes` from two describers ``f(scale_map) -> (keypoints
    N x 2, descriptors N x D)``: mutual nearest neighbours (with Lowe's ``ratio`` if given)."""

    def match(map_a, map_b):
        ka, da = describe_a(map_a)
        kb, db = describe_b(map_b)
        dist, idx = match_descriptors(da, db, ratio)
        return ka, kb, idx.numpy(), dist.numpy()

    return match


def sift_seed_points(image_a, image_b, num_features: int = 1000, ratio: float = 0.8):
    """Matches of OpenCV SIFT (DoG keypoints, top ``num_features``, SIFT descriptors, mutual nearest
    neighbours passing Lowe's ``ratio``): ``(points_a K x 2, points_b K x 2)`` float64.

    ``image_a``, ``image_b``: ``H x W x 3`` RGB or ``H x W`` uint8 arrays.
    """
    pts, descs = [], []
    for img in (image_a, image_b):
        gray = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if img.ndim == 3 else img
        kps, desc = cv2.SIFT_create(nfeatures=num_features).detectAndCompute(np.ascontiguousarray(gray), None)
        pts.append(np.array([k.pt for k in kps], np.float64).reshape(-1, 2))
        descs.append(np.zeros((0, 128), np.float32) if desc is None else desc)
    m = ratio_mutual_matches(descs[0], descs[1], ratio)
    return pts[0][m[:, 0]], pts[1][m[:, 1]]


def refine_matching(*args, **kwargs) -> RefinedMatching:
    """Deprecated name of :func:`refine_passes`; goes in the next release."""
    import warnings

    warnings.warn(
        "refine_matching is deprecated and goes in the next release: use refine_passes", DeprecationWarning, 2
    )
    return refine_passes(*args, **kwargs)
