"""Scale maps on 3D collections: mean error factor against the per-point truth of COLMAP models.

For each labelled collection (``LABELS/<collection>/pairs.npz`` of ``train/label_collections.py``,
which reconstructs the shared collections with pycolmap, ~6 min on one thread), up to
``--max-pairs`` seeded pairs, each as it is (``as-is``) and as close-ups (``closeup``: B a
2.5-6x window around a shared point, enlarged; ``closeup-turned``: also quarter-turned), see
:mod:`localscale.evaluation.maps3d`. Per pair the error factor ``exp(mean |ln(pred / truth)|)``
over its labelled points, averaged over pairs, for each predictor (``local``: Local-ScaleNet's map;
``scalenet``: ScaleNet's factor as a constant; ``one``: 1; any other name of
:mod:`localscale.evaluation.predictors`; ``--system MODULE:FUNCTION`` adds ``system``).

Per-pair records go to ``<out>.records.jsonl`` as they are computed (a rerun with the same weights
and options resumes); the table is printed and written to ``<out>.md``, the summary to ``--out``.

    OMP_NUM_THREADS=1 python eval/map_collections.py --labels runs/real_models --max-pairs 15 \\
        --out results/maps_3d/summary.json
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from localscale.core.errors import LocalScaleError
from localscale.evaluation import maps3d
from localscale.evaluation.predictors import prepare
from localscale.evaluation.records import RecordFile, weights_fingerprint
from localscale.evaluation.report import one_line_errors, write_table_and_json
from localscale.io import load_image
from localscale.training.real_pairs import load_covisible_pairs


def labelled_collections(labels: Path, names) -> dict[str, Path]:
    """``{collection: pairs.npz}`` of ``labels`` (``names`` None: every one there)."""
    if not labels.is_dir():
        raise LocalScaleError(
            f"no labels folder {labels}; make it with: python train/label_collections.py "
            f"../shared/data/collections -o {labels}"
        )
    found = {d.name: d / "pairs.npz" for d in sorted(labels.iterdir()) if (d / "pairs.npz").is_file()}
    if names:
        missing = [n for n in names if n not in found]
        if missing:
            raise LocalScaleError(f"no {labels}/<collection>/pairs.npz for {', '.join(missing)}")
        found = {n: found[n] for n in names}
    if not found:
        raise LocalScaleError(f"{labels}: no <collection>/pairs.npz")
    return found


def parse_args(argv):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--labels", type=Path, default=Path("runs/real_models"), help="folder of <collection>/pairs.npz")
    p.add_argument("--collections", nargs="*", default=None, help="default: every labelled collection")
    p.add_argument("--kinds", nargs="+", default=list(maps3d.KINDS), choices=maps3d.KINDS)
    p.add_argument("--max-pairs", type=int, default=20, help="pairs per collection (0: all)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--zoom", type=float, nargs=2, default=list(maps3d.ZOOM_RANGE), metavar=("MIN", "MAX"))
    p.add_argument("--predictors", nargs="+", default=["local", "scalenet", "one"])
    p.add_argument("--system", default=None, metavar="MODULE:FUNCTION", help="add the predictor 'system'")
    p.add_argument("--local-weights", default=None, help="Local-ScaleNet checkpoint (default: bundled)")
    p.add_argument("--global-weights", default=None, help="ScaleNet checkpoint (default: bundled)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--out", type=Path, default=Path("results/maps_3d/summary.json"))
    args = p.parse_args(argv)
    if args.max_pairs < 0:
        raise LocalScaleError(f"--max-pairs must be >= 0, got {args.max_pairs}")
    if not 1 <= args.zoom[0] <= args.zoom[1]:
        raise LocalScaleError(f"--zoom needs 1 <= MIN <= MAX, got {args.zoom[0]:g} {args.zoom[1]:g}")
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    files = labelled_collections(args.labels, args.collections)
    models, predictors = prepare(args.predictors, args.system, args.local_weights, args.global_weights, args.device)
    run = models.describe() | {
        "local_weights": weights_fingerprint(args.local_weights),
        "global_weights": weights_fingerprint(args.global_weights),
        "system": args.system,
        "seed": args.seed,
        "zoom": list(args.zoom),
    }
    records = RecordFile(args.out.with_suffix(".records.jsonl"), run)
    images: dict = {}

    def load(path):
        if path not in images:
            if len(images) >= 4:  # pairs in file order share their images with their neighbours
                images.pop(next(iter(images)))
            images[path] = load_image(path, "collection photo")
        return images[path]

    rows = []
    for name, npz in files.items():
        pairs = maps3d.choose_pairs(load_covisible_pairs(npz), args.max_pairs or None, args.seed, name)
        rows += maps3d.evaluate_collection(
            name, pairs, args.kinds, predictors, models, load, records, args.seed, tuple(args.zoom)
        )
        print(f"{name}: {len(pairs)} pairs", file=sys.stderr, flush=True)
    summary = maps3d.summarise(rows, predictors)
    table = maps3d.markdown(summary, predictors)
    print(table)
    if summary["skipped"]:
        print(f"warning: {summary['skipped']} pair(s) had too few labelled points and are left out", file=sys.stderr)
    doc = {"labels": str(args.labels), "predictors": predictors, "max_pairs": args.max_pairs} | run | summary
    write_table_and_json(args.out, table, doc)
    return 0


def cli(argv=None) -> int:
    """:func:`main` with bad input reported as one ``error:`` line and exit code 2."""
    return one_line_errors(main, argv)


if __name__ == "__main__":
    sys.exit(cli())
