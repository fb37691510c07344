"""localscale: per-pixel (Local-ScaleNet) and global (ScaleNet) scale estimation between images.

The models (and torch) are imported on first use of a name below, so that ``import localscale``
and the command line's ``--help`` stay fast.
"""

from .core.errors import CheckpointError, HomographyError, ImageError, LocalScaleError

__version__ = "0.1.0"
# fmt: off
_FROM_MODELS = ("LocalScaleNet", "LocalScaleBatch", "LocalScaleNetConfig", "LocalScalePrediction", "ScaleNet",
                "ScaleNetConfig", "predict_scale_map", "estimate_scale")
# fmt: on
__all__ = [*_FROM_MODELS, "LocalScaleError", "ImageError", "HomographyError", "CheckpointError"]


def __getattr__(name):
    if name in _FROM_MODELS:
        from . import models

        value = getattr(models, name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(__all__))
