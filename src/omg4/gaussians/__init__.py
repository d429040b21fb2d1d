"""4D Gaussians of Real-Time4DGS: rotation, covariance, conditioning on time, 4D SH, model.

Reference rt4dgs §1–2. The pure functions take plain tensors so that every model kind
(the baseline, the OMG4 stage models, the decoded compact model) reuses the same
geometry (:func:`slice_geometry`) and colour (:func:`colors_from_sh`) code.
"""

from omg4.gaussians.covariance import (SliceGeometry, condition_on_time, covariance_4d, scaled_rotation_4d,
                                       slice_geometry, temporal_marginal, temporal_variance)
from omg4.gaussians.model import GaussianConfig, Gaussians4D
from omg4.gaussians.rotation import ROTATION_CONVENTIONS, build_rotation_3d, build_rotation_4d
from omg4.gaussians.sh import (C0, colors_from_sh, eval_sh, eval_sh_4d, fold_time_sh, rgb_to_sh, sh_basis, sh_to_rgb,
                               view_directions)

__all__ = [
    "GaussianConfig", "Gaussians4D",
    "ROTATION_CONVENTIONS", "build_rotation_3d", "build_rotation_4d",
    "covariance_4d", "scaled_rotation_4d", "temporal_variance", "condition_on_time", "temporal_marginal", "SliceGeometry", "slice_geometry",
    "C0", "sh_basis", "eval_sh", "eval_sh_4d", "fold_time_sh", "colors_from_sh", "view_directions", "rgb_to_sh",
    "sh_to_rgb",
]
