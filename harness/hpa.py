"""The Kubernetes HorizontalPodAutoscaler's rule (``autoscaling/v2``), pure: what replica count
the controller sets at each sync from the pods' metric, for ``harness.fleet_sim``'s autoscaled
fleet (docs/scaling.md).

What it follows, from kube-controller-manager's ``podautoscaler`` package (Kubernetes 1.29-1.32):

* **The ratio.** ``desired = ceil(ready pods x mean metric / target)``, the mean over the pods
  that count; nothing changes while ``|1 - mean / target| <= TOLERANCE``.
* **Pods that do not count** (``groupPods``): a pod not running yet is set aside; for the CPU, a
  pod within ``CPU_INITIALIZATION_S`` of its start that is not ready, or whose sample was taken
  before it had been ready for one metric window, is set aside too (a starting process's CPU
  says nothing of the load); a pod with no sample is *missing*. Where the ratio says grow and
  pods were set aside, they count at 0 (missing ones too); where it says shrink, missing pods
  count at the target (the CPU: at 100 %), and the ratio is taken again: no change where it now
  lies within the tolerance or points the other way.
* **Behaviour** (``normalizeDesiredReplicasWithBehaviors``): the recommendation is held within
  the highest of the last ``scaleDown.stabilizationWindowSeconds``' recommendations and the
  lowest of the last ``scaleUp.stabilizationWindowSeconds``', then limited by the policies (a
  ``Pods`` policy: at most ``value`` pods added, or removed, in any ``periodSeconds``; a
  ``Percent`` one: that share of the replicas at the period's start; ``selectPolicy`` Max takes
  the policy that allows the most change, Min the least, Disabled none), then by
  ``minReplicas`` and ``maxReplicas``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Optional, Sequence, Tuple

import yaml

#: The controller's ``--horizontal-pod-autoscaler-tolerance``: a ratio within 10 % of 1 changes nothing.
TOLERANCE = 0.1
#: ``--horizontal-pod-autoscaler-sync-period``: seconds between the controller's passes.
SYNC_S = 15.0
#: ``--horizontal-pod-autoscaler-cpu-initialization-period``: seconds after a pod's start during
#: which its CPU counts only once it has been ready for a whole metric window.
CPU_INITIALIZATION_S = 300.0


@dataclass(frozen=True)
class Policy:
    """One scaling policy: ``kind`` ``"Pods"`` or ``"Percent"``, its ``value`` and ``period_s``."""

    kind: str
    value: int
    period_s: float


@dataclass(frozen=True)
class Rules:
    """One direction's behaviour: its stabilisation ``window_s``, ``policies`` and ``select``
    (``"Max"``, ``"Min"`` or ``"Disabled"``)."""

    window_s: float
    policies: Tuple[Policy, ...]
    select: str = "Max"


SELECTS = ("Max", "Min", "Disabled")
#: The API's defaults where a manifest sets no behaviour (``autoscaling/v2`` defaulting).
DEFAULT_UP = Rules(0.0, (Policy("Percent", 100, 15.0), Policy("Pods", 4, 15.0)))
DEFAULT_DOWN = Rules(300.0, (Policy("Percent", 100, 15.0),))


@dataclass(frozen=True)
class HpaSpec:
    """An HPA's spec: ``min_replicas``, ``max_replicas``, its one metric (``metric``: ``"cpu"``
    for the Resource metric, else the Pods or External metric's name) and ``target`` (the CPU:
    the utilisation's fraction of the request; else the average value a pod should have), and
    its ``up`` and ``down`` behaviour."""

    min_replicas: int
    max_replicas: int
    metric: str
    target: float
    up: Rules = DEFAULT_UP
    down: Rules = DEFAULT_DOWN

    @classmethod
    def load(cls, path: Path) -> "HpaSpec":
        """The one HorizontalPodAutoscaler of the manifest file ``path``.

        Raises:
            ValueError: no HPA in the file, more than one metric, or a metric or target kind
                this model does not run (naming the file and the field)."""
        try:
            docs = [d for d in yaml.safe_load_all(Path(path).read_text())
                    if isinstance(d, dict) and d.get("kind") == "HorizontalPodAutoscaler"]
        except yaml.YAMLError as e:
            raise ValueError(f"{path}: not YAML: {str(e).splitlines()[0]}") from None
        if len(docs) != 1:
            raise ValueError(f"{path}: {len(docs)} HorizontalPodAutoscaler(s), want one")
        try:
            return cls._of(docs[0]["spec"], path)
        except (KeyError, TypeError) as e:
            raise ValueError(f"{path}: the HorizontalPodAutoscaler lacks or mistypes a field ({e})") from None

    @classmethod
    def _of(cls, spec: dict, path: Path) -> "HpaSpec":
        if len(spec.get("metrics", ())) != 1:
            raise ValueError(f"{path}: spec.metrics: this model runs one metric, got {len(spec.get('metrics', ()))}")
        m = spec["metrics"][0]
        if m["type"] == "Resource" and m["resource"]["name"] == "cpu" and \
                m["resource"]["target"]["type"] == "Utilization":
            metric, target = "cpu", m["resource"]["target"]["averageUtilization"] / 100
        elif m["type"] == "Pods" and m["pods"]["target"]["type"] == "AverageValue":
            metric, target = m["pods"]["metric"]["name"], _quantity(m["pods"]["target"]["averageValue"])
        else:
            raise ValueError(f"{path}: spec.metrics[0]: a Resource cpu Utilization or a Pods AverageValue target, "
                             f"got {m['type']}")
        behavior = spec.get("behavior") or {}

        def rules(key: str, default: Rules) -> Rules:
            b = behavior.get(key)
            if not b:
                return default
            pols = tuple(Policy(p["type"], int(p["value"]), float(p["periodSeconds"])) for p in b.get("policies", ()))
            if any(p.kind not in ("Pods", "Percent") for p in pols) or b.get("selectPolicy", "Max") not in SELECTS:
                raise ValueError(f"{path}: spec.behavior.{key}: policies of type Pods or Percent and a selectPolicy "
                                 f"of {', '.join(SELECTS)}")
            return Rules(float(b.get("stabilizationWindowSeconds", default.window_s)), pols or default.policies,
                         b.get("selectPolicy", "Max"))

        return cls(int(spec.get("minReplicas", 1)), int(spec["maxReplicas"]), metric, float(target),
                   rules("scaleUp", DEFAULT_UP), rules("scaleDown", DEFAULT_DOWN))


def _quantity(q) -> float:
    """A Kubernetes quantity as a number: ``"1500m"`` is 1.5, ``"20"`` is 20."""
    s = str(q)
    return float(s[:-1]) / 1000 if s.endswith("m") else float(s)


@dataclass(frozen=True)
class PodSample:
    """One pod as the controller sees it at a sync: ``running`` (its phase is Running), ``ready``
    (its Ready condition), ``started`` and ``ready_since`` (seconds; None: never ready), and its
    metric ``value`` taken at ``sampled_at`` over ``window_s`` seconds (None: no sample)."""

    running: bool
    ready: bool
    started: float
    ready_since: Optional[float]
    value: Optional[float]
    sampled_at: float = 0.0
    window_s: float = 0.0


def metric_replicas(spec: HpaSpec, current: int, pods: Sequence[PodSample], now: float) -> int:
    """The replica count the metric asks for (``GetResourceReplicas`` for the CPU,
    ``GetMetricReplicas`` for a Pods metric: module docstring), ``current`` where it asks no
    change or no pod has a sample that counts."""
    counted: List[float] = []
    unready = missing = 0
    for p in pods:
        if not p.running:
            unready += 1
        elif p.value is None:
            missing += 1
        elif spec.metric == "cpu" and _cpu_unready(p, now):
            unready += 1
        else:
            counted.append(p.value)
    if not counted:
        return current
    ratio = sum(counted) / len(counted) / spec.target
    if not (unready and ratio > 1.0) and not missing:
        return current if abs(1.0 - ratio) <= TOLERANCE else math.ceil(ratio * len(counted))
    values = list(counted)
    if missing:
        values += [(max(1.0, spec.target) if spec.metric == "cpu" else spec.target) if ratio < 1.0 else 0.0] * missing
    if unready and ratio > 1.0:
        values += [0.0] * unready
    new = sum(values) / len(values) / spec.target
    if abs(1.0 - new) <= TOLERANCE or (ratio < 1.0 < new) or (ratio > 1.0 > new):
        return current
    n = math.ceil(new * len(values))
    if (new < 1.0 and n > current) or (new > 1.0 and n < current):
        return current
    return n


def _cpu_unready(p: PodSample, now: float) -> bool:
    if now < p.started + CPU_INITIALIZATION_S:
        return not p.ready or p.ready_since is None or p.sampled_at < p.ready_since + p.window_s
    return not p.ready and p.ready_since is None


@dataclass
class Hpa:
    """One HPA's controller state: the recommendations of its stabilisation windows and the
    scale events its policies count (module docstring)."""

    spec: HpaSpec
    recommendations: List[Tuple[float, int]] = field(default_factory=list)
    events: List[Tuple[float, int]] = field(default_factory=list)  # (when, replicas added; < 0: removed)

    def sync(self, now: float, current: int, pods: Sequence[PodSample]) -> int:
        """The replicas the controller sets at ``now`` for a Deployment of ``current`` replicas
        (its spec) whose pods are ``pods``; records the change for the policies."""
        s = self.spec
        if current > s.max_replicas or current < s.min_replicas:
            desired = min(s.max_replicas, max(s.min_replicas, current))
        else:
            desired = self._limit(now, current, self._stabilise(now, current, metric_replicas(s, current, pods, now)))
        if desired != current:
            self.events.append((now, desired - current))
        return desired

    def _stabilise(self, now: float, current: int, rec: int) -> int:
        up = [r for t, r in self.recommendations if t > now - self.spec.up.window_s]
        down = [r for t, r in self.recommendations if t > now - self.spec.down.window_s]
        keep = max(self.spec.up.window_s, self.spec.down.window_s)
        self.recommendations = [(t, r) for t, r in self.recommendations if t > now - keep] + [(now, rec)]
        return min(max(current, min(up + [rec])), max(down + [rec]))

    def _limit(self, now: float, current: int, desired: int) -> int:
        s = self.spec
        if desired > current:
            limit = self._policy_limit(now, current, s.up, up=True)
            return min(desired, max(limit, current), s.max_replicas)
        if desired < current:
            limit = self._policy_limit(now, current, s.down, up=False)
            return max(desired, min(limit, current), s.min_replicas)
        return desired

    def _policy_limit(self, now: float, current: int, rules: Rules, up: bool) -> int:
        if rules.select == "Disabled":
            return current
        proposals = []
        for p in rules.policies:
            added = sum(n for t, n in self.events if n > 0 and t > now - p.period_s)
            removed = -sum(n for t, n in self.events if n < 0 and t > now - p.period_s)
            start = current - added + removed
            if p.kind == "Pods":
                proposals.append(start + p.value if up else start - p.value)
            elif up:
                proposals.append(math.ceil(start * (1 + p.value / 100)))
            else:
                proposals.append(int(start * (1 - p.value / 100)))
        most = max if up else min
        return (most if rules.select == "Max" else (min if up else max))(proposals)
