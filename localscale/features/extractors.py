"""Local feature extractors, one small class each (hloc style: a ``default_conf``, options that replace it).

* :class:`SIFT`: OpenCV's SIFT (DoG keypoints and descriptors);
* :class:`ALIKED`, :class:`DISK`, :class:`XFeat`: kornia's models with pre-trained weights
  found on disk (:mod:`.pretrained`; nothing is downloaded);
* :class:`PatchExtractor`: a single-scale detector (Hessian by default) and a patch descriptor
  (HardNet by default) on patches whose size each keypoint's scale map corrects (the paper's path).

The dense extractors take a resize factor (:meth:`Extractor.extract`); keypoints always come back
in pixels of the image given. :data:`EXTRACTORS` maps the names a matcher configuration uses to
the classes.

Example::

    aliked = ALIKED(num_features=1024)
    f = aliked.extract(image)                  # H x W x 3 uint8 RGB
    f.keypoints, f.descriptors                 # N x 2 float32, N x 128
    f = aliked.extract(image, factor=0.5)      # extracted at half size, keypoints in the given pixels
    d = aliked.describe(image, f.keypoints, factor=2.0)  # the same keypoints described at twice the size
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Optional, Union

import cv2
import numpy as np
import torch

from ..devices import resolve_device
from ..errors import LocalScaleError
from .descriptors import HardNetDescriptor, PatchDescriptor, get_descriptor
from .detector import HessianDetector, get_detector, image_to_gray_tensor
from .patches import ScaleCorrectedPatches, patch_radii
from .pretrained import find_weights, load_weights

ALIKED_MODELS = ("aliked-n16", "aliked-n16rot", "aliked-n32", "aliked-t16")


@dataclass
class Features:
    """Local features of one image.

    Attributes:
        keypoints: ``N x 2`` float32 ``(x, y)`` in pixels of the image given to the extractor.
        descriptors: ``N x D`` float32 (L2-normalised).
        responses: ``N`` detector scores.
        image_shape: ``(H, W)`` of that image.
        radii: ``N`` patch radii (:class:`PatchExtractor`), else ``None``.
        lafs: ``1 x N x 2 x 3`` kornia LAFs (:class:`PatchExtractor`), else ``None``.
        frames: ``N x 2`` float32 ``(size, angle)``: the detector's own support diameter in pixels
            of the image given and orientation in degrees, OpenCV's convention (:class:`SIFT`), else ``None``.
        factor: the resize factor the image was extracted at (1: as given).
        seconds: the time the extraction took (also when the features come from a cache).
    """

    keypoints: np.ndarray
    descriptors: torch.Tensor
    responses: np.ndarray
    image_shape: tuple
    radii: Optional[np.ndarray] = None
    lafs: Optional[torch.Tensor] = None
    frames: Optional[np.ndarray] = None
    factor: float = 1.0
    seconds: float = 0.0

    def __len__(self) -> int:
        return len(self.keypoints)


def resize_image(image: np.ndarray, factor: float, min_side: int = 32) -> tuple[np.ndarray, float, float]:
    """``image`` resized by ``factor`` (when shrunk, the shorter side kept >= ``min_side``);
    returns it and the per-axis factors actually applied."""
    h, w = image.shape[:2]
    if factor > 1.0:
        nw, nh = max(1, round(w * factor)), max(1, round(h * factor))
        return cv2.resize(image, (nw, nh), interpolation=cv2.INTER_LINEAR), nw / w, nh / h
    factor = max(factor, min(1.0, min_side / max(1, min(h, w))))
    if factor >= 1.0:
        return image, 1.0, 1.0
    nw, nh = max(1, round(w * factor)), max(1, round(h * factor))
    return cv2.resize(image, (nw, nh), interpolation=cv2.INTER_AREA), nw / w, nh / h


def to_given_pixels(points: np.ndarray, fx: float, fy: float) -> np.ndarray:
    """Pixel coordinates of a resized image (pixel-centre convention) -> those of the given one."""
    if fx == 1.0 and fy == 1.0:
        return points
    return ((points + 0.5) / np.array([fx, fy], np.float32) - 0.5).astype(np.float32)


class Extractor:
    """Base of the extractors: their options; the dense ones ``extract(image, factor)`` -> :class:`Features`.

    Subclasses set ``default_conf`` and implement ``_extract(image) -> (xy N x 2, desc N x D, scores N)``,
    or ``(..., frames N x 2)`` for a detector with its own size and orientation (:attr:`Features.frames`).
    ``lightglue`` names the LightGlue configuration of kornia whose weights fit the descriptors (None: none).
    """

    default_conf: dict = {}
    lightglue: Optional[str] = None
    #: the image is resized by the pair's scale (True) or each keypoint's patch is (False)
    rectified: bool = True
    #: Lowe's ratio test of mutual NN matching: ``symmetric`` (kornia's) or ``a_to_b`` (as OpenCV users do)
    ratio_test: str = "symmetric"

    def __init__(self, device: str = "cpu", **conf):
        unknown = sorted(set(conf) - set(self.default_conf))
        if unknown:
            raise LocalScaleError(
                f"{type(self).__name__} has no option(s) {', '.join(unknown)}; "
                f"it takes {', '.join(sorted(self.default_conf)) or 'none'}"
            )
        self.conf = {**self.default_conf, **conf}
        self.device = resolve_device(device)

    def extract(self, image: np.ndarray, factor: float = 1.0) -> Features:
        """Features of ``image`` (``H x W x 3`` uint8 RGB) extracted at ``factor`` times its size,
        keypoints in pixels of ``image``."""
        t0 = time.perf_counter()
        img, fx, fy = resize_image(np.asarray(image), float(factor))
        xy, desc, scores, *rest = self._extract(img)
        factor = float(np.sqrt(fx * fy))
        # sizes in the given image's pixels; the orientation is unchanged by the resize
        frames = (rest[0] * np.array([1.0 / factor, 1.0], np.float32)).astype(np.float32) if rest else None
        return Features(
            to_given_pixels(xy, fx, fy),
            desc,
            scores,
            tuple(image.shape[:2]),
            frames=frames,
            factor=factor,
            seconds=time.perf_counter() - t0,
        )

    def describe(self, image: np.ndarray, keypoints: np.ndarray, factor: float = 1.0) -> Features:
        """Descriptors of given ``keypoints`` (``N x 2``, pixels of ``image``) on ``image`` resized by
        ``factor`` (what :meth:`extract` would have described there, had it detected them). ALIKED
        and DISK describe (:attr:`describes`); the others raise a :class:`LocalScaleError`."""
        if not self.describes:
            raise LocalScaleError(f"{type(self).__name__} cannot describe given keypoints")
        t0 = time.perf_counter()
        img, fx, fy = resize_image(np.asarray(image), float(factor))
        kp = np.asarray(keypoints, np.float32).reshape(-1, 2)
        xy = (kp + 0.5) * np.array([fx, fy], np.float32) - 0.5
        desc = self._describe(img, np.clip(xy, 0, [img.shape[1] - 1, img.shape[0] - 1]).astype(np.float32))
        return Features(
            kp, desc, np.zeros(len(kp), np.float32), tuple(image.shape[:2]),
            factor=float(np.sqrt(fx * fy)), seconds=time.perf_counter() - t0,
        )  # fmt: skip

    @property
    def describes(self) -> bool:
        """Whether :meth:`describe` works (the extractor implements ``_describe``)."""
        return type(self)._describe is not Extractor._describe

    def _extract(self, image: np.ndarray):
        raise NotImplementedError

    def _describe(self, image: np.ndarray, xy: np.ndarray) -> torch.Tensor:
        """``N x D`` descriptors at ``xy`` (``N x 2``, pixels of ``image``)."""
        raise NotImplementedError

    def _tensor(self, image: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1)[None].float().div(255).to(self.device)


def _outputs(xy: torch.Tensor, desc: torch.Tensor, scores: torch.Tensor):
    return (
        xy.float().cpu().numpy().astype(np.float32),
        desc.float().cpu(),
        scores.float().cpu().numpy().reshape(-1).astype(np.float32),
    )


class SIFT(Extractor):
    """OpenCV SIFT: DoG keypoints and 128-D descriptors, ``num_features`` at most."""

    default_conf = {"num_features": 4096}
    ratio_test = "a_to_b"

    def _extract(self, image: np.ndarray):
        gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
        kps, desc = cv2.SIFT_create(nfeatures=self.conf["num_features"]).detectAndCompute(
            np.ascontiguousarray(gray), None
        )
        xy = np.array([k.pt for k in kps], np.float32).reshape(-1, 2)
        d = torch.from_numpy(np.zeros((0, 128), np.float32) if desc is None else desc)
        frames = np.array([(k.size, k.angle) for k in kps], np.float32).reshape(-1, 2)
        return xy, d, np.array([k.response for k in kps], np.float32), frames


class ALIKED(Extractor):
    """kornia's ALIKED (``model``: ``aliked-n16``, ``-n16rot``, ``-n32``, ``-t16``); on CPU in the
    channels-last layout (same features, faster there)."""

    default_conf = {
        "model": "aliked-n16",
        "num_features": 2048,
        "detection_threshold": None,
        "weights": None,
        "channels_last": True,
    }
    lightglue = "aliked"

    def __init__(self, device: str = "cpu", **conf):
        super().__init__(device, **conf)
        import kornia.feature as KF

        c = self.conf
        if c["model"] not in ALIKED_MODELS:
            raise LocalScaleError(f"ALIKED model must be one of {ALIKED_MODELS}, got {c['model']!r}")
        th = 0.2 if c["detection_threshold"] is None else c["detection_threshold"]
        net = KF.ALIKED(c["model"], max_num_keypoints=c["num_features"], detection_threshold=th)
        self.net = load_weights(net, find_weights(f"{c['model']}.pth", c["weights"])).to(self.device)
        self.channels_last = c["channels_last"] and torch.device(self.device).type == "cpu"
        if self.channels_last:
            self.net.to(memory_format=torch.channels_last)

    def _extract(self, image: np.ndarray):
        t = self._tensor(image)
        if self.channels_last:
            t = t.contiguous(memory_format=torch.channels_last)
        with torch.inference_mode():
            f = self.net(t)[0]
        return _outputs(f.keypoints, f.descriptors, f.keypoint_scores)

    def _describe(self, image: np.ndarray, xy: np.ndarray) -> torch.Tensor:
        t = self._tensor(image)
        if self.channels_last:
            t = t.contiguous(memory_format=torch.channels_last)
        h, w = image.shape[:2]
        with torch.inference_mode():
            feature_map, _ = self.net.extract_dense_map(t)
            wh = torch.tensor([max(1, w - 1), max(1, h - 1)], dtype=torch.float32, device=self.device)
            normalised = torch.from_numpy(xy).to(self.device) / wh * 2 - 1  # kornia's [-1, 1] keypoints
            desc, _ = self.net.desc_head(feature_map, [normalised])
        return desc[0].float().cpu()


class DISK(Extractor):
    """kornia's DISK (the ``depth`` weights)."""

    default_conf = {"num_features": 2048, "detection_threshold": None, "weights": None}
    lightglue = "disk"

    def __init__(self, device: str = "cpu", **conf):
        super().__init__(device, **conf)
        import kornia.feature as KF

        path = find_weights("disk-depth-save.pth", self.conf["weights"])
        self.net = load_weights(KF.DISK(), path, lambda sd: sd.get("extractor", sd)).to(self.device)

    def _extract(self, image: np.ndarray):
        c = self.conf
        with torch.inference_mode():
            f = self.net(
                self._tensor(image),
                n=c["num_features"],
                score_threshold=c["detection_threshold"] or 0.0,
                pad_if_not_divisible=True,
            )[0]
        return _outputs(f.keypoints, f.descriptors, f.detection_scores)

    def _describe(self, image: np.ndarray, xy: np.ndarray) -> torch.Tensor:
        import torch.nn.functional as F

        t = self._tensor(image)
        h, w = image.shape[:2]
        t = F.pad(t, (0, -w % 16, 0, -h % 16))
        with torch.inference_mode():
            _, dense = self.net.heatmap_and_dense_descriptors(t)
            wh = torch.tensor([t.shape[3] - 1, t.shape[2] - 1], dtype=torch.float32, device=self.device)
            grid = (torch.from_numpy(xy).to(self.device) / wh * 2 - 1).view(1, -1, 1, 2)
            desc = F.grid_sample(dense, grid, mode="bilinear", align_corners=True)[0, :, :, 0].T
        return F.normalize(desc, dim=1).float().cpu()


class XFeat(Extractor):
    """kornia's XFeat (sparse keypoints, 64-D descriptors)."""

    default_conf = {"num_features": 4096, "detection_threshold": None, "weights": None}
    lightglue = "xfeat"

    def __init__(self, device: str = "cpu", **conf):
        super().__init__(device, **conf)
        import kornia.feature as KF

        net = KF.XFeat(top_k=self.conf["num_features"])
        load_weights(net.net, find_weights("xfeat.pt", self.conf["weights"]))
        self.net = net.eval().to(self.device)

    def _extract(self, image: np.ndarray):
        c = self.conf
        with torch.inference_mode():
            f = self.net.detectAndCompute(
                self._tensor(image), top_k=c["num_features"], detection_threshold=c["detection_threshold"]
            )[0]
        return _outputs(f["keypoints"], f["descriptors"], f["scores"])


class PatchExtractor(Extractor):
    """Keypoints of a single-scale detector, described on patches whose radius each keypoint's
    scale map corrects (``base_radius * S`` where the content is bigger in the other image).

    ``cache``: a dict kept per image by the caller; the keypoints are detected once, and a
    keypoint whose corrected radius is unchanged reuses its descriptor. Its :meth:`extract` takes
    the image's scale map where the dense extractors take a resize factor (``rectified = False``).
    """

    default_conf = {
        "num_features": 1000,
        "detector": "hessian",
        "descriptor": "hardnet",
        "descriptor_precision": "auto",
        "base_radius": 16.0,
        "orientation": "upright",
    }
    lightglue = None
    rectified = False
    ratio_test = "symmetric"

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


#: extractor name (as :class:`~localscale.matching.MatchConfig` names it) -> class
EXTRACTORS = {"patches": PatchExtractor, "sift": SIFT, "aliked": ALIKED, "disk": DISK, "xfeat": XFeat}


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
