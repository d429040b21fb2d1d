"""Raw captures for the ``omg4 prepare`` tests: a synthetic scene's videos cut to planted start offsets, renamed,
with a shared audio track (a fixed noise over the scene's timeline) in each, and no poses."""

from __future__ import annotations

from pathlib import Path

import av
import numpy as np

from omg4.io.video import write_video

AUDIO_RATE = 16_000


def shared_audio(seconds: float, seed: int = 0) -> np.ndarray:
    """A noise track as int16 samples at :data:`AUDIO_RATE`: every window of it is unlike every other."""
    rng = np.random.default_rng(seed)
    return (rng.normal(0, 6000, int(seconds * AUDIO_RATE))).clip(-32000, 32000).astype(np.int16)


def decoded(video: Path) -> list[np.ndarray]:
    with av.open(str(video)) as container:
        return [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]


def write_clip(path: Path, frames: list[np.ndarray], fps: int, audio: np.ndarray | None) -> None:
    """H.264 video (and PCM audio in the same .mkv) of ``frames`` at ``fps``."""
    write_video(path, frames, fps=fps, crf=12, audio=None if audio is None else (audio, AUDIO_RATE))


def raw_capture(scene: Path, out: Path, late: list[int], fps: int = 30, audio: bool = True,
                names: list[str] | None = None) -> list[str]:
    """Write camera i of the N3DV ``scene`` as ``out/<names[i]>.mkv`` starting ``late[i]`` frames into the clip, with
    the shared audio from that instant; returns the file names. The frames each must skip to start together are
    ``max(late) - late[i]``."""
    out.mkdir(parents=True, exist_ok=True)
    videos = sorted(scene.glob("cam*.mp4"))
    names = names or [f"phone_{chr(65 + i)}" for i in range(len(videos))]
    clips = [decoded(v) for v in videos]
    track = shared_audio(len(clips[0]) / fps + 1.0) if audio else None
    files = []
    for name, frames, start in zip(names, clips, late):
        sound = track[start * AUDIO_RATE // fps:] if track is not None else None
        write_clip(out / f"{name}.mkv", frames[start:], fps, sound)
        files.append(f"{name}.mkv")
    return files
