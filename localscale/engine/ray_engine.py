"""The Ray engine: a pool of actors, each holding its worker state (e.g. a loaded model) once.

Each actor reserves ``threads_per_worker`` CPUs of the cluster and runs torch with that many
threads (``torch.set_num_threads``, ``OMP_NUM_THREADS``), so ``workers`` actors never use more
cores than the cluster gave them. The driver keeps at most ``in_flight`` calls queued on each
actor, yields every result as it arrives (the caller writes it at once) and resubmits the items
of an actor that died (``kill -9``, out of memory, a lost node) to a fresh actor, up to
``max_retries`` times per item; after that the item fails with :class:`WorkerLostError`. An item
whose work raised a :class:`~localscale.core.errors.LocalScaleError` comes back as that exception,
never retried.

Without ``address`` a local cluster of ``workers x threads`` CPUs (no more than this machine has)
is started on the first ``map`` and stopped by :meth:`RayExecutor.close`: on loopback, with Ray's
token authentication, stopped by a watchdog if the driver dies (:mod:`.ray_local`). With
``address`` the driver joins that cluster (an address that accepts no connection within
``connect_timeout`` seconds is an error). Image paths and weight files must be readable on every
node.
"""

from __future__ import annotations

import logging
import os
import socket
import time
from collections import deque
from typing import Optional

from ..core.errors import LocalScaleError
from .base import RAY_INSTALL_HINT, EngineError, Executor, RunStats, WorkerLostError, progress_bar, state_key
from .ray_local import callers_sigterm_handler, start_local_cluster


def _import_ray():
    try:
        import ray
    except ImportError:
        raise EngineError(f"the ray engine needs Ray, which is not installed: {RAY_INSTALL_HINT}") from None
    return ray


def _host_port(address: str) -> Optional[tuple[str, int]]:
    """``(host, port)`` of ``host:port`` or ``ray://host:port``; None for ``auto``."""
    if address == "auto":
        return None
    rest = address[len("ray://") :] if address.startswith("ray://") else address
    host, sep, port = rest.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise EngineError(
            f"--ray-address {address!r}: expected host:port (e.g. 127.0.0.1:6379), ray://host:port or auto"
        )
    return host.strip("[]"), int(port)


def _machine_cpus() -> int:
    """The CPUs this process may run on."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def _auto_address(temp_dir: Optional[str]) -> Optional[tuple[str, int]]:
    """``(host, port)`` of the cluster ``--ray-address auto`` joins, as Ray finds it (``RAY_ADDRESS``,
    the cluster ``ray start`` recorded, else a GCS running on this machine); None when this Ray
    cannot tell (``ray.init`` decides then)."""
    try:
        from ray._private.services import canonicalize_bootstrap_address
    except ImportError:
        return None
    try:
        found = canonicalize_bootstrap_address("auto", temp_dir)
    except Exception:
        found = None
    if found is None:
        raise EngineError(
            "--ray-address auto: no running Ray cluster found (start one with `ray start --head`, "
            "set RAY_ADDRESS, or drop --ray-address for a local one)"
        )
    return _host_port(found)


def _refuses_without_token(target: tuple[str, int], timeout: float) -> bool:
    """Whether the GCS at ``target`` refuses a request from this process for want of Ray's token
    (``ray.init`` would retry for a while, then fail without saying why)."""
    if os.environ.get("RAY_AUTH_MODE", "").lower() == "token":  # this process sends its token
        return False
    try:
        import grpc
        from ray.core.generated import gcs_service_pb2, gcs_service_pb2_grpc
    except ImportError:
        return False
    host, port = target
    with grpc.insecure_channel(f"[{host}]:{port}" if ":" in host else f"{host}:{port}") as channel:
        try:
            stub = gcs_service_pb2_grpc.NodeInfoGcsServiceStub(channel)
            stub.GetClusterId(gcs_service_pb2.GetClusterIdRequest(), timeout=timeout)
        except grpc.RpcError as e:
            return e.code() == grpc.StatusCode.UNAUTHENTICATED
        except Exception:  # not a GCS there: ray.init says what is wrong
            return False
    return False


def _resolve_refs(item):
    """``item`` with every Ray object reference in it (at the top, or inside tuples, lists and
    dicts) replaced by its value, all fetched in one ``ray.get``."""
    import ray

    refs: list = []

    def find(x):
        if isinstance(x, ray.ObjectRef):
            refs.append(x)
        elif isinstance(x, (list, tuple)):
            for y in x:
                find(y)
        elif isinstance(x, dict):
            for y in x.values():
                find(y)

    find(item)
    if not refs:
        return item
    values = dict(zip(refs, ray.get(refs)))

    def build(x):
        if isinstance(x, ray.ObjectRef):
            return values[x]
        if isinstance(x, list):
            return [build(y) for y in x]
        if isinstance(x, tuple):
            parts = [build(y) for y in x]
            return type(x)(*parts) if hasattr(x, "_fields") else tuple(parts)
        if isinstance(x, dict):
            return {k: build(y) for k, y in x.items()}
        return x

    return build(item)


class _Worker:
    """One actor: builds the worker state once, then runs ``fn(state, item)`` per call."""

    def __init__(self, factory, threads: int):
        for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
            os.environ[var] = str(threads)
        import torch

        torch.set_num_threads(threads)
        self.state, self.error = None, None
        try:
            self.state = factory() if factory is not None else None
        except Exception as e:  # reported by ready(): the driver raises it
            self.error = e

    def ready(self):
        """None, or the exception that building the worker state raised."""
        return self.error

    def info(self) -> dict:
        import ray
        import torch

        return {
            "pid": os.getpid(),
            "node_id": ray.get_runtime_context().get_node_id(),
            "threads": torch.get_num_threads(),
        }

    def _call(self, fn, item):
        if self.error is not None:
            raise RuntimeError(f"the worker state could not be built: {self.error}")
        return fn(self.state, _resolve_refs(item))

    def run(self, fn, item):
        """``(None, result)``, or ``(error, None)`` for a :class:`LocalScaleError`."""
        try:
            return None, self._call(fn, item)
        except LocalScaleError as e:
            return e, None


class RayExecutor(Executor):
    """Runs ``fn(state, item)`` on an actor pool of a local or remote Ray cluster.

    ``workers``: actors (None: one per ``threads_per_worker`` CPUs of the cluster);
    ``threads_per_worker``: CPUs each actor reserves and torch threads it runs;
    ``address``: a running cluster (``host:port``, ``ray://host:port``, ``auto``) or None to start one;
    ``max_retries``: resubmissions of an item after its actor died; ``in_flight``: calls queued per
    actor; ``connect_timeout``: seconds to wait for ``address``; ``ready_timeout``: seconds for the
    actors to start (their state built); ``temp_dir``: Ray's session folder of a started cluster."""

    name = "ray"

    def __init__(
        self,
        workers: Optional[int] = None,
        threads_per_worker: int = 1,
        address: Optional[str] = None,
        max_retries: int = 2,
        in_flight: int = 2,
        connect_timeout: float = 5.0,
        ready_timeout: float = 300.0,
        temp_dir: Optional[str] = None,
    ):
        super().__init__()
        for value, option in (
            (workers, "workers"),
            (threads_per_worker, "threads_per_worker"),
            (in_flight, "in_flight"),
        ):
            if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
                raise EngineError(f"{option} must be a whole number >= 1, got {value!r}")
        if isinstance(max_retries, bool) or not isinstance(max_retries, int) or max_retries < 0:
            raise EngineError(f"max_retries must be a whole number >= 0, got {max_retries!r}")
        if address is not None:
            _host_port(address)  # a malformed address is an error now, before anything starts
        self._ray = _import_ray()
        self._workers, self.threads_per_worker, self.address = workers, threads_per_worker, address
        if address is None and not self._ray.is_initialized():
            need, machine = self._local_cpus(), _machine_cpus()
            if need > machine:  # a local cluster is this machine: more workers than CPUs only thrash
                raise EngineError(
                    f"{need // threads_per_worker} worker(s) x {threads_per_worker} thread(s) need {need} CPUs; "
                    f"this machine has {machine} (for more, join a bigger cluster with --ray-address)"
                )
        self.max_retries, self.in_flight = max_retries, in_flight
        self.connect_timeout, self.ready_timeout, self.temp_dir = connect_timeout, ready_timeout, temp_dir
        self._started = self._owns_session = False
        self._cluster = None  # the local cluster this executor started
        self._actors: list = []
        self._generation: list[int] = []
        self._pool_key = None
        self._factory = None
        self.startup_seconds = 0.0

    @property
    def workers(self) -> int:
        return self._workers or 0

    def _local_cpus(self) -> int:
        """The CPUs of the local cluster: ``workers`` x ``threads_per_worker`` (default: the machine's)."""
        return (self._workers or max(1, _machine_cpus() // self.threads_per_worker)) * self.threads_per_worker

    # ------------------------------------------------------------------ cluster and pool

    def start(self) -> "RayExecutor":
        """Start the local cluster, or join ``address``; idempotent."""
        if self._started:
            return self
        ray = self._ray
        t0 = time.perf_counter()
        os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")  # no usage report (no network)
        if ray.is_initialized():  # the caller's own Ray session
            self._owns_session = False
        elif self.address is None:
            cpus = self._local_cpus()
            try:
                with callers_sigterm_handler():
                    self._cluster = start_local_cluster(ray, cpus, self.temp_dir)
            except (OSError, RuntimeError, ValueError) as e:  # e.g. a temp_dir too long for Ray's sockets
                raise EngineError(f"cannot start a local Ray cluster: {' '.join(str(e).split())[:300]}") from None
            self._owns_session = True
        else:
            self.check_address()
            try:
                with callers_sigterm_handler():
                    ray.init(address=self.address, log_to_driver=False, logging_level=logging.ERROR)
            except (ConnectionError, RuntimeError, ValueError) as e:
                raise EngineError(
                    f"cannot join the Ray cluster at {self.address}: {' '.join(str(e).split())[:300]}"
                ) from None
            self._owns_session = True
        self._started = True
        cpus = int(ray.cluster_resources().get("CPU", 0))
        if self._workers is None:
            self._workers = max(1, cpus // self.threads_per_worker)
        need = self._workers * self.threads_per_worker
        if cpus < need:
            self.close()
            raise EngineError(
                f"the Ray cluster has {cpus} CPU(s); {self._workers} worker(s) x "
                f"{self.threads_per_worker} thread(s) need {need}"
            )
        self.startup_seconds += time.perf_counter() - t0
        return self

    def check_address(self) -> None:
        """Raise :class:`EngineError` (one line) unless ``address`` accepts a connection within
        ``connect_timeout`` seconds (``auto``: unless Ray finds a running cluster); nothing to check
        without ``address``. :func:`get_executor` calls it, so that a command fails before it writes."""
        if self.address is None:
            return
        target = _host_port(self.address)
        if target is None:
            target = _auto_address(self.temp_dir)
            if target is None:
                return
        try:
            socket.create_connection(target, timeout=self.connect_timeout).close()
        except OSError as e:
            reason = "timed out" if isinstance(e, socket.timeout) else (e.strerror or str(e))
            where = self.address if self.address != "auto" else f"{target[0]}:{target[1]} (auto)"
            raise EngineError(
                f"cannot reach the Ray cluster at {where}: {reason} "
                "(start it with `ray start --head`, or drop --ray-address for a local one)"
            ) from None
        explicit = self.address != "auto" and not self.address.startswith("ray://")  # auto: Ray sends a token it has
        if explicit and _refuses_without_token(target, self.connect_timeout):
            raise EngineError(
                f"the Ray cluster at {self.address} requires Ray's token: set RAY_AUTH_MODE=token (the token: "
                "RAY_AUTH_TOKEN, RAY_AUTH_TOKEN_PATH or ~/.ray/auth_token, as on the cluster)"
            )

    def _new_actor(self):
        ray = self._ray
        cls = ray.remote(_Worker).options(
            num_cpus=self.threads_per_worker, max_restarts=0, max_task_retries=0, scheduling_strategy="SPREAD"
        )
        return cls.remote(self._factory, self.threads_per_worker)

    def _pool(self, factory) -> None:
        """Actors holding ``factory``'s state (one factory's pool at a time)."""
        key = state_key(factory)
        if self._actors and self._pool_key == key:
            return
        self._kill_actors()
        ray = self._ray
        t0 = time.perf_counter()
        self._factory, self._pool_key = factory, key
        self._actors = [self._new_actor() for _ in range(self._workers)]
        self._generation = [0] * len(self._actors)
        deadline = time.perf_counter() + self.ready_timeout
        for slot in range(len(self._actors)):
            for attempt in range(self.max_retries + 1):  # an actor whose process died while starting is replaced
                try:
                    error = ray.get(self._actors[slot].ready.remote(), timeout=max(0.0, deadline - time.perf_counter()))
                    break
                except ray.exceptions.GetTimeoutError:
                    self._kill_actors()
                    raise EngineError(
                        f"the {self._workers} Ray worker(s) did not start within {self.ready_timeout:g} "
                        "s (are the cluster's CPUs in use by others?)"
                    ) from None
                except ray.exceptions.RayActorError as e:
                    if attempt == self.max_retries:
                        self._kill_actors()
                        raise EngineError(
                            f"a Ray worker died while starting, {attempt + 1} time(s): {' '.join(str(e).split())[:200]}"
                        ) from None
                    self._replace(slot)
            if error is not None:
                self._kill_actors()
                raise error
        self.startup_seconds += time.perf_counter() - t0

    def _replace(self, slot: int) -> None:
        try:
            self._ray.kill(self._actors[slot], no_restart=True)
        except Exception:  # already gone
            pass
        self._actors[slot] = self._new_actor()
        self._generation[slot] += 1

    def _kill_actors(self) -> None:
        for a in self._actors:
            try:
                self._ray.kill(a, no_restart=True)
            except Exception:
                pass
        self._actors, self._generation, self._pool_key, self._factory = [], [], None, None

    def worker_info(self, state=None) -> list[dict]:
        """``{"pid", "node_id", "threads"}`` of each actor of ``state``'s pool (started if needed)."""
        self.start()
        self._pool(state)
        return self._ray.get([a.info.remote() for a in self._actors])

    def close(self) -> None:
        if not self._started:
            return
        self._kill_actors()
        if self._cluster is not None:
            self._cluster.close()
        elif self._owns_session and self._ray.is_initialized():
            self._ray.shutdown()
        self._started = self._owns_session = False
        self._cluster = None

    # ------------------------------------------------------------------ map

    def map(self, fn, items, *, state=None, keep=False, progress=None, unit="item"):
        ray = self._ray
        items = list(items)
        startup = self.startup_seconds
        self.start()
        self._pool(state)
        stats = RunStats(
            self.name, self._workers, self.threads_per_worker, startup_seconds=self.startup_seconds - startup
        )
        self.last_run = stats
        calls = _MapCalls(self, fn, items, keep, stats)
        bar = progress_bar(len(items), progress, unit)
        t0 = time.perf_counter()
        try:
            while calls.pending or calls.running:
                calls.submit_pending()
                ready, _ = ray.wait(list(calls.running), num_returns=1)
                for ref in ready:
                    finished = calls.finish(ref)
                    if finished is None:  # queued again
                        continue
                    i, error, value = finished
                    stats.items += 1
                    stats.failed += error is not None
                    stats.seconds = time.perf_counter() - t0
                    if bar is not None:
                        bar.update()
                    yield i, (error if error is not None else value)
        finally:
            stats.seconds = time.perf_counter() - t0
            if bar is not None:
                bar.close()
            calls.cancel_running()


class _MapCalls:
    """The calls of one :meth:`RayExecutor.map`: the items waiting, the calls out on each actor slot,
    and what a finished call gives (its result, or its item queued again after its actor died)."""

    def __init__(self, executor: RayExecutor, fn, items: list, keep: bool, stats: RunStats):
        self.executor, self.fn, self.items, self.keep, self.stats = executor, fn, items, keep, stats
        slots = len(executor._actors)
        self.pending = deque(range(len(items)))
        self.attempts = [0] * len(items)
        self.running: dict = {}  # status reference -> (index, slot, generation)
        self.company: dict = {}  # (slot, generation) of a dead actor -> calls it had out
        self.isolated: set = set()  # items that died in company: next time they run alone
        self.alone: list = [None] * slots  # slot -> the isolated item it runs, if any
        self.values: dict = {}  # keep: index -> value reference
        self.load = [0] * slots  # calls out per actor slot

    def submit(self, i: int, slot: int) -> None:
        actor = self.executor._actors[slot]
        if self.keep:  # two returns: the status comes to the driver, the value stays in the object store
            status, self.values[i] = actor.run.options(num_returns=2).remote(self.fn, self.items[i])
        else:
            status = actor.run.remote(self.fn, self.items[i])
        self.running[status] = (i, slot, self.executor._generation[slot])
        self.load[slot] += 1

    def submit_pending(self) -> None:
        """Queue waiting items on every actor, up to ``in_flight`` each; an isolated item waits for
        an idle actor and runs there alone."""
        for slot in range(len(self.load)):
            while self.pending and self.load[slot] < self.executor.in_flight and self.alone[slot] is None:
                if self.pending[0] in self.isolated:
                    if self.load[slot]:
                        break
                    self.alone[slot] = self.pending[0]
                self.submit(self.pending.popleft(), slot)

    def finish(self, ref):
        """``(index, error or None, value)`` of the finished call ``ref``, or None when its actor died
        and its item is queued again. A bug in the work function (not a :class:`LocalScaleError`)
        is raised: it ends the run."""
        ray = self.executor._ray
        i, slot, generation = self.running.pop(ref)
        self.load[slot] -= 1
        if self.alone[slot] == i:
            self.alone[slot] = None
        try:
            got = ray.get(ref)
            error, value = (got, self.values.pop(i)) if self.keep else got
        except ray.exceptions.RayActorError:  # the actor died (kill -9, out of memory, lost node)
            self.values.pop(i, None)
            error = self._actor_died(i, slot, generation)
            if error is None:
                return None
            value = None
        except ray.exceptions.RayTaskError as e:  # a bug in the work function: end the run
            raise e.as_instanceof_cause() from None
        return i, error, value

    def _actor_died(self, i: int, slot: int, generation: int) -> Optional[WorkerLostError]:
        """Replace the dead actor (once per death) and queue item ``i`` again; the error of an item
        that used up its retries instead."""
        stats = self.stats
        if (slot, generation) not in self.company:  # first news of this death: replace the actor once
            self.company[slot, generation] = 1 + sum(
                (sl, g) == (slot, generation) for _, sl, g in self.running.values()
            )
            self.executor._replace(slot)
        if self.company[slot, generation] > 1:
            # which of its calls killed it is unknown (a finished call's reply can die with
            # the process too): each runs again alone, without using up a retry
            self.isolated.add(i)
            stats.retried += 1
            self.pending.appendleft(i)
            return None
        self.attempts[i] += 1
        if self.attempts[i] <= self.executor.max_retries:
            stats.retried += 1
            self.pending.appendleft(i)
            return None
        return WorkerLostError(f"its worker process died {self.attempts[i]} time(s) while running it")

    def cancel_running(self) -> None:
        """Drop the calls still queued (the caller stopped early)."""
        for ref in self.running:
            try:
                self.executor._ray.cancel(ref)
            except Exception:
                pass
