"""The process group is left cleanly: a gloo process that exits with its group up can abort."""

from __future__ import annotations

import torch.distributed as dist

from relightanyone.model.train.distributed import leave_process_group


def test_leave_process_group_destroys_the_group_and_is_idempotent(tmp_path):
    dist.init_process_group("gloo", init_method=f"file://{tmp_path / 'rendezvous'}", rank=0, world_size=1)
    assert dist.is_initialized()
    leave_process_group()
    assert not dist.is_initialized()
    leave_process_group()  # at exit after an explicit leave: nothing to do
    assert not dist.is_initialized()
