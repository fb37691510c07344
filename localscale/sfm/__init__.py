"""Structure from motion with localscale's matching, hloc style: one module per step, files between them.

Steps (:func:`reconstruct` runs them all, with the options of one
:class:`~.config.ReconstructConfig`; each also runs alone from files, as a function with paths in
:mod:`.steps` or as ``python -m localscale.sfm.<step>``):

1. :mod:`.images`: the usable images of a folder (:func:`find_images`);
2. :mod:`.extract`: local features, once per image (``features.h5``; :func:`extract_features`);
3. :mod:`.pairs`: every pair up to :data:`~.pairs.AUTO_EXHAUSTIVE_MAX` images, the nearest by a global descriptor beyond (``auto``,
   :func:`pairs_rule`), every pair, or from a file (``pairs.txt``);
4. :mod:`.match`: ``features.h5`` + ``pairs.txt`` -> matches with a correction (``none``,
   ``auto``, ...), one keypoint set per image (``matches.h5``, ``keypoints.h5``; :func:`match_pairs`);
5. :mod:`.geometry`: verified two-view geometries, once per pair (``geometries.h5``; :func:`verify_pairs`);
6. :mod:`.database`: the COLMAP database (:func:`write_database`, :func:`read_database`);
7. :mod:`.mapping`: pycolmap's incremental or global mapping (``sparse/0``; :func:`run_mapping`);
8. :mod:`.viz`: the model from above and the pair graph (:func:`plot_reconstruction`).

The submodules (torch, pycolmap, h5py) are imported on first use of a name below.

Example::

    from localscale.sfm import reconstruct
    summary = reconstruct("photos/", "out/", matcher="aliked-lightglue", correction="auto")
"""

from ..core.lazy import lazy_exports

_EXPORTS = {
    ".images": ("ImageInfo", "find_images", "names_to_pair", "IMAGE_SUFFIXES", "ImageFolderError"),
    ".extract": ("FeatureConf", "CONFS", "LevelMatcher", "extract_features", "read_features", "snap_factor"),
    ".pairs": (
        "pairs_exhaustive",
        "pairs_from_file",
        "pairs_from_retrieval",
        "pairs_rule",
        "PairsRule",
        "write_pairs",
        "read_pairs",
        "PairsFileError",
    ),
    ".match": ("KeypointSet", "match_pairs"),
    ".h5io": ("read_all_matches",),
    ".geometry": ("verify_pairs", "read_geometries", "estimate_pair"),
    ".cameras": ("CAMERA_MODES", "CameraSetup", "CameraFileError", "image_cameras", "read_camera_file"),
    ".database": ("write_database", "read_database"),
    ".mapping": ("run_mapping", "model_stats", "read_models"),
    ".viz": ("plot_reconstruction",),
    ".reconstruction": ("reconstruct",),
    ".summary": ("summary_table",),
    ".config": (
        "ReconstructConfig",
        "FeaturesConfig",
        "PairsConfig",
        "CorrectionConfig",
        "MappingConfig",
        "RESULT_OPTIONS",
        "SFM_CORRECTIONS",
    ),
    ".outdir": ("OUTPUTS", "OutputFolderError"),
}
__all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
