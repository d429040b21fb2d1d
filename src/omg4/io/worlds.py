"""The world each export writes: omg4's normalized world turned into the convention its readers assume.

omg4's normalized world is +Z up (:mod:`omg4.data.normalize`: the cameras' mean up vector becomes +z). Each slice
format's readers assume another, so the export turns the slice by a rotation baked into its positions, covariances
and SH coefficients (:func:`omg4.io.ply_export.turned_covariances_and_sh`) and records the matrix in the file:

- ``.glb`` (:data:`GLTF`): glTF is +Y up — (x, y, z) → (x, z, −y); ``asset.extras.from_omg4_world``.
- ``.ply`` (:data:`PLY`): the 3DGS viewers' world. 3DGS's captures come in COLMAP's world, y down, and SuperSplat,
  PlayCanvas and ``@playcanvas/splat-transform`` turn a ``.ply`` by 180° about z into their +Y-up world, so the slice
  is written y down: glTF's turn followed by that half turn, (x, y, z) → (−x, −z, −y); a ``comment from_omg4_world``
  header line.

With ``--original-world`` both write the dataset's own world as it is and name its up direction instead. The ``.splatv``
and the web player keep omg4's world, with cameras (the dataset's, or one framing the model) in that same world.
"""

from __future__ import annotations

import numpy as np

GLTF = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
"""omg4's world (+Z up) to glTF's (+Y up): a rotation of −90° about x, (x, y, z) → (x, z, −y)."""

PLY = np.diag([-1.0, -1.0, 1.0]) @ GLTF
"""omg4's world to the 3DGS viewers' (y down): (x, y, z) → (−x, −z, −y), glTF's turn then 180° about z."""

__all__ = ["GLTF", "PLY"]
