"""Data parallelism over processes, GPUs and nodes with torch.distributed (launched by ``torchrun``).

The replicated recipe (as Grendel-GS's replicated mode): every rank holds the whole model and the
same optimizer state; a step's global batch of views is drawn from the same generator on every rank
and split over the ranks (:meth:`World.shard`); each rank back-propagates its views' share of
Σ_v loss_v / B, and the gradients are summed over the ranks before the optimizer step
(:func:`all_reduce_gradients`), so the step equals the single-process step of the same global
batch. Densification statistics stay local between density events and are combined right before
one (sums for the gradient accumulators and view counts, max for the screen radii,
:func:`reduce_statistics`), so every rank makes the same density decisions with the same
generators. SD scores and evaluation are sharded by views and reduced (scores summed, per-view rows
gathered in view order). Rank 0 alone writes files and shows progress.

Backends: gloo on the CPU, NCCL on CUDA with one GPU per rank (``LOCAL_RANK``). One process, or a
world of size 1, runs no collective at all: its results are the plain command's, bit for bit.

Faults: each rank records its process id in the rendezvous store; a collective that fails because a
rank stopped becomes a one-line :class:`RankLost` naming the ranks whose processes are gone (on
one node) or the error a rank recorded before it stopped.
"""

from __future__ import annotations

import contextlib
import datetime
import hashlib
import json
import logging
import os
import sys
import threading
import time
from dataclasses import dataclass
from typing import NoReturn

import numba
import torch
from torch.distributed.distributed_c10d import _get_default_store

from omg4.errors import OMG4Error

TIMEOUT_S = float(os.environ.get("OMG4_DIST_TIMEOUT", "600"))
"""Seconds a collective waits for the other ranks (``OMG4_DIST_TIMEOUT``)."""


class RankLost(OMG4Error):
    """A rank of the job stopped (killed, crashed or raised); the message names it and the cause where known."""


@dataclass(frozen=True)
class World:
    """This process's place in the job: ``rank`` of ``size`` (``local_rank`` on its node)."""

    rank: int = 0
    size: int = 1
    local_rank: int = 0

    @property
    def main(self) -> bool:
        """Rank 0: the one that writes files, JSON and progress bars."""
        return self.rank == 0

    @property
    def parallel(self) -> bool:
        return self.size > 1

    def shard(self, items: list) -> list:
        """This rank's share of ``items``: every ``size``-th one from position ``rank`` (order kept)."""
        return list(items)[self.rank::self.size]


SINGLE = World()
_ALONE = threading.local()


def world() -> World:
    """The current process group's world, or :data:`SINGLE` when none is initialized (or inside :func:`alone`)."""
    if getattr(_ALONE, "active", False) or not (torch.distributed.is_available()
                                               and torch.distributed.is_initialized()):
        return SINGLE
    return World(torch.distributed.get_rank(), torch.distributed.get_world_size(),
                 int(os.environ.get("LOCAL_RANK", "0")))


@contextlib.contextmanager
def alone():
    """Inside this block this rank works as a single process (no collectives): for units of work a rank does on
    its own, such as whole segments of a long capture (``omg4 train --parallel segments``)."""
    previous = getattr(_ALONE, "active", False)
    _ALONE.active = True
    try:
        yield
    finally:
        _ALONE.active = previous


def launched() -> bool:
    """Whether this process was started by ``torchrun`` (or ``--nproc``) into a world of more than one rank."""
    return int(os.environ.get("WORLD_SIZE", "1")) > 1


def init(device: torch.device) -> tuple[World, torch.device]:
    """Join the job ``torchrun`` started (a no-op in a single process): gloo on the CPU, NCCL on CUDA, where each
    rank takes the GPU of its ``LOCAL_RANK``. Returns the world and the device this rank computes on."""
    if not launched():
        return SINGLE, device
    if not torch.distributed.is_initialized():
        backend = "nccl" if device.type == "cuda" else "gloo"
        if device.type == "cuda":
            device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
            torch.cuda.set_device(device)
        try:
            torch.distributed.init_process_group(backend, timeout=datetime.timedelta(seconds=TIMEOUT_S))
        except (RuntimeError, ValueError) as exc:
            raise OMG4Error(f"cannot join the distributed job ({_first_line(exc)})") from None
        _store().set(f"omg4/pid/{torch.distributed.get_rank()}", str(os.getpid()))
        if device.type == "cpu":  # the numba kernels take no more threads than torch was given per rank
            numba.set_num_threads(max(1, min(numba.get_num_threads(), torch.get_num_threads())))
    elif device.type == "cuda":
        device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
    return world(), device


def finish() -> None:
    """Leave the process group (after a last barrier, so no rank exits while others still talk to it)."""
    if world().parallel:
        barrier()
        torch.distributed.destroy_process_group()


def leave(status: int) -> NoReturn:
    """End this rank of a job that has finished its work (after :func:`finish`) without the interpreter's teardown.

    Torch's gloo backend may destroy its worker threads while the interpreter finalizes and abort the process
    ("terminate called without an active exception", SIGABRT) after everything was computed and written: the
    launcher would report a finished run as a failed one. Measured with 2 ranks on 2 CPUs under load: 3 of 90
    training runs. The standard streams and logging handlers are flushed first, so nothing printed is lost."""
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(status)


def record_failure(exc: BaseException) -> None:
    """Tell the other ranks (:func:`_lost`) and the launcher (torchrun's per-rank error file) why this rank stops."""
    if world().parallel:
        try:
            _store().set(f"omg4/error/{world().rank}", _first_line(exc))
        except Exception:  # the store may be gone with the job; nothing more to tell
            pass
    error_file = os.environ.get("TORCHELASTIC_ERROR_FILE")
    if error_file and launched():
        try:
            with open(error_file, "w") as f:
                json.dump({"message": _first_line(exc), "timestamp": int(time.time()),
                           "rank_lost": isinstance(exc, RankLost)}, f)
        except OSError:
            pass


def reports_failures() -> bool:
    """Whether this process prints its own failure: rank 0, unless ``omg4 --nproc`` launched it (the launcher then
    reports the job's root cause in one line)."""
    return world().main and not os.environ.get("OMG4_LAUNCHER")


def _store():
    return _get_default_store()


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return (text[0] if text else type(exc).__name__)[:300]


def _lost(what: str, exc: BaseException) -> RankLost:
    """The one-line error of a collective that failed because a rank stopped."""
    w = world()
    causes = []
    for rank in range(w.size):
        if rank == w.rank:
            continue
        try:
            recorded = _store().get(f"omg4/error/{rank}").decode() if _store().check([f"omg4/error/{rank}"]) else ""
        except Exception:
            recorded = ""
        if recorded:
            causes.append(f"rank {rank} stopped: {recorded}")
            continue
        try:
            pid = int(_store().get(f"omg4/pid/{rank}"))
        except Exception:
            continue
        if not _alive(pid):
            causes.append(f"rank {rank} (process {pid}) is gone, killed without a message")
    detail = "; ".join(causes) or f"another rank stopped ({_first_line(exc)})"
    return RankLost(f"{what}: {detail}")


def _alive(pid: int) -> bool:
    """Whether process ``pid`` (on this machine) still runs: not gone, not a zombie awaiting its parent."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        try:
            os.kill(pid, 0)
        except OSError:
            return False
        return True


def _collective(what: str, fn, *args, **kwargs):
    try:
        return fn(*args, **kwargs)
    except (RuntimeError, torch.distributed.DistBackendError) as exc:
        raise _lost(what, exc) from None


def main_first(fn, what: str = "waiting for rank 0"):
    """``fn()`` on rank 0, then on the other ranks (so caches rank 0 fills, such as decoded video frames, are only
    read by the others); returns its result."""
    if not world().parallel:
        return fn()
    if world().main:
        result = fn()
        barrier(what)
        return result
    barrier(what)
    return fn()


def barrier(what: str = "waiting for the other ranks") -> None:
    if world().parallel:
        _collective(what, torch.distributed.barrier)


def _reduction_device(tensor: torch.Tensor) -> torch.device:
    """Where a tensor is reduced: NCCL reduces CUDA tensors only, so a CPU tensor (a tally kept on the host) goes to
    this rank's GPU; gloo reduces it where it is."""
    if tensor.device.type != "cuda" and torch.distributed.get_backend() == "nccl":
        return torch.device("cuda", torch.cuda.current_device())
    return tensor.device


def all_reduce_(tensors: list[torch.Tensor], op: str = "sum", what: str = "combining results") -> None:
    """Reduce ``tensors`` over the ranks in place (``op``: ``"sum"`` or ``"max"``), as one flat message per dtype."""
    if not world().parallel or not tensors:
        return
    reduce_op = {"sum": torch.distributed.ReduceOp.SUM, "max": torch.distributed.ReduceOp.MAX}[op]
    by_dtype: dict[torch.dtype, list[torch.Tensor]] = {}
    for t in tensors:
        by_dtype.setdefault(t.dtype, []).append(t)
    for group in by_dtype.values():
        flat = torch.cat([t.reshape(-1) for t in group]).to(_reduction_device(group[0]))
        _collective(what, torch.distributed.all_reduce, flat, op=reduce_op)
        offset = 0
        for t in group:
            t.copy_(flat[offset:offset + t.numel()].view_as(t))
            offset += t.numel()


_GRADIENT_BUFFERS: dict[tuple, torch.Tensor] = {}


def all_reduce_gradients(params: list[torch.Tensor], what: str = "summing the gradients") -> int:
    """Sum the gradients of ``params`` over the ranks; returns the bytes of gradients each rank reduced.

    A parameter no rank has a gradient for keeps none (its optimizer then skips it, as in one process); one
    that some ranks have no gradient for (no views of theirs reached it) counts as zeros there. The gradients
    are gathered into one flat buffer per dtype, kept from step to step (no allocation), reduced in place, and
    the parameters' gradients become views of it (no copy back).
    """
    if not world().parallel or not params:
        return 0
    device = params[0].device
    present = torch.tensor([p.grad is not None for p in params], dtype=torch.float32, device=device)
    all_reduce_([present], "max", what)
    used = [p for p, flag in zip(params, present.tolist()) if flag]
    by_dtype: dict[torch.dtype, list[torch.Tensor]] = {}
    for p in used:
        by_dtype.setdefault(p.dtype, []).append(p)
    sent = 0
    for dtype, group in by_dtype.items():
        total = sum(p.numel() for p in group)
        key = (dtype, str(device), total)
        flat = _GRADIENT_BUFFERS.get(key)
        if flat is None:
            _GRADIENT_BUFFERS.clear()  # one layout at a time: the parameter set changes with densification
            flat = _GRADIENT_BUFFERS[key] = torch.empty(total, dtype=dtype, device=device)
        storage = flat.untyped_storage().data_ptr()
        if any(p.grad is not None and p.grad.untyped_storage().data_ptr() == storage for p in group):
            flat = _GRADIENT_BUFFERS[key] = torch.empty_like(flat)  # the gradients are last step's views of it
        torch.cat([p.grad.reshape(-1) if p.grad is not None else torch.zeros(p.numel(), dtype=dtype, device=device)
                   for p in group], out=flat)
        _collective(what, torch.distributed.all_reduce, flat, op=torch.distributed.ReduceOp.SUM)
        offset = 0
        for p in group:
            p.grad = flat[offset:offset + p.numel()].view_as(p)
            offset += p.numel()
        sent += flat.numel() * flat.element_size()
    return sent


def broadcast_(tensors: list[torch.Tensor], what: str = "sharing the model") -> None:
    """Give every rank rank 0's values of ``tensors`` (in place)."""
    if not world().parallel:
        return
    for t in tensors:
        _collective(what, torch.distributed.broadcast, t.data, src=0)


def gather_objects(obj, what: str = "gathering results") -> list:
    """``obj`` of every rank, by rank (picklable objects; on every rank)."""
    if not world().parallel:
        return [obj]
    out = [None] * world().size
    _collective(what, torch.distributed.all_gather_object, out, obj)
    return out


def interleave(shards: list[list]) -> list:
    """Undo :meth:`World.shard`: the items of every rank's shard back in their original order."""
    out = []
    for i in range(max((len(s) for s in shards), default=0)):
        out += [s[i] for s in shards if i < len(s)]
    return out


def reduce_statistics(stats) -> None:
    """Combine the densification statistics of every rank in place (sums of the gradient accumulators and view
    counts, max of the screen radii): each rank then holds what one process would have accumulated."""
    if world().parallel:
        all_reduce_([stats.grad_sum, stats.visible_views], "sum", "combining the densification statistics")
        all_reduce_([stats.max_radii], "max", "combining the densification statistics")


def parameter_digest(tensors: list[torch.Tensor]) -> str:
    """A SHA-256 of the tensors' bytes (CPU copies), to compare replicas."""
    h = hashlib.sha256()
    for t in tensors:
        h.update(t.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


def check_replicas(tensors: list[torch.Tensor], step: int) -> None:
    """Stop with a one-line error when any rank's ``tensors`` differ from rank 0's (``--check-replicas``)."""
    if not world().parallel:
        return
    digests = gather_objects(parameter_digest(tensors), "comparing the replicas")
    differing = [rank for rank, d in enumerate(digests) if d != digests[0]]
    if differing:
        which = f"ranks {', '.join(map(str, differing))} differ" if len(differing) > 1 else f"rank {differing[0]} differs"
        raise OMG4Error(f"the replicas diverged by step {step}: {which} from rank 0")


__all__ = ["World", "SINGLE", "RankLost", "world", "alone", "launched", "init", "finish", "leave", "record_failure", "reports_failures", "main_first", "barrier",
           "all_reduce_", "all_reduce_gradients", "broadcast_", "gather_objects", "interleave", "reduce_statistics",
           "parameter_digest", "check_replicas"]
