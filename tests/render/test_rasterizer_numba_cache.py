"""Where the numba kernels cache their compiled code."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from omg4.kernels import resolve_cache_dir


def test_environment_variable_wins():
    assert resolve_cache_dir({"NUMBA_CACHE_DIR": "/somewhere"}, "/pkg", lambda p: False) is None


def test_writable_package_keeps_numba_default():
    assert resolve_cache_dir({}, "/pkg", lambda p: True) is None


def test_read_only_package_uses_user_cache():
    folder = resolve_cache_dir({}, "/pkg", lambda p: False)
    assert folder == str(Path.home() / ".cache" / "omg4" / "numba")


def test_kernels_are_cached_in_numba_cache_dir(tmp_path):
    """A fresh process with NUMBA_CACHE_DIR writes the compiled kernels there.

    It also checks that starting numba's OpenMP pool leaves torch's thread count alone.
    """
    code = ("import torch; torch.set_num_threads(1); from omg4.render import rasterize;"
            "m = torch.tensor([[0.0, 0.0, 3.0]], requires_grad=True);"
            "r = rasterize(m, torch.eye(3)[None] * 0.01, torch.ones(1, 3), torch.full((1,), 0.5), torch.eye(4),"
            " torch.tensor([[10.0, 0, 4.5], [0, 10, 4.5], [0, 0, 1]]), 8, 8); r.image.sum().backward();"
            "print(float(r.alpha.detach().max()), torch.get_num_threads())")
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    alpha, torch_threads = out.stdout.split()
    assert abs(float(alpha) - 0.5) < 1e-6 and torch_threads == "1"
    names = [p.name for p in tmp_path.rglob("*")]
    assert any(n.startswith("cpu_kernels.composite_forward") and n.endswith(".nbi") for n in names), names
    assert any(n.startswith("cpu_kernels.composite_backward") and n.endswith(".nbi") for n in names), names
