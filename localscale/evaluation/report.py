"""Reports of an HPatches-style evaluation: summaries per split and method, markdown tables, MMA plots
and the output files (``results.json``, ``splits.csv``, ``results.md``, ``mma_<split>.png``)."""

from __future__ import annotations

import csv
import io
import json
import math
import re
import subprocess
import sys
from pathlib import Path
from typing import Optional

import numpy as np

#: MMA thresholds (pixels)
THRESHOLDS = tuple(range(1, 11))
H_AUC_THRESHOLDS = (3.0, 5.0, 10.0)
SOLVED_PX = 10.0
SIFT_RATIO = 0.8
PERSPECTIVE_EDGES = (0.1, 0.25)
SCALE_EDGES = (1.0, 2.0)
ROTATION_EDGES = (30.0, 90.0)


def git_commit(package: Optional[Path] = None) -> str:
    """The commit checked out where the package ``package`` (default: localscale) lies, by ``git
    rev-parse HEAD``; ``"unknown"`` outside a git checkout of it (an installed package, no git).
    What a result file records as the code that made it."""
    package = Path(package or Path(__file__).resolve().parents[1]).resolve()
    try:
        out = subprocess.run(
            ["git", "-C", str(package), "rev-parse", "--show-toplevel", "HEAD"],
            capture_output=True,
            text=True,
            timeout=10,
            check=True,
        ).stdout.split()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    if len(out) != 2 or Path(out[0]).resolve() != package.parent:
        return "unknown"
    return out[1]


def perspective_split(spread: float) -> str:
    return "easy" if spread < PERSPECTIVE_EDGES[0] else ("medium" if spread < PERSPECTIVE_EDGES[1] else "hard")


def scale_split(log2_scale: float) -> str:
    g = abs(log2_scale)
    return "scale<2x" if g < SCALE_EDGES[0] else ("scale2-4x" if g < SCALE_EDGES[1] else "scale>4x")


def rotation_split(degrees: float) -> str:
    r = abs(degrees)
    return "rot<30" if r < ROTATION_EDGES[0] else ("rot30-90" if r <= ROTATION_EDGES[1] else "rot>90")


def summarise(records: list[dict], pairs: list, methods, thresholds) -> dict:
    """Mean MMA / matches / features per split ('all', perspective splits, scale splits) and method."""
    groups = {"all": [p.name for p in pairs]}
    for p in pairs:
        groups.setdefault(p.perspective_split, []).append(p.name)
        groups.setdefault(p.scale_split, []).append(p.name)
        groups.setdefault(p.rotation_split, []).append(p.name)
    out = {}
    for g, names in groups.items():
        names = set(names)
        out[g] = {"num_pairs": len(names)}
        for m in methods:
            rs = [r for r in records if r["method"] == m and r["pair"] in names]
            if not rs:
                continue
            out[g][m] = {
                "mma": [float(np.mean([r["mma"][i] for r in rs])) for i in range(len(thresholds))],
                "num_matches": float(np.mean([r["num_matches"] for r in rs])),
                "num_correct_3px": float(np.mean([r.get("num_correct_3px", 0) for r in rs])),
                "seconds": float(np.mean([r.get("seconds", 0) + r.get("scale_seconds", 0) for r in rs])),
                "num_features": float(np.mean([(r["num_features_a"] + r["num_features_b"]) / 2 for r in rs])),
            }
            ce = [r["corner_error"] for r in rs if "corner_error" in r]
            if ce:
                from ..matching.metrics import homography_auc

                out[g][m]["h_auc"] = homography_auc(ce, H_AUC_THRESHOLDS)
                out[g][m]["h_solved"] = float(np.mean(np.asarray(ce) < SOLVED_PX))
                out[g][m]["corner_error_median"] = float(np.median(ce))
    return out


SPLIT_ORDER = ("all", "easy", "medium", "hard", "scale<2x", "scale2-4x", "scale>4x", "rot<30", "rot30-90", "rot>90")


def matching_table(summary: dict, methods, thresholds, title: str = "") -> str:
    """One table: a row per split and method (MMA@1/3/5/10, matches, correct at 3 px, features,
    homography AUC@3/5/10 px, share solved, seconds per pair)."""
    ti = [thresholds.index(t) for t in (1, 3, 5, 10) if t in thresholds]
    head = " | ".join(f"MMA@{thresholds[i]}" for i in ti)
    hh = " | ".join(f"H AUC@{t:g}" for t in H_AUC_THRESHOLDS)
    lines = [
        f"### {title}" if title else "",
        "",
        f"| split (pairs) | method | {head} | matches | correct@3 | features | {hh} | "
        f"solved (<{SOLVED_PX:g} px) | s/pair |",
        "|---|---|" + "---|" * len(ti) + "---|---|---|" + "---|" * (len(H_AUC_THRESHOLDS) + 1) + "---|",
    ]
    for g in [s for s in SPLIT_ORDER if s in summary] + [s for s in summary if s not in SPLIT_ORDER]:
        for m in methods:
            if m not in summary[g]:
                continue
            v = summary[g][m]
            vals = " | ".join(f"{v['mma'][i]:.3f}" for i in ti)
            hv = (
                " | ".join(f"{x:.3f}" for x in v["h_auc"]) + f" | {v['h_solved']:.3f}"
                if "h_auc" in v
                else " | ".join("-" for _ in range(len(H_AUC_THRESHOLDS) + 1))
            )
            lines.append(
                f"| {g} ({summary[g]['num_pairs']}) | {m} | {vals} | {v['num_matches']:.0f} | "
                f"{v.get('num_correct_3px', 0):.0f} | {v['num_features']:.0f} | {hv} | "
                f"{v.get('seconds', 0):.2f} |"
            )
    return "\n".join(lines) + "\n"


def plot_mma(summary: dict, methods, thresholds, out: Path, tag: str = "") -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = []
    for g in summary:
        fig, ax = plt.subplots(figsize=(4.5, 3.5))
        for m in methods:
            if m in summary[g]:
                ax.plot(thresholds, summary[g][m]["mma"], marker="o", ms=3, label=m)
        ax.set_xlabel("threshold [px]")
        ax.set_ylabel("MMA")
        ax.set_ylim(0, 1)
        ax.grid(alpha=0.3)
        ax.set_title(f"{tag} {g} ({summary[g]['num_pairs']} pairs)".strip())
        ax.legend()
        fig.tight_layout()
        safe = re.sub(r"[^A-Za-z0-9_.-]", "_", g.replace("<", "lt").replace(">", "gt"))
        f = out / f"mma_{tag + '_' if tag else ''}{safe}.png"
        from ..core.outputs import atomic_path

        try:
            with atomic_path(f) as tmp:
                fig.savefig(tmp, dpi=100, format="png")
        finally:
            plt.close(fig)
        files.append(f)
    return files


def _plain(x):
    """``x`` as strict JSON data: numpy scalars as numbers, NaN/inf (e.g. the log scale of a pair
    without a defined one) as null, unknown objects as strings."""
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple, set)):
        return [_plain(v) for v in x]
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        x = x.item()
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if x is None or isinstance(x, (str, int, bool)):
        return x
    return str(x)


def write_outputs(
    result: dict, pairs: list, methods, out, thresholds=THRESHOLDS, tag: str = "", extra: Optional[dict] = None
) -> dict:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    splits = [
        {
            "pair": p.name,
            "spread_log2": round(p.spread, 4),
            "log2_global_scale": round(p.log2_scale, 4),
            "covisible": round(p.covisible, 3),
            "rotation_deg": round(p.rotation, 2),
            "perspective_split": p.perspective_split,
            "scale_split": p.scale_split,
            "rotation_split": p.rotation_split,
        }
        for p in pairs
    ]
    from ..core.outputs import write_text

    buf = io.StringIO(newline="")
    w = csv.DictWriter(buf, fieldnames=list(splits[0]) if splits else ["pair"])
    w.writeheader()
    w.writerows(splits)
    write_text(out / "splits.csv", buf.getvalue())
    doc = {
        "thresholds": list(thresholds),
        "methods": list(methods),
        "splits": splits,
        "split_rules": {
            "perspective_edges_std_log2": PERSPECTIVE_EDGES,
            "scale_edges_abs_log2": SCALE_EDGES,
            "rotation_edges_deg": ROTATION_EDGES,
        },
        **(extra or {}),
        **result,
        "commit": git_commit(),
    }
    name = f"results{'_' + tag if tag else ''}"
    write_text(out / f"{name}.json", json.dumps(_plain(doc), indent=1, allow_nan=False))
    md = matching_table(result["summary"], methods, list(thresholds), tag)
    write_text(out / f"{name}.md", md)
    plot_mma(result["summary"], methods, list(thresholds), out, tag)
    return doc


def write_table_and_json(out: Path, table: str, doc: dict) -> None:
    """``out`` (JSON: ``doc`` and the commit, :func:`git_commit`) and the table beside it (``.md``),
    each written completely or not at all."""
    from ..core.outputs import atomic_path

    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out.with_suffix(".md")) as tmp:
        tmp.write_text(table)
    with atomic_path(out) as tmp:
        tmp.write_text(json.dumps({**doc, "commit": git_commit()}, indent=1))


def one_line_errors(main, argv=None) -> int:
    """``main(argv)`` of an evaluation script, with bad input reported as one ``error:`` line and exit code 2."""
    from ..core.errors import LocalScaleError

    try:
        return main(argv)
    except (LocalScaleError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2


def __getattr__(name):
    if name == "markdown_table":  # the old name of matching_table
        import warnings

        warnings.warn(
            f"{__name__}.markdown_table is deprecated, use matching_table; it goes in the next release",
            DeprecationWarning,
            stacklevel=2,
        )
        return matching_table
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
