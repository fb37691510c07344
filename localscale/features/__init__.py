"""Keypoints, scale-corrected patches, descriptors and matching (issue 5)."""
from .descriptors import HardNetDescriptor, PatchDescriptor, SIFTPatchDescriptor, get_descriptor
from .detector import HessianDetector, detect_keypoints, image_to_gray_tensor
from .patches import ScaleCorrectedPatches, extract_patches, make_lafs, patch_radii, sample_scale_map

__all__ = ["detect_keypoints", "HessianDetector", "image_to_gray_tensor", "patch_radii", "sample_scale_map",
           "make_lafs", "extract_patches", "ScaleCorrectedPatches", "PatchDescriptor", "HardNetDescriptor",
           "SIFTPatchDescriptor", "get_descriptor"]
