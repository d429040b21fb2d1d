"""Decode-once frame cache for videos (N3DV ``camXX.mp4``): uint8 frames in a memory-mapped ``.npy``.

Full N3DV (20 cameras × 300 frames × 1352×1014) is 24.7 GB as uint8 and four times that as
float32, so frames are decoded once with PyAV into an on-disk ``[F, H, W, 3]`` uint8 array
and read back through ``np.load(mmap_mode="r")``; a view converts its one frame to float32
only when asked (:meth:`FrameCache.image`).

Cache files live in one folder (``$OMG4_CACHE_DIR``, else ``~/.cache/omg4/frames``) and are
named ``<video stem>-<key>.npy`` where the key hashes the video's resolved path, size and
mtime and the decode options (output size, resize filter, cache version): a changed video
or a different resolution never reuses a stale cache. A cache holds the frames from its first one on:
from frame 0 (a prefix), so a run on frames 0–49 reuses a cache of all 300 frames, or, when no prefix
covers a later range, from its first frame (a window: one segment of a long capture, :mod:`omg4.data.segments`,
holds only its own frames on disk); asking for more frames than cached decodes a longer one and replaces the
file. Files are written with
:func:`omg4.atomic.atomic_path`: a crashed decode leaves at most a ``.tmp`` file, never a
cache that looks complete. Stale entries are not deleted automatically.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import av
import numpy as np

from omg4.atomic import atomic_path
from omg4.data.images import resize_rgb, to_float
from omg4.errors import DataError

CACHE_VERSION = 1
RESIZE_FILTER = "pil-bicubic"


@dataclass(frozen=True)
class VideoInfo:
    """Stream metadata of a video, read without decoding frames.

    Attributes:
        path: the video file.
        num_frames: frame count from the container (estimated from duration × rate when the
            container does not store it, else counted from the stream's packets).
        width, height: frame size in pixels.
        fps: average frame rate.
    """

    path: Path
    num_frames: int
    width: int
    height: int
    fps: float


def probe_video(path: Path) -> VideoInfo:
    """Metadata of ``path``'s first video stream; :class:`DataError` if it cannot be opened."""
    try:
        with av.open(str(path)) as container:
            if not container.streams.video:
                raise DataError(f"{path} contains no video stream")
            stream = container.streams.video[0]
            fps = float(stream.average_rate) if stream.average_rate else 0.0
            count = int(stream.frames or 0)
            if count == 0 and stream.duration and stream.time_base and fps > 0:
                count = int(round(float(stream.duration * stream.time_base) * fps))
            width, height = int(stream.codec_context.width), int(stream.codec_context.height)
            if count == 0:  # a container that records neither (Matroska, WebM): count the packets, no decoding
                count = sum(1 for packet in container.demux(stream) if packet.size)
    except FileNotFoundError:
        raise DataError(f"missing video file {path}") from None
    except (av.error.FFmpegError, OSError, ValueError) as e:
        raise DataError(f"cannot open video {path} (corrupt or not a video): {e}") from None
    if count <= 0 or width <= 0 or height <= 0:
        raise DataError(f"video {path} reports no frames (corrupt or empty)")
    return VideoInfo(path=Path(path), num_frames=count, width=width, height=height, fps=fps)


class FrameCache:
    """Frames ``first … num_frames − 1`` of one video at ``width × height``, as uint8 on disk.

    Args:
        video: the probed video.
        width, height: output frame size (frames are resized with PIL bicubic when it differs
            from the video's size).
        num_frames: frames up to this one (exclusive) must be available.
        cache_dir: folder of the cache files.
        first: the first frame the cache holds (0: a prefix of the video).
    """

    def __init__(self, video: VideoInfo, width: int, height: int, num_frames: int, cache_dir: Path, first: int = 0):
        self.video = video
        self.width, self.height = int(width), int(height)
        self.num_frames = int(num_frames)
        self.first = int(first)
        self.cache_dir = Path(cache_dir)
        self._frames: np.ndarray | None = None
        self._base = 0  # the video frame of the open cache's row 0

    @property
    def path(self) -> Path:
        """The cache file this cache decodes into: ``<cache_dir>/<stem>-<key>.npy``."""
        return self._path_for(self.first)

    def _path_for(self, first: int) -> Path:
        src = self.video.path.resolve()
        st = src.stat()
        fields = {"v": CACHE_VERSION, "path": str(src), "size": st.st_size, "mtime_ns": st.st_mtime_ns,
                  "w": self.width, "h": self.height, "filter": RESIZE_FILTER}
        if first:  # a window (prefix caches keep the key they always had)
            fields["first"] = first
        key = json.dumps(fields, sort_keys=True)
        return self.cache_dir / f"{src.stem}-{hashlib.sha256(key.encode()).hexdigest()[:20]}.npy"

    def is_cached(self) -> bool:
        """Whether a complete cache file with at least ``num_frames`` frames exists."""
        return self._open_existing() is not None

    def ensure(self, on_frame: Callable[[], None] | None = None) -> None:
        """Open the cache, decoding the video first if it is absent or too short.

        ``on_frame`` is called once per decoded frame (progress bars).
        """
        if self._frames is not None:
            return
        opened = self._open_existing()
        if opened is None:
            self._decode(on_frame)
            opened = self._open_existing()
            if opened is None:
                raise DataError(f"frame cache {self.path} is unreadable after decoding")
        self._frames, self._base = opened

    def frame(self, index: int) -> np.ndarray:
        """uint8 [H, W, 3] of frame ``index`` of the video (a read-only view into the memory map)."""
        if not self.first <= index < self.num_frames:
            raise DataError(f"frame {index} of {self.video.path} is outside the cached frames "
                            f"{self.first}-{self.num_frames - 1}")
        self.ensure()
        return self._frames[index - self._base]

    def image(self, index: int) -> np.ndarray:
        """float32 [H, W, 3] in [0, 1] of frame ``index`` (what a view's loader returns)."""
        return to_float(self.frame(index))

    def __getstate__(self) -> dict:
        # Worker processes reopen the memory map instead of receiving a copy of it.
        state = dict(self.__dict__)
        state["_frames"] = None
        return state

    def _open_existing(self) -> tuple[np.ndarray, int] | None:
        """(frames, first frame) of a complete cache covering the frames asked for: a prefix long enough, else this
        cache's own window; None when neither exists."""
        for first in dict.fromkeys((0, self.first)):
            path = self._path_for(first)
            if not path.exists():
                continue
            try:
                frames = np.load(path, mmap_mode="r")
            except (OSError, ValueError):
                continue
            if frames.dtype == np.uint8 and frames.shape[1:] == (self.height, self.width, 3) and \
                    frames.shape[0] >= self.num_frames - first:
                return frames, first
        return None

    def _decode(self, on_frame: Callable[[], None] | None) -> None:
        """Decode frames ``first … num_frames − 1`` into a temporary memmap (earlier frames are decoded and
        dropped), then rename it into place."""
        shape = (self.num_frames - self.first, self.height, self.width, 3)
        decoded = 0
        with atomic_path(self.path) as tmp:
            out = np.lib.format.open_memmap(tmp, mode="w+", dtype=np.uint8, shape=shape)
            try:
                with av.open(str(self.video.path)) as container:
                    stream = container.streams.video[0]
                    stream.thread_type = "AUTO"
                    for frame in container.decode(stream):
                        if decoded >= self.first:
                            out[decoded - self.first] = resize_rgb(frame.to_ndarray(format="rgb24"), self.width,
                                                                   self.height)
                            if on_frame is not None:
                                on_frame()
                        decoded += 1
                        if decoded == self.num_frames:
                            break
            except (av.error.FFmpegError, OSError, ValueError) as e:
                raise DataError(f"cannot decode video {self.video.path} at frame {decoded} (corrupt?): {e}") from None
            if decoded < self.num_frames:
                raise DataError(f"video {self.video.path} has only {decoded} decodable frames, "
                                f"{self.num_frames} needed")
            out.flush()
            del out
