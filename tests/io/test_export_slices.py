"""``omg4 export``: a decoded model's time slice as a 3DGS .ply re-renders as plain 3D Gaussians to our 4D
render; the command's outputs, sequences and refusals."""

import numpy as np
import pytest
import torch

from omg4.app.cli import main
from omg4.models import load_model
from omg4.render.api import rasterize
from omg4.render.paths import bounds_camera
from omg4.render.view import render_view
from omg4.testing import forge

from test_ply_export import PLY_WORLD, eval_real_sh, ply_gaussians, read_ply


@pytest.fixture(scope="module")
def omg4_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("export") / "m.omg4"
    forge.valid_file(path, 400, seed=3, codebook_scale=0.3)
    return path


def test_ply_slice_of_a_decoded_model_renders_like_the_4d_model(omg4_file, tmp_path, capsys):
    model = load_model(omg4_file)
    t0, t1 = model.config.time_range
    tau = t0 + 0.37 * (t1 - t0)
    assert main(["export", str(omg4_file), "--out", str(tmp_path / "s.ply"), "--time", repr(tau)]) == 0
    names, v = read_ply(tmp_path / "s.ply")
    means, cov, opacity, sh = ply_gaussians(names, v)  # in the 3DGS viewers' y-down world
    camera = bounds_camera(model.values["xyz"].numpy(), 96, 64)
    d = means - PLY_WORLD @ camera.center
    colors = np.maximum(eval_real_sh(sh, d / np.linalg.norm(d, axis=1, keepdims=True)) + 0.5, 0)
    turned_view = camera.viewmat @ np.block([[PLY_WORLD.T, np.zeros((3, 1))], [np.zeros((1, 3)), np.ones((1, 1))]])
    as_3d = rasterize(*(torch.as_tensor(a, dtype=torch.float32) for a in (means, cov, colors, opacity)),
                      torch.as_tensor(turned_view, dtype=torch.float32),
                      torch.as_tensor(camera.K, dtype=torch.float32), camera.width, camera.height, backend="cpu")
    with torch.no_grad():
        as_4d, sl = render_view(model, camera, tau, backend="cpu")
    assert len(v) == sl.index.numel() > 50
    assert as_4d.image.std() > 0.02  # the camera sees the model
    np.testing.assert_allclose(as_3d.image.numpy(), as_4d.image.numpy(), atol=2e-3)
    assert f"{len(v)}" in capsys.readouterr().out


def test_time_sequence(omg4_file, tmp_path):
    out = tmp_path / "seq.ply"
    assert main(["export", str(omg4_file), "--out", str(out), "--times", "0.1:0.9:3"]) == 0
    files = sorted(tmp_path.glob("seq_*.ply"))
    assert [f.name for f in files] == ["seq_0000.ply", "seq_0001.ply", "seq_0002.ply"]
    assert not out.exists()
    for f, tau in zip(files, (0.1, 0.5, 0.9)):
        assert main(["export", str(omg4_file), "--out", str(tmp_path / "one.ply"), "--time", str(tau), "--force"]) == 0
        assert (tmp_path / "one.ply").read_bytes() == f.read_bytes()


def test_original_world_undoes_the_files_normalization(omg4_file, tmp_path):
    """x_norm = s (R x + t): the original-world slice maps back through the normalization the file records."""
    header, sections = forge.split_container(omg4_file.read_bytes())
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    header["meta"]["normalization"] = {"scale": 2.0, "rotation": R.tolist(), "translation": [0.5, -1.0, 2.0]}
    moved = tmp_path / "moved.omg4"
    moved.write_bytes(forge.assemble_container(header, sections))
    assert main(["export", str(moved), "--out", str(tmp_path / "n.ply"), "--time", "0.4"]) == 0
    assert main(["export", str(moved), "--out", str(tmp_path / "o.ply"), "--time", "0.4", "--original-world"]) == 0
    names, norm = read_ply(tmp_path / "n.ply")
    _, orig = read_ply(tmp_path / "o.ply")
    x_norm, x_orig = (np.stack([v[k] for k in "xyz"], 1).astype(np.float64) for v in (norm, orig))
    x_norm = x_norm @ PLY_WORLD  # the normalized slice is written y down: back to omg4's world
    np.testing.assert_allclose(2.0 * (x_orig @ R.T + [0.5, -1.0, 2.0]), x_norm, atol=1e-5)
    cov_norm, cov_orig = PLY_WORLD.T @ ply_gaussians(names, norm)[1] @ PLY_WORLD, ply_gaussians(names, orig)[1]
    np.testing.assert_allclose(4.0 * R @ cov_orig @ R.T, cov_norm, rtol=1e-4, atol=1e-7)
    comments = [ln for ln in (tmp_path / "o.ply").read_bytes().split(b"end_header")[0].decode().splitlines()
                if ln.startswith("comment ")]
    np.testing.assert_allclose(np.array(comments[-1].split()[2:], float), R.T @ [0.0, 0.0, 1.0], atol=1e-9)
    assert main(["export", str(omg4_file), "--out", str(tmp_path / "x.ply"), "--original-world"]) == 0


@pytest.mark.parametrize("argv, message", [
    (["--out", "x.obj"], "must end in .ply, .glb or .splatv"),
    (["--out", "x.splatv", "--time", "0.5"], "apply to time slices"),
    (["--out", "x.ply", "--times", "0:1"], "expects A:B:N"),
    (["--out", "x.ply", "--times", "0:1:0"], "1 <= N"),
    (["--out", "x.ply", "--time", "99"], "outside the model's time range"),
])
def test_bad_requests_are_one_line_errors(omg4_file, tmp_path, capsys, argv, message):
    argv = [a if not a.startswith("x.") else str(tmp_path / a) for a in argv]
    assert main(["export", str(omg4_file), *argv]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1
    assert not list(tmp_path.iterdir())
