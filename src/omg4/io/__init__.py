"""Files in and out of omg4: official checkpoint import, images, video, and the export formats.

:data:`EXPORT_FORMATS` lists what ``omg4 export`` writes: a standard 3DGS ``.ply`` of one time
slice (:mod:`omg4.io.ply_export`) or the whole 4D model as a ``.splatv`` (:mod:`omg4.io.splatv`).
"""

EXPORT_FORMATS = {".ply": "ply", ".splatv": "splatv"}
"""Output suffix → the export format it names."""
