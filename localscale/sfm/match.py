"""The match step: match the pairs from ``features.h5`` and ``pairs.txt`` (``matches.h5``) and give every image one keypoint set (``keypoints.h5``).

``correction``:

* ``none``: the cached features of ``features.h5`` matched with the matcher (LightGlue or
  nearest neighbours), what an hloc user runs;
* ``auto``: scales and quarter turns found for the collection as a whole (:func:`~localscale.matching.auto.collection.match_with_graph`):
  every pair as it is with a two-view verification, the SIFT seed's geometry of the pairs that do
  not verify, then hypotheses composed along the verified pairs (:mod:`localscale.matching.auto.graph`: a close-up
  verified against one photo is related to that photo's neighbours) and the networks only for
  pairs that the graph cannot join; ``auto_graph=False``: the whole hypothesis loop
  (:func:`~localscale.matching.auto.try_hypotheses`) on every pair. One :class:`~.extract.LevelMatcher`, built
  from the configuration and seeded from ``features.h5``, is shared by all pairs, so that an image's features at a level and turn are computed once;
* ``global``, ``local``, ``fused``, ``searched``: the pair rectified by the correction's maps
  (:mod:`localscale.matching.correction`), again with the shared level cache.

Keypoints matched at another level, turn or window are mapped back to full-image pixels and merged
into the image's keypoint set (:class:`KeypointSet`: a keypoint within ``merge_px`` of one already
in the set is that keypoint; hloc merges the keypoints of dense matchers the same way), so that the
matches of different pairs share keypoints and form tracks. The set starts with ``features.h5``'s
keypoints (with ``none`` it is exactly them).

With ``auto``, a pair kept as it is comes with its two-view geometry (estimated once, by
:func:`~.geometry.pair_geometry`, with the images' cameras), stored beside its matches for the
geometry step.

A pair already in ``matches.h5`` (either order) is skipped: a rerun resumes. ``matches.h5`` and
``keypoints.h5`` are flushed together (keypoints first) every ``flush_s`` seconds and at the end.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from ..core.errors import LocalScaleError
from ..matching.auto.graph import Relation
from .config import SFM_CORRECTIONS, ReconstructConfig
from .extract import FeatureConf
from .h5io import H5FileError, H5Writer, groups_with, matches0_from_matches, read_group
from .images import names_to_pair
from .keypoints import KeypointSet, one_to_one
from .pair_runner import MatchPair, PairRunnerFactory
from .progress import progress
from .report import warn
from .steps import cameras_of, config_of, parser, run_step, step_images


@dataclass
class PairRecord:
    """What matching one pair found: matches, whether the matcher's own verification passed
    (``auto``; None otherwise), the hypothesis chosen, seconds."""

    a: str
    b: str
    num_matches: int
    verified: Optional[bool] = None
    chosen: str = ""
    seconds: float = 0.0
    relation: Optional[Relation] = None  #: ``auto``: the verified pair's scale and quarter turn

    def to_dict(self) -> dict:
        out = {
            "a": self.a,
            "b": self.b,
            "num_matches": self.num_matches,
            "verified": self.verified,
            "chosen": self.chosen,
            "seconds": round(self.seconds, 3),
        }
        if self.relation is not None:
            out["relation"] = {"scale": round(self.relation.scale, 4), "turn": self.relation.turn}
        return out


@dataclass
class MatchStats:
    pairs: list = field(default_factory=list)  # PairRecord, resumed ones included
    matched: int = 0  # pairs matched in this run
    resumed: int = 0  # pairs found in matches.h5
    feature_sets: int = 0  # feature sets the level cache computed
    added_keypoints: int = 0  # keypoints beyond features.h5's, all images
    seconds: float = 0.0
    steps: dict = field(default_factory=dict)  # auto on the pair graph: {step: {"pairs", "verified", "seconds"}}

    def to_dict(self) -> dict:
        return {
            "matched": self.matched,
            "resumed": self.resumed,
            "feature_sets_computed": self.feature_sets,
            "added_keypoints": self.added_keypoints,
            "seconds": round(self.seconds, 2),
            **({"auto_steps": self.steps} if self.steps else {}),
            "pairs": [p.to_dict() for p in self.pairs],
        }


def match_pairs(
    images: list,
    pairs: list,
    features_path,
    matches_path,
    keypoints_path,
    conf=None,
    device: str = "cpu",
    *,
    models: tuple = (None, None),
    overwrite: bool = False,
    show_progress: bool = True,
    executor=None,
    flush_s: float = 30.0,
) -> MatchStats:
    """Match ``pairs`` (``[(name_a, name_b), ...]``) of ``images`` and write ``matches_path`` and
    ``keypoints_path`` (module docstring). ``features_path`` must hold every image of the pairs
    (:func:`~.extract.extract_features` with the same features); the matcher and its level cache
    are built here from ``conf`` (:class:`~.config.ReconstructConfig`: its ``features``,
    ``correction`` and ``mapping.merge_px``; default: its defaults).

    ``models``: ``(local_model, global_model)``, the networks of the correction (None: bundled weights).
    ``overwrite``: rematch every pair (else pairs in ``matches_path`` are skipped).
    ``executor``: an :class:`~localscale.engine.Executor` other than the local one matches the pairs
    on its workers (each with its own level cache and the bundled networks); the driver merges the
    keypoints in pair order, so the outputs are those of the local run.
    """
    conf = conf or ReconstructConfig()
    f, correction = conf.features, conf.correction.correction
    fconf = FeatureConf(f.matcher, f.num_keypoints, f.max_side, f.lightglue_precision)
    if correction not in SFM_CORRECTIONS:
        raise LocalScaleError(
            f"correction must be one of {', '.join(SFM_CORRECTIONS)} for reconstruction, got {correction!r}"
        )
    from ..matching import get_correction

    method = get_correction(correction)
    t_start = time.perf_counter()
    _check_extracted(features_path, pairs)
    sets = _keypoint_sets(images, features_path, keypoints_path, conf.mapping.merge_px, fresh=overwrite)
    stats, todo = _split_resumed(pairs, {} if overwrite else _done_pairs(matches_path))
    cameras = cameras_of(images, conf) if method.auto else None
    output = _MatchOutput(matches_path, keypoints_path, sets, {im.name: im for im in images}, overwrite, cameras)
    factory = PairRunnerFactory(
        tuple(images), str(features_path), fconf, method, device, *models, cameras=cameras,
        prune_mnn=conf.correction.prune_mnn,
    )  # fmt: skip
    runner, run_items = _pair_runs(factory, executor, show_progress) if todo else (None, None)
    if todo and method.auto and conf.correction.auto_graph:
        from ..matching.auto.collection import match_with_graph

        def apply(results, pairs):
            apply_in_order(results, pairs, sets, output, stats, flush_s)

        match_with_graph(run_items, todo, apply, stats, fconf.match_config().auto.same_log2)
    elif todo:
        apply_in_order(run_items(todo, f"match ({method})"), todo, sets, output, stats, flush_s)
    else:
        output.flush()
    if runner is not None:
        stats.feature_sets = runner.feature_sets
    stats.added_keypoints = sum(len(s) - s.num_base for s in sets.values())
    stats.seconds = time.perf_counter() - t_start
    if method.auto:
        unverified = [p for p in stats.pairs if p.verified is False]
        if unverified and len(unverified) == len(stats.pairs):
            warn(f"auto verified none of the {len(stats.pairs)} pairs: the images may not overlap")
    return stats


def _pair_runs(factory: PairRunnerFactory, executor, show_progress: bool) -> tuple:
    """``(the pair runner of this process or None, run_items)``: ``run_items(items, label)`` yields
    ``(index, PairResult or Exception)`` of work items, on the executor's workers when it is not local."""
    if executor is not None and executor.name != "local":

        def run_remote(items, label):
            progress_label = label if show_progress else None
            return executor.map(MatchPair(), items, state=factory, progress=progress_label, unit="pair")

        return None, run_remote
    runner = factory()

    def run_here(items, label):
        work = MatchPair()
        return (
            (i, work(runner, it)) for i, it in enumerate(progress(items, label, unit="pair", disable=not show_progress))
        )

    return runner, run_here


def _check_extracted(features_path, pairs) -> None:
    """Every image of ``pairs`` has its features in ``features_path`` (else :class:`H5FileError`)."""
    have = set(groups_with(features_path, "keypoints"))
    missing = sorted({n for p in pairs for n in p} - have)
    if missing:
        raise H5FileError(
            f"{features_path} lacks the features of {missing[0]}"
            f"{f' and {len(missing) - 1} more' if len(missing) > 1 else ''}: run the extraction first"
        )


def _split_resumed(pairs, done: dict):
    """``(stats holding the pairs already in done (either order), the pairs still to match)``."""
    stats = MatchStats()
    todo = []
    for a, b in pairs:
        key = names_to_pair(a, b) if names_to_pair(a, b) in done else names_to_pair(b, a)
        if key in done:
            stats.pairs.append(done[key])
            stats.resumed += 1
        else:
            todo.append((a, b))
    return stats, todo


def apply_in_order(results, todo, sets, output, stats: MatchStats, flush_s: float) -> None:
    """Add the ``(index, PairResult)`` of ``results`` (any order) to ``output`` and ``stats`` in pair
    order, so that the keypoint sets grow as in a run in this process; flush every ``flush_s`` seconds
    and at the end (also when interrupted: what was applied is kept). A failed pair ends the run."""
    last, pending, applied = time.monotonic(), {}, 0
    try:
        for i, result in results:
            if isinstance(result, Exception):
                raise result
            pending[i] = result
            while applied in pending:
                (a, b), r = todo[applied], pending.pop(applied)
                rows, mm, ss = _index_matches(sets, a, b, r.kp_a, r.kp_b, r.matches, r.scores)
                stats.pairs.append(output.add(a, b, mm, ss, r.verified, r.chosen, r.seconds, r.relation))
                if r.geometry is not None:
                    output.add_geometry(a, b, r, rows, mm)
                stats.matched += 1
                stats.feature_sets += r.computed
                applied += 1
            if time.monotonic() - last >= flush_s:
                output.flush()
                last = time.monotonic()
    finally:
        output.flush()


def _index_matches(sets: dict, a: str, b: str, kp_a, kp_b, m, scores):
    """The matches ``m`` of keypoints ``kp_a``, ``kp_b`` (full-image pixels) in the keypoint sets of A and
    B (new points added to them): ``((ia, ib) the set indices of each row of m, K x 2 matches with one
    match per keypoint, K scores)``."""
    ia = sets[a].index(kp_a[m[:, 0]]) if len(m) else np.zeros(0, np.int64)
    ib = sets[b].index(kp_b[m[:, 1]]) if len(m) else np.zeros(0, np.int64)
    mm, ss = one_to_one(ia, ib, scores[: len(m)]) if len(m) else (np.zeros((0, 2), np.int64), np.zeros(0, np.float32))
    return (ia, ib), mm, ss


class _MatchOutput:
    """``matches.h5`` and ``keypoints.h5`` being written: the matches of each pair added, and the
    keypoint sets of the images they touched, flushed together (keypoints first)."""

    def __init__(self, matches_path, keypoints_path, sets: dict, by_name: dict, fresh: bool, cameras=None):
        self.matches_path, self.keypoints_path = matches_path, keypoints_path
        self.sets, self.by_name, self.cameras = sets, by_name, cameras
        self.m_writer = H5Writer(matches_path, fresh=fresh)
        self.k_writer = H5Writer(keypoints_path, fresh=fresh)
        self.changed = set(by_name) if (fresh or not Path(keypoints_path).exists()) else set()

    def add(self, a: str, b: str, mm, ss, verified, chosen: str, seconds: float, relation=None) -> PairRecord:
        """Add the matches ``mm`` (scores ``ss``) of a pair matched in ``seconds``; returns its record."""
        self.changed.update((a, b))
        m0, s0 = matches0_from_matches(mm, ss, len(self.sets[a]))
        rec = PairRecord(a, b, int(len(mm)), verified, chosen, seconds, relation)
        attrs = {
            "num_matches": rec.num_matches,
            "chosen": chosen,
            "seconds": rec.seconds,
            "name0": a,
            "name1": b,
        }
        if verified is not None:
            attrs["verified"] = bool(verified)
        if relation is not None:
            attrs["relation"] = np.array([relation.scale, relation.turn, relation.strength], np.float64)
        self.m_writer.add(names_to_pair(a, b), {"matches0": m0, "matching_scores0": s0}, attrs)
        return rec

    def add_geometry(self, a: str, b: str, r, rows: tuple, mm) -> None:
        """Store the two-view geometry ``r.geometry`` of the pair's result ``r`` beside its written
        matches ``mm`` (``rows``, ``mm``: :func:`_index_matches` of ``r``'s matches): a written
        match is an inlier when a match of ``r`` that it stands for is one, and the inputs' sha1 is
        that of the written matches as the geometry step reads them (:func:`~.geometry.inputs_sha1`)."""
        from .geometry import MIN_INLIERS, inputs_sha1, matched_datasets
        from .h5io import matches_from_matches0

        g, m = r.geometry, np.asarray(r.matches, np.int64).reshape(-1, 2)
        if not len(mm):
            return
        width = len(self.sets[b]) + 1
        ia, ib = rows
        row_of = {(int(i), int(j)): k for k, (i, j) in enumerate(m)}
        inl = np.asarray(g.data["inlier_matches"], np.int64).reshape(-1, 2)
        inlier_rows = [row_of[(int(i), int(j))] for i, j in inl if (int(i), int(j)) in row_of]
        written, _ = matches_from_matches0(matches0_from_matches(mm, np.zeros(len(mm)), len(self.sets[a]))[0])
        codes = written[:, 0] * width + written[:, 1]
        if not np.isin(codes, ia * width + ib).all():
            return
        keep = np.isin(codes, ia[inlier_rows] * width + ib[inlier_rows])
        inliers = written[keep] if keep.sum() >= MIN_INLIERS else written[:0]
        digest = inputs_sha1(
            self.sets[a].keypoints, self.sets[b].keypoints, written, self.cameras.camera(a), self.cameras.camera(b)
        )
        data = dict(g.data, inlier_matches=inliers.astype(np.int32).reshape(-1, 2))
        datasets, attrs = matched_datasets(type(g)(g.config, data, digest))
        self.m_writer.extend(names_to_pair(a, b), datasets, attrs)

    def flush(self) -> None:
        """Write what was added: the changed keypoint sets, then the matches."""
        for n in sorted(self.changed):
            im = self.by_name[n]
            self.k_writer.add(
                n,
                {"keypoints": self.sets[n].keypoints, "image_size": np.array([im.shape[1], im.shape[0]], np.int64)},
                {"num_base": self.sets[n].num_base},
            )
        self.changed.clear()
        if self.k_writer.pending or not Path(self.keypoints_path).exists():
            self.k_writer.flush()  # first: the matches index only keypoints it holds
        if self.m_writer.pending or not Path(self.matches_path).exists():
            self.m_writer.flush()


def _done_pairs(matches_path) -> dict:
    out = {}
    for key in groups_with(matches_path, "matches0"):
        g = read_group(matches_path, key, ("matches0",))
        at = g["attrs"]
        a, b = str(at.get("name0", "")), str(at.get("name1", ""))
        v, rel = at.get("verified"), at.get("relation")
        out[key] = PairRecord(
            a,
            b,
            int(np.sum(g["matches0"] >= 0)),
            None if v is None else bool(v),
            str(at.get("chosen", "")),
            float(at.get("seconds", 0.0)),
            None if rel is None else Relation(float(rel[0]), int(rel[1]), int(rel[2])),
        )
    return out


def _keypoint_sets(images, features_path, keypoints_path, merge_px: float, fresh: bool) -> dict:
    """Every image's :class:`KeypointSet`: ``keypoints.h5``'s (a resumed run) or ``features.h5``'s."""
    have = set() if fresh else set(groups_with(keypoints_path, "keypoints"))
    extracted = set(groups_with(features_path, "keypoints"))
    sets = {}
    for im in images:
        base = (
            read_group(features_path, im.name, ("keypoints",))["keypoints"]
            if im.name in extracted
            else np.zeros((0, 2), np.float32)
        )
        s = KeypointSet(base, merge_px)
        if im.name in have:
            stored = read_group(keypoints_path, im.name, ("keypoints",))["keypoints"]
            if len(stored) < len(base) or not np.array_equal(stored[: len(base)], base):
                raise H5FileError(
                    f"{keypoints_path}: the keypoints of {im.name} do not start with those of "
                    f"{features_path} (written by another extraction): rerun with overwrite"
                )
            s.index(stored[len(base) :])
            if len(s) != len(stored):
                raise H5FileError(
                    f"{keypoints_path}: the keypoints of {im.name} were merged with another "
                    "merge distance: rerun with overwrite"
                )
        sets[im.name] = s
    return sets


def match_files(images_dir, out_dir, conf: Optional[ReconstructConfig] = None, device="cpu", **kw):
    """The match step from the files of ``out_dir``: ``features.h5`` and ``pairs.txt`` ->
    ``matches.h5`` and ``keypoints.h5`` (``kw``: :func:`~.match.match_pairs`'s)."""
    from .pairs import read_pairs

    out = Path(out_dir)
    conf = conf or ReconstructConfig()
    pairs = read_pairs(out / "pairs.txt")
    images = step_images(images_dir, out, conf, {n for p in pairs for n in p})
    return match_pairs(images, pairs, out / "features.h5", out / "matches.h5", out / "keypoints.h5", conf, device, **kw)


def main(argv=None) -> int:
    """``python -m localscale.sfm.match``: this step alone, from files (:func:`match_files`)."""
    p = parser(
        "match",
        __doc__,
        ("matcher", "max_side", "num_keypoints", "lightglue_precision", "correction", "prune_mnn", "merge_px"),
    )
    p.add_argument("images", help="folder of images")
    p.add_argument("out", help="folder with features.h5 and pairs.txt; matches.h5 and keypoints.h5 are written there")
    p.add_argument("--device", default="cpu", help="torch device")
    args = p.parse_args(argv)
    return run_step(lambda: match_files(args.images, args.out, config_of(args), args.device))


if __name__ == "__main__":
    raise SystemExit(main())
