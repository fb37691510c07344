"""``localscale predict --pairs``: many pairs, resumable, with an index of what happened to each."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from ..core.errors import LocalScaleError
from ..core.outputs import make_dir, resolved_path, write_text
from ..io.pairs_file import read_pairs_file
from ..maps.files import scale_map_paths, write_scale_map
from .common import _model, check_output_dir, image_labels, short_name
from .options import executor_from_args
from .signals import SIGTERM_STATE


def pairs_output_names(pairs: list[tuple]) -> list[str]:
    """``<index:05d>_<A>_<B>`` per pair: the index is the pair's position in the list (so it does
    not depend on which pairs fail) and the names come from :func:`image_labels` over all images."""
    labels = image_labels([p for pair in pairs for p in pair])
    return [
        short_name(f"{i:05d}_{labels[resolved_path(a)]}_{labels[resolved_path(b)]}") for i, (a, b) in enumerate(pairs)
    ]


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
    return {
        "image_a": _file_record(image_a),
        "image_b": _file_record(image_b),
        "weights": _file_record(weights),
        "hard": bool(args.hard),
        "planar": bool(args.planar),
        "bf16": bool(args.bf16),
    }


def _shown(text: str, room: int = 300) -> str:
    """``text`` for a message line: a very long path is cut, with its length."""
    return text if len(text) <= room else f"{text[: room // 2]}... ({len(text)} characters)"


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
    or an output cannot be written (a full disk: the run stops, a rerun resumes); 143 after a
    SIGTERM (the pair being written is finished first)."""
    run = _PairsRun(args, out)
    executor = executor_from_args(args)
    run.check_images()
    SIGTERM_STATE.defer()  # from here a SIGTERM stops the run after the pair it is on (main resets this)
    if executor is None:
        model = _model(args, "local")
        todo = run.resume(model)
        make_dir(out)
        run.predict(model, todo)
    else:
        with executor:
            from ..engine.pairs import driver_model

            factory = _factory(args)
            todo = run.resume(driver_model(executor, factory))
            make_dir(out)
            run.predict_on(executor, factory, todo)
    return run.finish(todo)


def _factory(args):
    from ..engine import ModelFactory

    weights = str(resolved_path(args.local_weights)) if args.local_weights else None  # every node reads it
    return ModelFactory("local", weights, args.device)


class _PairsRun:
    """The state of one ``predict --pairs`` run: its pairs, output names and each pair's status."""

    def __init__(self, args, out: Path):
        self.args, self.out = args, out
        self.rows = read_pairs_file(args.pairs, with_lines=True)
        self.pairs = [(a, b) for _, a, b in self.rows]
        self.names = pairs_output_names(self.pairs)
        self.paths = {n: scale_map_paths(out, n, True) + [out / f"{n}_scale.json"] for n in self.names}
        check_output_dir(out, ["index.tsv"] + [p.name for n in self.names for p in self.paths[n]])
        inputs = [Path(args.pairs)] + [p for pair in self.pairs for p in pair]
        taken = {resolved_path(p): p for p in inputs}  # resolved once: 10,000 pairs stay fast
        self.index_path = out / "index.tsv"
        for p in [self.index_path] + [p for n in self.names for p in self.paths[n]]:
            if resolved_path(p) in taken:
                raise LocalScaleError(f"refusing to overwrite the input {taken[resolved_path(p)]} with an output")
        self.status: dict = {}
        self.problems: dict = {}  # pair -> what is wrong with one of its images
        self.failed = self.written = 0
        self.done: set = set()
        self.stopped = self.terminated = None
        self.cache = None

    def where(self, i: int) -> str:
        line, a, b = self.rows[i]
        return f"pair {i} (line {line}) {_shown(str(a))} {_shown(str(b))}"

    def check_images(self) -> None:
        """Every image checked once, before any model is loaded; a pair with a bad image is a warning."""
        from ..io import check_image_file

        checked: dict = {}
        for i, (a, b) in enumerate(self.pairs):
            for p, which in ((a, "image A"), (b, "image B")):
                if (p, which) not in checked:
                    try:
                        check_image_file(p, which)
                        checked[p, which] = None
                    except LocalScaleError as e:
                        checked[p, which] = _pair_problem(e, a, b)
                if checked[p, which]:
                    self.problems.setdefault(i, checked[p, which])
        if len(self.problems) == len(self.pairs):
            n = len(self.pairs)
            more = f" (and {n - 1} more pair(s), all with a bad image)" if n > 1 else ""
            raise LocalScaleError(f"{self.args.pairs}: no pair can be run: {self.where(0)}: {self.problems[0]}{more}")
        for i, msg in self.problems.items():
            print(f"warning: {self.where(i)}: {msg}", file=sys.stderr)
        self.status = {i: (f"error: {msg}", "") for i, msg in self.problems.items()}
        self.failed = len(self.status)

    def resume(self, model) -> list:
        """The pairs to run: all but those with a bad image and those whose outputs are complete and
        were made from the same inputs (unless ``--overwrite``)."""
        from ..models.base import WEIGHTS_DIR

        args, out = self.args, self.out
        visible = bool(getattr(model.config, "visibility", False))
        weights = args.local_weights or WEIGHTS_DIR / getattr(model, "default_weights", "")  # the bundled file
        self.records = {
            i: _pair_record(a, b, weights, args) for i, (a, b) in enumerate(self.pairs) if i not in self.problems
        }
        self.done = (
            set()
            if args.overwrite
            else {
                i
                for i in self.records
                if _complete(
                    scale_map_paths(out, self.names[i], visible), self.paths[self.names[i]][-1], self.records[i]
                )
            }
        )
        self.status.update({i: ("skipped (outputs already complete)", self.names[i]) for i in self.done})
        return [i for i in self.records if i not in self.done]

    def predict(self, model, todo: list) -> None:
        """Predict and write the pairs ``todo``, in order; stops on an output error or a SIGTERM."""
        from tqdm import tqdm

        from ..cache import FeatureCache, predict_pairs

        args = self.args
        self.cache = FeatureCache(model, max_bytes=int(args.cache_mb * 2**20), bf16=args.bf16)
        results = predict_pairs(
            model, [self.pairs[i] for i in todo], self.cache, args.batch_size, hard=args.hard, planar=args.planar
        )
        for i, (_, pred) in zip(todo, tqdm(results, total=len(todo), desc="pairs", unit="pair", disable=None)):
            if not self.write(i, pred):
                break
            if SIGTERM_STATE.requested and i != todo[-1]:
                self.stopped = self.terminated = "terminated by SIGTERM"
                break

    def predict_on(self, executor, factory, todo: list) -> None:
        """:meth:`predict` on an executor: pairs come back in the order they finish."""
        from tqdm import tqdm

        from ..engine import PairStats, predict_pairs_with

        args, stats = self.args, PairStats()
        results = predict_pairs_with(
            executor,
            [self.pairs[i] for i in todo],
            factory,
            bf16=args.bf16,
            hard=args.hard,
            planar=args.planar,
            stats=stats,
        )
        handled = 0
        for j, pred in tqdm(results, total=len(todo), desc="pairs", unit="pair", disable=None):
            handled += 1
            if not self.write(todo[j], pred):
                break
            if SIGTERM_STATE.requested and handled < len(todo):
                self.stopped = self.terminated = "terminated by SIGTERM"
                break
        self.engine_summary = stats.summary()

    def write(self, i: int, pred) -> bool:
        """Write pair ``i``'s prediction (or record its failure); False when the run must stop."""
        from tqdm import tqdm

        from ..core.errors import OutputError

        _, a, b = self.rows[i]
        name = self.names[i]
        if not isinstance(pred, Exception):
            try:
                write_scale_map(pred, self.out, name, (self.args.pairs, a, b))  # all inputs were checked above
                write_text(
                    self.paths[name][-1], json.dumps(self.records[i], indent=1) + "\n"
                )  # last: marks it complete
            except LocalScaleError as e:
                pred = e
        if not isinstance(pred, Exception):
            self.written += 1
            self.status[i] = ("ok", name)
            return True
        self.failed += 1
        msg = _pair_problem(pred, a, b)
        self.status[i] = (f"error: {msg}", "")
        tqdm.write(f"warning: {self.where(i)}: {msg}", file=sys.stderr)
        if isinstance(pred, OutputError):  # a full disk or a read-only folder: the next pairs would fail too
            self.stopped = msg
            return False
        return True

    def finish(self, todo: list) -> int:
        """Write ``index.tsv``, print the summary; the exit code."""
        n, index_path = len(self.pairs), self.index_path
        for i in todo:
            self.status.setdefault(i, (f"not run (stopped: {self.stopped})", ""))
        if not self.written and not self.done and self.failed == n:
            raise LocalScaleError(f"{self.args.pairs}: all {n} pairs failed (see the warnings above); nothing written")
        lines = ["index\tline\timage_a\timage_b\tstatus\toutput"]
        lines += [
            f"{i}\t{line}\t{a}\t{b}\t{self.status[i][0]}\t{self.status[i][1]}"
            for i, (line, a, b) in enumerate(self.rows)
        ]
        make_dir(self.out)
        write_text(index_path, "\n".join(lines) + "\n")
        c = self.cache
        if getattr(self, "engine_summary", None):
            print(f"engine: {self.engine_summary}", file=sys.stderr)
        print(
            f"{n} pairs: {self.written} written, {len(self.done)} skipped (outputs already complete; --overwrite "
            f"redoes them), {self.failed} failed; outputs in {self.out} (index: {index_path}; cache: "
            f"{c.misses if c else 0} images encoded, {c.hits if c else 0} reused)"
        )
        if self.terminated:
            left = sum(self.status[i][0].startswith("not run") for i in todo)
            print(
                f"stopped: {self.terminated} after {self.written} written pair(s), {left} not run; every written "
                f"output is complete, a rerun resumes (see {index_path})",
                file=sys.stderr,
            )
            return 143
        if self.stopped:
            raise LocalScaleError(
                f"stopped after {self.written} written pair(s): {self.stopped}; a rerun resumes (see {index_path})"
            )
        if self.failed:
            print(f"warning: {self.failed} of {n} pairs failed, see {index_path}", file=sys.stderr)
        return 1 if self.failed else 0
