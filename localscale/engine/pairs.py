"""``predict --pairs`` over an executor: each image encoded once, the head run per pair.

Two maps per chunk of pairs: :class:`EncodeImage` over the chunk's images not encoded yet
(``keep=True``: the encodings stay with the workers, in Ray's object store), then
:class:`PredictPair` over the chunk's pairs, each item holding its two images' encodings. An
encoding is dropped once the last pair that uses it is done, so memory stays bounded by the
images of about one chunk. Predictions come back to the driver (on the network's processing grid:
a few hundred KB each) in completion order; the driver writes the files
(:func:`localscale.maps.files.write_scale_map`), exactly as the in-process loop does.

    factory = ModelFactory("local", weights=None, device="cpu")
    with get_executor("ray", workers=2) as ex:
        for i, pred in predict_pairs_with(ex, pairs, factory):
            if isinstance(pred, Exception): ...      # that pair failed (bad image): warn, go on
            else: write_scale_map(pred, out, names[i], inputs)
"""

from __future__ import annotations

import os
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Optional, Sequence

from .base import Executor, LocalExecutor


@dataclass(frozen=True)
class ModelFactory:
    """The worker state of the pair work: a scale model, loaded once per worker."""

    kind: str = "local"
    weights: Optional[str] = None
    device: str = "cpu"

    def __call__(self):
        from ..loading import load_scale_model

        return load_scale_model(self.kind, self.weights, self.device)


@dataclass(frozen=True)
class EncodeImage:
    """Work of one image: its backbone features (an :class:`~localscale.models.base.EncodedImage`)."""

    bf16: bool = False

    def __call__(self, model, path):
        from ..cache import encode_batch

        return encode_batch(model, [path], self.bf16)[0]


@dataclass(frozen=True)
class PredictPair:
    """Work of one pair ``(encoding_a, encoding_b)``: the head, ``S_{A->B}`` on A's processing grid
    (read out at full resolution when the driver writes it)."""

    bf16: bool = False
    hard: bool = False
    planar: bool = False

    def __call__(self, model, encodings):
        from ..cache import predict_batch

        enc_a, enc_b = encodings
        return predict_batch(model, [enc_a], [enc_b], self.bf16, self.hard, self.planar)[0]


@dataclass
class PairStats:
    """What :func:`predict_pairs_with` did."""

    engine: str = ""
    workers: int = 0
    pairs: int = 0
    failed: int = 0
    encoded: int = 0  #: images encoded (once each)
    reused: int = 0  #: pair sides served by an encoding made for an earlier pair
    seconds: float = 0.0  #: from the call to the last pair, the workers' start included
    startup_seconds: float = 0.0
    retried: int = 0

    @property
    def pairs_per_second(self) -> float:
        return self.pairs / self.seconds if self.seconds > 0 else 0.0

    def summary(self) -> str:
        text = (
            f"{self.pairs} pairs in {self.seconds:.1f} s: {self.pairs_per_second:.2f} pairs/s on {self.workers} "
            f"worker(s) ({self.engine}; workers started in {self.startup_seconds:.1f} s); {self.encoded} images "
            f"encoded, {self.reused} reused"
        )
        if self.failed:
            text += f"; {self.failed} failed"
        if self.retried:
            text += f"; {self.retried} retried after a lost worker"
        return text


def image_key(path) -> tuple:
    """The same file under any name: resolved path and modification time (as the feature cache)."""
    p = Path(os.path.realpath(os.path.abspath(path)))
    try:
        return (str(p), p.stat().st_mtime_ns)
    except OSError:
        return (str(p), None)


def driver_model(executor: Executor, factory: ModelFactory):
    """The model for the driver's own use (its outputs' names, its weights): the local engine's
    worker state itself, else a model loaded here."""
    return executor.state(factory) if isinstance(executor, LocalExecutor) else factory()


def predict_pairs_with(
    executor: Executor,
    pairs: Sequence[tuple],
    model: Optional[ModelFactory] = None,
    *,
    bf16: bool = False,
    hard: bool = False,
    planar: bool = False,
    chunk_pairs: int = 256,
    stats: Optional[PairStats] = None,
) -> Iterator[tuple[int, object]]:
    """Yield ``(index, prediction)`` for each ``(path_a, path_b)`` of ``pairs`` in completion order;
    a pair with a bad image yields ``(index, LocalScaleError)`` and the others still run.

    ``model``: the worker state factory (default: the bundled Local-ScaleNet on the CPU);
    ``bf16`` / ``hard`` / ``planar``: as in :meth:`LocalScaleNet.predict`; ``chunk_pairs``: pairs
    per round (bounds the encodings held); ``stats``: a :class:`PairStats` filled as the run goes."""
    model = model if model is not None else ModelFactory()
    stats = stats if stats is not None else PairStats()
    stats.engine, stats.workers = executor.name, executor.workers
    t0 = time.perf_counter()
    pairs = [tuple(p) for p in pairs]
    keys = [(image_key(a), image_key(b)) for a, b in pairs]
    uses = Counter(k for ks in keys for k in ks)
    held: dict = {}  # image key -> encoding handle, or the LocalScaleError of its image
    encode, predict = EncodeImage(bf16), PredictPair(bf16, hard, planar)

    def add_run() -> None:
        run = executor.last_run
        stats.startup_seconds += run.startup_seconds
        stats.retried += run.retried
        stats.workers = executor.workers

    for start in range(0, len(pairs), max(1, chunk_pairs)):
        chunk = range(start, min(len(pairs), start + max(1, chunk_pairs)))
        paths = {}
        for i in chunk:
            for k, p in zip(keys[i], pairs[i]):
                if k not in held:
                    paths.setdefault(k, p)
                else:
                    stats.reused += 1
        new = list(paths)
        for j, handle in executor.map(encode, [paths[k] for k in new], state=model, keep=True):
            held[new[j]] = handle
            stats.encoded += not isinstance(handle, Exception)
        add_run()
        # a key seen twice within the chunk was encoded once: count its later uses as reused
        stats.reused += sum(
            uses_in_chunk - 1 for uses_in_chunk in Counter(k for i in chunk for k in keys[i] if k in paths).values()
        )
        ready = []
        for i in chunk:
            bad = next((held[k] for k in keys[i] if isinstance(held[k], Exception)), None)
            if bad is not None:
                stats.pairs += 1
                stats.failed += 1
                stats.seconds = time.perf_counter() - t0
                yield i, bad
            else:
                ready.append(i)
        items = [(held[keys[i][0]], held[keys[i][1]]) for i in ready]
        for j, pred in executor.map(predict, items, state=model):
            stats.pairs += 1
            stats.failed += isinstance(pred, Exception)
            stats.seconds = time.perf_counter() - t0
            yield ready[j], pred
        add_run()
        del items
        for i in chunk:  # drop the encodings no later pair needs
            for k in keys[i]:
                uses[k] -= 1
                if not uses[k]:
                    held.pop(k, None)
    stats.seconds = time.perf_counter() - t0
