"""Registered images whose pose is not to be trusted: re-registered with a plausible camera, or left out.

After mapping, an image of the largest model is *suspect* when

* its camera has implausible intrinsics (COLMAP's test: focal length outside 0.1-10 x the longer
  side, a distortion term beyond 1; a close-up's focal length may pass 10 x when within
  :data:`FOCAL_OFF` of its prior: a strong zoom);
* it is a close-up of a photo (:func:`closeup_sources`) and its centre lies more than
  :data:`CLOSEUP_FAR` x the model's spread from the photo's, or its focal length is more than
  :data:`FOCAL_OFF` times off the close-up's prior (its zoom x the photo's focal length). A close-up
  between :data:`CLOSEUP_NEAR` and :data:`CLOSEUP_FAR` spreads away is registered again too, but
  keeps the new pose only when it is nearer the photo, and is never left out;
* every registered image it shares 3D points with is more than :data:`FAR` x the spread away.

(The spread: the median distance of the registered centres to their median.) A suspect image is
registered again by its 2D-3D correspondences in the model (``pycolmap.estimate_and_refine_absolute_pose``)
with its focal length fixed: the close-up's prior, else the image's guessed camera, no distortion. The new
pose is kept when it has :data:`MIN_INLIERS` inliers and the image is no longer suspect; its outlier
observations are removed. Else the image is left out of the model (its frame deregistered: it is not
counted as registered).

A close-up of a photo: a verified pair whose geometry is a homography of a turning camera (COLMAP's
``PLANAR_OR_PANORAMIC`` or ``PANORAMIC``: both views from one place) and whose relation (``auto``'s
:class:`~localscale.matching.auto.graph.Relation`) shows the image :data:`CLOSEUP_ZOOM` x larger or
more; its source is the photo of the strongest such pair. Such a close-up is a zoom or a window cut
from the photo: its focal length is about zoom x the photo's (:func:`closeup_focal_priors` makes its
guessed camera a SIMPLE_PINHOLE starting there).
"""

from __future__ import annotations

import numpy as np

#: a pair shows a close-up when one image is this many times larger in the other
CLOSEUP_ZOOM = 2.0
#: two-view configurations of two views from one place (a homography of a turning camera)
SAME_PLACE_CONFIGS = ("PLANAR_OR_PANORAMIC", "PANORAMIC")
#: a close-up this many spreads from its photo's centre is misplaced
CLOSEUP_FAR = 0.5
#: a close-up this many spreads from its photo's centre is registered again too, and keeps the pose
#: that is nearer its photo
CLOSEUP_NEAR = 0.25
#: a registered image whose nearest co-visible image is this many spreads away is misplaced
FAR = 3.0
#: a close-up whose focal length is this many times off its prior is suspect
FOCAL_OFF = 1.5
#: inliers a re-registration needs (COLMAP's ``abs_pose_min_num_inliers``)
MIN_INLIERS = 30
#: COLMAP's bounds of plausible intrinsics
FOCAL_RATIO_RANGE = (0.1, 10.0)
MAX_EXTRA_PARAM = 1.0


def closeup_sources(pair_records, geometry_pairs: dict) -> dict:
    """``{close-up: (source photo, zoom)}`` (module docstring) from the matching step's
    :class:`~.match.PairRecord` list and the geometry step's ``{(a, b): {"config", "inliers"}}``."""
    best = {}
    for r in pair_records:
        g = geometry_pairs.get((r.a, r.b)) or geometry_pairs.get((r.b, r.a)) or {}
        if r.relation is None or g.get("config") not in SAME_PLACE_CONFIGS:
            continue
        s = float(r.relation.scale)  # size in b over size in a
        closeup, source, zoom = (r.b, r.a, s) if s >= 1 else (r.a, r.b, 1.0 / s)
        if zoom < CLOSEUP_ZOOM:
            continue
        strength = int(g.get("inliers", r.relation.strength))
        if closeup not in best or strength > best[closeup][2]:
            best[closeup] = (source, zoom, strength)
    return {k: (v[0], v[1]) for k, v in sorted(best.items())}


def closeups_from_files(matches_path, geometries_path) -> dict:
    """:func:`closeup_sources` of a run's ``matches.h5`` (the pairs' relations) and ``geometries.h5``."""
    from .geometry import config_name, read_geometries
    from .match import _done_pairs

    geo = {
        k: {"config": config_name(g), "inliers": len(g.inlier_matches)}
        for k, g in read_geometries(geometries_path).items()
    }
    return closeup_sources(list(_done_pairs(matches_path).values()), geo)


def closeup_focal_priors(cameras, closeups: dict) -> list:
    """Make each close-up's own guessed camera (``cameras``: a :class:`~.cameras.CameraSetup` with a
    camera per image) a SIMPLE_PINHOLE at zoom x its source photo's focal length (a window of the
    photo's middle has little distortion, and a narrow view lets a distortion term trade with the
    focal length); returns the names changed. A camera from EXIF or a file, or one the close-up shares, is left as it is."""
    if cameras.mode != "per_image" or cameras.source != "exif":
        return []
    changed = []
    for name, (source, zoom) in closeups.items():
        if name not in cameras.of_image or source not in cameras.of_image:
            continue
        cam, photo = cameras.camera(name), cameras.camera(source)
        if cam.has_prior_focal_length or cam.model not in ("SIMPLE_RADIAL", "SIMPLE_PINHOLE", "RADIAL"):
            continue
        cx, cy = cam.principal_point
        params = [float(zoom * photo.focal_lengths[0]), cx, cy]
        cameras.cameras[cameras.of_image[name]] = type(cam)("SIMPLE_PINHOLE", cam.width, cam.height, params, False)
        changed.append(name)
    return changed


def _centres(rec) -> dict:
    return {im.image_id: np.asarray(im.projection_center()) for im in rec.images.values() if im.has_pose}


def _spread(centres: dict) -> float:
    c = np.array(list(centres.values())).reshape(-1, 3)
    return float(np.median(np.linalg.norm(c - np.median(c, 0), axis=1))) if len(c) > 2 else 0.0


def _plausible(cam, focal_prior=None) -> bool:
    """COLMAP's test of plausible intrinsics; with a close-up's ``focal_prior``, its focal length may
    pass COLMAP's 10 x the image size (a strong zoom) when within :data:`FOCAL_OFF` of the prior."""
    if not cam.has_bogus_params(*FOCAL_RATIO_RANGE, MAX_EXTRA_PARAM):
        return True
    if focal_prior is None or any(abs(cam.params[i]) > MAX_EXTRA_PARAM for i in cam.extra_params_idxs()):
        return False
    ratio = cam.mean_focal_length() / focal_prior
    return ratio > 0 and max(ratio, 1 / ratio) <= FOCAL_OFF


def plausible_closeups(rec, closeups: dict) -> set:
    """The registered close-ups of ``rec`` whose intrinsics are plausible for their zoom (:func:`_plausible`)."""
    by_name = {im.name: im.image_id for im in rec.images.values()}
    centres = _centres(rec)
    out = set()
    for im in rec.images.values():
        prior = _closeup_prior(rec, im.name, closeups, by_name, centres) if im.has_pose else None
        if prior is not None and _plausible(rec.cameras[im.camera_id], prior[1]):
            out.add(im.name)
    return out


def _covisible(rec, image) -> set:
    ids = set()
    for p in image.points2D:
        if p.has_point3D():
            ids.update(e.image_id for e in rec.points3D[p.point3D_id].track.elements)
    ids.discard(image.image_id)
    return ids


def _why_suspect(rec, image, closeup, centres: dict, scale: float):
    """The reason ``image`` of ``rec`` is suspect, or None. ``closeup``: ``(source id, focal prior)`` or None."""
    cam = rec.cameras[image.camera_id]
    if not _plausible(cam, None if closeup is None else closeup[1]):
        return f"implausible intrinsics (focal length {cam.mean_focal_length():.0f} px, {cam.width}x{cam.height})"
    c = centres[image.image_id]
    if closeup is not None and closeup[0] in centres and scale > 0:
        far = float(np.linalg.norm(c - centres[closeup[0]])) / scale
        if far > CLOSEUP_FAR:
            return f"{far:.2f} x the cameras' spread from its photo's centre"
        ratio = cam.mean_focal_length() / closeup[1]
        if max(ratio, 1 / ratio) > FOCAL_OFF:
            return f"focal length {ratio:.2f} x its zoom over its photo's"
        if far > CLOSEUP_NEAR:
            return f"near: {far:.2f} x the cameras' spread from its photo's centre"
    near = [float(np.linalg.norm(c - centres[i])) for i in _covisible(rec, image) if i in centres]
    if near and scale > 0 and min(near) > FAR * scale:
        return f"{min(near) / scale:.1f} x the cameras' spread from every image it shares points with"
    return None


def check_registrations(rec, guessed: dict, closeups: dict, reregister: bool = True) -> list:
    """Re-register (when ``reregister``) or leave out the suspect images of ``rec`` (a
    ``pycolmap.Reconstruction``, changed in place; module docstring). ``guessed``: ``{name: focal
    length}`` of each image's guessed camera; ``closeups``: :func:`closeup_sources`. Returns ``[{"image", "reason", "action"}]``, ``action``
    ``re-registered`` or ``left out``."""
    by_name = {im.name: im.image_id for im in rec.images.values()}
    reports = []
    for _ in range(2):  # a second pass: an image left out can leave another one alone
        centres = _centres(rec)
        scale = _spread(centres)
        found = []
        for image_id in sorted(centres):
            image = rec.images[image_id]
            closeup = _closeup_prior(rec, image.name, closeups, by_name, centres)
            why = _why_suspect(rec, image, closeup, centres, scale)
            if why is not None:
                found.append((image_id, why, closeup))
        done = {r["image"] for r in reports}
        found = [f for f in found if rec.images[f[0]].name not in done]
        if not found:
            break
        for image_id, why, closeup in found:
            focal = _focal_for(rec, rec.images[image_id], closeup, guessed)
            kept = reregister and focal is not None and _reregister(rec, image_id, focal, closeup, scale)
            if not kept and why.startswith("near:"):
                continue  # within CLOSEUP_FAR and no nearer pose found: kept as it is
            if not kept:
                rec.deregister_frame(rec.images[image_id].frame_id)
            reports.append(
                {
                    "image": rec.images[image_id].name,
                    "reason": why.removeprefix("near: "),
                    "action": "re-registered" if kept else "left out",
                }
            )
    return reports


def _focal_for(rec, image, closeup, guessed: dict):
    """The focal length of a re-registration: the close-up's prior; else the model's when it is
    plausible and within :data:`FOCAL_OFF` of the guessed one (or none is given); else the guessed one."""
    if closeup is not None:
        return closeup[1]
    cam, prior = rec.cameras[image.camera_id], guessed.get(image.name)
    if not cam.has_bogus_params(*FOCAL_RATIO_RANGE, MAX_EXTRA_PARAM):
        ratio = cam.mean_focal_length() / prior if prior else 1.0
        if max(ratio, 1 / ratio) <= FOCAL_OFF:
            return cam.mean_focal_length()
    return prior


def _closeup_prior(rec, name: str, closeups: dict, by_name: dict, centres: dict):
    """``(source id, focal prior)`` of a close-up whose source photo is registered, else None."""
    if name not in closeups or by_name.get(closeups[name][0]) not in centres:
        return None
    source, zoom = closeups[name]
    photo = rec.images[by_name[source]]
    return photo.image_id, zoom * rec.cameras[photo.camera_id].mean_focal_length()


def _nearer(old_pose, rec, image_id: int, closeup) -> bool:
    """Whether a close-up's new pose puts it nearer its photo's centre than ``old_pose`` (True for other images)."""
    if closeup is None:
        return True
    photo = np.asarray(rec.images[closeup[0]].projection_center())
    new = np.asarray(rec.images[image_id].projection_center())
    return float(np.linalg.norm(new - photo)) < float(np.linalg.norm(old_pose.inverse().translation - photo))


def _reregister(rec, image_id: int, focal: float, closeup, scale: float) -> bool:
    """Register ``image_id`` again from its 2D-3D correspondences with focal length ``focal``, no
    distortion; keep it (True) when it has :data:`MIN_INLIERS` inliers and is no longer suspect."""
    import pycolmap

    image = rec.images[image_id]
    idx = [i for i, p in enumerate(image.points2D) if p.has_point3D()]
    if len(idx) < MIN_INLIERS:
        return False
    xy = np.array([image.points2D[i].xy for i in idx], np.float64)
    xyz = np.array([rec.points3D[image.points2D[i].point3D_id].xyz for i in idx], np.float64)
    cam = rec.cameras[image.camera_id]
    old = (np.array(cam.params), image.cam_from_world())
    pp = [cam.principal_point_x, cam.principal_point_y]
    trial = pycolmap.Camera(model="SIMPLE_PINHOLE", width=cam.width, height=cam.height, params=[focal, *pp])
    ref = pycolmap.AbsolutePoseRefinementOptions()
    ref.refine_focal_length, ref.refine_extra_params = False, False
    out = pycolmap.estimate_and_refine_absolute_pose(xy, xyz, trial, pycolmap.AbsolutePoseEstimationOptions(), ref)
    if out is None or int(out["num_inliers"]) < MIN_INLIERS:
        return False
    params = np.array(old[0])
    params[list(cam.focal_length_idxs())] = focal
    params[list(cam.extra_params_idxs())] = 0.0
    cam.params = params
    rec.frames[image.frame_id].rig_from_world = out["cam_from_world"]
    centres = _centres(rec)
    why = _why_suspect(rec, rec.images[image_id], closeup, centres, scale)
    if (why is not None and not why.startswith("near:")) or not _nearer(old[1], rec, image_id, closeup):
        cam.params = old[0]
        rec.frames[image.frame_id].rig_from_world = old[1]
        return False
    for i, inlier in zip(idx, np.asarray(out["inlier_mask"], bool)):
        if not inlier:
            rec.delete_observation(image_id, i)
    return True
