"""``omg4 prepare`` says how to install pycolmap before it reads a video, where pycolmap is missing (its own module, so
that the calibration tests of ``test_prepare.py`` keep their process to themselves under pytest-xdist)."""

from __future__ import annotations

from omg4.app.cli import main


def test_prepare_without_pycolmap_says_the_pip_command_before_reading_a_video(tmp_path, monkeypatch, capsys):
    import sys

    raw = tmp_path / "videos"
    raw.mkdir()
    (raw / "cam_a.mp4").write_bytes(b"not a video: reading it would fail with another message")
    monkeypatch.setitem(sys.modules, "pycolmap", None)  # as if it were not installed
    assert main(["prepare", str(raw), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "pip install 'pycolmap" in err
    assert not (tmp_path / "out").exists()
