"""Errors raised for bad input. Each carries a one-line message naming the problem."""


class LocalScaleError(ValueError):
    """Base class: bad input given to localscale (image, homography, checkpoint, pairs file)."""


class ImageError(LocalScaleError):
    """An image file or array cannot be used."""


class HomographyError(LocalScaleError):
    """A homography file or matrix cannot be used."""


class CheckpointError(LocalScaleError):
    """A checkpoint is missing, truncated or of another architecture."""


class OutputError(LocalScaleError):
    """An output file cannot be written (full disk, no permission, read-only file system)."""


class CameraError(LocalScaleError):
    """A camera (file, string, model or parameters) cannot be used."""
