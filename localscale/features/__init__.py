"""Keypoints, scale-corrected patches, descriptors and matching.

The submodules (torch, kornia, OpenCV) are imported on first use of a name below.
"""
import importlib

_EXPORTS = {
    ".descriptors": ("HardNetDescriptor", "PatchDescriptor", "SIFTPatchDescriptor", "get_descriptor"),
    ".detector": ("DETECTORS", "HessianDetector", "OpenCVDetector", "ResponseDetector", "detect", "detect_keypoints",
                  "get_detector", "image_to_gray_tensor"),
    ".patches": ("ScaleCorrectedPatches", "extract_patches", "make_lafs", "patch_radii", "sample_scale_map"),
    ".matching": ("match_descriptors", "matching_accuracy", "orient_homography",
                  "reprojection_errors"),
    ".correction": ("CORRECTIONS", "CORRECTION_METHODS", "Correction", "NO_GATE", "CorrectionGate", "fuse_local_global",
                    "get_correction", "models_for_correction", "scale_maps_for_pair"),
    ".matchers": ("MATCHERS", "MatchConfig", "Matcher", "Matches", "Features", "extract", "match_config", "pair_scale",
                  "rectify_factors"),
    ".keypoint_scaling": ("correction_factors", "describe_lafs", "keypoint_scales", "keypoints_to_xy",
                         "laf_from_opencv", "opencv_from_laf", "rescale_keypoint_pair", "rescale_keypoints"),
    ".pipeline": ("MatchResult", "draw_matches", "get_matcher", "match_pair", "refine_match", "run_match",
                  "save_matches"),
    ".verification": ("RefinedMatching", "RefinedScale", "VerificationConfig", "VerificationResult", "corner_error",
                      "describe_and_match", "estimate_fundamental", "estimate_homography", "homography_auc", "local_affine_scales",
                      "refine_matching", "refine_pair_maps", "refine_scale_map", "verify_matches"),
}
_WHERE = {name: mod for mod, names in _EXPORTS.items() for name in names}

__all__ = ["detect_keypoints", "detect", "get_detector", "DETECTORS", "ResponseDetector", "OpenCVDetector",
           "HessianDetector", "image_to_gray_tensor", "patch_radii", "sample_scale_map",
           "make_lafs", "extract_patches", "ScaleCorrectedPatches", "PatchDescriptor", "HardNetDescriptor",
           "SIFTPatchDescriptor", "get_descriptor", "keypoint_scales", "correction_factors", "rescale_keypoints",
           "rescale_keypoint_pair", "laf_from_opencv", "opencv_from_laf", "keypoints_to_xy", "describe_lafs"]
__all__ += ["match_descriptors", "reprojection_errors", "matching_accuracy", "extract",
            "match_pair", "get_matcher", "Features", "MatchResult", "CorrectionGate", "NO_GATE", "CORRECTIONS",
            "CORRECTION_METHODS", "Correction", "get_correction", "draw_matches", "save_matches", "run_match",
            "fuse_local_global", "scale_maps_for_pair", "models_for_correction", "refine_match", "MATCHERS",
            "MatchConfig", "Matcher", "Matches", "match_config", "pair_scale", "rectify_factors", "describe_and_match", "VerificationConfig", "VerificationResult",
            "RefinedScale", "RefinedMatching", "verify_matches", "refine_scale_map", "refine_pair_maps",
            "refine_matching", "estimate_homography", "estimate_fundamental", "local_affine_scales", "corner_error",
            "homography_auc"]


def __getattr__(name):
    mod = _WHERE.get(name)
    if mod is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(mod, __name__), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))
