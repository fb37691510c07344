"""The options of a reconstruction, in one place: :class:`ReconstructConfig` (hloc style, one section
per step), passed whole through :func:`~.reconstruction.reconstruct`, the CLI and ``run.json``.

* ``features`` (:class:`FeaturesConfig`): the matcher (its extractor and matching rule), the
  working resolution and keypoints per image (``features.h5``);
* ``pairs`` (:class:`PairsConfig`): every pair up to a number of images and the nearest by retrieval
  beyond (``auto``), every pair, or a pairs file (``pairs.txt``);
* ``correction`` (:class:`CorrectionConfig`): how the pairs are matched (``matches.h5``);
* ``mapping`` (:class:`MappingConfig`): the cameras, the keypoint merge distance and the mapper
  (``database.db``, ``sparse/``).

What the run does not change (device, threads, progress, plot, engine, the networks) stays an
argument of :func:`~.reconstruction.reconstruct`. A field whose metadata says ``result`` changes the
result: a resumed run must have the same (:data:`RESULT_OPTIONS`, compared in ``run.json``'s
``options``, :meth:`ReconstructConfig.options`).

Example::

    from localscale.sfm import ReconstructConfig, reconstruct
    conf = ReconstructConfig.from_flat(matcher="sift", correction="auto")
    reconstruct("photos/", "out/", conf)
"""

from __future__ import annotations

import dataclasses
import hashlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

from ..core.errors import LocalScaleError
from .weights import WEIGHT_OPTIONS

#: corrections the matching step runs (``gt`` needs a homography, ``refined`` is a two-pass pipeline)
SFM_CORRECTIONS = ("none", "auto", "global", "local", "fused", "searched")

_RESULT = {"result": True}
#: the values of ``pairs`` that are not a pairs file (:func:`~.pairs.pairs_rule`)
PAIRS_RULES = ("auto", "exhaustive")
#: what the mapping step does with a registered image whose pose is not to be trusted
SUSPECT_IMAGES = ("reregister", "leave_out", "keep")
#: the final bundle adjustment's distortion (:attr:`MappingConfig.final_distortion`)
FINAL_DISTORTION = ("none", "photos")


@dataclass
class FeaturesConfig:
    """The features: a name of :data:`localscale.matching.MATCHERS`, the working resolution (longer
    side) and keypoints per image (None: the matcher's own), and LightGlue's run-time precision
    (:data:`~localscale.matching.lightglue.LIGHTGLUE_PRECISIONS`; ``auto``: bfloat16 on a CPU that
    computes it natively)."""

    matcher: str = field(default="aliked-lightglue", metadata=_RESULT)
    max_side: Optional[int] = field(default=1024, metadata=_RESULT)
    num_keypoints: Optional[int] = field(default=2048, metadata=_RESULT)
    lightglue_precision: str = field(default="auto", metadata=_RESULT)


@dataclass
class PairsConfig:
    """``pairs``: ``"auto"`` (every pair up to a number of images, each image with its nearest by
    retrieval beyond: :func:`~.pairs.pairs_rule`), ``"exhaustive"`` (every pair) or a pairs file
    (:func:`~.pairs.pairs_from_file`); ``pairs_nearest``: with ``"auto"``, each image with its N
    most similar, whatever the number of images."""

    pairs: str = field(default="auto", metadata=_RESULT)
    pairs_nearest: Optional[int] = field(default=None, metadata=_RESULT)

    def __post_init__(self):
        self.pairs = str(self.pairs)


def upgrade_pairs(d: dict) -> dict:
    """``d`` (a pairs section or ``run.json``'s options) of a run written before ``auto`` existed
    (``pairs="exhaustive"`` was the default and ``pairs_nearest`` applied to it): ``pairs_nearest``
    with ``exhaustive`` is ``auto`` with ``pairs_nearest`` now."""
    if d.get("pairs") == "exhaustive" and d.get("pairs_nearest"):
        return {**d, "pairs": "auto"}
    return d


@dataclass
class CorrectionConfig:
    """``correction``: :data:`SFM_CORRECTIONS`; ``auto_graph``: ``auto`` driven by the pair
    graph (:func:`~.match.match_pairs`), False: the whole hypothesis loop per pair; ``prune_mnn``:
    a pair whose stored descriptors share fewer ratio-tested mutual nearest neighbours is not given
    to LightGlue as it is (:mod:`~.prune`; 0: every pair is)."""

    correction: str = field(default="none", metadata=_RESULT)
    auto_graph: bool = field(default=True, metadata=_RESULT)
    prune_mnn: int = field(default=0, metadata=_RESULT)


@dataclass
class MappingConfig:
    """The cameras (``camera_mode``: :data:`~.cameras.CAMERA_MODES`; ``camera_file``: a COLMAP
    ``cameras.txt`` with the one camera of all images), the keypoint merge distance (full-image
    pixels) and the mapper (:func:`~.mapping.run_mapping`: ``mapper``, ``mapping_trials``,
    ``mapper_options`` by pycolmap name)."""

    camera_mode: str = field(default="auto", metadata=_RESULT)
    camera_file: Optional[str] = None  #: compared by its sha1 (``camera_file_sha1``)
    merge_px: float = field(default=1.0, metadata=_RESULT)
    mapper: str = "incremental"
    mapping_trials: int = 3
    mapper_options: dict = field(default_factory=dict)
    #: registered images whose pose is not to be trusted (:mod:`.registration_check`): registered
    #: again with a plausible camera or left out (``reregister``), left out (``leave_out``), or kept (``keep``)
    suspect_images: str = "reregister"
    #: ``photos``: with a camera per image, a final bundle adjustment refines the focal lengths and
    #: radial distortion of the photos' cameras (not the close-ups'), :func:`~.refine.refine_distortion`
    final_distortion: str = "none"

    def __post_init__(self):
        self.camera_file = None if self.camera_file is None else str(self.camera_file)
        self.mapper_options = dict(self.mapper_options or {})


_SECTIONS = {
    "features": FeaturesConfig,
    "pairs": PairsConfig,
    "correction": CorrectionConfig,
    "mapping": MappingConfig,
}


@dataclass
class ReconstructConfig:
    """Every option of a reconstruction that is not run-time only (module docstring)."""

    features: FeaturesConfig = field(default_factory=FeaturesConfig)
    pairs: PairsConfig = field(default_factory=PairsConfig)
    correction: CorrectionConfig = field(default_factory=CorrectionConfig)
    mapping: MappingConfig = field(default_factory=MappingConfig)

    @staticmethod
    def names() -> dict:
        """``{option name: section name}`` of every option (the names are unique across sections)."""
        return {f.name: s for s, cls in _SECTIONS.items() for f in dataclasses.fields(cls)}

    def replace(self, **overrides) -> "ReconstructConfig":
        """A copy with the options ``overrides`` (flat names: ``matcher=``, ``correction=``, ...) set."""
        names = self.names()
        unknown = sorted(set(overrides) - set(names))
        if unknown:
            raise LocalScaleError(f"unknown reconstruction option {unknown[0]!r}; the options: {', '.join(names)}")
        sections = {s: {k: v for k, v in overrides.items() if names[k] == s} for s in _SECTIONS}
        return ReconstructConfig(**{s: dataclasses.replace(getattr(self, s), **kw) for s, kw in sections.items()})

    @classmethod
    def from_flat(cls, **options) -> "ReconstructConfig":
        """The default configuration with ``options`` (flat names) set."""
        return cls().replace(**options)

    @classmethod
    def from_dict(cls, d: dict) -> "ReconstructConfig":
        """The inverse of :meth:`asdict` (sections missing from ``d`` keep their defaults)."""
        conf = cls()
        for s, section_cls in _SECTIONS.items():
            given = d.get(s) or {}
            if s == "pairs":
                given = upgrade_pairs(given)
            known = {f.name for f in dataclasses.fields(section_cls)}
            unknown = sorted(set(given) - known)
            if unknown:
                raise LocalScaleError(f"unknown option {s}.{unknown[0]} in the configuration")
            setattr(conf, s, section_cls(**given))
        return conf

    def asdict(self) -> dict:
        return dataclasses.asdict(self)

    def flat(self) -> dict:
        """``{option name: value}`` of every option."""
        return {k: getattr(getattr(self, s), k) for k, s in self.names().items()}

    def check(self) -> None:
        """Raise a :class:`~localscale.core.errors.LocalScaleError` (one line) for a bad option; reads
        no file but the pairs and camera files' existence."""
        _check_features(self.features)
        _check_pairs(self.pairs)
        _check_correction(self.correction)
        _check_mapping(self.mapping)

    def options(self) -> dict:
        """``run.json``'s ``options``: the options, with the pairs file and camera file as their
        sha1 (the weights' are added by the run, :func:`~.weights.weight_options`)."""
        f, p, c, m = self.features, self.pairs, self.correction, self.mapping
        out = dict(dataclasses.asdict(f))
        out.update(
            correction=c.correction,
            auto_graph=c.auto_graph if c.correction == "auto" else None,
            prune_mnn=c.prune_mnn,
            pairs=p.pairs if p.pairs in PAIRS_RULES else "file",
            pairs_file_sha1=None if p.pairs in PAIRS_RULES else _sha1(p.pairs),
            pairs_nearest=p.pairs_nearest,
            camera_mode=m.camera_mode,
            camera_file_sha1=None if m.camera_file is None else _sha1(m.camera_file),
            merge_px=m.merge_px,
            mapper=m.mapper,
            mapping_trials=m.mapping_trials,
            mapper_options={str(k): v for k, v in sorted(m.mapper_options.items())},
            suspect_images=m.suspect_images,
            final_distortion=m.final_distortion,
        )
        return out


def _result_options() -> tuple:
    names = [f.name for cls in _SECTIONS.values() for f in dataclasses.fields(cls) if f.metadata.get("result")]
    return tuple(names) + ("pairs_file_sha1", "camera_file_sha1") + WEIGHT_OPTIONS


#: the options of ``run.json`` that change the result: a resumed run must have the same
RESULT_OPTIONS = _result_options()


def _sha1(path) -> str:
    return hashlib.sha1(Path(path).read_bytes()).hexdigest()


def _positive_int(value, least: int) -> bool:
    return not isinstance(value, bool) and isinstance(value, int) and value >= least


def _check_features(f: FeaturesConfig) -> None:
    from ..matching import MATCHERS

    if f.matcher not in MATCHERS:
        raise LocalScaleError(f"unknown matcher {f.matcher!r}; choose from {', '.join(MATCHERS)}")
    if f.max_side is not None and not _positive_int(f.max_side, 16):
        raise LocalScaleError(f"--max-side must be an integer >= 16, got {f.max_side!r}")
    if f.num_keypoints is not None and not _positive_int(f.num_keypoints, 1):
        raise LocalScaleError(f"--num-keypoints must be an integer >= 1, got {f.num_keypoints!r}")
    from ..matching.lightglue import LIGHTGLUE_PRECISIONS

    if f.lightglue_precision not in LIGHTGLUE_PRECISIONS:
        raise LocalScaleError(
            f"--lightglue-precision must be one of {', '.join(LIGHTGLUE_PRECISIONS)}, got {f.lightglue_precision!r}"
        )


def _check_pairs(p: PairsConfig) -> None:
    if p.pairs not in PAIRS_RULES and not Path(p.pairs).is_file():
        raise LocalScaleError(f"--pairs must be 'auto', 'exhaustive' or a pairs file; file not found: {p.pairs}")
    if p.pairs_nearest is not None:
        if p.pairs == "exhaustive":
            raise LocalScaleError(
                "--pairs-nearest chooses the pairs by retrieval: give it without --pairs exhaustive (every pair)"
            )
        if p.pairs != "auto":
            raise LocalScaleError("--pairs-nearest chooses the pairs itself: give it without a pairs file")
        if not _positive_int(p.pairs_nearest, 1):
            raise LocalScaleError(f"--pairs-nearest must be an integer >= 1, got {p.pairs_nearest!r}")


def _check_correction(c: CorrectionConfig) -> None:
    if c.correction not in SFM_CORRECTIONS:
        raise LocalScaleError(f"correction must be one of {', '.join(SFM_CORRECTIONS)}, got {c.correction!r}")
    if not _positive_int(c.prune_mnn, 0):
        raise LocalScaleError(f"--prune-mnn must be an integer >= 0, got {c.prune_mnn!r}")


def _check_mapping(m: MappingConfig) -> None:
    from .cameras import CAMERA_MODES, CameraFileError
    from .mapper_options import check_mapper, check_trials, mapping_options

    if m.camera_mode not in CAMERA_MODES:
        raise LocalScaleError(f"camera mode must be one of {', '.join(CAMERA_MODES)}, got {m.camera_mode!r}")
    if m.camera_file is not None and not Path(m.camera_file).is_file():
        raise CameraFileError(f"camera file not found: {m.camera_file}")
    check_mapper(m.mapper)
    check_trials(m.mapping_trials)
    if m.final_distortion not in FINAL_DISTORTION:
        raise LocalScaleError(
            f"--final-distortion must be one of {', '.join(FINAL_DISTORTION)}, got {m.final_distortion!r}"
        )
    if m.suspect_images not in SUSPECT_IMAGES:
        raise LocalScaleError(f"--suspect-images must be one of {', '.join(SUSPECT_IMAGES)}, got {m.suspect_images!r}")
    if m.mapper_options:
        mapping_options(mapper=m.mapper, overrides=m.mapper_options)
