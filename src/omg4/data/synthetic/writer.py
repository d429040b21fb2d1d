"""Writes the synthetic scene as an N3DV folder (``omg4 synth``), atomically.

Every camera's frames are rendered by the ray caster (:mod:`.raycast`) and encoded with the
project's video writer (:func:`omg4.io.video.write_video`); the frame-0 surface samples of the
training cameras become ``points3d.ply`` (:func:`omg4.data.points.write_ply`). The folder is
built beside the target and renamed into place when complete.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from omg4.atomic import atomic_folder
from omg4.data.points import write_ply
from omg4.data.scene import Camera, PointCloud
from omg4.data.synthetic.raycast import RayHits, StaticLayer, SyntheticScene, box_filter
from omg4.data.synthetic.rig import llff_poses_bounds
from omg4.data.synthetic.world import SynthConfig
from omg4.errors import OMG4Error
from omg4.io.video import write_video


GENERATOR = "omg4 synth"
"""The ``generator`` entry of the ``synth.json`` this writer leaves in every scene."""


def is_synthetic_scene(folder: str | os.PathLike) -> bool:
    """Whether ``folder`` holds a scene this writer wrote (its ``synth.json`` names :data:`GENERATOR`)."""
    try:
        meta = json.loads((Path(folder) / "synth.json").read_text())
    except (OSError, ValueError):
        return False
    return isinstance(meta, dict) and meta.get("generator") == GENERATOR


@dataclass
class SynthResult:
    """What :func:`write_synthetic_scene` wrote."""

    path: Path
    cameras: list[Camera]
    num_points: int
    poses_bounds: np.ndarray  # [N, 17]


def _prepare_target(out_dir: Path, force: bool) -> None:
    """Refuse an existing non-empty folder (or a file) at ``out_dir`` unless ``force``."""
    if out_dir.is_file() or out_dir.is_symlink():
        if not force:
            raise OMG4Error(f"{out_dir} exists and is not a folder (use --force to replace it)")
    elif out_dir.is_dir() and any(out_dir.iterdir()) and not force:
        raise OMG4Error(f"{out_dir} exists and is not empty (use --force to overwrite it)")


def write_synthetic_scene(out_dir: str | os.PathLike, config: SynthConfig = SynthConfig(), force: bool = False,
                          progress: bool = True) -> SynthResult:
    """Render the scene of ``config`` and write it as an N3DV folder at ``out_dir``.

    The folder is built beside the target and renamed into place when complete. An
    existing non-empty ``out_dir`` is refused unless ``force``.
    """
    config.validate()
    out_dir = Path(os.path.abspath(out_dir))
    _prepare_target(out_dir, force)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    scene = SyntheticScene(config)
    cams = scene.cameras
    n_train = len(cams) - 1
    per_cam = -(-config.num_points // n_train)
    near, far = np.zeros(len(cams)), np.zeros(len(cams))
    xyz, rgb = [], []
    with atomic_folder(out_dir) as tmp:
        with tqdm(total=len(cams) * config.num_frames, desc="omg4 synth", unit="frame", disable=not progress) as bar:

            def frames(i: int, layer: StaticLayer):
                """Camera ``i``'s box-filtered frames; frame 0 also gives its depth bounds and points."""
                for f in range(config.num_frames):
                    samples = scene.render_samples(i, f, layer)
                    if f == 0:
                        near[i], far[i], pts = _frame0_samples(cams[i], layer, samples)
                        if i > 0:
                            pick = scene.point_rng.choice(len(pts[0]), min(per_cam, len(pts[0])), replace=False)
                            xyz.append(pts[0][pick])
                            rgb.append(pts[1][pick])
                    yield box_filter(samples.rgb, config.supersample)
                    bar.update(1)

            for i, cam in enumerate(cams):
                write_video(tmp / f"{cam.name}.mp4", frames(i, scene.static_layer(i)), fps=config.fps, crf=config.crf,
                            reproducible=True)
        points = PointCloud(xyz=np.concatenate(xyz)[: config.num_points], rgb=np.concatenate(rgb)[: config.num_points])
        poses_bounds = llff_poses_bounds(cams, near, far)
        np.save(tmp / "poses_bounds.npy", poses_bounds)
        write_ply(tmp / "points3d.ply", points)
        meta = {"generator": GENERATOR, **asdict(config), "test_camera": "cam00",
                "world": "metres, +z up, LLFF poses", "time": "timestamp = frame / fps; motion phase = frame / frames"}
        (tmp / "synth.json").write_text(json.dumps(meta, indent=2) + "\n")
    return SynthResult(out_dir, cams, len(points.xyz), poses_bounds)


def _frame0_samples(cam: Camera, layer: StaticLayer, samples: RayHits):
    """Near/far z-depth bounds (0.9·min, 1.1·max) and the visible surface points
    ([K, 3], colours [K, 3]) of one camera's frame-0 supersamples."""
    t = samples.t.reshape(-1)
    hit = np.isfinite(t)
    points = layer.origin + t[hit, None] * layer.dirs[hit]
    depth = (points - layer.origin) @ cam.viewmat[2, :3].astype(np.float32)
    return 0.9 * depth.min(), 1.1 * depth.max(), (points, samples.rgb.reshape(-1, 3)[hit])
