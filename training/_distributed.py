"""The process group of a run under ``torchrun`` (``torch.distributed``): one process == N.

Rank and world size come from the environment torchrun sets (``RANK``, ``WORLD_SIZE``,
``LOCAL_RANK``, ``LOCAL_WORLD_SIZE``, ``MASTER_ADDR``, ``MASTER_PORT``); the group is made with
``init_method="env://"`` on first use, gloo for CPU tensors and objects, NCCL for CUDA tensors
where a GPU is present. Alone (``WORLD_SIZE`` unset or 1) there is no process group and every
helper below is the identity: nothing to configure.

The rules the long runs follow with it: work is split by rank (a contiguous :meth:`Group.block`
or a :meth:`Group.strided` share); decisions that read the file system are made on rank 0 and
broadcast (:meth:`Group.on_main`); results come back to rank 0 in rank order (:meth:`Group.gather`)
or to every rank (:meth:`Group.all_gather`); only rank 0 writes files and prints.
"""

from __future__ import annotations

import atexit
import functools
import os
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from itertools import islice
from typing import Any, TypeVar

T = TypeVar("T")
R = TypeVar("R")


def _env_int(name: str, default: int) -> int:
    text = os.environ.get(name)
    if text is None or text == "":
        return default
    try:
        return int(text)
    except ValueError:
        raise ValueError(f"${name}: expected an integer (as torchrun sets it), received {text!r}") from None


@dataclass(frozen=True)
class Group:
    """This process's place in the run: ``rank`` of ``world`` processes, ``local_world`` of them on
    this machine. ``Group()`` is a process alone."""

    rank: int = 0
    world: int = 1
    local_world: int = 1

    @property
    def main(self) -> bool:
        """Rank 0: the process that writes files, logs and prints."""
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.world > 1

    def cpus(self) -> int:
        """This process's fair share of the machine's CPUs (at least 1)."""
        try:
            n = len(os.sched_getaffinity(0))
        except (AttributeError, OSError):
            n = os.cpu_count() or 1
        return max(1, n // self.local_world)

    def block(self, n: int) -> range:
        """The contiguous share ``[rank n / world, (rank + 1) n / world)`` of ``n`` items (rank order
        = input order)."""
        return range(self.rank * n // self.world, (self.rank + 1) * n // self.world)

    def strided(self, items: Sequence[T]) -> list[T]:
        """Items ``rank, rank + world, ...`` (a balanced share of units of similar cost)."""
        return list(items[self.rank::self.world])

    def on_main(self, fn: Callable[[], T]) -> T:
        """``fn()`` on rank 0, its result (or its exception, raised on every rank) sent to all."""
        if not self.distributed:
            return fn()
        import torch.distributed as dist

        box: list[Any] = [None]
        if self.main:
            try:
                box[0] = (True, fn())
            except (ValueError, OSError) as err:  # domain and file errors: every rank stops with them
                box[0] = (False, err)
        dist.broadcast_object_list(box, src=0)
        ok, value = box[0]
        if not ok:
            raise value
        return value

    def gather(self, obj: T) -> list[T] | None:
        """Every rank's ``obj``, in rank order, on rank 0 (``None`` on the others)."""
        if not self.distributed:
            return [obj]
        import torch.distributed as dist

        out: list[Any] | None = [None] * self.world if self.main else None
        dist.gather_object(obj, out, dst=0)
        return out

    def all_gather(self, obj: T) -> list[T]:
        """Every rank's ``obj``, in rank order, on every rank."""
        if not self.distributed:
            return [obj]
        import torch.distributed as dist

        out: list[Any] = [None] * self.world
        dist.all_gather_object(out, obj)
        return out

    def all_reduce_sum(self, t: Any) -> Any:
        """Sum of the ranks' tensors ``t`` (in place, returned); alone ``t`` itself."""
        if self.distributed:
            import torch.distributed as dist

            dist.all_reduce(t, op=dist.ReduceOp.SUM)
        return t

    def ordered(self, items: Sequence[T], work: Callable[[Sequence[T]], Iterable[R]], *,
                per_round: int = 64, granule: int = 1) -> Iterator[R]:
        """``work`` over ``items`` split across the ranks; on rank 0, every result in input order
        (streamed: rounds of ``world * per_round`` items, each split into the ranks' blocks of whole
        ``granule``s of items), on the others nothing.

        ``work(share)`` must yield one result per item of ``share``, in order; each rank calls it
        once, on its blocks of all rounds. Alone: ``work(items)`` itself. ``granule``: a ``work``
        that batches its items in groups of ``granule`` gets the groups one process would
        (``per_round`` is rounded up to a multiple of it)."""
        if not self.distributed:
            yield from work(items)
            return
        size = self.world * granule * -(-per_round // granule)
        rounds = [items[r:r + size] for r in range(0, len(items), size)]
        blocks = []
        for chunk in rounds:
            mine = self.block(-(-len(chunk) // granule))  # granules of this round
            blocks.append(chunk[mine.start * granule:mine.stop * granule])
        results = iter(work([x for block in blocks for x in block]))
        for block in blocks:
            parts = self.gather(list(islice(results, len(block))))
            for part in parts or ():
                yield from part


class CallRecorder:
    """Stands in for an object (a TensorBoard writer) on a rank that does not write: records every
    method call, to be sent to rank 0 and :meth:`replay`-ed on the real one there."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, tuple[Any, ...], dict[str, Any]]] = []

    def __getattr__(self, name: str) -> Callable[..., None]:
        if name.startswith("_"):
            raise AttributeError(name)
        return lambda *args, **kwargs: self.calls.append((name, args, kwargs))

    def take(self) -> list[tuple[str, tuple[Any, ...], dict[str, Any]]]:
        """The calls recorded so far (and forget them)."""
        calls, self.calls = self.calls, []
        return calls

    @staticmethod
    def replay(calls: Iterable[tuple[str, tuple[Any, ...], dict[str, Any]]], target: Any) -> None:
        for name, args, kwargs in calls:
            getattr(target, name)(*args, **kwargs)


@functools.cache
def process_group() -> Group:
    """This process's :class:`Group`, from the environment torchrun sets; the first call under
    torchrun (``WORLD_SIZE`` > 1) joins the process group (``env://``; gloo, and NCCL for CUDA
    tensors where a GPU is present), left again at exit."""
    world = _env_int("WORLD_SIZE", 1)
    if world <= 1:
        return Group()
    import torch
    import torch.distributed as dist

    rank, local_rank = _env_int("RANK", 0), _env_int("LOCAL_RANK", 0)
    local_world = _env_int("LOCAL_WORLD_SIZE", world)
    if not dist.is_available():
        raise ValueError("WORLD_SIZE > 1 but this torch has no torch.distributed; run without torchrun")
    if not dist.is_initialized():
        backend = "gloo"
        if torch.cuda.is_available() and dist.is_nccl_available():
            torch.cuda.set_device(local_rank % torch.cuda.device_count())
            backend = "cpu:gloo,cuda:nccl"
        dist.init_process_group(backend=backend, init_method="env://", rank=rank, world_size=world)
        atexit.register(dist.destroy_process_group)
    return Group(rank=dist.get_rank(), world=dist.get_world_size(), local_world=local_world)
