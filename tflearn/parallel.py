"""Many processes through ``torch.distributed``: who this process is, which motions are
its own, and the few collective operations the pipeline needs.

A run started by ``torchrun`` (one process per rank; the environment names ``RANK``,
``WORLD_SIZE``, ``MASTER_ADDR``, ``MASTER_PORT``) joins one process group with
:func:`group` — gloo on CPU, NCCL when the device is CUDA. A process started without
those variables (or with ``WORLD_SIZE=1``) is a world of size 1: no process group is
made, every operation here returns its input as it is, and the run behaves exactly as
a plain single process.

The motions are dealt to ranks by :func:`shard` (motion j to rank j mod size), so
every rank knows every rank's share without asking. Results are exchanged as plain
Python objects (:func:`all_gather`, :func:`broadcast`: pickled, tensors moved to the
CPU first and back to the receiver's default device) or summed in place
(:func:`all_reduce_sum`: tensors on the group's device).
"""
from __future__ import annotations

import contextlib
import datetime
import os

import torch
import torch.distributed as dist

#: The environment torchrun sets for every process of a run.
ENV = ("RANK", "WORLD_SIZE", "MASTER_ADDR", "MASTER_PORT")


def active() -> bool:
    """Whether this process is one rank of a process group of size ≥ 2."""
    return dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1


def rank() -> int:
    """This process' rank (0 in a world of size 1)."""
    return dist.get_rank() if active() else 0


def size() -> int:
    """The number of processes of the run (1 without a process group)."""
    return dist.get_world_size() if active() else 1


def shard(n: int, rank: int, size: int) -> list:
    """The indices of ``n`` items that rank ``rank`` of ``size`` handles: j with
    j mod size = rank, ascending. Over the ranks every index appears exactly once."""
    if size < 1 or not 0 <= rank < size:
        raise ValueError(f"shard: rank {rank} is not one of {size} ranks")
    return list(range(rank, n, size))


def mine(n: int) -> list:
    """:func:`shard` of ``n`` items for this process."""
    return shard(n, rank(), size())


def local(device) -> torch.device:
    """``device`` for this process: plain ``cuda`` is the GPU numbered by torchrun's
    ``LOCAL_RANK`` (0 without torchrun); ``cuda:K`` and other devices as they are."""
    device = torch.device(device)
    if device.type == "cuda" and device.index is None:
        return torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
    return device


def backend(device: str) -> str:
    """The process-group backend for a device: NCCL for CUDA, gloo otherwise."""
    return "nccl" if torch.device(device).type == "cuda" else "gloo"


@contextlib.contextmanager
def group(device: str = "cpu", timeout_s: float = 1800.0):
    """``with group(device):`` the body runs in the process group torchrun describes
    (:data:`ENV`), made here and destroyed on leaving, every rank waiting for the others
    at the end of the body (a barrier). Without those variables, with
    ``WORLD_SIZE=1``, or when a process group already exists (made by the caller, who
    also ends it), nothing is made or destroyed."""
    made = False
    if int(os.environ.get("WORLD_SIZE", "1")) > 1 and not dist.is_initialized():
        missing = [k for k in ENV if k not in os.environ]
        if missing:
            raise RuntimeError(f"torch.distributed: WORLD_SIZE is set but not {', '.join(missing)} "
                               f"(start the processes with torchrun)")
        if torch.device(device).type == "cuda":
            torch.cuda.set_device(local(device))
        dist.init_process_group(backend(device), init_method="env://",
                                timeout=datetime.timedelta(seconds=timeout_s))
        made = True
    try:
        yield
        if made:           # leave together: torchrun stops every rank once one exits non-zero,
            dist.barrier()  # and rank 0 may still be writing the run's files
    finally:
        if made:
            dist.destroy_process_group()


def _map(obj, f):
    """``obj`` with ``f`` applied to every tensor in it (nested in lists, tuples, named
    tuples, dicts)."""
    if isinstance(obj, torch.Tensor):
        return f(obj)
    if isinstance(obj, tuple) and hasattr(obj, "_fields"):
        return type(obj)(*(_map(x, f) for x in obj))
    if isinstance(obj, (list, tuple)):
        return type(obj)(_map(x, f) for x in obj)
    if isinstance(obj, dict):
        return {k: _map(v, f) for k, v in obj.items()}
    return obj


def _to(obj, device):
    """``obj`` with every tensor in it moved to ``device``."""
    return _map(obj, lambda t: t.to(device))


def _own(t: torch.Tensor) -> torch.Tensor:
    """``t``, copied where its storage holds more than its elements: a pickled tensor
    carries its whole storage, so each row of a matrix sent as a view would carry the
    matrix (a thousand motions' rows, a thousand matrices)."""
    return t if t.untyped_storage().nbytes() == t.numel() * t.element_size() else t.clone()


def _cpu(obj):
    """``obj``'s tensors on the CPU, each in storage of its own size, to be pickled."""
    return _map(obj, lambda t: _own(t.to("cpu")))


def _here(obj):
    """``obj``'s tensors, received from another rank, on the device tensors are made on
    here (the CPU, or the run's device inside :func:`tflearn.train.on_device`)."""
    return _to(obj, torch.empty(()).device)


def all_gather(obj) -> list:
    """Every rank's ``obj``, by rank (size); [obj] in a world of size 1."""
    if not active():
        return [obj]
    out = [None] * size()
    dist.all_gather_object(out, _cpu(obj))
    return _here(out)


def broadcast(obj, src: int = 0):
    """Rank ``src``'s ``obj`` on every rank (the others' ``obj`` is ignored)."""
    if not active():
        return obj
    box = [_cpu(obj) if rank() == src else None]
    dist.broadcast_object_list(box, src=src)
    return _here(box[0])


def all_reduce_sum(tensor: torch.Tensor) -> torch.Tensor:
    """Σ over the ranks of ``tensor``, in place (and returned)."""
    if active():
        dist.all_reduce(tensor, op=dist.ReduceOp.SUM)
    return tensor


def gather_motions(n: int, part: list) -> list:
    """The per-motion results of all ranks in motion order (n): ``part`` is this rank's,
    one item per index of :func:`mine` (n), in that order. Any n items dealt by
    :func:`shard` are gathered so (EM's chunks of motions: :mod:`tflearn.fit.torque`);
    summed in that order afterwards, they add up as in one process, whatever the number
    of ranks — which :func:`all_reduce_sum`, adding each rank's partial sum, does not."""
    out = [None] * n
    for r, items in enumerate(all_gather(list(part))):
        for j, item in zip(shard(n, r, size()), items):
            out[j] = item
    return out
