"""Hostile runs of ``predict --pairs --engine ray``: kills of the driver and of a worker, signals, two
runs at once, bad ``--ray-address`` and ``--workers``; after each, what is left running and listening.

    python eval/ray_faults.py --work /tmp/rff            # every case; a markdown table on stdout
    python eval/ray_faults.py --work /tmp/rff --cases kill-mid kill-worker

Each case runs ``python -m localscale`` (the code on PYTHONPATH) with its own ``RAY_TMPDIR``, so the
processes of its cluster are those holding a file under that folder open (every Ray process keeps
its logs there), plus the engine's watchdog. Linux only (``/proc``)."""

from __future__ import annotations

import argparse
import ipaddress
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

PAIRS = 30


def processes_under(folder: Path, driver: int = 0) -> dict:
    """``{pid: (name, socket inodes)}`` of the live processes with a file under ``folder`` open, and of
    the watchdog (``ray_watchdog.py``) of the engine's ``driver``."""
    found = {}
    for entry in filter(str.isdigit, os.listdir("/proc")):
        try:
            stat = Path(f"/proc/{entry}/stat").read_bytes()
            if stat.rsplit(b")", 1)[1].split()[0] == b"Z":
                continue
            fds = os.listdir(f"/proc/{entry}/fd")
            args = Path(f"/proc/{entry}/cmdline").read_bytes()
        except OSError:
            continue
        links = []
        for fd in fds:
            try:
                links.append(os.readlink(f"/proc/{entry}/fd/{fd}"))
            except OSError:
                pass
        watchdog = b"ray_watchdog.py" in args and str(driver).encode() in args.split(b"\0")
        if watchdog or any(x.startswith(str(folder)) for x in links):
            name = stat.split(b"(", 1)[1].rsplit(b")", 1)[0].decode()
            found[int(entry)] = (name, {int(x[8:-1]) for x in links if x.startswith("socket:[")})
    return found


def listening() -> dict:
    """``{inode: ip}`` of the listening TCP sockets."""
    out = {}
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        for row in Path(table).read_text().splitlines()[1:]:
            cols = row.split()
            if cols[3] == "0A":
                raw = bytes.fromhex(cols[1].split(":")[0])
                out[int(cols[9])] = ipaddress.ip_address(b"".join(raw[i : i + 4][::-1] for i in range(0, len(raw), 4)))
    return out


def exposed(procs: dict) -> list:
    """The listening addresses of ``procs`` that are not loopback."""
    socks = listening()
    ips = [socks[i] for _, inodes in procs.values() for i in inodes if i in socks]
    loop = lambda ip: ip.is_loopback or (ip.version == 6 and ip.ipv4_mapped is not None and ip.ipv4_mapped.is_loopback)
    return [str(ip) for ip in ips if not loop(ip)]


def make_pairs(folder: Path) -> Path:
    rng = np.random.default_rng(0)
    base = cv2.GaussianBlur((rng.random((480, 640, 3)) * 255).astype(np.uint8), (0, 0), 2)
    names = []
    for i, f in enumerate((1.0, 0.8, 0.6, 0.5, 0.7, 0.9)):
        img = cv2.resize(base, None, fx=f, fy=f)
        names.append(folder / f"im{i}.png")
        cv2.imwrite(str(names[-1]), np.roll(img, 7 * i, axis=1))
    rows = [f"{a}\t{b}" for a in names for b in names if a != b][:PAIRS]
    (folder / "pairs.txt").write_text("\n".join(rows) + "\n")
    return folder / "pairs.txt"


class Case:
    """One driver run: its command, its RAY_TMPDIR, what it printed and what it left."""

    def __init__(self, work: Path, name: str, pairs: Path, extra=(), out_name="out"):
        self.tmp = Path(f"/tmp/rff-{name}")  # short: Ray's socket paths must fit in 107 bytes
        shutil.rmtree(self.tmp, ignore_errors=True)
        self.tmp.mkdir(parents=True)
        self.out = work / name / out_name
        shutil.rmtree(self.out, ignore_errors=True)
        self.out.parent.mkdir(parents=True, exist_ok=True)
        self.cmd = [sys.executable, "-m", "localscale", "predict", "--pairs", str(pairs), "-o", str(self.out)]
        workers = [] if "--workers" in extra else ["--workers", "2"]
        self.cmd += ["--engine", "ray", *workers, *extra]
        env = dict(os.environ, RAY_TMPDIR=str(self.tmp), RAY_USAGE_STATS_ENABLED="0", OMP_NUM_THREADS="1")
        self.err_path = work / name / f"{out_name}.stderr"
        self.proc = subprocess.Popen(
            self.cmd,
            env=env,
            cwd=work,  # not the repository: ``-m localscale`` imports the code on PYTHONPATH
            stdout=subprocess.DEVNULL,
            stderr=open(self.err_path, "w"),
            start_new_session=True,
        )
        self.exposed: list = []

    def outputs(self) -> int:
        return len(list(self.out.glob("*_scale.npy"))) if self.out.exists() else 0

    def wait_for(self, cond, timeout=120.0) -> bool:
        deadline = time.time() + timeout
        while time.time() < deadline and self.proc.poll() is None:
            if cond():
                return True
            time.sleep(0.05)
        return False

    def sample(self) -> None:
        self.exposed = sorted(set(self.exposed) | set(exposed(processes_under(self.tmp, self.proc.pid))))

    def finish(self, timeout=300.0) -> dict:
        try:
            rc = self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            os.killpg(self.proc.pid, signal.SIGKILL)
            rc = self.proc.wait()
        t_exit = time.time()
        left, after_10 = processes_under(self.tmp, self.proc.pid), None
        while left and time.time() - t_exit < 90:  # how long the leftovers stay (Ray's agents: about a minute)
            time.sleep(0.5)
            left = processes_under(self.tmp, self.proc.pid)
            if after_10 is None and time.time() - t_exit >= 10:
                after_10 = left
        gone_after = time.time() - t_exit
        for pid in left:  # still there after 90 s: stop them (this script started them)
            try:
                os.kill(pid, signal.SIGKILL)
            except OSError:
                pass
        err = self.err_path.read_text()
        return {
            "rc": rc,
            "errors": sum(line.startswith("error:") for line in err.splitlines()),
            "tracebacks": err.count("Traceback"),
            "left_10s": sorted(name for name, _ in (after_10 or {}).values()),
            "gone_s": round(gone_after, 1),
            "exposed": self.exposed,
            "outputs": self.outputs(),
            "out_exists": self.out.exists(),
            "last": err.strip().splitlines()[-1][:150] if err.strip() else "",
        }


def worker_pids(tmp: Path) -> list:
    return [pid for pid, (name, _) in processes_under(tmp).items() if name.startswith("ray::_Worker")]


def run_case(name: str, work: Path, pairs: Path) -> list:
    """``[(case, result), ...]`` of the case ``name`` (two for ``two-runs``)."""
    if name == "two-runs":
        a, b = Case(work, name, pairs, out_name="a"), Case(work, name, pairs, out_name="b")
        a.wait_for(lambda: a.outputs() > 0)
        a.sample()
        return [("two-runs (a)", a.finish()), ("two-runs (b)", b.finish())]
    extra = {
        "unreachable": ["--ray-address", f"127.0.0.1:{free_port()}"],
        "garbage-address": ["--ray-address", "nowhere:port"],
        "bad-port": ["--ray-address", "127.0.0.1:99999"],
        "auto-no-cluster": ["--ray-address", "auto"],
        "workers-0": ["--workers", "0"],
        "workers-huge": ["--workers", "10000"],
        "threads-huge": ["--threads-per-worker", "64"],
    }.get(name, [])
    c = Case(work, name, pairs, extra)
    if name == "kill-startup":
        time.sleep(1.5)  # while Python imports localscale and Ray
        c.proc.kill()
    elif name == "kill-init":  # while ray.init starts the cluster
        c.wait_for(lambda: any(n == "gcs_server" for n, _ in processes_under(c.tmp).values()))
        c.proc.kill()
    elif name in ("kill-mid", "killpg-mid", "sigint-mid", "sigterm-mid", "kill-worker", "kill-watchdog"):
        c.wait_for(lambda: c.outputs() >= 3)
        c.sample()
        if name == "kill-mid":
            c.proc.kill()
        elif name == "sigint-mid":
            os.killpg(c.proc.pid, signal.SIGINT)  # Ctrl-C in a terminal: the driver's whole process group
        elif name == "killpg-mid":
            os.killpg(c.proc.pid, signal.SIGKILL)  # the driver's whole process group, as a terminal's job kill
        elif name == "sigterm-mid":
            c.proc.terminate()
        elif name == "kill-watchdog":
            for pid, (_, _) in processes_under(c.tmp, c.proc.pid).items():
                if b"ray_watchdog.py" in Path(f"/proc/{pid}/cmdline").read_bytes():
                    os.kill(pid, signal.SIGKILL)
        else:
            os.kill(worker_pids(c.tmp)[0], signal.SIGKILL)
    elif name == "kill-end":  # every pair written: the driver is writing its summary or stopping the cluster
        c.wait_for(lambda: c.outputs() >= PAIRS, timeout=300)
        c.sample()
        c.proc.kill()
    elif name == "run":
        c.wait_for(lambda: c.outputs() >= 3)
        c.sample()
    return [(name, c.finish())]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


CASES = [
    "run",
    "kill-startup",
    "kill-init",
    "kill-mid",
    "kill-end",
    "killpg-mid",
    "kill-worker",
    "kill-watchdog",
    "sigint-mid",
    "sigterm-mid",
    "two-runs",
    "unreachable",
    "garbage-address",
    "bad-port",
    "auto-no-cluster",
    "workers-0",
    "workers-huge",
    "threads-huge",
]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--cases", nargs="*", default=CASES, choices=CASES)
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    (args.work / "images").mkdir(exist_ok=True)
    pairs = make_pairs(args.work / "images")
    print(
        "| case | rc | error lines | tracebacks | outputs | left 10 s after exit | all gone after (s) | non-loopback listeners | last stderr line |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for name in args.cases:
        for label, r in run_case(name, args.work, pairs):
            left = ", ".join(r["left_10s"]) or "none"
            out = r["outputs"] if r["out_exists"] else "no OUT"
            exposed_ips = ", ".join(r["exposed"]) or "none"
            print(
                f"| {label} | {r['rc']} | {r['errors']} | {r['tracebacks']} | {out} | {left} | {r['gone_s']} | "
                f"{exposed_ips} | {r['last'].replace('|', '/')} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
