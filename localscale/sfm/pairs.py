"""The pairs step: the image pairs to match (``pairs.txt``, hloc's format: ``name_a name_b`` per line).

Which pairs (:func:`pairs_rule`, from :class:`~.config.PairsConfig`): ``auto`` (the default) is
every pair up to :data:`AUTO_EXHAUSTIVE_MAX` images and each image with its :data:`AUTO_NEAREST`
nearest beyond (``pairs_nearest`` sets that number, and then applies whatever the number of
images); ``exhaustive`` is every pair; any other value is a pairs file.

* :func:`pairs_exhaustive`: every pair (hloc's ``pairs_from_exhaustive``);
* :func:`pairs_from_file`: a pairs file (:mod:`localscale.io.pairs_file`) of names or of image paths,
  checked against the images;
* :func:`pairs_from_retrieval`: each image with its ``N`` nearest by a cheap global descriptor,
  the local descriptors of ``features.h5`` aggregated (GeM of the L2-normalised descriptors,
  then normalised), compared by cosine similarity; both directions, as one pair.

Example::

    pairs = pairs_from_retrieval(images, "out/features.h5", num_nearest=10)
    write_pairs("out/pairs.txt", pairs)
"""

from __future__ import annotations

import itertools
import shlex
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from ..core.errors import LocalScaleError
from ..core.outputs import write_text
from ..io.pairs_file import PairsFileError, read_pairs_lines
from .config import PairsConfig, ReconstructConfig
from .h5io import read_group
from .steps import config_of, parser, run_step

#: ``auto``: every pair up to this many images (docs/decisions/retrieval-pairs-default.md)
AUTO_EXHAUSTIVE_MAX = 100
#: ``auto`` beyond :data:`AUTO_EXHAUSTIVE_MAX` images: each image with this many nearest by retrieval
AUTO_NEAREST = 30


@dataclass(frozen=True)
class PairsRule:
    """The pairs a run matches: ``rule`` is ``exhaustive`` (every pair), ``retrieval`` (each image
    with its ``nearest`` most similar, :func:`pairs_from_retrieval`) or ``file``."""

    rule: str
    nearest: Optional[int] = None

    def __str__(self) -> str:
        return f"retrieval ({self.nearest} nearest)" if self.rule == "retrieval" else self.rule


def pairs_rule(p: PairsConfig, num_images: int) -> PairsRule:
    """The :class:`PairsRule` of ``p`` for ``num_images`` images: a pairs file; with
    ``pairs_nearest``, retrieval with that many nearest; ``exhaustive``; ``auto``: every pair up to
    :data:`AUTO_EXHAUSTIVE_MAX` images, retrieval with :data:`AUTO_NEAREST` nearest beyond."""
    if p.pairs not in ("auto", "exhaustive"):
        return PairsRule("file")
    if p.pairs_nearest:
        return PairsRule("retrieval", int(p.pairs_nearest))
    if p.pairs == "exhaustive" or num_images <= AUTO_EXHAUSTIVE_MAX:
        return PairsRule("exhaustive")
    return PairsRule("retrieval", AUTO_NEAREST)


def pairs_exhaustive(names: list) -> list:
    """Every unordered pair of ``names``, in name order."""
    return list(itertools.combinations(sorted(names), 2))


def _unique(pairs) -> list:
    seen, out = set(), []
    for a, b in pairs:
        if a == b:
            continue
        key = (a, b) if a < b else (b, a)
        if key not in seen:
            seen.add(key)
            out.append((a, b))
    return out


def pairs_from_file(path, names: list, images_dir=None) -> list:
    """The pairs of a pairs file: one pair per line, ``A<TAB>B`` or ``A B`` (quote a name with
    spaces, as in a shell); blank lines and ``#`` comments ignored. A field is an image name (its
    path relative to the images folder, as in ``pairs.txt``), or, with ``images_dir``, a path
    (relative to the pairs file's folder) of an image in that folder. A pair repeated (in either
    order) is kept once; a pair of an image with itself is dropped.

    Raises:
        PairsFileError: the file is missing or not text, a line is not two names, a name is not
            one of ``names`` (e.g. an image that was skipped as unreadable), or no pair is left.
    """
    path = Path(path)
    known = set(names)
    root = None if images_dir is None else Path(images_dir).resolve()

    def name_of(field: str):
        if field in known or root is None:
            return field if field in known else None
        try:
            rel = (path.parent / field).resolve().relative_to(root).as_posix()
        except (ValueError, OSError):
            return None
        return rel if rel in known else None

    pairs = []
    for i, *fields in read_pairs_lines(path):
        resolved = [name_of(p) for p in fields]
        if None in resolved:
            bad = fields[resolved.index(None)]
            raise PairsFileError(
                f"{path}:{i}: {bad!r} is not one of the usable images "
                f"(names are paths relative to the images folder, e.g. {sorted(known)[0]!r})"
            )
        pairs.append(tuple(resolved))
    pairs = _unique(pairs)
    if not pairs:
        raise PairsFileError(f"{path}: no pair of two different images in the file")
    return pairs


def global_descriptors(features_path, names: list, p: float = 3.0) -> np.ndarray:
    """``len(names) x D``: each image's local descriptors aggregated by generalised mean pooling
    (GeM, power ``p``, of their absolute values after L2 normalisation), L2-normalised."""
    out = []
    for name in names:
        d = read_group(features_path, name, ("descriptors",))["descriptors"].astype(np.float32)  # D x N
        d = d / np.maximum(np.linalg.norm(d, axis=0, keepdims=True), 1e-12)
        g = np.mean(np.abs(d) ** p, axis=1) ** (1.0 / p) if d.shape[1] else np.zeros(d.shape[0], np.float32)
        out.append(g / max(float(np.linalg.norm(g)), 1e-12))
    return np.stack(out)


def pairs_from_retrieval(names: list, features_path, num_nearest: int) -> list:
    """Each image with its ``num_nearest`` most similar images (:func:`global_descriptors`,
    cosine similarity); a pair found from both sides is kept once."""
    if num_nearest < 1:
        raise LocalScaleError(f"--pairs-nearest must be >= 1, got {num_nearest}")
    names = sorted(names)
    g = global_descriptors(features_path, names)
    sim = g @ g.T
    np.fill_diagonal(sim, -np.inf)
    k = min(num_nearest, len(names) - 1)
    pairs = []
    for i in range(len(names)):
        for j in np.argsort(-sim[i], kind="stable")[:k]:
            pairs.append((names[i], names[int(j)]))
    return _unique(pairs)


def write_pairs(path, pairs: list) -> Path:
    """``pairs.txt`` (one ``A B`` per line, names with spaces quoted), atomically."""
    return write_text(path, "".join(f"{shlex.quote(a)} {shlex.quote(b)}\n" for a, b in pairs))


def read_pairs(path) -> list:
    """The pairs ``[(A, B), ...]`` of a ``pairs.txt`` written by :func:`write_pairs`, as written (no
    check against images; :func:`~localscale.io.pairs_file.read_pairs_lines` parses it)."""
    return [(a, b) for _, a, b in read_pairs_lines(path)]


def pairs_by_rule(rule: PairsRule, names: list, features_path) -> list:
    """The pairs of ``names`` by ``rule`` (``exhaustive`` or ``retrieval`` from ``features_path``)."""
    if rule.rule == "retrieval":
        return pairs_from_retrieval(names, features_path, rule.nearest)
    if rule.rule == "exhaustive":
        return pairs_exhaustive(names)
    raise LocalScaleError(f"the pairs of rule {rule.rule!r} come from its file")


def pairs_of_features(features_path, pairs_path, conf: Optional[ReconstructConfig] = None, images_dir=None):
    """The pairs step from paths: the pairs of the images of ``features_path`` (``conf.pairs``,
    :func:`pairs_rule`) written to ``pairs_path``."""
    from .h5io import groups_with

    p = (conf or ReconstructConfig()).pairs
    names = sorted(groups_with(features_path, "keypoints"))
    rule = pairs_rule(p, len(names))
    if rule.rule == "file":
        pairs = pairs_from_file(p.pairs, names, images_dir)
    else:
        pairs = pairs_by_rule(rule, names, features_path)
    Path(pairs_path).parent.mkdir(parents=True, exist_ok=True)
    return write_pairs(pairs_path, pairs)


def main(argv=None) -> int:
    """``python -m localscale.sfm.pairs``: this step alone, from files (:func:`pairs_of_features`)."""
    p = parser("pairs", __doc__, ("pairs", "pairs_nearest"))
    p.add_argument("features", help="features.h5 (its images are paired)")
    p.add_argument("output", help="pairs.txt to write")
    p.add_argument("--images", default=None, help="images folder (pairs files with paths)")
    args = p.parse_args(argv)
    return run_step(lambda: pairs_of_features(args.features, args.output, config_of(args), args.images))


if __name__ == "__main__":
    raise SystemExit(main())
