"""Speed of the whole user path on CPU (or --device cuda): prints a markdown table and writes JSON.

Stages, on a 640x480 pair (the bundled ``kodim01_a/b`` resized, with its homography) and
``--num-features`` keypoints per image:

* CLI start-up (``python -m localscale --help`` in a subprocess) and one ``localscale match``
  run end to end (subprocess: imports, model loads, matching, writing the picture);
* model load (Local-ScaleNet, ScaleNet, HardNet);
* scale map: Local-ScaleNet ``predict`` (both images encoded) and from cached encodings (the
  head; A's self-correlation terms kept with its encoding, as for 1-vs-N, or recomputed, as for
  a new A), ScaleNet ``predict``;
* keypoint detection, patch extraction (local correction), description (HardNet of ``--descriptor``
  at each precision of :data:`~localscale.features.descriptors.PRECISIONS` with both images'
  patches in one call, the default precision also in two calls; RootSIFT), mutual-NN matching;
* per matcher of ``--matcher`` (names of :data:`localscale.matching.MATCHERS`, each at
  ``--num-features``): building the :class:`~localscale.matching.Matcher` (its weights),
  ``Matcher.extract`` of both images and ``Matcher.match`` without scale maps, ``match_pair`` end to
  end per correction of ``--corrections`` (models and matcher loaded once), and one
  ``eval-hpatches`` pair (:func:`localscale.evaluation.hpatches.evaluate`) per method: the methods
  in a row on one fresh matcher (shared work, as in ``localscale eval-hpatches``) and each method
  alone;
* ``aliked-lightglue`` also with kornia's defaults (2048 keypoints, the contiguous layout),
  against which the default's speed-up is given;
* the comparisons behind the speed targets timed interleaved (ours and the reference in turn,
  ``max(--repeat, 5)`` rounds; 15 for the scale map): ``match_pair`` local / OpenCV's SIFT
  pipeline, the uncached scale map, ``aliked-lightglue`` / kornia's defaults;
* with ``--pairs-per-second N``: throughput on ``--device`` (CUDA synchronised) of
  ``match_pair`` with the local correction (hardnet matcher) and of batched scale maps, over
  ``N`` pairs;
* OpenCV's SIFT pipeline on the same images (``cv2.SIFT_create(nfeatures)`` detect + compute
  on both, ``BFMatcher(NORM_L2, crossCheck=True)``) as the reference: every stage is also given
  as a ratio to it;
* peak RSS (``resource.getrusage``).

Times are medians over ``--repeat`` runs (at least 15 for the scale maps; after one warm-up),
wall clock and process CPU time;
on a loaded machine the CPU time is the steadier number. Scale-model throughput with the feature
cache (1 vs N images, all pairs) is measured with ``--throughput``.

    python eval/benchmark.py --repeat 3 --threads 2 --out results/benchmark.json
    python eval/benchmark.py --matcher hardnet sift aliked-lightglue xfeat-lighterglue --no-cli
    python eval/benchmark.py --device cuda --pairs-per-second 50 --no-cli

Only the public API is used, so the same script times another checkout of the same API:
``PYTHONPATH=/path/to/other/checkout python eval/benchmark.py``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch

import localscale
from localscale.core.errors import LocalScaleError
from localscale.evaluation.report import git_commit
from localscale.evaluation.timing import interleaved, subprocess_ms, timeit
from localscale.features import HardNetDescriptor, ScaleCorrectedPatches, SIFTPatchDescriptor, image_to_gray_tensor
from localscale.features.descriptors import PRECISIONS
from localscale.features.detector import HessianDetector
from localscale.io import load_image, read_homography
from localscale.matching import match_descriptors, match_pair
from localscale.matching.config import MATCHERS, match_config
from localscale.matching.correction import CORRECTIONS, get_correction, scale_maps_for_pair
from localscale.matching.matcher import Matcher
from localscale.models import LocalScaleNet, ScaleNet

ASSETS = Path(localscale.__file__).resolve().parent / "assets"


def test_pair(size=(640, 480)):
    """The bundled pair resized to ``size`` (w, h) and its homography in the resized frames."""
    a, b = load_image(ASSETS / "kodim01_a.jpg"), load_image(ASSETS / "kodim01_b.jpg")
    H = read_homography(ASSETS / "H_a_b.txt")
    sa = np.diag([size[0] / a.shape[1], size[1] / a.shape[0], 1.0])
    sb = np.diag([size[0] / b.shape[1], size[1] / b.shape[0], 1.0])
    a = cv2.resize(a, size, interpolation=cv2.INTER_AREA)
    b = cv2.resize(b, size, interpolation=cv2.INTER_AREA)
    return a, b, sb @ H @ np.linalg.inv(sa)


def opencv_sift(a: np.ndarray, b: np.ndarray, n: int):
    sift = cv2.SIFT_create(nfeatures=n)
    ga, gb = cv2.cvtColor(a, cv2.COLOR_RGB2GRAY), cv2.cvtColor(b, cv2.COLOR_RGB2GRAY)
    ka, da = sift.detectAndCompute(ga, None)
    kb, db = sift.detectAndCompute(gb, None)
    return cv2.BFMatcher(cv2.NORM_L2, crossCheck=True).match(da, db)


def matcher_config(name: str, n: int, hardnet):
    """The :class:`MatchConfig` of matcher ``name`` at ``n`` keypoints; the patch matchers describe
    with the already loaded ``hardnet`` (on the benchmark's device) when they use HardNet."""
    cfg = match_config(name, num_features=n)
    if cfg.extractor == "patches" and cfg.descriptor == "hardnet":
        cfg = match_config(cfg, descriptor=hardnet)
    return cfg


def eval_pair_times(a, b, H, methods, cfg, device, local, glob, repeat, tmp) -> dict:
    """One eval-hpatches pair (:func:`evaluate`) with matcher ``cfg``: all methods in a row and
    each method alone, each run on a fresh :class:`Matcher` (built untimed: its feature cache
    empty, as at the start of an evaluation)."""
    from localscale.evaluation.hpatches import PairInfo, evaluate

    pa, pb = Path(tmp) / "a.png", Path(tmp) / "b.png"
    cv2.imwrite(str(pa), a[..., ::-1])
    cv2.imwrite(str(pb), b[..., ::-1])
    pair = PairInfo("bench", 2, pa, pb, H)

    def run(ms, matcher):
        return evaluate([pair], ms, matcher, local, glob, progress=False)["records"]

    fresh = lambda: Matcher(cfg, device)  # noqa: E731
    out = {"all_methods": timeit(lambda m: run(methods, m), repeat, setup=fresh)}
    recs = run(methods, fresh())
    out["mma5"] = {r["method"]: r["mma"][4] for r in recs}
    out["record_seconds"] = {r["method"]: {"seconds": r["seconds"], "scale_seconds": r["scale_seconds"]} for r in recs}
    out["alone"] = {m: timeit(lambda matcher, m=m: run([m], matcher), repeat, setup=fresh) for m in methods}
    out["alone_sum_ms"] = sum(v["ms"] for v in out["alone"].values())
    out["alone_sum_cpu_ms"] = sum(v["cpu_ms"] for v in out["alone"].values())
    return out


def synchronize(device) -> None:
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()


def pairs_per_second(img_a, img_b, H, local, matcher, device, n: int) -> dict:
    """Throughput on ``device``: ``match_pair`` (local correction, ``matcher``) and Local-ScaleNet
    maps in batches of up to 8 pairs, ``n`` pairs each (after one warm-up), CUDA synchronised."""
    match_pair(img_a, img_b, "local", H, local, None, matcher)
    synchronize(device)
    t = time.perf_counter()
    for _ in range(n):
        match_pair(img_a, img_b, "local", H, local, None, matcher)
    synchronize(device)
    match_s = time.perf_counter() - t
    batch = min(8, n)
    xa = torch.from_numpy(np.stack([img_a] * batch)).permute(0, 3, 1, 2).to(device)
    xb = torch.from_numpy(np.stack([img_b] * batch)).permute(0, 3, 1, 2).to(device)
    local.predict_batch(xa, xb)
    synchronize(device)
    t, done = time.perf_counter(), 0
    while done < n:
        k = min(batch, n - done)
        local.predict_batch(xa[:k], xb[:k])
        done += k
    synchronize(device)
    map_s = time.perf_counter() - t
    return {
        "device": str(device),
        "pairs": n,
        "match_pair_local_pairs_per_s": n / match_s,
        "scale_map_batched_pairs_per_s": n / map_s,
        "map_batch": batch,
    }


def throughput_sections(model, rng) -> dict:
    """Scale-model pairs/s uncached vs with the feature cache (1 vs N, all pairs of N images)."""
    from skimage import data

    from localscale.cache import encode_batch, predict_batch

    base = [data.astronaut(), data.coffee(), data.chelsea(), data.rocket()]

    def images(k):
        return [
            np.clip(
                cv2.resize(base[i % 4], (640, 480)).astype(np.int16) + rng.integers(-8, 8, (480, 640, 3)), 0, 255
            ).astype(np.uint8)
            for i in range(k)
        ]

    res = {}
    for n in (1, 10):
        ims = images(n + 1)
        t = time.perf_counter()
        for o in ims[1:]:
            model.predict(ims[0], o)
        unc = n / (time.perf_counter() - t)
        t = time.perf_counter()
        e_ref = encode_batch(model, [ims[0]])[0]
        encs = encode_batch(model, ims[1:])
        predict_batch(model, [e_ref] * len(encs), encs)
        res[f"1_vs_{n}"] = {"uncached_pairs_per_s": unc, "cached_pairs_per_s": n / (time.perf_counter() - t)}
    ims = images(8)
    pairs = [(i, j) for i in range(8) for j in range(8) if i != j]
    t = time.perf_counter()
    encs = encode_batch(model, ims)
    for k in range(0, len(pairs), 16):
        chunk = pairs[k : k + 16]
        predict_batch(model, [encs[i] for i, _ in chunk], [encs[j] for _, j in chunk])
    res["all_pairs_8_images"] = {"pairs": len(pairs), "cached_pairs_per_s": len(pairs) / (time.perf_counter() - t)}
    return res


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__
    )
    p.add_argument("--repeat", type=int, default=5, help="timed runs per stage (after one warm-up)")
    p.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    p.add_argument("--num-features", type=int, default=1000, help="keypoints per image (every matcher)")
    p.add_argument("--device", default="cpu")
    p.add_argument(
        "--matcher",
        nargs="+",
        default=["hardnet"],
        choices=list(MATCHERS),
        metavar="NAME",
        help=f"matchers timed: {', '.join(MATCHERS)} (default: hardnet)",
    )
    p.add_argument(
        "--corrections",
        nargs="+",
        default=list(CORRECTIONS),
        choices=CORRECTIONS,
        metavar="NAME",
        help=f"corrections of the match_pair stages: {', '.join(CORRECTIONS)} (default: all)",
    )
    p.add_argument(
        "--methods",
        nargs="+",
        default=["none", "local", "gt"],
        choices=CORRECTIONS,
        metavar="NAME",
        help="eval-hpatches methods timed (default: none local gt)",
    )
    p.add_argument("--no-cli", action="store_true", help="skip the subprocess timings (--help, match)")
    p.add_argument("--throughput", action="store_true", help="also time scale-model throughput with the cache")
    p.add_argument(
        "--pairs-per-second",
        type=int,
        default=0,
        metavar="N",
        help="also measure throughput on --device over N pairs (match_pair local, batched maps)",
    )
    p.add_argument("--descriptor", default=None, metavar="WEIGHTS", help="HardNet weights (default: bundled)")
    p.add_argument("--local-weights", default=None, help="Local-ScaleNet checkpoint (default: bundled)")
    p.add_argument("--global-weights", default=None, help="ScaleNet checkpoint (default: bundled)")
    p.add_argument("--out", default=None, help="JSON file")
    return p


KORNIA_DEFAULTS = "aliked-lightglue (kornia defaults: 2048 keypoints, contiguous)"


@dataclass
class Bench:
    """What the stages share: the options, the pair, the loaded models and matchers, and the
    timings (``st``: stage -> timing) and other results (``res``) gathered so far."""

    a: argparse.Namespace
    img_a: np.ndarray
    img_b: np.ndarray
    H: np.ndarray
    hardnet: object
    configs: dict
    matchers: dict
    kornia_defaults: object
    tmp: str = ""
    local: object = None
    glob: object = None
    st: dict = field(default_factory=dict)
    res: dict = field(default_factory=dict)

    @property
    def n(self) -> int:
        return self.a.num_features

    @property
    def rep(self) -> int:
        return self.a.repeat


def load_matchers(a, names: list):
    """``(hardnet, configs, matchers, kornia_defaults)``: every matcher's weights, loaded before
    anything is timed (``kornia_defaults``: ``aliked-lightglue`` with kornia's settings, or None)."""
    hardnet = HardNetDescriptor.from_pretrained(a.descriptor, device=a.device)
    configs = {name: matcher_config(name, a.num_features, hardnet) for name in names}
    matchers = {name: Matcher(cfg, a.device) for name, cfg in configs.items()}
    kornia_defaults = None
    if "aliked-lightglue" in names:
        cfg = match_config(
            "aliked-lightglue", name="aliked-lightglue (kornia defaults)", num_features=2048, channels_last=False
        )
        kornia_defaults = Matcher(cfg, a.device)
    return hardnet, configs, matchers, kornia_defaults


def run_info(b: Bench, names: list) -> dict:
    a = b.a
    return {
        "device": a.device,
        "threads": torch.get_num_threads(),
        "torch": torch.__version__,
        "cpu": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "load_average_start": os.getloadavg(),
        "localscale": str(Path(localscale.__file__).parent),
        "input": f"640x480 pair (bundled kodim01_a/b resized), {b.n} keypoints",
        "repeat": b.rep,
        "matchers": names,
        "descriptor": a.descriptor or "bundled",
        "descriptor_precision_auto": b.hardnet.resolved_precision(a.device),
        "local_weights": a.local_weights or "bundled",
        "global_weights": a.global_weights or "bundled",
        "commit": git_commit(),
    }


def cli_stages(b: Bench) -> None:
    """``localscale --help`` and one ``localscale match`` in subprocesses."""
    a, tmp = b.a, b.tmp
    env = dict(os.environ, OMP_NUM_THREADS=str(a.threads)) if a.threads else None
    b.st["cli: localscale --help"] = subprocess_ms([sys.executable, "-m", "localscale", "--help"], b.rep, tmp, env)
    pa, pb, ph = Path(tmp) / "a.png", Path(tmp) / "b.png", Path(tmp) / "H.txt"
    cv2.imwrite(str(pa), b.img_a[..., ::-1])
    cv2.imwrite(str(pb), b.img_b[..., ::-1])
    np.savetxt(ph, b.H)
    cmd = [sys.executable, "-m", "localscale", "match", str(pa), str(pb), "-o", str(Path(tmp) / "m")]
    cmd += ["--correction", "local", "--H", str(ph), "--num-features", str(b.n)]
    b.st["cli: localscale match (local)"] = subprocess_ms(cmd, max(1, min(b.rep, 3)), tmp, env)


def model_stages(b: Bench) -> None:
    """Model loads and scale maps (uncached, from cached encodings, ScaleNet)."""
    a, st, rep, img_a, img_b = b.a, b.st, b.rep, b.img_a, b.img_b
    st["load: Local-ScaleNet"] = timeit(lambda: LocalScaleNet.from_pretrained(a.local_weights, a.device), rep)
    st["load: ScaleNet"] = timeit(lambda: ScaleNet.from_pretrained(a.global_weights, a.device), rep)
    st["load: HardNet"] = timeit(lambda: HardNetDescriptor.from_pretrained(a.descriptor, device=a.device), rep)
    local = b.local = LocalScaleNet.from_pretrained(a.local_weights, a.device)
    glob = b.glob = ScaleNet.from_pretrained(a.global_weights, a.device)
    fast = max(rep, 15)  # short stages: more runs, a steadier median
    st["scale map: local, uncached (2 encodes + head)"] = timeit(lambda: local.predict(img_a, img_b), fast)
    ea, eb = local.encode_image(img_a), local.encode_image(img_b)
    st["scale map: local, cached encodings, A's self terms kept (head)"] = timeit(
        lambda: local.predict_from_features(ea, eb), fast
    )
    st["scale map: local, cached encodings, A's self terms recomputed (head)"] = timeit(
        lambda _: local.predict_from_features(ea, eb), fast, setup=ea.terms.clear
    )
    st["scale map: global ScaleNet"] = timeit(lambda: glob.predict(img_a, img_b), fast)


def patch_stages(b: Bench) -> None:
    """Detection, patches (local correction), description at each precision, mutual-NN matching."""
    a, st, rep, hardnet = b.a, b.st, b.rep, b.hardnet
    sift = SIFTPatchDescriptor().to(a.device).eval()
    ga, gb = image_to_gray_tensor(b.img_a), image_to_gray_tensor(b.img_b)
    det = HessianDetector(b.n)
    st["detect: 2 images"] = timeit(lambda: (det(ga), det(gb)), rep)
    ka, kb = det(ga)[0], det(gb)[0]
    sa, sb = scale_maps_for_pair(b.img_a, b.img_b, "local", None, b.local, b.glob)
    cutter = ScaleCorrectedPatches()
    st["patches: 2 images (local correction)"] = timeit(lambda: (cutter(ga, ka, sa), cutter(gb, kb, sb)), rep)
    pa_, pb_ = cutter(ga, ka, sa)[0], cutter(gb, kb, sb)[0]
    patches = torch.cat([pa_, pb_])
    default = hardnet.resolved_precision(a.device)
    for prec in PRECISIONS[1:]:
        if prec == "int8" and (not hardnet.int8_ranges or torch.device(a.device).type != "cpu"):
            continue
        hardnet.set_precision(prec)
        tag = " (default)" if prec == default else ""
        st[f"describe: HardNet {prec}{tag}, {len(patches)} patches, one call"] = timeit(
            lambda: hardnet.describe(patches), rep
        )
    hardnet.set_precision("auto")
    st[f"describe: HardNet {default}, {len(patches)} patches, two calls (A, B)"] = timeit(
        lambda: (hardnet.describe(pa_), hardnet.describe(pb_)), rep
    )
    st[f"describe: RootSIFT, {len(patches)} patches"] = timeit(lambda: sift.describe(patches), rep)
    da, db = hardnet.describe(pa_), hardnet.describe(pb_)
    st["match: mutual NN"] = timeit(lambda: match_descriptors(da, db), rep)


def matcher_stages(b: Bench, name: str) -> None:
    """One matcher: build, extract, match without maps, ``match_pair`` per correction, one
    eval-hpatches pair."""
    a, st, rep, img_a, img_b, H = b.a, b.st, b.rep, b.img_a, b.img_b, b.H
    m, cfg = b.matchers[name], b.configs[name]
    what = (
        "HardNet loaded above"
        if cfg.extractor == "patches" and not isinstance(cfg.descriptor, str)
        else "OpenCV"
        if cfg.extractor == "sift"
        else "loads its weights"
    )
    st[f"matcher {name}: build ({what})"] = timeit(lambda: Matcher(cfg, a.device), rep)
    st[f"matcher {name}: extract 2 images"] = timeit(lambda: (m.extract(img_a), m.extract(img_b)), rep)
    st[f"matcher {name}: match (extract + match, no maps)"] = timeit(lambda: m.match(img_a, img_b), rep)
    b.res["matches"][name] = {}
    for corr in a.corrections:
        needs = get_correction(corr).models
        lm = b.local if "local" in needs else None
        gm = b.glob if "global" in needs else None
        run = lambda corr=corr, lm=lm, gm=gm: match_pair(img_a, img_b, corr, H, lm, gm, m)  # noqa: E731
        st[f"match_pair {name}: {corr}"] = timeit(run, rep)
        r = run()
        b.res["matches"][name][corr] = {"matches": int(len(r.matches)), "mma5": r.accuracy(5.0)}
    ev = eval_pair_times(img_a, img_b, H, list(a.methods), cfg, a.device, b.local, b.glob, rep, b.tmp)
    st[f"eval pair {name}: {'+'.join(a.methods)} (shared work)"] = ev["all_methods"]
    for meth, t in ev["alone"].items():
        st[f"eval pair {name}: {meth} alone"] = t
    b.res["eval_pair"][name] = {
        "mma5": ev["mma5"],
        "record_seconds": ev["record_seconds"],
        "alone_sum": {"ms": ev["alone_sum_ms"], "cpu_ms": ev["alone_sum_cpu_ms"]},
    }


def kornia_default_stages(b: Bench) -> None:
    """``aliked-lightglue`` with kornia's defaults, and the default's speed-up over it."""
    km, st = b.kornia_defaults, b.st
    st[f"matcher {KORNIA_DEFAULTS}: extract 2 images"] = timeit(
        lambda: (km.extract(b.img_a), km.extract(b.img_b)), b.rep
    )
    st[f"matcher {KORNIA_DEFAULTS}: match (extract + match, no maps)"] = timeit(
        lambda: km.match(b.img_a, b.img_b), b.rep
    )
    ours = st["matcher aliked-lightglue: match (extract + match, no maps)"]
    kd = st[f"matcher {KORNIA_DEFAULTS}: match (extract + match, no maps)"]
    b.res["aliked_lightglue_speedup_over_kornia_defaults"] = {
        "wall": kd["ms"] / ours["ms"],
        "cpu": kd["cpu_ms"] / ours["cpu_ms"],
    }


def interleaved_stages(b: Bench) -> None:
    """The targets' comparisons, timed in turn (ratios robust to a drifting machine)."""
    img_a, img_b, rep = b.img_a, b.img_b, b.rep
    sift_ref = lambda: opencv_sift(img_a, img_b, b.n)  # noqa: E731
    pairs = {}
    if "hardnet" in b.matchers:
        hm = b.matchers["hardnet"]
        pairs["match_pair hardnet local / OpenCV SIFT pipeline"] = interleaved(
            {"ours": lambda: match_pair(img_a, img_b, "local", b.H, b.local, None, hm), "reference": sift_ref},
            max(rep, 5),
        )
    pairs["scale map uncached / OpenCV SIFT pipeline"] = interleaved(
        {"ours": lambda: b.local.predict(img_a, img_b), "reference": sift_ref}, max(rep, 15)
    )
    if b.kornia_defaults is not None:
        am, km = b.matchers["aliked-lightglue"], b.kornia_defaults
        pairs["aliked-lightglue default / kornia's defaults (match, no maps)"] = interleaved(
            {"ours": lambda: am.match(img_a, img_b), "reference": lambda: km.match(img_a, img_b)}, max(rep, 5)
        )
    for v in pairs.values():
        v["ratio"] = v["ours"]["ms"] / v["reference"]["ms"]
        v["ratio_cpu"] = v["ours"]["cpu_ms"] / v["reference"]["cpu_ms"]
    b.res["interleaved"] = pairs


def run_stages(b: Bench) -> None:
    """Every stage, in the order of the table."""
    a = b.a
    if not a.no_cli:
        cli_stages(b)
    model_stages(b)
    patch_stages(b)
    b.res["matches"], b.res["eval_pair"] = {}, {}
    for name in b.matchers:
        matcher_stages(b, name)
    if b.kornia_defaults is not None:
        kornia_default_stages(b)
    interleaved_stages(b)
    if a.pairs_per_second:
        matcher = b.matchers.get("hardnet") or Matcher(matcher_config("hardnet", b.n, b.hardnet), a.device)
        b.res["pairs_per_second"] = pairs_per_second(
            b.img_a, b.img_b, b.H, b.local, matcher, a.device, a.pairs_per_second
        )
    b.st["OpenCV SIFT: detect+compute 2 images + BFMatcher crossCheck"] = timeit(
        lambda: opencv_sift(b.img_a, b.img_b, b.n), b.rep
    )
    b.res["opencv_sift_matches"] = len(opencv_sift(b.img_a, b.img_b, b.n))


def print_stages(res: dict, st: dict, device: str) -> None:
    print(
        f"\n### localscale user path ({device}, {res['threads']} threads, torch {torch.__version__}, "
        f"{res['input']}; load average {res['load_average_start'][0]:.1f} -> {res['load_average_end'][0]:.1f})\n"
    )
    print("| stage | ms (median) | ms p90 | CPU ms | x OpenCV SIFT (wall) | x OpenCV SIFT (CPU) |")
    print("|---|---|---|---|---|---|")
    for name, t in st.items():
        print(
            f"| {name} | {t['ms']:.1f} | {t['ms_p90']:.1f} | {t['cpu_ms']:.1f} | {t['x_opencv_sift']:.2f} | "
            f"{t['x_opencv_sift_cpu']:.2f} |"
        )
    print()
    for name, ev in res["eval_pair"].items():
        s = ev["alone_sum"]
        print(
            f"eval pair {name}, methods alone summed: {s['ms']:.0f} ms ({s['cpu_ms']:.0f} CPU ms); "
            f"MMA@5 {', '.join(f'{k} {v:.3f}' for k, v in ev['mma5'].items())}"
        )
    for name, ms in res["matches"].items():
        print(f"matches {name}: " + ", ".join(f"{k} {v['matches']} (MMA@5 {v['mma5']:.3f})" for k, v in ms.items()))
    print(f"matches OpenCV SIFT: {res['opencv_sift_matches']}")


def print_comparisons(res: dict) -> None:
    print("\ninterleaved comparisons (ours and the reference timed in turn):\n")
    print("| comparison | ours ms | reference ms | ratio (wall) | ratio (CPU) |")
    print("|---|---|---|---|---|")
    for name, v in res["interleaved"].items():
        print(
            f"| {name} | {v['ours']['ms']:.1f} | {v['reference']['ms']:.1f} | {v['ratio']:.2f} | {v['ratio_cpu']:.2f} |"
        )
    print()
    if "aliked_lightglue_speedup_over_kornia_defaults" in res:
        v = res["aliked_lightglue_speedup_over_kornia_defaults"]
        print(f"aliked-lightglue default vs kornia's defaults: {v['wall']:.2f}x faster (wall), {v['cpu']:.2f}x (CPU)")
    if "pairs_per_second" in res:
        v = res["pairs_per_second"]
        print(
            f"throughput on {v['device']} ({v['pairs']} pairs): match_pair local {v['match_pair_local_pairs_per_s']:.2f} "
            f"pairs/s, scale maps in batches of {v['map_batch']} {v['scale_map_batched_pairs_per_s']:.1f} pairs/s"
        )
    if "throughput_local" in res:
        for k, v in res["throughput_local"].items():
            print(f"local model {k}: " + ", ".join(f"{kk} {vv:.1f}" for kk, vv in v.items()))
    print(f"peak RSS: {res['peak_rss_mb']:.0f} MB")


def main(argv=None) -> int:
    p = parser()
    a = p.parse_args(argv)
    if a.repeat < 1 or a.num_features < 1 or a.pairs_per_second < 0:
        p.error("--repeat and --num-features must be >= 1, --pairs-per-second >= 0")
    if a.threads:
        torch.set_num_threads(a.threads)
    names = list(dict.fromkeys(a.matcher))
    try:
        loaded = load_matchers(a, names)
    except LocalScaleError as e:
        print(f"error: {' '.join(str(e).split())}", file=sys.stderr)
        return 2
    b = Bench(a, *test_pair(), *loaded)
    b.res = run_info(b, names)
    with tempfile.TemporaryDirectory() as tmp:
        b.tmp = tmp
        run_stages(b)
    res, st = b.res, b.st
    if a.throughput:
        res["throughput_local"] = throughput_sections(b.local, np.random.default_rng(0))
    ref = st["OpenCV SIFT: detect+compute 2 images + BFMatcher crossCheck"]
    for t in st.values():
        t["x_opencv_sift"] = t["ms"] / ref["ms"]
        t["x_opencv_sift_cpu"] = t["cpu_ms"] / max(ref["cpu_ms"], 1e-9)
    res["stages"] = st
    res["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    res["load_average_end"] = os.getloadavg()
    print_stages(res, st, a.device)
    print_comparisons(res)
    if a.out:
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
