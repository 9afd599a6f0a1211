"""Ctrl-C and SIGTERM at any moment, for every console script of ``pyproject.toml``: each is run as
its installed script runs it (``from v2v_wire.commands import X; sys.exit(X())``), and the signal
is sent during start-up (the moment the SIGTERM handler is installed, before the command's module
is imported: numpy, torch, numba still loading) and while it works (a fit in numba's kernel, a
stream waited for, a corpus decoded). Each answers with one line naming the command and exit
status 130 (SIGINT) or 143 (SIGTERM), no traceback (numba's ``SystemError`` around an interrupt
included), and leaves no partial file: an output is whole or absent, and no temporary file stays."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import pytest

from harness.data import DAVIS346, RECORDINGS, SAMPLE_VIDEOS
from harness.serve import free_port

ROOT = Path(__file__).resolve().parents[1]


def _scripts() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]


def test_every_console_script_starts_in_the_one_entry():
    """A script that skipped ``v2v_wire.commands`` would answer an interrupt during its imports
    with a traceback (SIGINT) or die without a word (SIGTERM)."""
    from v2v_wire import commands

    scripts = _scripts()
    assert set(scripts) == set(commands.COMMANDS) == set(COMMANDS), scripts
    for name, target in scripts.items():
        module, _, fn = target.partition(":")
        assert module == "v2v_wire.commands" and callable(getattr(commands, fn)), (name, target)


def test_an_interrupt_wrapped_by_numba_is_found_at_any_depth():
    from v2v_wire.commands import Terminated, interrupt_in, interrupted_status

    def wrapped(inner: BaseException, depth: int) -> BaseException:
        e = inner
        for _ in range(depth):  # as numba's nested dispatchers report it: SystemError during handling
            try:
                try:
                    raise e
                except BaseException:
                    raise SystemError("CPUDispatcher(<function _kernel>) returned a result with an exception set")
            except SystemError as s:
                e = s
        return e

    for depth in (0, 1, 4):
        assert isinstance(interrupt_in(wrapped(KeyboardInterrupt(), depth)), KeyboardInterrupt)
        assert interrupted_status(wrapped(Terminated(), depth)) == 143
        assert interrupted_status(wrapped(KeyboardInterrupt(), depth)) == 130
    assert interrupt_in(wrapped(ValueError("no"), 4)) is None


def _handler_installed(pid: int) -> bool:
    """Whether the process has a handler for SIGTERM (``/proc/PID/status`` SigCgt): the entry's
    first act, before any of the command's imports."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("SigCgt:"):
                return bool(int(line.split()[1], 16) & (1 << (signal.SIGTERM - 1)))
    except OSError:
        pass
    return False


def _children(pid: int) -> list:
    """The process ids of ``pid``'s children (``/proc/PID/task/PID/children``)."""
    try:
        return Path(f"/proc/{pid}/task/{pid}/children").read_text().split()
    except OSError:
        return []


def _tiny_checkpoint(folder: Path) -> str:
    import torch

    from trainer.config import default_config, merge
    from trainer.core import Trainer

    cfg = merge(default_config("e2vid"), {"model": {"num_bins": 5, "base_num_channels": 4}})
    return str(Trainer(cfg, str(folder), torch.device("cpu")).save_checkpoint())


#: v2v-eval's signal waits for its first line of work and three recordings follow it: one recording
#: took 2.7 s on 2 idle cores, and on a faster machine it ended before a signal sent 4 s after start-up
PROPHESEE = (RECORDINGS / "prophesee_gen3_evt2.raw", RECORDINGS / "prophesee_evk4_evt3.raw")

#: script -> (its arguments, with {tmp} and {port}; what on its output says it is working, or
#: the seconds after start-up to wait instead)
COMMANDS = {
    "v2v-serve": (["--videos", str(SAMPLE_VIDEOS), "--workers", "1", "--bind", "tcp://127.0.0.1:{port}",
                   "--cache-dir", "{tmp}/cache", "--sequence-length", "8", "--crop-size", "64"], " serving "),
    "v2v-loadtest": (["--connect", "tcp://127.0.0.1:{port}", "--timeout", "60"], 3.0),
    "v2v-demo": (["--workers", "1", "--preview", "{tmp}/preview.png"], "server running"),
    "v2v-keygen": (["trainer-01", "--out", "{tmp}/keys"], None),
    "v2v-train": (["--task", "e2vid", "--connect", "tcp://127.0.0.1:{port}", "--out", "{tmp}/run", "--device", "cpu"],
                  "task e2vid"),
    "v2v-eval": (["--checkpoint", "{checkpoint}", "--recording", str(DAVIS346), *map(str, PROPHESEE), "--device",
                  "cpu", "--out", "{tmp}/eval", "--write-video", "{tmp}/video"], "trainer.evaluate"),
    "v2v-stats": (["--videos", str(SAMPLE_VIDEOS), "--samples", "40", "--out", "{tmp}/report"], "sampling"),
    "v2v-calibrate": (["--recording", str(DAVIS346), "--evaluations", "80", "--out", "{tmp}/fitted.yaml"],
                      "simulation"),
}
#: --check prints nothing until its verdicts: its signal comes once its pool's processes run
#: (a time after start-up came after its end in a loaded suite, and before its pool on a fast machine)
CHECK = (["--check", "--videos", str(SAMPLE_VIDEOS), "--workers", "2", "--cache-dir", "{tmp}/cache"], "pool")

CASES = [(name, "start-up", signal.SIGTERM) for name in COMMANDS] + \
        [(name, "start-up", signal.SIGINT) for name in ("v2v-calibrate", "v2v-stats")] + \
        [(name, "working", signal.SIGINT) for name, (_, when) in COMMANDS.items() if when is not None] + \
        [(name, "working", signal.SIGTERM) for name in ("v2v-serve", "v2v-calibrate", "v2v-train", "v2v-demo")] + \
        [("v2v-serve --check", "working", signal.SIGINT), ("v2v-serve --check", "working", signal.SIGTERM)]


def _run(name: str, args: list, when, sig: int, tmp: Path, moment: str) -> subprocess.CompletedProcess:
    script = name.split()[0]
    fn = _scripts()[script].partition(":")[2]
    code = f"import sys\nfrom v2v_wire.commands import {fn}\nsys.exit({fn}())"
    out_f, err_f = open(tmp / "stdout", "w+"), open(tmp / "stderr", "w+")
    proc = subprocess.Popen([sys.executable, "-c", code, *args], stdout=out_f, stderr=err_f, cwd=tmp,
                            env={**os.environ, "PYTHONUNBUFFERED": "1", "PYTHONFAULTHANDLER": "1"})  # a crash's stack
    try:
        deadline = time.monotonic() + 240
        while not _handler_installed(proc.pid):
            assert proc.poll() is None and time.monotonic() < deadline, "never installed its SIGTERM handler"
            time.sleep(0.002)
        if moment == "working":
            start = time.monotonic()
            while True:
                assert time.monotonic() < deadline, (name, "never started working", (tmp / "stderr").read_text())
                if proc.poll() is not None:
                    break
                if isinstance(when, float):
                    if time.monotonic() - start >= when:
                        break
                elif when == "pool":
                    if len(_children(proc.pid)) >= 2:  # its processes started: past the moment it
                        time.sleep(0.5)  # ignores Ctrl-C to start them, inside their imports or decoding
                        break
                elif when in (tmp / "stderr").read_text() + (tmp / "stdout").read_text():
                    time.sleep(0.5)
                    break
                time.sleep(0.05)
        assert proc.poll() is None, (name, moment, "ended before the signal", (tmp / "stderr").read_text())
        proc.send_signal(sig)
        proc.wait(120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    out_f.seek(0)
    err_f.seek(0)
    r = subprocess.CompletedProcess(proc.args, proc.returncode, out_f.read(), err_f.read())
    out_f.close()
    err_f.close()
    return r


def _whole(path: Path) -> bool:
    """Whether a file a command wrote is complete for its kind."""
    data = path.read_bytes()
    if path.suffix == ".json":
        json.loads(data)
        return True
    if path.suffix == ".png":
        return data.endswith(b"IEND\xaeB`\x82")
    if path.suffix == ".html":
        return data.rstrip().endswith(b"</html>")
    if path.suffix == ".yaml":
        import yaml

        return isinstance(yaml.safe_load(data), dict)
    if path.suffix == ".mp4":
        import av

        with av.open(str(path)) as c:
            return sum(1 for _ in c.decode(video=0)) > 0
    return True


@pytest.mark.parametrize("name, moment, sig", CASES,
                         ids=[f"{n.replace(' ', '')}-{m}-{signal.Signals(s).name}" for n, m, s in CASES])
def test_an_interrupt_at_any_moment_is_one_line_and_leaves_no_partial_file(tmp_path, name, moment, sig):
    args, when = CHECK if name == "v2v-serve --check" else COMMANDS[name]
    fill = {"tmp": str(tmp_path), "port": str(free_port())}
    if "{checkpoint}" in args:
        fill["checkpoint"] = _tiny_checkpoint(tmp_path / "ck")
    args = [a.format(**fill) for a in args]
    r = _run(name, args, when, sig, tmp_path, moment)
    script = name.split()[0]
    status = 128 + sig
    assert r.returncode == status, f"exit {r.returncode}, its stderr (a crash: faulthandler's stacks):\n{r.stderr[-8000:]}"
    assert "Traceback" not in r.stderr and "Exception ignored" not in r.stderr, r.stderr[-3000:]
    lines = [ln for ln in r.stderr.replace("\r", "\n").splitlines() if ln.strip()]
    if script == "v2v-serve" and moment == "working" and name == "v2v-serve":  # the server's own stop, logged
        assert sum(f"{signal.Signals(sig).name}: shutting down" in ln for ln in lines) == 1, lines[-5:]
    else:
        said = f"{script}: {'stopped (SIGTERM)' if sig == signal.SIGTERM else 'interrupted (Ctrl-C)'}"
        assert lines and lines[-1].startswith(said), lines[-5:]
        assert sum(ln.startswith(f"{script}: ") and ("interrupted" in ln or "stopped" in ln) for ln in lines) == 1
    leftovers = [p for p in tmp_path.rglob("*") if p.is_file() and (p.name.endswith((".tmp", ".part")) or
                                                                    ".v2v-write-check" in p.name)]
    assert not leftovers, leftovers
    for p in tmp_path.rglob("*"):
        if p.is_file() and (p.parent.name in ("report", "eval", "video", "run", "keys") or
                            p.name in ("fitted.yaml", "preview.png")):
            assert _whole(p), p
    keys = tmp_path / "keys"
    if keys.exists():  # both halves of the key pair, or neither
        assert len([p for p in keys.iterdir() if not p.name.startswith(".")]) in (0, 2), list(keys.iterdir())


#: Commands whose interrupt comes where Python cannot raise it at once: inside llvmlite's bindings
#: (LLVM calls back into Python as numba's JIT caches its object code: an exception there is
#: swallowed by ctypes, and between two statements there an exception frees a module the JIT owns),
#: inside another ctypes callback, and inside a ``__del__`` (an exception there is printed and
#: dropped). Each then works on for 60 s.
SWALLOWING = {
    "llvm-callback": '''
def main():
    import llvmlite.binding as llvm

    llvm.initialize_native_target()
    llvm.initialize_native_asmprinter()
    machine = llvm.Target.from_default_triple().create_target_machine()
    engine = llvm.create_mcjit_compiler(llvm.parse_assembly("define i32 @f() {\\n  ret i32 1\\n}"), machine)
    engine.set_object_cache(lambda module, buf: signal.raise_signal(SIG))  # its handler runs in the callback
    engine.finalize_object()
    time.sleep(60)
    return 0
''',
    "ctypes-callback": '''
import ctypes


def main():
    ctypes.CFUNCTYPE(None)(lambda: signal.raise_signal(SIG))()  # its handler runs in the callback
    time.sleep(60)
    return 0
''',
    "finaliser": '''
class Finalised:
    def __del__(self):
        signal.raise_signal(SIG)  # its handler runs in __del__


def main():
    Finalised()
    time.sleep(60)
    return 0
''',
}


@pytest.mark.parametrize("sig", (signal.SIGTERM, signal.SIGINT), ids=lambda s: signal.Signals(s).name)
@pytest.mark.parametrize("where", SWALLOWING)
def test_an_interrupt_where_python_cannot_raise_it_is_raised_after(tmp_path, where, sig):
    """The signal is neither lost (the command running on to its end) nor raised where it would
    be swallowed or break a native object: it ends the command, with its one line, as soon as
    Python code outside those places runs."""
    (tmp_path / "swallowing.py").write_text(f"import signal\nimport time\n\nSIG = {int(sig)}\n" + SWALLOWING[where])
    code = "import sys\nfrom v2v_wire.commands import run_command\nsys.exit(run_command('v2v-x', 'swallowing:main'))"
    r = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=120,
                       env={**os.environ, "PYTHONFAULTHANDLER": "1"})
    said = "v2v-x: stopped (SIGTERM)" if sig == signal.SIGTERM else "v2v-x: interrupted (Ctrl-C)"
    assert (r.returncode, r.stderr.strip()) == (128 + sig, said), (r.returncode, r.stderr[-3000:])


BOXING = '''
import signal
import sys
import time

import numpy as np

from v2v_server.simulation.kernel import run_kernel
from v2v_server.simulation.simulate import log_intensity_lut


def main():
    frames = np.random.default_rng(0).integers(0, 256, (3, 8, 8)).astype(np.uint8)
    run = lambda: run_kernel(frames, np.zeros((8, 8), np.float32), 0.2, 0.2, lut=log_intensity_lut(255), narrow=True)
    run()  # compiled (or loaded from the cache) before the signal

    def at_unpickle(frame, event, arg):
        if event == "call" and frame.f_code.co_name == "_numba_unpickle":
            sys.setprofile(None)
            signal.raise_signal(SIG)  # its handler runs in the callback, as the kernel's arrays are boxed

    sys.setprofile(at_unpickle)
    result = run()
    sys.setprofile(None)
    print("whole" if all(x is not None for x in result[:2]) and result.net.shape == (2, 8, 8) else "broken", flush=True)
    time.sleep(60)
    return 0
'''


@pytest.mark.parametrize("sig", (signal.SIGTERM, signal.SIGINT), ids=lambda s: signal.Signals(s).name)
def test_an_interrupt_while_the_kernels_arrays_are_boxed_is_raised_after_it_returns(tmp_path, sig):
    """numba boxes each array a compiled function returns with its Python type, unpickled by a
    Python function called back from C: an interrupt raised there left that array NULL, and the
    kernel's result came back with a missing item (v2v-calibrate died of SIGSEGV unpacking it) or
    wrapped in a SystemError. The result comes back whole, and the interrupt ends the command
    right after, with its one line."""
    (tmp_path / "boxing.py").write_text(f"SIG = {int(sig)}\n" + BOXING)
    code = "import sys\nfrom v2v_wire.commands import run_command\nsys.exit(run_command('v2v-x', 'boxing:main'))"
    r = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=120,
                       env={**os.environ, "PYTHONFAULTHANDLER": "1", "PYTHONPATH": str(ROOT)})
    said = "v2v-x: stopped (SIGTERM)" if sig == signal.SIGTERM else "v2v-x: interrupted (Ctrl-C)"
    assert (r.returncode, r.stderr.strip(), r.stdout.strip()) == (128 + sig, said, "whole"), \
        (r.returncode, r.stdout, r.stderr[-3000:])
