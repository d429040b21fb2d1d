"""A small synthetic scene with exact surfaces, shared by the initialization tests."""

from __future__ import annotations

import numpy as np
import pytest

from omg4.data import load_scene
from omg4.data.scene import Scene
from omg4.data.synthetic import SynthConfig, SyntheticScene, write_synthetic_scene

SYNTH = SynthConfig(num_cameras=8, num_frames=3, width=192, height=144)


@pytest.fixture(scope="session")
def synth_config() -> SynthConfig:
    return SYNTH


@pytest.fixture(scope="session")
def synth_scene(tmp_path_factory):
    folder = tmp_path_factory.mktemp("init") / "synth"
    write_synthetic_scene(folder, SYNTH, progress=False)
    return load_scene(folder, progress=False)


def _surface_error(scene: Scene, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per point: smallest relative depth error |t_hit − ‖p − c‖| / ‖p − c‖ over the training cameras
    (exact surface distance along the ray from camera c through p, from the generator's ray caster),
    and the ray caster's colour at that camera."""
    synth = SyntheticScene(SYNTH)
    p = scene.normalization.invert_points(xyz)  # back to the generator's metres
    best, colour = np.full(len(p), np.inf), np.zeros((len(p), 3))
    for cam in synth.cameras[1:]:  # cam00 is the test camera
        v = p - cam.center
        dist = np.linalg.norm(v, axis=1)
        hits = synth.cast(cam.center, v / dist[:, None], synth.phase(0))
        rel = np.abs(hits.t - dist) / dist
        better = rel < best
        best[better], colour[better] = rel[better], hits.rgb[better]
    return best, colour


@pytest.fixture(scope="session")
def surface_error():
    """``surface_error(scene, xyz) -> (relative depth error [M], surface colour [M, 3])``."""
    return _surface_error
