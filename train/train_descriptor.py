"""Train the HardNet descriptor on scale-corrected patches of synthetic homography pairs.

Data: for every training photo (the ``train`` part of ``localscale.data.split_images``),
random moderate homographies ``A -> B`` (``localscale.geometry.sample_homography``),
B = A warped (+ photometric jitter + noise). Keypoints are detected in A with the
single-scale Hessian detector, their exact correspondences in B come from ``H`` (plus
up to +-1 px jitter, as a detector would re-detect them), and both patches get the
ground-truth patch-size correction (``r_A = r0 max(1, 1/S)``, ``r_B = r0 max(1, S)``,
``S = S_{A->B}(x)``), so the descriptor learns to match scale-normalised, upright patches.
Patch pairs are generated once (deterministic in ``--seed``) and cached in ``--out``.

Loss: HardNet hardest-in-batch triplet margin loss (margin 1). Adam with linear decay.
Checkpoints (``--out/last.pt``) resume automatically. ``--max-minutes`` bounds wall time.

Example (the shipped weights)::

    OMP_NUM_THREADS=1 python train/train_descriptor.py --data ../shared/data/train_images \
        --out /tmp/hardnet_run --steps 2000 --max-minutes 20 --export localscale/weights/hardnet.pt
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from localscale.data import list_images, split_images
from localscale.features.descriptors import HardNetDescriptor, SIFTPatchDescriptor
from localscale.features.detector import detect_keypoints, image_to_gray_tensor
from localscale.features.patches import extract_patches, make_lafs
from localscale.geometry import HomographyConfig, homography_scale_at, project, sample_homography, warp_image
from localscale.io import load_image

MODERATE = HomographyConfig(scale_range=(0.35, 2.8), rotation_deg=10.0, skew=0.1, perspective=0.3, translation=0.15)


def _jitter(rng: np.random.Generator, img: np.ndarray) -> np.ndarray:
    x = img.astype(np.float32) / 255.0
    x = np.clip(x * rng.uniform(0.7, 1.3) + rng.uniform(-0.15, 0.15), 0, 1) ** rng.uniform(0.7, 1.4)
    x = x + rng.normal(0, rng.uniform(0, 0.02), x.shape)
    return (np.clip(x, 0, 1) * 255).round().astype(np.uint8)


def patch_pairs_from_image(rng: np.random.Generator, img: np.ndarray, per_pair: int = 150, base_radius: float = 16.0,
                           max_side: int = 480, cfg: HomographyConfig = MODERATE) -> tuple[torch.Tensor, torch.Tensor]:
    """One synthetic pair from a photo -> ``(patches_A, patches_B)`` uint8 ``N x 1 x 32 x 32``."""
    s = max_side / max(img.shape[:2])
    if s < 1:
        img = cv2.resize(img, (round(img.shape[1] * s), round(img.shape[0] * s)), interpolation=cv2.INTER_AREA)
    h, w = img.shape[:2]
    H = sample_homography(rng, (h, w), (h, w), cfg)
    b, valid = warp_image(img, H, (h, w))
    b = _jitter(rng, b)
    ka, _ = detect_keypoints(img, 3 * per_pair)
    if len(ka) == 0:
        return torch.zeros(0, 1, 32, 32, dtype=torch.uint8), torch.zeros(0, 1, 32, 32, dtype=torch.uint8)
    kb = project(H, ka.astype(np.float64))
    sab = homography_scale_at(H, ka.astype(np.float64))
    ra = base_radius * np.maximum(1, 1 / np.clip(sab, 0.125, 8))
    rb = base_radius * np.maximum(1, np.clip(sab, 0.125, 8))
    ok = np.isfinite(kb).all(1) & np.isfinite(sab)
    ok &= (kb[:, 0] >= rb) & (kb[:, 0] <= w - 1 - rb) & (kb[:, 1] >= rb) & (kb[:, 1] <= h - 1 - rb)
    ok &= (ra < min(h, w) / 2) & (rb < min(h, w) / 2)
    idx = np.flatnonzero(ok)
    if len(idx):
        kbi = np.clip(np.round(kb[idx]).astype(int), 0, [w - 1, h - 1])
        idx = idx[valid[kbi[:, 1], kbi[:, 0]] > 0.99]
    idx = idx[:per_pair]
    if len(idx) == 0:
        return torch.zeros(0, 1, 32, 32, dtype=torch.uint8), torch.zeros(0, 1, 32, 32, dtype=torch.uint8)
    kb_j = kb[idx] + rng.uniform(-1, 1, (len(idx), 2))
    pa = extract_patches(image_to_gray_tensor(img), make_lafs(ka[idx], torch.tensor(ra[idx])))
    pb = extract_patches(image_to_gray_tensor(b), make_lafs(kb_j.astype(np.float32), torch.tensor(rb[idx])))
    to8 = lambda p: (p * 255).round().clamp(0, 255).to(torch.uint8)
    return to8(pa), to8(pb)


def build_patch_set(files, seed: int, pairs_per_image: int, per_pair: int, desc: str = "patches"):
    rng = np.random.default_rng(seed)
    pa, pb, gid = [], [], []
    for i, f in enumerate(tqdm(files, desc=desc, mininterval=5)):
        img = load_image(f)
        for j in range(pairs_per_image):
            a, b = patch_pairs_from_image(rng, img, per_pair)
            pa.append(a)
            pb.append(b)
            gid.append(torch.full((len(a),), i * pairs_per_image + j))
    return torch.cat(pa), torch.cat(pb), torch.cat(gid)


def hardest_triplet_loss(da: torch.Tensor, db: torch.Tensor, margin: float = 1.0) -> torch.Tensor:
    """HardNet loss: for each pair, the hardest negative in the batch (row and column)."""
    d = torch.cdist(da, db).clamp_min(1e-8)
    pos = d.diag()
    eye = torch.eye(len(d), dtype=torch.bool)
    dn = d.masked_fill(eye, 10.0)
    dn = dn.masked_fill(dn < 0.008, 10.0)  # near-duplicate patches are not negatives
    neg = torch.minimum(dn.min(1).values, dn.min(0).values)
    return F.relu(margin + pos - neg).mean()


@torch.no_grad()
def evaluate(desc, pa: torch.Tensor, pb: torch.Tensor, chunk: int = 1000) -> dict:
    """FPR95 (positives: corresponding pairs; negatives: shifted pairs) and NN matching accuracy
    within chunks of ``chunk`` pairs."""
    da = desc.describe(pa.float() / 255)
    db = desc.describe(pb.float() / 255)
    pos = (da - db).norm(dim=1)
    neg = (da - db.roll(7, 0)).norm(dim=1)
    thr = torch.quantile(pos, 0.95)
    fpr95 = float((neg <= thr).float().mean())
    accs = []
    for i in range(0, len(da) - chunk + 1, chunk):
        d = torch.cdist(da[i:i + chunk], db[i:i + chunk])
        accs.append(float((d.argmin(1) == torch.arange(chunk)).float().mean()))
    return {"fpr95": fpr95, "nn_accuracy_1000": float(np.mean(accs)) if accs else float("nan"), "pairs": len(da)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", required=True, help="folder of training photos (the train split is used)")
    p.add_argument("--out", required=True, help="run folder: patch cache, last.pt, log")
    p.add_argument("--steps", type=int, default=2000)
    p.add_argument("--batch", type=int, default=256, help="pairs per batch")
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--pairs-per-image", type=int, default=3)
    p.add_argument("--per-pair", type=int, default=150)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--max-minutes", type=float, default=float("inf"), help="stop (and save) after this wall time")
    p.add_argument("--ckpt-every", type=int, default=50)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--export", default=None, help="write fp16 inference weights here at the end")
    p.add_argument("--limit-images", type=int, default=None, help="(tests) use only the first N images")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    t0 = time.time()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    train_files, held_files = split_images(list_images(args.data))
    if args.limit_images:
        train_files, held_files = train_files[:args.limit_images], held_files[:max(1, args.limit_images // 4)]
    cache = out / f"patches_seed{args.seed}.pt"
    if cache.is_file():
        data = torch.load(cache, map_location="cpu", weights_only=True)   # tensors only, no code
    else:
        tr = build_patch_set(train_files, args.seed, args.pairs_per_image, args.per_pair, "train patches")
        ho = build_patch_set(held_files, args.seed + 10_000, 2, args.per_pair, "held-out patches")
        data = {"train": tr, "held": ho}
        torch.save(data, cache)
    pa, pb, _ = data["train"]
    ha, hb, _ = data["held"]
    print(f"patch pairs: train {len(pa)} (from {len(train_files)} photos), held-out {len(ha)} "
          f"(from {len(held_files)} photos); data ready in {time.time() - t0:.0f}s", flush=True)

    model = HardNetDescriptor()
    opt = torch.optim.Adam(model.parameters(), lr=args.lr, weight_decay=1e-4)
    step, elapsed_before = 0, 0.0
    last = out / "last.pt"
    if last.is_file():
        ck = torch.load(last, map_location="cpu", weights_only=True)   # tensors and plain data only
        model.net.load_state_dict(ck["state_dict"])
        opt.load_state_dict(ck["optimizer"])
        step, elapsed_before = ck["step"], ck.get("elapsed", 0.0)
        print(f"resumed from {last} at step {step}", flush=True)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: max(0.02, 1 - s / args.steps), last_epoch=step - 1) \
        if step else torch.optim.lr_scheduler.LambdaLR(opt, lambda s: max(0.02, 1 - s / args.steps))
    t_start = time.time()

    def save():
        torch.save({"state_dict": model.net.state_dict(), "optimizer": opt.state_dict(), "step": step,
                    "elapsed": elapsed_before + time.time() - t_start, "args": vars(args)}, last)

    model.train()
    bar = tqdm(total=args.steps, initial=step, desc="hardnet", mininterval=10)
    stopped_early = False
    while step < args.steps:
        g = torch.Generator().manual_seed(args.seed * 1_000_003 + step)
        idx = torch.randperm(len(pa), generator=g)[:args.batch]
        a, b = pa[idx].float() / 255, pb[idx].float() / 255
        if step % 2:  # joint flip augmentation
            a, b = a.flip(-1), b.flip(-1)
        loss = hardest_triplet_loss(model(a), model(b))
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        step += 1
        bar.update(1)
        bar.set_postfix(loss=f"{loss.item():.3f}")
        if step % args.ckpt_every == 0:
            save()
        if (time.time() - t0) / 60 > args.max_minutes:
            stopped_early = True
            break
    bar.close()
    save()
    model.eval()
    score = evaluate(model, ha, hb)
    sift = evaluate(SIFTPatchDescriptor(), ha, hb)
    report = {"steps": step, "batch": args.batch, "train_pairs": len(pa), "held_out": score,
              "held_out_sift_baseline": sift, "stopped_by_time_limit": stopped_early,
              "train_wall_minutes": round((elapsed_before + time.time() - t_start) / 60, 1)}
    print(json.dumps(report, indent=1), flush=True)
    (out / "report.json").write_text(json.dumps(report, indent=1))
    if args.export:
        model.save(args.export, meta={"steps": step, "held_out": score, "command": " ".join(sys.argv)})
        print(f"exported {args.export}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
