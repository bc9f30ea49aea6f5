"""Data parallelism under ``torchrun``: one process per rank, DistributedDataParallel, gloo on CPUs, NCCL on GPUs.

``torchrun`` (PyTorch's ``torch.distributed.run``) starts the ranks and sets the variables of :data:`VARIABLES` in
each. :func:`from_environment` reads and checks them (None without torchrun: then nothing here is used and training
is the single-process loop), :func:`init` joins the process group. What each rank does in ``kpd train``:

- every rank checks the same arguments and the torchrun environment before any communication, so an inconsistency
  (a world size that does not divide ``--batch``, a rank outside the world, a missing GPU) ends every rank with one
  line and exit status 2 instead of a hang;
- rank 0 alone checks the output folder, reads the checkpoint of ``--resume`` and sends it to the others
  (:func:`only_main`, :func:`broadcast_state`), so only rank 0's machine needs the run folder;
- the sample cache is filled in turns (:func:`in_turn`): rank 0 first, then the first rank of every other node (for
  caches on node-local disks), then all other ranks, which find every entry cached;
- every rank takes its slice ``[rank * B / W, (rank + 1) * B / W)`` of each iteration's global batch, drawn from
  ``(seed, iteration)`` as in a single process; DDP averages the gradients, so the update is the single process's;
- rank 0 alone validates and writes the checkpoint, the curves and the record.

When rank 0 stops on an error it reports, the other ranks raise :class:`Stopped`, which the command turns into exit
status 2 without repeating the message.
"""

from __future__ import annotations

import io
import os
from datetime import timedelta
from typing import Callable, Mapping, NamedTuple, TypeVar

import torch
import torch.distributed as dist

from kpd.errors import InputError, KpdError

__all__ = ["VARIABLES", "WAIT_TIMEOUT", "World", "Stopped", "from_environment", "init", "shutdown", "only_main",
           "in_turn", "broadcast_state", "average", "barrier"]

VARIABLES = ("RANK", "LOCAL_RANK", "WORLD_SIZE", "LOCAL_WORLD_SIZE", "MASTER_ADDR", "MASTER_PORT")
# How long ranks wait for one another outside the training steps (rank 0 sampling a large collection into the cache,
# writing a checkpoint); the steps themselves use the backend's default timeout.
WAIT_TIMEOUT = timedelta(hours=6)

T = TypeVar("T")

_wait_group = None  # a gloo group with WAIT_TIMEOUT for the turns, flags and the checkpoint broadcast


class World(NamedTuple):
    """This process's place in a torchrun job.

    rank : 0 .. size - 1 over all nodes; local_rank : 0 .. local_size - 1 on this node.
    size : the world size W (processes over all nodes); local_size : processes on this node.
    backend : ``gloo`` (CPU) or ``nccl`` (CUDA).
    device : ``cpu`` or ``cuda:<local_rank>``.
    """

    rank: int
    local_rank: int
    size: int
    local_size: int
    backend: str
    device: torch.device

    @property
    def main(self) -> bool:
        return self.rank == 0

    def share(self, batch: int) -> slice:
        """This rank's pairs of a global batch of ``batch``: ``[rank * batch / W, (rank + 1) * batch / W)``."""
        per_rank = batch // self.size
        return slice(self.rank * per_rank, (self.rank + 1) * per_rank)

    def to_dict(self) -> dict:
        return {"world_size": self.size, "local_world_size": self.local_size, "backend": self.backend,
                "device_type": self.device.type}


class Stopped(KpdError):
    """Raised on the ranks that did not fail when another rank stopped with an error it reports itself (the command
    exits with status 2 without repeating it)."""


def _integer(environ: Mapping[str, str], name: str) -> int:
    try:
        return int(environ[name])
    except ValueError:
        raise InputError(f"torchrun environment: {name} must be an integer; got {environ[name]!r}") from None


def from_environment(batch: int, device: str = "auto", environ: Mapping[str, str] | None = None) -> World | None:
    """The torchrun job this process belongs to, checked; None when not started by torchrun.

    Parameters
    ----------
    batch : the global batch B (``--batch``), split evenly over the ranks.
    device : ``auto`` (CUDA when available), ``cpu`` or ``cuda``; each rank takes the GPU of its LOCAL_RANK.
    environ : default ``os.environ``.

    Raises
    ------
    InputError : when the variables are incomplete or inconsistent, W does not divide B, or the device cannot serve
        this rank; the message names the variable, its value and what was expected.
    Stopped : on ranks other than 0 for what every rank finds alike (W does not divide B, a --device torchrun cannot
        use), which rank 0 reports.
    """
    environ = os.environ if environ is None else environ
    if not any(name in environ for name in ("RANK", "LOCAL_RANK", "WORLD_SIZE")):
        return None
    missing = [name for name in VARIABLES if name not in environ]
    if missing:
        given = [name for name in VARIABLES if name in environ]
        raise InputError(f"incomplete torchrun environment: {', '.join(given)} set but {', '.join(missing)} missing; "
                         "start kpd train with torchrun (docs/training.md: Training on more machines) or unset them")
    rank, local_rank = _integer(environ, "RANK"), _integer(environ, "LOCAL_RANK")
    size, local_size = _integer(environ, "WORLD_SIZE"), _integer(environ, "LOCAL_WORLD_SIZE")
    port = _integer(environ, "MASTER_PORT")
    if size < 1 or not 0 <= rank < size:
        raise InputError(f"torchrun environment: RANK must lie in [0, WORLD_SIZE); got RANK={rank}, WORLD_SIZE={size}")
    if not 1 <= local_size <= size or not 0 <= local_rank < local_size:
        raise InputError(f"torchrun environment: need 0 <= LOCAL_RANK < LOCAL_WORLD_SIZE <= WORLD_SIZE; got "
                         f"LOCAL_RANK={local_rank}, LOCAL_WORLD_SIZE={local_size}, WORLD_SIZE={size}")
    if not 0 < port < 65536:
        raise InputError(f"torchrun environment: MASTER_PORT must lie in [1, 65535]; got {port}")
    # What every rank finds alike is reported by rank 0 alone (one line for the job); the others stop quietly.
    common = InputError if rank == 0 else Stopped
    if batch % size:
        raise common(f"--batch {batch} does not split over WORLD_SIZE={size} ranks: each rank takes batch / world "
                     f"size pairs, so pass a multiple of {size}")
    if not dist.is_available():
        raise common("this torch build has no torch.distributed; torchrun training needs it")
    kind = device.split(":", 1)[0]
    if device not in ("auto", "cpu", "cuda"):
        if kind in ("cpu", "cuda"):
            raise common(f"--device {device}: under torchrun each rank uses the GPU of its LOCAL_RANK; pass "
                         "--device cuda (or cpu)")
        raise common(f"--device {device}: torchrun training runs on cpu (gloo) or cuda (nccl)")
    use_cuda = torch.cuda.is_available() if device == "auto" else device == "cuda"
    if not use_cuda:
        if not dist.is_gloo_available():
            raise common("this torch build has no gloo backend; torchrun training on CPUs needs it")
        return World(rank, local_rank, size, local_size, "gloo", torch.device("cpu"))
    if not torch.cuda.is_available():
        raise InputError("--device cuda requested but CUDA is not available")
    count = torch.cuda.device_count()
    if local_rank >= count:
        raise InputError(f"torchrun environment: LOCAL_RANK={local_rank} needs GPU {local_rank} but this node has "
                         f"{count}; start at most {count} processes per node (--nproc_per_node)")
    if not dist.is_nccl_available():
        raise InputError("this torch build has no NCCL backend; torchrun training on GPUs needs it")
    return World(rank, local_rank, size, local_size, "nccl", torch.device("cuda", local_rank))


def init(world: World) -> None:
    """Join the process group of ``world`` (MASTER_ADDR/MASTER_PORT from torchrun) and set this rank's GPU."""
    global _wait_group
    if world.device.type == "cuda":
        torch.cuda.set_device(world.device)
        dist.init_process_group("nccl", rank=world.rank, world_size=world.size, device_id=world.device)
    else:
        dist.init_process_group("gloo", rank=world.rank, world_size=world.size)
    _wait_group = dist.new_group(backend="gloo", timeout=WAIT_TIMEOUT)


def shutdown() -> None:
    """Leave the process group (a no-op when none was joined)."""
    global _wait_group
    if dist.is_available() and dist.is_initialized():
        dist.destroy_process_group()
    _wait_group = None


def _any_failed(failed: bool) -> bool:
    """True on every rank when ``failed`` is True on any rank (the collective is also a barrier)."""
    flag = torch.tensor([int(failed)], dtype=torch.int32)
    dist.all_reduce(flag, op=dist.ReduceOp.MAX, group=_wait_group)
    return bool(flag.item())


def _turns(world: World | None, fn: Callable[[], T], turn: int, turns: int) -> T | None:
    """Run ``fn`` in turn number ``turn`` of ``turns``; every rank learns after each turn whether a rank failed."""
    result = None
    for current in range(turns):
        error = None
        if current == turn:
            try:
                result = fn()
            except Exception as exc:  # noqa: BLE001 - passed on after the other ranks know
                error = exc
        if _any_failed(error is not None):
            if error is not None:
                raise error
            raise Stopped(f"rank {world.rank} stopped: another rank failed (its error is printed above)")
    return result


def only_main(world: World | None, fn: Callable[[], T]) -> T | None:
    """``fn()`` on rank 0 (its result; None on the other ranks, which wait). Without torchrun: ``fn()``.

    An exception on rank 0 is raised there and :class:`Stopped` on the others.
    """
    if world is None:
        return fn()
    return _turns(world, fn, 0 if world.main else -1, 1)


def in_turn(world: World | None, fn: Callable[[], T]) -> T:
    """``fn()`` on every rank: rank 0 first, then the first rank of each other node, then the rest.

    Used to fill the sample cache once: rank 0 samples what is missing, a node with its own cache folder samples it
    once more, and the other ranks then find every entry. Without torchrun: ``fn()``.
    """
    if world is None:
        return fn()
    return _turns(world, fn, 0 if world.main else (1 if world.local_rank == 0 else 2), 3)


def broadcast_state(world: World | None, state: dict | None) -> dict:
    """Rank 0's ``state`` (a checkpoint dict) on every rank: sent as ``torch.save`` bytes, read with
    ``weights_only=True``. Without torchrun: ``state``."""
    if world is None or world.size == 1:
        return state
    if world.main:
        buffer = io.BytesIO()
        torch.save(state, buffer)
        data = torch.frombuffer(bytearray(buffer.getvalue()), dtype=torch.uint8)
        size = torch.tensor([len(data)], dtype=torch.int64)
    else:
        size = torch.zeros(1, dtype=torch.int64)
    dist.broadcast(size, 0, group=_wait_group)
    if not world.main:
        data = torch.empty(int(size.item()), dtype=torch.uint8)
    dist.broadcast(data, 0, group=_wait_group)
    return state if world.main else torch.load(io.BytesIO(data.numpy().tobytes()), weights_only=True)


def average(tensor: torch.Tensor) -> torch.Tensor:
    """The mean of ``tensor`` over all ranks, in place, on its device (NaN entries stay NaN)."""
    dist.all_reduce(tensor, op=dist.ReduceOp.SUM)
    return tensor.div_(dist.get_world_size())


def barrier(world: World | None) -> None:
    """Wait for every rank (with :data:`WAIT_TIMEOUT`). Without torchrun: nothing."""
    if world is not None:
        _any_failed(False)
