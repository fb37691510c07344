from .base import EncodedImage, ScaleModel
from .local import LocalScaleBatch, LocalScaleNet, LocalScaleNetConfig, LocalScalePrediction, predict_scale_map
from .registry import load_model
from .scalenet import GlobalScalePrediction, ScaleNet, ScaleNetConfig, estimate_scale

__all__ = [
    "EncodedImage",
    "ScaleModel",
    "LocalScaleNet",
    "LocalScaleNetConfig",
    "LocalScalePrediction",
    "predict_scale_map",
    "LocalScaleBatch",
    "ScaleNet",
    "ScaleNetConfig",
    "GlobalScalePrediction",
    "estimate_scale",
    "load_model",
]
