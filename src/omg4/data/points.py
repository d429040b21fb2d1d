"""Initial point clouds: ``points3d.ply`` files and the random initialization.

PLY: the COLMAP / 3DGS layout, a ``vertex`` element with ``x, y, z`` and optional
``red, green, blue`` (uchar → /255; float/double taken as [0, 1]); other vertex properties
(normals...) are ignored. ``binary_little_endian``, ``binary_big_endian`` and ``ascii``
bodies are read; :func:`write_ply` writes binary little-endian float x, y, z + uchar r, g, b.
Points without colours get mid grey (0.5).

Random initialization (:func:`random_initial_points`): Real-Time4DGS draws D-NeRF points
uniformly in a cube when no point cloud exists (rt4dgs §3.5); for multi-view scenes we
restrict the cube to the training cameras' common view volume (documented below).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from omg4.atomic import atomic_path
from omg4.data.scene import Camera, PointCloud, Scene
from omg4.errors import DataError

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


def _parse_header(f, path: Path) -> tuple[str, list[tuple[str, int, list[tuple[str, str]]]]]:
    """(format, [(element name, count, [(property, numpy type)])]); list properties are rejected."""
    if f.readline().strip() != b"ply":
        raise DataError(f"{path} is not a PLY file (no 'ply' magic)")
    fmt, elements = None, []
    while True:
        line = f.readline()
        if not line:
            raise DataError(f"{path}: PLY header has no end_header")
        words = line.decode("ascii", errors="replace").split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "end_header":
            break
        if words[0] == "format" and len(words) >= 2:
            fmt = words[1]
        elif words[0] == "element" and len(words) == 3:
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property" and elements:
            if words[1] == "list":
                if elements[-1][0] == "vertex" or elements[0][0] != "vertex":
                    raise DataError(f"{path}: list properties before or in the vertex element are not supported")
                elements[-1][2].append((words[-1], "list"))
                continue
            if words[1] not in _PLY_TYPES or len(words) != 3:
                raise DataError(f"{path}: unsupported PLY property line '{line.decode(errors='replace').strip()}'")
            elements[-1][2].append((words[2], _PLY_TYPES[words[1]]))
        else:
            raise DataError(f"{path}: malformed PLY header line '{line.decode(errors='replace').strip()}'")
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise DataError(f"{path}: unsupported PLY format '{fmt}'")
    return fmt, elements


def read_ply(path: str | Path) -> PointCloud:
    """Points of a PLY file: xyz [M, 3] float64 and rgb [M, 3] float32 in [0, 1] (in the file's world)."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            fmt, elements = _parse_header(f, path)
            names = [e[0] for e in elements]
            if "vertex" not in names:
                raise DataError(f"{path}: PLY file has no vertex element")
            if names[0] != "vertex":
                raise DataError(f"{path}: the vertex element must come first in the PLY file")
            _, count, props = elements[0]
            remaining = os.fstat(f.fileno()).st_size - f.tell()
            # bytes each vertex needs at least: its binary record, or one digit and a separator per ASCII value
            least = 2 * len(props) if fmt == "ascii" else np.dtype([(n, "<" + t) for n, t in props]).itemsize
            if count < 0 or count * max(least, 1) - 1 > remaining:  # the last value needs no separator
                raise DataError(f"{path}: PLY file is truncated or damaged: its header declares {count} vertices, "
                                f"more than its {remaining} bytes of data can hold")
            if fmt == "ascii":
                data = np.loadtxt(f, dtype=np.float64, max_rows=count, ndmin=2) if count else np.zeros((0, len(props)))
                if data.shape != (count, len(props)):
                    raise DataError(f"{path}: expected {count} vertices of {len(props)} values, got {data.shape}")
                columns = {name: data[:, k] for k, (name, _) in enumerate(props)}
            else:
                endian = "<" if fmt == "binary_little_endian" else ">"
                dtype = np.dtype([(name, endian + t) for name, t in props])
                raw = f.read(dtype.itemsize * count)
                if len(raw) < dtype.itemsize * count:
                    raise DataError(f"{path}: PLY file is truncated "
                                    f"({len(raw)} of {dtype.itemsize * count} vertex bytes)")
                data = np.frombuffer(raw, dtype=dtype, count=count)
                columns = {name: data[name] for name, _ in props}
    except FileNotFoundError:
        raise DataError(f"missing point cloud {path}") from None
    except ValueError as e:
        raise DataError(f"{path}: malformed PLY body: {e}") from None
    if not all(k in columns for k in "xyz"):
        raise DataError(f"{path}: PLY vertices lack x, y, z")
    xyz = np.stack([columns[k] for k in "xyz"], axis=1).astype(np.float64)
    if not np.isfinite(xyz).all():
        raise DataError(f"{path}: point positions contain NaN or Inf")
    if all(k in columns for k in ("red", "green", "blue")):
        rgb = np.stack([columns[k] for k in ("red", "green", "blue")], axis=1).astype(np.float32)
        if dict(props)["red"] not in ("f4", "f8"):
            rgb /= 255.0
        rgb = np.clip(rgb, 0.0, 1.0)
    else:
        rgb = np.full((len(xyz), 3), 0.5, dtype=np.float32)
    return PointCloud(xyz=xyz, rgb=rgb)


def write_ply(path: str | Path, points: PointCloud) -> None:
    """Write ``points`` (xyz [M, 3], rgb [M, 3] in [0, 1]) as binary little-endian PLY, atomically."""
    xyz = np.asarray(points.xyz, dtype=np.float32).reshape(-1, 3)
    rgb = np.clip(np.rint(np.asarray(points.rgb, dtype=np.float64).reshape(-1, 3) * 255.0), 0, 255).astype(np.uint8)
    if len(rgb) != len(xyz):
        raise ValueError(f"xyz has {len(xyz)} points but rgb {len(rgb)}")
    dtype = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    data = np.empty(len(xyz), dtype=dtype)
    for k, name in enumerate("xyz"):
        data[name] = xyz[:, k]
    for k, name in enumerate(("red", "green", "blue")):
        data[name] = rgb[:, k]
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(xyz)}\n"
              "property float x\nproperty float y\nproperty float z\n"
              "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n")
    with atomic_path(path) as tmp:
        tmp.write_bytes(header.encode("ascii") + data.tobytes())


def visible_counts(points: np.ndarray, cameras: list[Camera], near: float, far: float) -> np.ndarray:
    """[M] number of ``cameras`` that see each point of ``points`` [M, 3].

    A camera sees a point when its depth lies in ``[near, far]`` and its projection falls
    inside the image (pixel coordinates in ``[0, W) × [0, H)``).
    """
    viewmats = np.stack([c.viewmat for c in cameras])  # [C, 4, 4]
    Ks = np.stack([c.K for c in cameras])  # [C, 3, 3]
    size = np.array([[c.width, c.height] for c in cameras], dtype=np.float64)  # [C, 2]
    cam = np.einsum("cij,mj->cmi", viewmats[:, :3, :3], points) + viewmats[:, None, :3, 3]  # [C, M, 3]
    z = cam[..., 2]
    pix = np.einsum("cij,cmj->cmi", Ks, cam)
    uv = pix[..., :2] / np.where(np.abs(pix[..., 2:]) > 1e-12, pix[..., 2:], 1e-12)
    inside = (uv >= 0).all(-1) & (uv < size[:, None, :]).all(-1)
    return ((z >= near) & (z <= far) & inside).sum(0)


def random_initial_points(scene: Scene, num_points: int, seed: int = 0, *, min_views: int | None = None,
                          near: float = 0.2, far: float = 50.0, batch: int = 32768) -> PointCloud:
    """Random points in the training cameras' common view volume, in the normalized world.

    Candidates are drawn uniformly in the cube ``[−r, r]³`` with ``r`` = the largest
    training-camera distance from the origin (the normalized world centres the cameras' focus
    at the origin, mean camera distance 4); a candidate is kept when at least
    ``min(min_views, #cameras)`` training cameras see it at a depth in ``[near, far]``. By
    default ``min_views`` is half the training cameras (at least 2): points seen by only a
    couple of cameras of a dome are mostly empty space, and sparse far-off points become
    huge initial Gaussians that make every tile slow
    (normalized units; 0.2 is the rasterizer's near plane, rt4dgs §4.3). Batches of
    ``batch`` candidates are drawn until ``num_points`` are kept. Colours are grey-ish:
    0.5 + U(−0.05, 0.05) per channel, as Real-Time4DGS's random D-NeRF init is ≈ 0.5 grey
    (rt4dgs §3.5). Deterministic for a given scene, ``num_points`` and ``seed``.

    Returns:
        PointCloud with xyz [num_points, 3] float64 and rgb [num_points, 3] float32.
    """
    cameras = scene.train_cameras()
    if not cameras:
        raise DataError("the scene has no training cameras to place random points in")
    if num_points <= 0:
        raise DataError(f"num_points must be positive, got {num_points}")
    rng = np.random.default_rng(seed)
    radius = max(float(np.linalg.norm(c.center)) for c in cameras)
    if min_views is None:
        min_views = max(2, (len(cameras) + 1) // 2)
    need = min(min_views, len(cameras))
    kept, total, rounds = [], 0, 0
    while total < num_points:
        cand = rng.uniform(-radius, radius, size=(batch, 3))
        good = cand[visible_counts(cand, cameras, near, far) >= need]
        kept.append(good)
        total += len(good)
        rounds += 1
        if rounds >= 16 and total * 10_000 < num_points * rounds:  # would need > 10,000 rounds
            raise DataError(f"could not place {num_points} random points seen by {need} cameras "
                            f"(found {total} in {rounds * batch} candidates); the cameras share no common view")
    xyz = np.concatenate(kept)[:num_points]
    rgb = (0.5 + rng.uniform(-0.05, 0.05, size=(num_points, 3))).astype(np.float32)
    return PointCloud(xyz=xyz, rgb=rgb)


def load_initial_points(folder: Path, normalization, points_world: str) -> PointCloud | None:
    """``<folder>/points3d.ply`` mapped into the normalized world, or ``None`` when absent.

    ``points_world="original"``: the file is in the dataset's own pose world and is mapped by
    ``normalization``; ``"normalized"``: it is already in the normalized world (official
    n3v2blender output) and is used as is.
    """
    path = Path(folder) / "points3d.ply"
    if not path.exists():
        return None
    cloud = read_ply(path)
    if points_world == "original":
        cloud = PointCloud(xyz=normalization.apply_points(cloud.xyz), rgb=cloud.rgb)
    return cloud
