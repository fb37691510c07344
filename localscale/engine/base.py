"""Executors: where the per-image and per-pair work of a command runs.

An executor runs ``fn(state, item)`` for every item and yields ``(index, result)`` as each item
finishes (completion order, each index exactly once), so that the caller writes every result at
once and a rerun after an interruption skips what was written. ``state`` is built once per worker
by ``state_factory``, a picklable zero-argument callable (e.g. one that loads a model), and is
reused for all the items that worker runs; ``fn`` is picklable too (a module-level function or a
small frozen dataclass with ``__call__``).

A :class:`~localscale.core.errors.LocalScaleError` raised by ``fn`` is bad input for that item: the
exception instance is yielded as the item's result (never retried), like the local loop of a
command does. Any other exception is a bug and ends the run.

    with get_executor("ray", workers=2, threads_per_worker=1) as ex:
        for i, result in ex.map(fn, items, state=factory, progress="pairs"):
            if isinstance(result, Exception): ...   # that item failed
            else: ...                              # write it now

``keep=True`` leaves the results where the workers can read them (the Ray object store; in
process, the values themselves) and yields handles instead of values: put a handle inside the item
of a later ``map`` (directly, or inside a tuple, list or dict) and the worker receives the value.
That is how per-image features are computed once and shared by every pair that uses the image.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Iterator, Optional

from ..core.errors import LocalScaleError

#: the engines :func:`get_executor` knows
ENGINES = ("local", "ray")

#: the one line that says how to get the Ray engine
RAY_INSTALL_HINT = "pip install 'localscale[ray]'"


class EngineError(LocalScaleError):
    """Bad engine options, Ray missing, or a Ray cluster that cannot be used."""


class WorkerLostError(EngineError):
    """An item whose worker process died (killed, out of memory) on every attempt."""


@dataclass
class RunStats:
    """What one :meth:`Executor.map` did: items, failures, retries after a lost worker, time."""

    engine: str
    workers: int
    threads_per_worker: Optional[int] = None
    items: int = 0
    failed: int = 0
    retried: int = 0
    seconds: float = 0.0
    startup_seconds: float = 0.0

    @property
    def items_per_second(self) -> float:
        return self.items / self.seconds if self.seconds > 0 else 0.0

    def add(self, other: "RunStats") -> None:
        """Add another run's counts and time (several maps of one command)."""
        self.items += other.items
        self.failed += other.failed
        self.retried += other.retried
        self.seconds += other.seconds
        self.startup_seconds += other.startup_seconds

    def summary(self, unit: str = "item") -> str:
        threads = f", {self.threads_per_worker} thread(s) each" if self.threads_per_worker else ""
        text = (
            f"{self.items} {unit}s in {self.seconds:.1f} s: {self.items_per_second:.2f} {unit}s/s on "
            f"{self.workers} worker(s) ({self.engine}{threads})"
        )
        if self.startup_seconds:
            text += f"; workers started in {self.startup_seconds:.1f} s"
        if self.failed:
            text += f"; {self.failed} failed"
        if self.retried:
            text += f"; {self.retried} retried after a lost worker"
        return text


def progress_bar(total: int, desc: Optional[str], unit: str):
    """The one tqdm bar of a run (None without ``desc``; off when stderr is not a terminal)."""
    if desc is None:
        return None
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit=unit, disable=None)


def state_key(factory) -> Any:
    """A dictionary key for a state factory: the factory itself when hashable, else its identity."""
    try:
        hash(factory)
        return factory
    except TypeError:
        return ("id", id(factory))


class Executor:
    """Runs ``fn(state, item)`` over items; see the module docstring. A context manager."""

    name = "executor"

    def __init__(self) -> None:
        self.last_run: Optional[RunStats] = None

    @property
    def workers(self) -> int:
        return 1

    def map(
        self,
        fn: Callable,
        items: Iterable,
        *,
        state: Optional[Callable] = None,
        keep: bool = False,
        progress: Optional[str] = None,
        unit: str = "item",
    ) -> Iterator[tuple[int, Any]]:
        """Yield ``(index, result)`` for every item as it finishes; ``result`` is the exception for an
        item that failed with a :class:`LocalScaleError`. ``progress``: the tqdm bar's label."""
        raise NotImplementedError

    def close(self) -> None:
        """Stop the workers (and a cluster this executor started)."""

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class LocalExecutor(Executor):
    """Runs every item in this process, in input order, with one worker state per factory.

    ``threads_per_worker``: ``torch.set_num_threads`` for the run (None leaves torch's setting)."""

    name = "local"

    def __init__(self, threads_per_worker: Optional[int] = None):
        super().__init__()
        self.threads_per_worker = threads_per_worker
        self._states: dict = {}

    def state(self, factory: Optional[Callable]):
        """The worker state of ``factory``, built on first use (one factory's state is kept)."""
        if factory is None:
            return None
        key = state_key(factory)
        if key not in self._states:
            self._states = {key: factory()}
        return self._states[key]

    def map(self, fn, items, *, state=None, keep=False, progress=None, unit="item"):
        items = list(items)
        if self.threads_per_worker:
            import torch

            torch.set_num_threads(self.threads_per_worker)
        t0 = time.perf_counter()
        value = self.state(state)
        stats = RunStats(self.name, 1, self.threads_per_worker, startup_seconds=time.perf_counter() - t0)
        self.last_run = stats
        bar = progress_bar(len(items), progress, unit)
        t0 = time.perf_counter()
        try:
            for i, item in enumerate(items):
                try:
                    result = fn(value, item)
                except LocalScaleError as e:
                    result = e
                    stats.failed += 1
                stats.items += 1
                stats.seconds = time.perf_counter() - t0
                if bar is not None:
                    bar.update()
                yield i, result
        finally:
            stats.seconds = time.perf_counter() - t0
            if bar is not None:
                bar.close()

    def close(self) -> None:
        self._states = {}
