"""The whole 4D model as a ``.splatv`` file, the format of the splaTV web viewer (antimatter15/splaTV).

Layout (little-endian): ``u32`` magic ``0x674B``, ``u32`` length ``J`` of a UTF-8 JSON array
``[{"type": "splat", "size": S, "texwidth": 4096, "texheight": H, "cameras": [...]}]``, then
``S = 4096·H·16`` bytes: one 64-byte record (16 ``u32`` words, 1024 per texture row) per
Gaussian, zero records after the last one. Words: 0–2 position (float32); 3–4 quaternion
(w, x, y, z) and 5–6 linear scales, as fp16 pairs (low half first); 7 colour RGBA8 (straight
alpha); 8–12 nine motion coefficients (fp16: velocity, then acceleration and jerk, 0 here);
13–14 angular velocity (fp16, 0 here); 15 the temporal centre and scale (fp16). The viewer
shows a Gaussian at normalized time ``t ∈ [0, 1]`` at ``position + velocity · (t − centre)``
with opacity ``alpha · exp(−((t − centre) / scale)²)``.

Both backbones map onto it exactly for geometry (:attr:`omg4.gaussians.backbone.Backbone.motion`):
a Real-Time4DGS conditional mean moves linearly in t with velocity Σ12/Σtt and a constant
conditional covariance, and its temporal marginal ``exp(−½ dt²/Σtt)`` is the viewer's
Gaussian with ``scale = √(2 Σtt)``; FreeTimeGS's motion is linear by construction. Times are
normalized by the model's time range. The colour is approximated: one RGB per Gaussian, the
view-averaged colour (the SH DC term) at the Gaussian's own time centre
(:func:`omg4.gaussians.model.centre_appearance`), so view- and time-dependent colour is lost
(``benchmarks/studies/splatv_fidelity.py`` measures the PSNR this costs against our renderer). The
viewer also culls at a temporal factor of 0.02 where ours culls at ``time_cull`` (0.05).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from omg4.atomic import atomic_path
from omg4.data.scene import Camera
from omg4.errors import CorruptFileError, OMG4Error
from omg4.gaussians.model import centre_appearance
from omg4.io.ply_export import covariance_to_scale_rotation, model_in_float64

MAGIC = 0x674B
TEXTURE_WIDTH = 4096
RECORD_WORDS = 16
GAUSSIANS_PER_ROW = TEXTURE_WIDTH // 4
FP16_MAX = float(np.finfo(np.float16).max)


def _half_pair(low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """``packHalf2x16``: two fp16 values in one u32, ``low`` in the low 16 bits."""
    lo = np.asarray(low, np.float16).view(np.uint16).astype(np.uint32)
    hi = np.asarray(high, np.float16).view(np.uint16).astype(np.uint32)
    return lo | (hi << 16)


def _to_u8(x: np.ndarray) -> np.ndarray:
    return np.rint(np.clip(x, 0.0, 1.0) * 255.0).astype(np.uint32)


def _fp16(x: np.ndarray) -> np.ndarray:
    """``x`` clipped to the fp16 range, so no value becomes infinite (a NaN position in the viewer)."""
    return np.clip(x, -FP16_MAX, FP16_MAX)


def splatv_camera(camera: Camera, index: int) -> dict:
    """One ``cameras`` entry: the 3DGS ``cameras.json`` layout (centre, camera-to-world rotation, focal lengths)."""
    c2w = camera.camtoworld
    return {"id": index, "img_name": camera.name or f"{index:05d}", "width": int(camera.width),
            "height": int(camera.height), "position": c2w[:3, 3].tolist(), "rotation": c2w[:3, :3].tolist(),
            "fx": float(camera.K[0, 0]), "fy": float(camera.K[1, 1])}


def splatv_records(model) -> np.ndarray:
    """[N, 16] uint32 records of ``model`` (a :class:`~omg4.gaussians.Gaussians4D` or a render-only model),
    sorted by decreasing ``volume · opacity`` as splaTV's converter does (large splats load first)."""
    values, appearance = model_in_float64(model)
    config = model.config
    t0, t1 = config.time_range
    period = t1 - t0
    with torch.no_grad():
        velocity, covars, var_t = config.schema.motion(values, config)
        rgb, opacity = centre_appearance(values, config, model.active_sh_degree_t, appearance=appearance)
    log_scales, quats = covariance_to_scale_rotation(covars.numpy())
    scales = _fp16(np.exp(log_scales))
    xyz, opacity, rgb = values["xyz"].numpy(), opacity.numpy(), rgb.numpy()
    with np.errstate(over="ignore"):  # refused just below
        xyz32 = xyz.astype("<f4")
    if not np.isfinite(xyz32).all():
        raise OMG4Error("positions beyond the float32 range do not fit the .splatv format; nothing written")
    centre = _fp16((values["t"][:, 0].numpy() - t0) / period)
    time_scale = _fp16(np.sqrt(2.0 * var_t.numpy()) / period)
    motion = _fp16(velocity.numpy() * period)  # per unit of normalized time
    order = np.argsort(-(scales.prod(axis=1) * opacity), kind="stable")
    n = xyz.shape[0]
    words = np.zeros((n, RECORD_WORDS), np.uint32)
    words[:, 0:3] = xyz32.view("<u4")
    words[:, 3] = _half_pair(quats[:, 0], quats[:, 1])
    words[:, 4] = _half_pair(quats[:, 2], quats[:, 3])
    words[:, 5] = _half_pair(scales[:, 0], scales[:, 1])
    words[:, 6] = _half_pair(scales[:, 2], 0.0)
    rgba = _to_u8(np.concatenate([rgb, opacity[:, None]], axis=1))
    words[:, 7] = rgba[:, 0] | (rgba[:, 1] << 8) | (rgba[:, 2] << 16) | (rgba[:, 3] << 24)
    words[:, 8] = _half_pair(motion[:, 0], motion[:, 1])
    words[:, 9] = _half_pair(motion[:, 2], 0.0)  # acceleration, jerk and angular velocity stay 0
    words[:, 15] = _half_pair(centre, time_scale)
    return words[order]


def export_splatv(path: str | os.PathLike, model, cameras: list[Camera]) -> int:
    """Write ``model`` as a ``.splatv`` file (atomically) with ``cameras`` as the viewer's presets (keys 0–9;
    a file dropped onto the page starts at the first, a file opened by URL keeps the viewer's default view
    and takes only the first camera's focal length); returns the number of Gaussians written."""
    if not cameras:
        raise ValueError("a .splatv file needs at least one camera (the viewer takes its focal length)")
    records = splatv_records(model)
    rows = max(1, -(-records.shape[0] // GAUSSIANS_PER_ROW))
    body = np.zeros((rows * GAUSSIANS_PER_ROW, RECORD_WORDS), "<u4")
    body[: records.shape[0]] = records
    header = json.dumps([{"type": "splat", "size": body.nbytes, "texwidth": TEXTURE_WIDTH, "texheight": rows,
                          "cameras": [splatv_camera(c, i) for i, c in enumerate(cameras)]}]).encode("utf-8")
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(np.array([MAGIC, len(header)], "<u4").tobytes())
            f.write(header)
            f.write(body.tobytes())
    return int(records.shape[0])


def read_splatv(path: str | os.PathLike) -> tuple[dict, dict[str, np.ndarray]]:
    """(header, fields) of a ``.splatv`` file: float64 ``xyz [M, 3]``, ``quat [M, 4]`` (w, x, y, z), ``scale
    [M, 3]``, ``rgba [M, 4]`` in [0, 1], ``motion [M, 9]``, ``omega [M, 4]``, ``centre [M]``, ``time_scale [M]``
    (zero records dropped). Raises :class:`~omg4.errors.CorruptFileError` on a malformed file."""
    try:
        data = Path(path).read_bytes()
    except OSError as e:
        raise OMG4Error(f"cannot read {path}: {e.strerror or e}") from None
    if len(data) < 8 or int(np.frombuffer(data[:4], "<u4")[0]) != MAGIC:
        raise CorruptFileError(f"{path}: not a .splatv file (no 0x674B magic)")
    length = int(np.frombuffer(data[4:8], "<u4")[0])
    try:
        (header,) = json.loads(data[8:8 + length].decode("utf-8"))
        size = int(header["size"])
        body = np.frombuffer(data[8 + length:8 + length + size], "<u4")
        words = body.reshape(-1, RECORD_WORDS)
    except (ValueError, KeyError, TypeError) as e:
        raise CorruptFileError(f"{path}: not a .splatv file ({type(e).__name__}: {e})") from None
    if header.get("type") != "splat" or body.nbytes != size:
        raise CorruptFileError(f"{path}: malformed .splatv (chunk type {header.get('type')!r}, {body.nbytes} of "
                               f"{size} texture bytes)")
    words = words[words[:, 15] != 0]  # zero records pad the last texture row

    def halves(col: int) -> np.ndarray:
        return words[:, col].copy().view(np.float16).reshape(-1, 2).astype(np.float64)

    centre_scale = halves(15)
    return header, {
        "xyz": words[:, 0:3].copy().view("<f4").astype(np.float64),
        "quat": np.concatenate([halves(3), halves(4)], axis=1),
        "scale": np.concatenate([halves(5), halves(6)[:, :1]], axis=1),
        "rgba": words[:, 7].copy().view(np.uint8).reshape(-1, 4).astype(np.float64) / 255.0,
        "motion": np.concatenate([halves(c) for c in (8, 9, 10, 11, 12)], axis=1)[:, :9],
        "omega": np.concatenate([halves(13), halves(14)], axis=1),
        "centre": centre_scale[:, 0], "time_scale": centre_scale[:, 1],
    }


def splatv_state(fields: dict[str, np.ndarray], t: float, min_opacity: float = 0.02):
    """What splaTV's vertex shader draws at normalized time ``t``: (means [M, 3], covariances [M, 3, 3],
    colours [M, 3], opacities [M]) of the records whose temporal factor reaches ``min_opacity``."""
    dt = t - fields["centre"]
    temporal = np.exp(-((dt / fields["time_scale"]) ** 2))
    keep = temporal >= min_opacity
    dt, m = dt[keep, None], fields["motion"][keep]
    means = fields["xyz"][keep] + m[:, 0:3] * dt + m[:, 3:6] * dt**2 + m[:, 6:9] * dt**3
    q = fields["quat"][keep] + fields["omega"][keep] * dt
    R = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()
    covars = R @ (fields["scale"][keep, :, None] ** 2 * np.swapaxes(R, 1, 2))
    return means, covars, fields["rgba"][keep, :3], fields["rgba"][keep, 3] * temporal[keep]


__all__ = ["MAGIC", "TEXTURE_WIDTH", "export_splatv", "read_splatv", "splatv_camera", "splatv_records",
           "splatv_state"]
