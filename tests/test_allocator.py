"""The allocator setting takes effect on glibc: both mallopt calls accept their values."""

import platform

import pytest

from omg4.allocator import keep_freed_memory


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="mallopt tuning is glibc-only")
def test_keep_freed_memory_succeeds_on_glibc():
    assert keep_freed_memory() is True
    assert keep_freed_memory() is True  # idempotent
