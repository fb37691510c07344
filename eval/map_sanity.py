"""Sanity pairs from any photo: does each scale map get zooms, turns and rotations right?

For each photo and case of :func:`localscale.evaluation.sanity.default_cases` (zooms 1.5-8 in both
directions: B a centred window of A enlarged, truth ``z``, or A one of B, truth ``1/z``; quarter
turns and rotations of B, alone and with zooms 2 and 4), each predictor's map is compared with the
truth over the part of A that B shows: its median, the ratio to the truth, and pass when within 10 %
(``--tolerance``). Predictors (:mod:`localscale.evaluation.predictors`): ``local`` (the network's
map as it is), ``scalenet`` (one number), ``one`` (constant 1, the ``none`` correction),
``correction:global|local|fused|searched`` (what each correction gives A; ``searched`` ~20 s a
pair) and ``refined`` (``predict --refine``); ``--system MODULE:FUNCTION`` adds ``system``.

Photos: image files or folders (``--held-out``: only every 10th photo of a folder, sorted, the
photos training leaves out; ``--per-folder N``: N of them, evenly spaced). Per-case records go to
``<out>.records.jsonl`` as they are computed (a rerun with the same weights resumes); the table is
printed and written to ``<out>.md``, the summary to ``--out``.

    OMP_NUM_THREADS=1 python eval/map_sanity.py ../shared/data/train_images --held-out --per-folder 5 \\
        --out results/maps_sanity/held_out.json
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

from localscale.core.errors import LocalScaleError
from localscale.data import list_images, split_images
from localscale.evaluation import sanity
from localscale.evaluation.predictors import prepare
from localscale.evaluation.records import RecordFile, weights_fingerprint
from localscale.evaluation.report import one_line_errors, write_table_and_json
from localscale.io import load_image

DEFAULT_PREDICTORS = (
    "local",
    "scalenet",
    "one",
    "correction:global",
    "correction:local",
    "correction:fused",
    "refined",
)


def choose_photos(sources, held_out: bool, per_folder) -> list[Path]:
    """The photos of ``sources`` (files, or folders: held-out ones only with ``held_out``, then
    ``per_folder`` of them evenly spaced)."""
    photos = []
    for s in map(Path, sources):
        if s.is_file():
            photos.append(s)
            continue
        files = list_images(s)
        if held_out:
            files = split_images(files)[1]
        if per_folder is not None and per_folder < len(files):
            files = [files[i] for i in np.linspace(0, len(files) - 1, per_folder).round().astype(int)]
        photos += files
    if not photos:
        raise LocalScaleError("no photos")
    return photos


def read_photo(path: Path, max_side: int) -> np.ndarray:
    img = load_image(path, "photo")
    f = max_side / max(img.shape[:2])
    if f < 1:
        img = cv2.resize(img, (round(img.shape[1] * f), round(img.shape[0] * f)), interpolation=cv2.INTER_AREA)
    return img


def parse_args(argv):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("sources", nargs="+", help="photos or folders of photos")
    p.add_argument("--held-out", action="store_true", help="from folders, only the photos training holds out")
    p.add_argument("--per-folder", type=int, default=None, help="photos per folder (evenly spaced)")
    p.add_argument("--max-side", type=int, default=1024, help="larger photos are shrunk to this longer side")
    p.add_argument("--predictors", nargs="+", default=list(DEFAULT_PREDICTORS))
    p.add_argument("--system", default=None, metavar="MODULE:FUNCTION", help="add the predictor 'system'")
    p.add_argument("--local-weights", default=None, help="Local-ScaleNet checkpoint (default: bundled)")
    p.add_argument("--global-weights", default=None, help="ScaleNet checkpoint (default: bundled)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--zooms", type=float, nargs="*", default=[1.5, 2, 3, 4, 6, 8])
    p.add_argument("--turns", type=int, nargs="*", default=[1, 2, 3])
    p.add_argument("--rotations", type=float, nargs="*", default=[30, 45])
    p.add_argument("--combined-zooms", type=float, nargs="*", default=[2, 4])
    p.add_argument("--tolerance", type=float, default=sanity.TOLERANCE)
    p.add_argument("--out", type=Path, default=Path("results/maps_sanity/summary.json"))
    args = p.parse_args(argv)
    if args.per_folder is not None and args.per_folder < 1:
        raise LocalScaleError(f"--per-folder must be >= 1, got {args.per_folder}")
    if args.max_side < 64:
        raise LocalScaleError(f"--max-side must be >= 64, got {args.max_side}")
    if not 0 < args.tolerance < 1:
        raise LocalScaleError(f"--tolerance must be in (0, 1), got {args.tolerance}")
    if any(z <= 1 for z in args.zooms + args.combined_zooms):
        raise LocalScaleError("--zooms and --combined-zooms take factors > 1 (each is used both ways)")
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    photos = choose_photos(args.sources, args.held_out, args.per_folder)
    models, predictors = prepare(args.predictors, args.system, args.local_weights, args.global_weights, args.device)
    cases = sanity.default_cases(args.zooms, args.turns, args.rotations, args.combined_zooms)
    run = models.describe() | {
        "local_weights": weights_fingerprint(args.local_weights),
        "global_weights": weights_fingerprint(args.global_weights),
        "system": args.system,
        "max_side": args.max_side,
        "tolerance": args.tolerance,
    }
    records = RecordFile(args.out.with_suffix(".records.jsonl"), run)
    rows = []
    for i, path in enumerate(photos):
        rows += sanity.evaluate_photo(
            str(path.resolve()), read_photo(path, args.max_side), cases, predictors, models, records, args.tolerance
        )
        print(f"{i + 1}/{len(photos)} {path.name}", file=sys.stderr, flush=True)
    summary = sanity.summarise(rows, predictors)
    table = sanity.markdown(summary, predictors)
    print(table)
    doc = {"photos": [str(p) for p in photos], "predictors": predictors} | models.describe() | summary
    doc["system"], doc["tolerance"] = args.system, args.tolerance
    write_table_and_json(args.out, table, doc)
    return 0


def cli(argv=None) -> int:
    """:func:`main` with bad input reported as one ``error:`` line and exit code 2."""
    return one_line_errors(main, argv)


if __name__ == "__main__":
    sys.exit(cli())
