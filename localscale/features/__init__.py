"""Keypoints, scale-corrected patches, descriptors and matching."""
from .descriptors import HardNetDescriptor, PatchDescriptor, SIFTPatchDescriptor, get_descriptor
from .detector import HessianDetector, detect_keypoints, image_to_gray_tensor
from .patches import ScaleCorrectedPatches, extract_patches, make_lafs, patch_radii, sample_scale_map
from .keypoint_scales import (correction_factors, describe_lafs, keypoint_scales, keypoints_to_xy, laf_from_opencv,
                              opencv_from_laf, rescale_keypoint_pair, rescale_keypoints)

__all__ = ["detect_keypoints", "HessianDetector", "image_to_gray_tensor", "patch_radii", "sample_scale_map",
           "make_lafs", "extract_patches", "ScaleCorrectedPatches", "PatchDescriptor", "HardNetDescriptor",
           "SIFTPatchDescriptor", "get_descriptor", "keypoint_scales", "correction_factors", "rescale_keypoints",
           "rescale_keypoint_pair", "laf_from_opencv", "opencv_from_laf", "keypoints_to_xy", "describe_lafs"]
from .matching import MutualNNMatcher, match_descriptors, matching_accuracy, orient_homography, reprojection_errors
from .correction import CORRECTIONS, NO_GATE, CorrectionGate, fuse_local_global, scale_maps_for_pair
from .pipeline import (Features, MatchResult, add_match_arguments, draw_matches, extract, match_pair,
                       models_for_correction, run_match, run_match_cli, save_matches)

__all__ += ["match_descriptors", "MutualNNMatcher", "reprojection_errors", "matching_accuracy", "extract",
            "match_pair", "Features", "MatchResult", "CorrectionGate", "NO_GATE", "CORRECTIONS", "draw_matches",
            "save_matches", "run_match", "run_match_cli", "add_match_arguments", "fuse_local_global",
            "scale_maps_for_pair", "models_for_correction"]
