"""The model of a database that holds two images, or whose images are joined by single pairs only.

Both of COLMAP's mappers keep only points seen in three images or more by default, and a pair has
none: the incremental mapper triangulates its initial pair without the tracks of two views (an
option of its own that its pipeline does not expose), and the global mapper drops the tracks and
the models shorter than three, so a pair alone gives no model with their defaults. For a
database of two images, and for one where the mapper made no model (:func:`~.mapping.run_mapping`):

* ``incremental``: :func:`two_view_mapping` does what the incremental mapper does for its initial
  pair (pycolmap's ``IncrementalMapper``: the initial pair's relative pose, triangulation, global
  bundle adjustment, filtering), with the tracks of two views kept. When no initial pair is found,
  its thresholds are relaxed as COLMAP relaxes them (inliers halved, then the triangulation angle);
* ``global``: :data:`GLOBAL_TWO_VIEW_OPTIONS` lets tracks and models of two views through.
"""

from __future__ import annotations

#: the global mapper's options that let tracks and models of two views through
GLOBAL_TWO_VIEW_OPTIONS = {
    "min_model_size": 2,
    "mapper.track_min_num_views_per_track": 2,
    "mapper.global_positioning.min_num_view_per_track": 2,
    "mapper.bundle_adjustment.min_track_length": 2,
    "mapper.retriangulation.ignore_two_view_tracks": False,
}

#: relaxations of the initial pair's thresholds (COLMAP's: halve the inliers, then the angle, ...)
_RELAXATIONS = 4


def database_images(database_path) -> int:
    """The number of images in a COLMAP database."""
    import pycolmap

    db = pycolmap.Database.open(str(database_path))
    try:
        return db.num_images()
    finally:
        db.close()


def two_view_mapping(database_path, image_dir, output_path, options) -> dict:
    """The incremental mapper's model of a two-image database, ``{0: pycolmap.Reconstruction}``
    (``{}`` when the pair gives no model: no initial geometry, or no point survives). Same call as
    ``pycolmap.incremental_mapping`` (``options``: ``IncrementalPipelineOptions``); writes nothing."""
    import pycolmap

    db = pycolmap.Database.open(str(database_path))
    try:
        cache_options = pycolmap.DatabaseCacheOptions()
        cache_options.min_num_matches = options.min_num_matches
        cache = pycolmap.DatabaseCache.create(db, cache_options)
    finally:
        db.close()
    if options.random_seed >= 0:  # as COLMAP's pipeline: the same run gives the same model
        pycolmap.set_random_seed(options.random_seed)
    mapper_options = options.get_mapper()
    for step in range(_RELAXATIONS + 1):
        rec = _initial_pair_model(pycolmap, cache, options, mapper_options)
        if rec is not None:
            rec.extract_colors_for_all_images(str(image_dir))
            return {0: rec}
        if step % 2 == 0:
            mapper_options.init_min_num_inliers = max(1, mapper_options.init_min_num_inliers // 2)
        else:
            mapper_options.init_min_tri_angle /= 2
    return {}


def _initial_pair_model(pycolmap, cache, options, mapper_options):
    """The incremental mapper's initial step, with two-view tracks; None when it gives no model."""
    rec = pycolmap.Reconstruction()
    mapper = pycolmap.IncrementalMapper(cache)
    mapper.begin_reconstruction(rec)
    found = mapper.find_initial_image_pair(mapper_options, -1, -1)
    if found is None:
        mapper.end_reconstruction(True)
        return None
    (id1, id2), cam2_from_cam1 = found
    mapper.register_initial_image_pair(mapper_options, id1, id2, cam2_from_cam1)
    triangulation = options.get_triangulation()
    triangulation.ignore_two_view_tracks = False
    triangulation.min_angle = mapper_options.init_min_tri_angle
    for image_id in (id1, id2):
        mapper.triangulate_image(triangulation, image_id)
    mapper.adjust_global_bundle(mapper_options, options.get_global_bundle_adjustment())
    rec.normalize()
    mapper.filter_points(mapper_options)
    mapper.filter_frames(mapper_options)
    if rec.num_reg_images() < 2 or rec.num_points3D() == 0:
        mapper.end_reconstruction(True)
        return None
    mapper.end_reconstruction(False)
    return rec
