"""A final bundle adjustment of a model that refines the radial distortion of its cameras (COLMAP's
extra parameters) with the focal lengths, the cameras of some images (close-ups) kept as they are.

With a camera per image the incremental mapper keeps each camera's distortion as given (zero for a
guessed one, :data:`~.mapper_options.PER_IMAGE_CAMERA_OPTIONS`): along the way, one image's few
observations hardly constrain it. Once every image is registered, a photo's many observations do
(``docs/decisions/per-image-camera-distortion.md``). Example::

    refine_distortion(rec, keep={"closeup.jpg"})
"""

from __future__ import annotations

from .registration_check import FOCAL_RATIO_RANGE, MAX_EXTRA_PARAM


def refine_distortion(rec, keep=(), num_threads: int = -1) -> list:
    """Bundle-adjust ``rec`` (a ``pycolmap.Reconstruction``, in place) with the focal lengths and
    the distortion of the cameras refined, but those of the images named in ``keep`` and of cameras
    shared with them; a camera whose refined intrinsics are implausible goes back to what it was.
    Returns the names of the images whose camera was refined."""
    import numpy as np
    import pycolmap

    registered = [im for im in rec.images.values() if im.has_pose]
    kept_cams = {im.camera_id for im in registered if im.name in set(keep)}
    if len(registered) < 3:
        return []
    before = {cid: np.array(cam.params) for cid, cam in rec.cameras.items()}
    config = pycolmap.BundleAdjustmentConfig()
    for im in registered:
        config.add_image(im.image_id)
    for cid in kept_cams:
        config.set_constant_cam_intrinsics(cid)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.THREE_POINTS)
    opts = pycolmap.BundleAdjustmentOptions()
    opts.refine_focal_length, opts.refine_principal_point, opts.refine_extra_params = True, False, True
    opts.ceres.solver_options.num_threads = num_threads
    opts.print_summary = False
    pycolmap.create_default_bundle_adjuster(opts, config, rec).solve()
    refined = []
    for im in registered:
        cam = rec.cameras[im.camera_id]
        if im.camera_id in kept_cams:
            continue
        if cam.has_bogus_params(*FOCAL_RATIO_RANGE, MAX_EXTRA_PARAM):
            cam.params = before[im.camera_id]
        else:
            refined.append(im.name)
    return sorted(refined)


def finish_model(rec, mapping, camera_mode: str, guessed: dict, closeups: dict, num_threads: int = -1) -> tuple:
    """What the mapping step does to its largest model ``rec`` (in place) before writing it, as the
    options ``mapping`` (:class:`~.config.MappingConfig`) say: with a camera per image and the
    incremental mapper, ``final_distortion="photos"`` refines the photos' distortion
    (:func:`refine_distortion`, close-ups kept); then the suspect images
    (:func:`~.registration_check.check_registrations`, ``suspect_images``). Returns ``(names of the
    images whose camera was refined, the check's reports)``."""
    from .registration_check import check_registrations

    refined = []
    if mapping.final_distortion == "photos" and camera_mode == "per_image" and mapping.mapper == "incremental":
        refined = refine_distortion(rec, set(closeups), num_threads)
    if mapping.suspect_images == "keep":
        return refined, []
    return refined, check_registrations(rec, guessed, closeups, mapping.suspect_images == "reregister")
