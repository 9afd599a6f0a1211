"""A DDP training loop reading a plan (``v2v-serve``'s default delivery) through a plain DataLoader
with workers, one process per rank: ``torchrun --nproc_per_node N -m harness.plan_job ENDPOINT
OUT_DIR [--epochs E] [--batch-size B] [--workers W] [--stop-after S] [--resume POSITION.json]`` (gloo
on CPU).

Each step is a DDP step (an all-reduce in backward: ranks that took different numbers of steps
would hang). With ``--stop-after S`` the job leaves after S steps of its first epoch, rank 0 writing
the last batch's ``position`` to ``OUT_DIR/position.json``; with ``--resume`` it starts there.
Each rank writes ``OUT_DIR/rank{R}.json``: ``seen`` (``[epoch, id]`` of the rows trained on,
padding excluded), ``steps`` per epoch, ``world`` and ``times`` (``[epoch, wall-clock s, rows]`` of
each step, once its batch arrived: ``bench.fleet``'s ``readers`` row reads rates from them).
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch
import torch.distributed as dist
from torch.utils.data import DataLoader

from harness.dist_exit import leave
from v2v_client import V2VStreamDataset


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("endpoint")
    ap.add_argument("out", type=Path)
    ap.add_argument("--epochs", type=int, default=2)
    ap.add_argument("--batch-size", type=int, default=2)
    ap.add_argument("--workers", type=int, default=2, help="DataLoader workers per rank (0: the main process)")
    ap.add_argument("--stop-after", type=int, default=None)
    ap.add_argument("--resume", type=Path, default=None)
    a = ap.parse_args()
    dist.init_process_group("gloo")
    rank, world = dist.get_rank(), dist.get_world_size()
    ds = V2VStreamDataset(a.endpoint, a.batch_size, outputs=("frames",), timeout_s=120)
    first = 0
    if a.resume is not None:
        position = json.loads(a.resume.read_text())
        ds.load_state_dict(position)
        first = position["epoch"]
    model = torch.nn.parallel.DistributedDataParallel(torch.nn.Linear(1, 1))
    opt = torch.optim.SGD(model.parameters(), lr=0.01)
    rec = {"seen": [], "steps": {}, "world": world, "times": []}
    for epoch in range(first, a.epochs):
        ds.set_epoch(epoch)
        steps = 0
        for batch in DataLoader(ds, batch_size=None, num_workers=a.workers):
            keep = ~batch["padding"]
            rec["times"].append([epoch, time.time(), int(keep.sum())])
            rec["seen"] += [[epoch, s] for s, k in zip(batch["sample_ids"], keep.tolist()) if k]
            x = batch["frames"].flatten(1).mean(1, keepdim=True)
            loss = ((model(x) - 1.0) ** 2 * keep.float()[:, None]).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            steps += 1
            if a.stop_after is not None and steps == a.stop_after:
                if rank == 0:
                    (a.out / "position.json").write_text(json.dumps(batch["position"]))
                break
        rec["steps"][epoch] = steps
        if a.stop_after is not None:
            break
    (a.out / f"rank{rank}.json").write_text(json.dumps(rec))
    dist.barrier()
    dist.destroy_process_group()
    leave(0)


if __name__ == "__main__":
    main()
