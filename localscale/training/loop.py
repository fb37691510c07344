"""The training loop: :func:`train` builds the data, the model and the optimiser, resumes from
``last.pt`` when it exists, and runs the steps with checkpoints, validation and logs."""

from __future__ import annotations

import dataclasses
import signal
import sys
import threading
import time
from collections import Counter
from pathlib import Path

import torch
import torch.distributed as dist
from torch.utils.data import DataLoader, Subset

from ..checkpoint import (
    checkpoint_dict,
    non_finite_tensors,
    read_checkpoint,
    restore_train_state,
    save_atomic,
    save_model,
    train_state,
)
from ..core.devices import cpu_has_bf16
from ..core.errors import LocalScaleError
from ..core.outputs import check_writable_dir
from ..data import SyntheticPairs, collate, list_images, split_images
from .config import NEW_LAYER_PREFIXES, TrainConfig, TrainingDiverged
from .steps import (
    _grads_finite,
    _load_matching,
    _Logger,
    _setup_distributed,
    _single_threaded_worker,
    compute_loss,
    validate,
)


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
    check_writable_dir(out)  # before any work; the folder is created once the inputs are checked
    run = _Run(cfg, rank, world, device, out)
    try:
        return run.fit(max_steps_this_run)
    finally:
        if world > 1:
            dist.destroy_process_group()


def _datasets(cfg: TrainConfig, world: int) -> tuple[SyntheticPairs, SyntheticPairs]:
    """The training pairs and the held-out validation pairs (photos split by ``holdout_every``)."""
    files = list_images(cfg.data)
    train_files, held_files = split_images(files, cfg.holdout_every)
    if not held_files or len(train_files) < 2:
        raise LocalScaleError(
            f"{cfg.data}: need >= 2 training and >= 1 held-out image, got {len(train_files)} / {len(held_files)}"
        )
    pair_cfg = cfg.pair_config()
    train_set = SyntheticPairs(train_files, length=cfg.steps * cfg.batch_size * world, seed=cfg.seed, config=pair_cfg)
    val_set = SyntheticPairs(
        held_files + train_files[:1] if len(held_files) < 2 else held_files,
        length=cfg.val_pairs,
        seed=cfg.seed + 10_000,
        config=pair_cfg,
    )
    if cfg.real_pairs:
        from .real_pairs import MixedPairs, RealPairConfig, RealPairs

        real = RealPairs(_real_pairs(cfg.real_pairs), len(train_set), cfg.seed + 1, RealPairConfig(cfg.image_size))
        train_set = MixedPairs(train_set, real, cfg.real_fraction, cfg.seed)
    return train_set, val_set


def _real_pairs(files: str) -> list:
    from .real_pairs import load_covisible_pairs

    return [p for f in files.split(",") if f.strip() for p in load_covisible_pairs(f.strip())]


def real_validation_batches(files: str, n: int, seed: int, image_size: int, batch: int = 16, **sampling) -> list[dict]:
    """``n`` fixed samples (seeded) of the labelled real pairs in ``files`` (comma-separated), in batches;
    ``sampling``: :class:`~.real_pairs.RealPairConfig` fields (e.g. ``turn_probability=0``)."""
    from .real_pairs import RealPairConfig, RealPairs

    ds = RealPairs(_real_pairs(files), n, seed, RealPairConfig(image_size, **sampling))
    return [collate([ds[i] for i in range(j, min(j + batch, n))]) for j in range(0, n, batch)]


def _float_state(path) -> dict:
    src = read_checkpoint(path)
    return {k: v.float() if v.is_floating_point() else v for k, v in src["state_dict"].items()}


def build_model(cfg: TrainConfig, verbose: bool = True):
    """The model of ``cfg``, seeded, with the weights its ``init_*`` / ``vgg_weights`` options name."""
    torch.manual_seed(cfg.seed)
    model = cfg.build_model()
    if cfg.vgg_weights:
        model.extractor.backbone.load_torchvision_vgg16(cfg.vgg_weights)
    if cfg.init_weights:
        missing, _ = _load_matching(model, _float_state(cfg.init_weights), cfg.init_weights)
        if verbose and missing:
            print(
                f"init from {cfg.init_weights}: new layers {', '.join(sorted({k.rsplit('.', 1)[0] for k in missing}))}",
                file=sys.stderr,
            )
    if cfg.init_head:
        sd = {k: v for k, v in _float_state(cfg.init_head).items() if not k.startswith("extractor.")}
        missing, _ = _load_matching(model, sd, cfg.init_head, NEW_LAYER_PREFIXES + ("extractor.",))
        new = sorted({k.rsplit(".", 1)[0] for k in missing if not k.startswith("extractor.")})
        if verbose and new:
            print(f"init from {cfg.init_head}: new layers {', '.join(new)}", file=sys.stderr)
    if cfg.init_extractor:
        ext = {
            k[len("extractor.") :]: v for k, v in _float_state(cfg.init_extractor).items() if k.startswith("extractor.")
        }
        try:
            model.extractor.load_state_dict(ext)
        except RuntimeError as e:
            raise LocalScaleError(
                f"{cfg.init_extractor}: feature extractor does not fit ({str(e).splitlines()[0]})"
            ) from None
    if cfg.freeze_extractor:
        model.extractor.requires_grad_(False)
    return model


def cpu_bf16_pays(model, batch: dict, cfg: TrainConfig, margin: float = 0.9) -> bool:
    """Whether a training step (forward + backward) on ``batch`` runs faster on this CPU under bf16
    autocast than in fp32: one warm-up and one timed step each; bf16 must take under ``margin`` of the
    fp32 time. The answer differs between CPUs that all have native bf16 (1.9x faster on one, 1.25x
    slower on another), so it is measured, not read off the CPU flags. The model's state (batch-norm
    statistics) is restored and its gradients cleared after."""
    state = {k: v.clone() for k, v in model.state_dict().items()}

    def timed(enabled: bool) -> float:
        best = float("inf")
        for _ in range(2):
            t0 = time.perf_counter()
            with torch.autocast("cpu", dtype=torch.bfloat16, enabled=enabled):
                loss = compute_loss(model, batch, cfg.model, cfg.visibility_weight, cfg.loss_per_pair)
            loss.backward()
            best = min(best, time.perf_counter() - t0)
        return best

    try:
        return timed(True) < margin * timed(False)
    finally:
        model.zero_grad(set_to_none=True)
        model.load_state_dict(state)


def _autocast(cfg: TrainConfig, device: torch.device, use_amp: bool):
    """``(autocast context factory, GradScaler or None)`` for bf16/fp16 autocast when ``use_amp``."""
    if device.type != "cuda":
        return (lambda: torch.autocast("cpu", dtype=torch.bfloat16, enabled=use_amp)), None
    torch.backends.cudnn.benchmark = True
    # bf16 needs no loss scaling; fp16 + GradScaler only on GPUs without bf16
    bf16 = torch.cuda.is_bf16_supported()
    ctx = lambda: torch.autocast("cuda", dtype=torch.bfloat16 if bf16 else torch.float16, enabled=use_amp)  # noqa: E731
    return ctx, (None if bf16 else torch.amp.GradScaler("cuda", enabled=use_amp))


class _Run:
    """One training run: its data, model, optimiser and schedule, resumed from ``last.pt`` if present."""

    def __init__(self, cfg: TrainConfig, rank: int, world: int, device: torch.device, out: Path):
        self.cfg, self.rank, self.world, self.device, self.out = cfg, rank, world, device, out
        self.train_set, val_set = _datasets(cfg, world)
        model = build_model(cfg, verbose=rank == 0).to(device)
        self.opt = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=cfg.lr)
        self.sched = torch.optim.lr_scheduler.MultiStepLR(self.opt, list(cfg.lr_milestones), cfg.lr_gamma)
        self.last = out / "last.pt"
        try:
            out.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise LocalScaleError(f"cannot create output folder {out}: {e.strerror or e}") from None
        self.log = _Logger(out, rank == 0)
        self.step = self._resume(model) if self.last.exists() else 0
        self.saved_step = self.step if self.last.exists() else None
        if world > 1:
            if device.type == "cuda":
                model = torch.nn.SyncBatchNorm.convert_sync_batchnorm(model)
            model = torch.nn.parallel.DistributedDataParallel(
                model, device_ids=[device.index] if device.type == "cuda" else None
            )
        self.model, self.core = model, (model.module if world > 1 else model)
        self.val_batches = [
            collate([val_set[i] for i in range(j, min(j + 16, len(val_set)))]) for j in range(0, len(val_set), 16)
        ]
        self.real_val_batches = (
            real_validation_batches(cfg.real_val_pairs, cfg.val_pairs, cfg.seed + 20_000, cfg.image_size)
            if cfg.real_val_pairs
            else []
        )
        self.skipped = 0
        self.amp_ctx, self.scaler = _autocast(cfg, device, self._use_amp(device, val_set))

    def _use_amp(self, device: torch.device, pairs) -> bool:
        """``amp``: on, off, or auto: always on CUDA; on a CPU with native bf16, when a probe step is faster."""
        if self.cfg.amp != "auto":
            return self.cfg.amp == "on"
        if device.type == "cuda":
            return True
        if not cpu_has_bf16():
            return False
        n = min(self.cfg.batch_size, len(pairs))
        batch = {k: v.to(device) for k, v in collate([pairs[i] for i in range(n)]).items()}
        pays = cpu_bf16_pays(self.core, batch, self.cfg)
        if self.rank == 0:
            print(
                f"amp auto: bf16 autocast {'on' if pays else 'off'} (a probe step was "
                f"{'faster' if pays else 'not faster'} than fp32 on this CPU)",
                file=sys.stderr,
            )
        return pays

    def _resume(self, model) -> int:
        ckpt = read_checkpoint(self.last)
        try:
            model.load_state_dict(ckpt["state_dict"])
            step = restore_train_state(self.opt, self.sched, ckpt["train_state"])
        except (RuntimeError, KeyError, TypeError, ValueError) as e:
            first = [ln.strip() for ln in str(e).splitlines() if ln.strip()][:2]
            raise LocalScaleError(
                f"{self.last}: cannot resume, the checkpoint is of another configuration or has no "
                f"training state ({type(e).__name__}: {' '.join(first)[:160]}); use another "
                f"--out or remove it"
            ) from None
        self.sched.milestones = Counter(self.cfg.lr_milestones)  # a resumed run may extend its schedule
        self.log.truncate(step)
        if self.rank == 0:
            print(f"resuming from {self.last} at step {step}", file=sys.stderr)
        return step

    def kept_checkpoint(self) -> str:
        if self.saved_step is None:
            return "no checkpoint had been written yet"
        return f"the last good checkpoint ({self.last}, step {self.saved_step}) is kept"

    def save_last(self) -> None:
        if self.rank == 0:
            bad = non_finite_tensors(self.core.state_dict())
            if bad:
                raise TrainingDiverged(
                    f"weights became NaN or inf at step {self.step} ({bad[0]}); stopped without "
                    f"saving them, {self.kept_checkpoint()}"
                )
            ck = checkpoint_dict(self.core, meta={"train_config": dataclasses.asdict(self.cfg)})
            ck["train_state"] = train_state(self.opt, self.sched, self.step)
            save_atomic(ck, self.last)
        self.saved_step = self.step

    def loader(self, stop: int) -> DataLoader:
        """The samples of steps ``step .. stop - 1`` of this rank: index ``(step * world + rank) * batch + k``."""
        cfg, world, rank = self.cfg, self.world, self.rank
        indices = [
            i
            for s in range(self.step, stop)
            for i in range((s * world + rank) * cfg.batch_size, (s * world + rank + 1) * cfg.batch_size)
        ]
        return DataLoader(
            Subset(self.train_set, indices),
            batch_size=cfg.batch_size,
            shuffle=False,
            num_workers=cfg.workers,
            collate_fn=collate,
            persistent_workers=False,
            pin_memory=self.device.type == "cuda",
            worker_init_fn=_single_threaded_worker,
            # fork() after tqdm/OpenCV/OpenMP threads exist can deadlock a worker on a held lock
            multiprocessing_context="spawn" if cfg.workers > 0 else None,
        )

    def set_train(self) -> None:
        self.model.train()
        if self.cfg.freeze_extractor:
            self.core.extractor.eval()

    def train_step(self, batch: dict, bar) -> float:
        """One optimiser step on ``batch``; returns its loss."""
        batch = {k: v.to(self.device, non_blocking=True) for k, v in batch.items()}
        with self.amp_ctx():
            loss = compute_loss(self.model, batch, self.cfg.model, self.cfg.visibility_weight, self.cfg.loss_per_pair)
        if not torch.isfinite(loss):
            raise TrainingDiverged(f"loss is {loss.item()} at step {self.step + 1}; stopped, {self.kept_checkpoint()}")
        self.opt.zero_grad(set_to_none=True)
        if self.scaler is not None:
            self.scaler.scale(loss).backward()
            self.scaler.step(self.opt)
            self.scaler.update()
        else:
            loss.backward()
            if _grads_finite(self.core):
                self.opt.step()
            else:
                self.skipped += 1
                if self.skipped > 20:
                    raise TrainingDiverged(
                        f"non-finite gradients in {self.skipped} steps (last at step {self.step + 1}); "
                        f"stopped, {self.kept_checkpoint()}"
                    )
                if bar is not None:
                    bar.write(f"step {self.step + 1}: non-finite gradients, update skipped")
        self.sched.step()
        self.step += 1
        return loss.item()

    def validate(self, bar) -> dict:
        row = {"step": self.step, **validate(self.core, self.val_batches, self.cfg.model, self.device, self.amp_ctx)}
        if self.real_val_batches:
            real = validate(self.core, self.real_val_batches, self.cfg.model, self.device, self.amp_ctx)
            row.update({f"real_{k}": v for k, v in real.items()})
        self.set_train()
        self.log.validation(row)
        if bar is not None:
            bar.write(
                f"step {self.step}: val mean r {row['mean_r']:.3f} (median {row['median_r']:.3f}, "
                f"constant-1 {row['baseline_mean_r']:.3f})"
                + (f"; real mean r {row['real_mean_r']:.3f}" if "real_mean_r" in row else "")
            )
        return row

    def fit(self, max_steps_this_run: int | None = None) -> dict:
        """Run the steps up to ``cfg.steps`` (or ``max_steps_this_run`` more); checkpoints, validation,
        logs; Ctrl-C finishes the current step, writes ``last.pt`` and stops (a second one stops at once)."""
        cfg = self.cfg
        stop = cfg.steps if max_steps_this_run is None else min(cfg.steps, self.step + max_steps_this_run)
        loader = self.loader(stop)
        from tqdm import tqdm

        bar = tqdm(total=stop, initial=self.step, desc=f"train {cfg.model}", disable=self.rank != 0, dynamic_ncols=True)
        self.set_train()
        with _StopOnSigint(self.world == 1) as interrupted:
            t0, last_val, redrawn = time.time(), {}, 0
            for batch in loader:
                redrawn += int(batch.pop("redrawn").sum()) if "redrawn" in batch else 0
                loss = self.train_step(batch, bar)
                bar.update(1)
                bar.set_postfix(loss=f"{loss:.4f}")
                self.log.train(
                    {
                        "step": self.step,
                        "loss": round(loss, 6),
                        "lr": self.opt.param_groups[0]["lr"],
                        "time_s": round(time.time() - t0, 2),
                    }
                )
                if self.step % cfg.ckpt_every == 0 or self.step == stop or interrupted.is_set():
                    self.save_last()
                if interrupted.is_set():
                    break
                if self.rank == 0 and (self.step % cfg.val_every == 0 or self.step == cfg.steps):
                    last_val = self.validate(bar)
            bar.close()
        if redrawn and self.rank == 0:
            print(
                f"warning: {redrawn} training sample(s) were drawn again because a photo could not be used "
                f"(corrupt or smaller than a crop; each such photo was named once above)",
                file=sys.stderr,
            )
        if interrupted.is_set():
            raise KeyboardInterrupt
        if self.rank == 0 and self.step == cfg.steps:
            save_model(
                self.core,
                self.out / "model.pt",
                half=True,
                meta={"train_config": dataclasses.asdict(cfg), "steps": self.step, "validation": last_val},
            )
        return last_val


class _StopOnSigint:
    """While active (single process, main thread), the first SIGINT sets the event it returns and
    restores the previous handler (a second one stops at once). DDP: torchrun handles signals."""

    def __init__(self, enabled: bool):
        self.enabled = enabled and threading.current_thread() is threading.main_thread()
        self.event, self.previous = threading.Event(), None

    def __enter__(self) -> threading.Event:
        if self.enabled:

            def _on_sigint(signum, frame):
                self.event.set()
                signal.signal(signal.SIGINT, self.previous)

            self.previous = signal.signal(signal.SIGINT, _on_sigint)
        return self.event

    def __exit__(self, *exc) -> None:
        if self.previous is not None:
            signal.signal(signal.SIGINT, self.previous)
