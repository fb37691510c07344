"""Small plotting helpers (LightGlue ``viz2d`` style) for scale maps.

Scale maps are shown as ``log2 S`` with a diverging colormap centred on 0 (no scale
change): red = content bigger in B, blue = smaller in B. Figures fit the colour range to the map
and label the colourbar in factors (x0.5, x1, x2).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

LOG2_RANGE = 3.0  #: colour range of log2-scale plots: [-3, 3] = scales 1/8 .. 8
CMAP = "RdBu_r"


def colorize_log2_scale(scale: np.ndarray, vmax: float = LOG2_RANGE) -> np.ndarray:
    """``H x W`` scale map -> ``H x W x 3`` uint8 RGB (diverging colormap on log2 S)."""
    import matplotlib

    cmap = matplotlib.colormaps[CMAP]
    scale = np.asarray(scale)
    out = np.empty(scale.shape + (3,), np.uint8)
    step = max(1, (1 << 18) // max(1, scale.shape[-1])) if scale.ndim == 2 else len(scale)
    for y0 in range(0, len(scale), step):  # in row bands: the colormap's float RGBA is 32 bytes a pixel
        x = (np.log2(np.clip(scale[y0 : y0 + step], 1e-6, None)) / vmax + 1) / 2
        rgb = cmap(np.nan_to_num(np.clip(x, 0, 1), nan=0.5))[..., :3]
        out[y0 : y0 + step] = (rgb * 255).round()
    return out


def fitted_log2_range(*maps, percentile: float = 99.0, cap: float = LOG2_RANGE) -> float:
    """Symmetric colour range (in ``log2 S``) that fits the maps: the ``percentile`` of
    ``|log2 S|`` over the finite values, rounded up to 0.5, at least 0.5 and at most ``cap``."""
    vals = [
        np.abs(np.log2(np.asarray(m, np.float64)))[np.isfinite(np.log2(np.asarray(m, np.float64)))]
        for m in maps
        if m is not None
    ]
    vals = np.concatenate([v.ravel() for v in vals]) if vals else np.zeros(0)
    if not vals.size:
        return 1.0
    v = float(np.percentile(vals, percentile))
    return float(min(cap, max(0.5, np.ceil(v * 2) / 2)))


def factor_ticks(vmax: float) -> tuple[list[float], list[str]]:
    """Colourbar ticks on a ``log2 S`` axis of range ``[-vmax, vmax]``, labelled as factors
    (``x0.5``, ``x1``, ``x2``; half steps ``x0.71``, ``x1.41`` for ranges below 1.5)."""
    step = 1.0 if vmax >= 1.5 else 0.5
    n = int(np.floor(vmax / step + 1e-9))
    ticks = [k * step for k in range(-n, n + 1)]
    return ticks, [f"x{2.0**t:.3g}" for t in ticks]


def _factor_colorbar(fig, im, ax, vmax: float):
    ticks, labels = factor_ticks(vmax)
    cb = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.02, ticks=ticks)
    cb.ax.set_yticklabels(labels)
    cb.set_label("scale factor (log axis)")
    return cb


def plot_scale_prediction(
    image_a: np.ndarray,
    image_b: np.ndarray,
    scale: np.ndarray,
    confidence: np.ndarray | None = None,
    gt_scale: np.ndarray | None = None,
    gt_mask: np.ndarray | None = None,
    path: str | Path | None = None,
    title: str | None = None,
    visible: np.ndarray | None = None,
    sources: np.ndarray | None = None,
    points: tuple[np.ndarray, np.ndarray] | None = None,
):
    """Figure: A, B, predicted scale map (+ colourbar in factors), confidence, co-visibility
    (when ``visible`` is given), the source layer of a refined map (``sources``: 0 network,
    1 homography, 2 matches), the per-point truth (``points``: ``(xy N x 2, truth N)``, coloured
    dots on A, with the map's error at them), and GT + error if given.

    The scale maps share one symmetric colour range on ``log2 S`` fitted to the maps
    (:func:`fitted_log2_range`); the colourbar is labelled in factors (x0.5, x1, x2).
    Returns the matplotlib figure; saves it to ``path`` when given.
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    g = None
    if gt_scale is not None:
        g = np.where(gt_mask, gt_scale, np.nan) if gt_mask is not None else gt_scale
    vmax = fitted_log2_range(scale, g)
    panels = 3 + (confidence is not None) + (visible is not None) + 2 * (gt_scale is not None)
    panels += (sources is not None) + (points is not None)
    fig, axes = plt.subplots(1, panels, figsize=(3.6 * panels, 3.4), constrained_layout=True)
    axes = list(np.atleast_1d(axes))
    axes[0].imshow(image_a)
    axes[0].set_title("A")
    axes[1].imshow(image_b)
    axes[1].set_title("B")
    im = axes[2].imshow(np.log2(scale), cmap=CMAP, vmin=-vmax, vmax=vmax)
    axes[2].set_title("predicted scale S(A→B)")
    _factor_colorbar(fig, im, axes[2], vmax)
    k = 3
    if confidence is not None:
        ic = axes[k].imshow(confidence, cmap="viridis", vmin=0, vmax=1)
        axes[k].set_title("confidence")
        fig.colorbar(ic, ax=axes[k], fraction=0.046, pad=0.02)
        k += 1
    if visible is not None:
        iv = axes[k].imshow(visible, cmap="gray", vmin=0, vmax=1)
        axes[k].set_title("co-visible in B (probability)")
        fig.colorbar(iv, ax=axes[k], fraction=0.046, pad=0.02)
        k += 1
    if sources is not None:
        _sources_panel(axes[k], sources)
        k += 1
    if points is not None:
        _points_panel(fig, axes[k], image_a, scale, points, vmax)
        k += 1
    if gt_scale is not None:
        _truth_panels(fig, axes[k], axes[k + 1], scale, g, vmax)
    for ax in axes:
        ax.set_xticks([])
        ax.set_yticks([])
    if title:
        fig.suptitle(title)
    if path is not None:
        _save_figure(fig, path)
    return fig


def _truth_panels(fig, ax_truth, ax_error, scale: np.ndarray, g: np.ndarray, vmax: float) -> None:
    ig = ax_truth.imshow(np.log2(g), cmap=CMAP, vmin=-vmax, vmax=vmax)
    ax_truth.set_title("ground-truth scale S")
    _factor_colorbar(fig, ig, ax_truth, vmax)
    err = np.abs(np.log2(scale) - np.log2(g))
    ie = ax_error.imshow(err, cmap="magma", vmin=0, vmax=1.5)
    ax_error.set_title(f"|log2 error| (mean r {np.nanmean(np.exp2(err)):.2f})")
    fig.colorbar(ie, ax=ax_error, fraction=0.046, pad=0.02)


def _save_figure(fig, path) -> None:
    """``fig`` saved to ``path`` (complete file or none), then closed."""
    import matplotlib.pyplot as plt

    from .core.outputs import atomic_path

    Path(path).parent.mkdir(parents=True, exist_ok=True)
    try:
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=110, format=Path(path).suffix[1:] or None)
    finally:
        plt.close(fig)


def plot_refined_map(
    image_a: np.ndarray,
    network: np.ndarray,
    refined: np.ndarray,
    source: np.ndarray | None = None,
    gt_scale: np.ndarray | None = None,
    path: str | Path | None = None,
    title: str | None = None,
):
    """Figure: A, the network's map, the refined map (:func:`localscale.matching.refine_scale_map`),
    the ground-truth map when given (nan outside its mask) and the geometry's weight (``source``).

    The scale maps share one colour range on ``log2 S``; panel titles give the mean r against the
    ground truth where it is known. Returns the figure; saves it to ``path`` when given.
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    vmax = fitted_log2_range(network, refined, gt_scale)
    maps = [("network map", network), ("refined map", refined)] + (
        [("ground truth", gt_scale)] if gt_scale is not None else []
    )
    panels = 1 + len(maps) + (source is not None)
    fig, axes = plt.subplots(1, panels, figsize=(3.0 * panels, 2.6), constrained_layout=True)
    axes = list(np.atleast_1d(axes))
    axes[0].imshow(image_a)
    axes[0].set_title("A")
    ok = np.isfinite(gt_scale) if gt_scale is not None else None
    for ax, (name, m) in zip(axes[1:], maps):
        im = ax.imshow(np.log2(m), cmap=CMAP, vmin=-vmax, vmax=vmax)
        if ok is not None and m is not gt_scale and ok.any():
            r = np.exp(np.abs(np.log(m[ok]) - np.log(gt_scale[ok]))).mean()
            name = f"{name} (r {r:.2f})"
        ax.set_title(name, fontsize=9)
    _factor_colorbar(fig, im, axes[len(maps)], vmax)
    if source is not None:
        iw = axes[-1].imshow(source, cmap="viridis", vmin=0, vmax=1)
        axes[-1].set_title("geometry weight", fontsize=9)
        fig.colorbar(iw, ax=axes[-1], fraction=0.046, pad=0.02)
    for ax in axes:
        ax.set_xticks([])
        ax.set_yticks([])
    if title:
        fig.suptitle(title, fontsize=10)
    if path is not None:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        try:
            fig.savefig(path, dpi=80)
        finally:
            plt.close(fig)
    return fig


#: colours (RGB) of the source layer's labels: network grey, homography orange, matches green
SOURCE_COLOURS = {0: (150, 150, 150), 1: (240, 140, 30), 2: (40, 170, 80)}


def colorize_sources(layer: np.ndarray) -> np.ndarray:
    """``H x W`` source layer (0 network, 1 homography, 2 matches) -> ``H x W x 3`` uint8 RGB."""
    lut = np.zeros((256, 3), np.uint8)
    for k, c in SOURCE_COLOURS.items():
        lut[k] = c
    return lut[np.asarray(layer, np.uint8)]


def _sources_panel(ax, sources: np.ndarray) -> None:
    from matplotlib.patches import Patch

    ax.imshow(colorize_sources(sources), interpolation="nearest")
    names = {0: "network", 1: "homography", 2: "matches"}
    handles = [Patch(color=np.array(SOURCE_COLOURS[k]) / 255, label=names[k]) for k in names]
    ax.legend(handles=handles, loc="lower right", fontsize=7, framealpha=0.8)
    ax.set_title("source of each pixel")


def _points_panel(fig, ax, image_a: np.ndarray, scale: np.ndarray, points, vmax: float) -> None:
    """A dimmed, with the per-point truth as coloured dots; the title gives the map's mean error
    factor at the points."""
    xy, truth = (np.asarray(p, np.float64) for p in points)
    ok = np.isfinite(truth) & (truth > 0)
    xy, truth = xy[ok], truth[ok]
    ax.imshow((np.asarray(image_a, np.float32) * 0.5 + 64).astype(np.uint8))
    sc = ax.scatter(
        xy[:, 0], xy[:, 1], c=np.log2(truth), cmap=CMAP, vmin=-vmax, vmax=vmax, s=9, edgecolors="k", linewidths=0.3
    )
    _factor_colorbar(fig, sc, ax, vmax)
    h, w = scale.shape[:2]
    xi = np.clip(np.round(xy[:, 0]).astype(int), 0, w - 1)
    yi = np.clip(np.round(xy[:, 1]).astype(int), 0, h - 1)
    r = float(np.exp(np.abs(np.log(scale[yi, xi] / truth))).mean()) if len(truth) else float("nan")
    ax.set_title(f"3D truth at {len(truth)} points (map r {r:.2f})")
