"""``v2v-train``: train E2VID or EvFlow from a live ``v2v-serve`` stream (``--engine stream``,
the default) or from a Ray Data pipeline in Ray Train (``--engine ray``, ``trainer/ray_train.py``).

Both engines run the same steps (``trainer.core.Trainer``) in the same loop
(``trainer.loop.train_loop``). Outputs in ``--out``: ``train_log.csv`` (one row per step),
``train.log``, ``samples/step_NNNNNNN.png`` (voxel / prediction / ground truth),
``checkpoint_last.pt`` and ``checkpoint_NNNNNNN.pt`` (model, optimiser, step, config, the
stream's ``state_dict()``), ``summary.json``, TensorBoard event files (``tensorboard --logdir
runs/``; tags in ``trainer/tensorboard_log.py``; ``--no-tensorboard``: none).
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
import threading
import time
from pathlib import Path

from v2v_server.settings import add_flags, flag_values
from v2v_wire.commands import STARTED, input_overwritten, writable_problem, write_whole

from .config import RunSettings, apply_overrides, check_types, exit_on_config_error, load_config
from .core import Trainer, resolve_device
from .data import STREAM_ERRORS, ReadAhead, close_read_path, make_stream, read_path
from .models.lpips import LPIPSUnavailable
from .ray_train import add_ray_arguments
from .raft_flow import FlowSourceUnavailable
from .tasks import stream_outputs
from .tensorboard_log import tensorboard_problem

__all__ = ["build_arg_parser", "main"]

log = logging.getLogger("trainer")


def _setup_logging(out: Path):
    out.mkdir(parents=True, exist_ok=True)
    root = logging.getLogger()
    root.setLevel(logging.INFO)
    fmt = logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s")
    for h in (logging.StreamHandler(sys.stderr), logging.FileHandler(out / "train.log")):
        h.setFormatter(fmt)
        root.addHandler(h)


def build_arg_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="v2v-train", description="Train E2VID / HyperE2VID / ETNet / EvFlow from a v2v-serve stream.")
    p.add_argument("--config", help="YAML config (trainer/configs/e2vid.yaml, evflow.yaml, hypere2vid.yaml, etnet.yaml; "
                                    "keys: docs/trainer_config.md)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="config override, e.g. --set model.base_num_channels=8 (repeatable)")
    add_flags(p, RunSettings, "run (the config's top-level keys)")
    p.add_argument("--no-progress", action="store_true", help="no tqdm bar")
    p.add_argument("--no-tensorboard", action="store_true", help="no TensorBoard event files in --out "
                                                                  "(log.tensorboard: false)")
    p.add_argument("--engine", choices=["stream", "ray"], default="stream",
                   help="stream: read a v2v-serve endpoint (--connect); ray: make the samples in a Ray Data "
                        "pipeline from --videos and train in a Ray Train TorchTrainer (needs the 'ray' extra)")
    add_ray_arguments(p)
    return p


#: The files a run writes in ``--out`` besides its checkpoints and ``samples/``.
RUN_FILES = ("config.json", "train.log", "train_log.csv", "summary.json")


def out_problem(out: Path, config) -> str:
    """Why the run's ``--out`` cannot take it, or "": the folder or one of :data:`RUN_FILES` in
    it is the ``--config`` file (a run's own ``config.json`` given back as its config: copy it
    first), or the folder cannot be made or written. A resume reads ``checkpoint_last.pt`` there
    and the run then writes newer ones: that is what resuming is, not an input overwritten."""
    for target in (out, *(out / name for name in RUN_FILES)):
        why = input_overwritten(target, [("the config (--config)", config)])
        if why:
            return why if target == out else f"its {target.name} {why}"
    return writable_problem(out, folder=True)


@exit_on_config_error("v2v-train")
def main(argv=None) -> int:
    args = build_arg_parser().parse_args(argv)
    cfg = load_config(args.config, args.task)
    cfg = apply_overrides(cfg, args.set)
    cfg.update({k: v for k, v in flag_values(args, RunSettings).items() if k != "task"})
    if args.no_tensorboard:
        cfg["log"]["tensorboard"] = False
    check_types(cfg)
    out = Path(str(cfg["out"]).format(task=cfg["task"]))
    why = out_problem(out, args.config)
    if why:
        print(f"v2v-train: --out {out}: {why}", file=sys.stderr)
        return 2
    why = tensorboard_problem() if cfg["log"]["tensorboard"] else ""
    if why:
        print(f"v2v-train: log.tensorboard: {why}; or give --no-tensorboard", file=sys.stderr)
        return 2
    _setup_logging(out)
    if args.engine == "ray":
        from .ray_train import run_ray

        return run_ray(cfg, args, out)
    device = resolve_device(cfg["device"])
    log.info("task %s on %s, stream %s asking for %s", cfg["task"], device, cfg["connect"], stream_outputs(cfg))
    write_whole(out / "config.json", json.dumps(cfg, indent=2))
    lg = cfg["log"]
    resume = cfg.get("resume")
    if resume == "auto":
        resume = str(out / "checkpoint_last.pt") if (out / "checkpoint_last.pt").exists() else None
    t0 = time.perf_counter()
    opening = _Opening(lambda: _open(cfg, resume, device))  # the server asked and read while the model is built
    try:
        try:
            trainer = Trainer(cfg, str(out), device)
        except (FlowSourceUnavailable, LPIPSUnavailable) as e:  # RAFT or LPIPS asked for, weights missing
            log.error("%s", e)
            return 2
        log.info("model: %d parameters", sum(p.numel() for p in trainer.model.parameters()))
        t1 = time.perf_counter()
        _, feed, connect_s = opening.result()
        if resume:
            trainer.load_checkpoint(resume)
        trainer.fit(feed, int(cfg["max_steps"]), int(lg["image_every"]), int(lg["checkpoint_every"]),
                    progress=bool(lg["progress"]) and not args.no_progress, log_every=int(lg.get("every", 10)),
                    tensorboard=bool(lg["tensorboard"]),
                    startup={"connect": round(connect_s, 4), "model_build": round(t1 - t0, 4),
                             "to_loop": round(time.perf_counter() - STARTED, 4)})
    except STREAM_ERRORS as e:  # the server absent, silent, or refusing: one line, its own words
        print(f"v2v-train: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:  # Ctrl-C or SIGTERM: the checkpoint is written; no wait on a silent server
        opening.close(wait=False)
        raise
    finally:
        opening.close()
    return 0


def _open(cfg: dict, resume, device):
    """``(stream, read path, seconds to the server's answer)``: the run's stream (``make_stream``)
    at the resumed position, its read path reading (``read_path``; a plan's first fetches out)."""
    s = cfg["stream"]
    t = time.perf_counter()
    stream = make_stream(cfg["connect"], cfg["task"], timeout_s=s["timeout_s"], raw=s["raw"],
                         curve_keys=s.get("curve_keys") or None, outputs=stream_outputs(cfg))
    connect_s = time.perf_counter() - t
    if resume:
        _resume_stream(resume, stream)
    feed = read_path(stream, device)
    if isinstance(feed, ReadAhead):
        feed.start()
    return stream, feed, connect_s


class _Opening:
    """``open_`` run in a thread beside the model's build: :meth:`result` waits for it (raising
    what it raised, so a model that cannot be built is said before a server that cannot be
    reached); :meth:`close` closes the read path and the stream it made, now or when it ends (once:
    a later call does nothing; ``wait`` False, after an interrupt: without waiting for the read
    path's thread, ``trainer.data.close_read_path``)."""

    def __init__(self, open_):
        self._got, self._closed, self._wait = None, False, True
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, args=(open_,), name="v2v-open-stream", daemon=True)
        self._thread.start()

    def _run(self, open_) -> None:
        try:
            got = ("ok", open_())
        except BaseException as e:  # raised again in the caller's thread by result()
            got = ("error", e)
        with self._lock:
            self._got = got
            if self._closed:
                self._close()

    def result(self):
        self._thread.join()
        kind, value = self._got
        if kind == "error":
            raise value
        return value

    def close(self, wait: bool = True) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed, self._wait = True, wait
            if self._got is not None:
                self._close()

    def _close(self) -> None:
        if self._got[0] == "ok":
            for part in self._got[1][1::-1]:  # the read path, then the stream
                close_read_path(part, self._wait)


def _resume_stream(path: str, stream) -> None:
    """Hand the stream state of the checkpoint at ``path`` to ``stream`` before reading begins
    (the model and optimiser are restored later, by ``Trainer.load_checkpoint``)."""
    import torch

    state = torch.load(path, map_location="cpu", weights_only=False).get("stream_state")
    if state is not None and hasattr(stream, "load_state_dict"):
        stream.load_state_dict(state)
        log.info("resumed stream position from checkpoint")
    else:
        log.warning("checkpoint has no stream state or the client cannot load one: the stream restarts its epoch")


if __name__ == "__main__":  # pragma: no cover
    from v2v_wire.commands import main_of_module

    sys.exit(main_of_module("v2v-train", main))
