"""Data-parallel training under ``torchrun``: the process group, gradient averaging and sharing work.

Every trainer joins the group with :func:`setup_process_group` (gloo on CPU, NCCL on CUDA). Each process
draws the same global batch and trains on its slice; :func:`average_gradients` all-reduces the
gradients once per step so all processes keep identical weights. Work after training (held-out
scoring) is split with :func:`shard` and collected with :func:`gather_items` so no process waits on
another for long. The group is left at interpreter exit (:func:`leave_process_group`): a gloo process that
exits with its group still up can abort while its worker threads are torn down.
"""

from __future__ import annotations

import atexit
import os
from dataclasses import dataclass
from typing import Any

import torch
import torch.distributed as dist

from relightanyone.model.device import resolve_device


@dataclass
class ProcessGroup:
    rank: int
    world_size: int
    device: torch.device

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.world_size > 1


def setup_process_group(device_name: str = "auto") -> ProcessGroup:
    """Join the torchrun process group when ``WORLD_SIZE`` > 1 (gloo on CPU, NCCL with CUDA).

    ``device_name`` is a ``--device`` value (:func:`~relightanyone.model.device.resolve_device`); on CUDA
    under torchrun each process takes the GPU of its ``LOCAL_RANK``.
    """
    world_size = int(os.environ.get("WORLD_SIZE", "1"))
    device = resolve_device(device_name)
    use_cuda = device.type == "cuda"
    if world_size > 1 and not dist.is_initialized():
        dist.init_process_group("nccl" if use_cuda else "gloo")
        atexit.register(leave_process_group)
    rank = dist.get_rank() if world_size > 1 else 0
    if use_cuda:
        if world_size > 1 or device.index is None:
            device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
        torch.cuda.set_device(device)
    return ProcessGroup(rank=rank, world_size=world_size, device=device)


def leave_process_group() -> None:
    """Destroy the default process group, if one is up, while the interpreter is still whole."""
    if dist.is_initialized():
        dist.destroy_process_group()


def broadcast_weights(module: torch.nn.Module, group: ProcessGroup) -> None:
    """Every process takes rank 0's parameters and buffers (no-op in one process)."""
    if group.distributed:
        for tensor in list(module.parameters()) + list(module.buffers()):
            dist.broadcast(tensor.data, src=0)


def average_gradients(model: torch.nn.Module, world_size: int) -> None:
    """All-reduce every gradient (missing ones count as zero) and divide by the number of processes."""
    parameters = [p for p in model.parameters() if p.requires_grad]
    for parameter in parameters:
        if parameter.grad is None:
            parameter.grad = torch.zeros_like(parameter)
    flat = torch.cat([p.grad.reshape(-1) for p in parameters])
    dist.all_reduce(flat)
    flat /= world_size
    offset = 0
    for parameter in parameters:
        count = parameter.numel()
        parameter.grad.copy_(flat[offset : offset + count].view_as(parameter))
        offset += count


def weights_checksum(model: torch.nn.Module) -> float:
    """Sum of all parameters in float64: identical across processes when they are in sync."""
    return float(sum(p.detach().double().sum() for p in model.parameters()))


def sync_report(model: torch.nn.Module, group: ProcessGroup) -> dict:
    """``{"processes", "processes_in_sync"}`` from every process's weights checksum (collective);
    empty in one process."""
    if not group.distributed:
        return {}
    checksums = gather_items([weights_checksum(model)], group)
    return {"processes": group.world_size, "processes_in_sync": len(set(checksums)) == 1}


def shard(items: list, group: ProcessGroup) -> list[tuple[int, Any]]:
    """This process's share of ``items`` as (index, item) pairs: every ``world_size``-th one from its rank."""
    return [(i, item) for i, item in enumerate(items) if i % group.world_size == group.rank]


def gather_items(items: list, group: ProcessGroup) -> list:
    """Every process's ``items`` concatenated in rank order (collective; ``items`` itself in one process)."""
    if not group.distributed:
        return list(items)
    gathered: list = [None] * group.world_size
    dist.all_gather_object(gathered, items)
    return [item for part in gathered for item in part]
