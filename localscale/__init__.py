"""localscale: per-pixel (Local-ScaleNet) and global (ScaleNet) scale estimation between images."""
from .errors import CheckpointError, HomographyError, ImageError, LocalScaleError
from .models import (LocalScaleBatch, LocalScaleNet, LocalScaleNetConfig, LocalScalePrediction, ScaleNet, ScaleNetConfig,
                     estimate_scale, predict_scale_map)

__version__ = "0.1.0"
__all__ = ["LocalScaleNet", "LocalScaleBatch", "LocalScaleNetConfig", "LocalScalePrediction", "ScaleNet", "ScaleNetConfig",
           "predict_scale_map", "estimate_scale", "LocalScaleError", "ImageError", "HomographyError",
           "CheckpointError"]
