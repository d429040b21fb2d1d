"""Tools for testing and measuring omg4, and any other reader of its files (as ``numpy.testing`` is numpy's).

:mod:`omg4.testing.forge` makes valid ``.omg4`` files and sequences of any size and forges hostile ones past the
checksums; :func:`~omg4.testing.forge.exercise` runs a file through everything a user's command does with it.
:mod:`omg4.testing.browser` drives chromium for the web player; :mod:`omg4.testing.records` keeps the benchmarks'
results as records of runs (commit, date, machine). The test suite, ``benchmarks/`` and ``tools/`` use them; no
library module imports this package.
"""
