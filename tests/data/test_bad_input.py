"""Bad input gives one clear line (DataError), and ``omg4 info`` prints it and exits 2."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from omg4.app.cli import main
from omg4.data import load_scene
from omg4.errors import DataError


def assert_data_error(match: str, path, **kwargs) -> str:
    with pytest.raises(DataError, match=match) as info:
        load_scene(path, progress=False, **kwargs)
    message = str(info.value)
    assert "\n" not in message and len(message) < 300
    return message


def n3dv_folder(tmp_path: Path, source: Path, cams: list[int], rows: list[int]) -> Path:
    """A scratch N3DV folder: symlinks to some real videos, and some rows of the real poses."""
    folder = tmp_path / "n3dv"
    folder.mkdir()
    for c in cams:
        os.symlink(source / f"cam{c:02d}.mp4", folder / f"cam{c:02d}.mp4")
    if rows:
        np.save(folder / "poses_bounds.npy", np.load(source / "poses_bounds.npy")[rows])
    return folder


def test_missing_and_empty_folders(tmp_path):
    assert_data_error("does not exist", tmp_path / "nope")
    assert_data_error("is empty", tmp_path)
    (tmp_path / "notes.txt").write_text("hello")
    assert_data_error("no dataset found", tmp_path)
    assert_data_error("not a dataset folder", tmp_path / "notes.txt")


def test_missing_poses_bounds(tmp_path, n3dv_basketball):
    folder = n3dv_folder(tmp_path, n3dv_basketball, [0, 1], rows=[])
    assert_data_error("missing poses_bounds.npy", folder)


def test_video_count_not_matching_rows(tmp_path, n3dv_basketball):
    folder = n3dv_folder(tmp_path, n3dv_basketball, [0, 1], rows=[0, 1, 2])
    assert_data_error("2 videos but poses_bounds.npy has 3 rows", folder)


def test_bad_poses_bounds(tmp_path, n3dv_basketball):
    folder = n3dv_folder(tmp_path, n3dv_basketball, [0, 1], rows=[0, 1])
    pb = np.load(folder / "poses_bounds.npy")
    pb[1, 3] = np.nan
    np.save(folder / "poses_bounds.npy", pb)
    assert_data_error("NaN", folder)
    np.save(folder / "poses_bounds.npy", pb[:, :15])
    assert_data_error(r"shape \[N, 17\]", folder)
    (folder / "poses_bounds.npy").write_bytes(b"garbage")
    assert_data_error("cannot read", folder)


def test_corrupt_videos(tmp_path, n3dv_basketball):
    folder = n3dv_folder(tmp_path, n3dv_basketball, [0], rows=[0, 1])
    (folder / "cam01.mp4").write_bytes(os.urandom(5000))
    assert_data_error("cannot open video .*cam01.mp4", folder, cache_dir=tmp_path / "cache")
    # valid container, damaged payload: detected while decoding into the cache
    data = bytearray((n3dv_basketball / "cam01.mp4").read_bytes())
    data[60000:120000] = np.random.default_rng(0).integers(0, 256, 60000, dtype=np.uint8).tobytes()
    (folder / "cam01.mp4").write_bytes(bytes(data))
    assert_data_error("cannot decode video .*cam01.mp4", folder, cache_dir=tmp_path / "cache")
    assert not list((tmp_path / "cache").glob("cam01-*.npy"))  # no half cache left behind


def test_blender_json_problems(tmp_path, dnerf_mutant):
    (tmp_path / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 0.7, "frames": []}))
    assert_data_error("transforms_train.json has no frames", tmp_path)
    (tmp_path / "transforms_train.json").write_text("{not json")
    assert_data_error("cannot parse", tmp_path)
    frames = json.loads((dnerf_mutant / "transforms_train.json").read_text())["frames"][:2]
    (tmp_path / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 0.7, "frames": frames}))
    assert_data_error("missing image file .*r_000.png", tmp_path)
    os.symlink(dnerf_mutant / "train", tmp_path / "train")
    (tmp_path / "transforms_train.json").write_text(json.dumps({"frames": frames}))
    assert_data_error("no intrinsics", tmp_path)


def test_panoptic_problems(tmp_path, panoptic_basketball):
    meta = json.loads((panoptic_basketball / "test_meta.json").read_text())
    (tmp_path / "train_meta.json").write_text(json.dumps({**meta, "fn": [], "k": [], "w2c": [], "cam_id": []}))
    assert_data_error("train_meta.json has no frames", tmp_path)
    (tmp_path / "train_meta.json").write_text(json.dumps(meta))
    assert_data_error("missing image file", tmp_path)


def test_selection_errors(n3dv_basketball, tmp_path):
    assert_data_error("unknown camera 'cam99'", n3dv_basketball, cameras=["cam99"], decode=False)
    assert_data_error("frame 60 is out of range", n3dv_basketball, frames=range(58, 61), decode=False)
    assert_data_error("downscale must be", n3dv_basketball, downscale=0)
    assert_data_error("unknown dataset format", n3dv_basketball, format="colmap")


def test_cli_prints_one_line_and_exits_2(tmp_path, capsys):
    assert main(["info", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "is empty" in err
    (tmp_path / "model.omg4").write_bytes(b"x")
    assert main(["info", str(tmp_path / "model.omg4")]) == 2
    assert "not an .omg4 file" in capsys.readouterr().err
    (tmp_path / "notes.txt").write_text("x")
    assert main(["info", str(tmp_path / "notes.txt")]) == 2
    assert "is neither a dataset folder" in capsys.readouterr().err


def test_cli_info_json(tmp_path, dnerf_mutant, capsys):
    out = tmp_path / "info.json"
    assert main(["info", str(dnerf_mutant), "--json", str(out)]) == 0
    assert "blender" in capsys.readouterr().out
    info = json.loads(out.read_text())
    assert info["format"] == "blender" and info["num_frames"] == 150 and info["time_range"] == [0.0, 1.0]
    assert info["num_train_views"] == 150 and info["num_test_views"] == 20
    assert set(info["normalization"]) == {"scale", "rotation", "translation"}
    assert np.asarray(info["normalization"]["rotation"]).shape == (3, 3)
    assert len(info["cameras"]) == 170
    cam = info["cameras"][0]
    assert set(cam) == {"name", "split", "K", "viewmat", "width", "height"}
    assert np.asarray(cam["K"]).shape == (3, 3) and np.asarray(cam["viewmat"]).shape == (4, 4)
    assert sum(c["split"] == "test" for c in info["cameras"]) == 20


def test_cli_info_n3dv_reads_metadata_only(tmp_path, n3dv_basketball, monkeypatch, capsys):
    monkeypatch.setenv("OMG4_CACHE_DIR", str(tmp_path / "cache"))
    out = tmp_path / "info.json"
    assert main(["info", str(n3dv_basketball), "--json", str(out)]) == 0
    info = json.loads(out.read_text())
    assert info["format"] == "n3dv" and info["num_frames"] == 60 and info["time_range"] == [0.0, 2.0]
    assert (info["num_train_views"], info["num_test_views"]) == (1800, 60)
    assert [c["name"] for c in info["cameras"] if c["split"] == "test"] == ["cam00"]
    centers = [-np.asarray(c["viewmat"])[:3, :3].T @ np.asarray(c["viewmat"])[:3, 3] for c in info["cameras"]]
    assert np.linalg.norm(centers, axis=1).mean() == pytest.approx(4.0)  # normalized world
    assert not (tmp_path / "cache").exists()  # no video was decoded


def test_poses_bounds_that_is_empty_or_not_numbers(tmp_path, tiny_scene_dir):
    folder = tmp_path / "n3dv"
    folder.mkdir()
    os.symlink(tiny_scene_dir / "cam00.mp4", folder / "cam00.mp4")
    (folder / "poses_bounds.npy").write_bytes(b"")
    assert_data_error("cannot read .*poses_bounds.npy: No data left in file", folder)
    np.save(folder / "poses_bounds.npy", np.full((1, 17), "x"))
    assert_data_error("must hold a numeric array, got <U1", folder)


def _blender_folder(tmp_path: Path, **frame) -> Path:
    from PIL import Image

    (tmp_path / "train").mkdir(exist_ok=True)
    Image.new("RGB", (8, 6)).save(tmp_path / "train" / "r_000.png")
    record = {"file_path": "./train/r_000", "transform_matrix": np.eye(4).tolist(), **frame}
    top = {} if "camera_angle_x" in frame or "fl_x" in frame else {"camera_angle_x": 0.7}
    (tmp_path / "transforms_train.json").write_text(json.dumps({**top, "frames": [record]}))
    return tmp_path


@pytest.mark.parametrize("frame, match", [
    ({"camera_angle_x": 0.0}, r"camera_angle_x 0.0 is not an angle in \(0, π\)"),
    ({"camera_angle_x": 3.2}, "is not an angle"),
    ({"camera_angle_x": "wide"}, "non-numeric intrinsics"),
    ({"fl_x": -100.0}, "invalid intrinsics"),
    ({"fl_x": 100.0, "cx": float("inf")}, "invalid intrinsics"),
    ({"transform_matrix": np.zeros((4, 4)).tolist()}, "not a rigid camera pose"),
    ({"transform_matrix": (2 * np.eye(4)).tolist()}, "not a rigid camera pose"),
])
def test_blender_intrinsics_and_poses_that_cannot_be_cameras(tmp_path, frame, match):
    assert_data_error(match, _blender_folder(tmp_path, **frame))


def test_blender_folder_with_valid_values_reads(tmp_path):
    scene = load_scene(_blender_folder(tmp_path), progress=False)
    assert scene.train_views[0].camera.width == 8


def test_resized_images_beyond_the_rendering_limits_are_refused():
    from omg4.data.options import LoadOptions

    assert LoadOptions(downscale=0.25).output_size(640, 360) == (2560, 1440)
    with pytest.raises(DataError, match="640x360 images resized to 640000x360000 exceed 16384 pixels a side"):
        LoadOptions(downscale=0.001).output_size(640, 360)
    with pytest.raises(DataError, match="exceed"):  # each side fits, the pixel count does not
        LoadOptions(downscale=0.05).output_size(640, 640)
