"""A fleet's makes waiting on one host, pure: a reader of a fleet (``v2v_client.fleet_read``)
computes the plan itself and asks each video's samples, by ordinal, of the host it routes the
video to (``v2v_wire.plan_messages.Make``), or the video's windows only, which its plan unfolds
with. The host's scheduler (``plan_schedule.PlanScheduler``) decodes the videos makes wait on
after those its fetches wait on, in the order of (epoch, the make's position: the latest by which
its decode should start, ``v2v_wire.fleet.Router.start_by``), then of arrival; it keeps the
samples of the videos makes wait on, and for :data:`TOLD_S` after a make of a video was answered
the video's other samples (a decode makes all of them, and the reader asks each as its plan
reaches its position: the plan's shuffle buffer spreads a video's samples over about twice
its size in positions, past what a host's store keeps unnamed). ``tests/test_plan_schedule.py``."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Dict, Hashable, List, Mapping, Optional, Sequence, Set, Tuple

from v2v_wire.ids import SampleKey

__all__ = ["Order", "Orders", "TOLD_S"]

#: Seconds the samples of a video a make was answered for are kept unfetched: the reader asks for
#: them as its plan reaches them.
TOLD_S = 120.0


@dataclass
class Order:
    """A client's make: the samples ``ordinals`` (``SampleKey.ordinal``) of ``video`` in
    ``epoch``, or (``ordinals`` None) the video's windows only, answered once its slots are known;
    ``position``: the first position of the epoch that needs it (makes are decoded in that order)."""

    client: Hashable
    request: int
    epoch: int
    video: str
    ordinals: Optional[Tuple[int, ...]]
    position: int = 0


class Orders:
    """The makes a host holds (module docstring).

    Args:
        crops_per_window: the manifest's K (an ordinal is ``window * K + crop``).
    """

    def __init__(self, crops_per_window: int):
        self.kpw = crops_per_window
        self.waiting: List[Order] = []
        self.told: Dict[Tuple[int, str], float] = {}  # (epoch, video) -> when a make of it was last answered
        self.placed: Dict[Tuple[int, str], Tuple[str, float]] = {}  # (epoch, video) -> (host, when) (place)

    def add(self, order: Order, samples: Mapping[str, Optional[int]]) -> int:
        """Queue ``order``; ``samples``: each video's samples per epoch (None: not known yet).
        A make of the same client waiting here for samples all of which ``order`` names (of the
        same epoch and video) is replaced: a reader asks a make again after ``retry_s`` (its
        reply lost, or its make queued that long) and awaits only the new one, so answering both
        would send its rows twice and count its queue twice (``queued``, which readers route
        on). Returns the samples it names that no such make named: a retry is not new demand
        (``v2v_samples_asked_total``, which an HPA sizes the fleet on).

        Raises:
            ValueError: a video not in the manifest, or an ordinal past its samples where they are
                known (naming them)."""
        if order.video not in samples:
            raise ValueError(f"make: {order.video!r:.200} is not a video of this plan")
        n = samples[order.video]
        if order.ordinals is not None and n is not None and max(order.ordinals) >= n:
            raise ValueError(f"make: sample {max(order.ordinals)} of {order.video!r:.200}, which gives {n} "
                             "sample(s) an epoch")
        asked, named, waiting = set(order.ordinals or ()), set(), []
        for o in self.waiting:
            if (o.client, o.epoch, o.video) != (order.client, order.epoch, order.video):
                waiting.append(o)
            elif o.ordinals is None:  # its windows asked: kept unless asked again
                if order.ordinals is not None:
                    waiting.append(o)
            else:
                named.update(o.ordinals)
                if not set(o.ordinals) <= asked:  # a make of other samples too: the reader awaits it still
                    waiting.append(o)
        waiting.append(order)
        self.waiting = waiting
        return len(asked - named)

    def forget(self, client: Hashable) -> None:
        """Drop ``client``'s makes (it left)."""
        self.waiting = [o for o in self.waiting if o.client != client]

    def withdraw(self, of: Callable[[Hashable], bool], request: int) -> None:
        """Drop the waiting make ``request`` of the client ``of`` matches (its reader had the
        samples elsewhere)."""
        self.waiting = [o for o in self.waiting if not (o.request == request and of(o.client))]

    def keys(self, o: Order) -> List[SampleKey]:
        """The keys make ``o`` names (none for a make of a video's windows)."""
        return [SampleKey.at(o.video, i, self.kpw) for i in o.ordinals or ()]

    def rows(self, o: Order, store: Mapping, failed: Mapping, samples: Mapping[str, Optional[int]]):
        """``[(ordinal, key, sample or None, reason or None)]`` answering ``o`` once each key is
        made (in ``store``), failed for the epoch or past the video's samples (its slots learned
        after the make came: a padding row saying so), and, for a make of windows, once its
        video's samples are known; None before."""
        n = samples.get(o.video)
        if o.ordinals is None and n is None:
            return None  # its slots come from its decode
        rows = []
        for key in self.keys(o):
            sk = (o.epoch, key)
            if n is not None and key.ordinal(self.kpw) >= n:
                rows.append((key.ordinal(self.kpw), key, None, f"past {o.video}'s {n} sample(s) an epoch"))
            elif sk in store:
                rows.append((key.ordinal(self.kpw), key, store[sk], None))
            elif sk in failed:
                rows.append((key.ordinal(self.kpw), key, None, failed[sk]))
            else:
                return None
        return rows

    def videos(self, store: Mapping, failed: Mapping, samples: Mapping[str, Optional[int]]) -> List[Tuple[int, str]]:
        """(epoch, video) the makes wait on, by (epoch, position), then in the order asked."""
        out: Dict[Tuple[int, str], None] = {}
        for o in sorted(self.waiting, key=lambda o: (o.epoch, o.position)):  # stable: arrival within a position
            if self.rows(o, store, failed, samples) is None:
                out[(o.epoch, o.video)] = None
        return list(out)

    def place(self, epoch: int, video: str, route: Optional[str], now: float, move: bool = False,
              started: bool = False) -> Optional[str]:
        """Where a make of ``video`` in ``epoch`` asked at ``now`` with ``route``
        (``Make.route``) is made: None here, else the host a reader placed it at first (within
        :data:`TOLD_S`: a reader asks a video's samples as its plan reaches them). A route naming
        a host places the video there unless this host holds it (a make waits on it, or one was
        answered within :data:`TOLD_S`): the readers of a job, whose views of the hosts' queues
        differ, have each video made once, where the first of them to ask it chose. A ``move``
        (``Make.move``: a reader measured this host slow) places it at the route's host even so,
        unless its decode ``started`` here or a make of it was answered: its waiting makes go
        with it (:meth:`take`)."""
        if route is None:
            return None
        ev = (epoch, video)
        placed = self.placed.get(ev)
        if placed is not None and now - placed[1] < TOLD_S:
            return placed[0]
        if route == "" or ev in self.told or started or \
                not move and any((o.epoch, o.video) == ev for o in self.waiting):
            return None
        self.placed[ev] = (route, now)
        return route

    def take(self, epoch: int, video: str) -> List[Order]:
        """The makes waiting on ``video`` in ``epoch``, taken out (placed elsewhere: :meth:`place`)."""
        out = [o for o in self.waiting if (o.epoch, o.video) == (epoch, video)]
        self.waiting = [o for o in self.waiting if (o.epoch, o.video) != (epoch, video)]
        return out

    def queued(self, expected: Callable[[str], int]) -> int:
        """Samples the makes waiting ask, every client's: a make's ordinals, or for a make of a
        video's windows ``expected(video)``, the samples its decode makes."""
        return sum(expected(o.video) if o.ordinals is None else len(o.ordinals) for o in self.waiting)

    def answered(self, o: Order, now: float) -> None:
        """Make ``o`` was answered at ``now``: its video's other samples are kept a while."""
        self.told[(o.epoch, o.video)] = now

    def named(self, stored: Sequence[Tuple[int, SampleKey]], now: float) -> Set[Tuple[int, SampleKey]]:
        """The stored samples to keep for the makes: those of the videos a make waits on (a
        decode makes all of a video's samples before a make of its windows is answered), or was
        answered for within :data:`TOLD_S` of ``now``."""
        self.told = {ev: t for ev, t in self.told.items() if now - t < TOLD_S}
        self.placed = {ev: p for ev, p in self.placed.items() if now - p[1] < TOLD_S}
        videos = set(self.told) | {(o.epoch, o.video) for o in self.waiting}
        return {sk for sk in stored if (sk[0], sk[1].video) in videos}
