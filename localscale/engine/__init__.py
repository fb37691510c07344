"""Where the per-image and per-pair loops of a command run: in this process (``local``, the
default) or on a Ray cluster (``ray``: an actor pool, each actor holding the model once).

    from localscale.engine import get_executor
    with get_executor("ray", workers=2, threads_per_worker=1) as ex:
        for i, result in ex.map(fn, items, state=factory):
            ...   # completion order; ``result`` is the LocalScaleError of an item that failed

:func:`predict_pairs_with` is ``predict --pairs`` over an executor: features once per image, the
heads per pair, every prediction yielded to the driver as it finishes.
"""

from .base import (
    ENGINES,
    RAY_INSTALL_HINT,
    EngineError,
    Executor,
    LocalExecutor,
    RunStats,
    WorkerLostError,
)
from .choose import get_executor
from .pairs import EncodeImage, ModelFactory, PairStats, PredictPair, driver_model, predict_pairs_with

__all__ = [
    "ENGINES",
    "RAY_INSTALL_HINT",
    "EngineError",
    "Executor",
    "LocalExecutor",
    "RunStats",
    "WorkerLostError",
    "get_executor",
    "RayExecutor",
    "EncodeImage",
    "ModelFactory",
    "PairStats",
    "PredictPair",
    "predict_pairs_with",
    "driver_model",
]


def __getattr__(name):
    if name == "RayExecutor":  # imports nothing of Ray until used
        from .ray_engine import RayExecutor

        return RayExecutor
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
