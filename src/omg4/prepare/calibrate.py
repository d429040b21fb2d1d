"""Calibrating static cameras from several instants of their videos, with pycolmap.

A static camera's pose is one unknown over its whole video, so its keypoints at every instant can be pooled
into one image: each pair of cameras is matched only at the same instants (a moving subject is where it is in
both), the matches of all instants are pooled with their keypoints, verified together (one epipolar geometry
holds for every instant of a pair) and reconstructed once (incremental mapping). Moving subjects at different
instants give correspondences a single frame lacks; repeated structure that fools one instant is outvoted by
the others — with each instant as its own image, a dome of repeated panels converges to a consistent but wrong
solution (docs/prepare.md).

Intrinsics are per camera (``shared_intrinsics``: one for all), with radial distortion (k1, k2; COLMAP's
``RADIAL`` model); the principal point stays at the image centre, as pycolmap's default bundle adjustment
keeps it. The distortion is kept only where the observations ask for it (:func:`simplest_lens`): on a lens
without distortion, two free coefficients per camera trade focal length for distortion and pull the poses. A
calibration made to check another (``distortion`` given) takes that one's lens model instead of choosing its own.
"""

from __future__ import annotations

import itertools
import logging
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from PIL import Image

from omg4.errors import OMG4Error
from omg4.prepare.camera_model import project

logger = logging.getLogger(__name__)

CAMERA_MODEL = "RADIAL"
"""COLMAP's camera model: focal length, principal point, two radial distortion coefficients."""

DISTORTION_GAIN = 0.02
"""Lens distortion is kept when leaving it out raises the reprojection RMS by more than this fraction."""


@dataclass
class CalibratedCamera:
    """One camera as calibrated.

    Attributes:
        K: [3, 3] intrinsics in pixels (pixel centres at +0.5).
        distortion: (k1, k2) radial coefficients of COLMAP's ``RADIAL`` model.
        w2c: [4, 4] world-to-camera (OpenCV axes) in the reconstruction's world.
        reprojection_error_px: mean reprojection error of its observations.
        observations: how many reconstructed points it sees.
    """

    K: np.ndarray
    distortion: tuple[float, float]
    w2c: np.ndarray
    reprojection_error_px: float
    observations: int

    @property
    def center(self) -> np.ndarray:
        return -self.w2c[:3, :3].T @ self.w2c[:3, 3]


@dataclass
class Calibration:
    """A reconstruction of the rig: ``cameras`` by name (registered ones only), ``points`` [M, 3] and their
    ``colors`` [M, 3] in [0, 1], the instant each point was seen at (``point_instants`` [M], a position in the
    instants used: matches never cross instants), the cameras that see each point (``point_cameras``) and the
    names it could not register; the evidence behind it: each camera's pooled ``keypoints`` [P, 2], the verified
    ``matches`` of each camera pair [M, 2] (indices into those) and, per camera, which point each reconstructed
    keypoint observes (``observations``: keypoint index → point index); ``lens``: whether the distortion was
    kept and, when it was chosen here, the reprojection RMS with and without it (:func:`simplest_lens`)."""

    cameras: dict[str, CalibratedCamera]
    points: np.ndarray
    colors: np.ndarray
    point_instants: np.ndarray
    point_cameras: list[set[str]]
    unregistered: list[str]
    keypoints: dict[str, np.ndarray]
    matches: dict[tuple[str, str], np.ndarray]
    observations: dict[str, dict[int, int]]
    lens: dict = field(default_factory=dict)


def calibrate(frames: dict[str, list[np.ndarray]], work: str | os.PathLike, *, max_features: int = 8192,
              shared_intrinsics: bool = False, instants: list[int] | None = None, distortion: bool | None = None,
              threads: int = -1, seed: int = 0) -> Calibration:
    """Calibrate the cameras whose frames at the same instants are ``frames[name]`` (uint8 [H, W, 3] each, equal
    counts), working in the folder ``work`` (created; its contents are the caller's to remove). ``instants``
    selects the instants used (default all). ``distortion``: estimate the lens distortion (True), map without it
    from the start (False), or choose from the observations (None, :func:`simplest_lens`). ``seed``: of every
    random draw (RANSAC, the mapper's): one capture and seed, one calibration. Raises a one-line
    :class:`OMG4Error` when no two cameras can be reconstructed together.
    """
    import pycolmap  # pycolmap (a 38 MB extension) loads only where a capture is calibrated

    pycolmap.set_random_seed(seed)
    work = Path(work)
    names = sorted(frames)
    count = len(frames[names[0]])
    chosen = list(range(count)) if instants is None else list(instants)
    tag = "-".join(map(str, chosen)) if instants is not None else "all"
    per_instant = work / "instants"
    database = work / "instants.db"
    if not database.exists():
        _write_frames(frames, per_instant)
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.sift.max_num_features = max_features
        extraction.num_threads = threads
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = CAMERA_MODEL
        _quiet(pycolmap.extract_features, database, per_instant, camera_mode=pycolmap.CameraMode.PER_FOLDER,
               reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)
        pairs = work / "instant_pairs.txt"
        pairs.write_text("".join(f"{a}/{k:03d}.png {b}/{k:03d}.png\n"
                                 for k in range(count) for a, b in itertools.combinations(names, 2)))
        matching = pycolmap.FeatureMatchingOptions()
        matching.guided_matching = True
        matching.num_threads = threads
        pairing = pycolmap.ImportedPairingOptions()
        pairing.match_list_path = str(pairs)
        _quiet(pycolmap.match_image_pairs, database, matching_options=matching, pairing_options=pairing,
               verification_options=_verification(), device=pycolmap.Device.cpu)
    keypoints, matches, starts = _pooled(database, names, chosen)
    if not matches:
        raise OMG4Error("calibration failed: no two cameras share verified matches (do the views overlap?)")
    rec = _reconstruct(work / f"pooled-{tag}", frames, names, keypoints, matches, shared_intrinsics,
                       distortion is not False, threads, seed)
    if distortion is None:
        rec, lens = simplest_lens(rec, keypoints)
    else:
        lens = {"distortion": "kept" if distortion else "dropped"}
    return _calibration(rec, names, starts, keypoints, matches, lens)


def _write_frames(frames: dict[str, list[np.ndarray]], folder: Path) -> None:
    for name, images in frames.items():
        (folder / name).mkdir(parents=True, exist_ok=True)
        for k, image in enumerate(images):
            Image.fromarray(image).save(folder / name / f"{k:03d}.png")


def _pooled(database: Path, names: list[str], instants: list[int]
            ) -> tuple[dict[str, np.ndarray], dict[tuple[str, str], np.ndarray], dict[str, np.ndarray]]:
    """Per camera its keypoints of the ``instants`` end to end [P, 2]; per camera pair the verified matches of
    those instants, as indices into the pooled keypoints [M, 2]; per camera where each instant's keypoints start
    in its pooled ones [len(instants)]."""
    import pycolmap  # pycolmap (a 38 MB extension) loads only where a capture is calibrated

    db = pycolmap.Database.open(str(database))
    try:
        image_names = {image.image_id: image.name for image in db.read_all_images()}
        points = {n: db.read_keypoints(i)[:, :2] for i, n in image_names.items()}
        pair_ids, geometries = db.read_two_view_geometries()
    finally:
        db.close()
    offsets, keypoints, starts = {}, {}, {}
    for name in names:
        start, parts, firsts = 0, [], []
        for k in instants:
            image = f"{name}/{k:03d}.png"
            offsets[image] = start
            firsts.append(start)
            parts.append(points.get(image, np.zeros((0, 2))))
            start += len(parts[-1])
        keypoints[name] = np.concatenate(parts).astype(np.float32)
        starts[name] = np.asarray(firsts)
    matches: dict[tuple[str, str], list[np.ndarray]] = {}
    for pair_id, geometry in zip(pair_ids, geometries):
        first, second = (image_names[i] for i in pycolmap.pair_id_to_image_pair(pair_id))
        if first not in offsets or second not in offsets or len(geometry.inlier_matches) == 0:
            continue
        m = geometry.inlier_matches.astype(np.int64) + [offsets[first], offsets[second]]
        a, b = first.split("/")[0], second.split("/")[0]
        key, m = ((a, b), m) if a < b else ((b, a), m[:, ::-1])
        matches.setdefault(key, []).append(m)
    return keypoints, {k: np.concatenate(v) for k, v in matches.items()}, starts


def _reconstruct(folder: Path, frames: dict[str, list[np.ndarray]], names: list[str],
                 keypoints: dict[str, np.ndarray], matches: dict[tuple[str, str], np.ndarray],
                 shared_intrinsics: bool, distortion: bool, threads: int, seed: int):
    """One image per camera holding its pooled keypoints, the pooled matches verified and mapped (with the lens
    distortion estimated, or held at zero)."""
    import pycolmap  # pycolmap (a 38 MB extension) loads only where a capture is calibrated

    shutil.rmtree(folder, ignore_errors=True)
    images = folder / "images"
    images.mkdir(parents=True)
    for name in names:
        Image.fromarray(frames[name][0]).save(images / f"{name}.png")
    database = folder / "pooled.db"
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.sift.max_num_features = 16  # the database's cameras, images and frames; keypoints replaced below
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = CAMERA_MODEL
    mode = pycolmap.CameraMode.SINGLE if shared_intrinsics else pycolmap.CameraMode.PER_IMAGE
    _quiet(pycolmap.extract_features, database, images, camera_mode=mode, reader_options=reader,
           extraction_options=extraction, device=pycolmap.Device.cpu)
    db = pycolmap.Database.open(str(database))
    try:
        ids = {image.name[:-4]: image.image_id for image in db.read_all_images()}
        db.clear_keypoints()
        db.clear_descriptors()
        db.clear_matches()
        db.clear_two_view_geometries()
        for name in names:
            db.write_keypoints(ids[name], keypoints[name])
        for (a, b), m in matches.items():
            db.write_matches(ids[a], ids[b], m.astype(np.uint32))
    finally:
        db.close()
    pairs = folder / "pairs.txt"
    pairs.write_text("".join(f"{a}.png {b}.png\n" for a, b in matches))
    _quiet(pycolmap.verify_matches, database, pairs, options=_verification())
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = threads
    options.ba_refine_extra_params = distortion
    options.mapper.abs_pose_refine_extra_params = distortion
    options.random_seed = seed
    options.mapper.random_seed = seed
    reconstructions = _quiet(pycolmap.incremental_mapping, database, images, folder / "sparse", options=options)
    if not reconstructions:
        raise OMG4Error("calibration failed: pycolmap reconstructed no two cameras together")
    return max(reconstructions.values(), key=lambda r: r.num_reg_images())


def simplest_lens(rec, keypoints: dict[str, np.ndarray]):
    """The reconstruction ``rec`` or, when lens distortion does not explain its observations, a copy
    bundle-adjusted without it; and the evidence (``distortion``: ``kept`` or ``dropped``, ``rms_with_px``,
    ``rms_without_px``). Distortion is kept when the reprojection RMS without it is more than
    :data:`DISTORTION_GAIN` above the RMS with it. A statistical test would keep it on any lens: with tens of
    thousands of residuals, the two coefficients per camera always buy a significant fraction of a percent (on
    synthetic rigs with no distortion, 0.2–0.5 %, while bending the focal lengths by 2 % and the poses with
    them); a real lens's distortion left out raises the RMS by far more."""
    import pycolmap  # pycolmap (a 38 MB extension) loads only where a capture is calibrated

    pinhole = pycolmap.Reconstruction(rec)
    for camera in pinhole.cameras.values():
        params = np.asarray(camera.params, dtype=np.float64).copy()
        params[3:] = 0.0
        camera.params = params
    options = pycolmap.BundleAdjustmentOptions()
    options.refine_extra_params = False
    options.print_summary = False
    _quiet(pycolmap.bundle_adjustment, pinhole, options)
    radial, plain = _reprojection_rms(rec, keypoints), _reprojection_rms(pinhole, keypoints)
    radial_wins = plain > (1.0 + DISTORTION_GAIN) * radial
    lens = {"distortion": "kept" if radial_wins else "dropped", "rms_with_px": radial, "rms_without_px": plain}
    logger.info(f"lens distortion {lens['distortion']}: reprojection RMS {radial:.3f} px with it, {plain:.3f} px "
                "without")
    if radial_wins:
        return rec, lens
    pinhole.update_point_3d_errors()
    return pinhole, lens


def _reprojection_rms(rec, keypoints: dict[str, np.ndarray]) -> float:
    """Root mean square reprojection residual (pixels, per coordinate) of every observation of ``rec``."""
    seen: dict[int, tuple[list[int], list[np.ndarray]]] = {}
    for point in rec.points3D.values():
        for element in point.track.elements:
            entry = seen.setdefault(element.image_id, ([], []))
            entry[0].append(int(element.point2D_idx))
            entry[1].append(point.xyz)
    total, count = 0.0, 0
    for image_id, (indices, xyz) in seen.items():
        image = rec.images[image_id]
        camera = _camera(rec.cameras[image.camera_id], image)
        pixels, _ = project(np.asarray(xyz), camera.K, camera.distortion, camera.w2c)
        total += float(np.sum((pixels - keypoints[image.name[:-4]][indices]) ** 2))
        count += 2 * len(indices)
    return float(np.sqrt(total / max(count, 1)))


def _camera(camera, image, errors: list[float] | None = None) -> CalibratedCamera:
    """A registered pycolmap image and its ``RADIAL`` camera as a :class:`CalibratedCamera`."""
    f, cx, cy, k1, k2 = (float(v) for v in camera.params)
    pose = image.cam_from_world() if callable(image.cam_from_world) else image.cam_from_world
    w2c = np.eye(4)
    w2c[:3] = pose.matrix()
    errors = errors or []
    return CalibratedCamera(K=np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]]), distortion=(k1, k2),
                            w2c=w2c, reprojection_error_px=float(np.mean(errors)) if errors else float("nan"),
                            observations=len(errors))


def _calibration(rec, names: list[str], starts: dict[str, np.ndarray], keypoints: dict[str, np.ndarray],
                 matches: dict[tuple[str, str], np.ndarray], lens: dict) -> Calibration:
    cameras = {}
    errors: dict[str, list[float]] = {}
    observations: dict[str, dict[int, int]] = {}
    points, colors, instants, seen_by = [], [], [], []
    for index, point in enumerate(rec.points3D.values()):
        points.append(point.xyz)
        colors.append(np.asarray(point.color, dtype=np.float64) / 255.0)
        seen_by.append(set())
        for element in point.track.elements:
            name = rec.images[element.image_id].name[:-4]
            errors.setdefault(name, []).append(point.error)
            seen_by[-1].add(name)
            observations.setdefault(name, {})[int(element.point2D_idx)] = index
            instant = int(np.searchsorted(starts[name], element.point2D_idx, side="right")) - 1
        instants.append(instant)
    for image in rec.images.values():
        if not image.has_pose:
            continue
        name = image.name[:-4]
        cameras[name] = _camera(rec.cameras[image.camera_id], image, errors.get(name))
    return Calibration(cameras=cameras, points=np.asarray(points, dtype=np.float64).reshape(-1, 3),
                       colors=np.asarray(colors, dtype=np.float64).reshape(-1, 3),
                       point_instants=np.asarray(instants, dtype=np.int64), point_cameras=seen_by,
                       unregistered=[n for n in names if n not in cameras], keypoints=keypoints, matches=matches,
                       observations=observations, lens=lens)


def _verification():
    """Geometric verification with fixed RANSAC draws (one capture, one calibration)."""
    import pycolmap  # pycolmap (a 38 MB extension) loads only where a capture is calibrated

    options = pycolmap.TwoViewGeometryOptions()
    options.ransac.random_seed = 0
    return options


def _quiet(function, *args, **kwargs):
    """Call a pycolmap function with its log (glog, on stderr) limited to errors."""
    import pycolmap  # pycolmap (a 38 MB extension) loads only where a capture is calibrated

    logging_ = getattr(pycolmap, "logging", None)
    level = None
    if logging_ is not None and hasattr(logging_, "minloglevel"):
        level = logging_.minloglevel
        logging_.minloglevel = 2
    try:
        return function(*args, **kwargs)
    finally:
        if level is not None:
            logging_.minloglevel = level


__all__ = ["CAMERA_MODEL", "DISTORTION_GAIN", "Calibration", "CalibratedCamera", "calibrate", "simplest_lens"]
