"""Executors: the local engine and the Ray engine give the same results; Ray survives a worker
killed mid-run, reports bad input per item, resumes after its driver was killed and spreads work
over two nodes of a cluster. Serial and self-contained: every Ray cluster a test starts is
stopped by that test (or its fixture), and no test uses a cluster it did not start."""

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from localscale.core.errors import CheckpointError, ImageError, LocalScaleError
from localscale.engine import (
    EngineError,
    LocalExecutor,
    ModelFactory,
    WorkerLostError,
    get_executor,
    predict_pairs_with,
)
from localscale.engine.pairs import PairStats

try:
    import ray
except ImportError:  # the local engine's tests still run
    ray = None

needs_ray = pytest.mark.skipif(ray is None, reason="ray is not installed (pip install 'localscale[ray]')")
PYTHON = sys.executable
CPUS = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
needs_two_cpus = pytest.mark.skipif(CPUS < 2, reason="a local Ray cluster of 2 workers needs 2 CPUs")
needs_proc = pytest.mark.skipif(not os.path.isdir("/proc/self/fd"), reason="lists processes and sockets in /proc")
RAY_CLI = Path(sys.executable).with_name("ray")
LOOPBACK = ("127.0.0.1", "::1", "localhost")


def own_address(host) -> bool:
    """``host`` is loopback or an IP address of this machine (a socket can be bound to it): traffic to it
    never leaves the machine."""
    if host in LOOPBACK:
        return True
    try:
        with socket.socket(socket.AF_INET6 if ":" in str(host) else socket.AF_INET) as s:
            s.bind((host, 0))
        return True
    except (OSError, TypeError, ValueError):
        return False


@pytest.fixture(autouse=True)
def no_network(monkeypatch):
    """Like the suite's guard, but Ray's driver may talk to clusters on this machine (its own addresses)."""
    real_connect, real_getaddrinfo = socket.socket.connect, socket.getaddrinfo

    def connect(self, address):
        if self.family in (socket.AF_INET, socket.AF_INET6) and not own_address(address[0]):
            raise AssertionError(f"a test tried to connect to {address!r}")
        return real_connect(self, address)

    def getaddrinfo(host, *args, **kwargs):
        if host not in (socket.gethostname(), None) and not own_address(host):
            raise AssertionError(f"a test tried to resolve {host!r}")
        return real_getaddrinfo(host, *args, **kwargs)

    monkeypatch.setattr(socket.socket, "connect", connect)
    monkeypatch.setattr(socket, "getaddrinfo", getaddrinfo)


@pytest.fixture
def short_dir():
    """A folder with a short path: Ray's socket paths under it must fit in 107 bytes."""
    import shutil
    import tempfile

    d = Path(tempfile.mkdtemp(prefix="lsray-", dir="/tmp"))
    yield d
    shutil.rmtree(d, ignore_errors=True)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# ---------------------------------------------------------------- what a cluster leaves on this machine (/proc)


def cluster_processes(folder, also=()) -> dict:
    """``{pid: socket inodes}`` of the live processes holding a file under ``folder`` open (every process
    of a Ray cluster keeps its log files in its session folder, under ``temp_dir``, open), and of ``also``."""
    folder, found = str(folder), {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat", "rb") as f:
                if f.read().rsplit(b")", 1)[1].split()[0] == b"Z":
                    continue
            fds = os.listdir(f"/proc/{entry}/fd")
        except OSError:  # gone meanwhile
            continue
        links = []
        for fd in fds:
            try:
                links.append(os.readlink(f"/proc/{entry}/fd/{fd}"))
            except OSError:  # closed meanwhile
                pass
        if int(entry) in also or any(link.startswith(folder) for link in links):
            found[int(entry)] = {int(x[8:-1]) for x in links if x.startswith("socket:[")}
    return found


def wait_until_gone(folder, seconds: float) -> dict:
    """:func:`cluster_processes` of ``folder`` but this one, once none is left or when ``seconds`` have passed."""
    deadline = time.time() + seconds
    while True:
        left = {pid: s for pid, s in cluster_processes(folder).items() if pid != os.getpid()}
        if not left or time.time() > deadline:
            return left
        time.sleep(0.2)


def watchdogs_of(driver: int) -> list:
    """The live watchdog processes of ``driver`` (the local cluster's, see ``ray_local``)."""
    found = []
    for entry in filter(str.isdigit, os.listdir("/proc")):
        try:
            args = Path(f"/proc/{entry}/cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if any(a.endswith(b"ray_watchdog.py") for a in args) and str(driver).encode() in args:
            found.append(int(entry))
    return found


def listening_sockets() -> dict:
    """``{inode: ip_address}`` of this machine's listening TCP sockets (``/proc/net/tcp``, ``tcp6``)."""
    import ipaddress

    found = {}
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        with open(table) as f:
            for row in f.read().splitlines()[1:]:
                cols = row.split()
                if cols[3] != "0A":  # not LISTEN
                    continue
                raw = bytes.fromhex(cols[1].split(":")[0])
                raw = b"".join(raw[i : i + 4][::-1] for i in range(0, len(raw), 4))  # per 32-bit word, host order
                found[int(cols[9])] = ipaddress.ip_address(raw)
    return found


def is_loopback(ip) -> bool:
    return ip.is_loopback or (ip.version == 6 and ip.ipv4_mapped is not None and ip.ipv4_mapped.is_loopback)


# ---------------------------------------------------------------- work functions (pickled by value for Ray)


def double(state, x):
    return 2 * x


def slow_double(state, x):
    time.sleep(0.25)
    return 2 * x


def reject_three(state, item):
    """Fails item 3 as bad input; notes every attempt in a file, so retries can be counted."""
    x, log = item
    with open(log, "a") as f:
        f.write(f"{x}\n")
    if x == 3:
        raise ImageError(f"item {x} is bad")
    return 2 * x


def crash_on_three(state, x):
    if x == 3:
        os._exit(1)  # the worker process dies, as under kill -9 or the OOM killer
    return 2 * x


def buggy(state, x):
    return 1 // (x - 2)


def add_state(state, x):
    return state + x


class Counter:
    """A state factory that counts how often it was called."""

    calls = 0

    def __call__(self):
        Counter.calls += 1
        return 100


# ---------------------------------------------------------------- options and the local engine


def test_bad_options_are_one_line_errors(monkeypatch):
    for kwargs, text in [
        ({"engine": "spark"}, "unknown engine 'spark'"),
        ({"engine": "ray", "workers": 0}, "--workers must be >= 1"),
        ({"engine": "ray", "workers": "2"}, "--workers must be a whole number"),
        ({"engine": "ray", "threads_per_worker": 0}, "--threads-per-worker must be >= 1"),
        ({"engine": "local", "workers": 2}, "the local engine runs one worker"),
        ({"engine": "local", "address": "127.0.0.1:6379"}, "--ray-address needs --engine ray"),
        ({"engine": LocalExecutor(), "workers": 2}, "give the engine's options to the executor"),
    ]:
        with pytest.raises(EngineError, match=text) as e:
            get_executor(**kwargs)
        assert "\n" not in str(e.value) and isinstance(e.value, LocalScaleError)
    if ray is not None:
        with pytest.raises(EngineError, match="expected host:port"):
            get_executor("ray", address="nowhere")
        # a local cluster is this machine: no more CPUs than it has
        with pytest.raises(
            EngineError, match=rf"{CPUS} worker.s. x 2 thread.s. need {2 * CPUS} CPUs; this machine has {CPUS}\b"
        ):
            get_executor("ray", workers=CPUS, threads_per_worker=2)
        with pytest.raises(EngineError, match=rf"need {CPUS + 1} CPUs"):
            get_executor("ray", threads_per_worker=CPUS + 1)
    monkeypatch.setitem(sys.modules, "ray", None)  # Ray not installed
    with pytest.raises(EngineError, match=r"pip install 'localscale\[ray\]'"):
        get_executor("ray", workers=2)


def test_local_executor_builds_the_state_once_and_reports_bad_items():
    Counter.calls = 0
    ex = get_executor("local")
    assert isinstance(ex, LocalExecutor) and get_executor(ex) is ex
    with ex:
        assert list(ex.map(add_state, [1, 2, 3], state=Counter())) == [(0, 101), (1, 102), (2, 103)]
        assert list(ex.map(add_state, [4], state=Counter())) == [(0, 104)]  # equal factory: same state
        assert Counter.calls == 2  # Counter() instances are not equal: one build per map
        out = dict(ex.map(reject_three, [(x, os.devnull) for x in range(5)]))
    assert [out[i] for i in (0, 1, 2, 4)] == [0, 2, 4, 8]
    assert isinstance(out[3], ImageError) and str(out[3]) == "item 3 is bad"
    assert ex.last_run.failed == 1 and ex.last_run.items == 5
    with pytest.raises(ZeroDivisionError):  # a bug is not bad input: it ends the run
        list(LocalExecutor().map(buggy, range(5)))


class KillOnce:
    """The matching step's pair work, except that the first call anywhere kills its worker (``kill -9``)."""

    def __init__(self, marker: str, work):
        self.marker, self.work = marker, work

    def __call__(self, runner, pair):
        if not os.path.exists(self.marker):
            Path(self.marker).write_text(str(os.getpid()))
            os.kill(os.getpid(), signal.SIGKILL)
        return self.work(runner, pair)


# ---------------------------------------------------------------- Ray: one local cluster for the tests below


@pytest.fixture(scope="module")
def pickle_tests_by_value():
    """Workers cannot import this test module: ship its work functions by value."""
    import ray.cloudpickle

    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])
    yield
    ray.cloudpickle.unregister_pickle_by_value(sys.modules[__name__])


@pytest.fixture(scope="class")
def ray_executor(pickle_tests_by_value):
    ex = get_executor("ray", workers=2, threads_per_worker=1, max_retries=1)
    yield ex
    ex.close()
    assert not ray.is_initialized()


@pytest.fixture(scope="module")
def tiny_pairs(tmp_path_factory):
    from skimage import data

    d = tmp_path_factory.mktemp("engine_images")
    paths = []
    for name, img in [("astronaut", data.astronaut()), ("coffee", data.coffee()), ("chelsea", data.chelsea())]:
        p = d / f"{name}.png"
        cv2.imwrite(str(p), cv2.resize(img, (96, 72), interpolation=cv2.INTER_AREA)[..., ::-1])
        paths.append(p)
    (d / "broken.png").write_bytes(b"not an image")
    a, b, c = paths
    return [(a, b), (b, c), (a, d / "broken.png"), (c, a), (b, a), (a, c)]


@needs_ray
@needs_two_cpus
@pytest.mark.usefixtures("pickle_tests_by_value")
class TestRayLocalCluster:
    def test_unreachable_address_fails_fast(self):
        t0 = time.perf_counter()
        with pytest.raises(EngineError, match=r"cannot reach the Ray cluster at 127\.0\.0\.1:\d+: "):
            get_executor("ray", workers=1, address=f"127.0.0.1:{free_port()}").start()
        assert time.perf_counter() - t0 < 5
        assert not ray.is_initialized()

    def test_pairs_equal_local_engine_and_feature_cache(self, ray_executor, tiny_pairs, tmp_path):
        from localscale import LocalScaleNet
        from localscale.cache import FeatureCache, predict_pairs
        from localscale.maps.files import write_scale_map

        with get_executor("local") as ex:
            local = dict(predict_pairs_with(ex, tiny_pairs, chunk_pairs=4))
        stats = PairStats()
        got = list(predict_pairs_with(ray_executor, tiny_pairs, ModelFactory(), chunk_pairs=4, stats=stats))
        assert sorted(i for i, _ in got) == list(range(len(tiny_pairs)))  # each pair once
        remote = dict(got)
        model = LocalScaleNet.from_pretrained()
        reference = [p for _, p in predict_pairs(model, tiny_pairs, FeatureCache(model))]  # the CLI's loop today
        for i in range(len(tiny_pairs)):
            if i == 2:  # the broken image: the same error from every path
                assert all(isinstance(r, ImageError) for r in (local[i], remote[i], reference[i]))
                assert str(local[i]) == str(remote[i]) == str(reference[i])
                continue
            for name in ("scale", "confidence", "visible", "reliability"):
                np.testing.assert_allclose(remote[i].full(name), local[i].full(name), rtol=0, atol=1e-5)
                np.testing.assert_allclose(remote[i].full(name), reference[i].full(name), rtol=0, atol=1e-5)
            for pred, folder in ((local[i], tmp_path / "local"), (remote[i], tmp_path / "ray")):
                write_scale_map(pred, folder, f"pair{i}")  # the driver writes, as in the local engine
            for f in (tmp_path / "local").glob(f"pair{i}_*.npy"):
                np.testing.assert_allclose(np.load(tmp_path / "ray" / f.name), np.load(f), rtol=0, atol=1e-5)
        assert (stats.pairs, stats.failed, stats.encoded, stats.workers) == (6, 1, 3, 2)
        assert "pairs/s on 2 worker(s) (ray" in stats.summary()

    def test_worker_threads_and_shared_results(self, ray_executor):
        info = ray_executor.worker_info()
        assert len(info) == 2 and all(w["threads"] == 1 for w in info) and len({w["pid"] for w in info}) == 2
        handles = dict(ray_executor.map(double, range(4), keep=True))  # values stay in the object store
        assert all(isinstance(h, ray.ObjectRef) for h in handles.values())
        items = [(handles[i], [handles[3 - i]]) for i in range(4)]  # refs inside tuples and lists
        out = dict(ray_executor.map(lambda s, it: it[0] + it[1][0], items))
        assert out == {i: 6 for i in range(4)}

    def test_worker_killed_mid_run(self, ray_executor):
        pids = [w["pid"] for w in ray_executor.worker_info()]
        seen = []
        for i, result in ray_executor.map(slow_double, range(12), progress="items"):
            seen.append((i, result))
            if len(seen) == 2:
                os.kill(pids[0], signal.SIGKILL)
        assert sorted(seen) == [(i, 2 * i) for i in range(12)]  # nothing lost, nothing twice
        assert ray_executor.last_run.retried >= 1 and ray_executor.last_run.failed == 0
        new_pids = {w["pid"] for w in ray_executor.worker_info()}
        assert pids[0] not in new_pids and len(new_pids) == 2  # a fresh actor took its place

    def test_item_that_kills_every_worker_fails_after_retries(self, ray_executor):
        out = dict(ray_executor.map(crash_on_three, range(6)))
        assert isinstance(out.pop(3), WorkerLostError)  # max_retries=1: two attempts, then reported
        assert out == {i: 2 * i for i in (0, 1, 2, 4, 5)}
        assert ray_executor.last_run.retried >= 1 and ray_executor.last_run.failed == 1

    def test_bad_input_is_reported_once_not_retried(self, ray_executor, tmp_path):
        log = tmp_path / "attempts.txt"
        out = dict(ray_executor.map(reject_three, [(x, str(log)) for x in range(6)]))
        assert isinstance(out[3], ImageError) and str(out[3]) == "item 3 is bad"
        assert [out[i] for i in (0, 1, 2, 4, 5)] == [0, 2, 4, 8, 10]
        assert sorted(int(x) for x in log.read_text().split()) == list(range(6))  # one attempt each
        with pytest.raises(ZeroDivisionError):  # a bug ends the run, in the driver
            list(ray_executor.map(buggy, range(5)))

    def test_reconstruct_equals_local_engine_with_a_worker_killed(self, ray_executor, tmp_path, monkeypatch):
        pytest.importorskip("pycolmap")
        h5py = pytest.importorskip("h5py")
        import localscale.sfm.match as sfm_match
        from localscale.sfm import reconstruct
        from localscale.sfm.synthetic import write_scene

        write_scene(tmp_path / "scene", num_views=5, shape=(240, 320), seed=0)
        opts = dict(matcher="sift", num_keypoints=1024, num_threads=1, show_progress=False, plot=False)
        local = reconstruct(tmp_path / "scene", tmp_path / "local", **opts)
        marker = tmp_path / "killed"
        work = sfm_match.MatchPair()
        monkeypatch.setattr(sfm_match, "MatchPair", lambda: KillOnce(str(marker), work))
        remote = reconstruct(tmp_path / "scene", tmp_path / "ray", engine=ray_executor, **opts)
        assert marker.exists() and ray_executor.last_run.retried >= 1  # a worker died mid-matching
        assert remote["engine"] == {"name": "ray", "workers": 2} and local["engine"]["name"] == "local"
        assert remote["registered"] == local["registered"] == 5
        for name in ("features.h5", "matches.h5", "keypoints.h5"):
            with h5py.File(tmp_path / "local" / name) as a, h5py.File(tmp_path / "ray" / name) as b:
                keys_a, keys_b = [], []
                a.visit(lambda k: keys_a.append(k) if isinstance(a[k], h5py.Dataset) else None)
                b.visit(lambda k: keys_b.append(k) if isinstance(b[k], h5py.Dataset) else None)
                assert sorted(keys_a) == sorted(keys_b) and keys_a
                for k in keys_a:
                    x, y = a[k][()], b[k][()]
                    if np.issubdtype(x.dtype, np.floating):
                        np.testing.assert_allclose(y, x, rtol=0, atol=1e-5)
                    else:
                        np.testing.assert_array_equal(y, x)  # matches and indices identical

    def test_eval_hpatches_equals_local_engine(self, ray_executor, photos, tmp_path):
        import torch

        from localscale.evaluation import evaluate, load_hpatches, make_pairs, make_sequences
        from localscale.models import LocalScaleNet

        make_sequences([photos["astronaut"], photos["coffee"]], tmp_path, num_images=3, size=128, seed=0)
        broken = tmp_path / "s_001" / "2.png"
        broken.write_bytes(broken.read_bytes()[:300])  # truncated after its header: skipped on both engines
        pairs = make_pairs(load_hpatches(tmp_path))
        torch.manual_seed(0)
        local = LocalScaleNet(width=0.125, image_size=64).eval()
        opts = dict(descriptor="sift", num_features=150, local_model=local, progress=False)
        here = evaluate(pairs, ["none", "local", "gt"], "hardnet", **opts)
        there = evaluate(pairs, ["none", "local", "gt"], "hardnet", executor=ray_executor, **opts)
        assert here["skipped"] == there["skipped"] and len(here["skipped"]) == 1
        timing = ("seconds", "scale_seconds")
        strip = lambda recs: [{k: v for k, v in r.items() if k not in timing} for r in recs]  # noqa: E731
        assert strip(there["records"]) == strip(here["records"]) and len(here["records"]) == 9
        assert there["summary"]["all"]["gt"]["mma"] == here["summary"]["all"]["gt"]["mma"]

    def test_bad_weights_raise_in_the_driver(self, ray_executor, tmp_path):
        bad = tmp_path / "weights.pt"
        bad.write_bytes(b"truncated")
        with pytest.raises(CheckpointError):
            list(ray_executor.map(double, [1], state=ModelFactory("local", str(bad))))
        assert dict(ray_executor.map(double, [1, 2])) == {0: 2, 1: 4}  # the executor still works


@needs_ray
@needs_proc
def test_local_cluster_listens_on_loopback_only_and_needs_a_token(short_dir, monkeypatch):
    """Every listening socket of the local cluster (GCS, raylet, agents, workers, driver) is bound to
    loopback, and its GCS refuses a request without Ray's token (a driver without it is told so when
    it joins). The driver's SIGTERM handler (the command line's finishes the pair being written) is
    still its own once the cluster is up."""
    import grpc
    from ray.core.generated import gcs_service_pb2, gcs_service_pb2_grpc

    monkeypatch.delenv("RAY_AUTH_MODE", raising=False)  # Ray's default
    assert not ray.is_initialized()
    on_sigterm = lambda signum, frame: None  # noqa: E731
    previous = signal.signal(signal.SIGTERM, on_sigterm)
    try:
        with get_executor("ray", workers=1, threads_per_worker=1, temp_dir=str(short_dir)) as ex:
            ex.worker_info()  # the cluster and its worker are up
            assert signal.getsignal(signal.SIGTERM) is on_sigterm
            processes = cluster_processes(short_dir, also=(os.getpid(),))
            listening = listening_sockets()
            bound = {pid: [listening[i] for i in inodes if i in listening] for pid, inodes in processes.items()}
            assert os.getpid() in processes and len(processes) >= 5  # the driver, GCS, raylet, agents, worker
            assert sum(map(len, bound.values())) >= 4, bound  # GCS, raylet, worker, driver at least
            assert all(is_loopback(ip) for ips in bound.values() for ip in ips), bound
            with grpc.insecure_channel(ray.get_runtime_context().gcs_address) as channel:
                stub = gcs_service_pb2_grpc.NodeInfoGcsServiceStub(channel)
                with pytest.raises(grpc.RpcError) as refused:
                    stub.GetClusterId(gcs_service_pb2.GetClusterIdRequest(), timeout=10)
            assert refused.value.code() == grpc.StatusCode.UNAUTHENTICATED
            # a driver without the token is told so, at once (Ray's own connect retries, then fails without a reason)
            env = {k: v for k, v in os.environ.items() if k != "RAY_AUTH_MODE"}
            join = "import sys; from localscale.engine import get_executor; get_executor('ray', address=sys.argv[1])"
            gcs = ray.get_runtime_context().gcs_address
            joined = subprocess.run([PYTHON, "-c", join, gcs], capture_output=True, text=True, env=env, timeout=60)
            assert (
                f"EngineError: the Ray cluster at {gcs} requires Ray's token: set RAY_AUTH_MODE=token" in joined.stderr
            )
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert not wait_until_gone(short_dir, 10)  # closed: nothing of it runs


# ---------------------------------------------------------------- a killed driver; a two-node cluster

DRIVER = r"""
import os, sys, time
from localscale.engine import get_executor
from localscale.core.outputs import write_text

def work(state, x):
    time.sleep(0.3)
    return f"{x * x}\n"

out = sys.argv[1]
todo = [i for i in range(10) if not os.path.exists(f"{out}/{i}.txt")]   # a rerun skips what is complete
with get_executor("ray", workers=2, threads_per_worker=1, temp_dir=sys.argv[2]) as ex:
    for j, text in ex.map(work, todo):
        write_text(f"{out}/{todo[j]}.txt", text)
        print("wrote", todo[j], flush=True)
print("ran", len(todo), flush=True)
"""


def _stop_group(proc: subprocess.Popen) -> None:
    """Stop a process group this test started: SIGTERM, then SIGKILL what is left."""
    for sig, wait in ((signal.SIGTERM, 3), (signal.SIGKILL, 5)):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            return
        deadline = time.time() + wait
        while time.time() < deadline:
            try:
                os.killpg(proc.pid, 0)
            except ProcessLookupError:
                return
            time.sleep(0.2)


@needs_ray
@needs_two_cpus
@needs_proc
def test_killed_driver_rerun_resumes(tmp_path, short_dir):
    out = tmp_path / "out"
    out.mkdir()
    script = tmp_path / "driver.py"
    script.write_text(DRIVER)
    env = dict(os.environ, RAY_USAGE_STATS_ENABLED="0")
    cmd = [PYTHON, str(script), str(out), str(short_dir)]
    proc = subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=env, start_new_session=True
    )
    try:
        written = []
        deadline = time.time() + 60
        while len(written) < 3 and time.time() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            written.append(int(line.split()[1]))
        assert len(written) == 3, "the driver wrote nothing"
        assert cluster_processes(short_dir)
        os.kill(proc.pid, signal.SIGKILL)  # the driver only: its cluster goes down with it
        proc.wait(10)
        left = wait_until_gone(short_dir, 10)
        assert not left, f"{len(left)} process(es) of the killed driver's cluster still run"
        deadline = time.time() + 5
        while watchdogs_of(proc.pid) and time.time() < deadline:
            time.sleep(0.2)
        assert not watchdogs_of(proc.pid)  # the watchdog that stopped them exited too
    finally:
        _stop_group(proc)  # and anything of its cluster still running
    # a write the kill interrupted leaves only its hidden temporary file, never a partial output
    done = {int(p.stem) for p in out.glob("[0-9]*.txt")}
    assert set(written) <= done and len(done) < 10
    left = {p.name for p in out.iterdir() if p.name.startswith(".")}
    assert all(n.endswith(f".tmp-{proc.pid}.txt") for n in left), left
    rerun = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=90, start_new_session=True)
    assert rerun.returncode == 0, rerun.stderr[-2000:]
    assert not wait_until_gone(short_dir, 10)
    again = [int(line.split()[1]) for line in rerun.stdout.splitlines() if line.startswith("wrote")]
    assert sorted(again) == sorted(set(range(10)) - done)  # only what was missing, each once
    outputs = {p.name: p.read_text() for p in out.iterdir() if not p.name.startswith(".")}
    assert outputs == {f"{i}.txt": f"{i * i}\n" for i in range(10)}


TWO_NODE_DRIVER = r"""
import json, sys, time
import ray
from localscale.engine import EngineError, get_executor

def node_of(state, x):
    import ray, time
    time.sleep(0.2)
    return x, ray.get_runtime_context().get_node_id()

deadline = time.time() + 90
while True:  # the executor checks that the cluster has the 2 CPUs it needs: wait for the second node
    ex = get_executor("ray", workers=2, threads_per_worker=1, address=sys.argv[1])
    try:
        ex.start()
        break
    except EngineError as e:
        # the head's port opens before its services are up, and the second node comes later
        if not ("1 CPU(s)" in str(e) or "Failed to connect" in str(e)) or time.time() > deadline:
            raise
        time.sleep(0.5)
with ex:
    alive = sum(n["Alive"] for n in ray.nodes())
    out = [list(v) for _, v in sorted(ex.map(node_of, range(8)))]
print(json.dumps([alive, out]))
"""


@needs_ray
@pytest.mark.skipif(not RAY_CLI.exists(), reason="no `ray` command line")
def test_two_node_cluster(short_dir, monkeypatch):
    """A head and a second node started with `ray start` on this machine (1 CPU each, own ports and
    folders); the driver joins with an address and its actors run on both nodes."""
    # no token authentication on any process: a cluster of this machine, for this test only
    monkeypatch.setenv("RAY_AUTH_MODE", "disabled")
    # Ray joins a node to a cluster at 127.0.0.1 by this machine's own interface address when it has
    # one with a route: the nodes then use that address, which stays on this machine (it is bound here)
    from ray._private.services import resolve_ip_for_localhost

    node_ip = resolve_ip_for_localhost("127.0.0.1")
    if not own_address(node_ip):
        pytest.skip(f"Ray resolves 127.0.0.1 to {node_ip}, not an address of this machine")
    env = dict(os.environ, RAY_USAGE_STATS_ENABLED="0")
    port, client_port = free_port(), free_port()
    common = ["--block", "--num-cpus", "1", "--node-ip-address", node_ip, "--dashboard-agent-listen-port", "0"]
    head = subprocess.Popen(
        [
            str(RAY_CLI),
            "start",
            "--head",
            "--port",
            str(port),
            "--ray-client-server-port",
            str(client_port),
            "--include-dashboard",
            "false",
            "--disable-usage-stats",
            "--temp-dir",
            str(short_dir / "head"),
            *common,
        ],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    node = None
    try:
        deadline = time.time() + 60
        while time.time() < deadline and head.poll() is None:
            try:
                socket.create_connection((node_ip, port), timeout=1).close()
                break
            except OSError:
                time.sleep(0.3)
        assert head.poll() is None, "ray start --head failed"
        node = subprocess.Popen(
            [str(RAY_CLI), "start", "--address", f"{node_ip}:{port}", "--temp-dir", str(short_dir / "node"), *common],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            start_new_session=True,
        )
        # the driver runs in a process of its own: Ray keeps its authentication mode per process
        driver = subprocess.run(
            [PYTHON, "-c", TWO_NODE_DRIVER, f"{node_ip}:{port}"],
            capture_output=True,
            text=True,
            env=env,
            timeout=180,
        )
        assert driver.returncode == 0, driver.stderr[-2000:]
        alive, out = json.loads(driver.stdout.strip().splitlines()[-1])
        assert alive == 2
        assert sorted(x for x, _ in out) == list(range(8))
        assert len({n for _, n in out}) == 2  # work ran on both nodes
    finally:
        for proc in (node, head):
            if proc is not None:
                _stop_group(proc)


# ---------------------------------------------------------------- the command line


def _pairs_file(folder: Path) -> Path:
    rng = np.random.default_rng(0)
    base = cv2.GaussianBlur((rng.random((200, 260, 3)) * 255).astype(np.uint8), (0, 0), 2)
    cv2.imwrite(str(folder / "a.png"), base)
    cv2.imwrite(str(folder / "b.png"), cv2.resize(base, None, fx=0.6, fy=0.6))
    cv2.imwrite(str(folder / "c.png"), base[20:180, 30:230])
    pairs = folder / "pairs.txt"
    pairs.write_text("a.png\tb.png\nb.png\tc.png\nc.png\ta.png\n")
    return pairs


def test_predict_pairs_engine_options_need_ray(tmp_path, capsys):
    from localscale.cli import main

    pairs = _pairs_file(tmp_path)
    assert main(["predict", "--pairs", str(pairs), "-o", str(tmp_path / "out"), "--workers", "2"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:") and "--engine ray" in err[0]
    assert not (tmp_path / "out").exists()


@needs_ray
@pytest.mark.parametrize("command", ["predict", "reconstruct", "eval-hpatches"])
def test_unreachable_ray_address_fails_before_anything_is_written(command, tmp_path, capsys, photos):
    from localscale.cli import main

    out = tmp_path / "out"
    if command == "predict":
        argv = ["predict", "--pairs", str(_pairs_file(tmp_path)), "-o", str(out)]
    elif command == "reconstruct":
        pytest.importorskip("pycolmap")
        pytest.importorskip("h5py")
        from localscale.sfm.synthetic import write_scene

        write_scene(tmp_path / "scene", num_views=3, shape=(120, 160), seed=0)
        argv = ["reconstruct", str(tmp_path / "scene"), "-o", str(out), "--matcher", "sift", "--no-progress"]
    else:
        from localscale.evaluation import make_sequences

        make_sequences([photos["astronaut"]], tmp_path / "hp", num_images=2, size=96, seed=0)
        argv = ["eval-hpatches", str(tmp_path / "hp"), "-o", str(out), "--methods", "none", "--descriptor", "sift"]
    address = f"127.0.0.1:{free_port()}"  # nothing listens there
    assert main(argv + ["--engine", "ray", "--ray-address", address]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: cannot reach the Ray cluster at {address}: "), err
    assert not out.exists()


@needs_ray
def test_predict_pairs_on_ray_writes_what_the_local_engine_writes(tmp_path, capsys):
    from localscale.cli import main

    pairs = _pairs_file(tmp_path)
    assert main(["predict", "--pairs", str(pairs), "-o", str(tmp_path / "local")]) == 0
    assert (
        main(
            [
                "predict",
                "--pairs",
                str(pairs),
                "-o",
                str(tmp_path / "ray"),
                "--engine",
                "ray",
                "--workers",
                "1",
                "--threads-per-worker",
                "1",
            ]
        )
        == 0
    )
    assert "engine:" in capsys.readouterr().err
    local = sorted(p.name for p in (tmp_path / "local").glob("*.npy"))
    assert len(local) >= 6 and local == sorted(p.name for p in (tmp_path / "ray").glob("*.npy"))
    for name in local:
        assert np.allclose(np.load(tmp_path / "local" / name), np.load(tmp_path / "ray" / name), atol=1e-5)
