"""The options of COLMAP's mappers: which mappers there are, pycolmap's options of each with
overrides set by name (:func:`mapping_options`, :func:`set_options`), and the defaults
:func:`~.mapping.run_mapping` sets for a camera per image."""

from __future__ import annotations

from typing import Optional

from ..core.errors import LocalScaleError

#: the mappers of :func:`run_mapping`
MAPPERS = ("incremental", "global")

#: runs of the mapper (random seeds 0, 1, ...) while its largest model leaves images out
MAPPING_TRIALS = 3


#: options of the incremental mapper when every image has its own camera: the radial distortion
#: stays as given (zero for a guessed camera). One image's observations hardly constrain it, and a
#: close-up's narrow view lets it trade with the focal length (``docs/decisions/per-image-camera-distortion.md``)
PER_IMAGE_CAMERA_OPTIONS = {"ba_refine_extra_params": False, "mapper.abs_pose_refine_extra_params": False}


def default_overrides(mapper: str, camera_mode: str) -> dict:
    """The options :func:`run_mapping` sets by default for ``mapper`` and a database whose cameras
    are ``camera_mode`` (``single`` or ``per_image``): :data:`PER_IMAGE_CAMERA_OPTIONS` for the
    incremental mapper with a camera per image, else none (pycolmap's defaults)."""
    return dict(PER_IMAGE_CAMERA_OPTIONS) if mapper == "incremental" and camera_mode == "per_image" else {}


def mapping_options(
    num_threads: int = -1, min_model_size: int = 3, mapper: str = "incremental", overrides: Optional[dict] = None
):
    """pycolmap's options of ``mapper`` (``IncrementalPipelineOptions`` or ``GlobalPipelineOptions``),
    with ``overrides`` (:func:`set_options`, e.g. ``{"ba_refine_extra_params": False}``) set last."""
    import pycolmap

    check_mapper(mapper)
    opts = pycolmap.IncrementalPipelineOptions() if mapper == "incremental" else pycolmap.GlobalPipelineOptions()
    opts.num_threads = num_threads
    opts.min_model_size = min_model_size
    opts.random_seed = 0  # the same run gives the same model
    if mapper == "global" and not getattr(pycolmap, "has_cuda", False):
        # its solvers ask for the GPU by default and warn on a CPU build of COLMAP
        opts.mapper.bundle_adjustment.ceres.use_gpu = False
        opts.mapper.global_positioning.use_gpu = False
    return set_options(opts, overrides or {}, f"{mapper} mapper")


def set_options(opts, overrides: dict, what: str = "mapper"):
    """Set pycolmap options by name (``{"mapper.abs_pose_min_num_inliers": 15}``: a dotted path
    into ``opts``); a string value is read as the option's type (``"false"``, ``"15"``, ``"0.5"``).
    Returns ``opts``; raises :class:`LocalScaleError` on an unknown name or a value of another type."""
    for key, value in overrides.items():
        *path, name = str(key).split(".")
        target = opts
        for part in path:
            target = getattr(target, part, None)
            if target is None:
                break
        current = getattr(target, name, None) if target is not None and name else None
        if current is None or name.startswith("_") or callable(current):
            raise LocalScaleError(f"{what} has no option {key!r}")
        setattr(target, name, _option_value(key, current, value))
    return opts


def _option_value(key: str, current, value):
    """``value`` as the type of the option's ``current`` value (bool, int, float or str)."""
    kind = type(current)
    wanted = {bool: "true or false", int: "an integer", float: "a number", str: "a string"}.get(kind, kind.__name__)
    if isinstance(value, str) and kind is not str:
        text = value.strip().lower()
        if kind is bool:
            if text not in ("true", "false", "1", "0"):
                raise LocalScaleError(f"option {key!r} takes {wanted}, got {value!r}")
            return text in ("true", "1")
        try:
            return kind(text)
        except ValueError:
            raise LocalScaleError(f"option {key!r} takes {wanted}, got {value!r}") from None
    if (
        kind in (int, float, bool, str)
        and not isinstance(value, kind)
        and not (kind is float and isinstance(value, int))
    ):
        raise LocalScaleError(f"option {key!r} takes {wanted}, got {value!r}")
    return value


def check_mapper(mapper: str) -> None:
    if mapper not in MAPPERS:
        raise LocalScaleError(f"mapper must be one of {', '.join(MAPPERS)}, got {mapper!r}")


def check_trials(trials: int) -> None:
    if isinstance(trials, bool) or not isinstance(trials, int) or trials < 1:
        raise LocalScaleError(f"--mapping-trials must be an integer >= 1, got {trials!r}")
