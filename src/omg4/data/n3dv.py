"""N3DV / DyNeRF reader: ``poses_bounds.npy`` (LLFF) + ``camXX.mp4`` (rt4dgs §4.1).

Layout and conventions (official ``n3v2blender.py`` unless noted):

* Videos are all ``*.mp4`` files of the folder sorted by name; row ``i`` of
  ``poses_bounds.npy`` (``[N, 17]``: a row-major 3×5 ``[R | t | hwf]`` camera-to-world with
  axes [down, right, back], then near, far) belongs to the ``i``-th video. The first video
  (``cam00``) is the test camera, the others train.
* Intrinsics: ``fx = fy = focal``, ``cx = W / 2``, ``cy = H / 2`` (centred principal point,
  pixel centres at +0.5) from each row's ``hwf`` at ``W × H``. Deviation: the official
  script uses row 0's ``hwf`` for every camera; per-row is identical when the rows agree and
  correct when they do not (``n3dv_basketball`` has one focal per camera). If a video's
  size differs from ``hwf`` the intrinsics are scaled to the video, then to the requested
  output size.
* Time: ``timestamp = frame / fps`` seconds (fps from the stream, 30 for N3DV); the time
  range of frames ``f0 … f1`` is ``[f0 / fps, (f1 + 1) / fps]``, so 300 frames at 30 fps give
  the official ``[0, 10]``. Cameras with different frame counts are cut to the shortest.
* Frames are decoded once into the uint8 frame cache (:mod:`omg4.data.frame_cache`).
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
from tqdm import tqdm

from omg4.data.frame_cache import FrameCache, VideoInfo, probe_video
from omg4.data.normalize import official_normalization
from omg4.data.options import LoadOptions, select_cameras, select_frames
from omg4.data.points import load_initial_points
from omg4.data.scene import Camera, Normalization, Scene, View
from omg4.errors import DataError

DEFAULT_FPS = 30.0


def is_n3dv(folder: Path) -> bool:
    """Whether ``folder`` looks like N3DV: videos, or ``poses_bounds.npy`` without Blender JSONs."""
    has_transforms = any(folder.glob("transforms_*.json"))
    return any(folder.glob("*.mp4")) or ((folder / "poses_bounds.npy").exists() and not has_transforms)


def llff_to_opencv(poses_bounds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """LLFF rows → OpenCV camera-to-world and ``hwf``.

    Args:
        poses_bounds: [N, 17] rows ``(3×5 [down, right, back, t, hwf]).ravel(), near, far``.

    Returns:
        c2w: [N, 4, 4] OpenCV (right, down, forward) camera-to-world; hwf: [N, 3] (H, W, focal).
    """
    poses = poses_bounds[:, :15].reshape(-1, 3, 5)
    c2w = np.tile(np.eye(4), (len(poses), 1, 1))
    c2w[:, :3, 0] = poses[:, :, 1]
    c2w[:, :3, 1] = poses[:, :, 0]
    c2w[:, :3, 2] = -poses[:, :, 2]
    c2w[:, :3, 3] = poses[:, :, 3]
    return c2w, poses[:, :, 4]


def load_poses_bounds(folder: Path) -> np.ndarray:
    """[N, 17] float64 array of ``poses_bounds.npy``, validated."""
    path = folder / "poses_bounds.npy"
    if not path.exists():
        raise DataError(f"missing poses_bounds.npy in {folder}")
    try:
        arr = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as e:
        raise DataError(f"cannot read {path}: {e or 'empty file'}") from None
    if not isinstance(arr, np.ndarray) or not np.issubdtype(arr.dtype, np.number):
        raise DataError(f"{path} must hold a numeric array, got {getattr(arr, 'dtype', type(arr).__name__)}")
    if arr.ndim != 2 or arr.shape[1] != 17 or len(arr) == 0:
        raise DataError(f"{path} must have shape [N, 17] (LLFF), got {arr.shape}")
    arr = arr.astype(np.float64)
    if not np.isfinite(arr).all():
        raise DataError(f"{path} contains NaN or Inf")
    if (arr[:, [4, 9, 14]] <= 0).any():
        raise DataError(f"{path} has a non-positive image height, width or focal length")
    return arr


def read_n3dv(folder: Path, opts: LoadOptions) -> Scene:
    """The N3DV scene in ``folder`` (see the module docstring for the conventions)."""
    pb = load_poses_bounds(folder)
    videos = sorted(folder.glob("*.mp4"))
    if not videos:
        raise DataError(f"no camXX.mp4 videos in {folder}")
    if len(videos) != len(pb):
        raise DataError(f"{folder} has {len(videos)} videos but poses_bounds.npy has {len(pb)} rows")
    names = [v.stem for v in videos]
    c2w, hwf = llff_to_opencv(pb)
    norm = Normalization.identity() if opts.normalize is False else official_normalization(c2w)

    chosen = select_cameras(names, opts.cameras)
    infos = {n: probe_video(folder / f"{n}.mp4") for n in chosen}
    num_available = min(info.num_frames for info in infos.values())
    frame_ids = select_frames(opts.frames, num_available)
    fps = float(opts.fps or next(iter(infos.values())).fps or DEFAULT_FPS)

    train, test, caches = [], [], []
    cache_dir = opts.frame_cache_dir()
    for name in chosen:
        i = names.index(name)
        camera = _camera(name, c2w[i], hwf[i], infos[name], norm, opts)
        # frames from 0: a prefix cache every shorter run reuses; a later start (a segment): its own window
        cache = FrameCache(infos[name], camera.width, camera.height, int(frame_ids[-1]) + 1, cache_dir,
                           first=int(min(frame_ids)))
        caches.append(cache)
        views = [View(camera=camera, timestamp=float(f) / fps, frame_index=int(f),
                      loader=functools.partial(cache.image, int(f))) for f in frame_ids]
        (test if i == 0 else train).extend(views)
    if opts.decode:
        decode_all(caches, opts.progress)
    points_world = opts.points_world
    if points_world == "auto":
        points_world = "normalized" if (folder / "transforms_train.json").exists() else "original"
    return Scene(train_views=train, test_views=test,
                 time_range=(float(frame_ids[0]) / fps, float(frame_ids[-1] + 1) / fps),
                 normalization=norm, format="n3dv", name=folder.name,
                 initial_points=load_initial_points(folder, norm, points_world), num_frames=len(frame_ids))


def _camera(name: str, c2w: np.ndarray, hwf: np.ndarray, info: VideoInfo, norm: Normalization,
            opts: LoadOptions) -> Camera:
    """The normalized-world camera of one LLFF row at the output resolution."""
    h, w, focal = hwf
    K = np.array([[focal, 0.0, w / 2.0], [0.0, focal, h / 2.0], [0.0, 0.0, 1.0]])
    cam = Camera(K=K, viewmat=norm.apply_viewmat(np.linalg.inv(c2w)), width=int(round(w)), height=int(round(h)),
                 name=name)
    if (cam.width, cam.height) != (info.width, info.height):
        cam = cam.resized(info.width, info.height)
    out_w, out_h = opts.output_size(info.width, info.height)
    return cam.resized(out_w, out_h) if (out_w, out_h) != (cam.width, cam.height) else cam


def decode_all(caches: list[FrameCache], progress: bool = True) -> None:
    """Decode every cache that is not on disk yet, with one progress bar over all frames."""
    todo = [c for c in caches if not c.is_cached()]
    with tqdm(total=sum(c.num_frames - c.first for c in todo), unit="frame", desc="decoding videos",
              disable=not progress or not todo) as bar:
        for cache in todo:
            cache.ensure(on_frame=lambda: bar.update(1))
    for cache in caches:
        cache.ensure()
