"""Safe checkpoints: bit-exact round trip, metadata, damaged and foreign files."""

import json

import pytest
import torch
from safetensors.torch import save_file

from omg4.errors import CorruptFileError
from omg4.gaussians import GaussianConfig, Gaussians4D
from omg4.gaussians.checkpoint import describe_checkpoint, load_gaussians, save_gaussians
from test_gaussians_model import random_params


@pytest.fixture
def model():
    cfg = GaussianConfig(time_range=(0.0, 10.0), rotation_convention="legacy", sh_direction="canonical",
                         time_cull=0.1)
    return Gaussians4D(random_params(40, seed=11, dtype=torch.float32), cfg, 2, 1)


def test_round_trip_is_bit_exact(tmp_path, model):
    path = tmp_path / "m.safetensors"
    meta = {"normalization": {"scale": 0.5, "rotation": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "translation": [0, 0, 1]},
            "iteration": 1234, "time_range": [0.0, 10.0]}
    save_gaussians(path, model, meta)
    loaded, meta2 = load_gaussians(path)
    assert meta2 == meta
    assert loaded.config == model.config
    assert (loaded.active_sh_degree, loaded.active_sh_degree_t) == (2, 1)
    for k, v in model.params.items():
        assert loaded.params[k].dtype == torch.float32 and not loaded.params[k].requires_grad
        assert torch.equal(loaded.params[k], v), k
    assert [p.name for p in tmp_path.iterdir()] == ["m.safetensors"]  # no temporary files left


def test_params_requiring_grad_and_float64_are_saved_as_float32(tmp_path, model):
    params = {k: v.double().requires_grad_(True) for k, v in model.params.items()}
    save_gaussians(tmp_path / "m.safetensors", Gaussians4D(params, model.config))
    loaded, meta = load_gaussians(tmp_path / "m.safetensors")
    assert meta == {}
    assert torch.equal(loaded.params["xyz"], params["xyz"].detach().float())


def test_describe_checkpoint(tmp_path, model):
    path = tmp_path / "m.safetensors"
    save_gaussians(path, model, {"iteration": 7})
    d = describe_checkpoint(path)
    assert d["kind"] == "rt4dgs-checkpoint" and d["num_gaussians"] == 40
    assert (d["sh_degree"], d["sh_degree_t"], d["active_sh_degree"], d["active_sh_degree_t"]) == (3, 2, 2, 1)
    assert d["time_range"] == [0.0, 10.0] and d["iteration"] == 7
    assert d["file_size_bytes"] == path.stat().st_size
    assert d["file_size_mb"] == pytest.approx(path.stat().st_size / 2**20)
    json.dumps(d)


def _expect_corrupt(path, match):
    with pytest.raises(CorruptFileError, match=match) as e:
        load_gaussians(path)
    assert "\n" not in str(e.value)


def test_missing_file(tmp_path):
    _expect_corrupt(tmp_path / "nope.safetensors", "no such")
    with pytest.raises(CorruptFileError):
        describe_checkpoint(tmp_path / "nope.safetensors")


def test_truncated_and_garbage_files(tmp_path, model):
    path = tmp_path / "m.safetensors"
    save_gaussians(path, model)
    data = path.read_bytes()
    (tmp_path / "trunc.safetensors").write_bytes(data[: len(data) // 2])
    _expect_corrupt(tmp_path / "trunc.safetensors", "not a readable")
    (tmp_path / "junk.safetensors").write_bytes(b"\x00\x01garbage" * 50)
    _expect_corrupt(tmp_path / "junk.safetensors", "not a readable")
    (tmp_path / "empty.safetensors").write_bytes(b"")
    _expect_corrupt(tmp_path / "empty.safetensors", "not a readable")


def test_foreign_safetensors_file(tmp_path):
    save_file({"weight": torch.zeros(3)}, str(tmp_path / "other.safetensors"))
    _expect_corrupt(tmp_path / "other.safetensors", "not an omg4 checkpoint")
    save_file({"weight": torch.zeros(3)}, str(tmp_path / "other2.safetensors"), metadata={"omg4": '{"format": "x"}'})
    _expect_corrupt(tmp_path / "other2.safetensors", "not an omg4 Real-Time4DGS")


def _rewrite(src, dst, tensors=None, header_update=None):
    from safetensors import safe_open

    with safe_open(str(src), framework="pt") as f:
        header = json.loads(f.metadata()["omg4"])
        data = {k: f.get_tensor(k) for k in f.keys()}
    data.update(tensors or {})
    header.update(header_update or {})
    save_file(data, str(dst), metadata={"omg4": json.dumps(header)})


def test_wrong_shapes_nan_dtype_and_version(tmp_path, model):
    src = tmp_path / "m.safetensors"
    save_gaussians(src, model)
    _rewrite(src, tmp_path / "a.safetensors", {"t": torch.zeros(39, 1)})
    _expect_corrupt(tmp_path / "a.safetensors", "'t' has shape")
    bad = model.params["xyz"].clone()
    bad[3, 1] = float("nan")
    _rewrite(src, tmp_path / "b.safetensors", {"xyz": bad})
    _expect_corrupt(tmp_path / "b.safetensors", "'xyz' contains NaN")
    _rewrite(src, tmp_path / "c.safetensors", {"opacity": torch.zeros(40, 1, dtype=torch.float64)})
    _expect_corrupt(tmp_path / "c.safetensors", "dtype")
    _rewrite(src, tmp_path / "d.safetensors", header_update={"version": 99})
    _expect_corrupt(tmp_path / "d.safetensors", "version 99")
    _rewrite(src, tmp_path / "e.safetensors", header_update={"active_sh_degree": 5})
    _expect_corrupt(tmp_path / "e.safetensors", "inconsistent")


def test_metadata_that_is_no_json_object_is_refused(tmp_path, model):
    src = tmp_path / "m.safetensors"
    save_gaussians(src, model, {"scene": "x"})
    for k, value in enumerate(("a string", ["a", "list"], 7)):
        _rewrite(src, tmp_path / f"meta{k}.safetensors", header_update={"metadata": value})
        _expect_corrupt(tmp_path / f"meta{k}.safetensors", "metadata is not a JSON object")
    _rewrite(src, tmp_path / "none.safetensors", header_update={"metadata": None})  # absent metadata is fine
    assert load_gaussians(tmp_path / "none.safetensors")[1] == {}


def test_no_gaussians_and_zero_quaternions_are_refused(tmp_path, model):
    src = tmp_path / "m.safetensors"
    save_gaussians(src, model)
    empty = {k: v[:0].detach().clone().contiguous() for k, v in model.params.items()}
    _rewrite(src, tmp_path / "empty.safetensors", empty)
    _expect_corrupt(tmp_path / "empty.safetensors", "holds no Gaussians")
    for name in ("rotation", "rotation_r"):
        q = model.params[name].detach().clone()
        q[17] = 0.0
        _rewrite(src, tmp_path / f"{name}.safetensors", {name: q})
        _expect_corrupt(tmp_path / f"{name}.safetensors", f"'{name}' holds a zero quaternion")
    q = model.params["rotation"].detach().clone()
    q[17] = torch.tensor([0.0, 0.0, 0.0, 1e-30])  # tiny but not zero: normalizes to a rotation
    _rewrite(src, tmp_path / "tiny.safetensors", {"rotation": q})
    assert load_gaussians(tmp_path / "tiny.safetensors")[0].num_gaussians == 40
