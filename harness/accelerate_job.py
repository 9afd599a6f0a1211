"""A Hugging Face Accelerate job reading a v2v stream, one process per rank (start it with
``torchrun --nproc_per_node 2 -m harness.accelerate_job ENDPOINT OUT_DIR [options]``; gloo on CPU).

    --mode dispatch    v2v_client.prepare_loader, accelerate's default dispatch_batches
    --mode per-rank    v2v_client.prepare_loader with dispatch_batches=False
    --mode plain       accelerator.prepare(loader) as accelerate's docs show (add --per-rank-config
                       for dispatch_batches=False)
    --stateful --save-at K --stop-after K2   save_state after step K, leave the loop after step K2
    --resume DIR       load_state(DIR) first
    --skip-first N     read accelerator.skip_first_batches(loader, N) instead
    --prepare-twice    prepare_loader the loader it returned again (``twice``: whether it gave the same one)
    --again            after leaving the loop (--stop-after), iterate the loader again to its end

Each rank writes ``OUT_DIR/rank{R}.json``: the ids it trained on (padding excluded; with
``--save-at``, ``saved``: those trained up to the checkpoint), ``seen_epochs`` / ``saved_epochs`` (the
same as ``[epoch, id]``), padding rows, batches, per step ``epochs`` (the batch's server epoch),
``sync_gradients`` and ``end_of_dataloader``, ``twice``, ``error`` (the first line of an exception,
raised before any step or during one), and ``cpu_s`` / ``wall_s``: this process's CPU seconds (all
its threads) and seconds from its first batch to the end of the loop (``bench/launchers.py``), and
``io_threads``: the stream I/O threads still running when it wrote the record (it leaves by
``harness.dist_exit.leave``, so nothing of it is left to interpreter finalization).
"""
from __future__ import annotations

import argparse
import json
import os
import threading
import time
from pathlib import Path

import torch

from harness.dist_exit import leave


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("endpoint")
    ap.add_argument("out")
    ap.add_argument("--mode", choices=["dispatch", "per-rank", "plain"], default="dispatch")
    ap.add_argument("--per-rank-config", action="store_true")
    ap.add_argument("--stateful", action="store_true")
    ap.add_argument("--accumulate", type=int, default=1)
    ap.add_argument("--save-at", type=int, default=-1)
    ap.add_argument("--stop-after", type=int, default=-1)
    ap.add_argument("--resume", default="")
    ap.add_argument("--skip-first", type=int, default=0)
    ap.add_argument("--prepare-twice", action="store_true")
    ap.add_argument("--again", action="store_true")
    ap.add_argument("--outputs", default="frames", help="comma-separated; frames must be among them")
    args = ap.parse_args()

    from accelerate import Accelerator, DataLoaderConfiguration

    from v2v_client import V2VPushDataset, prepare_loader

    per_rank = args.mode == "per-rank" or args.per_rank_config
    config = DataLoaderConfiguration(dispatch_batches=False if per_rank else None,
                                     use_stateful_dataloader=args.stateful)
    acc = Accelerator(cpu=True, dataloader_config=config, gradient_accumulation_steps=args.accumulate)
    ds = V2VPushDataset(args.endpoint, outputs=tuple(args.outputs.split(",")), timeout_s=60, credits=2)
    loader = torch.utils.data.DataLoader(ds, batch_size=None)
    model = torch.nn.Linear(1, 1)
    opt = torch.optim.SGD(model.parameters(), lr=0.01)
    if args.mode == "plain":
        model, opt, loader = acc.prepare(model, opt, loader)
    else:
        loader = prepare_loader(acc, loader)
        model, opt = acc.prepare(model, opt)
    twice = None
    if args.prepare_twice:
        again = prepare_loader(acc, loader)
        twice, loader = again is loader, again
    if args.resume:
        acc.load_state(args.resume)
    if args.skip_first:
        loader = acc.skip_first_batches(loader, args.skip_first)
    rec = {"rank": acc.process_index, "seen": [], "seen_epochs": [], "saved": None, "saved_epochs": None,
           "padding": [], "batches": 0, "epochs": [], "sync": [], "end": [], "error": None, "twice": twice,
           "cpu_s": None, "wall_s": None}
    try:
        first = _train(acc, model, opt, loader, args, rec, args.stop_after)
        if args.again:
            _train(acc, model, opt, loader, args, rec, -1)
        if rec["batches"]:
            rec["cpu_s"], rec["wall_s"] = time.process_time() - first[0], time.monotonic() - first[1]
    except Exception as e:  # noqa: BLE001 - the test reads the line the user would read
        rec["error"] = f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"
    rec["io_threads"] = sum(t.name == "v2v-stream-io" for t in threading.enumerate())
    Path(args.out, f"rank{acc.process_index}.json").write_text(json.dumps(rec))
    if rec["error"] is None:
        acc.wait_for_everyone()
    acc.end_training()
    leave(0)  # not through interpreter finalization: harness/dist_exit.py says why


def _train(acc, model, opt, loader, args, rec, stop_after: int):
    """One pass of the training loop over ``loader`` (left after step ``stop_after``), recording into
    ``rec``; the CPU and wall clocks at its first batch."""
    clocks = (time.process_time(), time.monotonic())
    for step, batch in enumerate(loader):
        if step == 0:
            clocks = (time.process_time(), time.monotonic())
        with acc.accumulate(model):
            keep = ~batch["padding"]
            ids = batch["sample_ids"]
            rec["epochs"].append(batch["epoch"])
            rec["seen"] += [s for s, k in zip(ids, keep.tolist()) if k]
            rec["seen_epochs"] += [[batch["epoch"], s] for s, k in zip(ids, keep.tolist()) if k]
            rec["padding"] += [s for s, k in zip(ids, keep.tolist()) if not k]
            x = batch["frames"].flatten(1).mean(1, keepdim=True)
            loss = ((model(x) - 1.0) ** 2 * keep.float()[:, None]).mean()
            acc.backward(loss)
            opt.step()
            opt.zero_grad()
            rec["sync"].append(acc.sync_gradients)
            rec["end"].append(acc.gradient_state.end_of_dataloader)
        rec["batches"] += 1
        if step == args.save_at:
            acc.save_state(os.path.join(args.out, "ckpt"))
            rec["saved"], rec["saved_epochs"] = list(rec["seen"]), list(rec["seen_epochs"])
        if step == stop_after:
            break
    return clocks


if __name__ == "__main__":
    main()
