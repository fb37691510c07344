"""Evaluation protocols, each run by a thin script in ``eval/``: HPatches-style MMA with patch-size
correction (:mod:`.hpatches`, ``localscale eval-hpatches``), scale-map accuracy (:mod:`.scale_maps`,
:mod:`.scale_real`), scale maps on sanity pairs (:mod:`.sanity`) and on 3D collections (:mod:`.maps3d`)
with named predictors (:mod:`.predictors`), relative pose (:mod:`.pose`, :mod:`.pose_data`) and
reconstruction (:mod:`.reconstruction`) of photo collections. Result files record the commit
(:func:`.report.git_commit`)."""

from .hpatches import (
    HIGH_RES,
    METHODS,
    PairInfo,
    evaluate,
    load_hpatches,
    make_pairs,
    perspective_split,
    rotation_split,
    run,
    scale_split,
)
from .report import matching_table, summarise, write_outputs
from .synthetic import STRONG, make_sequences, random_pair

__all__ = [
    "load_hpatches",
    "make_pairs",
    "evaluate",
    "summarise",
    "matching_table",
    "write_outputs",
    "run",
    "perspective_split",
    "scale_split",
    "rotation_split",
    "PairInfo",
    "HIGH_RES",
    "METHODS",
    "make_sequences",
    "random_pair",
    "STRONG",
]


def __getattr__(name):
    if name == "markdown_table":  # the old name of matching_table: report's deprecation warning
        from . import report

        return report.__getattr__(name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
