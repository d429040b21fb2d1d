"""Distortion removal against a known distortion: a smooth pattern defined on the image plane, seen through a
radially distorted lens (rendered by inverting the model independently, by Newton's method), resampled by the
undistorter, equals the pattern seen by the pinhole it reports."""

from __future__ import annotations

import numpy as np

from omg4.prepare.undistort import Undistorter, pinhole_focal

WIDTH, HEIGHT = 160, 120
K = np.array([[130.0, 0.0, 83.0], [0.0, 130.0, 57.5], [0.0, 0.0, 1.0]])  # principal point off centre
DISTORTION = (-0.18, 0.04)  # barrel


def pattern(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """RGB in [0, 255] of normalized image-plane coordinates: smooth enough to interpolate."""
    return np.stack([127 + 100 * np.sin(9 * x) * np.cos(7 * y), 127 + 100 * np.cos(11 * x + 3 * y),
                     127 + 100 * np.sin(5 * (x * x + y * y) + 2 * y)], axis=-1)


def undistort_newton(xd: np.ndarray, yd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The undistorted (x, y) of distorted normalized coordinates: Newton's method on r·(1 + k1 r² + k2 r⁴) = rd."""
    k1, k2 = DISTORTION
    rd = np.hypot(xd, yd)
    r = rd.copy()
    for _ in range(50):
        g = r * (1 + k1 * r**2 + k2 * r**4) - rd
        r = r - g / (1 + 3 * k1 * r**2 + 5 * k2 * r**4)
    scale = np.where(rd > 0, r / np.maximum(rd, 1e-12), 1.0)
    return xd * scale, yd * scale


def test_the_undistorted_frame_is_the_pinhole_view_of_the_pattern():
    v, u = np.meshgrid(np.arange(HEIGHT) + 0.5, np.arange(WIDTH) + 0.5, indexing="ij")
    distorted = pattern(*undistort_newton((u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]))
    undistort = Undistorter(K, DISTORTION, WIDTH, HEIGHT)
    assert np.allclose(undistort.K[:2, 2], [WIDTH / 2, HEIGHT / 2]) and undistort.K[0, 0] == undistort.K[1, 1]
    out = undistort(np.round(distorted).astype(np.uint8)).astype(np.float64)
    expected = pattern((u - WIDTH / 2) / undistort.focal, (v - HEIGHT / 2) / undistort.focal)
    error = np.abs(out - expected)
    assert error.mean() < 1.5 and np.percentile(error, 99) < 6  # bilinear interpolation of a smooth pattern
    # without the correction the frame is far from the pinhole view
    assert np.abs(distorted - expected).mean() > 10


def test_the_pinhole_sees_no_border_and_no_more():
    def border_inside(focal: float) -> bool:
        edge = np.concatenate([np.stack([np.arange(WIDTH) + 0.5, np.full(WIDTH, y)], 1) for y in (0.5, HEIGHT - 0.5)]
                              + [np.stack([np.full(HEIGHT, x), np.arange(HEIGHT) + 0.5], 1) for x in (0.5, WIDTH - 0.5)])
        x, y = (edge[:, 0] - WIDTH / 2) / focal, (edge[:, 1] - HEIGHT / 2) / focal
        r2 = x * x + y * y
        d = 1 + DISTORTION[0] * r2 + DISTORTION[1] * r2 * r2
        su, sv = K[0, 0] * x * d + K[0, 2], K[1, 1] * y * d + K[1, 2]
        return bool(np.all((su >= 0.5 - 1e-6) & (su <= WIDTH - 0.5 + 1e-6) & (sv >= 0.5 - 1e-6)
                           & (sv <= HEIGHT - 0.5 + 1e-6)))

    focal = pinhole_focal(K, DISTORTION, WIDTH, HEIGHT)
    assert border_inside(focal) and not border_inside(0.99 * focal)  # inside, and the widest view that is
    centred = np.array([[130.0, 0.0, 80.0], [0.0, 130.0, 60.0], [0.0, 0.0, 1.0]])
    assert abs(pinhole_focal(centred, (0.0, 0.0), WIDTH, HEIGHT) - 130.0) < 1e-6  # no distortion: the same camera
