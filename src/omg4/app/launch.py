"""``--nproc N``: run a command as N ranks on this machine, through torch.distributed's launcher (``torchrun``).

The same as ``torchrun --standalone --nproc-per-node N -m omg4 ...``: one process per rank, one thread per
rank on the CPU (gloo), one GPU per rank with ``--device cuda`` (NCCL). When the job fails, this launcher prints
one line naming the rank that started it and how (killed by a signal, or the error it raised, read from the
rank's error file); the ranks themselves stay quiet.
"""

from __future__ import annotations

import logging
import os
import signal
import sys
import uuid


def without_nproc(argv: list[str]) -> list[str]:
    """``argv`` without ``--nproc N`` / ``--nproc=N``."""
    out, skip = [], False
    for a in argv:
        if skip:
            skip = False
        elif a == "--nproc":
            skip = True
        elif not a.startswith("--nproc="):
            out.append(a)
    return out


def launch(command: str, argv: list[str], nproc: int) -> int:
    """Run ``python -m omg4 argv`` as ``nproc`` ranks; returns the job's exit status (2 after a failure, reported in
    one line: :func:`root_cause`)."""
    from torch.distributed.elastic.multiprocessing.errors import ChildFailedError
    from torch.distributed.launcher.api import LaunchConfig, elastic_launch

    for name in ("torch.distributed.elastic", "torch.distributed.launcher"):
        logging.getLogger(name).setLevel(logging.CRITICAL)
    env_defaults = {"OMP_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1"}  # one thread per rank unless asked otherwise
    for key, value in env_defaults.items():
        os.environ.setdefault(key, value)
    os.environ["OMG4_LAUNCHER"] = "1"  # the ranks leave the report to this process
    config = LaunchConfig(min_nodes=1, max_nodes=1, nproc_per_node=nproc, run_id=uuid.uuid4().hex,
                          rdzv_backend="c10d", rdzv_endpoint="localhost:0", max_restarts=0, monitor_interval=0.2)
    try:
        elastic_launch(config, sys.executable)("-m", "omg4", *without_nproc(argv))
    except ChildFailedError as exc:
        # a rank stopped by the launcher may have left its progress bar mid-line: the report takes a line of its own
        fresh_line = "\r\033[K" if sys.stderr.isatty() else "\n"
        print(f"{fresh_line}omg4 {command}: error: {root_cause(exc.failures)}", file=sys.stderr)
        return 2
    return 0


def root_cause(failures: dict) -> str:
    """The failure that started it, in words: a rank killed by a signal other than the launcher's SIGTERM, else an
    error a rank raised itself (rather than one about losing another rank), else the earliest."""
    def rank_of(item):
        local_rank, failure = item
        data = failure.error_file_data if isinstance(failure.error_file_data, dict) else {}
        killed = failure.exitcode < 0 and failure.exitcode != -signal.SIGTERM
        raised = failure.exitcode > 0 and bool(data.get("message")) and not data.get("rank_lost")
        return (not killed, not raised, failure.exitcode == -signal.SIGTERM, failure.timestamp, local_rank)

    local_rank, failure = min(failures.items(), key=rank_of)
    data = failure.error_file_data if isinstance(failure.error_file_data, dict) else {}
    if failure.exitcode < 0:
        return f"rank {local_rank} {_how(failure.exitcode)}"
    message = data.get("message") if isinstance(data.get("message"), str) else None
    messages = {f.error_file_data.get("message") for f in failures.values() if isinstance(f.error_file_data, dict)}
    if message and messages == {message}:
        return message  # every rank stopped for the same reason (bad input, say): no rank to name
    return f"rank {local_rank}: {message}" if message else f"rank {local_rank} {_how(failure.exitcode)}"


def _how(exitcode: int) -> str:
    if exitcode < 0:
        try:
            return f"was stopped by {signal.Signals(-exitcode).name}"
        except ValueError:
            return f"was stopped by signal {-exitcode}"
    return f"exited with status {exitcode}"


__all__ = ["launch", "root_cause", "without_nproc"]
