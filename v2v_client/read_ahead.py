"""Reading ahead of the training loop: the fetch, the unpacking of rows into tensors and the
pinning for a non-blocking copy happen in a thread while the step runs (docs/trainer_feed.md
measures what it saves). Batches keep their order; a checkpoint is the position of the last
batch the loop took."""
from __future__ import annotations

import queue
import threading
import time
from typing import Iterator, Optional

import torch

from .fetch import stopped_by

__all__ = ["ReadAhead", "READ_AHEAD", "CLOSE_WAIT_S"]


#: Batches a :class:`ReadAhead` holds ready beyond the one the loop holds (``bench/trainer_feed.py``
#: measures the read path with it: docs/trainer_feed.md).
READ_AHEAD = 3
#: Seconds :meth:`ReadAhead.close` waits for its thread: the thread's waits on the servers end
#: within :data:`~v2v_client.fetch.POLL_S` of the stop (half a second in a fleet's loop), its
#: sockets closed as it unwinds, whether the servers answer or not (all of them stopped); past it
#: the thread (a daemon) is left to end by itself, so Ctrl-C ends the command within 2 s.
CLOSE_WAIT_S = 1.0


class ReadAhead:
    """A plan's epochs read ahead of the loop (``v2v-train``'s and ``v2v-loadtest``'s read path):
    a thread reads the next batches of ``stream`` (a :class:`~v2v_client.PlanEpochs`, or any
    iterable of batches with ``state_dict``) while the step runs: the fetches, their rows
    unpacked into tensors by ``V2VStreamDataset`` and, with ``pin``, their tensors pinned for a
    non-blocking host-to-device copy. It holds up to ``depth`` batches ready, so the loop takes
    a batch made ready during the last step and waits only for what the server has not made.

    Iterating yields the stream's batches in its order, each once. :meth:`state_dict` is the
    position of the last batch the loop took (its ``position``: ``V2VStreamDataset``'s checkpoint,
    which resumes at any layout), not of what the thread has read ahead; before any, the
    stream's own state when reading began. Reading starts at :meth:`start` or the first
    ``iter()`` and stops at :meth:`close`; one pass per object.

    ``first_batch_s``: seconds from the start of reading to the first batch ready (None before).

    Raises (from ``next``): what the stream raised (``TimeoutError``, ``PlanServerError``,
    ``PlanMismatch``, ...), the same exception object, its traceback through the reader thread.
    """

    def __init__(self, stream, pin: bool = False, depth: int = READ_AHEAD):
        if not isinstance(depth, int) or isinstance(depth, bool) or depth < 1:
            raise ValueError(f"depth must be an int >= 1, got {depth!r}")
        self.stream, self.pin, self.depth = stream, bool(pin), depth
        self._queue: "queue.Queue" = queue.Queue(maxsize=depth)
        self._stop = threading.Event()
        self._thread: Optional[threading.Thread] = None
        self._iterated = False
        self._taken: Optional[dict] = None  # the position after the last batch the loop took
        self._start_state: Optional[dict] = None
        self._t0 = 0.0
        self.first_batch_s: Optional[float] = None

    def state_dict(self) -> dict:
        """The checkpoint: the ``position`` of the last batch taken, else the stream's state."""
        if self._taken is not None:
            return dict(self._taken)
        return self._start_state if self._start_state is not None else self.stream.state_dict()

    def load_state_dict(self, state: dict) -> None:
        """The stream's ``load_state_dict``; before iterating only.

        Raises:
            RuntimeError: reading has begun."""
        if self._thread is not None:
            raise RuntimeError("ReadAhead.load_state_dict after reading began: load the state before iterating")
        self.stream.load_state_dict(state)

    def start(self) -> "ReadAhead":
        """Begin reading (the first ``iter()`` does it too): a run starts its first fetches before
        it builds its model. Raises what the stream's ``state_dict`` raises (``TimeoutError``)."""
        if self._thread is None:
            self._start_state = self.stream.state_dict()
            self._t0 = time.perf_counter()
            self._thread = threading.Thread(target=self._read, name="v2v-read-ahead", daemon=True)
            self._thread.start()
        return self

    def __iter__(self) -> Iterator[dict]:
        if self._iterated:
            raise RuntimeError("a ReadAhead is read once: make another for another pass")
        self._iterated = True
        self.start()
        return self._batches()

    def _batches(self) -> Iterator[dict]:
        while True:
            kind, value = self._queue.get()
            if kind == "batch":
                self._taken = value.get("position", self._taken)
                yield value
            elif kind == "end":
                return
            else:
                raise value

    def _put(self, item: tuple) -> bool:
        """Hand ``item`` to the loop, waiting while ``depth`` are ready; False once closed."""
        while not self._stop.is_set():
            try:
                self._queue.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def _read(self) -> None:
        it = iter(self.stream)
        try:
            with stopped_by(self._stop):  # close() ends the fetch in hand too (fetch.ReadStopped)
                for batch in it:
                    if self.pin:
                        batch = {k: v.pin_memory() if isinstance(v, torch.Tensor) else v for k, v in batch.items()}
                    if self.first_batch_s is None:
                        self.first_batch_s = time.perf_counter() - self._t0
                    if not self._put(("batch", batch)):
                        return
            self._put(("end", None))
        except BaseException as e:  # raised in the loop's thread, the same object (type and traceback kept)
            self._put(("error", e))
        finally:
            close = getattr(it, "close", None)
            if close is not None:
                close()

    def close(self, timeout_s: float = CLOSE_WAIT_S) -> None:
        """Stop reading: the thread's fetch in hand ends (``fetch.stopped_by``) and its connections
        close; waits up to ``timeout_s`` for it (:data:`CLOSE_WAIT_S`)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
