"""The raw cameras of a capture: a folder of videos (any names, any container and codec PyAV reads) or of
per-camera image folders.

Each :class:`Source` knows its frame count, size and frame rate (image folders take the rate they are given),
reads chosen frames (:meth:`Source.frames`) and, for a video with sound, its audio as mono samples
(:meth:`Source.audio`). Nothing is written next to the inputs.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import av
import numpy as np
from PIL import Image

from omg4.data.frame_cache import probe_video
from omg4.errors import DataError, OMG4Error

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")
AUDIO_RATE = 16_000
"""Sample rate audio is read at for synchronization (Hz)."""


@dataclass
class Source:
    """One camera's raw frames.

    Attributes:
        path: the video file or image folder.
        name: its name in messages and ``calibration.json`` (the file or folder name).
        num_frames, width, height: frame count and size.
        fps: frame rate (frames per second).
        images: an image folder's files in order (None for a video).
        has_audio: a video with an audio stream.
    """

    path: Path
    name: str
    num_frames: int
    width: int
    height: int
    fps: float
    images: list[Path] | None = None
    has_audio: bool = False

    @property
    def stem(self) -> str:
        return Path(self.name).stem

    def frames(self, indices: list[int]) -> Iterator[tuple[int, np.ndarray]]:
        """``(index, uint8 [H, W, 3])`` of each frame in ``indices`` (sorted, within the source), in order."""
        wanted = sorted(set(indices))
        if not wanted:
            return
        if self.images is not None:
            for i in wanted:
                yield i, _read_image(self.images[i], self.width, self.height)
            return
        position, next_wanted = 0, iter(wanted)
        target = next(next_wanted)
        try:
            with av.open(str(self.path)) as container:
                stream = container.streams.video[0]
                stream.thread_type = "AUTO"
                for frame in container.decode(stream):
                    if position == target:
                        yield position, frame.to_ndarray(format="rgb24")
                        target = next(next_wanted, None)
                        if target is None:
                            return
                    position += 1
        except (av.error.FFmpegError, OSError, ValueError) as exc:
            raise DataError(f"cannot decode {self.path} at frame {position}: {exc}") from None
        raise DataError(f"{self.path} has only {position} decodable frames, frame {target} needed")

    def audio(self, max_seconds: float | None = None) -> np.ndarray:
        """The audio track as mono float32 samples at :data:`AUDIO_RATE` (the first ``max_seconds`` of it)."""
        if not self.has_audio:
            raise OMG4Error(f"{self.name} has no audio track")
        resampler = av.AudioResampler(format="flt", layout="mono", rate=AUDIO_RATE)
        chunks, total = [], 0
        limit = None if max_seconds is None else int(max_seconds * AUDIO_RATE)
        try:
            with av.open(str(self.path)) as container:
                for frame in container.decode(container.streams.audio[0]):
                    for out in resampler.resample(frame):
                        chunk = out.to_ndarray().reshape(-1)
                        chunks.append(chunk)
                        total += len(chunk)
                    if limit is not None and total >= limit:
                        break
                for out in resampler.resample(None):
                    chunks.append(out.to_ndarray().reshape(-1))
        except (av.error.FFmpegError, OSError, ValueError) as exc:
            raise DataError(f"cannot decode the audio of {self.path}: {exc}") from None
        samples = np.concatenate(chunks).astype(np.float32) if chunks else np.zeros(0, np.float32)
        return samples if limit is None else samples[:limit]


def _read_image(path: Path, width: int, height: int) -> np.ndarray:
    try:
        with Image.open(path) as img:
            rgb = np.asarray(img.convert("RGB"))
    except (OSError, ValueError) as exc:
        raise DataError(f"cannot read image {path}: {exc}") from None
    if rgb.shape[:2] != (height, width):
        raise DataError(f"{path} is {rgb.shape[1]}x{rgb.shape[0]}, the folder's first image {width}x{height}")
    return rgb


def find_sources(src: str | Path, image_fps: float = 30.0) -> list[Source]:
    """The cameras in the folder ``src``: its video files, or its subfolders of images (one per camera), in name
    order. Other files (notes, a ``.DS_Store``) are skipped; a file that looks like a video but cannot be read is
    a one-line error naming it, and so is a folder with fewer than two cameras."""
    src = Path(src)
    if not src.is_dir():
        raise OMG4Error(f"{src} is not a folder of videos or of per-camera image folders")
    entries = sorted(p for p in src.iterdir() if not p.name.startswith("."))
    folders = [p for p in entries if p.is_dir() and _images_in(p)]
    files = [p for p in entries if p.is_file() and p.suffix.lower() not in IMAGE_SUFFIXES + (".json", ".txt", ".md")]
    if folders and files:
        raise OMG4Error(f"{src} holds both videos ({files[0].name}) and image folders ({folders[0].name}): give "
                        "one kind")
    sources = [_image_source(p, image_fps) for p in folders] if folders else [_video_source(p) for p in files]
    if len(sources) < 2:
        raise OMG4Error(f"{src} holds {len(sources)} camera{'s' if len(sources) != 1 else ''}: a multi-view capture "
                        "needs at least two videos (or image folders)")
    return sources


def _images_in(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)


def _image_source(folder: Path, fps: float) -> Source:
    images = _images_in(folder)
    with Image.open(images[0]) as first:
        width, height = first.size
    return Source(path=folder, name=folder.name, num_frames=len(images), width=width, height=height, fps=fps,
                  images=images)


def _video_source(path: Path) -> Source:
    try:
        info = probe_video(path)
    except DataError as exc:
        raise OMG4Error(f"{path.name}: not a readable video ({exc})") from None
    try:
        with av.open(str(path)) as container:
            has_audio = bool(container.streams.audio)
    except (av.error.FFmpegError, OSError):
        has_audio = False
    return Source(path=path, name=path.name, num_frames=info.num_frames, width=info.width, height=info.height,
                  fps=info.fps, has_audio=has_audio)


def check_frame_rates(sources: list[Source], tolerance: float = 1e-3) -> float:
    """The capture's frame rate; sources whose rates differ are a one-line error naming them."""
    reference = sources[0]
    odd = [s for s in sources if abs(s.fps - reference.fps) > tolerance * reference.fps]
    if odd:
        raise OMG4Error(f"frame rates differ: {reference.name} {reference.fps:g} fps, {odd[0].name} {odd[0].fps:g} "
                        "fps (convert the videos to one rate first)")
    return reference.fps


__all__ = ["AUDIO_RATE", "IMAGE_SUFFIXES", "Source", "check_frame_rates", "find_sources"]
