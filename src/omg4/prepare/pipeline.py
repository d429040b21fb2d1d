"""``omg4 prepare``: a folder of raw multi-view videos (or per-camera image folders) → a dataset every command
reads (N3DV layout), synchronized, calibrated, checked and undistorted (docs/prepare.md).

The dataset holds ``cam00.mp4`` (the test camera) … ``camNN.mp4`` over the span all cameras share,
``poses_bounds.npy`` (the LLFF poses of the undistorted cameras, in the normalized world of the official N3DV
preprocessing, with near/far from the points), ``points3d.ply`` (the calibration's points, coloured from the
frames), ``calibration.json`` (every input camera as calibrated, whether it can be trusted and why not, the
synchronization) and ``rig.png``. It is built beside its target and renamed into place.
"""

from __future__ import annotations

import json
import logging
import os
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from omg4.atomic import atomic_folder
from omg4.data.normalize import official_normalization
from omg4.data.points import write_ply
from omg4.data.scene import Camera, PointCloud
from omg4.data.synthetic.rig import llff_poses_bounds
from omg4.errors import OMG4Error
from omg4.io.video import write_video
from omg4.prepare.calibrate import CalibratedCamera, Calibration, calibrate
from omg4.prepare.camera_model import project, sample
from omg4.prepare.check import CameraCheck, check_and_repair, rig_disagreement
from omg4.prepare.sources import Source, check_frame_rates, find_sources
from omg4.prepare.sync import Offsets, common_span, synchronize
from omg4.prepare.undistort import Undistorter

logger = logging.getLogger(__name__)

MAX_REPROJECTION_PX = 2.0
"""A camera whose points reproject worse than this on average (pixels) is not trusted."""


MATCHED_PAIRS = 4000
"""The calibration matches about this many image pairs: as many instants as that allows, within
:data:`INSTANT_RANGE` (a few cameras pool many instants, a large rig fewer)."""

INSTANT_RANGE = (10, 30)


def default_instants(num_cameras: int) -> int:
    """How many instants the calibration pools for a rig of ``num_cameras`` (see :data:`MATCHED_PAIRS`)."""
    pairs = num_cameras * (num_cameras - 1) // 2
    return int(np.clip(round(MATCHED_PAIRS / max(pairs, 1)), *INSTANT_RANGE))


def prepare_capture(src: str | os.PathLike, out: str | os.PathLike, *, sync: str = "auto",
                    test_camera: str | None = None, shared_intrinsics: bool = False, instants: int | None = None,
                    max_features: int = 8192, image_fps: float = 30.0, threads: int = -1, force: bool = False,
                    progress: bool = False) -> dict:
    """Turn the raw cameras in ``src`` into the dataset ``out`` (see the module docstring); returns the
    ``calibration.json`` record. ``sync``: ``auto``, ``audio``, ``none`` or a file of frames to skip
    (:mod:`omg4.prepare.sync`); ``test_camera``: a source's file name or stem (default: the most central
    camera); ``instants``: how many instants of the shared span the calibration pools (default
    :func:`default_instants`); ``image_fps``: the frame
    rate of image folders; ``threads``: of pycolmap's extraction, matching and mapping (-1: every core; 1: the same
    calibration every run — with more, the order their work finishes in moves the result). Nothing is written into
    ``src``; an existing ``out`` needs ``force``. A capture that
    cannot be calibrated, or whose calibration cannot be trusted, is a one-line :class:`OMG4Error`."""
    started = time.perf_counter()
    src, out = Path(src).resolve(), Path(out).resolve()
    _check_target(src, out, force)
    sources = find_sources(src, image_fps)
    fps = check_frame_rates(sources)
    offsets = synchronize(sources, sync)
    length = common_span(sources, offsets.frames)
    chosen = _instants(length, instants or default_instants(len(sources)))
    logger.info(f"{len(sources)} cameras, {length} shared frames at {fps:g} fps (sync: {offsets.method}); "
                f"calibrating from {len(chosen)} instants")
    frames = {s.stem: [image for _, image in s.frames([k + off for k in chosen])]
              for s, off in zip(_bar(sources, progress, "reading instants"), offsets.frames)}
    with tempfile.TemporaryDirectory(prefix="omg4-prepare-") as work:
        for seed in MAPPER_SEEDS:
            try:
                calibration, checks, kept, halves = _trusted_calibration(frames, work, sources, len(chosen),
                                                                         max_features, shared_intrinsics, seed,
                                                                         threads)
                break
            except UntrustedCalibration as exc:
                refusal = exc
                if seed != MAPPER_SEEDS[-1]:
                    logger.info(f"{exc}; mapping again with the random seed {seed + 1}")
        else:
            raise refusal
    test = _test_source(kept, calibration, test_camera)
    order = [test, *[s for s in kept if s is not test]]
    names = {s.stem: f"cam{i:02d}" for i, s in enumerate(order)}
    undistorters = {s.stem: Undistorter(calibration.cameras[s.stem].K, calibration.cameras[s.stem].distortion,
                                        s.width, s.height) for s in order}
    normalization = _world(calibration, order)
    points = normalization.apply_points(calibration.points)
    colors = point_colors(calibration, frames)
    cameras = {s.stem: _undistorted_camera(calibration.cameras[s.stem], undistorters[s.stem], normalization, s,
                                           names[s.stem]) for s in order}
    record = _record(sources, offsets, length, fps, calibration, checks, names, test, cameras)
    record.update(halves=halves, mapper_seed=seed)
    with atomic_folder(out) as folder:
        _write_videos(folder, order, offsets, sources, length, fps, undistorters, names, progress)
        _write_geometry(folder, order, cameras, points, colors, names)
        (folder / "calibration.json").write_text(json.dumps(record, indent=1) + "\n")
        rig_plot(folder / "rig.png", [cameras[s.stem] for s in order], points, colors, names[test.stem])
    record["wall_time_s"] = time.perf_counter() - started
    return record


MAPPER_SEEDS = (0, 1, 2)
"""The random seeds a capture is mapped with, in turn, until a calibration passes the checks: the incremental
mapper can settle on a solution the evidence does not hold from one seed's draws (the features and matches are
computed once)."""


class UntrustedCalibration(OMG4Error):
    """A calibration the checks refuse (too few cameras hold, or the halves of the instants disagree with it)."""


def _trusted_calibration(frames: dict[str, list[np.ndarray]], work: str, sources: list[Source], count: int,
                         max_features: int, shared_intrinsics: bool, seed: int, threads: int):
    """(calibration, per-camera checks, the sources that hold, the halves' rows) of the rig mapped with ``seed``, or
    :class:`UntrustedCalibration` saying why it cannot be trusted."""
    calibration = calibrate(frames, work, max_features=max_features, shared_intrinsics=shared_intrinsics, seed=seed,
                            threads=threads)
    halves = _halves(frames, work, count, max_features, shared_intrinsics, calibration.lens["distortion"] == "kept",
                     seed, threads)
    calibration, checks = check_and_repair(calibration, {s.stem: (s.width, s.height) for s in sources})
    checks = _reprojection_checks(calibration, checks)
    kept = [s for s in sources if checks[s.stem].reliable]
    if len(kept) < max(2, (len(sources) + 1) // 2):
        worst = next(s for s in sources if not checks[s.stem].reliable)
        raise UntrustedCalibration(f"the calibration cannot be trusted: {len(kept)} of {len(sources)} cameras hold "
                                   f"({worst.name}: {checks[worst.stem].reason})")
    doubt, halves = rig_disagreement({s.stem: calibration.cameras[s.stem] for s in kept}, halves)
    if doubt:
        raise UntrustedCalibration(f"the calibration cannot be trusted: {doubt}")
    return calibration, checks, kept, halves


def _check_target(src: Path, out: Path, force: bool) -> None:
    """Refuse, before any work, an output inside (or holding) the capture and an existing one without ``force``."""
    if out == src or src in out.parents or out in src.parents:
        raise OMG4Error(f"--out {out} must lie outside the capture folder {src} (nothing is written into it)")
    if out.exists() and (not out.is_dir() or any(out.iterdir())) and not force:
        raise OMG4Error(f"--out {out} exists: choose a new folder, or add --force to replace it")


def _halves(frames: dict[str, list[np.ndarray]], work: str, count: int, max_features: int,
            shared_intrinsics: bool, distortion: bool, seed: int, threads: int) -> list[dict[str, CalibratedCamera]]:
    """The rig calibrated again from the even and from the odd ones of its ``count`` instants (the features and
    matches already in ``work``; the whole rig's lens model, ``distortion``), for
    :func:`~omg4.prepare.check.rig_disagreement`; none when there are fewer than four instants, an empty rig for a
    half that cannot be reconstructed. A half left to choose its own lens model can keep a distortion the whole
    rig dropped, and trade focal length for it (10 % on a synthetic rig)."""
    if count < 4:
        logger.info("fewer than four instants: the rig is not calibrated again from each half of them")
        return []
    halves = []
    for part in (list(range(0, count, 2)), list(range(1, count, 2))):
        try:
            halves.append(calibrate(frames, work, max_features=max_features, shared_intrinsics=shared_intrinsics,
                                    instants=part, distortion=distortion, seed=seed, threads=threads).cameras)
        except OMG4Error:
            halves.append({})
    return halves


def _instants(length: int, count: int) -> list[int]:
    """``count`` frames spread evenly over a span of ``length`` (all of them when it is shorter)."""
    count = max(1, min(count, length))
    return sorted({int(round(k * (length - 1) / max(count - 1, 1))) for k in range(count)})


def _bar(items, progress: bool, what: str):
    return tqdm(items, desc=what, unit="camera", disable=not progress)


def _reprojection_checks(calibration: Calibration, checks: dict[str, CameraCheck]) -> dict[str, CameraCheck]:
    """Cameras whose points reproject worse than :data:`MAX_REPROJECTION_PX` are not trusted either."""
    out = dict(checks)
    for name, camera in calibration.cameras.items():
        error = camera.reprojection_error_px
        if out[name].reliable and np.isfinite(error) and error > MAX_REPROJECTION_PX:
            out[name] = replace(out[name], reliable=False,
                                reason=f"its points reproject {error:.2f} px off on average (> {MAX_REPROJECTION_PX})")
    return out


def _test_source(kept: list[Source], calibration: Calibration, name: str | None) -> Source:
    """The source named ``name`` (file name or stem), else the camera nearest the rig's mean centre."""
    if name is not None:
        found = [s for s in kept if name in (s.name, s.stem)]
        if not found:
            raise OMG4Error(f"--test-camera {name}: no trusted camera has that name (trusted: "
                            f"{', '.join(s.name for s in kept)})")
        return found[0]
    centres = np.stack([calibration.cameras[s.stem].center for s in kept])
    return kept[int(np.argmin(np.linalg.norm(centres - centres.mean(0), axis=1)))]


def _world(calibration: Calibration, order: list[Source]):
    """The normalized world of the official N3DV preprocessing for the kept cameras."""
    return official_normalization(np.stack([np.linalg.inv(calibration.cameras[s.stem].w2c) for s in order]))


def point_colors(calibration: Calibration, frames: dict[str, list[np.ndarray]]) -> np.ndarray:
    """Each point's colour in [0, 1]: the median over the cameras that see it of their frame at the instant it
    was seen, where it projects (each camera's calibrated model)."""
    samples: list[list[np.ndarray]] = [[] for _ in range(len(calibration.points))]
    for name, camera in calibration.cameras.items():
        seen = np.array([name in who for who in calibration.point_cameras], dtype=bool)
        if not seen.any():
            continue
        pixels, _ = project(calibration.points[seen], camera.K, camera.distortion, camera.w2c)
        rows = np.nonzero(seen)[0]
        for k, image in enumerate(frames[name]):
            at = calibration.point_instants[rows] == k
            for row, color in zip(rows[at], sample(image, pixels[at], radius=0)):
                samples[row].append(color)
    return np.array([np.median(s, axis=0) if s else (0.5, 0.5, 0.5) for s in samples]).reshape(-1, 3)


def _undistorted_camera(camera: CalibratedCamera, undistorter: Undistorter, normalization, source: Source,
                        name: str):
    return Camera(K=undistorter.K, viewmat=normalization.apply_viewmat(camera.w2c), width=source.width,
                  height=source.height, name=name)


def _near_far(camera, points: np.ndarray) -> tuple[float, float]:
    """Depth bounds of the points a camera sees (LLFF's near/far): 0.9 × the 1st and 1.1 × the 99th percentile of
    their depths; the rig's scale when it sees none."""
    cam = points @ camera.viewmat[:3, :3].T + camera.viewmat[:3, 3]
    uv = cam[:, :2] / np.maximum(cam[:, 2:], 1e-9) @ camera.K[:2, :2].T + camera.K[:2, 2]
    inside = (cam[:, 2] > 1e-6) & (uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] >= 0) & \
        (uv[:, 1] < camera.height)
    depths = cam[inside, 2]
    if len(depths) < 10:
        distance = float(np.linalg.norm(camera.center))
        return 0.1 * distance, 3.0 * distance
    return 0.9 * float(np.percentile(depths, 1)), 1.1 * float(np.percentile(depths, 99))


def _write_videos(folder: Path, order: list[Source], offsets: Offsets, sources: list[Source], length: int,
                  fps: float, undistorters: dict[str, Undistorter], names: dict[str, str], progress: bool) -> None:
    skip = {s.stem: k for s, k in zip(sources, offsets.frames)}
    for source in _bar(order, progress, "writing videos"):
        first = skip[source.stem]
        undistort = undistorters[source.stem]
        frames = (undistort(image) for _, image in source.frames(list(range(first, first + length))))
        write_video(folder / f"{names[source.stem]}.mp4", frames, fps=fps, reproducible=True)


def _write_geometry(folder: Path, order: list[Source], cameras: dict, points: np.ndarray, colors: np.ndarray,
                    names: dict[str, str]) -> None:
    rig = [cameras[s.stem] for s in order]
    bounds = np.array([_near_far(c, points) for c in rig])
    np.save(folder / "poses_bounds.npy", llff_poses_bounds(rig, bounds[:, 0], bounds[:, 1]))
    write_ply(folder / "points3d.ply", PointCloud(xyz=points.astype(np.float32), rgb=colors.astype(np.float32)))


def _record(sources: list[Source], offsets: Offsets, length: int, fps: float, calibration: Calibration,
            checks: dict[str, CameraCheck], names: dict[str, str], test: Source, cameras: dict) -> dict:
    """``calibration.json``: per input camera its calibration as estimated (before resampling) and its verdict."""
    entries = []
    for source, skipped, confidence in zip(sources, offsets.frames, offsets.confidence):
        camera = calibration.cameras.get(source.stem)
        check = checks[source.stem]
        entry = {"source": source.name, "name": names.get(source.stem), "reliable": check.reliable,
                 "offset_frames": int(skipped)}
        if confidence is not None:
            entry["sync_confidence"] = confidence if np.isfinite(confidence) else None
        if camera is not None:
            entry.update(K=camera.K.tolist(), distortion={"model": "radial", "k1": camera.distortion[0],
                                                          "k2": camera.distortion[1]},
                         w2c=camera.w2c.tolist(), reprojection_error_px=_finite(camera.reprojection_error_px),
                         observations=camera.observations)
        entry.update(match_agreement=check.agreement, reregistered=check.reregistered)
        if check.reason:
            entry["reason"] = check.reason
        if source.stem in cameras:
            entry["undistorted_K"] = cameras[source.stem].K.tolist()
        entries.append(entry)
    return {"reliable": all(c.reliable for c in checks.values()), "fps": fps, "frames": length,
            "sync": offsets.method, "test_camera": names[test.stem], "test_source": test.name,
            "lens": calibration.lens,
            "world": "w2c: the calibration's own world (OpenCV axes); poses_bounds.npy: the normalized world",
            "cameras": entries}


def _finite(value: float):
    return float(value) if np.isfinite(value) else None


def rig_plot(path: Path, cameras: list, points: np.ndarray, colors: np.ndarray, test: str) -> None:
    """A picture of the rig: each camera's centre and viewing direction (the test camera in red) above the
    calibration's points, seen from above and from the side."""
    import matplotlib  # matplotlib loads only where a plot is drawn

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # matplotlib loads only where a plot is drawn

    rng = np.random.default_rng(0)
    shown = rng.choice(len(points), min(len(points), 4000), replace=False) if len(points) else np.zeros(0, int)
    centres = np.stack([c.center for c in cameras])
    if len(shown):  # the scene, not its stray points: the points' 2nd–98th percentiles and the cameras
        low, high = np.percentile(points[shown], 2, axis=0), np.percentile(points[shown], 98, axis=0)
        low, high = np.minimum(low, centres.min(0)), np.maximum(high, centres.max(0))
        shown = shown[np.all((points[shown] >= low) & (points[shown] <= high), axis=1)]
    forwards = np.stack([c.viewmat[2, :3] for c in cameras])
    scale = 0.15 * float(np.ptp(centres, axis=0).max() or 1.0)
    figure, axes = plt.subplots(1, 2, figsize=(11, 5))
    for ax, (i, j, label) in zip(axes, ((0, 1, "from above (x, y)"), (0, 2, "from the side (x, z)"))):
        ax.scatter(points[shown, i], points[shown, j], s=1, c=np.clip(colors[shown], 0, 1))
        for camera, c, f in zip(cameras, centres, forwards):
            color = "red" if camera.name == test else "black"
            ax.plot([c[i], c[i] + scale * f[i]], [c[j], c[j] + scale * f[j]], color=color)
            ax.scatter([c[i]], [c[j]], color=color, s=30 if camera.name == test else 12, zorder=3)
            ax.annotate(camera.name, (c[i], c[j]), fontsize=6)
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_title(label)
    figure.suptitle(f"{len(cameras)} cameras ({test}: the test camera, red), {len(points)} points")
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)


__all__ = ["INSTANT_RANGE", "MATCHED_PAIRS", "MAX_REPROJECTION_PX", "default_instants", "point_colors", "prepare_capture",
           "rig_plot"]
