"""Train the HardNet descriptor on scale-corrected patches of synthetic homography pairs.

Data: for every training photo (the ``train`` part of ``localscale.data.split_images``),
random moderate homographies ``A -> B`` (``localscale.geometry.sample_homography``, rotation
up to +-15 deg), B = A warped. Both images get independent photometric changes (gain, gamma,
colour, blur, noise, JPEG), as two photos of a scene do. Keypoints are detected in A with the
single-scale Hessian detector, their correspondences in B come from ``H`` plus up to
+-``--jitter`` px (a detector re-detects them only approximately). Both patches get the
patch-size correction of the matcher (``r_A = r0 max(1, 1/S)``, ``r_B = r0 max(1, S)``) with
``S`` the true ``S_{A->B}(x)`` times a log-normal error of ``--scale-error`` (the residual error
of a predicted scale map), so the descriptor learns the imperfect patches it will be given.
Patch pairs are generated once (deterministic in ``--seed``) and cached in ``--out``.

Batches: ``--images-per-batch`` synthetic pairs contribute ``batch / images-per-batch`` patch
pairs each, so the hardest negatives come from the same image, as in matching; negatives whose
keypoints lie within ``--min-negative-distance`` px in A (overlapping patches) are not used.

Loss: HardNet hardest-in-batch triplet margin loss (margin 1). Adam with linear decay.
Distillation (``--teacher WEIGHTS``, e.g. a narrower ``--widths 16 32 64`` student of the
shipped HardNet): the loss adds ``--distill-weight`` times the mean squared distance between the
student's and the teacher's descriptors of the same (flipped) patches.
Checkpoints (``--out/last.pt``) resume automatically. ``--max-minutes`` bounds wall time.

int8: ``--export`` also stores the activation ranges of the int8 path
(:mod:`localscale.features.quantization`), calibrated on ``--calibration-patches`` random training
patches; ``--calibrate-int8 WEIGHTS`` adds them to existing weights (in place, atomic) and
prints the held-out scores in float32 and int8.

Example (docs/TRAINING.md has the commands of the shipped weights)::

    OMP_NUM_THREADS=1 python train/train_descriptor.py --data ../shared/data/train_images \
        --out /tmp/hardnet_run --steps 2000 --max-minutes 20 --export /tmp/hardnet_run/hardnet.pt
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
from localscale.evaluation.report import git_commit
from localscale.features.descriptors import HardNetDescriptor, SIFTPatchDescriptor
from localscale.features.detector import detect_keypoints, image_to_gray_tensor
from localscale.features.patches import extract_patches, make_lafs
from localscale.geometry import HomographyConfig, homography_scale_at, project, sample_homography, warp_image
from localscale.io import load_image

MODERATE = HomographyConfig(scale_range=(0.3, 3.2), rotation_deg=15.0, skew=0.1, perspective=0.35, translation=0.15)


def _photometric(rng: np.random.Generator, img: np.ndarray) -> np.ndarray:
    """Gain, gamma, colour cast, then (each sometimes) blur, sensor noise and JPEG."""
    x = img.astype(np.float32) / 255.0
    cast = np.exp(rng.uniform(-0.1, 0.1, 3)).astype(np.float32) if x.ndim == 3 else 1.0
    gain = np.exp(rng.uniform(np.log(0.35), np.log(1.6)))
    x = np.clip(x * gain * cast + rng.uniform(-0.08, 0.08), 0, 1) ** np.exp(rng.uniform(-0.4, 0.4))
    out = (x * 255).round().astype(np.uint8)
    if rng.random() < 0.3:
        out = cv2.GaussianBlur(out, (0, 0), rng.uniform(0.4, 1.3))
    if rng.random() < 0.4:
        out = (out + rng.normal(0, rng.uniform(1, 6), out.shape)).round().clip(0, 255).astype(np.uint8)
    if rng.random() < 0.3:
        ok, buf = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, int(rng.integers(30, 90))])
        if ok:
            out = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED).reshape(img.shape)
    return out


def patch_pairs_from_image(
    rng: np.random.Generator,
    img: np.ndarray,
    per_pair: int = 150,
    base_radius: float = 16.0,
    max_side: int = 480,
    cfg: HomographyConfig = MODERATE,
    scale_error: float = 0.25,
    jitter: float = 1.5,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One synthetic pair from a photo -> ``(patches_A, patches_B, keypoints_A)``: uint8
    ``N x 1 x 32 x 32`` patches and ``N x 2`` float keypoints of A (pixels of the resized photo)."""
    s = max_side / max(img.shape[:2])
    if s < 1:
        img = cv2.resize(img, (round(img.shape[1] * s), round(img.shape[0] * s)), interpolation=cv2.INTER_AREA)
    h, w = img.shape[:2]
    H = sample_homography(rng, (h, w), (h, w), cfg)
    b, valid = warp_image(img, H, (h, w))
    a, b = _photometric(rng, img), _photometric(rng, b)
    empty = (torch.zeros(0, 1, 32, 32, dtype=torch.uint8),) * 2 + (torch.zeros(0, 2),)
    ka, _ = detect_keypoints(a, 3 * per_pair)
    if len(ka) == 0:
        return empty
    kb = project(H, ka.astype(np.float64))
    sab = homography_scale_at(H, ka.astype(np.float64))
    s_used = (
        np.clip(sab * np.exp(rng.normal(0, scale_error, len(sab))), 0.125, 8)
        if scale_error > 0
        else np.clip(sab, 0.125, 8)
    )
    ra = base_radius * np.maximum(1, 1 / s_used)
    rb = base_radius * np.maximum(1, s_used)
    ok = np.isfinite(kb).all(1) & np.isfinite(sab)
    ok &= (kb[:, 0] >= rb) & (kb[:, 0] <= w - 1 - rb) & (kb[:, 1] >= rb) & (kb[:, 1] <= h - 1 - rb)
    ok &= (ra < min(h, w) / 2) & (rb < min(h, w) / 2)
    idx = np.flatnonzero(ok)
    if len(idx):
        kbi = np.clip(np.round(kb[idx]).astype(int), 0, [w - 1, h - 1])
        idx = idx[valid[kbi[:, 1], kbi[:, 0]] > 0.99]
    idx = idx[:per_pair]
    if len(idx) == 0:
        return empty
    kb_j = kb[idx] + rng.uniform(-jitter, jitter, (len(idx), 2))
    pa = extract_patches(image_to_gray_tensor(a), make_lafs(ka[idx], torch.tensor(ra[idx])))
    pb = extract_patches(image_to_gray_tensor(b), make_lafs(kb_j.astype(np.float32), torch.tensor(rb[idx])))
    to8 = lambda p: (p * 255).round().clamp(0, 255).to(torch.uint8)
    return to8(pa), to8(pb), torch.from_numpy(ka[idx].astype(np.float32))


def build_patch_set(
    files,
    seed: int,
    pairs_per_image: int,
    per_pair: int,
    desc: str = "patches",
    scale_error: float = 0.25,
    jitter: float = 1.5,
):
    """Patch pairs of all photos -> ``(patches_A, patches_B, pair_id, keypoints_A)``."""
    rng = np.random.default_rng(seed)
    pa, pb, gid, kp = [], [], [], []
    for i, f in enumerate(tqdm(files, desc=desc, mininterval=5)):
        img = load_image(f)
        for j in range(pairs_per_image):
            a, b, k = patch_pairs_from_image(rng, img, per_pair, scale_error=scale_error, jitter=jitter)
            pa.append(a)
            pb.append(b)
            kp.append(k)
            gid.append(torch.full((len(a),), i * pairs_per_image + j))
    return torch.cat(pa), torch.cat(pb), torch.cat(gid), torch.cat(kp)


def group_batch(
    gid: torch.Tensor, groups: list[torch.Tensor], batch: int, images_per_batch: int, generator: torch.Generator
) -> torch.Tensor:
    """Indices of a batch: ``images_per_batch`` random pairs, ``batch / images_per_batch`` patches each
    (all of them when a pair has fewer), topped up with random patches."""
    per = max(1, batch // max(1, images_per_batch))
    chosen = torch.randperm(len(groups), generator=generator)[:images_per_batch]
    parts = []
    for g in chosen.tolist():
        members = groups[g]
        parts.append(members[torch.randperm(len(members), generator=generator)[:per]])
    idx = torch.cat(parts) if parts else torch.zeros(0, dtype=torch.long)
    if len(idx) < batch:
        extra = torch.randperm(len(gid), generator=generator)[: batch - len(idx)]
        idx = torch.cat([idx, extra])
    return idx[:batch]


def hardest_triplet_loss(
    da: torch.Tensor, db: torch.Tensor, margin: float = 1.0, not_negative: torch.Tensor | None = None
) -> torch.Tensor:
    """HardNet loss: for each pair, the hardest negative in the batch (row and column).
    ``not_negative``: ``B x B`` bool, pairs that must not be used as negatives (overlapping patches)."""
    d = torch.cdist(da, db).clamp_min(1e-8)
    pos = d.diag()
    eye = torch.eye(len(d), dtype=torch.bool)
    dn = d.masked_fill(eye, 10.0)
    if not_negative is not None:
        dn = dn.masked_fill(not_negative, 10.0)
    dn = dn.masked_fill(dn < 0.008, 10.0)  # near-duplicate patches are not negatives
    neg = torch.minimum(dn.min(1).values, dn.min(0).values)
    return F.relu(margin + pos - neg).mean()


def calibration_set(pa: torch.Tensor, pb: torch.Tensor, n: int, seed: int = 0) -> torch.Tensor:
    """``n`` random training patches (half from A, half from B), float in [0, 1]."""
    g = torch.Generator().manual_seed(seed)
    ia = torch.randperm(len(pa), generator=g)[: (n + 1) // 2]
    ib = torch.randperm(len(pb), generator=g)[: n // 2]
    return torch.cat([pa[ia], pb[ib]]).float() / 255


def add_int8_ranges(model: HardNetDescriptor, patches: torch.Tensor) -> HardNetDescriptor:
    """Round the weights to float16 (as saved) and calibrate the int8 path on ``patches``."""
    model.net.half().float()
    return model.calibrate_int8(patches)


def scores_by_precision(model: HardNetDescriptor, ha: torch.Tensor, hb: torch.Tensor) -> dict:
    """Held-out scores in float32 and, when the model has int8 ranges, in int8."""
    out = {"fp32": evaluate(model.set_precision("fp32"), ha, hb)}
    if model.int8_ranges:
        out["int8"] = evaluate(model.set_precision("int8"), ha, hb)
    model.set_precision("auto")
    return out


@torch.no_grad()
def evaluate(desc, pa: torch.Tensor, pb: torch.Tensor, chunk: int = 1000) -> dict:
    """FPR95 (positives: corresponding pairs; negatives: shifted pairs), and within chunks of
    ``chunk`` pairs (a few synthetic pairs each): nearest-neighbour accuracy and mAP (the mean
    over A's patches of the average precision of ranking B's patches, one positive each)."""
    da = desc.describe(pa.float() / 255)
    db = desc.describe(pb.float() / 255)
    pos = (da - db).norm(dim=1)
    neg = (da - db.roll(7, 0)).norm(dim=1)
    thr = torch.quantile(pos, 0.95)
    fpr95 = float((neg <= thr).float().mean())
    accs, aps = [], []
    for i in range(0, len(da) - chunk + 1, chunk):
        d = torch.cdist(da[i : i + chunk], db[i : i + chunk])
        accs.append(float((d.argmin(1) == torch.arange(chunk)).float().mean()))
        rank = (d < d.diag()[:, None]).sum(1) + 1
        aps.append(float((1.0 / rank.float()).mean()))
    nan = float("nan")
    return {
        "fpr95": fpr95,
        "nn_accuracy_1000": float(np.mean(accs)) if accs else nan,
        "map_1000": float(np.mean(aps)) if aps else nan,
        "pairs": len(da),
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", required=True, help="folder of training photos (the train split is used)")
    p.add_argument("--out", required=True, help="run folder: patch cache, last.pt, log")
    p.add_argument("--steps", type=int, default=2000)
    p.add_argument("--batch", type=int, default=256, help="pairs per batch")
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--pairs-per-image", type=int, default=3)
    p.add_argument("--per-pair", type=int, default=150)
    p.add_argument(
        "--scale-error",
        type=float,
        default=0.25,
        help="std of the log error applied to the true scale before cutting patches",
    )
    p.add_argument("--jitter", type=float, default=1.5, help="max keypoint re-detection error in B, px")
    p.add_argument(
        "--images-per-batch", type=int, default=16, help="synthetic pairs per batch (0: patches drawn uniformly)"
    )
    p.add_argument(
        "--min-negative-distance",
        type=float,
        default=8.0,
        help="keypoints of one pair closer than this (px in A) are not negatives",
    )
    p.add_argument(
        "--evaluate-only",
        default=None,
        metavar="WEIGHTS",
        help="score these descriptor weights (and SIFT) on the held-out patches of --out, no training",
    )
    p.add_argument(
        "--calibrate-int8",
        default=None,
        metavar="WEIGHTS",
        help="add int8 activation ranges (from training patches of --out) to these weights, in place",
    )
    p.add_argument("--calibration-patches", type=int, default=4096, help="training patches for the int8 ranges")
    p.add_argument("--init", default=None, help="start from these descriptor weights (localscale/kornia format)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--max-minutes", type=float, default=float("inf"), help="stop (and save) after this wall time")
    p.add_argument("--ckpt-every", type=int, default=50)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument(
        "--widths",
        type=int,
        nargs=3,
        default=None,
        metavar=("C1", "C2", "C3"),
        help="channel widths of the three stages (default: HardNet's 32 64 128, or --init's)",
    )
    p.add_argument("--teacher", default=None, metavar="WEIGHTS", help="distil from these descriptor weights")
    p.add_argument("--distill-weight", type=float, default=1.0, help="weight of the distillation term")
    p.add_argument("--export", default=None, help="write fp16 inference weights here at the end")
    p.add_argument("--limit-images", type=int, default=None, help="(tests) use only the first N images")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    t0 = time.time()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    train_files, held_files = split_images(list_images(args.data))
    if args.limit_images:
        train_files, held_files = train_files[: args.limit_images], held_files[: max(1, args.limit_images // 4)]
    cache = out / f"patches_v2_seed{args.seed}_e{args.scale_error:g}_j{args.jitter:g}_p{args.pairs_per_image}.pt"
    if cache.is_file():
        data = torch.load(cache, map_location="cpu", weights_only=True)  # tensors only, no code
    else:
        tr = build_patch_set(
            train_files, args.seed, args.pairs_per_image, args.per_pair, "train patches", args.scale_error, args.jitter
        )
        ho = build_patch_set(
            held_files, args.seed + 10_000, 2, args.per_pair, "held-out patches", args.scale_error, args.jitter
        )
        data = {"train": tr, "held": ho}
        torch.save(data, cache)
    pa, pb, gid, kpa = data["train"]
    ha, hb = data["held"][:2]
    groups = [g for g in torch.split(torch.argsort(gid, stable=True), torch.bincount(gid).tolist()) if len(g)]
    print(
        f"patch pairs: train {len(pa)} (from {len(train_files)} photos), held-out {len(ha)} "
        f"(from {len(held_files)} photos); data ready in {time.time() - t0:.0f}s",
        flush=True,
    )

    if args.evaluate_only:
        report = {
            "weights": args.evaluate_only,
            "held_out": scores_by_precision(HardNetDescriptor.from_pretrained(args.evaluate_only), ha, hb),
            "held_out_sift_baseline": evaluate(SIFTPatchDescriptor(), ha, hb),
        }
        print(json.dumps(report, indent=1), flush=True)
        return 0
    if args.calibrate_int8:
        path = Path(args.calibrate_int8)
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
        model = add_int8_ranges(
            HardNetDescriptor.from_pretrained(path), calibration_set(pa, pb, args.calibration_patches, args.seed)
        )
        model.save(path, meta=ckpt.get("meta", {}), half=True)
        report = {
            "weights": str(path),
            "calibration_patches": args.calibration_patches,
            "held_out": scores_by_precision(HardNetDescriptor.from_pretrained(path), ha, hb),
        }
        print(json.dumps(report, indent=1), flush=True)
        return 0
    model = (
        HardNetDescriptor.from_pretrained(args.init)
        if args.init
        else HardNetDescriptor(tuple(args.widths))
        if args.widths
        else HardNetDescriptor()
    )
    teacher = HardNetDescriptor.from_pretrained(args.teacher).eval() if args.teacher else None
    model.net.float()
    opt = torch.optim.Adam(model.parameters(), lr=args.lr, weight_decay=1e-4)
    step, elapsed_before = 0, 0.0
    last = out / "last.pt"
    if last.is_file():
        ck = torch.load(last, map_location="cpu", weights_only=True)  # tensors and plain data only
        model.net.load_state_dict(ck["state_dict"])
        opt.load_state_dict(ck["optimizer"])
        step, elapsed_before = ck["step"], ck.get("elapsed", 0.0)
        print(f"resumed from {last} at step {step}", flush=True)
    sched = (
        torch.optim.lr_scheduler.LambdaLR(opt, lambda s: max(0.02, 1 - s / args.steps), last_epoch=step - 1)
        if step
        else torch.optim.lr_scheduler.LambdaLR(opt, lambda s: max(0.02, 1 - s / args.steps))
    )
    t_start = time.time()

    def save():
        torch.save(
            {
                "state_dict": model.net.state_dict(),
                "optimizer": opt.state_dict(),
                "step": step,
                "elapsed": elapsed_before + time.time() - t_start,
                "args": vars(args),
            },
            last,
        )

    model.train()
    bar = tqdm(total=args.steps, initial=step, desc="hardnet", mininterval=10)
    stopped_early = False
    while step < args.steps:
        g = torch.Generator().manual_seed(args.seed * 1_000_003 + step)
        idx = (
            group_batch(gid, groups, args.batch, args.images_per_batch, g)
            if args.images_per_batch
            else torch.randperm(len(pa), generator=g)[: args.batch]
        )
        a, b = pa[idx].float() / 255, pb[idx].float() / 255
        if step % 2:  # joint flip augmentation
            a, b = a.flip(-1), b.flip(-1)
        same = gid[idx][:, None] == gid[idx][None, :]
        close = torch.cdist(kpa[idx], kpa[idx]) < args.min_negative_distance
        da, db = model(a), model(b)
        loss = hardest_triplet_loss(da, db, not_negative=same & close)
        if teacher is not None:
            with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16, enabled=a.device.type == "cpu"):
                ta, tb = teacher(a).float(), teacher(b).float()
            loss = loss + args.distill_weight * 0.5 * (((da - ta) ** 2).sum(1).mean() + ((db - tb) ** 2).sum(1).mean())
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
    add_int8_ranges(model, calibration_set(pa, pb, args.calibration_patches, args.seed))
    scores = scores_by_precision(model, ha, hb)
    score = scores["fp32"]
    sift = evaluate(SIFTPatchDescriptor(), ha, hb)
    report = {
        "widths": list(model.widths),
        "teacher": args.teacher,
        "steps": step,
        "batch": args.batch,
        "images_per_batch": args.images_per_batch,
        "train_pairs": len(pa),
        "held_out": score,
        "held_out_int8": scores.get("int8"),
        "held_out_sift_baseline": sift,
        "stopped_by_time_limit": stopped_early,
        "train_wall_minutes": round((elapsed_before + time.time() - t_start) / 60, 1),
        "commit": git_commit(),
    }
    print(json.dumps(report, indent=1), flush=True)
    (out / "report.json").write_text(json.dumps(report, indent=1))
    if args.export:
        model.save(args.export, meta={"steps": step, "held_out": score, "command": " ".join(sys.argv)})
        print(f"exported {args.export}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
