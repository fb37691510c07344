"""The local Ray cluster of the Ray engine: on loopback, with token authentication, stopped with its driver.

:func:`start_local_cluster` runs ``ray.init`` for a cluster of this machine only:

- its node address is ``127.0.0.1``, so the GCS, the raylet, the agents, the workers and the driver
  listen on loopback only (Ray otherwise replaces 127.0.0.1 by this machine's network address and
  listens on every interface);
- token authentication, as ``ray.init`` starts a local cluster since Ray 2.59 (unless
  ``RAY_AUTH_MODE=disabled`` is set): every request needs Ray's token (``RAY_AUTH_TOKEN``,
  ``RAY_AUTH_TOKEN_PATH`` or ``~/.ray/auth_token``, which Ray creates when there is none);
- a watchdog process (:mod:`.ray_watchdog`, Linux) stops every process of the cluster when the
  driver dies without closing it (``kill -9``); :meth:`LocalCluster.close` stops it with the cluster.
"""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import threading
from contextlib import contextmanager
from pathlib import Path
from typing import Optional

#: Ray's switch between a node on loopback (off: what Ray does on Windows and macOS) and one on a network address
SINGLE_NODE_ENV = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"


@contextmanager
def callers_sigterm_handler():
    """Keep this process's SIGTERM handler across ``ray.init``, which replaces it with its own (an
    exit with Ray's crash report, code 1): e.g. the command line's, which finishes the item being
    written first."""
    saved = signal.getsignal(signal.SIGTERM) if threading.current_thread() is threading.main_thread() else None
    try:
        yield
    finally:
        if saved is not None:
            signal.signal(signal.SIGTERM, saved)


def _children() -> set:
    """This process's child processes (Linux), empty elsewhere."""
    from .ray_watchdog import children

    return set(children(os.getpid()))


class LocalCluster:
    """A local Ray cluster this process started, and the watchdog that stops it if this process dies."""

    def __init__(self, ray, watchdog: Optional[subprocess.Popen]):
        self.ray, self.watchdog = ray, watchdog

    def close(self) -> None:
        """``ray.shutdown()``, then the watchdog stops whatever of the cluster is left and exits."""
        try:
            if self.ray.is_initialized():
                self.ray.shutdown()
        finally:
            if self.watchdog is not None:
                try:
                    self.watchdog.stdin.write(b"close\n")
                    self.watchdog.stdin.close()
                except OSError:  # it is gone already
                    pass
                try:
                    self.watchdog.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    self.watchdog.kill()
                    self.watchdog.wait()
                self.watchdog = None


def _start_watchdog() -> Optional[subprocess.Popen]:
    if not Path(f"/proc/{os.getpid()}/task").is_dir():  # no /proc: no watchdog
        return None
    script = Path(__file__).with_name("ray_watchdog.py")
    return subprocess.Popen(
        [sys.executable, "-I", "-S", str(script), str(os.getpid()), *map(str, _children())],
        stdin=subprocess.PIPE,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,  # a signal to the driver's process group leaves it running, to clean up
    )


def start_local_cluster(ray, num_cpus: int, temp_dir: Optional[str] = None) -> LocalCluster:
    """``ray.init`` of a local cluster of ``num_cpus`` CPUs on loopback, token-authenticated, watched."""
    import ray._private.ray_constants as ray_constants

    saved = os.environ.get(SINGLE_NODE_ENV), ray_constants.ENABLE_RAY_CLUSTER
    os.environ[SINGLE_NODE_ENV] = "0"  # the cluster's processes inherit it
    ray_constants.ENABLE_RAY_CLUSTER = False  # this process read it when Ray was imported
    watchdog = _start_watchdog()
    cluster = LocalCluster(ray, watchdog)
    try:
        ray.init(
            num_cpus=num_cpus,
            include_dashboard=False,
            log_to_driver=False,
            logging_level=logging.ERROR,
            _node_ip_address="127.0.0.1",
            _temp_dir=temp_dir,
        )
    except BaseException:
        cluster.close()
        raise
    finally:
        ray_constants.ENABLE_RAY_CLUSTER = saved[1]
        if saved[0] is None:
            os.environ.pop(SINGLE_NODE_ENV, None)
        else:
            os.environ[SINGLE_NODE_ENV] = saved[0]
    if watchdog is not None:
        try:
            watchdog.stdin.write(b"started\n")
            watchdog.stdin.flush()
        except OSError:
            pass
    return cluster
