"""Per-keypoint scales for any detector: rescaled LAFs / OpenCV keypoints cover the same content."""

import cv2
import kornia.feature as KF
import numpy as np
import pytest
import torch

from localscale import LocalScaleError
from localscale.features import (
    correction_factors,
    describe_lafs,
    extract_patches,
    image_to_gray_tensor,
    keypoint_scales,
    laf_from_opencv,
    opencv_from_laf,
    patch_radii,
    rescale_keypoint_pair,
    rescale_keypoints,
)
from localscale.geometry import homography_scale_map, project


def _ncc(p, q):
    p = p.flatten(1) - p.flatten(1).mean(1, keepdim=True)
    q = q.flatten(1) - q.flatten(1).mean(1, keepdim=True)
    return (p * q).sum(1) / (p.norm(dim=1) * q.norm(dim=1) + 1e-8)


@pytest.fixture(scope="module")
def zoom_pair(photos):
    """B = A zoomed x2 about its centre (known homography), their exact maps and keypoints in both."""
    a = cv2.resize(photos["astronaut"], (256, 256), interpolation=cv2.INTER_AREA)
    H = np.array([[2.0, 0, -128], [0, 2.0, -128], [0, 0, 1]])  # x_B = 2 x_A - 128
    b = cv2.warpPerspective(a, H, (256, 256), flags=cv2.INTER_CUBIC)
    s_a = homography_scale_map(H, 256, 256)  # S_{A->B} = 2 on A
    s_b = homography_scale_map(np.linalg.inv(H), 256, 256)  # S_{B->A} = 1/2 on B
    g = np.linspace(100, 156, 6)
    xy_a = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2).astype(np.float32)
    xy_b = project(H, xy_a).astype(np.float32)
    return a, b, s_a, s_b, xy_a, xy_b


def test_exact_maps_give_x2_radii_and_matching_patches(zoom_pair):
    a, b, s_a, s_b, xy_a, xy_b = zoom_pair
    assert np.allclose(keypoint_scales(xy_a, s_a).numpy(), 2.0, rtol=1e-3)
    assert np.allclose(keypoint_scales(xy_b, s_b).numpy(), 0.5, rtol=1e-3)
    lafs_a, lafs_b = rescale_keypoint_pair(xy_a, xy_b, s_a, s_b, base_radius=8.0)
    r_a, r_b = KF.get_laf_scale(lafs_a)[0, :, 0, 0], KF.get_laf_scale(lafs_b)[0, :, 0, 0]
    assert torch.allclose(r_a, torch.full_like(r_a, 8.0)) and torch.allclose(r_b / r_a, torch.full_like(r_a, 2.0))
    # the same rule as patch_radii (the pipeline's patches)
    assert torch.allclose(r_b, patch_radii(xy_b, s_b, 8.0, (256, 256)))
    ga, gb = image_to_gray_tensor(a), image_to_gray_tensor(b)
    corrected = _ncc(extract_patches(ga, lafs_a), extract_patches(gb, lafs_b))
    plain = _ncc(extract_patches(ga, lafs_a), extract_patches(gb, rescale_keypoints(xy_b, None, base_radius=8.0)))
    assert corrected.mean() > 0.9 and corrected.mean() > plain.mean() + 0.3


def test_opencv_keypoints_sizes_differ_by_the_zoom(zoom_pair):
    _, _, s_a, s_b, xy_a, xy_b = zoom_pair
    kps_a = [cv2.KeyPoint(float(x), float(y), 12.0, 30.0, 0.5, 1, 7) for x, y in xy_a]
    kps_b = [cv2.KeyPoint(float(x), float(y), 12.0, 30.0, 0.5, 1, 7) for x, y in xy_b]
    out_a, out_b = rescale_keypoint_pair(kps_a, kps_b, s_a, s_b)
    assert all(isinstance(k, cv2.KeyPoint) for k in out_a + out_b)
    assert [k.size for k in out_a] == pytest.approx([12.0] * len(kps_a))
    assert [k.size for k in out_b] == pytest.approx([24.0] * len(kps_b), rel=1e-4)
    k, k0 = out_b[0], kps_b[0]
    assert (*k.pt, k.angle, k.response, k.octave, k.class_id) == pytest.approx(
        (*k0.pt, k0.angle, k0.response, k0.octave, k0.class_id)
    )


def test_lafs_keep_orientation_and_shape_batched_maps(zoom_pair):
    _, _, s_a, s_b, xy_a, xy_b = zoom_pair
    xy = torch.from_numpy(np.stack([xy_a, xy_b]))
    lafs = KF.laf_from_center_scale_ori(xy, torch.full((2, len(xy_a), 1, 1), 5.0), torch.full((2, len(xy_a), 1), 40.0))
    lafs[..., 0, 0] *= 1.5  # anisotropic
    out = rescale_keypoints(lafs, torch.from_numpy(np.stack([s_a, s_b])))  # B x H x W maps from predict_batch
    assert torch.allclose(out[0], lafs[0], atol=1e-5)  # A: factor 1
    assert torch.allclose(out[1, :, :, :2], 2 * lafs[1, :, :, :2], atol=1e-4)  # B: x2 about the centre
    assert torch.allclose(out[..., 2], lafs[..., 2])
    assert torch.allclose(KF.get_laf_orientation(out), KF.get_laf_orientation(lafs), atol=1e-3)
    f = correction_factors(lafs, torch.from_numpy(np.stack([s_a, s_b])))
    assert f.shape == (2, len(xy_a)) and torch.allclose(f[1], torch.full_like(f[1], 2.0), rtol=1e-3)
    with pytest.raises(LocalScaleError, match="3 scale maps for a batch of 2"):
        rescale_keypoints(lafs, np.stack([s_a, s_b, s_a]))


def test_global_scale_deadzone_and_image_cap():
    xy = np.array([[10.0, 20.0], [30.0, 5.0]], np.float32)
    assert torch.allclose(
        KF.get_laf_scale(rescale_keypoints(xy, 0.25, base_radius=4.0))[0, :, 0, 0], torch.tensor([16.0, 16.0])
    )
    assert torch.allclose(correction_factors(xy, 0.9, deadzone_log2=0.5), torch.ones(2))
    kps = [cv2.KeyPoint(10.0, 20.0, 30.0)]
    # at most the image: size <= max(H, W)
    assert rescale_keypoints(kps, 0.125, image_shape=(40, 50))[0].size == pytest.approx(50.0)
    assert rescale_keypoints([], 0.5) == []


def test_opencv_laf_round_trip_preserves_position_size_angle():
    kps = [
        cv2.KeyPoint(12.5, 40.25, 7.0, 0.0),
        cv2.KeyPoint(100.0, 3.0, 31.0, 135.5, 0.7),
        cv2.KeyPoint(55.0, 66.0, 2.5, 359.0),
    ]
    for mr in (0.5, 6.0):
        lafs = laf_from_opencv(kps, mr_size=mr)
        assert lafs.shape == (1, 3, 2, 3)
        assert torch.allclose(KF.get_laf_scale(lafs)[0, :, 0, 0], mr * torch.tensor([7.0, 31.0, 2.5]))
        back = opencv_from_laf(lafs, mr_size=mr, responses=[k.response for k in kps])
        for k, k2 in zip(kps, back):
            assert k2.pt == pytest.approx(k.pt, abs=1e-4) and k2.size == pytest.approx(k.size, rel=1e-5)
            assert min(abs(k2.angle - k.angle), 360 - abs(k2.angle - k.angle)) < 1e-3
            assert k2.response == pytest.approx(k.response)
    # OpenCV angles are clockwise in image coordinates (y down): the patch x-axis points along them
    laf = laf_from_opencv([cv2.KeyPoint(0.0, 0.0, 2.0, 90.0)])
    assert torch.allclose(laf[0, 0, :, 0], torch.tensor([0.0, 1.0]), atol=1e-6)


def test_orientation_convention_follows_an_image_rotation(photos):
    """A keypoint and its copy in the image rotated 90 degrees clockwise (angle + 90) give the same patch."""
    img = cv2.resize(photos["coffee"], (200, 160), interpolation=cv2.INTER_AREA)
    rot = cv2.rotate(img, cv2.ROTATE_90_CLOCKWISE)  # (x, y) -> (H - 1 - y, x)
    pts = [(60.0, 50.0, 20.0), (120.0, 90.0, 65.0), (90.0, 110.0, 200.0)]
    kps = [cv2.KeyPoint(x, y, 24.0, a) for x, y, a in pts]
    kps_r = [cv2.KeyPoint(159.0 - y, x, 24.0, (a + 90.0) % 360) for x, y, a in pts]
    pa = extract_patches(image_to_gray_tensor(img), laf_from_opencv(kps))
    pr = extract_patches(image_to_gray_tensor(rot), laf_from_opencv(kps_r))
    assert _ncc(pa, pr).min() > 0.98


@pytest.mark.parametrize("descriptor", ["sift", "kornia-sift", "kornia-hardnet"])
def test_describe_lafs_with_any_patch_descriptor(zoom_pair, descriptor):
    a, b, s_a, s_b, xy_a, xy_b = zoom_pair
    desc = {
        "sift": "sift",
        "kornia-sift": KF.SIFTDescriptor(32, rootsift=True),
        "kornia-hardnet": KF.HardNet(pretrained=False),
    }[descriptor]
    lafs_a, lafs_b = rescale_keypoint_pair(xy_a, xy_b, s_a, s_b, base_radius=8.0)
    da, db = describe_lafs(a, lafs_a, desc), describe_lafs(b, lafs_b, desc)
    assert da.shape == db.shape == (len(xy_a), 128)
    if descriptor != "kornia-hardnet":  # untrained HardNet: shapes only
        nn = torch.cdist(da, db).argmin(1)
        assert (nn == torch.arange(len(xy_a))).float().mean() > 0.8


def test_bad_keypoints_are_refused():
    with pytest.raises(LocalScaleError, match="N x 2"):
        keypoint_scales(np.zeros((3, 3)), 1.0)
    with pytest.raises(LocalScaleError, match="base_radius"):
        rescale_keypoints(np.zeros((3, 2)), 1.0, base_radius=0)
    with pytest.raises(LocalScaleError, match="1 x N x 2 x 3"):
        opencv_from_laf(torch.zeros(2, 3, 2, 3))
