"""Sparse triangulation of the first frame with pycolmap (``omg4 train --init colmap``).

The official Real-Time4DGS N3DV pipeline starts from COLMAP points of frame 0 of the
training cameras, computed with the known poses (rt4dgs §3.5: feature_extractor
→ exhaustive_matcher → point_triangulator, then MVS; §4.1: in the normalized world). This
module does the sparse part of that with ``pycolmap``, in the scene's normalized world:

1. the first-frame training images are written as PNG, upsampled by an integer factor so
   their longer side is about :attr:`TriangulationOptions.target_size` (more SIFT features on
   small images; the intrinsics are scaled with them);
2. SIFT features on the CPU, one PINHOLE camera per image with ``K`` of its :class:`Camera`;
3. exhaustive matching; the geometric verification uses the *known* relative poses instead of
   RANSAC: a match is kept when its Sampson error to the known fundamental matrix is below
   :attr:`TriangulationOptions.epipolar_threshold` (deterministic, and no pair is lost to a
   failed RANSAC);
4. ``pycolmap.triangulate_points`` with the poses and intrinsics fixed, then a filter on the
   reprojection error and track length of every point.

pycolmap is a dependency of the package (``omg4 prepare`` calibrates with it too); it is imported when used.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image
from tqdm import tqdm

from omg4.data.scene import Camera, PointCloud, Scene, View
from omg4.errors import OMG4Error


@dataclass(frozen=True)
class TriangulationOptions:
    """Knobs of :func:`triangulate_views`.

    Attributes:
        target_size: images are upsampled by ``max(1, round(target_size / longest side))``
            before SIFT (320×180 → ×2; 800×800 → ×1).
        epipolar_threshold: largest Sampson distance (pixels at the scene's resolution) of a
            match to the known epipolar geometry.
        max_reproj_error: largest mean reprojection error (pixels at the scene's resolution)
            of a kept point.
        min_track_length: fewest images observing a kept point (2 admits two-view points).
        min_points: fewer kept points than this raise :class:`OMG4Error`.
        max_features: SIFT features per image at most.
        num_threads: CPU threads of every pycolmap step; 1 is bitwise repeatable, more threads
            change the order of database writes and the points' last bits run to run.
        seed: pycolmap's random seed (triangulation RANSAC).
    """

    target_size: int = 640
    epipolar_threshold: float = 1.0
    max_reproj_error: float = 1.0
    min_track_length: int = 2
    min_points: int = 100
    max_features: int = 8192
    num_threads: int = 1
    seed: int = 0


@dataclass
class Triangulation:
    """The kept points of :func:`triangulate_views` and their quality.

    Attributes:
        points: xyz [M, 3] float64 in the normalized world, rgb [M, 3] float32 in [0, 1].
        errors: [M] mean reprojection error of each point in pixels at the scene's resolution.
        track_lengths: [M] number of images observing each point.
        num_triangulated: points pycolmap triangulated before the filter.
        upsample: the integer factor the images were upsampled by.
    """

    points: PointCloud
    errors: np.ndarray
    track_lengths: np.ndarray
    num_triangulated: int
    upsample: int


def relative_pose(cam1: Camera, cam2: Camera) -> tuple[np.ndarray, np.ndarray]:
    """cam2_from_cam1 as (R [3, 3], t [3]) = (R2 R1ᵀ, t2 − R t1) from the world-to-camera matrices."""
    R = cam2.viewmat[:3, :3] @ cam1.viewmat[:3, :3].T
    return R, cam2.viewmat[:3, 3] - R @ cam1.viewmat[:3, 3]


def essential_from_poses(cam1: Camera, cam2: Camera) -> np.ndarray:
    """[3, 3] essential matrix E = [t]ₓ R of :func:`relative_pose` (Hartley & Zisserman, eq. 9.12)."""
    R, t = relative_pose(cam1, cam2)
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    return tx @ R


def fundamental_from_poses(cam1: Camera, cam2: Camera) -> np.ndarray:
    """[3, 3] fundamental matrix F = K2⁻ᵀ E K1⁻¹ (Hartley & Zisserman, eq. 9.6), ``x2ᵀ F x1 = 0``
    for pixels x1 of ``cam1`` and x2 of ``cam2`` seeing the same point."""
    return np.linalg.inv(cam2.K).T @ essential_from_poses(cam1, cam2) @ np.linalg.inv(cam1.K)


def sampson_errors(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Sampson distances [M] (squared pixels) of correspondences x1 [M, 2] ↔ x2 [M, 2] to F [3, 3].

    (x2ᵀ F x1)² / ((F x1)₁² + (F x1)₂² + (Fᵀ x2)₁² + (Fᵀ x2)₂²), the first-order geometric
    error (Hartley & Zisserman, eq. 11.9).
    """
    h1 = np.concatenate([x1, np.ones((len(x1), 1))], axis=1)
    h2 = np.concatenate([x2, np.ones((len(x2), 1))], axis=1)
    Fx1 = h1 @ F.T
    Ftx2 = h2 @ F
    num = np.einsum("mi,mi->m", h2, Fx1) ** 2
    den = Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2
    return num / np.maximum(den, 1e-300)


def upsample_factor(views: list[View], target_size: int) -> int:
    """``max(1, round(target_size / longest image side))`` over ``views``."""
    longest = max(max(v.camera.width, v.camera.height) for v in views)
    return max(1, int(round(target_size / longest)))


def triangulate_first_frame(scene: Scene, options: TriangulationOptions = TriangulationOptions(),
                            progress: bool = True) -> PointCloud:
    """COLMAP-style sparse points of the scene's first frame (rt4dgs §3.5), in the normalized world.

    Returns:
        PointCloud with xyz [M, 3] float64 and rgb [M, 3] float32 in [0, 1].
    """
    return triangulate_views(scene.first_frame_views(), options, progress).points


def triangulate_views(views: list[View], options: TriangulationOptions = TriangulationOptions(),
                      progress: bool = True) -> Triangulation:
    """Triangulate the static content of simultaneous ``views`` from their known cameras.

    Raises :class:`OMG4Error` when pycolmap is missing, fewer than two views are given, or
    fewer than ``options.min_points`` points survive the filter.
    """
    try:
        import pycolmap  # pycolmap (a 38 MB extension) loads only where a capture is calibrated
    except ImportError:
        raise OMG4Error("--init colmap needs pycolmap, a dependency of omg4 missing here: "
                        "pip install 'pycolmap>=4.0,<5'") from None

    if len(views) < 2:
        raise OMG4Error(f"triangulation needs at least 2 training cameras in the first frame, got {len(views)}")
    up = upsample_factor(views, options.target_size)
    cameras = {f"{i:04d}.png": v.camera.resized(v.camera.width * up, v.camera.height * up)
               for i, v in enumerate(views)}
    old_level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 2  # errors only: keep COLMAP's per-image log lines off the console
    pycolmap.set_random_seed(options.seed)
    try:
        with tempfile.TemporaryDirectory(prefix="omg4-colmap-") as tmp, \
                tqdm(total=5, desc="colmap frame 0", unit="step", disable=not progress) as bar:
            root = Path(tmp)
            image_dir, db_path, out_dir = root / "images", root / "database.db", root / "sparse"
            image_dir.mkdir()
            out_dir.mkdir()
            bar.set_postfix_str(f"writing {len(views)} images ×{up}")
            _write_images(views, list(cameras), image_dir, up)
            bar.update()
            bar.set_postfix_str("SIFT")
            _extract_features(pycolmap, db_path, image_dir, cameras, options)
            bar.update()
            bar.set_postfix_str("matching")
            matching = pycolmap.FeatureMatchingOptions()
            matching.num_threads = options.num_threads
            matching.use_gpu = False
            matching.skip_geometric_verification = True
            pycolmap.match_exhaustive(db_path, matching_options=matching, device=pycolmap.Device.cpu)
            bar.update()
            bar.set_postfix_str("epipolar check")
            reconstruction = _verify_and_pose(pycolmap, db_path, cameras, options.epipolar_threshold * up)
            bar.update()
            bar.set_postfix_str("triangulating")
            pipeline = pycolmap.IncrementalPipelineOptions()
            pipeline.num_threads = options.num_threads
            pipeline.random_seed = options.seed
            pipeline.triangulation.ignore_two_view_tracks = options.min_track_length > 2
            result = pycolmap.triangulate_points(reconstruction, db_path, image_dir, out_dir, clear_points=True,
                                                 options=pipeline, refine_intrinsics=False)
            bar.update()
    except (ValueError, RuntimeError) as e:  # pycolmap's refusals, e.g. too few images with matched features
        raise OMG4Error(f"COLMAP could not triangulate the first frame ({e}); try --init mvs or --init random") from None
    finally:
        pycolmap.logging.minloglevel = old_level
    return _filter_points(result, up, options)


def _write_images(views: list[View], names: list[str], image_dir: Path, up: int) -> None:
    """Write each view's image (float [H, W, 3]) as 8-bit PNG, bicubically upsampled ×``up``."""
    for view, name in zip(views, names):
        image = Image.fromarray((np.clip(view.image(), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8))
        if up > 1:
            image = image.resize((image.width * up, image.height * up), Image.BICUBIC)
        image.save(image_dir / name)


def _extract_features(pycolmap, db_path: Path, image_dir: Path, cameras: dict[str, Camera],
                      options: TriangulationOptions) -> None:
    """CPU SIFT into a new database, then each image's camera set to its known PINHOLE intrinsics."""
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = options.num_threads
    extraction.use_gpu = False
    extraction.sift.max_num_features = options.max_features
    pycolmap.extract_features(db_path, image_dir, image_names=list(cameras),
                              camera_mode=pycolmap.CameraMode.PER_IMAGE,
                              reader_options=pycolmap.ImageReaderOptions(camera_model="PINHOLE"),
                              extraction_options=extraction, device=pycolmap.Device.cpu)
    db = pycolmap.Database.open(db_path)
    try:
        for image in db.read_all_images():
            camera = db.read_camera(image.camera_id)
            K = cameras[image.name].K
            camera.params = [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]
            camera.has_prior_focal_length = True
            db.update_camera(camera)
    finally:
        db.close()


def _verify_and_pose(pycolmap, db_path: Path, cameras: dict[str, Camera], threshold: float):
    """Keep the matches consistent with the known epipolar geometry; a reconstruction with the known poses.

    Every matched pair gets a CALIBRATED two-view geometry whose inliers are the matches with
    Sampson distance < ``threshold``² (pixels of the written images). The returned
    ``pycolmap.Reconstruction`` holds every connected image, registered at its ``viewmat``.
    """
    db = pycolmap.Database.open(db_path)
    try:
        images = {image.image_id: image for image in db.read_all_images()}
        keypoints = {i: db.read_keypoints(i)[:, :2].astype(np.float64) for i in images}
        for pair_id, matches in zip(*db.read_all_matches()):
            id1, id2 = pycolmap.pair_id_to_image_pair(pair_id)
            cam1, cam2 = cameras[images[id1].name], cameras[images[id2].name]
            F = fundamental_from_poses(cam1, cam2)
            errors = sampson_errors(F, keypoints[id1][matches[:, 0]], keypoints[id2][matches[:, 1]])
            geometry = pycolmap.TwoViewGeometry()
            geometry.inlier_matches = matches[errors < threshold**2]
            geometry.config = (pycolmap.TwoViewGeometryConfiguration.CALIBRATED if len(geometry.inlier_matches)
                               else pycolmap.TwoViewGeometryConfiguration.DEGENERATE)
            geometry.F = F
            geometry.E = essential_from_poses(cam1, cam2)
            R, t = relative_pose(cam1, cam2)
            geometry.cam2_from_cam1 = pycolmap.Rigid3d(np.concatenate([R, t[:, None] / np.linalg.norm(t)], axis=1))
            if db.exists_two_view_geometry(id1, id2):
                db.update_two_view_geometry(id1, id2, geometry)
            else:
                db.write_two_view_geometry(id1, id2, geometry)
        reconstruction = pycolmap.Reconstruction()
        reconstruction.load(pycolmap.DatabaseCache.create(db, pycolmap.DatabaseCacheOptions()))
    finally:
        db.close()
    for image in reconstruction.images.values():
        viewmat = cameras[image.name].viewmat
        reconstruction.frame(image.frame_id).set_cam_from_world(image.camera_id, pycolmap.Rigid3d(viewmat[:3, :4]))
        reconstruction.register_frame(image.frame_id)
    return reconstruction


def _filter_points(reconstruction, up: int, options: TriangulationOptions) -> Triangulation:
    """The points with reprojection error ≤ ``max_reproj_error`` and track length ≥ ``min_track_length``,
    sorted by position."""
    points = list(reconstruction.points3D.values())
    xyz = np.array([p.xyz for p in points], dtype=np.float64).reshape(-1, 3)
    rgb = np.array([p.color for p in points], dtype=np.float32).reshape(-1, 3) / 255.0
    errors = np.array([p.error for p in points], dtype=np.float64) / up
    tracks = np.array([p.track.length() for p in points], dtype=np.int64)
    keep = (errors <= options.max_reproj_error) & (tracks >= options.min_track_length) & np.isfinite(xyz).all(1)
    keep = np.flatnonzero(keep)
    keep = keep[np.lexsort(xyz[keep].T[::-1])]  # by x, then y, then z: independent of pycolmap's thread timing
    if len(keep) < options.min_points:
        raise OMG4Error(f"triangulating the first frame kept only {len(keep)} points of {len(points)} "
                        f"(need {options.min_points}); the images may lack texture or overlap, use --init random")
    return Triangulation(points=PointCloud(xyz=xyz[keep], rgb=rgb[keep]), errors=errors[keep],
                         track_lengths=tracks[keep], num_triangulated=len(points), upsample=up)
