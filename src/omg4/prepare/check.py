"""Whether a calibration can be trusted, camera by camera, and the repair of cameras it placed wrongly.

Geometry can be fooled: on a dome of repeated panels incremental mapping registers a camera where the panels it
sees repeat, its own observations agree with that place, and independent subsets of instants converge to the same
wrong pose. What gives it away is the rest of its evidence: of the matches the camera verified with every other
camera (all instants pooled), a correct pose explains most (:func:`match_agreement`); the wrong one explains a
fraction of what the rig's other cameras do. Such a camera is registered again by RANSAC from all its matches to
the points the others reconstructed (:func:`reregister`); if its matches still disagree it is unreliable and is
left out of the dataset, with the reason.

A whole rig can be wrong too: the mapper can settle on focal lengths far from the truth with every pose bent to
match them, and then every camera agrees with every other. Such a solution is a path the mapper happened to take,
not what the evidence holds: the rig calibrated again from each half of the instants (alternate ones) does not
reproduce it (:func:`rig_disagreement`, :func:`pose_differences`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from omg4.prepare.calibrate import CalibratedCamera, Calibration

MATCH_TOLERANCE_PX = 4.0
"""A match agrees with two calibrated cameras when its Sampson distance is below this (pixels)."""

AGREEMENT_RATIO = 0.5
"""A camera whose matches agree at less than this fraction of the rig's median agreement is suspect."""

HALVES_ROTATION_DEG = 8.0
"""A calibration from half the instants that turns the rig's cameras by more than this (median) does not reproduce
it. Halves of good calibrations (mapped with the whole rig's lens model) lie 0.05–0.40° from the whole on synthetic
rigs and 2–3° on the Panoptic dome; the wrong rigs seen lay 6–20° off, and far off in focal length too."""

HALVES_FOCAL_PCT = 20.0
"""... nor one that changes their focal lengths by more than this many percent (median): good halves 0.2–2.8 %, the
wrong rigs seen 33–96 %."""


@dataclass
class CameraCheck:
    """The verdict on one camera: ``agreement`` (the fraction of its verified matches its pose explains),
    ``reliable``, ``reason`` (empty when reliable) and ``reregistered`` (its pose was estimated again)."""

    agreement: float
    reliable: bool
    reason: str = ""
    reregistered: bool = False


def undistorted_rays(pixels: np.ndarray, camera: CalibratedCamera, iterations: int = 20) -> np.ndarray:
    """Homogeneous normalized undistorted coordinates [N, 3] of pixels [N, 2] (fixed-point inversion of the
    radial model)."""
    f, cx, cy = camera.K[0, 0], camera.K[0, 2], camera.K[1, 2]
    k1, k2 = camera.distortion
    xd, yd = (pixels[:, 0] - cx) / f, (pixels[:, 1] - cy) / f
    x, y = xd.copy(), yd.copy()
    for _ in range(iterations):
        r2 = x * x + y * y
        d = 1.0 + k1 * r2 + k2 * r2 * r2
        x, y = xd / d, yd / d
    return np.stack([x, y, np.ones_like(x)], axis=1)


def sampson_px(a: CalibratedCamera, b: CalibratedCamera, pa: np.ndarray, pb: np.ndarray) -> np.ndarray:
    """Sampson distance (in pixels of ``a``'s focal length) of matched pixels ``pa``, ``pb`` [N, 2] under the
    relative pose of the two calibrated cameras."""
    R = b.w2c[:3, :3] @ a.w2c[:3, :3].T
    t = b.w2c[:3, 3] - R @ a.w2c[:3, 3]
    E = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]]) @ R
    xa, xb = undistorted_rays(pa, a), undistorted_rays(pb, b)
    Ex, Etx = xa @ E.T, xb @ E
    numerator = np.sum(xb * Ex, axis=1) ** 2
    denominator = Ex[:, 0] ** 2 + Ex[:, 1] ** 2 + Etx[:, 0] ** 2 + Etx[:, 1] ** 2
    return np.sqrt(numerator / np.maximum(denominator, 1e-30)) * a.K[0, 0]


def match_agreement(cameras: dict[str, CalibratedCamera], keypoints: dict[str, np.ndarray],
                    matches: dict[tuple[str, str], np.ndarray]) -> dict[str, float]:
    """Per calibrated camera, the fraction of its verified matches with the other calibrated cameras that their
    poses explain (Sampson distance < :data:`MATCH_TOLERANCE_PX`)."""
    agree = {name: [0, 0] for name in cameras}
    for (a, b), m in matches.items():
        if a not in cameras or b not in cameras or not len(m):
            continue
        ok = int((sampson_px(cameras[a], cameras[b], keypoints[a][m[:, 0]], keypoints[b][m[:, 1]])
                  < MATCH_TOLERANCE_PX).sum())
        for name in (a, b):
            agree[name][0] += ok
            agree[name][1] += len(m)
    return {name: (ok / total if total else 0.0) for name, (ok, total) in agree.items()}


def suspects(agreement: dict[str, float]) -> list[str]:
    """The cameras whose agreement is below :data:`AGREEMENT_RATIO` of the rig's median."""
    median = float(np.median(list(agreement.values())))
    return sorted(n for n, a in agreement.items() if a < AGREEMENT_RATIO * median)


def reregister(camera: CalibratedCamera, name: str, calibration: Calibration, trusted: set[str],
               refine_intrinsics: bool = False) -> CalibratedCamera | None:
    """A new pose for camera ``name`` (intrinsics from ``camera``, refined too with ``refine_intrinsics``) by
    LO-RANSAC PnP (pycolmap) from all its matches to the points the ``trusted`` cameras observe; None when there
    are too few correspondences or no pose is found."""
    import pycolmap  # pycolmap (a 38 MB extension) loads only where a capture is calibrated

    pixels, points = [], []
    for (a, b), m in calibration.matches.items():
        if name not in (a, b):
            continue
        other, mine, theirs = (b, m[:, 0], m[:, 1]) if a == name else (a, m[:, 1], m[:, 0])
        if other not in trusted:
            continue
        seen = calibration.observations.get(other, {})
        for k_mine, k_theirs in zip(mine, theirs):
            index = seen.get(int(k_theirs))
            if index is not None:
                pixels.append(calibration.keypoints[name][k_mine])
                points.append(calibration.points[index])
    if len(pixels) < 12:
        return None
    colmap_camera = pycolmap.Camera(model="RADIAL", width=int(round(2 * camera.K[0, 2])),
                                    height=int(round(2 * camera.K[1, 2])),
                                    params=[camera.K[0, 0], camera.K[0, 2], camera.K[1, 2], *camera.distortion])
    estimation = pycolmap.AbsolutePoseEstimationOptions()
    estimation.ransac.max_error = MATCH_TOLERANCE_PX
    refinement = pycolmap.AbsolutePoseRefinementOptions()
    refinement.refine_focal_length = refinement.refine_extra_params = refine_intrinsics
    result = pycolmap.estimate_and_refine_absolute_pose(np.asarray(pixels, np.float64), np.asarray(points, np.float64),
                                                        colmap_camera, estimation_options=estimation,
                                                        refinement_options=refinement)
    if not result:
        return None
    w2c = np.eye(4)
    w2c[:3] = result["cam_from_world"].matrix()
    f, cx, cy, k1, k2 = (float(v) for v in colmap_camera.params)
    return replace(camera, w2c=w2c, K=np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]]), distortion=(k1, k2))


def check_and_repair(calibration: Calibration, image_sizes: dict[str, tuple[int, int]]
                     ) -> tuple[Calibration, dict[str, CameraCheck]]:
    """The calibration with its suspect (and unregistered) cameras registered again where that makes their matches
    agree, and the verdict on every camera; ``image_sizes[name] = (width, height)``."""
    cameras = dict(calibration.cameras)
    agreement = match_agreement(cameras, calibration.keypoints, calibration.matches)
    median = float(np.median(list(agreement.values()))) if agreement else 0.0
    flagged = set(suspects(agreement)) | set(calibration.unregistered)
    trusted = set(cameras) - flagged
    checks = {name: CameraCheck(agreement[name], True) for name in trusted}
    for name in sorted(flagged):
        before = agreement.get(name, 0.0)
        start = cameras.get(name) or _fresh_camera(cameras, image_sizes[name])
        repaired = reregister(start, name, calibration, trusted, refine_intrinsics=name not in cameras)
        if repaired is not None:
            after = match_agreement({**{n: cameras[n] for n in trusted}, name: repaired}, calibration.keypoints,
                                    calibration.matches)[name]
            if after >= AGREEMENT_RATIO * median:
                cameras[name] = repaired
                checks[name] = CameraCheck(after, True, reregistered=True)
                continue
        cameras.pop(name, None)
        reason = ("the reconstruction did not register it" if name in calibration.unregistered else
                  f"its matches contradict its pose ({before:.0%} agree, the rig's median {median:.0%})")
        checks[name] = CameraCheck(before, False, reason + ", and registering it again did not help")
    unreliable = sorted(n for n, c in checks.items() if not c.reliable)
    return replace(calibration, cameras=cameras, unregistered=unreliable), checks


def pose_differences(estimated: dict[str, tuple[np.ndarray, float]], reference: dict[str, tuple[np.ndarray, float]]
                     ) -> dict:
    """How far the cameras of ``estimated`` lie from those of ``reference`` (both: name → (w2c [4, 4], focal)), on
    the cameras both hold, after one similarity: the rotation that best aligns the orientations (chordal mean),
    then the scale from the centres. Rotation differences in degrees, centre differences in % of the reference
    rig's diameter, focal-length differences in %; medians, maxima and per camera."""
    names = sorted(set(estimated) & set(reference))
    if len(names) < 2:
        return {"cameras": len(names), "of": len(reference)}
    rotation = lambda m: m[:3, :3]  # noqa: E731
    centre = lambda m: -m[:3, :3].T @ m[:3, 3]  # noqa: E731
    M = sum(rotation(reference[n][0]).T @ rotation(estimated[n][0]) for n in names)
    U, _, Vt = np.linalg.svd(M)
    R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    angles = [float(np.degrees(np.arccos(np.clip((np.trace(rotation(estimated[n][0]) @ R.T
                                                           @ rotation(reference[n][0]).T) - 1) / 2, -1, 1))))
              for n in names]
    ours = np.stack([centre(estimated[n][0]) for n in names]) @ R.T
    true = np.stack([centre(reference[n][0]) for n in names])
    ours, true = ours - ours.mean(0), true - true.mean(0)
    scale = (ours * true).sum() / max((ours ** 2).sum(), 1e-30)
    diameter = max(max(np.linalg.norm(a - b) for a in true for b in true), 1e-30)
    centres = [float(c) for c in 100 * np.linalg.norm(scale * ours - true, axis=1) / diameter]
    focal = [100 * abs(estimated[n][1] / reference[n][1] - 1) for n in names]
    return {"cameras": len(names), "of": len(reference), "rotation_deg_median": float(np.median(angles)),
            "rotation_deg_max": float(np.max(angles)), "centre_pct_median": float(np.median(centres)),
            "centre_pct_max": float(np.max(centres)), "focal_pct_median": float(np.median(focal)),
            "focal_pct_max": float(np.max(focal)),
            "per_camera": {n: {"rotation_deg": a, "centre_pct": c} for n, a, c in zip(names, angles, centres)}}


def rig_disagreement(cameras: dict[str, CalibratedCamera], halves: list[dict[str, CalibratedCamera]]
                     ) -> tuple[str | None, list[dict]]:
    """Why the rig ``cameras`` (the trusted ones) cannot be trusted, or None; and how far each calibration of
    ``halves`` (from half the instants) lies from it (:func:`pose_differences`, per-camera rows left out). A half
    reproduces the rig when it holds at least three of its cameras, turns them by at most
    :data:`HALVES_ROTATION_DEG` and changes their focal lengths by at most :data:`HALVES_FOCAL_PCT` (medians). The
    rig is not trusted when some half can be compared and none reproduces it: with half the evidence a half can
    lose its way too, but not every half the same way the whole did."""
    as_pairs = lambda cams: {n: (c.w2c, float(c.K[0, 0])) for n, c in cams.items()}  # noqa: E731
    rows = []
    for half in halves:
        row = pose_differences(as_pairs(half), as_pairs(cameras))
        row.pop("per_camera", None)
        rows.append(row)
    compared = [row for row in rows if row["cameras"] >= 3]
    if not compared or any(row["rotation_deg_median"] <= HALVES_ROTATION_DEG
                           and row["focal_pct_median"] <= HALVES_FOCAL_PCT for row in compared):
        return None, rows
    closest = min(compared, key=lambda row: row["rotation_deg_median"])
    return (f"calibrated again from each half of the instants alone, the rig differs by at least "
            f"{closest['rotation_deg_median']:.1f}° and {min(r['focal_pct_median'] for r in compared):.0f} % in "
            f"focal length (medians; at most {HALVES_ROTATION_DEG:g}° and {HALVES_FOCAL_PCT:g} % hold): a solution "
            "the mapper settled on, not one the evidence holds"), rows


def _fresh_camera(cameras: dict[str, CalibratedCamera], size: tuple[int, int]) -> CalibratedCamera:
    """A starting camera of ``size`` for one the reconstruction missed: the median focal length (relative to the
    width) of the others, a centred principal point, no distortion."""
    width, height = size
    focal = float(np.median([c.K[0, 0] / (2 * c.K[0, 2]) for c in cameras.values()])) * width
    K = np.array([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]])
    return CalibratedCamera(K=K, distortion=(0.0, 0.0), w2c=np.eye(4), reprojection_error_px=float("nan"),
                            observations=0)


__all__ = ["AGREEMENT_RATIO", "HALVES_FOCAL_PCT", "HALVES_ROTATION_DEG", "CameraCheck", "MATCH_TOLERANCE_PX",
           "check_and_repair", "match_agreement", "pose_differences", "reregister", "rig_disagreement", "sampson_px",
           "suspects", "undistorted_rays"]
