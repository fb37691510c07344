"""Small plotting helpers (LightGlue ``viz2d`` style) for scale maps.

Scale maps are shown as ``log2 S`` with a diverging colormap centred on 0 (no scale
change): red = content bigger in B, blue = smaller in B.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

LOG2_RANGE = 3.0   #: colour range of log2-scale plots: [-3, 3] = scales 1/8 .. 8
CMAP = "RdBu_r"


def colorize_log2_scale(scale: np.ndarray, vmax: float = LOG2_RANGE) -> np.ndarray:
    """``H x W`` scale map -> ``H x W x 3`` uint8 RGB (diverging colormap on log2 S)."""
    import matplotlib

    cmap = matplotlib.colormaps[CMAP]
    x = (np.log2(np.clip(scale, 1e-6, None)) / vmax + 1) / 2
    rgb = cmap(np.nan_to_num(np.clip(x, 0, 1), nan=0.5))[..., :3]
    return (rgb * 255).round().astype(np.uint8)


def plot_scale_prediction(image_a: np.ndarray, image_b: np.ndarray, scale: np.ndarray,
                          confidence: np.ndarray | None = None, gt_scale: np.ndarray | None = None,
                          gt_mask: np.ndarray | None = None, path: str | Path | None = None,
                          title: str | None = None):
    """Figure: A, B, predicted log2 scale (+ colorbar), confidence, and GT + error if given.

    Returns the matplotlib figure; saves it to ``path`` when given.
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    panels = 3 + (confidence is not None) + 2 * (gt_scale is not None)
    fig, axes = plt.subplots(1, panels, figsize=(3.6 * panels, 3.4), constrained_layout=True)
    axes = list(np.atleast_1d(axes))
    axes[0].imshow(image_a)
    axes[0].set_title("A")
    axes[1].imshow(image_b)
    axes[1].set_title("B")
    im = axes[2].imshow(np.log2(scale), cmap=CMAP, vmin=-LOG2_RANGE, vmax=LOG2_RANGE)
    axes[2].set_title("predicted log2 S(A→B)")
    fig.colorbar(im, ax=axes[2], fraction=0.046, pad=0.02)
    k = 3
    if confidence is not None:
        ic = axes[k].imshow(confidence, cmap="viridis", vmin=0, vmax=1)
        axes[k].set_title("confidence")
        fig.colorbar(ic, ax=axes[k], fraction=0.046, pad=0.02)
        k += 1
    if gt_scale is not None:
        g = np.where(gt_mask, gt_scale, np.nan) if gt_mask is not None else gt_scale
        ig = axes[k].imshow(np.log2(g), cmap=CMAP, vmin=-LOG2_RANGE, vmax=LOG2_RANGE)
        axes[k].set_title("ground truth log2 S")
        fig.colorbar(ig, ax=axes[k], fraction=0.046, pad=0.02)
        err = np.abs(np.log2(scale) - np.log2(g))
        ie = axes[k + 1].imshow(err, cmap="magma", vmin=0, vmax=1.5)
        axes[k + 1].set_title(f"|log2 error| (mean r {np.nanmean(np.exp2(err)):.2f})")
        fig.colorbar(ie, ax=axes[k + 1], fraction=0.046, pad=0.02)
    for ax in axes:
        ax.set_xticks([])
        ax.set_yticks([])
    if title:
        fig.suptitle(title)
    if path is not None:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path, dpi=110)
        plt.close(fig)
    return fig
