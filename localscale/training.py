"""One trainer for both scale models (``--model local`` or ``--model global``).

Features: config dataclass, KL loss on co-visible cells (local) / both directions (global),
Adam with step decay, bf16 autocast on CPU and AMP on CUDA, DDP under ``torchrun``, tqdm
progress, periodic validation on held-out photos (mean scale-ratio error r), checkpoints
that resume exactly (data is a pure function of ``(seed, sample index)``), CSV/JSON logs,
and a stop on a non-finite loss that keeps the last good checkpoint.

    python -m localscale.training --model local --data ../shared/data/train_images --out runs/local
"""
from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import os
import signal
import sys
import threading
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.distributed as dist
import torch.nn.functional as F
from torch.utils.data import DataLoader, Subset

from . import scales
from .checkpoint import (checkpoint_dict, non_finite_tensors, read_checkpoint, restore_train_state, save_atomic,
                         save_model, train_state)
from .data import PairConfig, SyntheticPairs, collate, list_images, split_images
from .errors import LocalScaleError
from .geometry import HomographyConfig
from .models import LocalScaleNet, LocalScaleNetConfig, ScaleNet, ScaleNetConfig
from .outputs import check_writable_dir


class TrainingDiverged(RuntimeError):
    """The loss became NaN/inf; the last good checkpoint is kept."""


@dataclass
class TrainConfig:
    model: str = "local"                   #: "local" (Local-ScaleNet) or "global" (ScaleNet)
    data: str = "../shared/data/train_images"
    out: str = "runs/local"
    backbone: str = "vgg"                  #: "vgg" (trainable) or a frozen pre-trained one ("xfeat", "aliked")
    width: float = 0.25
    feature_dim: int = 128
    image_size: int = 192
    steps: int = 10000
    batch_size: int = 8
    lr: float = 1e-4
    lr_milestones: tuple[int, ...] = ()    #: steps where lr is multiplied by ``lr_gamma`` (paper: 0.1)
    lr_gamma: float = 0.1
    perspective: float = 0.45
    scale_min: float = 0.16
    scale_max: float = 6.0
    context: bool = False                  #: B shows the photo's real surroundings of A (PairConfig.context)
    crop_min: float = 0.6                  #: smallest side of A's crop, as a fraction of the photo
    holdout_every: int = 10                #: every n-th photo (sorted) is held out for validation
    val_pairs: int = 64
    val_every: int = 500
    ckpt_every: int = 250
    workers: int = 1
    seed: int = 0
    device: str = "cpu"
    amp: str = "auto"                      #: "on"/"off"/"auto": fp16 AMP on CUDA, bf16 autocast on CPU
                                           #: ("auto" = CUDA, or a CPU with AMX where bf16 is faster)
    threads: int = 0                       #: torch CPU threads (0 = torch default)
    vgg_weights: str = ""                  #: optional local torchvision VGG16(-BN) state dict (width 1)
    init_weights: str = ""                 #: checkpoint of the same architecture to fine-tune from (new schedule)
    init_extractor: str = ""               #: checkpoint whose feature extractor initialises this model
    init_head: str = ""                    #: checkpoint whose layers after the feature extractor (reductions,
                                           #: cues, head) initialise this model (e.g. across backbones)
    freeze_extractor: bool = False         #: train only the correlation/reduction/head layers
    topk: int = 0                          #: extra cue: k largest correlations per pixel
    warp_features: bool = False            #: extra cue: B's features soft-warped onto A
    visibility: bool = False               #: local: also predict per-pixel co-visibility (BCE loss)
    visibility_weight: float = 0.5         #: weight of the visibility BCE beside the KL loss
    rotation: float = 30.0                 #: max |in-plane rotation| in degrees of ordinary pairs
    translation: float = 0.2               #: max shift of A's centre in B, fraction of B's size
    identity_probability: float = 0.0      #: PairConfig: share of exact / near identity pairs
    full_rotation_probability: float = 0.0 #: PairConfig: share of pairs rotated over the whole circle
    low_overlap_probability: float = 0.0   #: PairConfig: share of pairs with A far off B's centre
    unrelated_probability: float = 0.0     #: PairConfig: share of pairs where B is another photo
    gray_one_side_probability: float = 0.0 #: PairConfig: one side gray
    strong_light_probability: float = 0.0  #: PairConfig: strong lighting change on B
    degrade_probability: float = 0.0       #: PairConfig: blur / noise / JPEG, each, on each side
    swap_probability: float = 0.0          #: PairConfig: share of pairs with A and B swapped
    photometric: float = 0.25              #: PairConfig: strength of the mild photometric jitter

    def check(self) -> None:
        """Refuse settings that cannot train (one-line :class:`LocalScaleError`)."""
        import math

        for name in ("steps", "batch_size", "ckpt_every", "val_every", "val_pairs", "holdout_every"):
            if getattr(self, name) < 1:
                raise LocalScaleError(f"{name.replace('_', '-')} must be >= 1, got {getattr(self, name)}")
        if self.workers < 0:
            raise LocalScaleError(f"workers must be >= 0, got {self.workers}")
        if self.image_size < 32 or self.image_size % 8:
            raise LocalScaleError(f"image-size must be a multiple of 8 and >= 32, got {self.image_size}")
        for name in ("lr_gamma", "width"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise LocalScaleError(f"{name.replace('_', '-')} must be a finite number > 0, got {v}")
        if not 0 <= self.lr <= 1:
            raise LocalScaleError(f"lr must be in [0, 1] (Adam's step size), got {self.lr}")
        if self.feature_dim < 1:
            raise LocalScaleError(f"feature-dim must be >= 1, got {self.feature_dim}")
        if self.model not in ("local", "global"):
            raise LocalScaleError(f"unknown model {self.model!r} (use 'local' or 'global')")
        from .devices import resolve_device

        resolve_device(self.device)   # cuda on a CPU-only torch, cuda:N beyond the GPUs, unknown names
        from .models.backbones import BACKBONE_NAMES

        if self.backbone not in BACKBONE_NAMES:
            raise LocalScaleError(f"unknown backbone {self.backbone!r} (choose from {', '.join(BACKBONE_NAMES)})")
        if self.vgg_weights and self.backbone != "vgg":
            raise LocalScaleError(f"vgg-weights needs --backbone vgg, got {self.backbone!r}")

    def pair_config(self) -> PairConfig:
        if not 0 < self.crop_min <= 1:
            raise LocalScaleError(f"crop_min must be in (0, 1] (a fraction of the photo side), got {self.crop_min}")
        for name in ("identity_probability", "full_rotation_probability", "low_overlap_probability",
                     "unrelated_probability", "gray_one_side_probability", "strong_light_probability",
                     "degrade_probability", "swap_probability"):
            if not 0 <= getattr(self, name) <= 1:
                raise LocalScaleError(f"{name.replace('_', '-')} must be in [0, 1], got {getattr(self, name)}")
        return PairConfig(image_size=self.image_size, homography=HomographyConfig(
            scale_range=(self.scale_min, self.scale_max), perspective=self.perspective,
            rotation_deg=self.rotation, translation=self.translation),
            crop_fraction=(self.crop_min, 1.0), context=self.context, photometric=self.photometric,
            identity_probability=self.identity_probability,
            full_rotation_probability=self.full_rotation_probability,
            low_overlap_probability=self.low_overlap_probability,
            unrelated_probability=self.unrelated_probability,
            gray_one_side_probability=self.gray_one_side_probability,
            strong_light_probability=self.strong_light_probability,
            degrade_probability=self.degrade_probability, swap_probability=self.swap_probability)

    def build_model(self):
        if self.model == "local":
            return LocalScaleNet(LocalScaleNetConfig(self.width, self.feature_dim, self.image_size,
                                                     topk=self.topk, warp_features=self.warp_features,
                                                     visibility=self.visibility, backbone=self.backbone))
        if self.model == "global":
            return ScaleNet(ScaleNetConfig(self.width, self.feature_dim, self.image_size,
                                           topk=self.topk, warp_features=self.warp_features,
                                           backbone=self.backbone))
        raise LocalScaleError(f"unknown model {self.model!r} (use 'local' or 'global')")


#: layers a fine-tune may add to a trained model (initialised fresh when absent from the source)
NEW_LAYER_PREFIXES = ("head.visible.",)


def _load_matching(model, state_dict: dict, source: str,
                   may_miss: tuple[str, ...] = NEW_LAYER_PREFIXES) -> tuple[list[str], list[str]]:
    """Load ``state_dict``; only layers starting with ``may_miss`` (default: the optional new
    layers, :data:`NEW_LAYER_PREFIXES`) may be missing."""
    try:
        missing, unexpected = model.load_state_dict(state_dict, strict=False)
    except RuntimeError as e:
        raise LocalScaleError(f"{source}: weights do not fit this model ({str(e).splitlines()[0]})") from None
    bad = [k for k in missing if not k.startswith(may_miss)] + list(unexpected)
    if bad:
        raise LocalScaleError(f"{source}: weights do not fit this model ({len(bad)} mismatched keys, e.g. {bad[0]})")
    return list(missing), list(unexpected)


def cpu_has_amx() -> bool:
    """True on x86 CPUs with AMX tiles (bf16 matmuls are then 2-3x faster than fp32).

    Without AMX (AVX-512 only) bf16 autocast was measured *slower* than fp32 here
    (0.94 vs 0.75 s/step, quarter width, 192 px, batch 8), so ``amp="auto"`` leaves it off.
    """
    try:
        return "amx_bf16" in Path("/proc/cpuinfo").read_text()
    except OSError:
        return False


def compute_loss(model, batch: dict, kind: str, visibility_weight: float = 0.5) -> torch.Tensor:
    """Local: KL on the co-visible cells (+ BCE of the visibility output over A's image region).
    Global: KL of both directions on pairs that share content."""
    if kind == "local":
        logits, vis = model(batch["a"], batch["b"], all_outputs=True)
        target = scales.scale_to_distribution(batch["scale"], dim=1)
        loss = scales.kl_loss(logits, target, batch["mask"])
        if vis is not None:
            valid = batch["valid"].float()
            bce = F.binary_cross_entropy_with_logits(vis[:, 0].float(), batch["mask"].float(), reduction="none")
            loss = loss + visibility_weight * (bce * valid).sum() / valid.sum().clamp_min(1.0)
        return loss
    l_ab, l_ba = model(batch["a"], batch["b"])
    g = batch["global_scale"].float()
    related = batch["related"] if "related" in batch else None
    return 0.5 * (scales.kl_loss(l_ab, scales.scale_to_distribution(g, 1), related)
                  + scales.kl_loss(l_ba, scales.scale_to_distribution(1.0 / g, 1), related))



@torch.no_grad()
def validate(model, batches: list[dict], kind: str, device, amp_ctx) -> dict:
    """Mean scale-ratio error r on held-out pairs, with the constant-1 baseline."""
    model.eval()
    errs, base, inter, union = [], [], 0.0, 0.0
    for batch in batches:
        batch = {k: v.to(device) for k, v in batch.items()}
        with amp_ctx():
            out = model(batch["a"], batch["b"], all_outputs=True) if kind == "local" else model(batch["a"], batch["b"])
        if kind == "local":
            out, vis = out
            if vis is not None:
                pv, gv, valid = vis[:, 0] > 0, batch["mask"], batch["valid"]
                inter += float((pv & gv & valid).sum())
                union += float(((pv | gv) & valid).sum())
            log_s = scales.soft_log_scale(torch.softmax(out.float(), 1), 1)
            m = batch["mask"]
            gt = torch.log(batch["scale"])
            errs.append((log_s - gt).abs()[m].cpu())
            base.append(gt.abs()[m].cpu())
        else:
            ls_ab = scales.soft_log_scale(torch.softmax(out[0].float(), 1), 1)
            ls_ba = scales.soft_log_scale(torch.softmax(out[1].float(), 1), 1)
            gt = torch.log(batch["global_scale"].float())
            keep = batch["related"] if "related" in batch else torch.ones_like(gt, dtype=torch.bool)
            errs.append((scales.consistent_log_scale(ls_ab, ls_ba) - gt).abs()[keep].cpu())
            base.append(gt.abs()[keep].cpu())
    e, b = torch.cat(errs).double(), torch.cat(base).double()
    row = {"mean_r": float(torch.exp(e).mean()), "median_r": float(torch.exp(e.median())),
           "baseline_mean_r": float(torch.exp(b).mean())}
    if union:
        row["visibility_iou"] = inter / union
    return row


def _grads_finite(model) -> bool:
    return all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)


class _Logger:
    def __init__(self, out: Path, enabled: bool):
        self.enabled = enabled
        self.csv = out / "train_log.csv"
        self.val = out / "val_log.jsonl"

    def train(self, row: dict) -> None:
        if not self.enabled:
            return
        new = not self.csv.exists()
        with open(self.csv, "a", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(row))
            if new:
                w.writeheader()
            w.writerow(row)

    def truncate(self, step: int) -> None:
        """On resume, drop log rows written after the checkpoint (they will be written again)."""
        if not self.enabled:
            return
        if self.csv.exists():
            lines = self.csv.read_text().splitlines(keepends=True)
            self.csv.write_text("".join(lines[:1] + [ln for ln in lines[1:] if int(ln.split(",", 1)[0]) <= step]))
        if self.val.exists():
            rows = [ln for ln in self.val.read_text().splitlines(keepends=True) if json.loads(ln)["step"] <= step]
            self.val.write_text("".join(rows))

    def validation(self, row: dict) -> None:
        if self.enabled:
            with open(self.val, "a") as f:
                f.write(json.dumps(row) + "\n")


def _setup_distributed(cfg: TrainConfig) -> tuple[int, int, torch.device]:
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world > 1:
        local_rank = int(os.environ.get("LOCAL_RANK", "0"))
        if cfg.device.startswith("cuda"):
            torch.cuda.set_device(local_rank)
            device = torch.device("cuda", local_rank)
        else:
            device = torch.device("cpu")
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
        return dist.get_rank(), world, device
    return 0, 1, torch.device(cfg.device)


def die_with_parent() -> None:
    """Make this process exit when its parent dies, even by ``kill -9``.

    On Linux the kernel sends SIGKILL to it when the parent exits (``prctl(PR_SET_PDEATHSIG)``);
    if the parent died before that was set, it exits now. Elsewhere a thread polls the parent.
    """
    import multiprocessing

    parent = multiprocessing.parent_process()
    parent_pid = parent.pid if parent is not None else os.getppid()
    if sys.platform.startswith("linux"):
        try:
            import ctypes

            libc = ctypes.CDLL(None, use_errno=True)
            PR_SET_PDEATHSIG = 1
            libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
        except (OSError, AttributeError):  # pragma: no cover - no usable libc
            pass
    if os.getppid() != parent_pid:   # the parent is already gone
        os._exit(1)
    if not sys.platform.startswith("linux"):  # pragma: no cover
        def _watch():
            while os.getppid() == parent_pid:
                time.sleep(1.0)
            os._exit(1)
        threading.Thread(target=_watch, daemon=True).start()


def _single_threaded_worker(_: int) -> None:
    # each DataLoader worker renders whole samples; OpenCV's own thread pool would oversubscribe the cores
    die_with_parent()
    import cv2
    cv2.setNumThreads(1)
    signal.signal(signal.SIGINT, signal.SIG_IGN)   # Ctrl-C is the main process's: it saves and stops


def train(cfg: TrainConfig, max_steps_this_run: int | None = None) -> dict:
    """Train (or resume) a model into ``cfg.out``. Returns the last validation row.

    ``max_steps_this_run`` stops early (for tests / time-boxed sessions); the run resumes
    from ``last.pt`` next time with identical results.
    """
    cfg.check()
    rank, world, device = _setup_distributed(cfg)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    out = Path(cfg.out)
    check_writable_dir(out)   # before any work; the folder is created once the inputs are checked

    files = list_images(cfg.data)
    train_files, held_files = split_images(files, cfg.holdout_every)
    if not held_files or len(train_files) < 2:
        raise LocalScaleError(f"{cfg.data}: need >= 2 training and >= 1 held-out image, got "
                              f"{len(train_files)} / {len(held_files)}")
    pair_cfg = cfg.pair_config()
    train_set = SyntheticPairs(train_files, length=cfg.steps * cfg.batch_size * world, seed=cfg.seed, config=pair_cfg)
    val_set = SyntheticPairs(held_files + train_files[:1] if len(held_files) < 2 else held_files,
                             length=cfg.val_pairs, seed=cfg.seed + 10_000, config=pair_cfg)

    torch.manual_seed(cfg.seed)
    model = cfg.build_model().to(device)
    if cfg.vgg_weights:
        model.extractor.backbone.load_torchvision_vgg16(cfg.vgg_weights)
    if cfg.init_weights:
        src = read_checkpoint(cfg.init_weights)
        sd = {k: v.float() if v.is_floating_point() else v for k, v in src["state_dict"].items()}
        missing, unexpected = _load_matching(model, sd, cfg.init_weights)
        if rank == 0 and missing:
            print(f"init from {cfg.init_weights}: new layers {', '.join(sorted({k.rsplit('.', 1)[0] for k in missing}))}",
                  file=sys.stderr)
    if cfg.init_head:
        src = read_checkpoint(cfg.init_head)
        sd = {k: v.float() if v.is_floating_point() else v for k, v in src["state_dict"].items()
              if not k.startswith("extractor.")}
        missing, _ = _load_matching(model, sd, cfg.init_head, NEW_LAYER_PREFIXES + ("extractor.",))
        new = sorted({k.rsplit('.', 1)[0] for k in missing if not k.startswith("extractor.")})
        if rank == 0 and new:
            print(f"init from {cfg.init_head}: new layers {', '.join(new)}", file=sys.stderr)
    if cfg.init_extractor:
        src = read_checkpoint(cfg.init_extractor)
        ext = {k[len("extractor."):]: v.float() for k, v in src["state_dict"].items() if k.startswith("extractor.")}
        try:
            model.extractor.load_state_dict(ext)
        except RuntimeError as e:
            raise LocalScaleError(f"{cfg.init_extractor}: feature extractor does not fit ({str(e).splitlines()[0]})") from None
    if cfg.freeze_extractor:
        model.extractor.requires_grad_(False)
    opt = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=cfg.lr)
    sched = torch.optim.lr_scheduler.MultiStepLR(opt, list(cfg.lr_milestones), cfg.lr_gamma)
    step = 0
    last = out / "last.pt"
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise LocalScaleError(f"cannot create output folder {out}: {e.strerror or e}") from None
    log = _Logger(out, rank == 0)
    if last.exists():
        ckpt = read_checkpoint(last)
        try:
            model.load_state_dict(ckpt["state_dict"])
            step = restore_train_state(opt, sched, ckpt["train_state"])
        except (RuntimeError, KeyError, TypeError, ValueError) as e:
            first = [ln.strip() for ln in str(e).splitlines() if ln.strip()][:2]
            raise LocalScaleError(f"{last}: cannot resume, the checkpoint is of another configuration or has no "
                                  f"training state ({type(e).__name__}: {' '.join(first)[:160]}); use another "
                                  f"--out or remove it") from None
        sched.milestones = Counter(cfg.lr_milestones)   # a resumed run may extend its schedule
        log.truncate(step)
        if rank == 0:
            print(f"resuming from {last} at step {step}", file=sys.stderr)
    if world > 1:
        if device.type == "cuda":
            model = torch.nn.SyncBatchNorm.convert_sync_batchnorm(model)
        model = torch.nn.parallel.DistributedDataParallel(model, device_ids=[device.index] if device.type == "cuda" else None)
    core = model.module if world > 1 else model

    use_amp = cfg.amp == "on" or (cfg.amp == "auto" and (device.type == "cuda" or cpu_has_amx()))
    if device.type == "cuda":
        torch.backends.cudnn.benchmark = True
        # bf16 needs no loss scaling; fp16 + GradScaler only on GPUs without bf16
        bf16 = torch.cuda.is_bf16_supported()
        amp_ctx = lambda: torch.autocast("cuda", dtype=torch.bfloat16 if bf16 else torch.float16,  # noqa: E731
                                         enabled=use_amp)
        scaler = None if bf16 else torch.amp.GradScaler("cuda", enabled=use_amp)
    else:
        amp_ctx = lambda: torch.autocast("cpu", dtype=torch.bfloat16, enabled=use_amp)  # noqa: E731
        scaler = None

    def save_last():
        if rank != 0:
            return
        bad = non_finite_tensors(core.state_dict())
        if bad:
            raise TrainingDiverged(f"weights became NaN or inf at step {step} ({bad[0]}); stopped without "
                                   f"saving them, {kept_checkpoint()}")
        ck = checkpoint_dict(core, meta={"train_config": dataclasses.asdict(cfg)})
        ck["train_state"] = train_state(opt, sched, step)
        save_atomic(ck, last)

    def kept_checkpoint() -> str:
        if saved_step is None:
            return "no checkpoint had been written yet"
        return f"the last good checkpoint ({last}, step {saved_step}) is kept"

    val_batches = [collate([val_set[i] for i in range(j, min(j + 16, len(val_set)))])
                   for j in range(0, len(val_set), 16)]
    stop = cfg.steps if max_steps_this_run is None else min(cfg.steps, step + max_steps_this_run)
    # sample index of (step, rank, k) = (step * world + rank) * batch + k
    indices = [i for s in range(step, stop) for i in range((s * world + rank) * cfg.batch_size,
                                                           (s * world + rank + 1) * cfg.batch_size)]
    loader = DataLoader(Subset(train_set, indices), batch_size=cfg.batch_size, shuffle=False,
                        num_workers=cfg.workers, collate_fn=collate, persistent_workers=False,
                        pin_memory=device.type == "cuda", worker_init_fn=_single_threaded_worker,
                        # fork() after tqdm/OpenCV/OpenMP threads exist can deadlock a worker on a held lock
                        multiprocessing_context="spawn" if cfg.workers > 0 else None)
    try:
        from tqdm import tqdm
        bar = tqdm(total=stop, initial=step, desc=f"train {cfg.model}", disable=rank != 0, dynamic_ncols=True)
    except ImportError:  # pragma: no cover
        bar = None
    def set_train():
        model.train()
        if cfg.freeze_extractor:
            core.extractor.eval()

    set_train()
    # Ctrl-C / SIGINT finishes the current step, writes last.pt and stops (a second one stops at once)
    interrupted = threading.Event()
    previous_handler = None
    if world == 1 and threading.current_thread() is threading.main_thread():   # DDP: torchrun handles signals
        def _on_sigint(signum, frame):
            interrupted.set()
            signal.signal(signal.SIGINT, previous_handler)
        previous_handler = signal.signal(signal.SIGINT, _on_sigint)
    t0, last_val, skipped, redrawn = time.time(), {}, 0, 0
    saved_step = step if last.exists() else None
    for batch in loader:
        redrawn += int(batch.pop("redrawn").sum()) if "redrawn" in batch else 0
        batch = {k: v.to(device, non_blocking=True) for k, v in batch.items()}
        with amp_ctx():
            loss = compute_loss(model, batch, cfg.model, cfg.visibility_weight)
        if not torch.isfinite(loss):
            raise TrainingDiverged(f"loss is {loss.item()} at step {step + 1}; stopped, {kept_checkpoint()}")
        opt.zero_grad(set_to_none=True)
        if scaler is not None:
            scaler.scale(loss).backward()
            scaler.step(opt)
            scaler.update()
        else:
            loss.backward()
            if _grads_finite(core):
                opt.step()
            else:
                skipped += 1
                if skipped > 20:
                    raise TrainingDiverged(f"non-finite gradients in {skipped} steps (last at step {step + 1}); "
                                           f"stopped, {kept_checkpoint()}")
                if bar is not None:
                    bar.write(f"step {step + 1}: non-finite gradients, update skipped")
        sched.step()
        step += 1
        if bar is not None:
            bar.update(1)
            bar.set_postfix(loss=f"{loss.item():.4f}")
        log.train({"step": step, "loss": round(loss.item(), 6), "lr": opt.param_groups[0]["lr"],
                   "time_s": round(time.time() - t0, 2)})
        if step % cfg.ckpt_every == 0 or step == stop or interrupted.is_set():
            save_last()
            saved_step = step
        if interrupted.is_set():
            break
        if rank == 0 and (step % cfg.val_every == 0 or step == cfg.steps):
            last_val = {"step": step, **validate(core, val_batches, cfg.model, device, amp_ctx)}
            set_train()
            log.validation(last_val)
            if bar is not None:
                bar.write(f"step {step}: val mean r {last_val['mean_r']:.3f} (median {last_val['median_r']:.3f}, "
                          f"constant-1 {last_val['baseline_mean_r']:.3f})")
    if bar is not None:
        bar.close()
    if redrawn and rank == 0:
        print(f"warning: {redrawn} training sample(s) were drawn again because a photo could not be used "
              f"(corrupt or smaller than a crop; each such photo was named once above)", file=sys.stderr)
    if previous_handler is not None:
        signal.signal(signal.SIGINT, previous_handler)
    if interrupted.is_set():
        raise KeyboardInterrupt
    if rank == 0 and step == cfg.steps:
        save_model(core, out / "model.pt", meta={"train_config": dataclasses.asdict(cfg), "steps": step,
                                                 "validation": last_val}, half=True)
    if world > 1:
        dist.destroy_process_group()
    return last_val


def parse_args(argv: list[str] | None = None, model: str | None = None) -> TrainConfig:
    from .cli_options import OneLineErrorParser

    p = OneLineErrorParser(description="Train Local-ScaleNet or ScaleNet on synthetic homography pairs.")
    for f in dataclasses.fields(TrainConfig):
        if model is not None and f.name == "model":
            continue
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        if model == "global" and f.name == "out":
            default = "runs/global"
        flag = "--" + f.name.replace("_", "-")
        if isinstance(default, bool):
            p.add_argument(flag, action=argparse.BooleanOptionalAction, default=default)
        elif isinstance(default, tuple):
            p.add_argument(flag, type=int, nargs="*", default=list(default))
        else:
            p.add_argument(flag, type=type(default), default=default)
    p.add_argument("--max-steps-this-run", type=int, default=None,
                   help="stop after this many steps (resume later with the same command)")
    a = vars(p.parse_args(argv))
    max_run = a.pop("max_steps_this_run")
    if model is not None:
        a["model"] = model
    a["lr_milestones"] = tuple(a["lr_milestones"])
    cfg = TrainConfig(**a)
    cfg._max_steps_this_run = max_run  # type: ignore[attr-defined]
    return cfg


def main(argv: list[str] | None = None, model: str | None = None) -> int:
    cfg = parse_args(argv, model)
    try:
        res = train(cfg, getattr(cfg, "_max_steps_this_run", None))
    except (LocalScaleError, TrainingDiverged) as e:
        print(f"error: {' '.join(str(e).split())}", file=sys.stderr)
        return 2
    except OSError as e:   # a file the run reads or writes (full disk, no permission)
        where = f"{e.filename}: " if e.filename else ""
        print(f"error: {where}{e.strerror or e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"interrupted; resume with the same command (checkpoint: {Path(cfg.out) / 'last.pt'})", file=sys.stderr)
        return 130
    if res:
        print(json.dumps(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
