"""The anchored local map (the default of ``LocalScaleNet.predict``): strong zooms and quarter turns."""

import math

import cv2
import numpy as np
import pytest

from localscale import LocalScaleNet
from localscale.cli import main
from localscale.models.anchor import Anchor


@pytest.fixture(scope="module")
def local():
    return LocalScaleNet.from_pretrained()


def zoom_pair(img, zoom):
    """The image and its centre ``1/zoom`` enlarged back to its size; the mask of A that B shows."""
    h, w = img.shape[:2]
    ch, cw = round(h / zoom), round(w / zoom)
    y0, x0 = (h - ch) // 2, (w - cw) // 2
    crop = cv2.resize(img[y0 : y0 + ch, x0 : x0 + cw], (w, h), interpolation=cv2.INTER_LINEAR)
    mask = np.zeros((h, w), bool)
    mask[y0 : y0 + ch, x0 : x0 + cw] = True
    return crop, mask


def _error(scale, truth):
    return math.exp(abs(math.log(float(np.median(scale)) / truth)))


def test_strong_zooms_beat_the_plain_map_and_keep_up_with_scalenet(local, photos):
    """Zooms 4 and 6 both ways on four photos: mean error factor of the median over what B shows
    (bundled weights: anchored 1.400, plain 1.511, ScaleNet's number 1.532)."""
    errs = {"anchored": [], "plain": [], "global": []}
    for name in ("astronaut", "coffee", "chelsea", "rocket"):
        for zoom in (4, 6):
            crop, mask = zoom_pair(photos[name], zoom)
            for a, b, m, truth in ((photos[name], crop, mask, zoom), (crop, photos[name], None, 1 / zoom)):
                pred = local.predict(a, b)
                sel = (lambda s: s[m]) if m is not None else (lambda s: s)
                errs["anchored"].append(_error(sel(pred.scale), truth))
                errs["plain"].append(_error(sel(local.predict(a, b, anchor=False).scale), truth))
                errs["global"].append(_error(pred.meta["anchor"]["scale"], truth))
    mean = {k: float(np.mean(v)) for k, v in errs.items()}
    assert mean["anchored"] < 0.95 * mean["plain"] and mean["anchored"] < 1.05 * mean["global"], mean


@pytest.mark.parametrize("turns", [1, 3])
def test_a_quarter_turn_keeps_scale_one(local, photos, turns):
    img = photos["astronaut"]
    s = local.predict(img, np.ascontiguousarray(np.rot90(img, turns))).scale
    assert _error(s, 1.0) < 1.3, np.median(s)


def test_an_image_against_itself_and_swapping(local, photos):
    a = photos["coffee"]
    same = local.predict(a, a)
    assert same.meta["anchor"]["scale"] == pytest.approx(1.0, abs=1e-4) and same.meta["anchor"]["window"] is None
    assert abs(float(np.median(same.scale)) - 1) < 0.03
    b, mask = zoom_pair(a, 2)
    ab = float(np.median(np.log2(local.predict(a, b).scale[mask])))
    ba = float(np.median(np.log2(local.predict(b, a).scale)))
    assert abs(ab + ba) < 0.25, (ab, ba)


def test_a_given_anchor_is_used_and_the_plain_map_stays_available(local, photos):
    a = photos["coffee"]
    b, mask = zoom_pair(a, 3)
    plain = local.predict(a, b, anchor=False)
    assert "anchor" not in plain.meta
    given = local.predict(a, b, anchor=Anchor(3.0, 0))
    assert given.meta["anchor"]["scale"] == 3.0 and given.meta["anchor"]["window"] is not None


def test_cli_no_anchor_writes_the_plain_map(tmp_path, photos, capsys):
    a, (b, _) = photos["coffee"], zoom_pair(photos["coffee"], 4)
    cv2.imwrite(str(tmp_path / "a.png"), a[..., ::-1])
    cv2.imwrite(str(tmp_path / "b.png"), b[..., ::-1])
    args = ["predict", str(tmp_path / "a.png"), str(tmp_path / "b.png")]
    assert main(args + ["-o", str(tmp_path / "anchored")]) == 0
    assert "anchor: ScaleNet" in capsys.readouterr().err
    assert main(args + ["-o", str(tmp_path / "plain"), "--no-anchor"]) == 0
    plain = np.load(tmp_path / "plain" / "a_b_scale.npy")
    anchored = np.load(tmp_path / "anchored" / "a_b_scale.npy")
    ref = LocalScaleNet.from_pretrained().predict(tmp_path / "a.png", tmp_path / "b.png", anchor=False).scale
    np.testing.assert_allclose(plain, ref, rtol=1e-4)
    assert np.median(anchored) > 1.2 * np.median(plain)
