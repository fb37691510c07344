"""Speed of the scale models on CPU (or --device cuda): prints a table and writes JSON.

Measures, for 640x480 inputs at the model's processing size:
* model load time (bundled checkpoint),
* ms per pair (median, p90): full pair (load-free: arrays in memory, letterbox + 2 encodes + head)
  and cached pair (features of both images already encoded: head only), fp32 and bf16,
* throughput (pairs/s) of one reference image against N others (N = 1, 10, 100) uncached vs
  with the feature cache, and all pairs among N images (every image in N-1 pairs),
* peak RSS.

    python eval/benchmark.py --out results/benchmark.json
"""
from __future__ import annotations

import argparse
import json
import platform
import resource
import sys
import time
from pathlib import Path

import numpy as np
import torch

from localscale import LocalScaleNet, ScaleNet
from localscale.cache import encode_batch, predict_batch


def timeit(fn, repeat: int, warmup: int = 2) -> np.ndarray:
    for _ in range(warmup):
        fn()
    out = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t)
    return np.array(out) * 1000


def images(n: int, rng) -> list[np.ndarray]:
    from skimage import data

    base = [data.astronaut(), data.coffee(), data.chelsea(), data.rocket()]
    import cv2

    out = []
    for i in range(n):
        im = cv2.resize(base[i % len(base)], (640, 480))
        out.append(np.clip(im.astype(np.int16) + rng.integers(-8, 8, im.shape), 0, 255).astype(np.uint8))
    return out


def bench_model(cls, path, device, repeat, rng) -> dict:
    t = time.perf_counter()
    model = cls.from_pretrained(path, device=device)
    load_ms = (time.perf_counter() - t) * 1000
    a, b = images(2, rng)
    res = {"load_ms": load_ms}
    for bf16 in (False, True):
        tag = "bf16" if bf16 else "fp32"
        full = timeit(lambda: model.predict(a, b, bf16=bf16), repeat)
        ea, eb = model.encode_image(a, bf16=bf16), model.encode_image(b, bf16=bf16)
        cached = timeit(lambda: model.predict_from_features(ea, eb, bf16=bf16), repeat)
        enc = timeit(lambda: model.encode_image(a, bf16=bf16), repeat)
        res[tag] = {"pair_ms_median": float(np.median(full)), "pair_ms_p90": float(np.percentile(full, 90)),
                    "cached_pair_ms_median": float(np.median(cached)), "cached_pair_ms_p90": float(np.percentile(cached, 90)),
                    "encode_ms_median": float(np.median(enc))}
    return res, model


def throughput(model, n: int, rng, batch: int = 8) -> dict:
    ims = images(n + 1, rng)
    ref, others = ims[0], ims[1:]
    t = time.perf_counter()
    for o in others:
        model.predict(ref, o)
    unc = n / (time.perf_counter() - t)
    t = time.perf_counter()
    e_ref = encode_batch(model, [ref])[0]
    for i in range(0, n, batch):
        encs = encode_batch(model, others[i:i + batch])
        predict_batch(model, [e_ref] * len(encs), encs)
    cached = n / (time.perf_counter() - t)
    return {"n": n, "uncached_pairs_per_s": unc, "cached_pairs_per_s": cached, "speedup": cached / unc}


def all_pairs(model, n: int, rng, batch: int = 16) -> dict:
    ims = images(n, rng)
    pairs = [(i, j) for i in range(n) for j in range(n) if i != j]
    t = time.perf_counter()
    for i, j in pairs[:min(len(pairs), 40)]:
        model.predict(ims[i], ims[j])
    unc = min(len(pairs), 40) / (time.perf_counter() - t)
    t = time.perf_counter()
    encs = [e for k in range(0, n, batch) for e in encode_batch(model, ims[k:k + batch])]
    for k in range(0, len(pairs), batch):
        chunk = pairs[k:k + batch]
        predict_batch(model, [encs[i] for i, _ in chunk], [encs[j] for _, j in chunk])
    cached = len(pairs) / (time.perf_counter() - t)
    return {"images": n, "pairs": len(pairs), "uncached_pairs_per_s": unc, "cached_pairs_per_s": cached,
            "speedup": cached / unc}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--local-model", default=None)
    p.add_argument("--global-model", default=None)
    p.add_argument("--device", default="cpu")
    p.add_argument("--repeat", type=int, default=20)
    p.add_argument("--threads", type=int, default=0)
    p.add_argument("--out", default=None)
    a = p.parse_args(argv)
    if a.threads:
        torch.set_num_threads(a.threads)
    rng = np.random.default_rng(0)
    res = {"device": a.device, "threads": torch.get_num_threads(), "cpu": platform.processor() or platform.machine(),
           "torch": torch.__version__, "input": "640x480 RGB arrays"}
    for name, cls, path in (("local", LocalScaleNet, a.local_model), ("global", ScaleNet, a.global_model)):
        try:
            r, model = bench_model(cls, path, a.device, a.repeat, rng)
        except Exception as e:  # a missing default model should not hide the other one
            print(f"skipping {name}: {e}", file=sys.stderr)
            continue
        r["processing_size"] = model.config.image_size
        if name == "local":
            r["one_vs_n"] = [throughput(model, n, rng) for n in (1, 10, 100)]
            r["all_pairs"] = all_pairs(model, 20, rng)
        res[name] = r
    res["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024

    print(f"\n### benchmark ({a.device}, {res['threads']} threads, torch {torch.__version__}, 640x480 inputs)\n")
    print("| model | load ms | precision | pair ms (median / p90) | cached pair ms (median / p90) | encode ms |")
    print("|---|---|---|---|---|---|")
    for name in ("local", "global"):
        if name not in res:
            continue
        for tag in ("fp32", "bf16"):
            r = res[name][tag]
            print(f"| {name} ({res[name]['processing_size']} px) | {res[name]['load_ms']:.0f} | {tag} | "
                  f"{r['pair_ms_median']:.1f} / {r['pair_ms_p90']:.1f} | {r['cached_pair_ms_median']:.2f} / "
                  f"{r['cached_pair_ms_p90']:.2f} | {r['encode_ms_median']:.1f} |")
    if "local" in res:
        print("\n| local, fp32 | pairs/s uncached | pairs/s cached | speed-up |\n|---|---|---|---|")
        for t in res["local"]["one_vs_n"]:
            print(f"| 1 vs {t['n']} | {t['uncached_pairs_per_s']:.1f} | {t['cached_pairs_per_s']:.1f} | {t['speedup']:.1f}x |")
        t = res["local"]["all_pairs"]
        print(f"| all {t['pairs']} pairs of {t['images']} images | {t['uncached_pairs_per_s']:.1f} | "
              f"{t['cached_pairs_per_s']:.1f} | {t['speedup']:.1f}x |")
    print(f"\npeak RSS: {res['peak_rss_mb']:.0f} MB")
    if a.out:
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
