"""Choosing the executor of ``--engine local|ray``: :func:`get_executor`."""

from __future__ import annotations

from typing import Optional

from .base import ENGINES, EngineError, Executor, LocalExecutor


def _check_count(value, option: str) -> Optional[int]:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int):
        raise EngineError(f"{option} must be a whole number >= 1, got {value!r}")
    if value < 1:
        raise EngineError(f"{option} must be >= 1, got {value}")
    return value


def get_executor(
    engine="local",
    workers: Optional[int] = None,
    threads_per_worker: Optional[int] = None,
    address: Optional[str] = None,
    **ray_options,
) -> Executor:
    """The executor of ``--engine local|ray --workers N --threads-per-worker T --ray-address ADDR``.

    ``engine`` may also be an :class:`Executor` (returned as it is). ``local`` runs in this process
    (one worker). ``ray`` without ``address`` starts a local Ray cluster of ``workers`` x
    ``threads_per_worker`` CPUs (stopped by :meth:`Executor.close`); with ``address``
    (``host:port``, ``ray://host:port`` or ``auto``) it joins that cluster. ``workers=None``: one
    worker per ``threads_per_worker`` CPUs of the machine (or of the cluster). Bad options, and an
    ``address`` that accepts no connection, raise :class:`EngineError` (one line); nothing is
    started before the first ``map``."""
    if isinstance(engine, Executor):
        if workers is not None or threads_per_worker is not None or address is not None:
            raise EngineError("give the engine's options to the executor itself, not with an Executor object")
        return engine
    if engine not in ENGINES:
        raise EngineError(f"unknown engine {engine!r}: choose one of {', '.join(ENGINES)}")
    workers = _check_count(workers, "--workers")
    threads_per_worker = _check_count(threads_per_worker, "--threads-per-worker")
    if engine == "local":
        if workers not in (None, 1):
            raise EngineError(
                f"--workers {workers}: the local engine runs one worker in this process; use --engine ray for more"
            )
        if address is not None:
            raise EngineError("--ray-address needs --engine ray")
        if ray_options:
            raise EngineError(f"options of the ray engine given to the local one: {', '.join(sorted(ray_options))}")
        return LocalExecutor(threads_per_worker)
    from .ray_engine import RayExecutor  # Ray is imported only when it is asked for

    executor = RayExecutor(workers, threads_per_worker or 1, address, **ray_options)
    executor.check_address()
    return executor
