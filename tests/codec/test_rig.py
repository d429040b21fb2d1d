"""The camera rig a compressed file records (omg4.codec.rig): round trip, every validation rule, and the viewer's
presets taken from it."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from omg4.codec.payload import decode_payload
from omg4.codec.rig import check_rig, rig_cameras, rig_json
from omg4.data.scene import Camera, look_at_viewmat
from omg4.errors import CorruptFileError
from omg4.testing import forge


def _cameras() -> list[Camera]:
    K = np.array([[1234.5678901, 0.0, 960.25], [0.0, 1230.125, 540.5], [0.0, 0.0, 1.0]])
    return [Camera(K=K, viewmat=look_at_viewmat(np.array([3.0 * np.cos(a), 3.0 * np.sin(a), 0.7]), np.zeros(3)),
                   width=1920, height=1080, name=f"cam{i:02d}") for i, a in enumerate(np.linspace(0, 1.5, 5))]


def test_a_rig_keeps_every_camera_to_seven_digits_and_which_are_held_out():
    cameras = _cameras()
    rig = rig_json(cameras, 2)
    assert rig["test"] == 2 and len(rig["cameras"]) == 5
    back = [Camera.from_json(c) for c in rig_cameras({"rig": rig})]
    for c, d in zip(cameras, back):
        assert (d.name, d.width, d.height) == (c.name, c.width, c.height)
        np.testing.assert_allclose(d.K, c.K, rtol=1e-6)
        np.testing.assert_allclose(d.viewmat, c.viewmat, rtol=1e-6, atol=1e-6)
    assert rig_cameras({}) is None


@pytest.mark.parametrize("edit, message", [
    (lambda r: r.update(test=6), "test count"),
    (lambda r: r.update(test=True), "test count"),
    (lambda r: r.update(cameras=[]), "test count"),
    (lambda r: r.update(cameras=r["cameras"] * 300), "test count"),
    (lambda r: r["cameras"][1].update(name="x" * 65), "camera 1"),
    (lambda r: r["cameras"][1].update(width=0), "camera 1"),
    (lambda r: r["cameras"][1].update(height=16385), "camera 1"),
    (lambda r: r["cameras"][1].update(width=64.0), "camera 1"),
    (lambda r: r["cameras"][2]["K"].__setitem__(0, 0.0), "camera 2"),
    (lambda r: r["cameras"][2]["K"].__setitem__(3, float("nan")), "camera 2"),
    (lambda r: r["cameras"][2].update(K=[1.0, 1.0, 0.0]), "camera 2"),
    (lambda r: r["cameras"][3]["pose"].__setitem__(11, float("inf")), "camera 3"),
    (lambda r: r["cameras"][3]["pose"].__setitem__(0, 1.01), "no rotation"),
    (lambda r: r["cameras"][3]["pose"].__setitem__(5, 1e300), "no rotation"),
    (lambda r: r["cameras"][3].update(pose=r["cameras"][3]["pose"][:11]), "camera 3"),
])
def test_every_rule_of_a_rig_refuses_a_forged_one(edit, message):
    rig = rig_json(_cameras(), 2)
    check_rig(copy.deepcopy(rig))
    edit(rig)
    with pytest.raises(CorruptFileError, match=message):
        check_rig(rig)


def test_a_rotation_off_by_less_than_the_tolerance_is_a_rotation():
    rig = rig_json(_cameras(), 2)
    rig["cameras"][0]["pose"][0] *= 1.0004  # 0.08 % off: rounding, not forgery
    check_rig(rig)


def test_a_file_with_a_forged_rig_is_a_one_line_error(tmp_path):
    header, sections = forge.split_container(forge.valid_file(tmp_path / "m.omg4", 200, codec="compact"))
    header["meta"]["rig"]["cameras"][0]["width"] = -5
    with pytest.raises(CorruptFileError, match="camera 0"):
        decode_payload(forge.assemble_container(header, sections))


def test_the_viewer_opens_at_the_files_rig_without_the_dataset(tmp_path):
    from omg4.app.viewer import view_presets
    from omg4.models import load_model

    forge.valid_file(tmp_path / "m.omg4", 200, codec="compact")
    presets = view_presets(load_model(tmp_path / "m.omg4"), None)
    assert [c.name for c in presets] == ["cam00", "cam01", "cam02"]
    assert presets[0].width == 64 and np.allclose(presets[0].center, [0.0, -4.0, 1.0], atol=1e-5)
