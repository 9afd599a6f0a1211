"""How the harness's multi-process torch jobs leave once their records are written.

A DDP job on gloo (torch 2.13) can abort at interpreter exit, after its work is done: SIGABRT,
"terminate called without an active exception". The cause is in torch. The DDP gradient
all-reduce is queued inside ``backward()`` and captures the thread-local state, which then holds
the context ``backward()`` stashed (``torch.autograd.graph._engine_run_backward``). A later
barrier holds that work, and gloo's worker thread may drop the barrier after the main thread has
gone on (``ProcessGroupGloo::runLoop`` -> ``~AsyncWork`` -> ``~ThreadLocalState`` ->
``gil_scoped_acquire``). DDP keeps the process group, and so its worker threads, alive past
``destroy_process_group()``. If the drop comes during interpreter finalization, taking the GIL
ends the thread by forced unwinding through a ``noexcept`` destructor: ``std::terminate``.

A job leaves by :func:`leave`: what it wrote is flushed, and the process ends with its status
without finalizing the interpreter, so its exit status says whether the job itself failed. Our
own threads need no finalization: a stream's I/O thread has ended when its stream did.
"""
from __future__ import annotations

import os
import sys


def leave(status: int = 0) -> None:
    """Flush stdout and stderr and end this process with ``status`` (``os._exit``: no interpreter
    finalization, no atexit handlers). Call it last, after the job's records are written and
    closed and its process group destroyed."""
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(status)
