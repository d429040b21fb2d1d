"""The built-in procedural dynamic scene (``omg4 synth``), written as an N3DV folder.

A small analytic ray caster of its own (no Gaussians), in four modules: the camera rig
(:mod:`.rig`), what the world contains (:mod:`.world`: ground, backdrop, static and moving
textured solids, one light, soft shadows, so moving objects also change the static surfaces
around them), the ray caster that shades rays against it (:mod:`.raycast`) and the writer of
the N3DV folder (:mod:`.writer`).

World: metres, +z up, the cameras on a forward-facing arc at y < 0 looking at the
scene centre (+y), like the N3DV rig. Motion is a function of the clip phase
``s = frame / num_frames`` (one cycle of motion per clip whatever the frame count).
Everything random (rig jitter, object sizes, paths, colours, textures) comes from
``seed`` through independent streams, so e.g. the camera count does not change the
objects.

Output (the N3DV layout read by ``omg4.data.load_scene``, docs/architecture.md "Datasets"):

* ``camXX.mp4``: H.264 (libx264, yuv420p) per camera, ``cam00`` the central test camera;
* ``poses_bounds.npy``: [N, 17] float64, one row per camera in sorted-name order:
  the 3×5 matrix ``[R | t | hwf]`` (camera-to-world with LLFF axes [down, right, back],
  ``hwf = [H, W, focal]``) flattened row-major, then near and far z-depth bounds;
* ``points3d.ply``: binary little-endian ``float x, y, z`` + ``uchar red, green, blue``:
  points on the surfaces seen by the training cameras at frame 0 (the role of the
  COLMAP frame-0 points of N3DV, rt4dgs §3.5), in the same world as the poses;
* ``synth.json``: the generator's parameters.
"""

from omg4.data.synthetic.raycast import RayHits, SyntheticScene, box_filter
from omg4.data.synthetic.rig import camera_rays, camera_rig, llff_poses_bounds, look_at_viewmat
from omg4.data.synthetic.world import SynthConfig
from omg4.data.synthetic.writer import SynthResult, write_synthetic_scene

__all__ = ["RayHits", "SynthConfig", "SynthResult", "SyntheticScene", "box_filter", "camera_rays", "camera_rig",
           "llff_poses_bounds", "look_at_viewmat", "write_synthetic_scene"]
