"""Local features: detectors, patch descriptors, scale-corrected patches, keypoint scaling,
the extractors (SIFT, ALIKED, DISK, XFeat, patches), their registry and their pre-trained weights.

The submodules (torch, kornia, OpenCV) are imported on first use of a name below. The matching
names once kept here (``match_pair``, ``MatchConfig``, ...) live in :mod:`localscale.matching`;
taken from here they still work, with a :class:`DeprecationWarning`.
"""

import importlib
import warnings

from ..core.lazy import lazy_exports

_EXPORTS = {
    ".descriptors": ("HardNetDescriptor", "PatchDescriptor", "SIFTPatchDescriptor", "get_descriptor"),
    ".detector": (
        "DETECTORS",
        "HessianDetector",
        "OpenCVDetector",
        "ResponseDetector",
        "detect",
        "detect_keypoints",
        "get_detector",
        "image_to_gray_tensor",
    ),
    ".patches": ("ScaleCorrectedPatches", "extract_patches", "make_lafs", "patch_radii", "sample_scale_map"),
    ".registry": ("EXTRACTORS", "register", "get_extractor"),
    ".pretrained": ("WeightFile",),
    ".extractors": (
        "Extractor",
        "Features",
        "SIFT",
        "ALIKED",
        "DISK",
        "XFeat",
        "PatchExtractor",
        "extract",
    ),
    ".keypoint_scaling": (
        "correction_factors",
        "describe_lafs",
        "keypoint_scales",
        "keypoints_to_xy",
        "laf_from_opencv",
        "opencv_from_laf",
        "rescale_keypoint_pair",
        "rescale_keypoints",
    ),
}
#: names that moved to :mod:`localscale.matching`
_MOVED = (
    "match_descriptors",
    "matching_accuracy",
    "reprojection_errors",
    "CORRECTIONS",
    "CORRECTION_METHODS",
    "Correction",
    "NO_GATE",
    "CorrectionGate",
    "fuse_local_global",
    "get_correction",
    "models_for_correction",
    "scale_maps_for_pair",
    "MATCHERS",
    "MatchConfig",
    "Matcher",
    "Matches",
    "match_config",
    "pair_scale",
    "rectify_factors",
    "MatchResult",
    "draw_matches",
    "get_matcher",
    "match_pair",
    "refine_match",
    "run_match",
    "save_matches",
    "RefinedMatching",
    "RefinedScale",
    "VerificationConfig",
    "VerificationResult",
    "corner_error",
    "describe_and_match",
    "estimate_fundamental",
    "estimate_homography",
    "homography_auc",
    "local_affine_scales",
    "refine_matching",
    "refine_pair_maps",
    "refine_scale_map",
    "verify_matches",
)


def _moved(name):
    if name not in _MOVED:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    warnings.warn(
        f"localscale.features.{name} moved to localscale.matching.{name}; the old name will be "
        "removed in the next release",
        DeprecationWarning,
        stacklevel=3,
    )
    return getattr(importlib.import_module("localscale.matching"), name)


__all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, fallback=_moved)
