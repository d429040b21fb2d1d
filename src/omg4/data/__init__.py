"""Scenes from real and synthetic multi-view data: cameras, timed views, the normalized world."""

from omg4.data.points import random_initial_points, read_ply, write_ply
from omg4.data.readers import detect_format, load_scene
from omg4.data.scene import Camera, Normalization, PointCloud, Scene, View

__all__ = ["Camera", "Normalization", "PointCloud", "Scene", "View", "detect_format", "load_scene",
           "random_initial_points", "read_ply", "write_ply"]
