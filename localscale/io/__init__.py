"""Reading inputs: images and homographies with clear errors for bad input (:mod:`.images`),
image files read without decoding them (:mod:`.image_files`), letterboxing into the networks'
processing frame (:mod:`.preprocess`) and pairs files (:mod:`.pairs_file`).

The names of :mod:`.images` are this package's too (``localscale.io.load_image``).

The submodules (NumPy, OpenCV, torch) are imported on first use of a name.
"""

from ..core.lazy import lazy_exports

_EXPORTS = {
    ".images": (
        "MAX_PIXELS",
        "MIN_SIDE",
        "ImageLike",
        "accepting_damaged",
        "check_image_file",
        "header_shape",
        "image_shape",
        "load_image",
        "load_image_array",
        "load_image_reduced",
        "load_working_image",
        "read_homography",
        "reduction_factor",
        "to_rgb",
        "to_rgb_uint8",
    )
}
__all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
