"""Stops what is left of a local Ray cluster when the process that started it dies.

``python -I -S ray_watchdog.py DRIVER_PID [PID ...]``, with a pipe from the driver on standard input
(Linux: it reads ``/proc``; the standard library only, nothing of localscale, torch or Ray). The
PIDs are the driver's children from before its cluster started. Every 0.1 s the watchdog notes
(pid and start time) each process that descends from the driver and not from those children nor
from itself. Once the driver writes ``started`` (its cluster is up) it notes, every 0.5 s, only
the descendants of the processes already noted (the workers the raylet starts later): nothing the
driver starts afterwards is taken for part of its cluster. When the pipe closes, or the driver is
gone, every noted process still alive gets SIGTERM and, 2 s later, SIGKILL; then the watchdog
exits. The driver writes ``close`` after stopping its cluster itself: the watchdog then stops what
is left the same way, at once.

Ray's own fate-sharing stops the GCS and the raylet with their driver, but its dashboard and
runtime-env agents outlive them by a minute (they wait on the dead GCS), one of them with a port
open, and they ignore SIGTERM meanwhile.
"""

import os
import select
import signal
import sys
import time

POLL_S = 0.1  # while the cluster starts
POLL_S_STARTED = 0.5
GRACE_S = 2.0


def start_time(pid: int):
    """The start time of process ``pid`` (clock ticks since boot), or None when it is gone or a zombie."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            fields = f.read().rsplit(b")", 1)[1].split()
    except (OSError, IndexError):
        return None
    return None if fields[0] == b"Z" else int(fields[19])


def children(pid: int) -> list:
    """The child processes of ``pid`` (of every thread of it)."""
    out = []
    try:
        tasks = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return out
    for tid in tasks:
        try:
            with open(f"/proc/{pid}/task/{tid}/children") as f:
                out += [int(c) for c in f.read().split()]
        except OSError:
            pass
    return out


def descendants(roots, skip) -> dict:
    """``{pid: start time}`` of the processes below ``roots`` (not the roots), except the subtrees of ``skip``."""
    found, todo = {}, list(roots)
    while todo:
        for child in children(todo.pop()):
            if child in skip or child in found:
                continue
            t = start_time(child)
            if t is not None:
                found[child] = t
                todo.append(child)
    return found


def alive(noted: dict) -> list:
    """The noted processes that still run (same pid and start time)."""
    return [pid for pid, t in noted.items() if start_time(pid) == t]


def stop(noted: dict) -> None:
    """SIGTERM to every noted process still alive, SIGKILL to those still alive ``GRACE_S`` later."""
    for sig in (signal.SIGTERM, signal.SIGKILL):
        for pid in alive(noted):
            try:
                os.kill(pid, sig)
            except OSError:
                pass
        deadline = time.monotonic() + GRACE_S
        while alive(noted) and time.monotonic() < deadline:
            time.sleep(0.05)


def watch(driver: int, before: set) -> None:
    born = start_time(driver)
    skip = before | {os.getpid()}
    noted: dict = {}
    started = False
    stdin = sys.stdin.fileno()
    while born is not None and start_time(driver) == born:
        noted.update(descendants(alive(noted) if started else [driver], skip))
        if select.select([stdin], [], [], POLL_S_STARTED if started else POLL_S)[0]:
            data = os.read(stdin, 4096)
            if not data or b"close" in data:  # the pipe closed (the driver died), or the driver stopped its cluster
                break
            started = started or b"started" in data
    stop(noted)


if __name__ == "__main__":
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):  # the driver's Ctrl-C or hang-up: outlive it, clean up
        signal.signal(sig, signal.SIG_IGN)
    watch(int(sys.argv[1]), {int(p) for p in sys.argv[2:]})
