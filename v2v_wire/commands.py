"""The one entry of every ``v2v-*`` console script, and what all the commands share about their
files: Ctrl-C and SIGTERM answered at any moment with one line, outputs written whole, and an
output that would overwrite an input refused before any work.

``pyproject.toml`` points each console script at a function of this module (``serve``,
``calibrate``...): it installs the SIGTERM and SIGINT handlers before anything else is imported,
then imports the command's module and runs its ``main``. An interrupt, during those imports too,
ends the command with one line on stderr (``v2v-calibrate: interrupted (Ctrl-C)``, then what the
command said of it: a command that has something to add, such as the checkpoint it saved, raises
the interrupt again with that text) and status 130 (SIGINT) or 143 (SIGTERM, 128 + 15, as a
shell reports a process killed by it), never a traceback: numba's dispatcher reports an interrupt
inside compiled code as a ``SystemError`` whose context holds the ``KeyboardInterrupt`` (once per
nested dispatcher: four deep in the simulation kernel), and :func:`interrupt_in` finds it at any
depth. A second signal while the command cleans up ends the process at once, with the same status
and no second line.

The interrupt is raised where Python code may stop, never inside llvmlite's bindings (numba's
compiler under them): they hand an LLVM object to another between two statements (a module given
to the JIT, then marked owned) and call back from LLVM into Python, and an exception there either
frees the module twice (the process dies of SIGSEGV once the traceback goes) or is swallowed by
ctypes (the signal lost, the command running on); nor inside numba's unpickling, which a compiled
function's return calls to get the Python type of each array it boxes: an exception there leaves
the array's type NULL, and the result comes back with a missing item or the process dies of
SIGSEGV unpacking it. A signal that comes there is sent again 10 ms later until it lands outside;
one swallowed anywhere else (a ``__del__``, a callback) is sent again rather than printed.

Standard library only: this module is imported before the command's own packages.
"""
from __future__ import annotations

import importlib
import os
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Callable, Iterable, Optional, Tuple, Union

#: When the command began (``time.perf_counter``; this module is imported first): ``v2v-train``'s
#: summary counts its start-up from it.
STARTED = time.perf_counter()

#: Console script -> ``module:function`` of its command (each ``main(argv=None) -> int``).
COMMANDS = {
    "v2v-serve": "v2v_server.cli:main",
    "v2v-loadtest": "v2v_client.loadtest:main",
    "v2v-demo": "v2v_client.demo:main",
    "v2v-keygen": "v2v_server.ops.keygen:main",
    "v2v-train": "trainer.train:main",
    "v2v-eval": "trainer.evaluate:main",
    "v2v-stats": "trainer.stats_report:main",
    "v2v-calibrate": "trainer.calibrate:main",
}


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread like Ctrl-C's ``KeyboardInterrupt`` (a subclass, so
    every ``except KeyboardInterrupt`` that stops a query or removes a temporary file handles
    it too)."""


#: Modules whose frames an interrupt is not raised in (module docstring): llvmlite's bindings, and
#: numba's unpickling (``numba.core.serialize._numba_unpickle``, called back from C while a
#: compiled function's arrays are boxed for its return).
UNSAFE_MODULES = ("llvmlite.binding", "numba.core.serialize")
#: Seconds after which a signal that came inside :data:`UNSAFE_MODULES` is sent again.
RETRY_S = 0.01
_UNSAFE_PACKAGES = tuple(m + "." for m in UNSAFE_MODULES)
_retry_pending = threading.Lock()


def _in_unsafe_code(frame) -> bool:
    """Whether ``frame`` or a frame below it (its callers) runs a module of :data:`UNSAFE_MODULES`
    or :func:`_on_unraisable` (an exception raised there is swallowed too)."""
    while frame is not None:
        name = frame.f_globals.get("__name__") or ""
        if name in UNSAFE_MODULES or name.startswith(_UNSAFE_PACKAGES):
            return True
        if frame.f_code is _on_unraisable.__code__:
            return True
        frame = frame.f_back
    return False


def _send_again(signum: int, delay: float = RETRY_S) -> None:
    """Send ``signum`` to this process again after ``delay`` seconds (one retry pending at once)."""
    if not _retry_pending.acquire(blocking=False):
        return

    def send():
        _retry_pending.release()
        os.kill(os.getpid(), signum)

    timer = threading.Timer(delay, send)
    timer.daemon = True
    try:
        timer.start()
    except RuntimeError:  # the interpreter is exiting: no thread starts, and none is needed
        _retry_pending.release()


def _on_interrupt(signum, frame) -> None:
    """SIGINT and SIGTERM: :class:`KeyboardInterrupt` or :class:`Terminated` raised in the main
    thread, or the signal sent again when it came inside :data:`UNSAFE_MODULES`."""
    if _in_unsafe_code(frame):
        _send_again(signum)
        return
    raise Terminated() if signum == signal.SIGTERM else KeyboardInterrupt()


def _on_unraisable(unraisable) -> None:
    """``sys.unraisablehook``: an interrupt that Python could not raise (it came inside a
    ``__del__``, a weakref or ctypes callback) is sent again, not printed; anything else is
    printed as Python prints it."""
    if isinstance(unraisable.exc_value, KeyboardInterrupt):
        _send_again(signal.SIGTERM if isinstance(unraisable.exc_value, Terminated) else signal.SIGINT)
        return
    sys.__unraisablehook__(unraisable)


def install_interrupt_handlers() -> None:
    """SIGTERM and SIGINT (where not ignored) answered by :func:`_on_interrupt`, and interrupts
    that Python swallows sent again (:func:`_on_unraisable`): the first act of every command."""
    signal.signal(signal.SIGTERM, _on_interrupt)
    if signal.getsignal(signal.SIGINT) is not signal.SIG_IGN:
        signal.signal(signal.SIGINT, _on_interrupt)
    sys.unraisablehook = _on_unraisable


def interrupt_in(exc: BaseException, depth: int = 32) -> Optional[KeyboardInterrupt]:
    """The ``KeyboardInterrupt`` (or :class:`Terminated`) that ``exc`` is or was raised while
    handling (its ``__cause__`` / ``__context__`` chain, up to ``depth`` links), or None."""
    seen = 0
    while exc is not None and seen < depth:
        if isinstance(exc, KeyboardInterrupt):
            return exc
        exc = exc.__cause__ or exc.__context__
        seen += 1
    return None


def interrupted_status(exc: BaseException) -> int:
    """The exit status of a command ended by ``exc``: 143 for SIGTERM, 130 for Ctrl-C."""
    return 143 if isinstance(interrupt_in(exc) or exc, Terminated) else 130


def run_command(prog: str, target: str) -> int:
    """Run the command ``target`` (``module:function``, called without arguments: it reads
    ``sys.argv``) as ``prog``: SIGTERM and SIGINT handled first (:func:`install_interrupt_handlers`),
    then its module imported and its function called. Returns its exit status; an interrupt at
    any moment is one line and 130 or 143 (module docstring)."""
    install_interrupt_handlers()
    try:
        module, _, name = target.partition(":")
        return getattr(importlib.import_module(module), name)()
    except BaseException as e:  # noqa: BLE001 - an interrupt, however wrapped, is one line
        return _interrupted(prog, e)


def main_of_module(prog: str, main: Callable[[], int]) -> int:
    """``python -m`` of a command's module: ``main()`` with the interrupt handling of
    :func:`run_command` (the module's imports are done by then)."""
    install_interrupt_handlers()
    try:
        return main()
    except BaseException as e:  # noqa: BLE001
        return _interrupted(prog, e)


def _interrupted(prog: str, e: BaseException) -> int:
    """The one line and the status of a command that ``e`` ended, when ``e`` is (or wraps) an
    interrupt; ``e`` raised again otherwise."""
    interrupt = interrupt_in(e)
    if interrupt is None:
        raise e
    status = interrupted_status(interrupt)
    _end_on_next_signal(status)
    try:
        sys.stdout.flush()
    except (OSError, ValueError):
        pass
    detail = str(interrupt)
    print(f"{prog}: {'stopped (SIGTERM)' if status == 143 else 'interrupted (Ctrl-C)'}{'; ' + detail if detail else ''}",
          file=sys.stderr, flush=True)
    return status


def _end_on_next_signal(status: int) -> None:
    """A second Ctrl-C or SIGTERM while the interrupted command cleans up (threads joined,
    files closed at exit) ends the process at once with ``status``."""
    def now(signum, frame):
        os._exit(status)

    for sig in (signal.SIGINT, signal.SIGTERM):
        if signal.getsignal(sig) is not signal.SIG_IGN:
            signal.signal(sig, now)


def _entry(prog: str) -> Callable[[], int]:
    def entry() -> int:
        return run_command(prog, COMMANDS[prog])
    entry.__name__ = prog.replace("v2v-", "").replace("-", "_")
    entry.__doc__ = f"The ``{prog}`` console script (:func:`run_command` of ``{COMMANDS[prog]}``)."
    return entry


serve = _entry("v2v-serve")
loadtest = _entry("v2v-loadtest")
demo = _entry("v2v-demo")
keygen = _entry("v2v-keygen")
train = _entry("v2v-train")
evaluate = _entry("v2v-eval")
stats = _entry("v2v-stats")
calibrate = _entry("v2v-calibrate")


# -- files -----------------------------------------------------------------------------------

def write_whole(path: Union[str, Path], data: Union[str, bytes]) -> None:
    """Write ``data`` (text as UTF-8, or bytes) to ``path`` whole or not at all: into a
    temporary file beside it, then renamed over it (``os.replace``, atomic on one file system),
    so an interrupt or a full disk leaves the old file or none, never part of the new one.

    Raises:
        OSError: the folder cannot be written (the temporary file is removed).
    """
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as f:
            f.write(data.encode() if isinstance(data, str) else data)
        os.replace(tmp, path)
    except BaseException:
        try:
            tmp.unlink()
        except OSError:
            pass
        raise


def writable_problem(out: Path, folder: bool = False) -> str:
    """Why the output ``out`` (a file, or with ``folder`` a folder, made when missing) cannot be
    written, or "": checked before any work, by making and removing a file where the output
    goes (an existing read-only file is refused too: it is not replaced)."""
    where = out if folder else out.parent
    if folder and out.exists() and not out.is_dir():
        return "exists and is not a folder"
    if not folder and out.is_dir():
        return "is a folder"
    if not folder and out.exists() and not os.access(out, os.W_OK):
        return "is read-only"
    try:
        where.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        return f"{'' if folder else 'its folder '}cannot be made ({e.strerror or e})"
    probe = where / f".v2v-write-check.{os.getpid()}"
    try:
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        return f"cannot be written ({where}: {e.strerror or e})"
    return ""


def json_output_problem(out: Path) -> str:
    """Why the JSON results file ``out`` cannot be written, or "": :func:`writable_problem`, and an
    existing file not named ``.json`` is refused (a source or an input named by mistake is never
    replaced by results)."""
    if out.is_file() and out.suffix != ".json":
        return "exists and is not a .json file: results never replace it"
    return writable_problem(out)


def same_path(a: Union[str, Path], b: Union[str, Path]) -> bool:
    """Whether ``a`` and ``b`` name the same file or folder (links and ``..`` resolved; a path
    that does not exist compares by its resolved name)."""
    try:
        return os.path.samefile(a, b)
    except OSError:
        return Path(a).resolve() == Path(b).resolve()


def input_overwritten(out: Union[str, Path], inputs: Iterable[Tuple[str, Optional[Union[str, Path]]]],
                      inside: Iterable[Tuple[str, Optional[Union[str, Path]], Optional[Tuple[str, ...]]]] = ()) -> str:
    """Why writing the output file or folder ``out`` would overwrite what the command reads, or
    "": ``"is the recording (--recording)"`` when ``out`` is one of ``inputs`` (``(what, path)``,
    a file or folder read; None: not given), or lies inside one of the folders of ``inside``
    (``(what, folder, suffixes)``: a corpus folder and its video suffixes, a recording folder
    and None for any file). A command never writes over its input: checked before any work."""
    for what, path in inputs:
        if path and same_path(out, path):
            return f"is {what}: a command never writes over what it reads"
    target = Path(out).resolve()
    for what, folder, suffixes in inside:
        if folder and Path(folder).is_dir() and Path(folder).resolve() in target.parents and \
                (suffixes is None or target.suffix.lower() in suffixes):
            return f"is {what}: a command never writes over what it reads"
    return ""
