"""MMA of other keypoint detectors with and without the scale maps, as one markdown table.

    OMP_NUM_THREADS=1 python eval/detector_table.py ROOT -o results/detectors

For every detector x descriptor it runs the HPatches-style evaluation
(:func:`localscale.evaluation.hpatches.evaluate`, methods ``none`` and ``local``, the default
``CorrectionGate``) on the sequences of ``ROOT`` and writes ``OUT/<detector>_<descriptor>.json``
(the evaluation's records and summary, plus the versions used). A combination whose JSON is
already in ``OUT`` is not run again (``--force`` re-runs it, e.g. after new weights), so an
interrupted run resumes. Then ``OUT/table.md`` and ``OUT/table.json`` are built from all the
JSON files in ``OUT``: MMA@5 over all pairs and over the ``hard`` perspective split, and the
mean number of matches, for each method.

A detector this installation cannot run (``akaze`` on OpenCV 5) is skipped with a note; run
the script again for it in an environment that has it, with the same ``-o``, and the table
includes it (its row names the OpenCV version).
"""

import argparse
import json
import sys
import time
from pathlib import Path

import torch

from localscale.core.errors import LocalScaleError
from localscale.evaluation.hpatches import evaluate, load_hpatches, load_scale_models, make_pairs
from localscale.evaluation.report import git_commit
from localscale.features.detector import DETECTORS, get_detector

DEFAULT_DETECTORS = ("hessian", "sift", "orb", "akaze", "harris", "gftt", "dog")


def run_one(pairs, detector, descriptor, methods, models, args) -> dict:
    import cv2
    import kornia

    t0 = time.time()
    res = evaluate(
        pairs,
        methods,
        "hardnet",
        models.get("local"),
        models.get("global"),
        max_side=0,
        progress=not args.quiet,
        descriptor=descriptor,
        num_features=args.num_features,
        detector=detector,
    )
    return {
        "detector": detector,
        "descriptor": descriptor,
        "methods": list(methods),
        "root": str(args.root),
        "num_features": args.num_features,
        "local_weights": args.local_weights or "bundled",
        "versions": {"opencv": cv2.__version__, "torch": torch.__version__, "kornia": kornia.__version__},
        "seconds": round(time.time() - t0, 1),
        **res,
    }


def table(docs: list, methods) -> tuple[str, list]:
    """Markdown table and rows (MMA@5 all / hard, matches) of the result documents."""
    rows = []
    for d in docs:
        s = d["summary"]
        row = {
            "detector": d["detector"],
            "descriptor": d["descriptor"],
            "opencv": d["versions"]["opencv"],
            "pairs": s["all"]["num_pairs"],
            "hard_pairs": s.get("hard", {}).get("num_pairs", 0),
            "features": round(s["all"][methods[0]]["num_features"]),
        }
        for m in methods:
            row[f"mma5_{m}"] = s["all"][m]["mma"][4]
            row[f"mma5_hard_{m}"] = s["hard"][m]["mma"][4] if m in s.get("hard", {}) else None
            row[f"matches_{m}"] = s["all"][m]["num_matches"]
        rows.append(row)
    order = {n: i for i, n in enumerate(DETECTORS)}
    rows.sort(key=lambda r: (order.get(r["detector"], 99), r["descriptor"] != "hardnet", r["descriptor"]))
    versions = [r["opencv"] for r in rows]
    usual_cv = max(set(versions), key=versions.count) if versions else ""
    fmt = lambda v: "-" if v is None else f"{v:.3f}"  # noqa: E731
    pairs = rows[0]["pairs"] if rows else 0
    hard = rows[0]["hard_pairs"] if rows else 0
    head = (
        " | ".join(f"MMA@5 {m}" for m in methods)
        + " | "
        + " | ".join(f"hard ({hard}) {m}" for m in methods)
        + " | "
        + " | ".join(f"matches {m}" for m in methods)
    )
    lines = [
        f"| detector + descriptor ({pairs} pairs) | features | {head} |",
        "|---|---|" + "---|" * (3 * len(methods)),
    ]
    for r in rows:
        name = f"{r['detector']} + {r['descriptor']}"
        if r["opencv"] != usual_cv and r["detector"] in ("sift", "orb", "akaze"):
            name += f" (OpenCV {r['opencv']})"
        vals = (
            [fmt(r[f"mma5_{m}"]) for m in methods]
            + [fmt(r[f"mma5_hard_{m}"]) for m in methods]
            + [f"{r[f'matches_{m}']:.0f}" for m in methods]
        )
        lines.append(f"| {name} | {r['features']} | " + " | ".join(vals) + " |")
    return "\n".join(lines) + "\n", rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("root", help="folder of sequences (HPatches layout)")
    p.add_argument("-o", "--out", default="results/detectors", help="output folder (default: %(default)s)")
    p.add_argument("--detectors", nargs="+", default=list(DEFAULT_DETECTORS), help=f"of {', '.join(DETECTORS)}")
    p.add_argument("--descriptors", nargs="+", default=["hardnet", "sift"], help="hardnet | sift")
    p.add_argument("--methods", nargs="+", default=["none", "local"], choices=["none", "local", "global", "gt"])
    p.add_argument("--num-features", type=int, default=1000)
    p.add_argument("--local-weights", default=None, help="Local-ScaleNet checkpoint (default: bundled)")
    p.add_argument("--global-weights", default=None, help="ScaleNet checkpoint (default: bundled)")
    p.add_argument("--force", action="store_true", help="re-run combinations whose JSON exists")
    p.add_argument("--table-only", action="store_true", help="only rebuild the table from OUT/*.json")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    out = Path(args.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
        if not args.table_only:
            unknown = [d for d in args.detectors if d not in DETECTORS]
            if unknown:
                raise LocalScaleError(f"unknown detector {unknown[0]!r}; choose from {', '.join(DETECTORS)}")
            pairs = make_pairs(load_hpatches(args.root))
            methods = list(args.methods)
            models, notes = load_scale_models(methods, args.local_weights, args.global_weights)
            for n in notes:
                print("note:", n)
            for det in args.detectors:
                try:
                    get_detector(det)
                except LocalScaleError as e:
                    print(f"note: {det} skipped: {e}", flush=True)
                    continue
                for desc in args.descriptors:
                    f = out / f"{det}_{desc}.json"
                    if f.is_file() and not args.force:
                        print(f"{f} exists, kept (--force re-runs it)", flush=True)
                        continue
                    doc = {**run_one(pairs, det, desc, methods, models, args), "commit": git_commit()}
                    f.write_text(json.dumps(doc, indent=1))
                    a = doc["summary"]["all"]
                    print(
                        f"{det} + {desc}: "
                        + ", ".join(f"MMA@5 {m} {a[m]['mma'][4]:.3f}" for m in methods)
                        + f" ({doc['seconds']:.0f} s)",
                        flush=True,
                    )
        docs = [json.loads(f.read_text()) for f in sorted(out.glob("*.json")) if f.name != "table.json"]
        if not docs:
            raise LocalScaleError(f"no results in {out}")
        methods = docs[0]["methods"]
        md, rows = table(docs, methods)
        (out / "table.md").write_text(md)
        (out / "table.json").write_text(
            json.dumps({"methods": methods, "rows": rows, "commit": git_commit()}, indent=1)
        )
    except LocalScaleError as e:
        print(f"error: {' '.join(str(e).split())}", file=sys.stderr)
        return 2
    print(md)
    print(f"wrote {out}/table.md and {out}/table.json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
