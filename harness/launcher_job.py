"""Training loops under the launchers people train with, reading a v2v plan, one process per
rank (start it with ``torchrun --nproc_per_node 2 [--max-restarts 1] -m harness.launcher_job
LAUNCHER ENDPOINT OUT_DIR --plan BATCH``; gloo on CPU):

    fabric       Lightning Fabric: fabric.setup_dataloaders(DataLoader(ds, batch_size=None))
    ignite       PyTorch Ignite: idist.Parallel, idist.auto_dataloader(ds, batch_size=None) as its docs
                 show (the error it raises is recorded), then an Engine run over DataLoader(ds, batch_size=None)
    elastic      plain DDP under torchrun --max-restarts 1: every step each rank checkpoints its model
                 step and the batch's ``position``; on the first attempt rank 1 kills itself (SIGKILL) after
                 step --kill-after, before that step's checkpoint; the restarted job resumes from the
                 last step both ranks checkpointed
    deepspeed    deepspeed.initialize(training_data=ds) (the error it raises is recorded), then the
                 engine over DataLoader(ds, batch_size=None)

The ranks read ``v2v-serve`` through ``V2VStreamDataset(ENDPOINT, BATCH)`` (``--plan BATCH``: rows a
rank), whose rank and world size come from the process group.

Each rank writes ``OUT_DIR/rank{R}.json``: ``seen`` (ids trained on, padding excluded, in the
history that survives: with ``elastic``, the checkpoint's plus those after the resume), ``batches``,
``refused`` (the first line of the error the launcher's own loader helper raised, if any) and
``attempt`` (torchelastic's restart count).
"""
from __future__ import annotations

import argparse
import json
import os
import signal
from pathlib import Path

import torch
from torch.utils.data import DataLoader

from harness.dist_exit import leave


def _record(batch, rec) -> torch.Tensor:
    """Note a batch's ids; a small loss over its frames with padding rows masked out."""
    keep = ~batch["padding"]
    rec["seen"] += [s for s, k in zip(batch["sample_ids"], keep.tolist()) if k]
    rec["batches"] += 1
    return batch["frames"].flatten(1).mean(1, keepdim=True), keep.float()[:, None]


def _first_line(e: BaseException) -> str:
    return f"{type(e).__name__}: {(str(e).splitlines() or [''])[0]}"


def fabric(ds, rec) -> None:
    import lightning as L

    fab = L.Fabric(accelerator="cpu", devices=2, strategy="ddp")
    fab.launch()
    model = torch.nn.Linear(1, 1)
    model, opt = fab.setup(model, torch.optim.SGD(model.parameters(), lr=0.01))
    for batch in fab.setup_dataloaders(DataLoader(ds, batch_size=None)):
        x, w = _record(batch, rec)
        fab.backward(((model(x) - 1.0) ** 2 * w).mean())
        opt.step()
        opt.zero_grad()


def ignite(ds, rec) -> None:
    import ignite.distributed as idist
    from ignite.engine import Engine

    def training(_local_rank):
        try:
            idist.auto_dataloader(ds, batch_size=None)
        except Exception as e:  # noqa: BLE001 - recorded for the test: ignite's own check of batch_size
            rec["refused"] = _first_line(e)
        model = idist.auto_model(torch.nn.Linear(1, 1))
        opt = idist.auto_optim(torch.optim.SGD(model.parameters(), lr=0.01))

        def step(engine, batch):
            x, w = _record(batch, rec)
            loss = ((model(x) - 1.0) ** 2 * w).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            return loss.item()

        Engine(step).run(DataLoader(ds, batch_size=None), max_epochs=1)

    with idist.Parallel(backend="gloo") as parallel:
        parallel.run(training)


def _checkpoints(out: Path, world: int):
    """The last step every rank checkpointed, and this rank's checkpoint of it (None, None without one)."""
    rank = torch.distributed.get_rank()
    steps = [{int(p.stem.split("step")[1]) for p in out.glob(f"ckpt.rank{r}.step*.json")} for r in range(world)]
    common = set.intersection(*steps) if steps else set()
    if not common:
        return None, None
    last = max(common)
    return last, json.loads((out / f"ckpt.rank{rank}.step{last}.json").read_text())


def _attempt_group(attempt: int) -> None:
    """The process group of this attempt, on torchelastic's agent store under a prefix of its own:
    the agent keeps its store across restarts, and a restarted rank reading the previous attempt's
    gloo addresses before its peer replaced them fails in connectFullMesh (Connection refused)."""
    rank, world = int(os.environ["RANK"]), int(os.environ["WORLD_SIZE"])
    store = torch.distributed.TCPStore(os.environ["MASTER_ADDR"], int(os.environ["MASTER_PORT"]), world,
                                       is_master=False)
    torch.distributed.init_process_group("gloo", store=torch.distributed.PrefixStore(f"attempt{attempt}", store),
                                         rank=rank, world_size=world)


def elastic(ds, rec, out: Path, kill_after: int) -> None:
    _attempt_group(rec["attempt"])
    rank, world = torch.distributed.get_rank(), torch.distributed.get_world_size()
    model = torch.nn.parallel.DistributedDataParallel(torch.nn.Linear(1, 1))
    opt = torch.optim.SGD(model.parameters(), lr=0.01)
    start, ckpt = _checkpoints(out, world)
    if ckpt is not None:
        ds.load_state_dict(ckpt["stream"])
        model.load_state_dict({k: torch.tensor(v) for k, v in ckpt["model"].items()})
        rec["seen"] = ckpt["seen"]
        rec["resumed_from"] = start
    step = -1 if start is None else start
    for batch in DataLoader(ds, batch_size=None):
        step += 1
        x, w = _record(batch, rec)
        ((model(x) - 1.0) ** 2 * w).mean().backward()
        opt.step()
        opt.zero_grad()
        if rec["attempt"] == 0 and rank == 1 and step == kill_after:
            os.kill(os.getpid(), signal.SIGKILL)  # mid-epoch, before this step's checkpoint
        state = {"stream": batch["position"], "seen": rec["seen"],
                 "model": {k: v.tolist() for k, v in model.state_dict().items()}}
        tmp = out / f".ckpt.rank{rank}.tmp"
        tmp.write_text(json.dumps(state))
        tmp.rename(out / f"ckpt.rank{rank}.step{step}.json")
    torch.distributed.destroy_process_group()


def deepspeed(ds, rec) -> None:
    import deepspeed as ds_lib

    ds_lib.init_distributed(dist_backend="gloo")
    config = {"train_micro_batch_size_per_gpu": 1, "optimizer": {"type": "SGD", "params": {"lr": 0.01}}}
    try:
        ds_lib.initialize(model=torch.nn.Linear(1, 1), config=config, training_data=ds)
    except Exception as e:  # noqa: BLE001 - recorded for the test: what DeepSpeed's own loader does
        rec["refused"] = _first_line(e)
    model = torch.nn.Linear(1, 1)
    engine, _, _, _ = ds_lib.initialize(model=model, model_parameters=model.parameters(), config=config)
    for batch in DataLoader(ds, batch_size=None):
        x, w = _record(batch, rec)
        loss = ((engine(x) - 1.0) ** 2 * w).mean()
        engine.backward(loss)
        engine.step()


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("launcher", choices=["fabric", "ignite", "elastic", "deepspeed"])
    ap.add_argument("endpoint")
    ap.add_argument("out")
    ap.add_argument("--kill-after", type=int, default=1)
    ap.add_argument("--plan", type=int, required=True, metavar="BATCH", help="rows of the plan a rank reads a step")
    args = ap.parse_args()

    from v2v_client import V2VStreamDataset

    out = Path(args.out)
    ds = V2VStreamDataset(args.endpoint, args.plan, outputs=("frames",), timeout_s=60)
    rec = {"seen": [], "batches": 0, "refused": None, "attempt": int(os.environ.get("TORCHELASTIC_RESTART_COUNT", 0))}
    if args.launcher == "fabric":
        fabric(ds, rec)
    elif args.launcher == "ignite":
        ignite(ds, rec)
    elif args.launcher == "elastic":
        elastic(ds, rec, out, args.kill_after)
    else:
        deepspeed(ds, rec)
    (out / f"rank{os.environ.get('RANK', '0')}.json").write_text(json.dumps(rec))
    leave(0)  # not through interpreter finalization: harness/dist_exit.py says why


if __name__ == "__main__":
    main()
