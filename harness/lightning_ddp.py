"""A Lightning DDP job reading a v2v plan: 2 CPU ranks (gloo) launched by Lightning's own
``ddp`` launcher (it re-runs this module once per extra rank), the dataset built at import,
before the process group exists, as a DataModule's ``__init__`` would, and tested for truth in
each training step (``if self.ds:``).

    python -m harness.lightning_ddp ENDPOINT OUT_DIR [--devices 2]

The dataset is a ``V2VStreamDataset`` of batches of 2, read through a DataLoader with 2 workers.

Each rank writes ``OUT_DIR/rank{R}.json``: its batch count, the sample ids it trained on
(padding excluded) and the padding ids. A rank with more batches than another would hang or
die in the gradient all-reduce.
"""
from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import torch

from harness.dist_exit import leave
from v2v_client import V2VStreamDataset


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("endpoint")
    ap.add_argument("out")
    ap.add_argument("--devices", type=int, default=2)
    args = ap.parse_args()

    import lightning as L

    # before fit: its rank and world size are found when first needed
    ds = V2VStreamDataset(args.endpoint, 2, outputs=("voxels",), timeout_s=60)

    class Tiny(L.LightningModule):
        def __init__(self):
            super().__init__()
            self.ds = ds
            self.w = torch.nn.Parameter(torch.zeros(1))
            self.seen, self.padding, self.batches = [], [], 0

        def training_step(self, batch, _):
            if not self.ds:  # the idiom: a dataset is truthy whatever len() says
                raise RuntimeError("no dataset")
            self.batches += 1
            keep = ~batch["padding"]
            self.seen += [s for s, k in zip(batch["sample_ids"], keep.tolist()) if k]
            self.padding += [s for s, k in zip(batch["sample_ids"], keep.tolist()) if not k]
            x = batch["voxels"].flatten(1).mean(1)
            return ((self.w * x - 1.0) ** 2 * keep.float()).mean()

        def configure_optimizers(self):
            return torch.optim.SGD(self.parameters(), lr=0.01)

        def train_dataloader(self):
            return torch.utils.data.DataLoader(ds, batch_size=None, num_workers=2)

        def on_train_end(self):
            rank = self.global_rank
            Path(args.out, f"rank{rank}.json").write_text(json.dumps(
                {"rank": rank, "env_world_size": os.environ.get("WORLD_SIZE"), "dataset_world_size": ds.world_size,
                 "batches": self.batches, "seen": self.seen, "padding": self.padding}))

    trainer = L.Trainer(accelerator="cpu", devices=args.devices, strategy="ddp", max_epochs=1, logger=False,
                        enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False)
    trainer.fit(Tiny())
    leave(0)  # not through interpreter finalization: harness/dist_exit.py says why


if __name__ == "__main__":
    main()
