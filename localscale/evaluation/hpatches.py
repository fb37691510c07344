"""HPatches-style matching evaluation with and without patch-size correction.

Layout: ``<root>/<seq>/1.ppm .. 6.ppm`` (also ``.png`` / ``.jpg``) and ``H_1_2 .. H_1_6``;
``v_*`` (viewpoint) and ``i_*`` (illumination) sequences as in HPatches, or folders
without a prefix (e.g. the Oxford ``bark``, ``boat``...). ``i_*`` sequences are skipped by
default (``--include-illumination``); ``--exclude-hires`` drops the usual high-resolution
sequences :data:`HIGH_RES`.

Protocol (D2-Net's MMA): for each pair ``(1, k)``: the single-scale Hessian detector's
top-K keypoints (default 1000; ``--detector`` swaps in another single-scale detector of
:data:`localscale.features.detector.DETECTORS`) in both images, 32x32 patches with the patch-size
correction of each method, descriptors, mutual nearest neighbours, and the
mean matching accuracy MMA@t = fraction of matches with ``|H x_A - x_B| < t`` px
(t = 1..10), averaged over pairs; plus mean numbers of matches and features.

Methods: ``none``, ``global`` (ScaleNet), ``local`` (Local-ScaleNet, gated), ``gt``
(analytic map of the GT homography), ``gt_gated`` (the GT map through the same gate as
``local``, to measure what gating costs an oracle), ``pyramid`` (optional baseline: no scale maps,
keypoints detected and described on a 4-level image pyramid with step sqrt(2)... 2),
``refined`` (the ``local`` maps, matching, verification with a MAGSAC homography, maps refined by
the verified geometry and a second matching pass; when the first pass is not verified, the
``opencv-sift`` matches are verified instead and their geometry refines the maps;
:func:`localscale.matching.refine_passes`),
``opencv-sift`` (baseline: OpenCV's DoG detector, top-K keypoints, OpenCV SIFT descriptors,
mutual nearest neighbours that pass Lowe's ratio test 0.8).

Homography accuracy (every method): a homography estimated from the method's matches with OpenCV
``USAC_MAGSAC`` (3 px), the mean error of A's four corners against the ground truth
(:func:`localscale.matching.corner_error`), its AUC at 3 / 5 / 10 px over the pairs
and the share of pairs solved (corner error < 10 px).

Splits, from the GT homography of each pair:

* perspective: ``spread`` = std of ``log2`` of the analytic scale map over the co-visible
  region (:func:`localscale.geometry.perspective_spread`): ``easy`` < 0.1 <= ``medium``
  < 0.25 <= ``hard``;
* global scale: ``g = |log2 global_scale|`` (geometric mean of the map over the co-visible
  region): ``scale<1.4x`` for g < 0.5, ``scale1.4-2.8x`` for 0.5 <= g < 1.5, ``scale>2.8x``.

Predicted maps go through :class:`localscale.matching.CorrectionGate` (default pair level 0.25;
``docs/decisions/correction-gate-weighting.md``). Compare gates with ``--gate-pair X [--no-consistency]``.

Outputs in ``--out``: ``results.json`` (per-pair records, summaries, splits), ``splits.csv``
(the split of every pair), ``results.md`` (tables) and ``mma_<split>.png`` plots.
"""

from __future__ import annotations

import re
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

import cv2
import numpy as np

from ..core.errors import LocalScaleError
from ..io import load_image
from ..matching import CORRECTIONS, GATE_WEIGHTINGS  # noqa: F401
from .pairs import (  # noqa: F401
    HIGH_RES,
    IMAGE_EXTS,
    MIN_AGREEMENT,
    MIN_COVISIBLE,
    HSequence,
    PairInfo,
    _warn,
    content_agreement,
    image_size,
    load_hpatches,
    make_pairs,
)
from .report import (  # noqa: F401
    THRESHOLDS,
    matching_table,
    perspective_split,
    rotation_split,
    scale_split,
    summarise,
    write_outputs,
)

METHODS = CORRECTIONS  #: the correction methods (one registry: localscale.matching.correction)


class _PairScales:
    """The maps of the correction methods for the pairs of a run, sharing the networks' work:
    each image is encoded once while it is in the current pair (image 1 of a sequence is in
    every pair of it), each pair's global scale and local maps are predicted once (``global`` and
    ``fused`` share ScaleNet's, ``local``, ``fused`` and ``refined`` the local maps). Each map
    keeps the seconds it took, so the time of a method is what it costs on its own."""

    def __init__(self, local_model, global_model, gate):
        self.local_model, self.global_model, self.gate = local_model, global_model, gate
        self._enc, self._genc, self._memo, self._maps = {}, {}, {}, {}
        self._pair = None

    def start(self, pair: PairInfo, a: np.ndarray, b: np.ndarray) -> None:
        """Begin a pair (its images at the working resolution); drops what other images kept."""
        self._pair, self._images = pair, {pair.image_a: a, pair.image_b: b}
        keep = set(self._images)
        self._enc = {k: v for k, v in self._enc.items() if k[0] in keep}
        self._genc = {k: v for k, v in self._genc.items() if k[0] in keep}
        self._memo, self._maps = {}, {}

    def _key(self, path):
        return (path, self._images[path].shape)

    def encoding(self, path):
        k = self._key(path)
        if k not in self._enc:
            self._enc[k] = self.local_model.encode_image(self._images[path])
        return self._enc[k]

    def global_encoding(self, path):
        k = self._key(path)
        if k not in self._genc:
            self._genc[k] = self.global_model.encode_image(self._images[path], "image")
        return self._genc[k]

    def once(self, key, fn):
        if key not in self._memo:
            self._memo[key] = fn()
        return self._memo[key]

    def maps(self, method, H) -> tuple:
        """``(map of A, map of B, seconds)`` of a :class:`~localscale.matching.Correction` (:meth:`~.Correction.maps`)."""
        pair = self._pair
        a, b = self._images[pair.image_a], self._images[pair.image_b]
        key = (method.name, a.shape, b.shape)
        if key not in self._maps:
            t0 = time.perf_counter()
            enc = (self.encoding(pair.image_a), self.encoding(pair.image_b)) if method.local_encodings else None
            # other local uses (the search) make and drop many encodings: keyed by id(), the shared
            # cache could mix them up
            local = (
                None
                if "local" not in method.models
                else (_SharedLocal(self, self.local_model) if method.local_encodings else self.local_model)
            )
            glob = _SharedGlobal(self, self.global_model, pair) if "global" in method.models else None
            sa, sb = method.maps(a, b, H, local, glob, self.gate, enc)
            self._maps[key] = (sa, sb, time.perf_counter() - t0)
        return self._maps[key]


def _evaluate_pair(
    matcher, scales: _PairScales, pair: PairInfo, a, b, fa: float, fb: float, methods, thresholds
) -> list[dict]:
    """The records of one pair and one matcher: each method's maps, matches, MMA and corner error."""
    from ..matching import (
        get_correction,
        match_auto,
        match_refined,
        match_result,
        match_with_truth,
        matching_accuracy,
        reprojection_errors,
    )

    H = np.diag([fb, fb, 1.0]) @ pair.H @ np.diag([1 / fa, 1 / fa, 1.0])
    key_a, key_b = (str(pair.image_a), a.shape), (str(pair.image_b), b.shape)
    recs = []
    for m in methods:
        method = get_correction(m)
        sa, sb, map_seconds = scales.maps(method, H)
        t0 = time.perf_counter()
        extra = {}
        if method.auto:
            keyed = _Keyed(matcher, key_a, key_b)
            res = match_auto(keyed, a, b, scales.local_model, scales.global_model, H, method, (key_a, key_b))
            auto = res.meta["auto"]
            extra = {"verified": bool(auto["verified"]), "chosen": auto["chosen"], "trials": auto["trials"]}
            seconds = time.perf_counter() - t0 - keyed.wall + keyed.standalone
        elif method.refine or matcher.config.refine:
            keyed = _Keyed(matcher, key_a, key_b)
            res = match_refined(keyed, a, b, sa, sb, None, None, H, method)
            extra = {
                "verified": bool(res.verification.verified),
                "passes": res.meta["passes"],
                "inlier_counts": res.meta["inlier_counts"],
                "seed_inliers": res.meta["seed_inliers"],
            }
            # every pass's matching on its own, plus verification and refinement
            seconds = time.perf_counter() - t0 - keyed.wall + keyed.standalone
        else:
            found = match_with_truth(matcher, a, b, sa, sb, H, method, (key_a, key_b))
            res = match_result(matcher, found, H, method)
            seconds = found.seconds
        ka, kb, idx = res.keypoints_a, res.keypoints_b, res.matches
        err = reprojection_errors(ka, kb, idx, H)
        mma = matching_accuracy(err, thresholds)
        recs.append(
            {
                "pair": pair.name,
                "matcher": matcher.name,
                "method": m,
                "num_features_a": int(len(ka)),
                "num_features_b": int(len(kb)),
                "num_matches": int(len(idx)),
                "num_correct_3px": int((err < 3).sum()),
                "num_correct_5px": int((err < 5).sum()),
                "mma": [float(v) for v in mma],
                "corner_error": homography_corner_error(ka, kb, idx, H, a.shape),
                "factors": res.meta["factors"],
                "seconds": round(seconds, 3),
                "scale_seconds": round(map_seconds, 3),
                "perspective_split": pair.perspective_split,
                "scale_split": pair.scale_split,
                "rotation_split": pair.rotation_split,
                **extra,
            }
        )
    return recs


class _Keyed:
    """A matcher whose ``match`` passes the cache keys of the pair's two images."""

    def __init__(self, matcher, key_a, key_b):
        self._m, self._keys = matcher, (key_a, key_b)
        self.config, self.name, self.extractor = matcher.config, matcher.name, matcher.extractor
        self.wall = self.standalone = 0.0  #: seconds spent in match, and what they cost on their own

    def match(self, a, b, scale_a=None, scale_b=None, keys=None, max_side=None):
        t0 = time.perf_counter()
        found = self._m.match(a, b, scale_a, scale_b, self._keys if keys is None else keys, max_side=max_side)
        self.wall += time.perf_counter() - t0
        self.standalone += found.seconds
        return found


def homography_corner_error(keypoints_a, keypoints_b, matches, H_true, shape_a) -> float:
    """Corner error (px of B) of the homography estimated from the matches (``USAC_MAGSAC``, 3 px);
    ``inf`` when none can be estimated."""
    from ..matching import corner_error, estimate_homography

    m = np.asarray(matches, np.int64).reshape(-1, 2)
    H_est, _ = estimate_homography(np.asarray(keypoints_a)[m[:, 0]], np.asarray(keypoints_b)[m[:, 1]])
    return corner_error(H_est, H_true, shape_a)


class _SharedLocal:
    """The local model for one pair: ``predict_from_features`` of an ordered pair of encodings runs once."""

    def __init__(self, scales: _PairScales, model):
        self._scales, self._model = scales, model

    def predict_from_features(self, ea, eb, **kw):
        key = ("local", id(ea), id(eb), tuple(sorted(kw.items())))
        return self._scales.once(key, lambda: self._model.predict_from_features(ea, eb, **kw))

    def __getattr__(self, name):
        return getattr(self._model, name)


class _SharedGlobal:
    """The global model for one pair: each image is encoded once per run (while it is in the current
    pair), the pair's prediction is made once. ``predict(a, b)`` is ``predict_from_features`` of the
    two encodings with :meth:`ScaleNet.retry_turned`, as in :meth:`ScaleNet.predict`."""

    def __init__(self, scales: _PairScales, model, pair: PairInfo):
        self._scales, self._model, self._pair = scales, model, pair

    def predict(self, image_a, image_b, bf16: bool = False):
        sc, pair = self._scales, self._pair
        if image_a is not sc._images[pair.image_a] or image_b is not sc._images[pair.image_b] or bf16:
            return self._model.predict(image_a, image_b, bf16=bf16)

        def predict():
            ea, eb = sc.global_encoding(pair.image_a), sc.global_encoding(pair.image_b)
            first = self._model.predict_from_features(ea, eb, False)
            return self._model.retry_turned(first, image_a, image_b, ea, eb, False)

        return sc.once(("global", image_a.shape, image_b.shape), predict)

    def __getattr__(self, name):
        return getattr(self._model, name)


def evaluate(
    pairs: list[PairInfo],
    methods=("none", "gt"),
    matcher="hardnet",
    local_model=None,
    global_model=None,
    max_side: Optional[int] = None,
    thresholds=THRESHOLDS,
    progress: bool = True,
    executor=None,
    **options,
) -> dict:
    """Run the protocol on ``pairs`` with one matcher; returns ``{"records", "summary", "skipped",
    "suspicious"}``.

    Args:
        methods: names of :data:`localscale.matching.CORRECTIONS`.
        matcher: a name of :data:`localscale.matching.MATCHERS`, a ``MatchConfig`` or a ``Matcher``.
        local_model, global_model: the models the methods need.
        max_side: working resolution of every image (longer side; None: the matcher's own; 0: full size).
        executor: an :class:`~localscale.engine.Executor` other than the local one evaluates the pairs on
            its workers (each with its own matcher and the models, shipped once); the records are the same.
        **options: ``MatchConfig`` fields replacing the matcher's (``descriptor="sift"``, ``num_features``, ``gate``).
    """
    from ..matching import get_correction, get_matcher

    for m in methods:
        needs = get_correction(m).models
        if "local" in needs and local_model is None:
            raise LocalScaleError(f"method '{m}' needs a local model")
        if "global" in needs and global_model is None:
            raise LocalScaleError(f"method '{m}' needs a global model")
    if max_side is not None:
        options["max_side"] = max_side or None  # 0: full resolution
    if options and hasattr(matcher, "config"):  # a built Matcher with other options: rebuilt
        from ..matching import Matcher, match_config

        matcher = Matcher(match_config(matcher.config, **options), matcher.device)
        options = {}
    matcher = get_matcher(matcher, **options)
    work = EvaluatePair(tuple(methods), tuple(thresholds))
    label = f"eval {result_tag(matcher.config)}" if progress else None
    if executor is None or executor.name == "local":
        state = (matcher, _PairScales(local_model, global_model, matcher.config.gate))
        results = _in_process(work, state, pairs, label)
    else:
        factory = EvaluationState(matcher.config, str(matcher.device), local_model, global_model)
        results = executor.map(work, pairs, state=factory, progress=label, unit="pair")
    by_pair, skipped, suspicious = {}, {}, {}
    for i, result in results:
        p = pairs[i]
        if isinstance(result, LocalScaleError):  # e.g. an image that is truncated after its header
            reason = " ".join(str(result).split())
            _warn(f"pair {p.name} skipped: {reason}")
            skipped[i] = {"pair": p.name, "reason": reason}
            continue
        records, agreement = result
        if agreement < MIN_AGREEMENT:
            suspicious[p.name] = round(agreement, 3)
            _warn(
                f"pair {p.name}: image {p.k} warped by H_1_{p.k} does not look like image 1 "
                f"(correlation {agreement:.2f}); check that H and the image sizes belong together"
            )
        by_pair[i] = records
    records = [r for i in sorted(by_pair) for r in by_pair[i]]
    done = [pairs[i] for i in sorted(by_pair)]
    return {
        "matcher": matcher.name,
        "records": records,
        "summary": summarise(records, done, methods, list(thresholds)),
        "skipped": [skipped[i] for i in sorted(skipped)],
        "suspicious": suspicious,
    }


def _in_process(work, state, pairs, label):
    """``(index, records or the LocalScaleError)`` of every pair, in order, in this process."""
    from tqdm import tqdm

    for i, p in enumerate(tqdm(pairs, desc=label, disable=label is None, mininterval=5)):
        try:
            yield i, work(state, p)
        except LocalScaleError as e:
            yield i, e


@dataclass(frozen=True)
class EvaluationState:
    """Worker state of :func:`evaluate` on an executor: the matcher of ``config`` and the pair's map cache."""

    config: Any
    device: str = "cpu"
    local_model: Any = None
    global_model: Any = None

    def __call__(self):
        from ..matching import Matcher

        return Matcher(self.config, self.device), _PairScales(self.local_model, self.global_model, self.config.gate)


@dataclass(frozen=True)
class EvaluatePair:
    """Work of one pair: ``(its records for every method, the content agreement of the two images under H)``."""

    methods: tuple
    thresholds: tuple

    def __call__(self, state, p: PairInfo):
        matcher, scales = state
        side = matcher.config.max_side
        a, fa = _resize(load_image(p.image_a), side)
        b, fb = _resize(load_image(p.image_b), side)
        H = np.diag([fb, fb, 1.0]) @ p.H @ np.diag([1 / fa, 1 / fa, 1.0])
        agreement = content_agreement(a, b, H)
        scales.start(p, a, b)
        return _evaluate_pair(matcher, scales, p, a, b, fa, fb, self.methods, list(self.thresholds)), agreement


def _resize(img: np.ndarray, max_side: Optional[int]) -> tuple[np.ndarray, float]:
    if not max_side or max(img.shape[:2]) <= max_side:
        return img, 1.0
    f = max_side / max(img.shape[:2])
    return cv2.resize(img, (round(img.shape[1] * f), round(img.shape[0] * f)), interpolation=cv2.INTER_AREA), f


def load_scale_models(methods: list, local_weights=None, global_weights=None, device: str = "cpu") -> tuple[dict, list]:
    """Load the models the ``methods`` need (:func:`localscale.loading.load_scale_model`); a method
    whose bundled weights cannot be loaded is removed from ``methods`` (in place) with a note.
    Returns ``({"local"|"global": model}, notes)``."""
    from ..core.devices import resolve_device
    from ..core.errors import CheckpointError
    from ..loading import load_scale_model
    from ..matching import get_correction

    models, notes = {}, []
    device = resolve_device(device)
    for kind, w in (("local", local_weights), ("global", global_weights)):
        users = [m for m in methods if kind in get_correction(m).models]
        if not users:
            continue
        try:
            models[kind] = load_scale_model(kind, w, device)
            if w:
                notes.append(f"{kind}: weights {w}")
        except CheckpointError as e:
            if w is not None:  # weights the user named must load
                raise
            for x in users:
                methods.remove(x)
            notes.append(f"{', '.join(users)} skipped: {e}")
    return models, notes


def gate_from_args(args):
    """``CorrectionGate`` with the ``--gate-*`` / ``--no-consistency`` options a parser defined."""
    from ..matching import CorrectionGate

    gate = CorrectionGate()
    if getattr(args, "gate_pair", None) is not None:
        gate.min_pair_log2 = args.gate_pair
    if getattr(args, "gate_deadzone", None) is not None:
        gate.deadzone_log2 = args.gate_deadzone
    if getattr(args, "gate_min_confidence", None) is not None:
        gate.min_confidence = args.gate_min_confidence
    if getattr(args, "gate_weighting", None) is not None:
        gate.weighting = args.gate_weighting
    gate.consistency = not getattr(args, "no_consistency", False)
    return gate


def result_tag(config) -> str:
    """The name of a matcher's results files: the matcher's name, with the descriptor and
    detector of the hardnet matcher when they are not its defaults (``hardnet-sift``, ``hardnet-orb``)."""
    tag = config.name
    conf, defaults = config.extractor_conf, config.extractor_class.default_conf
    if "detector" in conf and conf["detector"] != defaults["detector"]:
        tag += f"-{conf['detector']}"
    if "descriptor" in conf:
        d = conf["descriptor"] if isinstance(conf["descriptor"], str) else getattr(conf["descriptor"], "name", "custom")
        d = d if d in ("hardnet", "sift") else Path(d).stem
        tag += f"-{d}" if d != defaults["descriptor"] else ""
    return re.sub(r"[^A-Za-z0-9_.-]", "_", tag)


def run(
    pairs: list[PairInfo],
    methods: list,
    configs: list,
    out,
    models: dict,
    notes: list,
    skipped: list,
    max_side: Optional[int] = None,
    extra: Optional[dict] = None,
    executor=None,
) -> dict:
    """Evaluate every matcher config on ``pairs`` and write the results into ``out``:
    ``results_<tag>.{json,md}`` and ``mma_<tag>_*.png`` per matcher, ``splits.csv``, and
    ``results.md`` (all matchers' tables). Returns ``{tag: results}``."""
    out = Path(out)
    docs, tables = {}, []
    for cfg in configs:
        res = evaluate(pairs, methods, cfg, models.get("local"), models.get("global"), max_side, executor=executor)
        res["skipped"] = skipped + res["skipped"]
        if res["skipped"]:
            _warn(f"{len(res['skipped'])} pair(s) skipped (listed under 'skipped' in the results)")
        conf = getattr(cfg, "config", cfg)
        tag = result_tag(conf)
        flat = {k: v for k, v in vars(conf).items() if k != "extractor_conf"} | conf.extractor_conf
        cfg_doc = {k: (v if isinstance(v, (str, int, float, bool, type(None))) else str(v)) for k, v in flat.items()}
        write_outputs(
            res, pairs, methods, out, tag=tag, extra={"notes": notes, "matcher_config": cfg_doc, **(extra or {})}
        )
        table = matching_table(res["summary"], methods, list(THRESHOLDS), tag)
        print(table)
        tables.append(table)
        docs[tag] = res
    from ..core.outputs import write_text

    write_text(out / "results.md", "\n".join(tables))
    return docs
