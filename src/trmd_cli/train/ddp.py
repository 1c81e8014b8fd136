"""Data-parallel training across processes (``torchrun``), and the single-process default.

``torchrun --nproc_per_node=K [--nnodes …] -m trmd_cli train …`` starts K copies of the command
with ``RANK``, ``WORLD_SIZE``, ``LOCAL_RANK``, ``MASTER_ADDR`` and ``MASTER_PORT`` set;
:func:`setup` reads them and joins the process group (gloo on CPU, nccl on CUDA). Every process
trains on its own share of each epoch; gradients are averaged by DDP; only rank 0 writes files.
Without those variables everything here is a no-op for one process.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import torch

from ..errors import InputError

__all__ = ["Dist", "setup", "teardown", "all_reduce_sum", "any_flag", "barrier"]


@dataclass(frozen=True)
class Dist:
    """Where this process stands: ``rank`` of ``world`` processes, on ``device``."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0
    device: torch.device = torch.device("cpu")

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @property
    def enabled(self) -> bool:
        return self.world > 1


def _env_int(name: str, default: int) -> int:
    text = os.environ.get(name)
    if text is None:
        return default
    try:
        return int(text)
    except ValueError:
        raise InputError(f"environment variable {name}={text!r} is not an integer") from None


def setup(device: str = "auto") -> Dist:
    """Read torchrun's variables, pick the device, join the process group when world > 1.

    Args:
        device: ``"auto"`` (CUDA if available), ``"cpu"`` or ``"cuda"``.
    """
    if device not in ("auto", "cpu", "cuda"):
        raise InputError(f"`device={device!r}` is not auto, cpu or cuda")
    world = _env_int("WORLD_SIZE", 1)
    rank = _env_int("RANK", 0)
    local = _env_int("LOCAL_RANK", 0)
    use_cuda = torch.cuda.is_available() if device == "auto" else device == "cuda"
    if use_cuda and not torch.cuda.is_available():
        raise InputError("`device='cuda'` but no CUDA device is available",
                         hint="use `device='cpu'`")
    if use_cuda:
        torch.cuda.set_device(local % torch.cuda.device_count())
        dev = torch.device("cuda", torch.cuda.current_device())
    else:
        dev = torch.device("cpu")
    if world > 1 and not torch.distributed.is_initialized():
        torch.distributed.init_process_group(backend="nccl" if use_cuda else "gloo",
                                             rank=rank, world_size=world)
    return Dist(rank=rank, world=world, local_rank=local, device=dev)


def teardown(dist: Dist) -> None:
    if dist.enabled and torch.distributed.is_initialized():
        torch.distributed.destroy_process_group()


def all_reduce_sum(dist: Dist, values: list[float]) -> list[float]:
    """Sum of ``values`` over processes (float64)."""
    if not dist.enabled:
        return list(values)
    t = torch.tensor(values, dtype=torch.float64,
                     device=dist.device if dist.device.type == "cuda" else "cpu")
    torch.distributed.all_reduce(t)
    return t.tolist()


def any_flag(dist: Dist, flag: bool) -> bool:
    """True on every process when ``flag`` is true on any (e.g. the time budget ran out)."""
    if not dist.enabled:
        return flag
    return all_reduce_sum(dist, [1.0 if flag else 0.0])[0] > 0


def barrier(dist: Dist) -> None:
    if dist.enabled:
        torch.distributed.barrier()
