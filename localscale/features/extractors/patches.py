"""Patches whose size each keypoint's scale map corrects, described by a patch descriptor (the ``hardnet`` matcher)."""

from __future__ import annotations

import time
from typing import Optional, Union

import numpy as np
import torch

from ...core.checks import check_number
from ...core.errors import LocalScaleError
from ..descriptors import PRECISIONS, HardNetDescriptor, PatchDescriptor, get_descriptor
from ..detector import HessianDetector, get_detector, image_to_gray_tensor
from ..patches import ScaleCorrectedPatches, patch_radii
from ..registry import register
from .base import Extractor, Features


@register
class PatchExtractor(Extractor):
    """Keypoints of a single-scale detector, described on patches whose radius each keypoint's
    scale map corrects (``base_radius * S`` where the content is bigger in the other image).

    ``cache``: a dict kept per image by the caller; the keypoints are detected once, and a
    keypoint whose corrected radius is unchanged reuses its descriptor. Its :meth:`extract` takes
    the image's scale map where the dense extractors take a resize factor (``patch_based``).
    """

    name = "patches"
    default_conf = {
        "num_features": 1000,
        "detector": "hessian",
        "descriptor": "hardnet",
        "descriptor_precision": "auto",
        "base_radius": 16.0,
        "orientation": "upright",
    }
    max_side = 2048
    patch_based = True
    #: the paper's path: Hessian keypoints, HardNet on scale-corrected patches, mutual nearest neighbours
    matchers = {"hardnet": {}}

    @classmethod
    def check_conf(cls, conf: dict) -> dict:
        full = super().check_conf(conf)
        check_number(full["base_radius"], "base_radius", low=0.5)
        if full["descriptor_precision"] not in PRECISIONS:
            raise LocalScaleError(
                f"descriptor_precision must be one of {PRECISIONS}, got {full['descriptor_precision']!r}"
            )
        if full["orientation"] not in ("upright", "gradient"):
            raise LocalScaleError(f"orientation must be 'upright' or 'gradient', got {full['orientation']!r}")
        return full

    def __init__(self, device: str = "cpu", **conf):
        super().__init__(device, **conf)
        c = self.conf
        self.detector = get_detector(c["detector"], c["num_features"])  # an unknown name fails here
        self.descriptor = get_descriptor(c["descriptor"]).to(self.device)
        if isinstance(self.descriptor, HardNetDescriptor):
            self.descriptor.set_precision(c["descriptor_precision"])
        self.cutter = ScaleCorrectedPatches(c["base_radius"], self.descriptor.patch_size, c["orientation"])
        self.described = 0  #: patches described so far

    def detect(self, image: np.ndarray):
        """``(gray 1 x H x W, keypoints N x 2, responses N)`` of the detector."""
        gray = image_to_gray_tensor(image)
        kps, resp = self.detector(gray)
        return gray, kps, resp

    def extract(self, image: np.ndarray, scale_map=None, cache: Optional[dict] = None) -> Features:
        """Features of ``image`` with each patch's radius corrected by ``scale_map``
        (``S_{this->other}``: an ``H x W`` map, a float or None)."""
        t0 = time.perf_counter()
        cache = {} if cache is None else cache
        if "keypoints" not in cache:
            cache["keypoints"] = self.detect(image)
            cache["detect_seconds"] = time.perf_counter() - t0
        gray, kps, resp = cache["keypoints"]
        t1 = time.perf_counter()
        radii = patch_radii(kps, scale_map, self.conf["base_radius"], tuple(gray.shape[-2:]), self.cutter.deadzone_log2)
        known = cache.setdefault("descriptors", [])
        desc = torch.zeros(len(kps), self.descriptor.dim)
        todo = torch.ones(len(kps), dtype=torch.bool)
        for r, d in known:
            same = todo & (r == radii)
            desc[same] = d[same]
            todo &= ~same
        lafs = None
        if todo.all():
            patches, lafs = self.cutter.patches_from_radii(gray, kps, radii)
            desc = self.descriptor.describe(patches)
        elif todo.any():
            idx = torch.nonzero(todo).flatten()
            patches, _ = self.cutter.patches_from_radii(gray, kps[idx], radii[idx])
            desc[idx] = self.descriptor.describe(patches)
        n_new = int(todo.sum())
        self.described += n_new
        if n_new:
            known.append((radii, desc))
            cache["seconds_per_patch"] = (time.perf_counter() - t1) / n_new
        # the cost on its own: detection, and describing every patch (reused ones at the rate of these)
        seconds = cache["detect_seconds"] + cache.get("seconds_per_patch", 0.0) * len(kps)
        return Features(kps.numpy(), desc, resp.numpy(), tuple(gray.shape[-2:]), radii.numpy(), lafs, seconds=seconds)


def extract(
    image,
    scale_map=None,
    num_features: int = 1000,
    descriptor: Union[str, PatchDescriptor] = "hardnet",
    base_radius: float = 16.0,
    orientation: str = "upright",
    detector_sigma: float = 2.0,
    detector: str = "hessian",
) -> Features:
    """Detect up to ``num_features`` keypoints and describe scale-corrected patches.

    Args:
        image: path, ``H x W x 3`` uint8 array or ``1 x H x W`` float tensor.
        scale_map: ``S_{this->other}`` (``H x W``), a float, or ``None``.
        descriptor: ``"hardnet"``, ``"sift"``, a weights path or a :class:`PatchDescriptor`.
        detector_sigma: detection scale of the ``hessian`` detector.
        detector: a single-scale detector of :data:`localscale.features.detector.DETECTORS`; its
            keypoint positions are used, the patch radii come from ``base_radius`` and ``scale_map``.
    """
    gray = image_to_gray_tensor(image)
    desc = get_descriptor(descriptor)
    det = (
        HessianDetector(num_features, detector_sigma) if detector == "hessian" else get_detector(detector, num_features)
    )
    kps, resp = det(gray)
    patches, lafs, radii = ScaleCorrectedPatches(base_radius, desc.patch_size, orientation)(gray, kps, scale_map)
    return Features(kps.numpy(), desc.describe(patches), resp.numpy(), tuple(gray.shape[-2:]), radii.numpy(), lafs)
