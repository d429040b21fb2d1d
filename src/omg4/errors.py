"""User-facing errors.

Every problem a user can cause (missing files, wrong formats, corrupt files, NaNs, empty
scenes) is raised as :class:`OMG4Error` with a one-line message naming the problem; the
command line prints that line and exits non-zero instead of showing a traceback.
"""


class OMG4Error(Exception):
    """A problem with the user's input, reported as one line without a traceback."""


class DataError(OMG4Error):
    """A dataset folder is missing, incomplete or malformed."""


class CorruptFileError(OMG4Error):
    """A model, checkpoint or ``.omg4`` file is truncated, damaged or of an unknown kind."""
