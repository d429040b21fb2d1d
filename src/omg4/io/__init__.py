"""Files in and out of omg4: official checkpoint import, images, video, and the export formats.

:data:`EXPORT_FORMATS` lists the files ``omg4 export`` writes: a standard 3DGS ``.ply`` of one time
slice (:mod:`omg4.io.ply_export`), the same slice as a glTF binary with ``KHR_gaussian_splatting``
(:mod:`omg4.io.gltf_export`), or the whole 4D model as a ``.splatv`` (:mod:`omg4.io.splatv`);
:data:`EXPORT_FOLDERS` the folders: ``web``, a static player of the ``.omg4`` file (:mod:`omg4.io.web_player`).
"""

EXPORT_FORMATS = {".ply": "ply", ".glb": "gltf", ".splatv": "splatv"}
"""Output suffix → the export format it names."""

EXPORT_FOLDERS = ("web",)
"""Export formats whose output (``--out``) is a folder."""
