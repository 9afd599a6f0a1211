"""Every bundled trainer configuration (trainer/configs/*.yaml) resolves through the public loader
(jsonargparse checks the types) to these values: each one is written in the file or is its task's
declared default (trainer/config.py), floats stored as floats."""
import pytest

from trainer.config import load_config

#: what every bundled configuration shares: the run's shell, the stream and the log cadence
SHELL = {'connect': 'tcp://127.0.0.1:5555',
         'device': 'auto',
         'max_steps': 200000,
         'seed': 0,
         'amp': 'fp32',
         'compile': False,
         'speed': 'eager',
         'require_lpips': False,
         'resume': None,
         'stream': {'timeout_s': 60.0,
                    'raw': True,
                    'curve_keys': None},
         'log': {'image_every': 500, 'checkpoint_every': 1000, 'progress': True, 'every': 10, 'tensorboard': True}}
ADAM = {'optimizer': 'adam',
        'lr': 0.0001,
        'amsgrad': True,
        'weight_decay': 0.0,
        'lr_gamma': 1.0,
        'lr_gamma_every': 1000,
        'clip_grad_norm': None}
#: the loss of the reconstruction tasks (e2vid, etnet, hypere2vid)
RECONSTRUCTION_LOSS = {'preset': 'v+l1+h',
                       'l1_weight': 1.0,
                       'perceptual_weight': 1.0,
                       'lpips_net': 'vgg',
                       'lpips_weights': None,
                       'use_lpips_package': True,
                       'tc_weight': 1.0,
                       'tc_alpha': 50.0,
                       'tc_start_fraction': 0.5,
                       'flow_source': 'stream',
                       'raft_num_flow_updates': 12,
                       'raft_weights': None}
#: the loss of the optical flow tasks (eraft, evflow)
FLOW_LOSS = {'flow_l1_weight': 1.0, 'flow_source': 'stream', 'raft_num_flow_updates': 12, 'raft_weights': None}


def _resolved(task: str, optim: dict, model: dict, loss: dict, **more) -> dict:
    return {'task': task, 'out': f'runs/{task}', **SHELL, 'optim': optim, 'model': model, 'loss': loss, **more}


RESOLVED = {
    'trainer/configs/e2vid.yaml': _resolved(
        'e2vid', ADAM,
        {'num_bins': 5,
         'base_num_channels': 32,
         'num_encoders': 3,
         'num_residual_blocks': 2,
         'num_output_channels': 1,
         'skip_type': 'sum',
         'kernel_size': 5},
        RECONSTRUCTION_LOSS),
    'trainer/configs/eraft.yaml': _resolved(
        'eraft', ADAM,
        {'num_bins': 5, 'subtype': 'warm_start', 'iters': 12, 'corr_levels': 4, 'corr_radius': 4},
        FLOW_LOSS),
    'trainer/configs/etnet.yaml': _resolved(
        'etnet', {**ADAM, 'optimizer': 'adamw', 'lr': 0.0002, 'weight_decay': 0.01, 'lr_gamma': 0.94},
        {'num_bins': 5,
         'd_model': 256,
         'nhead': 8,
         'encoder_layers': 3,
         'decoder_layers': 2,
         'dim_feedforward': 1024,
         'dropout': 0.1},
        RECONSTRUCTION_LOSS),
    'trainer/configs/evflow.yaml': _resolved(
        'evflow', ADAM,
        {'num_bins': 5,
         'base_num_channels': 32,
         'num_encoders': 4,
         'num_residual_blocks': 2,
         'num_output_channels': 2,
         'skip_type': 'concat',
         'kernel_size': 3},
        FLOW_LOSS),
    'trainer/configs/hypere2vid.yaml': _resolved(
        'hypere2vid', {**ADAM, 'lr': 0.001},
        {'num_bins': 5,
         'base_num_channels': 32,
         'num_encoders': 3,
         'num_residual_blocks': 2,
         'kernel_size': 5},
        RECONSTRUCTION_LOSS,
        curriculum={'fraction': 0.2, 'stages': 16}),
}


@pytest.mark.parametrize("path", sorted(RESOLVED))
def test_bundled_config_resolves_to_its_values(path):
    cfg = load_config(path)
    assert cfg == RESOLVED[path]
    floats = [(s, k) for s, sec in RESOLVED[path].items() if isinstance(sec, dict) for k, v in sec.items()
              if isinstance(v, float)]
    assert all(isinstance(cfg[s][k], float) for s, k in floats)  # 1 == 1.0 would hide an int


def test_the_bundled_configs_are_all_pinned():
    from pathlib import Path

    assert sorted(RESOLVED) == sorted(str(p) for p in Path("trainer/configs").glob("*.yaml"))


@pytest.mark.parametrize("item,message", [
    ("optim.amsgrad=1", "config field 'optim.amsgrad' must be a bool, got 1"),
    ("log.checkpoint_every=2.5", "config field 'log.checkpoint_every' must be an int, got 2.5"),
    ("model.skip_type=mul", "config field 'model.skip_type' must be one of ['sum', 'concat'], got 'mul'"),
    ("max_steps=null", "config field 'max_steps' may not be null"),
    ("optim.lr=.nan", "config field 'optim.lr' must be a finite number, got nan"),
    ("optim.lr='5'", "config field 'optim.lr' must be a float, got the string '5'"),
    ("log.progress=on_", "config field 'log.progress' must be a bool, got the string 'on_'"),
    ("optim=3", "config field 'optim' must be a mapping, got 3"),
    ("stream.curve_keys=a.key", "config field 'stream.curve_keys' must be a list or null, got the string 'a.key'"),
    ("loss.preset='null'", "config field 'loss.preset' must be one of ['v+l1+h', 'alex+tc', 'alex', 'alex+th'] or null, "
                           "got 'null'"),
    ("loss.preset=[1]", "config field 'loss.preset' must be one of"),
])
def test_bad_values_are_named_with_their_field(item, message):
    from trainer.config import ConfigError, apply_overrides

    cfg = load_config("trainer/configs/e2vid.yaml")
    with pytest.raises(ConfigError) as e:
        apply_overrides(cfg, [item])
    assert message in str(e.value)


def test_values_keep_their_meaning(tmp_path):
    from trainer.config import apply_overrides

    cfg = apply_overrides(load_config("trainer/configs/e2vid.yaml"),
                          ["optim.clip_grad_norm=1", "loss.flow_source=raft_small", "resume=null", "stream.curve_keys=[a, b]"])
    assert cfg["optim"]["clip_grad_norm"] == 1.0 and isinstance(cfg["optim"]["clip_grad_norm"], float)
    assert cfg["loss"]["flow_source"] == "raft-small" and cfg["resume"] is None
    assert cfg["stream"]["curve_keys"] == ["a", "b"]
    p = tmp_path / "run.yaml"
    p.write_text("task: evflow\nresume: 'null'\noptim: {lr: 1}\n")
    got = load_config(str(p))
    assert got["resume"] == "null" and got["optim"]["lr"] == 1.0 and isinstance(got["optim"]["lr"], float)
