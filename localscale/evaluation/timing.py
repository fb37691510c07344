"""Timing helpers of the speed benchmarks: medians of wall and CPU time, timed in turn where a
drifting machine would skew ratios, and of subprocesses."""

from __future__ import annotations

import resource
import subprocess
import time

import numpy as np


def timeit(fn, repeat: int, warmup: int = 1, setup=None) -> dict:
    """Median / p90 wall ms and median CPU ms (this process, all threads) of ``fn()``, or of
    ``fn(setup())`` with ``setup`` run untimed before each call."""
    for _ in range(warmup):
        fn() if setup is None else fn(setup())
    wall, cpu = [], []
    for _ in range(repeat):
        arg = None if setup is None else setup()
        t, c = time.perf_counter(), time.process_time()
        fn() if setup is None else fn(arg)
        wall.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    wall, cpu = np.array(wall) * 1000, np.array(cpu) * 1000
    return {"ms": float(np.median(wall)), "ms_p90": float(np.percentile(wall, 90)), "cpu_ms": float(np.median(cpu))}


def interleaved(fns: dict, repeat: int) -> dict:
    """Median wall and CPU ms of each of ``fns`` (name -> callable), timed in turn within each of
    ``repeat`` rounds (after one warm-up round), so that a machine whose speed drifts (a shared
    VM) slows all of them alike and their ratios hold."""
    for fn in fns.values():
        fn()
    wall = {k: [] for k in fns}
    cpu = {k: [] for k in fns}
    for _ in range(repeat):
        for k, fn in fns.items():
            t, c = time.perf_counter(), time.process_time()
            fn()
            wall[k].append((time.perf_counter() - t) * 1000)
            cpu[k].append((time.process_time() - c) * 1000)
    return {k: {"ms": float(np.median(wall[k])), "cpu_ms": float(np.median(cpu[k]))} for k in fns}


def subprocess_ms(cmd: list, repeat: int, cwd: str, env=None) -> dict:
    """Median wall ms and median child CPU ms of running ``cmd`` ``repeat`` times."""
    wall, cpu = [], []
    for _ in range(repeat):
        r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        t = time.perf_counter()
        subprocess.run(cmd, cwd=cwd, env=env, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        wall.append(time.perf_counter() - t)
        r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu.append(r1.ru_utime + r1.ru_stime - r0.ru_utime - r0.ru_stime)
    return {
        "ms": float(np.median(wall) * 1000),
        "ms_p90": float(np.percentile(wall, 90) * 1000),
        "cpu_ms": float(np.median(cpu) * 1000),
    }
