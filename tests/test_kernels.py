"""Handing tensors to the numba kernels (omg4.kernels.as_numpy): the same memory, viewed without an operation where
it can be, copied where it is not contiguous, and a parameter's view kept only while it is that parameter's."""

import gc
import weakref
from collections import Counter

import numpy as np
import torch
from torch.utils._python_dispatch import TorchDispatchMode

from omg4 import kernels
from omg4.kernels import as_numpy


class Dispatched(TorchDispatchMode):
    def __init__(self):
        super().__init__()
        self.ops = Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.ops[str(func.overloadpacket)] += 1
        return func(*args, **(kwargs or {}))


def test_a_parameter_is_viewed_once_and_follows_its_updates():
    p = torch.nn.Parameter(torch.arange(6.0).reshape(2, 3))
    first = as_numpy(p)
    with Dispatched() as counted:
        again = as_numpy(p)
    assert again is first and sum(counted.ops.values()) == 0  # no detach the second time
    with torch.no_grad():
        p.mul_(2)  # an optimizer's in-place step: the view shows it
    assert np.array_equal(as_numpy(p), np.arange(6.0).reshape(2, 3) * 2)
    p.data = torch.zeros(4, 3)  # replaced (pruning, densification): a new view of the new memory
    assert as_numpy(p).shape == (4, 3) and not as_numpy(p).any()


def test_a_parameter_gone_leaves_no_view_behind():
    p = torch.nn.Parameter(torch.ones(1000))
    as_numpy(p)
    assert id(p) in kernels._PARAMETER_VIEWS
    gone, key = weakref.ref(p), id(p)
    del p
    gc.collect()
    assert gone() is None and key not in kernels._PARAMETER_VIEWS


def test_other_tensors_are_views_or_copies_of_their_values():
    t = torch.arange(12.0).reshape(3, 4)
    assert np.shares_memory(as_numpy(t), t.numpy())
    strided = t[:, ::2]
    copied = as_numpy(strided)
    assert copied.flags.c_contiguous and np.array_equal(copied, strided.numpy())
    needs_grad = torch.arange(4.0, requires_grad=True) * 2  # not a leaf: detached, never kept
    assert np.array_equal(as_numpy(needs_grad), [0.0, 2.0, 4.0, 6.0]) and id(needs_grad) not in kernels._PARAMETER_VIEWS
