"""Run ``v2v-train`` and record what it trained on, one JSON line per step, so that a test can
kill it (SIGKILL) and still know which samples reached the model before the kill.

Run: ``python -m harness.train_recorder RECORD.jsonl v2v-train-arguments...``. Each line of
``RECORD.jsonl`` is ``{"step": s, "epoch": e, "ids": [...]}``, written (and flushed) after the
optimiser step ``s`` is done; padding samples are left out, as the loss leaves them out. With
``V2V_SIGKILL_AFTER_STEP=N`` in the environment the process sends itself SIGKILL once step N is
recorded: a crash at a known step (no checkpoint, no goodbye to the servers, no flush).
"""
from __future__ import annotations

import json
import os
import signal
import sys
from typing import List


def main(argv: List[str]) -> int:
    from trainer import core, train

    record = open(argv[0], "a", buffering=1)
    orig = core.Trainer.train_step
    kill_after = int(os.environ.get("V2V_SIGKILL_AFTER_STEP", "0"))

    def recording_step(self, batch, sync=True):
        stats = orig(self, batch, sync)
        pad = batch.get("padding")
        ids = [s for i, s in enumerate(batch["sample_ids"]) if pad is None or not bool(pad[i])]
        record.write(json.dumps({"step": self.step, "epoch": int(batch["epoch"]), "ids": ids}) + "\n")
        if kill_after and self.step >= kill_after:
            os.kill(os.getpid(), signal.SIGKILL)
        return stats

    core.Trainer.train_step = recording_step
    return train.main(argv[1:])


def trained_until(path: str, step: int) -> List[tuple]:
    """``(epoch, sample_id)`` of every step up to ``step`` in a record written by :func:`main`."""
    out = []
    with open(path) as f:
        for line in f:
            r = json.loads(line)
            if r["step"] <= step:
                out += [(r["epoch"], s) for s in r["ids"]]
    return out


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
