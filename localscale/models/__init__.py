from .base import EncodedImage, ScaleModel
from .local import LocalScaleNet, LocalScaleNetConfig, predict_scale_map
from .local_prediction import LocalScaleBatch, LocalScalePrediction
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
