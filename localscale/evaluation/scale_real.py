"""Scale maps on real pairs with a known homography (HPatches-layout folders): the local map,
ScaleNet's global scale as a constant map, the constant 1 and the best constant of each pair
(oracle), each as the mean scale-ratio error over the co-visible pixels of A
(:func:`localscale.evaluation.scale_maps.pixel_errors`), then the mean over pairs.

Optional columns: ``refined``, the local maps (gated) for a first HardNet matching pass, the
matches verified with a MAGSAC homography, the local map refined by the verified geometry
(:func:`localscale.matching.match_refined_pair`; an OpenCV SIFT seed when the first pass is not
verified), or the geometry ``auto`` verifies with a given matcher; where verification fails the
refined map is the local map. ``search``: the window search
(:func:`localscale.search.search_scale_map`), ScaleNet on the windows it chose and the refinement
seeded by the searched maps of both directions.

Also: co-visibility IoU of ``pred.visible``, the AUROC and calibration of ``pred.reliability``,
the pair flag on bad and good pairs, the pairs whose correction goes the wrong way, and the
identity and gray-copy invariants on the first folder's reference images.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import List, Optional

import cv2
import numpy as np
from tqdm import tqdm

from ..core.errors import LocalScaleError
from ..geometry import covisible_mask, homography_scale_map
from ..io import load_image
from .scale_maps import STRIDE, pixel_errors, real_pairs

#: a pair's true scale must be at least this far from 1 (log2) for its direction to count
DIRECTION_MIN_LOG2 = 0.5

#: the sets of the table: a selector of pair names each
GROUPS = {
    "all": lambda r: True,
    "sequences": lambda r: not r["name"].startswith("pairs/"),
    "extreme pairs": lambda r: r["name"].startswith("pairs/"),
    "bark": lambda r: "/bark/" in r["name"],
    "leuven 1-6": lambda r: r["name"].endswith("leuven/1-6"),
    "ExtremeZoom": lambda r: "ExtremeZoom" in r["name"],
}

#: the columns' titles
TITLES = {
    "local": "local map, one pass",
    "anchored": "local map anchored on ScaleNet (predict's default)",
    "search": "local map, window search",
    "refined": "refined (verified geometry, else local)",
    "global": "global ScaleNet as a constant map",
    "const1": "constant 1",
    "oracle": "best constant per pair (oracle)",
    "global-search": "global ScaleNet on the searched windows",
    "search-refined": "refined from the searched maps (verified geometry, else searched)",
}


def _verification(v, **extra) -> dict:
    return {
        "verified": bool(v.verified),
        "model": v.model,
        "num_inliers": int(v.num_inliers),
        "num_matches": int(len(v.inliers)),
        "reasons": list(v.reasons),
        **extra,
    }


def _base_row(name, fwd, g, H, shape_b) -> dict:
    """The local map's, ScaleNet's, the constant's and the oracle's errors of one pair, its
    co-visibility IoU and the reliability score on the grid."""
    pe = pixel_errors(fwd.scale, H, shape_b)
    h, w = fwd.scale.shape
    ys = np.minimum(np.arange(math.ceil(h / STRIDE)) * STRIDE + STRIDE // 2, h - 1)
    xs = np.minimum(np.arange(math.ceil(w / STRIDE)) * STRIDE + STRIDE // 2, w - 1)
    gt = homography_scale_map(H, h, w, STRIDE)
    cov = covisible_mask(H, (h, w), shape_b, STRIDE)
    m = cov & np.isfinite(gt)
    row = {
        "name": name,
        "local": pe["err"],
        "global": np.abs(math.log(g.scale) - pe["log_gt"]),
        "gt_median_log2": float(np.median(pe["log_gt"])) / math.log(2),
        "local_median_log2": float(np.median(pe["log_pred"])) / math.log(2),
        "global_log2": math.log2(g.scale),
        "const1": pe["const1"],
        "oracle": pe["oracle"],
        "log_gt": pe["log_gt"],
        "global_pair_error_log2": abs(math.log2(g.scale) - float(np.mean(pe["log_gt"])) / math.log(2)),
        "global_inconsistency_log2": abs(math.log2(g.scale_ab) + math.log2(g.scale_ba)),
    }
    if fwd.visible is not None:
        pv = fwd.visible[np.ix_(ys, xs)] > 0.5
        row["iou"] = float((pv & cov).sum() / max(1, (pv | cov).sum()))
    score = fwd.reliability if fwd.reliability is not None else fwd.confidence
    row["score"] = score[np.ix_(ys, xs)][m]
    return row


def _refined(row, local, scalenet, a, b, H, fwd, bwd, sift_seed: bool, refine_matcher) -> None:
    """``row["refined"]`` and its verification: the geometry of ``auto`` with ``refine_matcher``,
    or HardNet's refinement passes."""
    from ..matching.pipeline import match_pair, refine_predictions

    if refine_matcher is not None:
        res = match_pair(a, b, "auto", local_model=local, global_model=scalenet, matcher=refine_matcher, refine=True)
        row["refined"] = pixel_errors(res.refined_a.scale, H, b.shape[:2])["err"]
        row["verification"] = _verification(res.verification, auto=res.meta["auto"])
        return
    res = refine_predictions(a, b, fwd, bwd, sift_seed=sift_seed)
    row["refined"] = pixel_errors(res.refined_a.scale, H, b.shape[:2])["err"]
    row["verification"] = _verification(
        res.verification, inlier_counts=res.meta["inlier_counts"], seed_inliers=res.meta["seed_inliers"]
    )


def _searched(row, local, scalenet, a, b, H, refine: bool, sift_seed: bool) -> None:
    """The window search's columns, and the refinement seeded by the searched maps."""
    from ..matching.pipeline import refine_predictions
    from ..search import search_global_scale, search_scale_map

    gp, res = search_global_scale(local, scalenet, a, b)
    row["search"] = pixel_errors(res.prediction.scale, H, b.shape[:2])["err"]
    row["global-search"] = np.abs(math.log(gp.scale) - row["log_gt"])
    row["search_windows"] = {"a": res.window_a, "b": res.window_b, "score": res.score, "base_score": res.base_score}
    if refine:
        back = search_scale_map(local, b, a).prediction
        sref = refine_predictions(a, b, res.prediction, back, sift_seed=sift_seed)
        row["search-refined"] = pixel_errors(sref.refined_a.scale, H, b.shape[:2])["err"]
        row["search_refined_verified"] = bool(sref.verification.verified)


def pair_row(local, scalenet, name, a, b, H, refine=True, sift_seed=True, search=False, refine_matcher=None) -> dict:
    """Every column's per-pixel errors of one pair, with the pair statistics of the flag."""
    from ..reliability import pair_statistics

    ea, eb = local.encode_image(a), local.encode_image(b)
    fwd = local.predict_from_features(ea, eb)
    bwd = local.predict_from_features(eb, ea)
    row = _base_row(name, fwd, scalenet.predict(a, b), H, b.shape[:2])
    row["anchored"] = pixel_errors(local.predict(a, b).scale, H, b.shape[:2])["err"]
    if refine:
        _refined(row, local, scalenet, a, b, H, fwd, bwd, sift_seed, refine_matcher)
    if search:
        _searched(row, local, scalenet, a, b, H, refine, sift_seed)
    row.update(pair_statistics(fwd, bwd))
    return row


def direction_errors(rows: List[dict]) -> dict:
    """Pairs whose true scale (median over the co-visible pixels of A) is at least x1.41 away from
    1 and whose predicted scale (median of the local map there / ScaleNet's one number) lies on the
    other side of 1: the correction goes the wrong way."""
    due = [r for r in rows if abs(r["gt_median_log2"]) >= DIRECTION_MIN_LOG2]
    wrong = lambda key: [r["name"] for r in due if r[key] * r["gt_median_log2"] < 0]  # noqa: E731
    return {
        "pairs_counted": len(due),
        "rule": f"|log2 true median| >= {DIRECTION_MIN_LOG2}, prediction on the other side of 1",
        "local": len(wrong("local_median_log2")),
        "global": len(wrong("global_log2")),
        "local_pairs": wrong("local_median_log2"),
        "global_pairs": wrong("global_log2"),
    }


def columns(refined: bool, search: bool) -> tuple:
    """The table's columns, in order."""
    keys = ("local", "anchored", "refined", "global", "const1", "oracle")
    keys = keys if refined else tuple(k for k in keys if k != "refined")
    if search:
        keys = keys[:2] + ("search",) + keys[2:] + ("global-search",)
        if refined:
            keys = keys[:4] + ("search-refined",) + keys[4:]
    return keys


def _mean_r(errors) -> float:
    return float(np.exp(errors).mean())


def per_pair(r: dict, cfg) -> dict:
    """One pair's summary: each column's mean r, the scales, the flag's statistics and reasons."""
    from ..reliability import flag_reasons

    out = {
        "local_mean_r": _mean_r(r["local"]),
        "global_mean_r": _mean_r(r["global"]),
        "const1_mean_r": _mean_r(r["const1"]),
        "oracle_mean_r": _mean_r(r["oracle"]),
        "gt_median_log2": r["gt_median_log2"],
        "local_median_log2": r["local_median_log2"],
        "global_log2": r["global_log2"],
        "iou": r.get("iou"),
        "inconsistency_log2": r["inconsistency_log2"],
        "visible_fraction": r["visible_fraction"],
        "mean_reliability": r["mean_reliability"],
        "flag_reasons": flag_reasons(r, cfg),
    }
    if "refined" in r:
        out |= {"refined_mean_r": _mean_r(r["refined"]), **r["verification"]}
    if "search" in r:
        out |= {
            "search_mean_r": _mean_r(r["search"]),
            "global_search_mean_r": _mean_r(r["global-search"]),
            **r["search_windows"],
        }
    if "search-refined" in r:
        out |= {
            "search_refined_mean_r": _mean_r(r["search-refined"]),
            "search_refined_verified": r["search_refined_verified"],
        }
    return out


def refined_summary(rows: List[dict]) -> dict:
    """How many pairs verify, and how many refined maps are worse than the local one."""
    ver = [r for r in rows if r["verification"]["verified"]]
    unv = [r for r in rows if not r["verification"]["verified"]]
    worse = lambda rs: sum(_mean_r(r["refined"]) > _mean_r(r["local"]) + 1e-9 for r in rs)  # noqa: E731
    return {
        "verified_pairs": len(ver),
        "unverified_pairs": len(unv),
        "verified_refined_worse_than_local": worse(ver),
        "unverified_refined_worse_than_local": worse(unv),
        "unverified": [r["name"] for r in unv],
    }


def reliability_summary(rows: List[dict], cfg) -> dict:
    """Co-visibility IoU, the reliability AUROC (r <= 1.25 against r > 1.5) and its calibration per
    score bin, and the pair flag on bad (mean r > 2) and good (mean r < 1.3) pairs."""
    from ..reliability import auroc, flag_reasons

    ious = [r["iou"] for r in rows if "iou" in r]
    err = np.exp(np.concatenate([r["local"] for r in rows]))
    score = np.concatenate([r["score"] for r in rows])
    keep = (err <= 1.25) | (err > 1.5)
    bins = np.linspace(0, 1, 11)
    curve = []
    for lo, hi in zip(bins[:-1], bins[1:] + np.r_[np.zeros(9), 1e-9]):
        sel = (score >= lo) & (score < hi)
        share = float((err[sel] <= 1.25).mean()) if sel.any() else None
        curve.append({"score": f"{lo:.1f}-{hi:.1f}", "pixels": int(sel.sum()), "share_r_below_1.25": share})
    bad = [r for r in rows if np.exp(r["local"]).mean() > 2]
    good = [r for r in rows if np.exp(r["local"]).mean() < 1.3]
    return {
        "visibility_iou_mean": float(np.mean(ious)) if ious else None,
        "reliability_auroc": auroc(score[keep], err[keep] <= 1.25),
        "reliability_curve": curve,
        "flag": {
            "fires_on_bad (mean r > 2)": f"{sum(bool(flag_reasons(r, cfg)) for r in bad)}/{len(bad)}",
            "fires_on_good (mean r < 1.3)": f"{sum(bool(flag_reasons(r, cfg)) for r in good)}/{len(good)}",
        },
    }


def invariants(local, scalenet, root: Path) -> List[dict]:
    """``predict(A, A)``, ``predict(gray A, A)`` and ScaleNet's ``(A, A)`` on each reference image."""
    out = []
    for seq in sorted(p for p in root.iterdir() if p.is_dir()):
        a = load_image(next(iter(sorted(seq.glob("1.*")))))
        same = float(np.median(local.predict(a, a).scale))
        gray = float(np.median(local.predict(np.repeat(cv2.cvtColor(a, cv2.COLOR_RGB2GRAY)[..., None], 3, 2), a).scale))
        out.append(
            {
                "image": f"{seq.name}/1",
                "identity_median": same,
                "gray_vs_colour_median": gray,
                "global_identity": scalenet.predict(a, a).scale,
            }
        )
    return out


def evaluate_real(
    local,
    scalenet,
    roots: List[Path],
    refine: bool = True,
    sift_seed: bool = True,
    search: bool = False,
    refine_matcher: Optional[str] = None,
) -> dict:
    """Every pair of the HPatches-layout folders ``roots``: the table per set, per-pair summaries
    and the reliability, direction and invariant checks (module docstring)."""
    from ..reliability import PairCheckConfig

    options = {"refine": refine, "sift_seed": sift_seed, "search": search, "refine_matcher": refine_matcher}
    rows = [pair_row(local, scalenet, *item, **options) for item in tqdm(list(real_pairs(roots)), desc="real pairs")]
    if not rows:
        raise LocalScaleError(
            f"no image pairs (1.* + H_1_k) in the sequence folders under {', '.join(map(str, roots))}"
        )
    keys = columns(refine, search)
    cfg = PairCheckConfig()
    res = {"roots": [str(r) for r in roots], "pairs": len(rows), "stride_px": STRIDE}

    def pooled(key, sel):  # mean over pairs of each pair's mean r
        e = [_mean_r(r[key]) for r in rows if sel(r)]
        return float(np.mean(e)) if e else float("nan")

    res["table"] = {g: {k: pooled(k, sel) for k in keys} | {"pairs": sum(map(sel, rows))} for g, sel in GROUPS.items()}
    res["per_pair"] = {r["name"]: per_pair(r, cfg) for r in rows}
    res["direction_errors"] = direction_errors(rows)
    if refine:
        if search:
            res["search_refined_verified_pairs"] = sum(r["search_refined_verified"] for r in rows)
        res["refined_summary"] = refined_summary(rows)
    res.update(reliability_summary(rows, cfg))
    res["invariants"] = invariants(local, scalenet, roots[0])
    return res
