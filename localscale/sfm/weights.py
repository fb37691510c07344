"""The identity of the weights a reconstruction uses, for ``run.json`` and the resume check.

A run records the sha256 of each weight file it reads: the scale networks of its correction
(``local_weights_sha256``, ``global_weights_sha256``: the checkpoint a model was loaded from, the
bundled one for a model not given, or a hash of the parameters of a model built in memory; None
for a network the correction does not use) and the files of its matcher's extractor and
LightGlue (``matcher_weights_sha256``: file name -> sha256; None for SIFT, which reads none). A
rerun with other weights then differs in :data:`WEIGHT_OPTIONS` and is refused instead of resumed.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

#: the options of ``run.json`` that name the weights (checked on resume as the other options)
WEIGHT_OPTIONS = ("local_weights_sha256", "global_weights_sha256", "matcher_weights_sha256")

_CHUNK = 1 << 20


def file_sha256(path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(_CHUNK), b""):
            h.update(block)
    return h.hexdigest()


def model_sha256(model, kind: str) -> str:
    """The sha256 of ``model``'s checkpoint file (``weights_file``, set when it was loaded), of the
    bundled checkpoint of ``kind`` when ``model`` is None, else ``params:<sha256 of its parameters>``."""
    if model is None:
        from ..models import LocalScaleNet, ScaleNet
        from ..models.base import WEIGHTS_DIR

        return file_sha256(WEIGHTS_DIR / (LocalScaleNet if kind == "local" else ScaleNet).default_weights)
    path = getattr(model, "weights_file", None)
    if path is not None and Path(path).is_file():
        return file_sha256(path)
    h = hashlib.sha256()
    for name, tensor in sorted(model.state_dict().items()):
        h.update(name.encode())
        h.update(tensor.detach().cpu().contiguous().numpy().tobytes())
    return "params:" + h.hexdigest()


def matcher_weight_files(matcher: str) -> list:
    """The pre-trained weight files that ``matcher`` (a name of ``MATCHERS``) reads: its extractor's
    and its LightGlue's (none for SIFT; the bundled HardNet for the patch matcher)."""
    from ..features.descriptors import BUNDLED_HARDNETS
    from ..features.extractors import get_extractor
    from ..features.pretrained import find_weights
    from ..matching import match_config

    cfg = match_config(matcher)
    cls = get_extractor(cfg.extractor)
    conf = cls.check_conf(cfg.extractor_conf)
    files = list(cls.weight_files(conf))
    if cfg.matching == "lightglue" and cls.lightglue_weights is not None:
        files.append(cls.lightglue_weights)
    paths = [find_weights(f, cfg.weights) for f in files]
    if cls.patch_based and conf.get("descriptor") in BUNDLED_HARDNETS:
        paths.append(BUNDLED_HARDNETS[conf["descriptor"]])
    return paths


def weight_options(correction: str, matcher: str, local_model=None, global_model=None) -> dict:
    """:data:`WEIGHT_OPTIONS` of a run (module docstring). A matcher weight file that is not installed
    is left out here; the extractor says so when it loads."""
    from ..core.errors import CheckpointError
    from ..matching import get_correction

    used = get_correction(correction).models
    sha: dict = {}
    for kind, model in (("local", local_model), ("global", global_model)):
        sha[kind] = model_sha256(model, kind) if kind in used else None
    try:
        files = {p.name: file_sha256(p) for p in matcher_weight_files(matcher)}
    except CheckpointError:
        files = {}
    return {
        "local_weights_sha256": sha["local"],
        "global_weights_sha256": sha["global"],
        "matcher_weights_sha256": files or None,
    }
