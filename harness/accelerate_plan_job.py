"""A Hugging Face Accelerate job reading a plan (``v2v-serve``'s default delivery), one process per
rank: ``torchrun --nproc_per_node 2 -m harness.accelerate_plan_job ENDPOINT OUT_DIR [options]``
(gloo on CPU), the loader built as a new user writes it: ``DataLoader(ds, batch_size=None)`` over
``V2VStreamDataset(ENDPOINT, B)`` (rank and world size found by the dataset).

    --prepare plain    accelerator.prepare(loader) (default)
    --prepare loader   v2v_client.prepare_loader(accelerator, loader)
    --per-rank         DataLoaderConfiguration(dispatch_batches=False) (default: accelerate's, dispatch)
    --batch-size B     the dataset's batch size (default 2)
    --workers K        the DataLoader's num_workers
    --epochs E         epochs, each started by loader.set_epoch(epoch)
    --stateful --save-at S --stop-after S2   use_stateful_dataloader=True; save_state after step S
                       of the first epoch (and write its epoch), leave the job after step S2
    --resume DIR       load_state(DIR) first and start at the epoch saved with it

Each rank writes ``OUT_DIR/rank{R}.json``: ``seen`` (``[epoch, id]`` of the rows trained on,
padding excluded), ``saved`` (those up to the checkpoint), ``steps`` (per epoch), ``positions``
(``[epoch, sample_in_epoch]`` of each batch's position), ``len`` (``len(loader)`` per epoch),
``cpu_s`` and ``wall_s`` (this process's CPU seconds, every thread, and wall seconds from its first
batch to the end of its loop: ``bench.launchers``) and ``error`` (the first line of an exception raised before or during the loop). Every step is a
DDP step (the gradients all-reduced): ranks taking different numbers of steps would hang.
"""
from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import torch

from harness.dist_exit import leave


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("endpoint")
    ap.add_argument("out")
    ap.add_argument("--prepare", choices=["plain", "loader"], default="plain")
    ap.add_argument("--per-rank", action="store_true")
    ap.add_argument("--batch-size", type=int, default=2)
    ap.add_argument("--workers", type=int, default=0)
    ap.add_argument("--epochs", type=int, default=1)
    ap.add_argument("--stateful", action="store_true")
    ap.add_argument("--save-at", type=int, default=-1)
    ap.add_argument("--stop-after", type=int, default=-1)
    ap.add_argument("--resume", default="")
    args = ap.parse_args()

    from accelerate import Accelerator, DataLoaderConfiguration

    from v2v_client import V2VStreamDataset, prepare_loader

    config = DataLoaderConfiguration(dispatch_batches=False if args.per_rank else None,
                                     use_stateful_dataloader=args.stateful)
    acc = Accelerator(cpu=True, dataloader_config=config)
    ds = V2VStreamDataset(args.endpoint, args.batch_size, outputs=("frames",), timeout_s=60)
    loader = torch.utils.data.DataLoader(ds, batch_size=None, num_workers=args.workers)
    model = torch.nn.Linear(1, 1)
    opt = torch.optim.SGD(model.parameters(), lr=0.01)
    rec = {"rank": acc.process_index, "seen": [], "saved": None, "steps": {}, "positions": [], "len": [],
           "cpu_s": 0.0, "wall_s": 0.0, "error": None}
    clock = None  # (CPU, wall) seconds at the first batch
    try:
        if args.prepare == "plain":
            model, opt, loader = acc.prepare(model, opt, loader)
        else:
            loader = prepare_loader(acc, loader)
            model, opt = acc.prepare(model, opt)
        first = 0
        if args.resume:
            acc.load_state(args.resume)
            first = json.loads(Path(args.resume, "epoch.json").read_text())
        for epoch in range(first, args.epochs):
            loader.set_epoch(epoch)
            steps = 0
            for step, batch in enumerate(loader):
                clock = clock or (time.process_time(), time.perf_counter())
                keep = ~batch["padding"]
                rec["seen"] += [[batch["epoch"], s] for s, k in zip(batch["sample_ids"], keep.tolist()) if k]
                rec["positions"].append([batch["position"]["epoch"], batch["position"]["sample_in_epoch"]])
                x = batch["frames"].flatten(1).mean(1, keepdim=True)
                loss = ((model(x) - 1.0) ** 2 * keep.float()[:, None]).mean()
                acc.backward(loss)
                opt.step()
                opt.zero_grad()
                steps += 1
                if epoch == first and step == args.save_at:
                    ckpt = os.path.join(args.out, "ckpt")
                    acc.save_state(ckpt)
                    if acc.is_main_process:
                        Path(ckpt, "epoch.json").write_text(json.dumps(epoch))
                    rec["saved"] = list(rec["seen"])
                if epoch == first and step == args.stop_after:
                    break
            rec["steps"][epoch] = steps
            if clock:
                rec["cpu_s"], rec["wall_s"] = time.process_time() - clock[0], time.perf_counter() - clock[1]
            rec["len"].append(len(loader))  # after the pass: IterableDatasetShard's len fails before it
            if epoch == first and args.stop_after >= 0 and steps == args.stop_after + 1:
                break
    except Exception as e:  # noqa: BLE001 - the test reads the line the user would read
        rec["error"] = f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"
    Path(args.out, f"rank{acc.process_index}.json").write_text(json.dumps(rec))
    if rec["error"] is None:
        acc.wait_for_everyone()
    acc.end_training()
    leave(0)  # not through interpreter finalization: harness/dist_exit.py says why


if __name__ == "__main__":
    main()
