"""A fleet that follows the job: the HorizontalPodAutoscaler's rule (``harness.hpa``), the
autoscaled fleet simulator (``harness.fleet_sim.autoscale``) running deploy/k8s-autoscale's HPA
against a job of fixed appetite, and the /metrics series that HPA scales on, through a real
``v2v-serve`` host."""
from __future__ import annotations

import time
import urllib.request
from pathlib import Path

import pytest

from harness.fleet_sim import ASKED, DEPLOY_HPA, METRIC_WINDOW_S, Fleet, Job, autoscale
from harness.hpa import Hpa, HpaSpec, Policy, PodSample, Rules, metric_replicas

#: The fleet of the brief's scenario: hosts of 8 workers (the deploy file's CPU request).
FLEET = Fleet(videos=40_000, slots=8)


def pod(value, ready_since=0.0, running=True, started=-60.0, sampled_at=100.0):
    return PodSample(running, ready_since is not None, started, ready_since, value, sampled_at, 15.0)


CPU = HpaSpec(2, 16, "cpu", 0.8)
ASKS = HpaSpec(2, 16, ASKED, 0.85)


def test_the_ratio_rounds_up_and_a_ratio_within_the_tolerance_changes_nothing():
    assert metric_replicas(CPU, 4, [pod(1.0)] * 4, 400.0) == 5  # ceil(4 x 1.0 / 0.8)
    assert metric_replicas(CPU, 4, [pod(0.85)] * 4, 400.0) == 4  # 1.0625: within 0.1
    assert metric_replicas(CPU, 4, [pod(0.4)] * 4, 400.0) == 2


def test_pods_that_do_not_count_count_at_zero_to_grow_and_at_the_target_to_shrink():
    # a CPU sample taken less than a window after the pod was ready is set aside, then counts 0 to grow
    fresh = pod(1.0, ready_since=95.0, started=60.0)
    assert metric_replicas(CPU, 3, [pod(1.0), pod(1.0), fresh], 110.0) == 3  # (1.25 + 1.25 + 0) / 3: within 0.1
    assert metric_replicas(CPU, 3, [pod(1.0), pod(1.0), pod(None)], 400.0) == 3  # missing: 0 to grow, likewise
    # missing counts at the target to shrink: 2 x 0.5 / 0.85 with one at 1.0 gives 0.78, so 3 x 0.78 -> 3
    assert metric_replicas(ASKS, 3, [pod(0.5), pod(0.5), pod(None)], 400.0) == 3
    assert metric_replicas(ASKS, 3, [pod(0.5), pod(0.5), pod(0.5)], 400.0) == 2
    # not running: set aside; a Pods metric does not look at readiness
    assert metric_replicas(ASKS, 3, [pod(0.85), pod(0.85), pod(None, None, running=False)], 400.0) == 3


def test_the_scale_down_window_keeps_the_highest_recommendation_and_policies_limit_each_period():
    spec = HpaSpec(2, 16, "cpu", 0.8, Rules(0.0, (Policy("Pods", 4, 60.0),)), Rules(300.0, (Policy("Pods", 1, 120.0),)))
    hpa = Hpa(spec)
    assert hpa.sync(0.0, 2, [pod(1.0)] * 2) == 3
    assert hpa.sync(15.0, 3, [pod(1.0)] * 3) == 4
    assert hpa.sync(30.0, 4, [pod(4.0)] * 4) == 6  # 20 asked, 2 of this minute's 4 pods already added
    assert hpa.sync(100.0, 6, [pod(0.1)] * 6) == 6  # recommendations of 4, 5, 20 within 300 s
    assert hpa.sync(340.0, 6, [pod(0.1)] * 6) == 5  # the window's highest is 2: one pod a period
    assert hpa.sync(355.0, 5, [pod(0.1)] * 5) == 5
    assert hpa.sync(461.0, 5, [pod(0.1)] * 5) == 4


def test_the_deploy_files_hpa_is_what_the_simulator_runs():
    spec = HpaSpec.load(DEPLOY_HPA)
    assert (spec.metric, spec.target, spec.min_replicas) == (ASKED, 0.85, 2)
    with pytest.raises(ValueError, match="HorizontalPodAutoscaler"):
        HpaSpec.load(DEPLOY_HPA.parent / "kustomization.yaml")


@pytest.mark.timeout(120)
def test_the_deploy_files_hpa_follows_a_job_and_the_cpu_would_not():
    """docs/scaling.md's scenario: a job taking 48 samples/s (6.2 hosts of 8 workers) starts on
    2 fresh hosts and halves its appetite at 15 min, read by the client's own pass. On the
    deploy file's HPA (the share of each host's capacity the job asks of it): from 5 min on the
    job waits on under 5 % of its steps and the fleet holds at most 1.3x the hosts it needs; it
    never shrinks while the appetite holds, nor grows while the hosts idle, and gives hosts back
    to at most 1.3x within 20 min of the halving. After the halving it grows only while a host
    that served was out (stalled) for at least half the metric's minute: its work went to the
    others, which the metric reads as need (it is: the job is short of a host), and the fleet
    then ends above 1.3x only inside the scale-down window of that growth. The same HPA on the
    CPU (80 %) keeps 1.6x the hosts after the halving: the CPU of hosts making the reader's stock
    ahead, and its 15 s samples, hold its recommendations up."""
    r = autoscale(FLEET, Job())
    g = r.figures()
    half = Job().halve_at_s
    assert r.metric == ASKED and r.needed(0) == pytest.approx(6.2, abs=0.1)
    assert g["waited"] < 0.05 and g["held"] <= 1.3
    assert g["downs_before_half"] == 0 and g["ups_while_idle"] == 0 and g["waited_half"] < 0.05
    spec, window = HpaSpec.load(DEPLOY_HPA), METRIC_WINDOW_S[ASKED]
    ups = [t for t, before, after, _ in r.changes() if t >= half and after > before]
    # the metric's minute and the scale-up window's before each: what the growth read
    assert all(r.out_for(t - window - spec.up.window_s, t) >= window / 2 for t in ups), ups
    back = next(t - half for t, n, *_ in r.syncs if t >= half and n <= 1.3 * r.needed(t))
    assert back < 1200
    assert g["end"] <= 1.3 or r.syncs[-1][0] - ups[-1] <= spec.down.window_s
    assert max(n for _, _, n, _ in r.changes()) < 2 * r.needed(0)
    cpu = autoscale(FLEET, Job(metric="cpu", target=0.8)).figures()
    assert cpu["end"] > 1.3 and cpu["given_back_s"] == float("inf")


@pytest.mark.timeout(120)
def test_a_reader_that_asks_ahead_for_the_hosts_it_read_at_the_start_makes_a_grown_fleet_wait():
    """docs/scaling.md: a reader that sizes its window once an epoch (``fleet_pass.Pass`` follows
    the fleet instead), in a job started on 2 hosts, waits on long clips on a tenth of its steps
    and more whatever the fleet, which idles enough that the HPA holds it near what is needed."""
    g = autoscale(FLEET, Job(window_follows=False)).figures()
    assert g["waited"] > 0.1 and g["held"] < 1.2


def scrape(port: int) -> dict:
    page = urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=10).read().decode()
    return {line.split()[0]: float(line.split()[-1]) for line in page.splitlines() if line and line[0] != "#"}


@pytest.mark.timeout(300)
def test_a_host_exports_the_samples_asked_of_it_and_the_capacity_it_said(tmp_path, videos):
    """The series deploy/prometheus-adapter's rule divides: ``v2v_samples_asked_total`` counts
    the samples every make named (made already or not; a make asked again while it waits, a
    reader's retry, replaces it: answered and counted once), ``v2v_capacity_samples_per_second`` is the capacity the host
    said in its last answer, absent before it said one."""
    from harness.serve import ServeProcess, free_port
    from v2v_client.fetch import Link
    from v2v_wire.plan_messages import Make, Rows
    from tests.test_fleet_read import setup
    from tests.test_scale_out import OUTPUTS

    root, want, base = setup(tmp_path, videos)
    port = free_port()
    with ServeProcess(base + ["--metrics-port", str(port)]) as host, Link(host.endpoint, 60) as link:
        plan = link.ask().plan
        before = scrape(port)
        assert before["v2v_samples_asked_total"] == 0 and "v2v_capacity_samples_per_second" not in before
        video = want[0].split("#")[0]
        ordinals = sorted(int(s.split("#")[1]) for s in want if s.split("#")[0] == video)
        link._send(Make(1, 0, video, tuple(ordinals[:1]), OUTPUTS, plan).to_wire())
        link._send(Make(2, 0, video, tuple(ordinals[:1]), OUTPUTS, plan).to_wire())  # asked again as it waits
        got = link._recv(time.monotonic() + 60)
        assert got is not None and isinstance(got[0], Rows) and got[0].request == 2  # the retry replaced make 1
        assert link._recv(time.monotonic() + 1) is None  # its rows sent once
        asked, last = 1, None
        for request, ask in enumerate((ordinals, ordinals[-1:]), 3):  # made already
            link._send(Make(request, 0, video, tuple(ask), OUTPUTS, plan).to_wire())
            got = link._recv(time.monotonic() + 60)
            assert got is not None and isinstance(got[0], Rows)
            asked, last = asked + len(ask), got[0]
        deadline = time.monotonic() + 10
        while (m := scrape(port))["v2v_samples_asked_total"] != asked and time.monotonic() < deadline:
            time.sleep(0.2)  # the page is rendered at most once a second
        assert m["v2v_samples_asked_total"] == asked
        assert last.rate > 0 and m["v2v_capacity_samples_per_second"] == pytest.approx(last.rate)


def test_the_adapters_rule_serves_the_hpas_metric_from_the_hosts_series():
    import yaml

    from v2v_server.ops.metrics import ServerMetrics

    rule, = yaml.safe_load((Path(DEPLOY_HPA).parents[1] / "prometheus-adapter" / "values.yaml").read_text())[
        "rules"]["custom"]
    assert rule["name"]["as"] == HpaSpec.load(DEPLOY_HPA).metric
    m = ServerMetrics(progress=False)
    m.said = 1.0
    page = m.exposition().decode()
    for series in ("v2v_samples_asked_total", "v2v_capacity_samples_per_second"):
        assert series in rule["metricsQuery"] and f"\n{series} " in page
