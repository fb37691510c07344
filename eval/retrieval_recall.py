"""Retrieval pairs against every pair: how many pairs each image's K nearest (GeM of the stored
ALIKED descriptors, :func:`localscale.sfm.pairs.pairs_from_retrieval`) match, and how many of the
truly co-visible pairs they keep, on the photo collections (``/work/shared/data/collections``).

    OMP_NUM_THREADS=1 python eval/retrieval_recall.py -o results/speed/retrieval_recall

Per collection, the features are extracted once, as ``localscale reconstruct`` stores them
(:func:`localscale.sfm.extract.extract_folder` at the defaults: ALIKED, 2048 keypoints, 1024 px),
into ``runs/retrieval_recall/<collection>/features.h5`` (kept: a rerun reuses it), from the folder
of the photos and their close-ups (:func:`localscale.evaluation.reconstruction.make_closeups`,
seed 0, zoom 2.5-5, one per third photo, turned by quarter turns).

The truth of a pair of photos (``truth`` column):

* ``model``: the 3D points the collection's COLMAP model sees in both photos (its ``points3D``
  tracks: skull_alansartlog, kermit_bundler);
* ``verified``: the inliers of a fundamental matrix (OpenCV USAC MAGSAC, 1.5 px) on the mutual
  nearest neighbours of the stored descriptors (every collection; cached in
  ``runs/retrieval_recall/<collection>/verified.json``). It comes from the descriptors that
  retrieval aggregates, so it favours retrieval: the ``model`` rows are the independent check.

For each K: the pairs of the photos alone (retrieval vs ``n(n-1)/2``), the recall of the pairs
with >= 50 and >= 200 shared points (inliers), the photos that have such a pair in the collection
but none among the retrieval pairs, the connected parts of the graph of the retrieved pairs with >= 50,
and, on the photos with their close-ups, how many close-ups have their own photo among their K
nearest (and the pair among the pairs). The table is printed and written to ``OUT.md``; the
numbers to ``OUT.json``.
"""

from __future__ import annotations

import argparse
import json
import struct
import sys
import time
from pathlib import Path

import numpy as np

THRESHOLDS = (50, 200)
COLLECTIONS = (
    "skull_alansartlog",
    "kermit_bundler",
    "plush_dog_smartdatascan",
    "kitchen_vggsfm",
    "temple_sparse_ring_middlebury",
    "cyprus_dim",
)
#: the COLMAP model of a collection: (points3D file, images.txt naming its image ids)
MODELS = {
    "skull_alansartlog": ("colmap_sparse_0/points3D.bin", "derived/colmap_txt_resized/images.txt"),
    "kermit_bundler": ("derived/colmap_txt/points3D.txt", "derived/colmap_txt/images.txt"),
}


def image_names(images_txt: Path) -> dict:
    """``{image id: name}`` of a COLMAP ``images.txt`` (its lines of 10 fields)."""
    out = {}
    for line in images_txt.read_text().splitlines():
        f = line.split()
        if len(f) >= 10 and not line.startswith("#") and f[0].isdigit():
            out[int(f[0])] = f[9]
    return out


def tracks(points3d: Path) -> list:
    """The image ids of each 3D point's track (``points3D.bin`` or ``.txt``)."""
    out = []
    if points3d.suffix == ".txt":
        for line in points3d.read_text().splitlines():
            if line and not line.startswith("#"):
                f = line.split()
                out.append([int(v) for v in f[8::2]])
        return out
    data = points3d.read_bytes()
    (n,), o = struct.unpack_from("<Q", data, 0), 8
    for _ in range(n):
        o += 8 + 24 + 3 + 8
        (length,) = struct.unpack_from("<Q", data, o)
        o += 8
        out.append(np.frombuffer(data, np.uint32, 2 * length, o)[0::2].tolist())
        o += 8 * length
    return out


def model_covisibility(root: Path, collection: str, names: list) -> dict:
    """``{(a, b): shared 3D points}`` (a < b) of the collection's model, for images of ``names``."""
    points, images = MODELS[collection]
    ids = image_names(root / collection / images)
    known = set(names)
    out = {}
    for track in tracks(root / collection / points):
        seen = sorted({ids[i] for i in track if i in ids and ids[i] in known})
        for i, a in enumerate(seen):
            for b in seen[i + 1 :]:
                out[(a, b)] = out.get((a, b), 0) + 1
    return out


def verified_covisibility(features_path: Path, names: list, cache: Path) -> dict:
    """``{(a, b): inliers}`` (a < b): a fundamental matrix on the stored descriptors' mutual nearest neighbours."""
    import cv2

    from localscale.sfm.extract import read_features

    done = {tuple(k.split("\t")): v for k, v in json.loads(cache.read_text()).items()} if cache.is_file() else {}
    feats = {}
    for n in names:
        f = read_features(features_path, n)
        d = f["descriptors"].astype(np.float32)
        feats[n] = (f["keypoints"], d / np.maximum(np.linalg.norm(d, axis=0, keepdims=True), 1e-12))
    names = sorted(names)
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            if (a, b) in done:
                continue
            (ka, da), (kb, db) = feats[a], feats[b]
            sim = da.T @ db
            ab, ba = sim.argmax(1), sim.argmax(0)
            mutual = np.flatnonzero(ba[ab] == np.arange(len(ab)))
            inliers = 0
            if len(mutual) >= 8:
                _, mask = cv2.findFundamentalMat(ka[mutual], kb[ab[mutual]], cv2.USAC_MAGSAC, 1.5, 0.999, 10000)
                inliers = 0 if mask is None else int(mask.sum())
            done[(a, b)] = inliers
        cache.write_text(json.dumps({f"{a}\t{b}": v for (a, b), v in done.items()}))
    return {k: v for k, v in done.items() if k[0] in feats and k[1] in feats}


def components(names: list, edges) -> int:
    parent = {n: n for n in names}

    def find(x):
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    for a, b in edges:
        parent[find(a)] = find(b)
    return len({find(n) for n in names})


def evaluate(collection: str, photos: list, closeups: dict, features: Path, truth: dict, label: str, ks) -> list:
    from localscale.sfm.pairs import global_descriptors, pairs_from_retrieval

    rows = []
    n = len(photos)
    every = n * (n - 1) // 2
    allnames = sorted(photos + list(closeups))
    g = global_descriptors(features, allnames)
    sim = g @ g.T
    np.fill_diagonal(sim, -np.inf)
    index = {m: i for i, m in enumerate(allnames)}
    for k in ks:
        pairs = {tuple(sorted(p)) for p in pairs_from_retrieval(photos, features, k)}
        row = {"collection": collection, "truth": label, "images": n, "K": k, "pairs": len(pairs), "exhaustive": every}
        for t in THRESHOLDS:
            good = {p for p, v in truth.items() if v >= t}
            kept = good & pairs
            row[f"recall_{t}"] = len(kept) / len(good) if good else None
            row[f"good_{t}"] = len(good)
            have = {m for p in good for m in p}
            keep = {m for p in kept for m in p}
            row[f"lost_images_{t}"] = sorted(have - keep)
            row[f"parts_{t}"] = components(sorted(have), kept) if good else None
            row[f"parts_all_{t}"] = components(sorted(have), good) if good else None
        if closeups:
            with_pairs = {tuple(sorted(p)) for p in pairs_from_retrieval(allnames, features, k)}
            ranks = {}
            for c, meta in closeups.items():
                order = [allnames[j] for j in np.argsort(-sim[index[c]], kind="stable")]
                ranks[c] = order.index(meta["source"]) + 1
            row["closeups"] = len(closeups)
            row["closeup_source_in_k"] = sum(r <= k for r in ranks.values())
            row["closeup_pair_kept"] = sum(tuple(sorted((c, m["source"]))) in with_pairs for c, m in closeups.items())
            row["closeup_ranks"] = ranks
            row["pairs_with_closeups"] = len(with_pairs)
            row["exhaustive_with_closeups"] = len(allnames) * (len(allnames) - 1) // 2
        rows.append(row)
    return rows


def pct(v) -> str:
    return "-" if v is None else f"{100 * v:.1f}%"


def markdown(rows: list) -> str:
    head = (
        "| collection | truth | n | K | pairs / every pair | recall >=50 | recall >=200 | photos losing all >=50 pairs "
        "| parts (>=50 graph, all pairs -> kept) | close-ups: own photo in K | close-ups: pair kept |"
    )
    lines = [head, "|" + "---|" * 11]
    for r in rows:
        lost = r["lost_images_50"]
        parts = "-" if r["parts_50"] is None else f"{r['parts_all_50']} -> {r['parts_50']}"
        lines.append(
            f"| {r['collection']} | {r['truth']} | {r['images']} | {r['K']} "
            f"| {r['pairs']} / {r['exhaustive']} ({pct(r['pairs'] / max(1, r['exhaustive']))}) "
            f"| {pct(r['recall_50'])} (of {r['good_50']}) | {pct(r['recall_200'])} (of {r['good_200']}) "
            f"| {len(lost) if r['good_50'] else '-'} | {parts} "
            f"| {r.get('closeup_source_in_k', '-')}/{r.get('closeups', '-')} "
            f"| {r.get('closeup_pair_kept', '-')}/{r.get('closeups', '-')} |"
        )
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument(
        "--root", default="/work/shared/data/collections", help="folder of the collections (default: shared)"
    )
    p.add_argument("--collections", nargs="+", default=list(COLLECTIONS), help="default: all six")
    p.add_argument("--ks", type=int, nargs="+", default=[5, 10, 15, 20, 30], help="default: 5 10 15 20 30")
    p.add_argument("--cache", default="runs/retrieval_recall", help="features and close-ups (default: %(default)s)")
    p.add_argument(
        "-o", "--output", default="results/speed/retrieval_recall", help="OUT.md, OUT.json (default: %(default)s)"
    )
    a = p.parse_args(argv)
    import torch

    from localscale.evaluation.reconstruction import make_closeups
    from localscale.evaluation.report import git_commit
    from localscale.sfm.extract import extract_folder
    from localscale.sfm.h5io import groups_with

    torch.set_num_threads(1)
    root, cache = Path(a.root), Path(a.cache)
    rows, seconds = [], {}
    for c in a.collections:
        t = time.perf_counter()
        folder = cache / c / "images"
        closeups = make_closeups(root / c / "images", folder, (2.5, 5.0), 0)
        features = cache / c / "features.h5"
        extract_folder(folder, features)
        seconds[f"{c}_extract"] = time.perf_counter() - t
        names = sorted(groups_with(features, "keypoints"))
        photos = [n for n in names if n not in closeups]
        t = time.perf_counter()
        truths = {"verified": verified_covisibility(features, photos, cache / c / "verified.json")}
        if c in MODELS:
            truths = {"model": model_covisibility(root, c, photos), **truths}
        seconds[f"{c}_truth"] = time.perf_counter() - t
        for label, truth in truths.items():
            rows += evaluate(c, photos, closeups, features, truth, label, a.ks)
        print(markdown([r for r in rows if r["collection"] == c]), flush=True)
    table = markdown(rows)
    print(table)
    out = Path(a.output)
    out.parent.mkdir(parents=True, exist_ok=True)
    command = "OMP_NUM_THREADS=1 python eval/retrieval_recall.py " + " ".join(
        argv if argv is not None else sys.argv[1:]
    )
    head = (
        "# Retrieval pairs against every pair\n\n"
        f"`{command.strip()}` (commit {git_commit()}; module docstring of `eval/retrieval_recall.py`: truth, columns). "
        "`model`: 3D points shared in the collection's COLMAP model; `verified`: fundamental-matrix inliers of the "
        "stored descriptors' mutual nearest neighbours (favours retrieval). Close-ups: turned by quarter turns, "
        "zoom 2.5-5.\n\n"
    )
    out.with_suffix(".md").write_text(head + table)
    doc = {"rows": rows, "seconds": seconds, "command": command.strip(), "commit": git_commit()}
    out.with_suffix(".json").write_text(json.dumps(doc, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
