"""Per-keypoint scales for any detector: rescale LAFs or OpenCV keypoints with a pair's scale maps.

Plug Local-ScaleNet into another pipeline: detect keypoints with any detector, sample the
pair's maps at them and enlarge each keypoint's support region so that the patches of A and B
cover the same content; then describe them with any patch descriptor (kornia's HardNet,
SIFTDescriptor, ... via :func:`kornia.feature.extract_patches_from_pyramid`) and match.

Maps: each image gets the map of its own direction, as in :mod:`.patches`: for A
``S_{A->B}`` on A's pixels (``LocalScaleNet.predict(A, B).scale``), for B ``S_{B->A}`` on B's
pixels (``predict(B, A).scale``). ``predict_batch`` maps (``B x H x W``) go with batched LAFs.

Rule: the one of :func:`.patches.patch_radii`. Each keypoint's radius is multiplied by
``max(1, 1 / S(x))`` (``S`` clamped to ``[1/8, 8]``): the image that shows the content bigger
enlarges its patch, the other keeps it. With a fixed ``base_radius`` (or plain ``N x 2``
points) the radius is exactly ``patch_radii``; otherwise each keypoint keeps its own size
(LAF scale, OpenCV ``size``) times that factor.

Use a *single-scale* detector (one octave of SIFT, ORB with ``nlevels=1``, the Hessian of
:mod:`.detector`, a fixed-size grid): a multi-scale detector already adapts its sizes to the
zoom, and correcting them again would apply the scale change twice.

Keypoint kinds (the output is of the same kind):

* ``N x 2`` array/tensor of ``(x, y)`` -> LAFs ``1 x N x 2 x 3`` (upright, radius ``base_radius``);
* a list of ``cv2.KeyPoint`` -> new ``cv2.KeyPoint`` (``size`` rescaled, the rest copied);
* kornia LAFs ``B x N x 2 x 3`` -> LAFs (shape and orientation kept, scaled about the centre).

OpenCV <-> LAF: ``LAF scale = mr_size * kp.size`` and ``angle_LAF = -kp.angle`` (the
kornia_moons convention; its ``laf_from_opencv_kpts`` uses ``mrSize=6.0``, i.e. a support of
6 keypoint sizes; the default here, 0.5, makes the patch side equal to ``kp.size``).

Example::

    pa, pb = net.predict(A, B), net.predict(B, A)
    lafs_a = rescale_keypoints(lafs_a, pa.scale)          # kornia LAFs of A
    kps_b = rescale_keypoints(kps_b, pb.scale)            # cv2.KeyPoint of B
    desc_a = describe_lafs(A, lafs_a, kornia.feature.HardNet(True))
"""

from __future__ import annotations

from typing import Optional, Sequence, Union

import cv2
import numpy as np
import torch
import torch.nn as nn
from kornia.feature import get_laf_center, get_laf_orientation, get_laf_scale, laf_from_center_scale_ori, scale_laf

from ..core.errors import LocalScaleError
from .patches import ScaleMapLike, extract_patches, make_lafs, patch_radii, sample_scale_map

MR_SIZE = 0.5  #: default LAF scale per unit of OpenCV ``size`` (patch side = ``size``)
KeypointsLike = Union[np.ndarray, torch.Tensor, Sequence[cv2.KeyPoint]]

__all__ = [
    "keypoint_scales",
    "correction_factors",
    "rescale_keypoints",
    "rescale_keypoint_pair",
    "laf_from_opencv",
    "opencv_from_laf",
    "keypoints_to_xy",
    "describe_lafs",
    "MR_SIZE",
]


def _is_cv2(keypoints) -> bool:
    return isinstance(keypoints, (list, tuple)) and (len(keypoints) == 0 or isinstance(keypoints[0], cv2.KeyPoint))


def _is_laf(keypoints) -> bool:
    return isinstance(keypoints, torch.Tensor) and keypoints.dim() == 4 and keypoints.shape[-2:] == (2, 3)


def _map(scale_map):
    """A map, a prediction (its ``.scale``), a float or None -> what ``sample_scale_map`` takes (on the CPU)."""
    if hasattr(scale_map, "scale") and not isinstance(scale_map, (float, int, np.ndarray, torch.Tensor)):
        scale_map = scale_map.scale
    if isinstance(scale_map, torch.Tensor):
        return scale_map.detach().float().cpu()
    return scale_map


def _maps_per_image(scale_map, batch: int) -> list:
    """One map per LAF batch element: a ``B x H x W`` map stack is split, anything else is shared."""
    m = _map(scale_map)
    if isinstance(m, (np.ndarray, torch.Tensor)) and m.ndim == 3 and not (m.shape[0] == 1 and batch == 1):
        if m.shape[0] != batch:
            raise LocalScaleError(f"{m.shape[0]} scale maps for a batch of {batch} LAF sets")
        return [m[i] for i in range(batch)]
    return [m] * batch


def _shape(scale_map, image_shape) -> Optional[tuple[int, int]]:
    if image_shape is not None:
        return tuple(int(v) for v in image_shape[-2:])
    if isinstance(scale_map, (np.ndarray, torch.Tensor)) and scale_map.ndim >= 2:
        return tuple(int(v) for v in scale_map.shape[-2:])
    return None


def keypoints_to_xy(keypoints: KeypointsLike) -> torch.Tensor:
    """Centres ``(x, y)``: ``N x 2`` for points and OpenCV keypoints, ``B x N x 2`` for LAFs."""
    if _is_cv2(keypoints):
        return torch.tensor([kp.pt for kp in keypoints], dtype=torch.float32).reshape(-1, 2)
    if _is_laf(keypoints):
        return get_laf_center(keypoints)
    kp = keypoints if isinstance(keypoints, torch.Tensor) else torch.as_tensor(np.asarray(keypoints, np.float32))
    if kp.dim() != 2 or kp.shape[1] != 2:
        raise LocalScaleError(
            f"keypoints must be N x 2 (x, y), a list of cv2.KeyPoint or B x N x 2 x 3 LAFs, got shape {tuple(kp.shape)}"
        )
    return kp.float()


def keypoint_scales(
    keypoints: KeypointsLike, scale_map: ScaleMapLike, image_shape: Optional[tuple[int, int]] = None
) -> torch.Tensor:
    """``S_{this->other}`` at each keypoint (bilinear in ``log S``; non-finite samples are 1).

    Args:
        keypoints: ``N x 2``, a list of ``cv2.KeyPoint`` or LAFs ``B x N x 2 x 3``.
        scale_map: this image's map (``H x W``; ``B x H x W`` with batched LAFs), a prediction
            (its ``.scale``), a float or None.
        image_shape: ``(H, W)`` of the image when the map has another resolution.

    Returns:
        ``N`` (``B x N`` for LAFs) float32 scales on the keypoints' device.
    """
    xy = keypoints_to_xy(keypoints)
    if xy.dim() == 3:
        maps = _maps_per_image(scale_map, xy.shape[0])
        s = (
            torch.stack([sample_scale_map(m, xy[i].detach().cpu(), _shape(m, image_shape)) for i, m in enumerate(maps)])
            if xy.shape[0]
            else torch.zeros(0, xy.shape[1])
        )
        return s.to(xy.device)
    m = _map(scale_map)
    return sample_scale_map(m, xy.detach().cpu(), _shape(m, image_shape)).to(xy.device)


def correction_factors(
    keypoints: KeypointsLike,
    scale_map: ScaleMapLike,
    image_shape: Optional[tuple[int, int]] = None,
    deadzone_log2: float = 0.0,
) -> torch.Tensor:
    """The enlargement ``max(1, 1 / clamp(S, 1/8, 8))`` of each keypoint's radius
    (:func:`.patches.patch_radii` with a unit radius): ``N`` or ``B x N`` for LAFs."""
    xy = keypoints_to_xy(keypoints)
    if xy.dim() == 3:
        maps = _maps_per_image(scale_map, xy.shape[0])
        f = (
            torch.stack(
                [
                    patch_radii(xy[i].detach().cpu(), m, 1.0, _shape(m, image_shape), deadzone_log2)
                    for i, m in enumerate(maps)
                ]
            )
            if xy.shape[0]
            else torch.zeros(0, xy.shape[1])
        )
        return f.to(xy.device)
    m = _map(scale_map)
    return patch_radii(xy.detach().cpu(), m, 1.0, _shape(m, image_shape), deadzone_log2).to(xy.device)


def _cap(radius: torch.Tensor, own: torch.Tensor, shape: Optional[tuple[int, int]]) -> torch.Tensor:
    """``patch_radii``'s limit: a patch never exceeds the image (``r <= max(H, W) / 2``), unless
    the keypoint's own radius already does."""
    if shape is None:
        return radius
    return torch.minimum(radius, torch.clamp(own, min=max(shape) / 2.0))


def rescale_keypoints(
    keypoints: KeypointsLike,
    scale_map: ScaleMapLike,
    image_shape: Optional[tuple[int, int]] = None,
    base_radius: Optional[float] = None,
    deadzone_log2: float = 0.0,
    mr_size: float = MR_SIZE,
):
    """Enlarge each keypoint's support so that the pair's patches cover the same content.

    Args:
        keypoints: ``N x 2`` points, a list of ``cv2.KeyPoint`` or kornia LAFs ``B x N x 2 x 3``.
        scale_map: ``S_{this->other}`` on this image (``H x W``, ``B x H x W`` for batched LAFs,
            a prediction with ``.scale``), a float (global scale) or None (no correction).
        image_shape: ``(H, W)`` of the image (default: the map's); caps radii at ``max(H, W) / 2``.
        base_radius: radius (pixels, = LAF scale) before correction for every keypoint, which then
            gets exactly ``patch_radii``; None keeps each keypoint's own size (16 for points).
        deadzone_log2: corrections with ``|log2 S|`` below this are skipped.
        mr_size: LAF scale per unit of OpenCV ``size`` (only with ``base_radius`` for OpenCV keypoints).

    Returns:
        The same kind as ``keypoints``: LAFs ``1 x N x 2 x 3`` for points, new ``cv2.KeyPoint``
        (rescaled ``size``) for OpenCV keypoints, LAFs for LAFs (orientation and shape kept).
    """
    if base_radius is not None and base_radius <= 0:
        raise LocalScaleError(f"base_radius must be > 0, got {base_radius}")
    m = _map(scale_map) if not _is_laf(keypoints) else scale_map
    if _is_laf(keypoints):
        lafs = keypoints
        if lafs.shape[1] == 0:
            return lafs.clone()
        f = correction_factors(lafs, scale_map, image_shape, deadzone_log2).to(lafs.dtype)
        maps = _maps_per_image(scale_map, lafs.shape[0])
        own = get_laf_scale(lafs)[..., 0, 0]
        target = (torch.full_like(own, float(base_radius)) if base_radius is not None else own) * f
        target = torch.stack(
            [
                _cap(
                    target[i],
                    own[i] if base_radius is None else torch.full_like(own[i], base_radius),
                    _shape(mp, image_shape),
                )
                for i, mp in enumerate(maps)
            ]
        )
        return scale_laf(lafs, (target / own)[..., None, None])
    shape = _shape(m, image_shape)
    if _is_cv2(keypoints):
        if not keypoints:
            return []
        f = correction_factors(keypoints, m, shape, deadzone_log2)
        own = torch.tensor([kp.size for kp in keypoints], dtype=torch.float32)
        base = own if base_radius is None else torch.full_like(own, base_radius / mr_size)
        size = _cap(base * f * mr_size, base * mr_size, shape) / mr_size
        return [
            cv2.KeyPoint(kp.pt[0], kp.pt[1], float(s), kp.angle, kp.response, kp.octave, kp.class_id)
            for kp, s in zip(keypoints, size.tolist())
        ]
    xy = keypoints_to_xy(keypoints)
    radii = patch_radii(xy.detach().cpu(), m, 16.0 if base_radius is None else base_radius, shape, deadzone_log2)
    return make_lafs(xy.detach().cpu(), radii).to(xy.device)


def rescale_keypoint_pair(
    keypoints_a: KeypointsLike,
    keypoints_b: KeypointsLike,
    scale_a: ScaleMapLike,
    scale_b: ScaleMapLike,
    shape_a: Optional[tuple[int, int]] = None,
    shape_b: Optional[tuple[int, int]] = None,
    **kwargs,
):
    """:func:`rescale_keypoints` on both images of a pair: ``scale_a`` = ``S_{A->B}`` on A
    (``predict(A, B)``), ``scale_b`` = ``S_{B->A}`` on B (``predict(B, A)``). Returns ``(a, b)``."""
    return (
        rescale_keypoints(keypoints_a, scale_a, shape_a, **kwargs),
        rescale_keypoints(keypoints_b, scale_b, shape_b, **kwargs),
    )


def laf_from_opencv(
    keypoints: Sequence[cv2.KeyPoint], mr_size: float = MR_SIZE, device: Union[str, torch.device] = "cpu"
) -> torch.Tensor:
    """OpenCV keypoints -> kornia LAFs ``1 x N x 2 x 3``: scale ``mr_size * size``, angle
    ``-kp.angle`` (an angle of -1, "not applicable", is read as 0)."""
    if not _is_cv2(keypoints):
        raise LocalScaleError(f"expected a list of cv2.KeyPoint, got {type(keypoints).__name__}")
    n = len(keypoints)
    xy = torch.tensor([kp.pt for kp in keypoints], dtype=torch.float32).reshape(1, n, 2)
    scale = torch.tensor([mr_size * kp.size for kp in keypoints], dtype=torch.float32).reshape(1, n, 1, 1)
    ang = torch.tensor([-kp.angle if kp.angle >= 0 else 0.0 for kp in keypoints], dtype=torch.float32).reshape(1, n, 1)
    return laf_from_center_scale_ori(xy, scale, ang).to(device)


def opencv_from_laf(lafs: torch.Tensor, mr_size: float = MR_SIZE, responses=None) -> list:
    """Kornia LAFs ``1 x N x 2 x 3`` -> OpenCV keypoints (``size = scale / mr_size``,
    ``angle = -orientation`` in [0, 360)); the inverse of :func:`laf_from_opencv`."""
    if not _is_laf(lafs) or lafs.shape[0] != 1:
        raise LocalScaleError(f"expected LAFs of shape 1 x N x 2 x 3, got {tuple(getattr(lafs, 'shape', ()))}")
    xy = get_laf_center(lafs)[0].detach().cpu().tolist()
    size = (get_laf_scale(lafs)[0, :, 0, 0] / mr_size).detach().cpu().tolist()
    ang = ((-get_laf_orientation(lafs)[0, :, 0]) % 360.0).detach().cpu().tolist()
    resp = [0.0] * len(xy) if responses is None else [float(r) for r in np.asarray(responses).reshape(-1)]
    return [
        cv2.KeyPoint(float(p[0]), float(p[1]), float(s), float(a) % 360.0, r) for p, s, a, r in zip(xy, size, ang, resp)
    ]


@torch.no_grad()
def describe_lafs(
    image, lafs: torch.Tensor, descriptor: Union[str, nn.Module] = "hardnet", patch_size: Optional[int] = None
) -> torch.Tensor:
    """Describe the patches of LAFs with any patch descriptor.

    Args:
        image: this image (path, ``H x W x 3`` uint8, ``1 x 1 x H x W`` gray tensor in [0, 1]).
        lafs: ``1 x N x 2 x 3`` (e.g. from :func:`rescale_keypoints`).
        descriptor: ``"hardnet"`` / ``"sift"`` (:func:`.descriptors.get_descriptor`) or any module
            mapping ``N x 1 x PS x PS`` patches to ``N x D`` (``kornia.feature.HardNet``,
            ``kornia.feature.SIFTDescriptor``, ...).
        patch_size: PS (default: the descriptor's ``patch_size`` attribute, else 32).

    Returns:
        ``N x D`` descriptors (CPU; patches cut from the pyramid level matching each LAF's size).
    """
    from .descriptors import PatchDescriptor, get_descriptor
    from .detector import image_to_gray_tensor

    desc = get_descriptor(descriptor) if isinstance(descriptor, str) else descriptor
    ps = patch_size or getattr(desc, "patch_size", None) or 32
    gray = image_to_gray_tensor(image)
    patches = extract_patches(gray, lafs.detach().cpu(), ps)
    if isinstance(desc, PatchDescriptor):
        return desc.describe(patches)
    was_training = desc.training
    desc.eval()
    dev = next(iter(desc.parameters()), torch.empty(0)).device
    out = desc(patches.to(dev)).cpu() if len(patches) else torch.zeros(0, 128)
    desc.train(was_training)
    return out
