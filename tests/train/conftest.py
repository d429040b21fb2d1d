"""A tiny synthetic N3DV scene shared by the training and compression tests."""

import pytest

from omg4.data import load_scene
from omg4.data.synthetic import SynthConfig, write_synthetic_scene


@pytest.fixture(scope="session")
def tiny_scene_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("tiny") / "scene"
    write_synthetic_scene(out, SynthConfig(num_cameras=5, num_frames=6, width=64, height=48, num_points=600),
                          progress=False)
    return out


@pytest.fixture(scope="session")
def tiny_scene(tiny_scene_dir):
    return load_scene(tiny_scene_dir, progress=False)
