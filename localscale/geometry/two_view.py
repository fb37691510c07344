"""Two-view geometry of a match set, chosen per pair as COLMAP chooses it.

:func:`estimate_two_view_geometry` fits a homography ``H``, a fundamental matrix ``F`` and, when
both cameras' focal lengths are known, an essential matrix ``E`` (OpenCV ``USAC_MAGSAC``), and
classifies the pair with COLMAP's rules (names of ``pycolmap.TwoViewGeometryConfiguration``):

* ``E`` has at least ``min_num_inliers`` inliers and ``E``/``F`` inliers > ``min_E_F_inlier_ratio``:
  ``CALIBRATED``, unless ``H``/``E`` inliers > ``max_H_inlier_ratio`` (``PLANAR_OR_PANORAMIC``);
* else ``F`` has enough inliers: ``UNCALIBRATED``, or ``PLANAR_OR_PANORAMIC`` when
  ``H``/``F`` inliers > ``max_H_inlier_ratio``;
* else ``H`` has enough inliers: ``PLANAR_OR_PANORAMIC``; else ``DEGENERATE``.

With cameras, ``PLANAR_OR_PANORAMIC`` is resolved: ``PANORAMIC`` when a pure rotation explains the
homography's inliers (the baseline is too small to observe: no translation), else ``PLANAR``.
The relative pose (``x_B = R x_A + t``, ``|t| = 1``) then comes from ``E`` (``CALIBRATED``, by
``cv2.recoverPose``'s cheirality test on the normalised inliers), from ``K_B^T F K_A``
(``UNCALIBRATED`` with cameras), or from the decomposition of ``H`` (``PLANAR``; ``PANORAMIC``:
the rotation, ``t = 0``). The essential matrix's own pose is also kept (``R_E``, ``t_E``): the
relative-pose benchmarks (SuperGlue/LightGlue protocol) score it whatever the configuration.

Points are ``N x 2`` pixels (localscale convention: the top-left pixel's centre is ``(0, 0)``);
with cameras, ``H`` and ``F`` are fitted to undistorted pixels (same ``K``) and ``E`` to undistorted
normalised coordinates, its threshold ``max_error`` divided by the mean focal length (as COLMAP).

Example::

    from localscale.geometry.cameras import Camera
    g = estimate_two_view_geometry(pts_a, pts_b, Camera.parse("PINHOLE 640 480 500 500 320 240"),
                                   Camera.parse("PINHOLE 640 480 500 500 320 240"))
    g.configuration, g.num_inliers, g.R, g.t
    rot_err, trans_err = relative_pose_error(g.R_E, g.t_E, R_gt, t_gt)
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
from typing import List, Optional, Tuple

import cv2
import numpy as np

from ..core.errors import LocalScaleError
from .cameras import as_camera
from .relative_pose import (
    epipolar_errors,  # noqa: F401  (the protocol's match precision)
    median_triangulation_angle,
    pose_auc,  # noqa: F401  (the protocol's AUC, with the geometry)
    pose_from_essential,
    pose_from_homography,
    refine_relative_pose,
    relative_pose_error,  # noqa: F401
    rotation_fit,
    skew,
)

#: the configurations this module returns (names of ``pycolmap.TwoViewGeometryConfiguration``)
CONFIGURATIONS = ("DEGENERATE", "CALIBRATED", "UNCALIBRATED", "PLANAR", "PANORAMIC", "PLANAR_OR_PANORAMIC")

#: the model whose inliers each configuration reports
CONFIGURATION_MODEL = {
    "DEGENERATE": "none",
    "CALIBRATED": "essential",
    "UNCALIBRATED": "fundamental",
    "PLANAR": "homography",
    "PANORAMIC": "homography",
    "PLANAR_OR_PANORAMIC": "homography",
}


class TwoViewError(LocalScaleError):
    """Points or options that two-view geometry cannot use."""


@dataclass
class TwoViewConfig:
    """Thresholds of :func:`estimate_two_view_geometry` (defaults: COLMAP's ``TwoViewGeometryOptions``).

    Attributes:
        max_error: robust-estimation threshold in pixels (``H``: reprojection error in B; ``F``:
            distance to the epipolar line; ``E``: the same divided by the mean focal length).
        confidence, max_iters: RANSAC confidence and iteration cap.
        min_num_inliers: inliers a model needs to count.
        min_E_F_inlier_ratio: ``E`` inliers / ``F`` inliers above which the pair is calibrated.
        max_H_inlier_ratio: ``H`` inliers / ``E`` (or ``F``) inliers above which the pair is planar
            or panoramic.
        min_inlier_ratio: inliers / matches of the chosen model below which the pair is
            ``DEGENERATE`` (0: no check).
        panoramic_min_inlier_ratio: with cameras, the share of the homography's inliers a pure
            rotation (fitted to them) must explain within ``max_error`` for ``PANORAMIC``.
        min_tri_angle: median triangulation angle (degrees) of the inliers under which a pose's
            translation is flagged as weakly observed.
        refine_pose: refine the essential matrix's pose on its inliers (Levenberg-Marquardt on
            Sampson errors, :func:`refine_relative_pose`); ``E`` is then ``[t]x R`` of the refined pose.
        refine_loss_scale: pixels where the refinement's Huber loss turns linear (inliers of the
            ``max_error`` test that lie farther from their epipolar line count less).
        seed: OpenCV's RNG seed before estimation (reproducible results); ``None`` leaves it.
    """

    max_error: float = 4.0
    confidence: float = 0.999
    max_iters: int = 10000
    min_num_inliers: int = 15
    min_E_F_inlier_ratio: float = 0.95
    max_H_inlier_ratio: float = 0.8
    min_inlier_ratio: float = 0.0
    panoramic_min_inlier_ratio: float = 0.9
    min_tri_angle: float = 1.0
    refine_pose: bool = True
    refine_loss_scale: float = 1.0
    seed: Optional[int] = 0

    def check(self) -> "TwoViewConfig":
        if not (self.max_error > 0):
            raise TwoViewError(f"two-view max_error must be > 0, got {self.max_error}")
        if not (0 < self.confidence < 1):
            raise TwoViewError(f"two-view confidence must be in (0, 1), got {self.confidence}")
        if self.max_iters < 1 or self.min_num_inliers < 0:
            raise TwoViewError("two-view max_iters must be >= 1 and min_num_inliers >= 0")
        for name in ("min_E_F_inlier_ratio", "max_H_inlier_ratio", "min_inlier_ratio", "panoramic_min_inlier_ratio"):
            v = getattr(self, name)
            if not (0 <= v <= 1):
                raise TwoViewError(f"two-view {name} must be in [0, 1], got {v}")
        return self


@dataclass
class TwoViewGeometry:
    """Two-view geometry of ``N`` matches (:func:`estimate_two_view_geometry`).

    Attributes:
        configuration: a name of :data:`CONFIGURATIONS`.
        model: the model whose inliers are reported: ``"essential"``, ``"fundamental"``,
            ``"homography"`` or ``"none"``.
        H: ``3 x 3`` homography A -> B (pixels), ``F``: ``3 x 3`` fundamental matrix
            (``x_B^T F x_A = 0``, pixels), ``E``: ``3 x 3`` essential matrix (normalised
            coordinates); each ``None`` when not estimated.
        R, t: relative pose of the configuration, ``x_B = R x_A + t`` (``3 x 3``, ``3``, ``|t| = 1``,
            ``t = 0`` for ``PANORAMIC``); ``None`` without cameras or without a pose.
        R_E, t_E: the pose of the essential matrix (``cv2.recoverPose``), whatever the configuration.
        pose_source: ``"E"``, ``"F"``, ``"H"``, ``"rotation"`` or ``None``.
        inliers: ``N`` bool mask of the chosen model's inliers; num_inliers: their count.
        num_inliers_H, num_inliers_F, num_inliers_E: inliers of each fitted model (0 when not fitted).
        tri_angle: median triangulation angle (degrees) of the pose's inliers (``None`` without pose).
        num_matches: ``N``.
        reasons: why the result is degenerate or its pose untrustworthy (empty when it is fine).
    """

    configuration: str
    model: str
    num_matches: int
    inliers: np.ndarray
    num_inliers: int = 0
    H: Optional[np.ndarray] = None
    F: Optional[np.ndarray] = None
    E: Optional[np.ndarray] = None
    R: Optional[np.ndarray] = None
    t: Optional[np.ndarray] = None
    R_E: Optional[np.ndarray] = None
    t_E: Optional[np.ndarray] = None
    pose_source: Optional[str] = None
    num_inliers_H: int = 0
    num_inliers_F: int = 0
    num_inliers_E: int = 0
    tri_angle: Optional[float] = None
    reasons: List[str] = field(default_factory=list)

    @property
    def reliable(self) -> bool:
        """A configuration other than ``DEGENERATE`` and nothing flagged in :attr:`reasons`."""
        return self.configuration != "DEGENERATE" and not self.reasons

    @property
    def has_pose(self) -> bool:
        return self.R is not None

    def swapped(self) -> "TwoViewGeometry":
        """The same geometry seen from B (B -> A): inverse ``H``, transposed ``F`` and ``E``, inverse poses."""

        def inverse(R, t):
            return (None, None) if R is None or t is None else (R.T, -R.T @ t)

        R, t = inverse(self.R, self.t)
        R_E, t_E = inverse(self.R_E, self.t_E)
        return replace(
            self,
            H=None if self.H is None else np.linalg.inv(self.H),
            F=None if self.F is None else self.F.T,
            E=None if self.E is None else self.E.T,
            R=R,
            t=t,
            R_E=R_E,
            t_E=t_E,
            reasons=list(self.reasons),
        )

    def pycolmap_configuration(self):
        """The configuration as ``pycolmap.TwoViewGeometryConfiguration`` (needs pycolmap)."""
        from .cameras import import_pycolmap

        return getattr(import_pycolmap().TwoViewGeometryConfiguration, self.configuration)

    def to_dict(self) -> dict:
        """JSON-ready dict: matrices as nested lists, the inlier mask as a list of match indices."""
        out = {}
        for k, v in asdict(self).items():
            if k == "inliers":
                out["inlier_indices"] = np.flatnonzero(v).tolist()
            elif isinstance(v, np.ndarray):
                out[k] = v.tolist()
            else:
                out[k] = v
        out["reliable"] = self.reliable
        return out


def estimate_two_view_geometry(
    points_a, points_b, camera_a=None, camera_b=None, config: Optional[TwoViewConfig] = None
) -> TwoViewGeometry:
    """Two-view geometry of ``N`` matches, classified as COLMAP does (module docstring).

    Args:
        points_a, points_b: ``N x 2`` matched pixels in A and B (row ``i`` of both is match ``i``).
        camera_a, camera_b: the cameras (:class:`~localscale.geometry.cameras.Camera`, ``pycolmap.Camera``,
            ``cameras.txt`` line, dict or camera file), or ``None``. ``E`` is estimated when both
            have a known focal length (``has_prior_focal_length``); with both cameras given, the
            pose is computed also from ``F`` or ``H``.
        config: thresholds (default :class:`TwoViewConfig`).

    Returns:
        :class:`TwoViewGeometry`. Too few matches give ``DEGENERATE`` with a reason, not an error.

    Raises:
        TwoViewError: points that are not ``N x 2`` finite numbers of equal length, or bad options.
    """
    cfg = (config or TwoViewConfig()).check()
    pa, pb = _check_points(points_a, points_b)
    return _Estimation(pa, pb, as_camera(camera_a), as_camera(camera_b), cfg).run()


class _Estimation:
    """One :func:`estimate_two_view_geometry` of checked points, one method per stage (fit the
    models, classify, the essential matrix's pose, the configuration's pose, its triangulation
    angle), each filling :attr:`geo`."""

    def __init__(self, pa: np.ndarray, pb: np.ndarray, cam_a, cam_b, cfg: TwoViewConfig):
        self.pa, self.pb, self.cam_a, self.cam_b, self.cfg = pa, pb, cam_a, cam_b, cfg
        self.n = len(pa)
        self.geo = TwoViewGeometry("DEGENERATE", "none", self.n, np.zeros(self.n, bool))

    def run(self) -> TwoViewGeometry:
        """The stages in order, stopping at the first that leaves nothing more to estimate."""
        cfg, geo, n = self.cfg, self.geo, self.n
        need = max(cfg.min_num_inliers, 5)
        if n < need:
            geo.reasons.append(f"only {n} matches, {need} needed")
            return geo
        if cfg.seed is not None:
            cv2.setRNGSeed(int(cfg.seed))
        self.fit_models()
        if not self.classify():
            return geo
        self.essential_pose()
        if not self.both:
            return geo
        if not self.calibrated:
            geo.reasons.append("a focal length is a guess: the pose is approximate")
        if self.configuration_pose():
            self.check_triangulation()
        return geo

    def fit_models(self) -> None:
        """``H``, ``F`` and (both focal lengths known) ``E`` with their inlier masks and counts."""
        cfg, cam_a, cam_b, pa, pb = self.cfg, self.cam_a, self.cam_b, self.pa, self.pb
        self.both = both = cam_a is not None and cam_b is not None
        self.calibrated = both and cam_a.has_prior_focal_length and cam_b.has_prior_focal_length
        # H and F on undistorted pixels when the cameras are known; E on normalised coordinates
        self.ua = cam_a.undistort_points(pa) if both else pa
        self.ub = cam_b.undistort_points(pb) if both else pb

        self.H, self.mask_H = _fit_homography(self.ua, self.ub, cfg)
        self.F, self.mask_F = _fit_fundamental(self.ua, self.ub, cfg)
        self.E, self.mask_E = (None, np.zeros(self.n, bool))
        self.na = self.nb = None
        if both:
            self.na, self.nb = cam_a.normalize(pa), cam_b.normalize(pb)
        if self.calibrated:
            thr = 0.5 * (
                cam_a.pixel_threshold_to_normalized(cfg.max_error) + cam_b.pixel_threshold_to_normalized(cfg.max_error)
            )
            self.E, self.mask_E = _fit_essential(self.na, self.nb, thr, cfg)
        geo = self.geo
        geo.H, geo.F, geo.E = self.H, self.F, self.E
        geo.num_inliers_H = int(self.mask_H.sum())
        geo.num_inliers_F = int(self.mask_F.sum())
        geo.num_inliers_E = int(self.mask_E.sum())

    def classify(self) -> bool:
        """The configuration and its inliers (:func:`_classify`); False (with the reason) when degenerate."""
        cfg, geo, n = self.cfg, self.geo, self.n
        config_name, mask = _classify(cfg, self.E, self.F, self.H, self.mask_E, self.mask_F, self.mask_H)
        if config_name == "DEGENERATE":
            geo.reasons.append(
                f"no model has {cfg.min_num_inliers} inliers "
                f"(H {geo.num_inliers_H}, F {geo.num_inliers_F}, E {geo.num_inliers_E})"
            )
            return False
        if cfg.min_inlier_ratio > 0 and mask.sum() / n < cfg.min_inlier_ratio:
            geo.reasons.append(f"inlier ratio {mask.sum() / n:.2f} < {cfg.min_inlier_ratio}")
            return False
        geo.configuration, geo.inliers, geo.num_inliers = config_name, mask, int(mask.sum())
        geo.model = CONFIGURATION_MODEL[config_name]
        return True

    def essential_pose(self) -> None:
        """``R_E``, ``t_E``: the pose of ``E`` when it has enough inliers (refined if asked, ``E`` then its own)."""
        cfg, geo, cam_a, cam_b = self.cfg, self.geo, self.cam_a, self.cam_b
        if self.E is None or geo.num_inliers_E < cfg.min_num_inliers:
            return
        na, nb, mask_E = self.na, self.nb, self.mask_E
        geo.R_E, geo.t_E, _ = pose_from_essential(self.E, na[mask_E], nb[mask_E])
        if geo.R_E is not None and cfg.refine_pose:
            scale = 0.5 * (
                cam_a.pixel_threshold_to_normalized(cfg.refine_loss_scale)
                + cam_b.pixel_threshold_to_normalized(cfg.refine_loss_scale)
            )
            geo.R_E, geo.t_E = refine_relative_pose(geo.R_E, geo.t_E, na[mask_E], nb[mask_E], scale)
            geo.E = skew(geo.t_E) @ geo.R_E

    def configuration_pose(self) -> bool:
        """``R``, ``t`` and ``pose_source`` of the configuration (both cameras given); resolves
        ``PLANAR_OR_PANORAMIC``. False (with the reason) when the pose is missing or only a rotation."""
        cfg, geo, na, nb = self.cfg, self.geo, self.na, self.nb
        if geo.configuration == "CALIBRATED":
            geo.R, geo.t, geo.pose_source = geo.R_E, geo.t_E, "E"
        elif geo.configuration == "UNCALIBRATED":
            E_f = self.cam_b.K().T @ self.F @ self.cam_a.K()
            geo.R, geo.t, _ = pose_from_essential(E_f, na[self.mask_F], nb[self.mask_F])
            geo.pose_source = "F"
        else:
            mask_H = self.mask_H
            R_rot, rot_share = rotation_fit(self.ua[mask_H], self.ub[mask_H], self.cam_a, self.cam_b, cfg.max_error)
            if rot_share >= cfg.panoramic_min_inlier_ratio:
                geo.configuration, geo.R, geo.t, geo.pose_source = "PANORAMIC", R_rot, np.zeros(3), "rotation"
                geo.reasons.append("panoramic: the baseline is too small to give a translation")
                return False
            geo.configuration = "PLANAR"
            pose = pose_from_homography(self.H, self.cam_a, self.cam_b, na, nb, mask_H, cfg)
            if pose is None:
                geo.reasons.append("no decomposition of H puts the points in front of both cameras")
                return False
            geo.R, geo.t = pose
            geo.pose_source = "H"
        if geo.R is None:
            geo.reasons.append("no pose passes the cheirality test")
            return False
        return True

    def check_triangulation(self) -> None:
        """``tri_angle`` of the pose's inliers; a small one flags the translation as weakly observed."""
        cfg, geo = self.cfg, self.geo
        geo.tri_angle = median_triangulation_angle(geo.R, geo.t, self.na[geo.inliers], self.nb[geo.inliers])
        if geo.tri_angle is not None and geo.tri_angle < cfg.min_tri_angle:
            geo.reasons.append(
                f"median triangulation angle {geo.tri_angle:.2f} deg < {cfg.min_tri_angle}: translation weakly observed"
            )


def _classify(cfg, E, F, H, mask_E, mask_F, mask_H) -> Tuple[str, np.ndarray]:
    """COLMAP's decision among the fitted models: configuration name and inlier mask."""
    m = cfg.min_num_inliers
    nH, nF, nE = int(mask_H.sum()), int(mask_F.sum()), int(mask_E.sum())
    if E is not None and nE >= m and nE > cfg.min_E_F_inlier_ratio * nF:
        mask = mask_E if nE >= nF else mask_F
        if nH > cfg.max_H_inlier_ratio * nE:
            return "PLANAR_OR_PANORAMIC", (mask_H if nH > mask.sum() else mask)
        return "CALIBRATED", mask
    if F is not None and nF >= m:
        if nH > cfg.max_H_inlier_ratio * nF:
            return "PLANAR_OR_PANORAMIC", (mask_H if nH > nF else mask_F)
        return "UNCALIBRATED", mask_F
    if H is not None and nH >= m:
        return "PLANAR_OR_PANORAMIC", mask_H
    return "DEGENERATE", np.zeros_like(mask_H)


# ---------------------------------------------------------------------- robust fits
def _fit_homography(pa, pb, cfg):
    n = len(pa)
    if n < 4:
        return None, np.zeros(n, bool)
    try:
        H, mask = cv2.findHomography(
            pa, pb, cv2.USAC_MAGSAC, cfg.max_error, maxIters=cfg.max_iters, confidence=cfg.confidence
        )
    except cv2.error:
        return None, np.zeros(n, bool)
    if H is None or mask is None or not np.all(np.isfinite(H)):
        return None, np.zeros(n, bool)
    return H / H[2, 2] if abs(H[2, 2]) > 1e-12 else H, mask.ravel().astype(bool)


def _fit_fundamental(pa, pb, cfg):
    n = len(pa)
    if n < 8:
        return None, np.zeros(n, bool)
    try:
        F, mask = cv2.findFundamentalMat(pa, pb, cv2.USAC_MAGSAC, cfg.max_error, cfg.confidence, cfg.max_iters)
    except cv2.error:
        return None, np.zeros(n, bool)
    if F is None or mask is None or F.shape != (3, 3) or not np.all(np.isfinite(F)):
        return None, np.zeros(n, bool)
    return F, mask.ravel().astype(bool)


def _fit_essential(na, nb, threshold, cfg):
    n = len(na)
    if n < 5:
        return None, np.zeros(n, bool)
    try:
        E, mask = cv2.findEssentialMat(
            na, nb, np.eye(3), method=cv2.USAC_MAGSAC, prob=cfg.confidence, threshold=threshold, maxIters=cfg.max_iters
        )
    except cv2.error:
        return None, np.zeros(n, bool)
    if E is None or mask is None or E.shape[0] < 3 or not np.all(np.isfinite(E[:3])):
        return None, np.zeros(n, bool)
    return E[:3], mask.ravel().astype(bool)


# ---------------------------------------------------------------------- poses
def _check_points(points_a, points_b) -> Tuple[np.ndarray, np.ndarray]:
    try:
        pa = np.asarray(points_a, np.float64)
        pb = np.asarray(points_b, np.float64)
    except (TypeError, ValueError):
        raise TwoViewError("points must be N x 2 arrays of numbers") from None
    if pa.size == 0 and pb.size == 0:
        return np.zeros((0, 2)), np.zeros((0, 2))
    if pa.ndim != 2 or pa.shape[1] != 2 or pb.ndim != 2 or pb.shape[1] != 2:
        raise TwoViewError(f"points must be N x 2, got {pa.shape} and {pb.shape}")
    if len(pa) != len(pb):
        raise TwoViewError(f"points_a and points_b must have the same number of rows, got {len(pa)} and {len(pb)}")
    if not (np.all(np.isfinite(pa)) and np.all(np.isfinite(pb))):
        raise TwoViewError("points must be finite (no NaN or inf)")
    return np.ascontiguousarray(pa), np.ascontiguousarray(pb)
