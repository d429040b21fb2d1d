"""Your own capture: raw multi-view videos → a synchronized, calibrated, checked dataset (``omg4 prepare``)."""

from omg4.prepare.pipeline import prepare_capture

__all__ = ["prepare_capture"]
