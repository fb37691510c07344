"""Export a training run as shipped weights + a JSON model card.

    python train/make_model_card.py --run runs/local --name local_scalenet \
        --eval results/scale_accuracy_local.json --command "localscale-train ..."

Writes ``localscale/weights/<name>.pt`` (fp16 weights, config, metadata) and ``<name>.json``.
Uses ``<run>/model.pt`` when the run finished, else its latest ``last.pt``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from localscale.checkpoint import backbone_record, read_checkpoint, save_model
from localscale.models import load_model

DATA_CARD = {
    "source": "../shared/data/train_images (291 photos, longer side <= 640 px); training used the 'train' split: "
    "every 10th file in sorted order is held out for validation/evaluation (localscale.data.split_images)",
    "groups_and_licences": {
        "bsd68 (60)": "CBSD68 / Berkeley Segmentation Dataset BSDS300 (Martin et al. ICCV 2001): non-commercial research and educational use",
        "urban100 (88)": "Urban100 (Huang et al. CVPR 2015), Flickr photos, Creative Commons per the authors",
        "sunhays80 (71)": "Sun-Hays 80 (Sun & Hays ICCP 2012), Flickr scene photos, licence not stated",
        "set14 (8) + set5 (1)": "classic super-resolution test images, licence not stated",
        "kodak (20)": "Kodak Lossless True Color Image Suite, released for unrestricted use",
        "wikiphotos (43)": "Wikimedia Commons photos (mostly CC, attribution per file page; list in shared/data/SOURCES.md)",
    },
    "pairs": "synthetic: random homography (log-uniform scale, rotation, skew, perspective, shift) warps a crop "
    "of a photo into the target; the target's empty region is filled from another random photo; "
    "ground truth = analytic sqrt|det J_H| on the stride-8 grid",
    "never_used": "the evaluation sequences/pairs (../shared/data/sequences, ../shared/data/pairs) and scikit-image photos",
}


#: licence of each shared photo collection (its SOURCES.md), for models trained on its real-pair labels
COLLECTION_LICENCES = {
    "skull_alansartlog": "CC BY 4.0",
    "plush_dog_smartdatascan": "CC BY-NC-SA 4.0",
    "temple_sparse_ring_middlebury": "Middlebury multi-view stereo data (Seitz et al.), no licence text given",
    "kitchen_vggsfm": "CC BY-NC 4.0 (the vggsfm repository licence)",
    "cyprus_dim": "BSD 3-Clause (the deep-image-matching repository licence)",
    "kermit_bundler": "GNU GPL as stated for Bundler (no version)",
}


def real_pairs_card(train_cfg: dict) -> dict | None:
    """The real-pair labels a run trained on (``--real-pairs``): collections, licences, the one held out."""
    files = [f for f in str(train_cfg.get("real_pairs") or "").split(",") if f]
    if not files:
        return None
    used = [Path(f).parent.name for f in files]
    held = Path(str(train_cfg.get("real_val_pairs") or "")).parent.name
    return {
        "labels": "the paper's real-pair labels made dense (localscale/training/real_pairs.py) from pycolmap SIFT "
        "models of the shared photo collections (train/label_collections.py); close-up windows and quarter "
        f"turns drawn per sample; {train_cfg.get('real_fraction')} of the samples",
        "collections": {c: COLLECTION_LICENCES.get(c, "see the collection's SOURCES.md") for c in used},
        "held_out": held or None,
    }


CONTEXT_NOTE = (
    "; with context (--context): the target is rendered from the whole photo, so around the "
    "crop's content it shows the photo's real surroundings, and the fill photo covers only what lies "
    "beyond the photo"
)


def backbone_card(model) -> dict:
    """The feature backbone: trained here (VGG layout) or frozen pre-trained (name, weight file,
    sha256, licence, the data it was trained on), with its parameter count."""
    record = backbone_record(model)
    n = sum(p.numel() for p in model.extractor.backbone.parameters())
    if record is None:
        return {"name": "vgg", "trained": "with the model, from scratch, on the data below", "parameters": n}
    return dict(
        record,
        trained="frozen: pre-trained weights, not changed by our training (not in our .pt; "
        "read from the weight file, which must have this sha256)",
        parameters=n,
    )


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--run", required=True)
    p.add_argument("--name", required=True, help="file stem in localscale/weights/")
    p.add_argument("--eval", nargs="*", default=[], help="eval JSON files to include")
    p.add_argument("--command", default="", help="the command that trained it")
    p.add_argument("--notes", default="")
    p.add_argument("--hardware", default="2 CPU cores (no GPU), fp32, 1 torch thread")
    p.add_argument(
        "--init-card",
        default="",
        help="model card of the weights this run was initialised from (--init-weights); "
        "its training record is kept under training.initialised_from",
    )
    a = p.parse_args(argv)
    run = Path(a.run)
    src = run / "model.pt" if (run / "model.pt").exists() else run / "last.pt"
    model = load_model(src)
    if (run / "last.pt").exists():
        ck = read_checkpoint(run / "last.pt")
        step, train_cfg = ck["train_state"]["step"], ck["meta"].get("train_config", {})
    else:  # only the exported model came back (e.g. from a remote GPU run)
        meta = read_checkpoint(src)["meta"]
        step, train_cfg = meta.get("steps", meta.get("campaign_step")), meta.get("train_config", {})
    val = [json.loads(line) for line in open(run / "val_log.jsonl")] if (run / "val_log.jsonl").exists() else []
    out_dir = Path(__file__).resolve().parent.parent / "localscale" / "weights"
    weights = out_dir / f"{a.name}.pt"
    meta = {"steps": step, "train_config": train_cfg, "validation": val[-1] if val else {}}
    save_model(model, weights, meta=meta, half=True)
    card = {
        "name": a.name,
        "architecture": model.arch,
        "config": {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(model.config).items()},
        "parameters": sum(p.numel() for p in model.parameters() if p.requires_grad),
        "weights_file": weights.name,
        "weights_mb": round(weights.stat().st_size / 2**20, 2),
        "storage": "fp16",
        "training": {
            "steps": step,
            "batch_size": train_cfg.get("batch_size"),
            "config": train_cfg,
            "command": a.command,
            "hardware": a.hardware,
        },
        "data": dict(DATA_CARD, pairs=DATA_CARD["pairs"] + (CONTEXT_NOTE if train_cfg.get("context") else "")),
        "real_pairs": real_pairs_card(train_cfg),
        "validation_history": val,
        "evaluation": {Path(e).stem: json.loads(Path(e).read_text()) for e in a.eval},
        "backbone": backbone_card(model),
        "convention": "S_{A->B} > 1: content looks bigger in B",
        "notes": a.notes,
    }
    if a.init_card:
        init = json.loads(Path(a.init_card).read_text())
        card["training"]["initialised_from"] = {
            k: init.get(k) for k in ("name", "training", "validation_history", "notes")
        }
    (out_dir / f"{a.name}.json").write_text(json.dumps(card, indent=1))
    print(f"wrote {weights} ({card['weights_mb']} MB) and {a.name}.json (step {step})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
