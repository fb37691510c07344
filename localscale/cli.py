"""``localscale`` command line; every command mirrors a Python API call.

    localscale predict A B -o out/                # LocalScaleNet.predict  -> .npy, float TIFF, colour PNG
    localscale predict --pairs pairs.txt -o out/  # predict_pairs with the feature cache (+ out/index.tsv)
    localscale show A B -o out/ [--H H_a_b]       # viz.plot_scale_prediction -> out/<A>_<B>_figure.png
    localscale demo [-o out/]                     # show on the bundled example pair
    localscale scale A B                          # ScaleNet.predict (global scale)
    localscale rectify A B -o out/                # resize one image by the global scale (+ JSON sidecar)
    localscale match A B -o out/ --correction local
    localscale eval-hpatches ROOT -o out/

Every command takes the same model options: ``--local-weights`` / ``--global-weights``
(checkpoints; default: the bundled weights), ``--device`` and, where a network runs, ``--bf16``.
``-o`` is always an output folder. Bad input is a one-line ``error: ...`` and exit code 2.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import shlex
import signal
import sys
import threading
from collections import Counter, defaultdict
from pathlib import Path
from typing import TYPE_CHECKING

from .cli_options import (HelpFormatter, OneLineErrorParser, _LazyArgumentParser, add_hpatches_options,  # noqa: F401
                          add_match_options, add_model_options, add_refine_matcher_options, add_refine_options,
                          nonnegative_int, positive_float, positive_int)
from . import loading
from .errors import LocalScaleError
from .loading import MODEL_KINDS, load_scale_model  # noqa: F401
from .map_files import scale_map_paths, write_refinement, write_scale_map  # noqa: F401
from .outputs import ensure_not_input, make_dir, resolved_path, write_image, write_npy, write_npy_bands, write_text  # noqa: F401

if TYPE_CHECKING:
    import numpy as np

# numpy, torch, OpenCV and the models are imported inside the commands that use them, so that
# ``localscale --help`` (and argument errors) return without loading them.

ASSETS = Path(__file__).resolve().parent / "assets"   #: the example pair (also in examples/)


# ---------------------------------------------------------------- models, paths

def _model(args, kind: str):
    return loading.load_scale_model(kind, getattr(args, f"{kind}_weights", None), args.device)


def check_output_dir(path, names=()) -> Path:
    """``-o``: a folder (created later, when writing). Checked before any work: an existing file,
    a folder that cannot be written, or file ``names`` too long for the file system are errors."""
    from .outputs import check_writable_dir

    return check_writable_dir(Path(path), names)


def image_labels(paths, always_parent: bool = False) -> dict:
    """Short, distinct names of image files for output names: the stem, or ``<parent>-<stem>``
    when another file among ``paths`` has the same stem (``v_churchill/1.ppm`` ->
    ``v_churchill-1``) or when ``always_parent``. Keyed by the resolved path."""
    uniq = list(dict.fromkeys(resolved_path(p) for p in paths))
    by_stem = defaultdict(list)
    for p in uniq:
        by_stem[p.stem].append(p)

    def with_parent(p: Path, name: str) -> str:
        return f"{p.parent.name}-{name}" if p.parent.name else name

    labels = {p: with_parent(p, p.stem) if (always_parent or len(ps) > 1) else p.stem
              for ps in by_stem.values() for p in ps}
    counts = Counter(labels.values())
    for p in uniq:   # same folder and stem, other extension
        if counts[labels[p]] > 1:
            labels[p] = with_parent(p, p.name.replace(".", "-"))
    return labels


def short_name(name: str, room: int = 200) -> str:
    """``name`` unchanged if it has at most ``room`` bytes, else its start and a hash of it
    (output file names stay within the file system's 255-byte limit)."""
    raw = name.encode("utf-8", "surrogateescape")
    if len(raw) <= room:
        return name
    digest = hashlib.sha1(raw).hexdigest()[:10]
    return raw[:room - 11].decode("utf-8", "ignore") + "~" + digest


def pair_name(image_a, image_b, always_parent: bool = False) -> str:
    """``<A>_<B>`` from :func:`image_labels` (``A_B`` for arrays); shortened by :func:`short_name`
    when too long for a file name."""
    if hasattr(image_a, "shape") or hasattr(image_b, "shape"):
        return "A_B"
    labels = image_labels([image_a, image_b], always_parent)
    return short_name(f"{labels[resolved_path(image_a)]}_{labels[resolved_path(image_b)]}")


# ---------------------------------------------------------------- predict

PAIRS_FORMAT = ("one pair per line: 'A<TAB>B' (each field taken as written: spaces, '#' and quotes are part "
                "of the name), or 'A B' with shell-like quoting (\"my photo.jpg\" 'b #2.png'); lines "
                "starting with '#' and blank lines are skipped; relative paths are relative to the file's folder")


def _parse_pairs_line(line: str) -> list[str]:
    if "\t" in line:
        return [f for f in line.split("\t") if f != ""]
    return shlex.split(line, comments=False, posix=True)


def read_pairs_file(path: str | Path, with_lines: bool = False) -> list[tuple]:
    """Read a pairs file: :data:`PAIRS_FORMAT`.

    Returns ``[(A, B), ...]``, or ``[(line_number, A, B), ...]`` with ``with_lines``. Bad lines
    (not two fields, unbalanced quotes, not UTF-8) are all reported, by number, in one
    :class:`LocalScaleError`; so is a pairs file that cannot be read or is not a regular file
    (a named pipe or a device would block the read). A UTF-8 byte order mark at the start is dropped.
    """
    import stat

    path = Path(path)
    try:
        mode = path.stat().st_mode
        if not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):   # a folder: the read below says so
            kind = ("a named pipe" if stat.S_ISFIFO(mode) else "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode)
                    else "a socket" if stat.S_ISSOCK(mode) else "a special file")
            raise LocalScaleError(f"pairs file is not a regular file ({kind}): {path}")
        data = path.read_bytes()
    except OSError as e:
        import errno

        what = {errno.ENOENT: "pairs file not found", errno.ELOOP: "pairs file is a symbolic link loop",
                errno.EISDIR: "pairs file is a folder", errno.EACCES: "pairs file is not readable (permission denied)",
                errno.ENAMETOOLONG: "pairs file name too long"}.get(e.errno, f"cannot read pairs file ({e.strerror})")
        if e.errno == errno.ENOENT and path.is_symlink():
            what = "pairs file is a broken symbolic link"
        raise LocalScaleError(f"{what}: {path}") from None
    if data.startswith(b"\xef\xbb\xbf"):   # UTF-8 byte order mark (some editors write one)
        data = data[3:]
    pairs, bad = [], []
    for n, raw in enumerate(data.split(b"\n"), 1):
        try:
            line = raw.decode("utf-8")
        except UnicodeDecodeError as e:
            bad.append((n, f"not UTF-8 text (byte 0x{raw[e.start]:02x} at column {e.start + 1})"))
            continue
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        try:
            parts = _parse_pairs_line(line.rstrip("\r"))
        except ValueError as e:
            bad.append((n, f"{e} (quote paths with spaces: \"a b.jpg\", or separate the two paths by a TAB)"))
            continue
        if len(parts) != 2:
            bad.append((n, f"expected two image paths, got {len(parts)} field(s)"))
            continue
        if any("\0" in p for p in parts):
            bad.append((n, "a path contains a NUL character"))
            continue
        pair = tuple((path.parent / p) if not Path(p).is_absolute() else Path(p) for p in parts)
        pairs.append((n, *pair) if with_lines else pair)
    if bad:
        more = f" (and {len(bad) - 1} more bad line(s): {', '.join(str(n) for n, _ in bad[1:6])}" \
               f"{'...' if len(bad) > 6 else ''})" if len(bad) > 1 else ""
        raise LocalScaleError(f"{path}:{bad[0][0]}: {bad[0][1]}{more}")
    if not pairs:
        raise LocalScaleError(f"{path}: no pairs in the file ({PAIRS_FORMAT})")
    return pairs


def pairs_output_names(pairs: list[tuple]) -> list[str]:
    """``<index:05d>_<A>_<B>`` per pair: the index is the pair's position in the list (so it does
    not depend on which pairs fail) and the names come from :func:`image_labels` over all images."""
    labels = image_labels([p for pair in pairs for p in pair])
    return [short_name(f"{i:05d}_{labels[resolved_path(a)]}_{labels[resolved_path(b)]}") for i, (a, b) in enumerate(pairs)]


def cmd_predict(args) -> int:
    out = check_output_dir(args.output)
    if args.pairs:
        if args.image_a or args.image_b:
            raise LocalScaleError("predict: give two images A B or --pairs FILE, not both")
        if getattr(args, "refine", False):
            raise LocalScaleError("predict: --refine works on one pair A B, not with --pairs")
        if args.search:
            raise LocalScaleError("predict: --search works on one pair A B, not with --pairs")
        return _predict_pairs(args, out)
    if getattr(args, "refine", False) and args.refine_passes < 1:
        raise LocalScaleError(f"--refine-passes must be >= 1, got {args.refine_passes}")
    if args.matcher != "hardnet":
        from .features.matchers import MATCHERS

        if args.matcher not in MATCHERS:
            raise LocalScaleError(f"predict: --matcher {args.matcher!r}: not a matcher ({', '.join(MATCHERS)})")
        if not getattr(args, "refine", False):
            raise LocalScaleError(f"predict: --matcher {args.matcher} is the matcher of --refine; add --refine")
        if args.search:
            raise LocalScaleError("predict: --search refines with the hardnet matcher; drop --matcher")
    if not (args.image_a and args.image_b):
        raise LocalScaleError("predict: give two images A B, or --pairs FILE")
    inputs = (args.image_a, args.image_b)
    check_output_dir(out, [p.name for p in scale_map_paths(out, pair_name(*inputs), True)])
    from .reliability import check_pair

    model = _model(args, "local")
    if args.search and (args.hard or args.planar):
        raise LocalScaleError("predict: --search uses the soft read-out; drop --hard/--planar")
    check = check_pair(model, args.image_a, args.image_b, bf16=args.bf16, hard=args.hard, planar=args.planar)
    pred = check.forward
    if args.search:
        from .search import search_scale_map

        found = search_scale_map(model, args.image_a, args.image_b, bf16=args.bf16)
        pred = found.prediction
        print(f"search: {found.candidates} window pairs scored; kept {found.kept()} "
              f"(score {found.score:.1f}, whole images {found.base_score:.1f})", file=sys.stderr)
    for p in write_scale_map(pred, out, pair_name(*inputs), inputs):
        print(p)
    import numpy as np

    s = pred.sampled("scale")
    print(f"S(A->B): median {np.median(s):.3f}, min {s.min():.3f}, max {s.max():.3f}", file=sys.stderr)
    if not check.reliable:
        scope = " (checked on the whole images)" if args.search else ""
        print(f"warning: this scale map is unreliable{scope}: {'; '.join(check.reasons)}", file=sys.stderr)
    if getattr(args, "refine", False) and args.matcher != "hardnet":
        from .features.pipeline import match_pair

        options = {"refine": True} | ({"weights": args.matcher_weights} if args.matcher_weights else {})
        res = match_pair(args.image_a, args.image_b, "auto", None, model, None, args.matcher, **options)
        v = res.verification
        extra = {k: res.meta[k] for k in ("passes", "inlier_counts", "seed_inliers")} | {"auto": res.meta["auto"]}
        for p in write_refinement(out, pair_name(*inputs) + "_", res.refined_a, None, extra, inputs):
            print(p)
        state = "verified" if v.verified else f"not verified ({'; '.join(v.reasons)}), network map kept"
        print(f"refine: {args.matcher} auto chose {res.meta['auto']['chosen']}; {v.model} with {v.num_inliers} "
              f"inliers, {state}", file=sys.stderr)
    elif getattr(args, "refine", False):
        from .features.correction import CorrectionGate
        from .features.pipeline import refine_match

        back = check.backward
        if args.search:   # B's map from its own search, as the searched correction of match does
            back = search_scale_map(model, args.image_b, args.image_a, bf16=args.bf16).prediction
        first_a, first_b = CorrectionGate().apply_predictions(pred, back)
        res = refine_match(args.image_a, args.image_b, first_a, first_b, pred.scale, back.scale,
                           max_passes=args.refine_passes, sift_seed=args.refine_seed == "sift")
        v = res.verification
        for p in write_refinement(out, pair_name(*inputs) + "_", res.refined_a, None,
                                  {k: res.meta[k] for k in ("passes", "inlier_counts", "seed_inliers")}, inputs):
            print(p)
        state = "verified" if v.verified else f"not verified ({'; '.join(v.reasons)}), network map kept"
        print(f"refine: {v.model} with {v.num_inliers}/{len(v.inliers)} inliers, {state}", file=sys.stderr)
    return 0


def _complete(paths: list[Path], record_path: Path | None = None, record: dict | None = None) -> bool:
    """True when every output file of a pair exists (files are written atomically, so an existing
    file is complete), its ``.npy`` files have a readable header and, with ``record_path``, the
    record of what made them (:func:`_pair_record`, written last) equals ``record``."""
    import numpy as np

    try:
        for p in paths:
            if not p.is_file():
                return False
            if p.suffix == ".npy":
                np.load(p, mmap_mode="r")
        if record_path is not None and json.loads(record_path.read_text(encoding="utf-8")) != record:
            return False
    except (OSError, ValueError):
        return False
    return True


def _file_record(path) -> dict:
    """An input file as a rerun recognises it: resolved path, size and modification time."""
    p = resolved_path(path)
    try:
        st = p.stat()
    except OSError:
        return {"path": str(p), "bytes": None, "mtime_ns": None}
    return {"path": str(p), "bytes": st.st_size, "mtime_ns": st.st_mtime_ns}


def _pair_record(image_a, image_b, weights, args) -> dict:
    """What a pair's maps were made from: both images, the weights and the read-out options.
    Written beside the maps (``<name>_scale.json``); a rerun redoes a pair whose record differs."""
    return {"image_a": _file_record(image_a), "image_b": _file_record(image_b), "weights": _file_record(weights),
            "hard": bool(args.hard), "planar": bool(args.planar), "bf16": bool(args.bf16)}


def _shown(text: str, room: int = 300) -> str:
    """``text`` for a message line: a very long path is cut, with its length."""
    return text if len(text) <= room else f"{text[:room // 2]}... ({len(text)} characters)"


def _pair_problem(e: Exception, a, b) -> str:
    msg = " ".join(str(e).split())
    for p in (str(a), str(b)):
        if len(p) > 300:
            msg = msg.replace(p, _shown(p))
    return msg


def _predict_pairs(args, out: Path) -> int:
    """``predict --pairs``: resumable. Pairs whose outputs are complete and were made from the same
    images (size and modification time), weights and read-out options are skipped (unless
    ``--overwrite``); ``index.tsv`` lists every pair's status; the summary counts pairs written,
    skipped and failed.

    Every input path is checked (one ``stat`` each) before the model is loaded. A pair that fails
    gets a ``warning:`` line and its reason in ``index.tsv``; the other pairs still run. Exit code
    0 when no pair failed, 1 when some did (last line: ``N of M pairs failed, see index.tsv``), 2
    (one ``error:`` line) when the pairs file cannot be used, every pair failed (nothing written)
    or an output cannot be written (a full disk: the run stops, a rerun resumes)."""
    from tqdm import tqdm

    from .cache import FeatureCache, predict_pairs
    from .errors import OutputError
    from .io import check_image_file

    rows = read_pairs_file(args.pairs, with_lines=True)
    pairs = [(a, b) for _, a, b in rows]
    names = pairs_output_names(pairs)
    paths = {n: scale_map_paths(out, n, True) + [out / f"{n}_scale.json"] for n in names}
    check_output_dir(out, ["index.tsv"] + [p.name for n in names for p in paths[n]])
    inputs = [Path(args.pairs)] + [p for pair in pairs for p in pair]
    taken = {resolved_path(p): p for p in inputs}   # resolved once: 10,000 pairs stay fast
    index_path = out / "index.tsv"
    for p in [index_path] + [p for n in names for p in paths[n]]:
        if resolved_path(p) in taken:
            raise LocalScaleError(f"refusing to overwrite the input {taken[resolved_path(p)]} with an output")

    def where(i: int) -> str:
        line, a, b = rows[i]
        return f"pair {i} (line {line}) {_shown(str(a))} {_shown(str(b))}"

    checked: dict = {}
    problems: dict = {}   # pair -> what is wrong with one of its images
    for i, (a, b) in enumerate(pairs):   # before any model is loaded
        for p, which in ((a, "image A"), (b, "image B")):
            if (p, which) not in checked:
                try:
                    check_image_file(p, which)
                    checked[p, which] = None
                except LocalScaleError as e:
                    checked[p, which] = _pair_problem(e, a, b)
            if checked[p, which]:
                problems.setdefault(i, checked[p, which])
    if len(problems) == len(pairs):
        more = f" (and {len(pairs) - 1} more pair(s), all with a bad image)" if len(pairs) > 1 else ""
        raise LocalScaleError(f"{args.pairs}: no pair can be run: {where(0)}: {problems[0]}{more}")
    for i, msg in problems.items():
        print(f"warning: {where(i)}: {msg}", file=sys.stderr)
    status = {i: (f"error: {msg}", "") for i, msg in problems.items()}
    failed = len(status)
    model = _model(args, "local")
    visible = bool(getattr(model.config, "visibility", False))
    from .models.base import WEIGHTS_DIR

    weights = args.local_weights or WEIGHTS_DIR / getattr(model, "default_weights", "")   # the bundled file
    records = {i: _pair_record(a, b, weights, args) for i, (a, b) in enumerate(pairs) if i not in problems}
    done = set() if args.overwrite else {
        i for i in records if _complete(scale_map_paths(out, names[i], visible), paths[names[i]][-1], records[i])}
    status.update({i: ("skipped (outputs already complete)", names[i]) for i in done})
    todo = [i for i in records if i not in done]
    make_dir(out)
    cache = FeatureCache(model, max_bytes=int(args.cache_mb * 2**20), bf16=args.bf16)
    written, stopped = 0, None
    results = predict_pairs(model, [pairs[i] for i in todo], cache, args.batch_size, hard=args.hard,
                            planar=args.planar)
    for i, (_, pred) in zip(todo, tqdm(results, total=len(todo), desc="pairs", unit="pair", disable=None)):
        _, a, b = rows[i]
        if not isinstance(pred, Exception):
            try:
                write_scale_map(pred, out, names[i], (args.pairs, a, b))   # all inputs were checked above
                write_text(paths[names[i]][-1], json.dumps(records[i], indent=1) + "\n")   # last: marks it complete
            except LocalScaleError as e:
                pred = e
        if isinstance(pred, Exception):
            failed += 1
            msg = _pair_problem(pred, a, b)
            status[i] = (f"error: {msg}", "")
            tqdm.write(f"warning: {where(i)}: {msg}", file=sys.stderr)
            if isinstance(pred, OutputError):   # a full disk or a read-only folder: the next pairs would fail too
                stopped = msg
                break
        else:
            written += 1
            status[i] = ("ok", names[i])
    for i in todo:
        status.setdefault(i, (f"not run (stopped: {stopped})", ""))
    if not written and not done and failed == len(pairs):
        raise LocalScaleError(f"{args.pairs}: all {len(pairs)} pairs failed (see the warnings above); nothing written")
    lines = ["index\tline\timage_a\timage_b\tstatus\toutput"]
    lines += [f"{i}\t{line}\t{a}\t{b}\t{status[i][0]}\t{status[i][1]}" for i, (line, a, b) in enumerate(rows)]
    make_dir(out)
    write_text(index_path, "\n".join(lines) + "\n")
    print(f"{len(pairs)} pairs: {written} written, {len(done)} skipped (outputs already complete; --overwrite "
          f"redoes them), {failed} failed; outputs in {out} (index: {index_path}; cache: {cache.misses} images "
          f"encoded, {cache.hits} reused)")
    if stopped:
        raise LocalScaleError(f"stopped after {written} written pair(s): {stopped}; a rerun resumes (see {index_path})")
    if failed:
        print(f"warning: {failed} of {len(pairs)} pairs failed, see {index_path}", file=sys.stderr)
    return 1 if failed else 0


# ---------------------------------------------------------------- show, demo

#: images larger than this (longer side) are shown, and predicted for the figure, at this size
SHOW_MAX_SIDE = 2048


def show_pair(image_a, image_b, output, H=None, model=None, title=None, bf16: bool = False) -> Path:
    """Predict and write the figure (A, B, scale factor map, confidence, and GT/error when ``H`` is
    given) to the file ``output``; returns its path."""
    import numpy as np

    from .geometry import covisible_mask, homography_scale_map
    from .io import load_working_image, read_homography
    from .viz import plot_scale_prediction

    output = ensure_not_input(output, (image_a, image_b, H))
    model = model or loading.load_scale_model("local")
    a, to_a = load_working_image(image_a, SHOW_MAX_SIDE, "image A")   # a figure needs no more pixels
    b, to_b = load_working_image(image_b, SHOW_MAX_SIDE, "image B")
    pred = model.predict(a, b, bf16=bf16)
    gt = mask = None
    if H is not None:
        Hm = to_b @ read_homography(H) @ np.linalg.inv(to_a)
        gt = homography_scale_map(Hm, *a.shape[:2])
        mask = covisible_mask(Hm, a.shape[:2], b.shape[:2])
    make_dir(Path(output).parent)
    try:
        plot_scale_prediction(a, b, pred.scale, pred.confidence, gt, mask, output, title,
                              visible=getattr(pred, "visible", None))
    except (OSError, ValueError) as e:
        raise LocalScaleError(f"cannot write figure {output}: {e}") from None
    return Path(output)


def cmd_show(args) -> int:
    name = f"{pair_name(args.image_a, args.image_b)}_figure.png"
    out = check_output_dir(args.output, [name])
    fig = ensure_not_input(out / name, (args.image_a, args.image_b, args.H))
    print(show_pair(args.image_a, args.image_b, fig, args.H, _model(args, "local"), bf16=args.bf16))
    return 0


def cmd_demo(args) -> int:
    a, b, H = ASSETS / "kodim01_a.jpg", ASSETS / "kodim01_b.jpg", ASSETS / "H_a_b.txt"
    out = check_output_dir(args.output, ["demo.png"]) / "demo.png"
    show_pair(a, b, out, H, _model(args, "local"), title="localscale demo: Local-ScaleNet", bf16=args.bf16)
    print(out)
    return 0


# ---------------------------------------------------------------- scale, rectify

def cmd_scale(args) -> int:
    if args.search:
        from .search import search_global_scale

        p, found = search_global_scale(_model(args, "local"), _model(args, "global"), args.image_a, args.image_b,
                                       bf16=args.bf16)
        print(f"search: {found.candidates} window pairs scored; ScaleNet on {found.kept()}",
              file=sys.stderr)
    else:
        p = _model(args, "global").predict(args.image_a, args.image_b, bf16=args.bf16)
    import numpy as np

    if not (all(math.isfinite(v) for v in (p.scale, p.scale_ab, p.scale_ba, p.hard_scale))
            and np.isfinite(p.probs_ab).all()):
        raise LocalScaleError("ScaleNet predicted a non-finite scale (NaN or inf): the model is broken")
    if not p.reliable:
        print(f"warning: the global scale is unreliable: A->B {p.scale_ab:.3f} and 1/(B->A) {1 / p.scale_ba:.3f} "
              f"disagree by x{2 ** p.inconsistency_log2:.2f}", file=sys.stderr)
    if any(p.turns):
        which = "A" if p.turns[0] else "B"
        print(f"warning: the upright images gave inconsistent scales; this one comes from {which} turned by "
              f"{90 * max(p.turns)} deg", file=sys.stderr)
    if args.json:
        print(json.dumps(allow_nan=False, obj={"scale": p.scale, "scale_ab": p.scale_ab, "scale_ba": p.scale_ba,
                          "hard_scale": p.hard_scale, "reliable": p.reliable, "turns": list(p.turns),
                          "inconsistency_log2": p.inconsistency_log2, "probs_ab": p.probs_ab.round(4).tolist()}))
    else:
        print(f"S(A->B) = {p.scale:.4f}  (A->B {p.scale_ab:.4f}, 1/(B->A) {1 / p.scale_ba:.4f}, "
              f"D-ScaleNet {p.hard_scale:.4f})")
    return 0


def rectify_pair(image_a, image_b, output, model=None, bf16: bool = False) -> dict:
    """Downscale the image whose content is bigger by the global scale so the pair has scale ~1.

    Writes ``<output>/<A>_<B>_rectified_<A|B>.png`` (``<A>``, ``<B>`` = ``<parent>-<stem>``, so pairs
    of different sequences do not collide) and ``<A>_<B>_rectified.json`` (scale, which image was
    resized, factor, sizes, paths); returns that record.
    """
    import cv2

    from .io import image_shape, load_image_reduced

    name = pair_name(image_a, image_b, always_parent=True)
    out = check_output_dir(output, [f"{name}_rectified_A.png", f"{name}_rectified.json"])
    inputs = (image_a, image_b)
    for which in "AB":
        ensure_not_input(out / f"{name}_rectified_{which}.png", inputs)
    model = model or loading.load_scale_model("global")
    s = float(model.predict(image_a, image_b, bf16=bf16).scale)
    if not (math.isfinite(s) and s > 0):
        raise LocalScaleError(f"ScaleNet predicted a non-finite scale ({s}): the model is broken; nothing written")
    which, factor = ("B", 1 / s) if s > 1 else ("A", s)
    src = image_b if which == "B" else image_a
    h, w = image_shape(src, f"image {which}")
    size = (max(1, round(w * factor)), max(1, round(h * factor)))
    img, (h, w) = load_image_reduced(src, f"image {which}", max(size))   # decoded no larger than needed
    resized = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
    dst = ensure_not_input(out / f"{name}_rectified_{which}.png", inputs)
    sidecar = ensure_not_input(out / f"{name}_rectified.json", inputs)
    make_dir(out)
    write_image(dst, resized[..., ::-1])
    record = {"image_a": "array" if hasattr(image_a, "shape") else str(image_a),
              "image_b": "array" if hasattr(image_b, "shape") else str(image_b),
              "scale": s, "resized": which, "resized_image": "array" if hasattr(src, "shape") else str(src),
              "factor": factor, "size_before": [w, h], "size_after": list(size),
              "output": str(dst)}
    write_text(sidecar, json.dumps(record, indent=1) + "\n")
    record["sidecar"] = str(sidecar)
    return record


def cmd_rectify(args) -> int:
    name = pair_name(args.image_a, args.image_b, always_parent=True)
    check_output_dir(args.output, [f"{name}_rectified_A.png", f"{name}_rectified.json"])
    r = rectify_pair(args.image_a, args.image_b, args.output, _model(args, "global"), bf16=args.bf16)
    print(f"S(A->B) = {r['scale']:.4f}: image {r['resized']} resized by {r['factor']:.4f} -> {r['output']} "
          f"(record: {r['sidecar']})")
    return 0


# ---------------------------------------------------------------- match

#: options of ``match`` that only the patch matcher (``--matcher hardnet``) reads
PATCH_OPTIONS = ("descriptor", "descriptor_precision", "detector", "orientation", "ratio")


def match_options(args) -> dict:
    """The :class:`~localscale.features.matchers.MatchConfig` fields that ``match`` / ``eval-hpatches``
    options set (options left at None keep the matcher's own values)."""
    opts = {}
    for name in ("num_features", "max_side", "pyramid"):
        v = getattr(args, name, None)
        if v is not None:
            opts[name] = v or None if name == "max_side" else v
    if getattr(args, "matcher_weights", None) is not None:
        opts["weights"] = args.matcher_weights
    for name in PATCH_OPTIONS:
        v = getattr(args, name, None)
        if v is not None:
            opts[name] = v
    if getattr(args, "bf16", False):
        opts["bf16"] = True
    return opts


def cmd_match(args) -> int:
    from .features.correction import get_correction, models_for_correction
    from .features.matchers import MATCHERS, match_config
    from .features.pipeline import get_matcher, run_match

    out = check_output_dir(args.output, ["matches.npz", "matches.png"])
    for f in ("matches.npz", "matches.png"):
        ensure_not_input(out / f, (args.image_a, args.image_b, args.H))
    from .devices import resolve_device

    resolve_device(args.device)
    opts = match_options(args)
    if args.matcher != "hardnet":
        used = [f"--{n.replace('_', '-')}" for n in PATCH_OPTIONS if getattr(args, n, None) is not None]
        if used:
            raise LocalScaleError(f"{', '.join(used)}: only the hardnet matcher takes patch options, "
                                  f"not --matcher {args.matcher}")
    if args.matcher == "hardnet" and getattr(args, "matcher_weights", None) is not None:
        raise LocalScaleError("--matcher-weights: the hardnet matcher uses our bundled weights "
                              "(--descriptor PATH for other HardNet weights)")
    refine = getattr(args, "refine", False)
    opts.update(refine=refine, max_passes=args.refine_passes, sift_seed=args.refine_seed == "sift")
    cfg = match_config(MATCHERS[args.matcher], **opts)
    needs = get_correction(args.correction).models
    for kind in MODEL_KINDS:
        if getattr(args, f"{kind}_weights", None) is not None and kind not in needs:
            print(f"note: --{kind}-weights is not used by --correction {args.correction}", file=sys.stderr)
    matcher = get_matcher(cfg)   # loads the matcher's weights: a missing file fails before the scale models load
    local_model, global_model = models_for_correction(args.correction, args.local_weights, args.global_weights,
                                                      args.device)
    run_match(args.image_a, args.image_b, out, args.correction, args.H, local_model, global_model, matcher)
    return 0


def cmd_eval_hpatches(args) -> int:
    from .evaluation.hpatches import gate_from_args, load_hpatches, load_scale_models, make_pairs, result_tag, run
    from .features.matchers import MATCHERS, match_config
    from .features.pipeline import get_matcher

    opts = match_options(args)
    opts.pop("max_side", None)                  # one working resolution for every matcher, below
    if getattr(args, "base_radius", None) is not None:
        opts["base_radius"] = args.base_radius
    patch_opts = {k: opts.pop(k) for k in list(opts) if k in PATCH_OPTIONS + ("base_radius",)}
    if patch_opts and "hardnet" not in args.matcher:
        raise LocalScaleError(f"--{', --'.join(k.replace('_', '-') for k in patch_opts)}: only the hardnet matcher "
                              f"takes patch options")
    gate = gate_from_args(args)
    configs = [match_config(MATCHERS[n], gate=gate, **opts, **(patch_opts if n == "hardnet" else {}))
               for n in dict.fromkeys(args.matcher)]
    tags = [result_tag(c) for c in configs]
    check_output_dir(args.out, ["splits.csv", "results.md"] + [f"results_{t}.{e}" for t in tags for e in ("json", "md")]
                     + [f"mma_{t}_rot30-90.png" for t in tags])
    from .devices import resolve_device

    resolve_device(args.device)
    matchers = [get_matcher(c) for c in configs]   # a missing weight file fails before any pair runs
    seqs = load_hpatches(args.root, args.include_illumination, args.exclude_hires, args.exclude, args.sequences)
    if args.pairs is not None:
        for s in seqs:
            s.homographies = {k: H for k, H in s.homographies.items() if k in args.pairs}
            s.bad = {k: v for k, v in s.bad.items() if k in args.pairs}
    skipped: list = []
    pairs = make_pairs(seqs, skipped)
    if not pairs:
        raise LocalScaleError(f"no pair of {args.root} can be evaluated ({len(skipped)} skipped; first: "
                              f"{skipped[0]['pair']}: {skipped[0]['reason']})" if skipped else
                              f"no pairs in {args.root}")
    methods = list(dict.fromkeys(args.methods))
    models, notes = load_scale_models(methods, args.local_weights, args.global_weights, args.device)
    if not methods:
        raise LocalScaleError(f"none of the methods {list(args.methods)} can run: {'; '.join(notes)}")
    for n in notes:
        print("note:", n)
    print(f"{len(seqs)} sequences, {len(pairs)} pairs; matchers {[m.name for m in matchers]}; methods {methods}")
    run(pairs, methods, matchers, args.out, models, notes, skipped, args.max_side,
        extra={"gate": vars(gate), "args": {k: v for k, v in vars(args).items() if not callable(v)}})
    print(f"wrote {args.out}/")
    return 0


# ---------------------------------------------------------------- parser

EXAMPLES = {
    "predict": """examples:
  localscale predict examples/kodim01_a.jpg examples/kodim01_b.jpg -o out/
      -> out/kodim01_a_kodim01_b_scale.{npy,tif,png}, _confidence.npy
  localscale predict --pairs pairs.txt -o out/ --batch-size 8
  localscale predict wide.jpg closeup.jpg -o out/ --search     (strong zoom or low overlap)
  localscale predict examples/kodim01_a.jpg examples/kodim01_b.jpg -o out/ --refine
      -> also out/<A>_<B>_refined_scale.npy, _refined_source.npy, _geometry.json
  localscale predict A.jpg B.jpg -o out/ --refine --matcher aliked-lightglue   (geometry from auto)
      pairs.txt: one pair per line, 'A<TAB>B' (names as written) or 'A B' with shell-like
      quoting ("my photo.jpg" b.jpg); relative to the file's folder; lines starting with '#'
      are comments. A rerun skips pairs whose outputs are complete and whose images, weights
      and options are unchanged (--overwrite redoes them).
      -> out/<index>_<A>_<B>_scale.* (index = the pair's position in the file; <A> is
         <folder>-<stem> when stems collide; _scale.json records the inputs) and out/index.tsv
         (index, line, A, B, status, output). A bad pair is a 'warning:' line and exit code 1,
         the other pairs still run; a pairs file with no usable pair is an 'error:', exit 2.""",
    "show": """example:
  localscale show seq/1.ppm seq/2.ppm --H seq/H_1_2 -o figures/
      -> figures/1_2_figure.png""",
    "demo": """example:
  localscale demo -o out/      -> out/demo.png""",
    "scale": """example:
  localscale scale examples/kodim01_a.jpg examples/kodim01_b.jpg --json
  localscale scale wide.jpg closeup.jpg --search     (strong zoom or low overlap)""",
    "rectify": """example:
  localscale rectify v_churchill/1.ppm v_churchill/2.ppm -o out/
      -> out/v_churchill-1_v_churchill-2_rectified_B.png (the resized image) and
         out/v_churchill-1_v_churchill-2_rectified.json (scale, resized image, factor, sizes)""",
    "match": """example:
  localscale match examples/kodim01_a.jpg examples/kodim01_b.jpg -o out/ --correction fused \\
      --H localscale/assets/H_a_b.txt --num-features 500
      -> out/matches.npz, out/matches.png""",
    "eval-hpatches": """example:
  localscale eval-hpatches hpatches-sequences-release/ -o results/hpatches --methods none local gt
      ROOT/<seq>/1.ppm .. 6.ppm and H_1_2 .. H_1_6; writes results_<descriptor>.{json,md},
      splits.csv and mma_*.png into -o
  localscale eval-hpatches ROOT -o out/ --methods none local --detector orb
      -> out/results_orb_<descriptor>.{json,md}: the same with one-level ORB keypoints""",
}


def build_parser() -> argparse.ArgumentParser:
    p = OneLineErrorParser(prog="localscale", description=__doc__, formatter_class=HelpFormatter)
    from . import __version__
    p.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=_LazyArgumentParser)

    def command(name, summary, description, add_options=None):
        return sub.add_parser(name, help=summary, description=description, epilog=EXAMPLES[name],
                              formatter_class=HelpFormatter, add_options=add_options)

    sp = command("predict", "per-pixel scale map S(A->B) -> .npy/.tif/.png",
                 "Per-pixel scale map S(A->B) of Local-ScaleNet for one pair (A B) or for every pair of a\n"
                 "pairs file (--pairs, with a feature cache: each image is encoded once).")
    sp.add_argument("image_a", nargs="?", help="image A (omit with --pairs)")
    sp.add_argument("image_b", nargs="?", help="image B (omit with --pairs)")
    sp.add_argument("-o", "--output", default="out", help="output folder")
    sp.add_argument("--pairs", help="text file with one pair per line: 'A<TAB>B', or 'A B' with shell-like "
                                    "quoting for names with spaces (default: none, predict A B)")
    sp.add_argument("--hard", action="store_true", help="D-ScaleNet (arg-max bin) read-out")
    sp.add_argument("--planar", action="store_true", help="fit a homography's scale field (planar scenes only)")
    sp.add_argument("--search", action="store_true",
                    help="window search: re-estimate on the windows of A or B (1/2, 1/4 of the sides) that share "
                         "the most content with the other image; for strong zooms and low overlap, ~30x slower")
    sp.add_argument("--batch-size", type=positive_int, default=8, help="pairs per network batch with --pairs")
    sp.add_argument("--cache-mb", type=positive_float, default=256, help="feature cache bound (MiB) with --pairs")
    sp.add_argument("--overwrite", action="store_true",
                    help="with --pairs: redo pairs whose outputs already exist (default: skip them)")
    add_refine_matcher_options(add_refine_options(sp))
    add_model_options(sp, local=True, global_=False, model_alias="local")
    sp.set_defaults(func=cmd_predict)

    sp = command("show", "figure: A, B, predicted map, confidence (+ GT and error with --H)",
                 "Figure of a pair: A, B, the predicted scale map S(A->B) (colours = factors), the\n"
                 "confidence, and with --H the ground-truth map and the error.")
    sp.add_argument("image_a", help="image A")
    sp.add_argument("image_b", help="image B")
    sp.add_argument("-o", "--output", default="out", help="output folder (figure <A>_<B>_figure.png)")
    sp.add_argument("--H", help="ground-truth homography A->B (3x3 text file; default: none)")
    add_model_options(sp, local=True, global_=False, model_alias="local")
    sp.set_defaults(func=cmd_show)

    sp = command("demo", "run show on the bundled example pair and write out/demo.png",
                 "The figure of 'show' on the bundled example pair (with its ground-truth homography).")
    sp.add_argument("-o", "--output", default="out", help="output folder (demo.png)")
    add_model_options(sp, local=True, global_=False, model_alias="local")
    sp.set_defaults(func=cmd_demo)

    sp = command("scale", "global scale S(A->B) with ScaleNet",
                 "Global scale S(A->B) of ScaleNet: consistency-checked, both directions, D-ScaleNet.")
    sp.add_argument("image_a", help="image A")
    sp.add_argument("image_b", help="image B")
    sp.add_argument("--json", action="store_true", help="print one JSON object")
    sp.add_argument("--search", action="store_true",
                    help="run ScaleNet on the window pair Local-ScaleNet's window search keeps (see predict --search): "
                         "strong zoom, low overlap; ~30x slower")
    add_model_options(sp, local=True, global_=True, model_alias="global")
    sp.set_defaults(func=cmd_scale)

    sp = command("rectify", "resize one image by the global scale so the pair has scale ~1",
                 "Downscale the image whose content is bigger by ScaleNet's global scale, so that the\n"
                 "pair has scale ~1; writes the resized image and a JSON record of what was done.")
    sp.add_argument("image_a", help="image A")
    sp.add_argument("image_b", help="image B")
    sp.add_argument("-o", "--output", default="out", help="output folder")
    add_model_options(sp, local=False, global_=True, model_alias="global")
    sp.set_defaults(func=cmd_rectify)

    sp = command("match", "match two images: our scale-corrected patches, SIFT, ALIKED/DISK/XFeat + LightGlue",
                 "Match two images with a matcher (--matcher) and a scale correction (--correction): our\n"
                 "scale-corrected patches (hardnet: the patch size of each keypoint follows the scale map),\n"
                 "or SIFT / learned features on a pair rectified to scale 1 (the image whose content is\n"
                 "bigger is shrunk by the correction's level).", add_options=add_match_options)
    sp.set_defaults(func=cmd_match)

    sp = command("eval-hpatches", "HPatches-style MMA evaluation",
                 "HPatches-style mean matching accuracy of the correction methods on a folder of sequences.",
                 add_options=add_hpatches_options)
    sp.set_defaults(func=cmd_eval_hpatches)
    return p


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread so that files being written are cleaned up."""


def _on_sigterm(signum, frame):
    raise Terminated()


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args = build_parser().parse_args(argv)
    previous = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGTERM, _on_sigterm)
    try:
        return args.func(args)
    except Terminated:
        print("terminated; no partial output file was left (a rerun of predict --pairs resumes)", file=sys.stderr)
        return 143
    except LocalScaleError as e:
        print(f"error: {' '.join(str(e).split())}", file=sys.stderr)
        return 2
    except OSError as e:   # a file the command reads or writes (e.g. a full disk, no permission)
        where = f"{e.filename}: " if e.filename else ""
        print(f"error: {where}{e.strerror or e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted; no partial output file was left", file=sys.stderr)
        return 130
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


if __name__ == "__main__":
    sys.exit(main())
