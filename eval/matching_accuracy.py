"""Mean matching accuracy at 5 px: Hessian detector + {our HardNet, SIFT} x correction {none, global, local, fused, gt}.

Datasets: (1) held-out synthetic perspective pairs generated from the *held-out* photos of
``--train-images`` (``localscale.data.split_images``), HPatches layout in a temp folder;
(2) the real sequences in ``--sequences`` (pairs 1-k). ``local``/``global`` use the bundled
default models when ``localscale/weights/*.pt`` exist (or ``--local-weights`` /
``--global-weights``), else those columns are skipped with a note.

    OMP_NUM_THREADS=1 python eval/matching_accuracy.py -o eval_out/matching [--quick]
"""

import argparse
import json
import sys
import tempfile
from pathlib import Path

import torch

from localscale.data import list_images, split_images
from localscale.evaluation.hpatches import (
    THRESHOLDS,
    evaluate,
    gate_from_args,
    load_hpatches,
    load_scale_models,
    make_pairs,
    matching_table,
)
from localscale.evaluation.report import git_commit
from localscale.evaluation.synthetic import make_sequences
from localscale.matching.correction import CORRECTIONS, GATE_WEIGHTINGS


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("-o", "--out", default="eval_out/matching")
    p.add_argument("--train-images", default="../shared/data/train_images")
    p.add_argument("--sequences", default="../shared/data/sequences")
    p.add_argument("--num-synthetic", type=int, default=30, help="held-out photos used (1 pair each)")
    p.add_argument("--descriptors", nargs="+", default=["hardnet", "sift"])
    p.add_argument("--num-features", type=int, default=1000)
    p.add_argument("--local-weights", default=None)
    p.add_argument("--global-weights", default=None)
    p.add_argument(
        "--max-side",
        type=int,
        default=None,
        help="downscale the real sequences to this longer side (speed; default: full resolution)",
    )
    p.add_argument("--gate-pair", type=float, default=None, help="pair-level gate (default: CorrectionGate)")
    p.add_argument("--gate-deadzone", type=float, default=None)
    p.add_argument("--gate-weighting", choices=GATE_WEIGHTINGS, default=None)
    p.add_argument("--orientation", choices=("upright", "gradient"), default="upright")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--crop",
        type=float,
        default=1.0,
        help="< 1: image 1 is this central part of the photo, image 2 shows its real surroundings",
    )
    p.add_argument("--methods", nargs="+", default=list(CORRECTIONS), choices=CORRECTIONS)
    a = p.parse_args(argv)
    if not 0 < a.crop <= 1:
        p.error(f"--crop must be in (0, 1], got {a.crop}")
    torch.set_num_threads(1)
    methods = list(a.methods)
    models, notes = load_scale_models(methods, a.local_weights, a.global_weights)
    gate = gate_from_args(a)
    for n in notes:
        print("note:", n)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    held = split_images(list_images(a.train_images))[1][: a.num_synthetic]
    tmp = tempfile.mkdtemp(prefix="ls_synth_")
    make_sequences(held, tmp, num_images=2, size=480, seed=a.seed, crop=a.crop)
    datasets = {"synthetic-heldout" + ("" if a.crop == 1 else f"-crop{a.crop:g}"): make_pairs(load_hpatches(tmp))}
    if a.sequences and Path(a.sequences).is_dir():
        datasets["sequences"] = make_pairs(load_hpatches(a.sequences))
    doc = {"notes": notes, "gate": vars(gate), "orientation": a.orientation, "results": {}}
    rows = []
    for dname, pairs in datasets.items():
        for d in a.descriptors:
            res = evaluate(
                pairs,
                methods,
                "hardnet",
                models.get("local"),
                models.get("global"),
                max_side=(a.max_side or 0) if dname == "sequences" else 0,
                descriptor=d,
                num_features=a.num_features,
                gate=gate,
                orientation=a.orientation,
            )
            doc["results"][f"{dname}/{d}"] = res
            (out / f"{dname}_{d}.md").write_text(
                matching_table(res["summary"], methods, list(THRESHOLDS), f"{dname} / {d}")
            )
            for split in ("all", "easy", "medium", "hard"):
                s = res["summary"].get(split)
                if s:
                    rows.append(
                        (
                            f"{dname} {split}",
                            s["num_pairs"],
                            d,
                            [s[m]["mma"][4] if m in s else float("nan") for m in methods],
                            [s[m]["num_matches"] if m in s else float("nan") for m in methods],
                        )
                    )
    (out / "matching_accuracy.json").write_text(json.dumps({**doc, "commit": git_commit()}, indent=1))
    hdr = f"{'dataset / split':<26}{'pairs':>6} {'descriptor':<10}" + "".join(f"{m:>10}" for m in methods)
    print("\nMMA@5px (mutual NN; mean #matches in brackets)\n" + hdr)
    for dname, n, d, mma, nm in rows:
        print(f"{dname:<26}{n:>6} {d:<10}" + "".join(f"{v:>6.3f}({c:>3.0f})" for v, c in zip(mma, nm)))
    print(f"wrote {out}/matching_accuracy.json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
