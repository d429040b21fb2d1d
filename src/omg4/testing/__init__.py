"""Tools for testing omg4 and any other reader of its files (as ``numpy.testing`` is numpy's).

:mod:`omg4.testing.forge` makes valid ``.omg4`` files and sequences of any size and forges hostile ones past the
checksums; :func:`~omg4.testing.forge.exercise` runs a file through everything a user's command does with it.
The test suite and the fuzz benchmark (``benchmarks/fuzz_omg4.py``) drive it.
"""
