"""One trainer for both scale models (``--model local`` or ``--model global``).

Features: config dataclass (:mod:`.config`), KL loss on co-visible cells (local) / both
directions (global), Adam with step decay, bf16 autocast on CPU and AMP on CUDA, DDP under
``torchrun``, tqdm progress, periodic validation on held-out photos (mean scale-ratio error r),
checkpoints that resume exactly (data is a pure function of ``(seed, sample index)``),
CSV/JSON logs, and a stop on a non-finite loss that keeps the last good checkpoint
(:mod:`.loop`, :mod:`.steps`); the command line is :mod:`localscale.cli.train`.

    localscale-train --model local --data ../shared/data/train_images --out runs/local
"""

from .config import NEW_LAYER_PREFIXES, TrainConfig, TrainingDiverged
from .loop import build_model, train
from .steps import _single_threaded_worker, compute_loss, die_with_parent, validate  # noqa: F401

__all__ = [
    "TrainConfig",
    "TrainingDiverged",
    "NEW_LAYER_PREFIXES",
    "train",
    "build_model",
    "compute_loss",
    "validate",
    "die_with_parent",
]
