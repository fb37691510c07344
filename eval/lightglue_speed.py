"""LightGlue on CPU: time, layers run and matches of the pairs of a ``features.h5`` (``reconstruct``'s
stored ALIKED features) under several run-time variants, and the mutual nearest-neighbour count of
every pair (the pruning check of :mod:`localscale.sfm.prune`).

    OMP_NUM_THREADS=1 python eval/lightglue_speed.py OUT/kermit_bundler/aliked-lg-auto/features.h5 \\
        --matches OUT/kermit_bundler/aliked-lg-auto/matches.h5 --pairs 12 --json results/speed/lightglue_kermit.json

Variants: ``fp32`` (kornia's defaults, adaptive depth 0.95 and width 0.99), ``fp32-noadapt``
(both off), ``fp32-0.9`` (depth / width confidence 0.9 / 0.95), ``int8`` (dynamic int8 quantisation
of the linear layers, :func:`torch.ao.quantization.quantize_dynamic`), ``bf16`` (kornia's ``mp``, CPU
autocast), ``bf16-0.9``. ``--matches``: a ``matches.h5`` of an ``auto`` run gives each pair's ``verified`` flag
(pair kind ``verified`` / ``not verified``), a ``geometries.h5`` the pairs with 15 inliers or more. Each timed pair also gets the seconds of each layer LightGlue ran (the
last number: all but the layers). Every pair of the file gets its MNN count
(``--mnn-only`` stops there).
"""

from __future__ import annotations

import argparse
import itertools
import json
import statistics
import time
from pathlib import Path

import torch

from localscale.matching import Matcher, match_config
from localscale.sfm.extract import features_for_matcher
from localscale.sfm.h5io import groups_with, read_group
from localscale.sfm.images import names_to_pair
from localscale.sfm.prune import mutual_nn_count

VARIANTS = ("fp32", "fp32-noadapt", "fp32-0.9", "int8", "bf16", "bf16-0.9")


def matcher_of(variant: str) -> Matcher:
    precision, _, conf = variant.partition("-")
    opts = {
        "noadapt": dict(depth_confidence=-1, width_confidence=-1),
        "0.9": dict(depth_confidence=0.9, width_confidence=0.95),
    }
    return Matcher(match_config("aliked-lightglue", lightglue_precision=precision, **opts.get(conf, {})))


def verified_flags(path, min_inliers: int = 15) -> dict:
    """``{pair key: verified}``: an ``auto`` run's ``matches.h5`` (its flag) or a ``geometries.h5``
    (COLMAP's verification kept at least ``min_inliers`` inliers)."""
    import h5py

    out = {}
    if Path(path).name.startswith("geometries"):
        with h5py.File(path, "r") as f:
            for a in f:
                for b in f[a]:
                    out[names_to_pair(a, b)] = len(f[a][b]["inlier_matches"]) >= min_inliers
        return out
    for key in groups_with(path, "matches0"):
        at = read_group(path, key, ("matches0",))["attrs"]
        if "verified" in at:
            out[key] = bool(at["verified"])
    return out


def layer_seconds(m: Matcher, fa, fb) -> list:
    """Seconds of each transformer layer LightGlue ran on the pair (forward hooks), then the rest."""
    net, marks = m._lightglue, []
    hooks = [
        h
        for layer in net.transformers
        for h in (
            layer.register_forward_pre_hook(lambda *_: marks.append(("in", time.perf_counter()))),
            layer.register_forward_hook(lambda *_: marks.append(("out", time.perf_counter()))),
        )
    ]
    t0 = time.perf_counter()
    m.match_features(fa, fb)
    total = time.perf_counter() - t0
    for h in hooks:
        h.remove()
    layers = [b[1] - a[1] for a, b in zip(marks[::2], marks[1::2])]
    return [round(x, 4) for x in layers] + [round(total - sum(layers), 4)]


def run_pair(m: Matcher, fa, fb) -> dict:
    stops = []
    net = m._lightglue
    hook = net.register_forward_hook(lambda mod, inp, out: stops.append(int(out.get("stop", -1))))
    t, c = time.perf_counter(), time.process_time()
    matches, _ = m.match_features(fa, fb)
    seconds, cpu = time.perf_counter() - t, time.process_time() - c
    hook.remove()
    return {"seconds": seconds, "cpu_s": cpu, "matches": int(len(matches)), "layers": stops[0] if stops else -1}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("features")
    p.add_argument("--matches", default=None)
    p.add_argument("--pairs", type=int, default=10, help="pairs timed (the first N of each kind)")
    p.add_argument("--any-pairs", action="store_true", help="without --matches: time the first N pairs")
    # the first variant is the reference of the speed-ups (per pair, median)
    p.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS)
    p.add_argument("--mnn-only", action="store_true")
    p.add_argument("--json", default=None)
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    names = sorted(groups_with(a.features, "keypoints"))
    feats = {n: features_for_matcher(a.features, n)[0] for n in names}
    flags = verified_flags(a.matches) if a.matches else {}
    rows = []
    for x, y in itertools.combinations(names, 2):
        key = names_to_pair(x, y) if names_to_pair(x, y) in flags else names_to_pair(y, x)
        da, db = feats[x].descriptors, feats[y].descriptors
        rows.append(
            {
                "a": x,
                "b": y,
                "verified": flags.get(key),
                "mnn": mutual_nn_count(da, db),
                "mnn_noratio": mutual_nn_count(da, db, 1.0),
            }
        )
    for kind in (True, False):
        counts = sorted(r["mnn"] for r in rows if r["verified"] is kind)
        if counts:
            print(f"verified={kind}: {len(counts)} pairs, MNN (ratio 0.9) {counts}")
            print("   no ratio:", sorted(r["mnn_noratio"] for r in rows if r["verified"] is kind))
    timing = {}
    if not a.mnn_only:
        chosen = [r for r in rows if r["verified"]][: a.pairs] + [r for r in rows if r["verified"] is False][: a.pairs]
        if a.any_pairs and not flags:
            chosen = rows[: a.pairs]
        matchers = {v: matcher_of(v) for v in a.variants}
        for m in matchers.values():
            run_pair(m, feats[chosen[0]["a"]], feats[chosen[0]["b"]])  # warm-up
        for r in chosen:  # the variants in turn on each pair: the machine's load falls on all of them
            for v, m in matchers.items():
                r[v] = run_pair(m, feats[r["a"]], feats[r["b"]])
                r[v]["layer_seconds"] = layer_seconds(m, feats[r["a"]], feats[r["b"]])
        for v in a.variants:
            for kind in (True, False, None):
                sel = [r for r in chosen if r["verified"] is kind]
                if not sel:
                    continue
                s = statistics.median(r[v]["seconds"] for r in sel)
                ratio = statistics.median(r[a.variants[0]]["seconds"] / r[v]["seconds"] for r in sel)
                mt = statistics.median(r[v]["matches"] for r in sel)
                lay = statistics.median(r[v]["layers"] for r in sel)
                timing[f"{v} verified={kind}"] = {
                    "median_s": round(s, 3),
                    "median_cpu_s": round(statistics.median(r[v]["cpu_s"] for r in sel), 3),
                    f"speed-up_vs_{a.variants[0]}": round(ratio, 2),
                    "median_matches": mt,
                    "median_layers": lay,
                    "pairs": len(sel),
                }
                print(
                    f"{v:13s} verified={kind!s:5s}: median {s:.3f} s/pair ({ratio:.2f}x), {mt} matches, {lay} layers",
                    flush=True,
                )
    if a.json:
        Path(a.json).parent.mkdir(parents=True, exist_ok=True)
        Path(a.json).write_text(json.dumps({"features": a.features, "timing": timing, "pairs": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
