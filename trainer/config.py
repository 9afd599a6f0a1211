"""Trainer configuration: defaults per task, YAML files, and dotted command-line overrides.

Defaults follow the V2V paper's reference training configs (Lou et al., NeurIPS 2025):
Adam lr 1e-4 (amsgrad, no weight decay, constant), batch 12, sequences of 40 voxels of
5 bins, crop 128 (the server's defaults; the trainer checks what arrives).
"""
from __future__ import annotations

import contextlib
import copy
import functools
import math
import re
import sys
from dataclasses import asdict, dataclass, fields
from typing import Any, Iterable, Literal, Optional, Union, get_args, get_origin, get_type_hints

import yaml
from jsonargparse import ArgumentError, ArgumentParser

from v2v_server.settings import YamlLoader, load_yaml, setting
from v2v_server.checks import check_choice, check_keys

__all__ = ["DEFAULTS", "SECTIONS", "TASK_SECTIONS", "LOSS_PRESETS", "FLOW_SOURCES", "RunSettings", "default_config",
           "load_config", "apply_overrides", "apply_loss_preset", "SPELLINGS", "merge", "check_types",
           "reference_markdown", "ConfigError", "exit_on_config_error"]

#: The V2V paper's loss combinations for reconstruction, as ``loss`` section values. "V+L1+H"
#: (Table 2; the authors' train_v2v_*_10k.yaml): LPIPS-VGG + L1 + temporal consistency from
#: voxel L0 = 20 of 40. "Alex+TC" (Table 2; the authors' train_ablation_e2vid_esim.yaml):
#: LPIPS-Alex + temporal consistency over the whole sequence (their default L0 = 1, i.e.
#: fraction 0 here). The appendix's ablations: "Alex" (LPIPS-Alex only) and "Alex+TH"
#: (LPIPS-Alex + temporal consistency on the last half).
LOSS_PRESETS = {
    "v+l1+h": {"l1_weight": 1.0, "perceptual_weight": 1.0, "lpips_net": "vgg", "tc_weight": 1.0,
               "tc_start_fraction": 0.5},
    "alex+tc": {"l1_weight": 0.0, "perceptual_weight": 1.0, "lpips_net": "alex", "tc_weight": 1.0,
                "tc_start_fraction": 0.0},
    "alex": {"l1_weight": 0.0, "perceptual_weight": 1.0, "lpips_net": "alex", "tc_weight": 0.0,
             "tc_start_fraction": 0.0},
    "alex+th": {"l1_weight": 0.0, "perceptual_weight": 1.0, "lpips_net": "alex", "tc_weight": 1.0,
                "tc_start_fraction": 0.5},
}
#: ``loss.flow_source``: where the flow that a loss needs comes from. "stream": the server's
#: ``flow``; "raft-small" / "raft-large" (the names of the server's RAFT ``flow_preset``):
#: torchvision's RAFT on the batch's ground-truth frames on the training device
#: (``trainer/raft_flow.py``; the authors' ``optical_flow_source``).
FLOW_SOURCES = ("stream", "raft-small", "raft-large")
#: Other spellings a configuration may use for a choice, read as the listed one:
#: ``raft_small`` / ``raft_large`` (torchvision's function names, the authors' spelling).
SPELLINGS = {"raft_small": "raft-small", "raft_large": "raft-large"}
_RAFT_WEIGHTS_HELP = ("local .pth state dict of torchvision's raft_small / raft_large for flow_source raft-*; null: "
                      "$V2V_RAFT_WEIGHTS, else $TORCH_HOME/hub/checkpoints/raft_<size>*.pth (never downloaded)")


@dataclass
class RunSettings:
    """The run: task, stream endpoint, device, output folder, steps."""

    task: str = setting("e2vid", help="what to train", choices=("e2vid", "evflow", "hypere2vid", "etnet", "eraft"))
    connect: str = setting("tcp://127.0.0.1:5555", help="v2v-serve endpoint(s); several servers (shards) as "
                                                        "'tcp://a:5555,tcp://b:5555' (fan-in)")
    device: str = setting("auto", help="auto | cpu | cuda | cuda:N")
    out: str = setting("runs/{task}", help="output folder")
    max_steps: int = setting(200000, help="total optimiser steps")
    seed: int = setting(0, help="torch seed of the model's initialisation")
    amp: str = setting("fp32", help="fp32 as the reference trains; bf16: the network's forward under bf16 autocast "
                                    "(losses and metrics in float32)", choices=("fp32", "bf16"))
    compile: bool = setting(False, help="run the network through torch.compile (the authors' use_compile)")
    speed: str = setting("eager", help="eager: the authors' step; fast: channels-last, fused optimiser, one "
                                       "bf16 weight cast per step on the CPU, CUDA graphs and TF32 matmuls on "
                                       "CUDA (trainer/speed.py)",
                         choices=("eager", "fast"))
    require_lpips: bool = setting(False, help="refuse to start (exit 2) when the LPIPS weights are missing instead "
                                              "of training with the 1 - SSIM stand-in")
    resume: Optional[str] = setting(None, help="checkpoint path, or 'auto' = <out>/checkpoint_last.pt if present")


@dataclass
class StreamSettings:
    """``stream``: how the trainer reads v2v-serve (``V2VStreamDataset``)."""

    timeout_s: float = setting(60.0, help="seconds a server may stay silent (down, restarting) before the run "
                                          "ends with a TimeoutError naming it")
    raw: bool = setting(True, help="wire dtypes to the device, converted there")
    curve_keys: Optional[list] = setting(None, help="[client .key_secret file, server .key file] for a server "
                                                    "that requires CurveZMQ")


@dataclass
class OptimSettings:
    """``optim``: Adam as the reference trains E2VID and EvFlow (lr 1e-4, amsgrad, no weight decay, constant)."""

    optimizer: str = setting("adam", help="adam (L2 weight decay) or adamw (decoupled weight decay)",
                             choices=("adam", "adamw"))
    lr: float = setting(1.0e-4, help="learning rate")
    amsgrad: bool = setting(True, help="AMSGrad variant of Adam")
    weight_decay: float = setting(0.0, help="weight decay")
    lr_gamma: float = setting(1.0, help="exponential decay: lr = lr * lr_gamma ** (step // lr_gamma_every)")
    lr_gamma_every: int = setting(1000, help="optimiser steps per decay of lr_gamma (the reference decays per epoch)")
    clip_grad_norm: Optional[float] = setting(None, help="clip the gradient norm to this (None: off)")


@dataclass
class HyperE2VIDOptim(OptimSettings):
    """``optim`` of hypere2vid: Adam lr 1e-3, amsgrad, constant (the paper's appendix, the
    authors' train_v2v_hyper_10k.yaml)."""

    lr: float = setting(1.0e-3, help="learning rate")


@dataclass
class ETNetOptim(OptimSettings):
    """``optim`` of etnet: AdamW lr 2e-4, weight decay 0.01, amsgrad, lr x 0.94 per epoch
    (the paper's appendix, the authors' train_v2v_etnet_10k.yaml)."""

    optimizer: str = setting("adamw", help="adam (L2 weight decay) or adamw (decoupled weight decay)",
                             choices=("adam", "adamw"))
    lr: float = setting(2.0e-4, help="learning rate")
    weight_decay: float = setting(0.01, help="weight decay")
    lr_gamma: float = setting(0.94, help="exponential decay: lr = lr * lr_gamma ** (step // lr_gamma_every)")


@dataclass
class LogSettings:
    """``log``: what the run writes and when."""

    image_every: int = setting(500, help="steps between preview images (0: only at the end)")
    checkpoint_every: int = setting(1000, help="steps between checkpoints (0: only at the end)")
    progress: bool = setting(True, help="a progress bar on stderr")
    every: int = setting(10, help="steps between reads of the losses from the device (CSV rows are written then, "
                                  "one per step); no other step waits for the device")
    tensorboard: bool = setting(True, help="TensorBoard event files in the run's folder: the CSV's columns, the "
                                           "data-wait fraction, the previews, the config (trainer/tensorboard_log.py; "
                                           "v2v-train --no-tensorboard: off)")


@dataclass
class VoxelInput:
    """What every network reads: discrete voxel grids of ``num_bins`` bins (the server's
    ``num_bins``, checked against each batch)."""

    num_bins: int = setting(5, help="bins per voxel grid, B (the server's num_bins)")


@dataclass
class E2VIDModel(VoxelInput):
    """``model`` of e2vid: E2VID recurrent (Rebecq et al. 2019), the reference's sizes."""

    base_num_channels: int = setting(32, help="channels of the first encoder")
    num_encoders: int = setting(3, help="encoders (each halves the resolution)")
    num_residual_blocks: int = setting(2, help="residual blocks at the bottleneck")
    num_output_channels: int = setting(1, help="output channels (grey)")
    skip_type: str = setting("sum", help="skip connections", choices=("sum", "concat"))
    kernel_size: int = setting(5, help="encoder kernel size")


@dataclass
class E2VIDLoss:
    """``loss`` of the reconstruction tasks (e2vid, hypere2vid, etnet); default "V+L1+H": L1 +
    LPIPS-VGG, temporal consistency on the last half. ``preset`` sets the five term keys at
    once; keys written beside it (file or later ``--set``) win."""

    preset: Optional[str] = setting("v+l1+h", help="the paper's loss combination; null: the keys below as given",
                                    choices=tuple(LOSS_PRESETS))
    l1_weight: float = setting(1.0, help="weight of the L1 term")
    perceptual_weight: float = setting(1.0, help="weight of LPIPS (VGG); 1 - SSIM when no LPIPS weights")
    lpips_net: str = setting("vgg", help="LPIPS backbone", choices=("vgg", "alex"))
    lpips_weights: Any = setting(None, help="local LPIPS weight file(s); see trainer/models/lpips.py")
    use_lpips_package: bool = setting(True, help="allow 'import lpips' when no file is given")
    tc_weight: float = setting(1.0, help="weight of the temporal-consistency term")
    tc_alpha: float = setting(50.0, help="visibility sharpness of the temporal-consistency term")
    tc_start_fraction: float = setting(0.5, help="the term covers voxels from this fraction of L on (20..39 of 40)")
    flow_source: str = setting("stream", help="flow of the temporal-consistency term: the stream's, or RAFT on the "
                               "frames on the training device (the authors': raft-small)", choices=FLOW_SOURCES)
    raft_num_flow_updates: int = setting(12, help="RAFT's refinement iterations (flow_source raft-*)")
    raft_weights: Optional[str] = setting(None, help=_RAFT_WEIGHTS_HELP)


@dataclass
class HyperE2VIDModel(VoxelInput):
    """``model`` of hypere2vid: HyperE2VID (Ercan et al. 2024), the authors' sizes."""

    base_num_channels: int = setting(32, help="channels of the first encoder")
    num_encoders: int = setting(3, help="encoders (3: the dynamic decoder's context is at 1/4 resolution)")
    num_residual_blocks: int = setting(2, help="residual blocks at the bottleneck")
    kernel_size: int = setting(5, help="kernel size of the convolutions and of the dynamic per-pixel filters")


@dataclass
class HyperCurriculum:
    """``curriculum`` of hypere2vid: the previous reconstruction fed to the dynamic decoder is
    mixed with the ground-truth frame, ``(1 - beta) * rec + beta * frame``; beta falls from 1 in
    ``stages`` equal steps over the first ``fraction`` of max_steps, then stays 0 (the authors'
    ``hyper_epochs``: 16 of 80 epochs, beta = 1 - epoch / 16)."""

    fraction: float = setting(0.2, help="share of max_steps under the curriculum (16 of 80 epochs); 0: off")
    stages: int = setting(16, help="equal steps in which beta falls from 1 to 0 (one per reference epoch)")


@dataclass
class ETNetModel(VoxelInput):
    """``model`` of etnet: ETNet (Weng et al. 2021), the authors' sizes; smaller values for CPU demos."""

    d_model: int = setting(256, help="token width (channels of the bottleneck)")
    nhead: int = setting(8, help="attention heads")
    encoder_layers: int = setting(3, help="transformer encoder layers per scale")
    decoder_layers: int = setting(2, help="transformer decoder layers per scale")
    dim_feedforward: int = setting(1024, help="hidden width of the feed-forward blocks")
    dropout: float = setting(0.1, help="dropout in the transformer layers")


@dataclass
class EvFlowModel(VoxelInput):
    """``model`` of evflow: EV-FlowNet (Zhu et al. 2018), the reference's sizes."""

    base_num_channels: int = setting(32, help="channels of the first encoder")
    num_encoders: int = setting(4, help="encoders (each halves the resolution)")
    num_residual_blocks: int = setting(2, help="residual blocks at the bottleneck")
    num_output_channels: int = setting(2, help="output channels (flow x, y)")
    skip_type: str = setting("concat", help="skip connections", choices=("sum", "concat"))
    kernel_size: int = setting(3, help="encoder kernel size")


@dataclass
class EvFlowLoss:
    """``loss`` of evflow: dense L1 against the flow targets (the stream's, or RAFT's)."""

    flow_l1_weight: float = setting(1.0, help="weight of the flow L1 term")
    flow_source: str = setting("stream", help="flow targets: the stream's, or RAFT on the frames on the training "
                               "device (the authors': raft-large)", choices=FLOW_SOURCES)
    raft_num_flow_updates: int = setting(12, help="RAFT's refinement iterations (flow_source raft-*)")
    raft_weights: Optional[str] = setting(None, help=_RAFT_WEIGHTS_HELP)


@dataclass
class ERAFTModel(VoxelInput):
    """``model`` of eraft: E-RAFT (Gehrig et al. 2021) as the V2V authors train it
    (config/train_v2v_eraft_10k.yaml: 5 first channels, their n_first_channels = num_bins; warm
    start, 12 iterations). The parameters of ``trainer.models.eraft.ERAFT``, declared here only."""

    subtype: str = setting("warm_start", help="warm_start: the previous pair's flow initialises the next; "
                           "standard: every pair starts from zero flow", choices=("warm_start", "standard"))
    iters: int = setting(12, help="refinement iterations per voxel pair")
    corr_levels: int = setting(4, help="correlation pyramid levels (3 allows 64-pixel crops, small CPU runs; "
                               "not the authors' checkpoint)")
    corr_radius: int = setting(4, help="correlation lookup radius, cells")


@dataclass
class ERAFTLoss:
    """``loss`` of eraft: L1 between the last iteration's flow and the targets (the stream's, or
    RAFT's), over voxels 1..L-1 (each from the pair of grids l-1, l)."""

    flow_l1_weight: float = setting(1.0, help="weight of the flow L1 term")
    flow_source: str = setting("stream", help="flow targets: the stream's, or RAFT on the frames on the training "
                               "device (the authors': raft-large)", choices=FLOW_SOURCES)
    raft_num_flow_updates: int = setting(12, help="RAFT's refinement iterations (flow_source raft_*)")
    raft_weights: Optional[str] = setting(None, help=_RAFT_WEIGHTS_HELP)


#: Sections common to every task, and each task's model and loss sections.
SECTIONS = {"stream": StreamSettings, "optim": OptimSettings, "log": LogSettings}
TASK_SECTIONS = {"e2vid": {"model": E2VIDModel, "loss": E2VIDLoss},
                 "evflow": {"model": EvFlowModel, "loss": EvFlowLoss},
                 "hypere2vid": {"model": HyperE2VIDModel, "loss": E2VIDLoss, "optim": HyperE2VIDOptim,
                                "curriculum": HyperCurriculum},
                 "etnet": {"model": ETNetModel, "loss": E2VIDLoss, "optim": ETNetOptim},
                 "eraft": {"model": ERAFTModel, "loss": ERAFTLoss}}


def _schema(task: str) -> dict:
    """{key: (dataclass field, its type for jsonargparse) or {section key: (field, type)}} of
    ``task``'s configuration."""
    out = {f.name: (f, _library_type(RunSettings, f)) for f in fields(RunSettings)}
    for name, cls in {**SECTIONS, **TASK_SECTIONS[task]}.items():
        out[name] = {f.name: (f, _library_type(cls, f)) for f in fields(cls)}
    return out


def _defaults(task: str) -> dict:
    d = asdict(RunSettings(task=task))
    for name, cls in {**SECTIONS, **TASK_SECTIONS[task]}.items():
        d[name] = asdict(cls())
    return d


#: The defaults of each task, as plain nested dicts (the form checkpoints store).
DEFAULTS = {task: _defaults(task) for task in TASK_SECTIONS}


class ConfigError(ValueError):
    """A trainer configuration that cannot be used (a YAML file, a ``--set`` override, a flag, or
    the configuration a checkpoint stores); the message names the file, the key and what is
    allowed."""


@contextlib.contextmanager
def _config_errors(source: str = ""):
    """``ValueError`` (and a missing file) inside become :class:`ConfigError`, prefixed with
    ``source`` (a file's path) unless the message already names it."""
    try:
        yield
    except (ValueError, FileNotFoundError) as e:
        msg = str(e)
        if not source or source in msg:
            raise ConfigError(msg) from None
        raise ConfigError(f"{source}: {msg}") from None


def exit_on_config_error(prog: str):
    """Decorator of a command's ``main(argv) -> int`` (``v2v-train``, ``v2v-eval``): a
    :class:`ConfigError` raised inside prints ``<prog>: configuration error: <message>`` on
    stderr, without a traceback, and the command returns 2, as ``v2v-serve`` does."""

    def wrap(main):
        @functools.wraps(main)
        def run(*args, **kwargs):
            try:
                return main(*args, **kwargs)
            except ConfigError as e:
                print(f"{prog}: configuration error: {e}", file=sys.stderr)
                return 2

        return run

    return wrap


def merge(base: dict, upd: dict) -> dict:
    """Recursive dict merge; ``upd`` wins. Returns a new dict."""
    out = copy.deepcopy(base)
    for k, v in (upd or {}).items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = merge(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


def default_config(task: str) -> dict:
    """A deep copy of the defaults of ``task`` (a key of ``TASK_SECTIONS``); ``ValueError`` otherwise."""
    if task not in DEFAULTS:
        raise ValueError(f"task must be one of {sorted(DEFAULTS)}, got {task!r}")
    return copy.deepcopy(DEFAULTS[task])


def _check_keys(cfg: dict, ref: dict, section: str = ""):
    """Every key of ``cfg`` (and of its sections, the model's included) is one of ``ref``'s;
    ``ValueError`` from :func:`check_keys` naming the section and the allowed keys."""
    check_keys(cfg, ref, section)
    for k, v in cfg.items():
        if isinstance(v, dict) and isinstance(ref[k], dict):
            _check_keys(v, ref[k], f"{section}.{k}" if section else k)


def _library_type(cls, f) -> Any:
    """The type jsonargparse checks a field against: its annotation, with its ``choices`` as a
    ``Literal``; a field defaulting to None may be None."""
    t = get_type_hints(cls)[f.name]
    optional = type(None) in get_args(t) or f.default is None
    choices = f.metadata.get("choices")
    if choices:
        t = Literal[tuple(choices)]
    return Optional[t] if optional and t is not Any else t


@functools.lru_cache(maxsize=None)
def _parser(task: str) -> ArgumentParser:
    """The jsonargparse parser of ``task``'s configuration: one key per field of ``RunSettings``
    and one ``section.key`` per field of each section."""
    parser = ArgumentParser(exit_on_error=False, default_env=False)
    for key, ref in _schema(task).items():
        for sub, (_, t) in (ref.items() if isinstance(ref, dict) else [(None, ref)]):
            parser.add_argument(f"--{key}" + (f".{sub}" if sub else ""), type=t, default=None)
    return parser


def _library_error(e: Exception, cfg: dict, schema: dict) -> ValueError:
    """jsonargparse's refusal of a field as one line in the words of the other checks:
    ``config field 'optim.amsgrad' must be a bool, got 1``."""
    msg = " ".join(str(e).split())
    m = re.match(r'Parser key "([^"]+)"', msg)
    if not m:
        return ValueError(msg)
    key, node, ref = m.group(1), cfg, schema
    for part in key.split("."):
        node, ref = node.get(part) if isinstance(node, dict) else None, ref.get(part)
    return ValueError(f"config field {key!r} must be {_type_name(ref[1])}, got {node!r}")


def check_types(cfg: dict) -> dict:
    """Check ``cfg`` against the declared fields of its task (``RunSettings`` and the section
    dataclasses; jsonargparse checks each value against its annotation), in place, and return
    it: ints must be integers, floats finite numbers (stored as ``float``), booleans booleans,
    strings strings of the listed choices (``SPELLINGS`` read as the listed one); only a field
    declared Optional (or defaulting to None) may be None. Keys outside the schema are left
    alone (:func:`load_config` and :func:`apply_overrides` refuse them, naming the allowed ones).

    Raises:
        ConfigError: (a ``ValueError``) naming the dotted field.
    """
    with _config_errors():
        task = cfg.get("task", "e2vid")
        check_choice("config field 'task'", task, tuple(TASK_SECTIONS))
        schema = _schema(task)
        known = _known(cfg, schema, "")
        try:
            parsed = _parser(task).parse_object(known, defaults=False).as_dict()
        except ArgumentError as e:
            raise _library_error(e, known, schema) from None
        _write_back(cfg, parsed, schema)
        return cfg


def _known(cfg: dict, schema: dict, prefix: str) -> dict:
    """The keys of ``cfg`` that ``schema`` declares, spellings replaced (in ``cfg`` too) by the
    listed choice. ``ValueError`` for what jsonargparse would let through: a section that is not
    a mapping, None where the field may not be None, a float that is not finite, a string for a
    number or a boolean."""
    out = {}
    for k, v in cfg.items():
        name, ref = prefix + k, schema.get(k)
        if isinstance(ref, dict):
            if not isinstance(v, dict):
                raise ValueError(f"config field {name!r} must be a mapping, got {v!r}")
            out[k] = _known(v, ref, name + ".")
        elif ref is not None:
            field_, t = ref
            choices = field_.metadata.get("choices")
            if choices and isinstance(v, str) and v not in choices:
                v = cfg[k] = SPELLINGS.get(v, v)  # stored as the listed choice
            if v is None and t is not Any and type(None) not in get_args(t):
                raise ValueError(f"config field {name!r} may not be null")
            if isinstance(v, float) and not math.isfinite(v) and t is not Any:
                raise ValueError(f"config field {name!r} must be a finite number, got {v!r}")
            if isinstance(v, str) and not _takes_text(t):
                raise ValueError(f"config field {name!r} must be {_type_name(t)}, got the string {v!r}")
            out[k] = v
    return out


def _takes_text(t) -> bool:
    """Whether type ``t`` holds strings (jsonargparse would also read "5" as the int 5 and
    "yes" as true; a configuration's numbers and booleans are written as such)."""
    args = get_args(t)
    return t is Any or t is str or any(isinstance(a, str) or _takes_text(a) for a in args)


def _type_name(t) -> str:
    """``a float``, ``one of ['sum', 'concat']``, ``a str or null``: what type ``t`` holds."""
    if get_origin(t) is Literal:
        return f"one of {list(get_args(t))}"
    if get_origin(t) is Union:
        return " or ".join("null" if a is type(None) else _type_name(a) for a in get_args(t))
    name = getattr(t, "__name__", str(t))
    return f"{'an' if name[0] in 'aeiou' else 'a'} {name}"


def _write_back(cfg: dict, parsed: dict, schema: dict, prefix: str = "") -> None:
    """The one conversion the check makes, in place: an int given for a float field is stored
    as the float jsonargparse made of it; every other value stays as given (a string field's
    ``'null'`` is that string). ``ValueError`` for another string jsonargparse read as null (a
    choice that is not one)."""
    for k, v in parsed.items():
        given, ref = cfg.get(k), schema.get(k)
        if isinstance(ref, dict):
            _write_back(given, v, ref, f"{prefix}{k}.")
        elif v is None and given is not None and not (isinstance(given, str) and (ref[1] is Any or str in get_args(ref[1]))):
            raise ValueError(f"config field {prefix + k!r} must be {_type_name(ref[1])}, got {given!r}")
        elif isinstance(v, float) and isinstance(given, int) and not isinstance(given, bool):
            cfg[k] = v


def load_config(path: Optional[str] = None, task: Optional[str] = None) -> dict:
    """Load a YAML config over the task's defaults.

    The task comes from ``task`` if given, else the file's ``task:`` key, else 'e2vid'.

    Raises:
        ConfigError: (a ``ValueError``) naming the file, the key and the allowed keys for an
            unknown key; the file and the field for a bad value; a missing or unreadable file.
    """
    with _config_errors(str(path) if path else ""):
        user = dict(load_yaml(path)) if path else {}
        file_task = user.get("task")
        task = task or file_task or "e2vid"
    with _config_errors(str(path) if path and task == file_task else ""):
        base = default_config(task)
    with _config_errors(str(path) if path else ""):
        return _over_defaults(user, base, file_task, task)


def _over_defaults(user: dict, base: dict, file_task: Optional[str], task: str) -> dict:
    """``user`` (a file's mapping, of ``file_task``) over ``base`` (the defaults of ``task``),
    its keys and values checked."""
    if file_task and file_task != task:
        # --task overrides a file written for another task: the sections either task has its
        # own defaults for (model, loss, and optim/curriculum where one has them) do not carry
        # over; the new task's defaults apply.
        for name in set(TASK_SECTIONS.get(file_task, {"model": 0, "loss": 0})) | set(TASK_SECTIONS[task]):
            user.pop(name, None)
    user["task"] = task
    _check_keys(user, base)
    if isinstance(user.get("loss"), dict) and user["loss"].get("preset") is not None and "loss" in base:
        apply_loss_preset(base["loss"], user["loss"]["preset"])
    return check_types(merge(base, user))


def _parse_value(s: str) -> Any:
    return yaml.load(s, Loader=YamlLoader)


def apply_overrides(cfg: dict, overrides: Iterable[str]) -> dict:
    """Apply ``key.sub=value`` strings (values parsed as YAML) to a copy of ``cfg``.

    Raises:
        ConfigError: (a ``ValueError``) for a malformed item, an unknown key path (naming the
            override and the allowed keys) or a value of the wrong type (see :func:`check_types`).
    """
    cfg = copy.deepcopy(cfg)
    with _config_errors():
        _apply(cfg, overrides)
    return check_types(cfg)


def _apply(cfg: dict, overrides: Iterable[str]) -> None:
    for item in overrides or ():
        if "=" not in item:
            raise ValueError(f"override must be key.path=value, got {item!r}")
        key, val = item.split("=", 1)
        parts = key.strip().split(".")
        node = cfg
        for p in parts[:-1]:
            if not isinstance(node.get(p), dict):
                raise ValueError(f"unknown config section {p!r} in override {item!r}")
            node = node[p]
        check_keys(parts[-1:], node, ".".join(parts[:-1]), f"--set {item}")
        try:
            node[parts[-1]] = _parse_value(val)
        except yaml.YAMLError as e:
            why = getattr(e, "problem", None) or e
            raise ValueError(f"--set {item}: the value is not valid YAML ({why})") from None
        if parts == ["loss", "preset"] and node["preset"] is not None:
            apply_loss_preset(node, node["preset"])


def apply_loss_preset(loss: dict, name: str) -> dict:
    """Set ``loss["preset"]`` and the preset's term keys (``LOSS_PRESETS[name]``) in place and
    return ``loss``. Raises ``ValueError`` naming the known presets for another name."""
    if not isinstance(name, str) or name not in LOSS_PRESETS:
        raise ValueError(f"config field 'loss.preset' must be one of {list(LOSS_PRESETS)} or null, got {name!r}")
    loss.update(LOSS_PRESETS[name])
    loss["preset"] = name
    return loss


def reference_markdown() -> str:
    """The trainer's configuration reference (docs/trainer_config.md)."""
    from v2v_server.settings import reference_markdown as table

    parts = ["# v2v-train configuration", "",
             "Keys of a `v2v-train --config` YAML file; `--set section.key=value` overrides any of them. Generated by "
             "`python -m trainer.config --markdown > docs/trainer_config.md`.", "",
             table(RunSettings, (RunSettings,))]
    for name, cls in SECTIONS.items():
        parts.append(table(cls, (cls,), lambda f, n=name: f"`--set {n}.{f.name}=`"))
    seen = set()
    for task, secs in TASK_SECTIONS.items():
        for name, cls in secs.items():
            if cls not in seen:  # the reconstruction tasks share one loss section
                seen.add(cls)
                parts.append(table(cls, (cls,), lambda f, n=name: f"`--set {n}.{f.name}=`"))
    return "\n".join(parts)


if __name__ == "__main__":
    if sys.argv[1:] != ["--markdown"]:
        raise SystemExit("usage: python -m trainer.config --markdown")
    print(reference_markdown())
