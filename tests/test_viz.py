import numpy as np
import pytest

from localscale.viz import factor_ticks, fitted_log2_range, plot_scale_prediction


def test_colour_range_is_fitted_to_the_map():
    assert fitted_log2_range(np.full((4, 4), 1.1, np.float32)) == 0.5
    assert fitted_log2_range(np.array([[0.5, 1.0], [2.0, 1.0]])) == 1.0
    assert fitted_log2_range(np.array([[1 / 3, 3.0]])) == 2.0
    assert fitted_log2_range(np.array([[1e-3, 1e3]])) == 3.0  # capped
    assert fitted_log2_range(np.array([[1.0, 1.2]]), np.array([[np.nan, 4.0]])) == 2.0  # GT counts, NaN ignored


@pytest.mark.parametrize(
    "vmax,labels",
    [
        (0.5, ["x0.707", "x1", "x1.41"]),
        (1.0, ["x0.5", "x0.707", "x1", "x1.41", "x2"]),
        (2.0, ["x0.25", "x0.5", "x1", "x2", "x4"]),
    ],
)
def test_colourbar_is_labelled_in_factors(vmax, labels):
    ticks, text = factor_ticks(vmax)
    assert text == labels and ticks[0] == -ticks[-1] and abs(ticks[-1]) <= vmax


def test_figure_colourbar_and_visibility_panel(tmp_path):
    rng = np.random.default_rng(0)
    img = rng.integers(0, 255, (24, 32, 3), dtype=np.uint8)
    scale = np.exp2(np.linspace(-0.8, 0.8, 24 * 32)).reshape(24, 32).astype(np.float32)
    fig = plot_scale_prediction(
        img, img, scale, np.ones_like(scale), visible=np.full_like(scale, 0.5), path=tmp_path / "f.png"
    )
    assert (tmp_path / "f.png").stat().st_size > 0
    bars = [ax for ax in fig.axes if ax.get_ylabel() == "scale factor (log axis)"]
    assert len(bars) == 1
    assert [t.get_text() for t in bars[0].get_yticklabels()] == ["x0.5", "x0.707", "x1", "x1.41", "x2"]
    assert "co-visible in B (probability)" in [ax.get_title() for ax in fig.axes]
