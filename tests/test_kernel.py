"""The one simulation kernel: its noise stream, noisy V2V against a float64 transcription, and
refinement composed with non-idealities in one call."""
from __future__ import annotations

import math

import numba
import numpy as np
import pytest

from tests.conftest import read_luma_clip
from v2v_server.simulation.kernel import (NOISE_LANES, NOISE_MAX, _jsf_words, _ln32, _sincos_turn, full_scale_of,
                               noise_field, run_kernel)
from v2v_server.simulation.nonideal import NonIdealities, draw_pixel_state, simulate_voxels_nonideal
from v2v_server.simulation.refine import simulate_voxels_refined
from v2v_server.simulation.simulate import SensorParams, log_intensity_lut, simulate_voxels


def test_noise_is_standard_normal():
    z = noise_field(123, 40, (100, 100)).ravel()  # 400k draws
    assert abs(z.mean()) < 4 / math.sqrt(z.size)
    assert z.std() == pytest.approx(1.0, abs=0.005)
    # tail masses of N(0, 1) out to 4 sigma
    for q, tail in ((1.0, 0.317311), (2.0, 0.0455003), (3.0, 0.0026998), (3.6541528853610088, 0.000258),
                    (4.0, 6.334e-5)):
        expect = tail * z.size
        assert abs((np.abs(z) > q).sum() - expect) < 5 * math.sqrt(expect) + 3, q
    assert 4.0 < np.abs(z).max() <= NOISE_MAX * (1 + 1e-6)
    # third and fourth moments (skew 0, kurtosis 3)
    assert abs((z**3).mean()) < 0.02 and (z**4).mean() == pytest.approx(3.0, abs=0.05)
    # Kolmogorov-Smirnov distance to the normal CDF: 1.63 / sqrt(n) is its 1 % critical value
    zs = np.sort(z)
    cdf = 0.5 * (1.0 + np.array([math.erf(v / math.sqrt(2.0)) for v in zs]))
    n = zs.size
    d = max(np.max(np.arange(1, n + 1) / n - cdf), np.max(cdf - np.arange(n) / n))
    assert d < 1.63 / math.sqrt(n)


def test_noise_depends_only_on_seed_and_pair():
    whole = noise_field(7, 10, (8, 9))
    np.testing.assert_array_equal(noise_field(7, 4, (8, 9), first_pair=6), whole[6:])
    assert not np.array_equal(noise_field(8, 10, (8, 9)), whole)
    # the streams of different pairs are uncorrelated (10k pixels: |r| ~ 0.01)
    big = noise_field(7, 10, (100, 100)).reshape(10, -1)
    assert np.abs(np.corrcoef(big)[np.triu_indices(10, 1)]).max() < 0.05


def test_noise_halves_and_lanes_are_uncorrelated():
    # pixel j and pixel ceil(n/2) + j are one Box-Muller pair (cos and sin): uncorrelated,
    # also in their squares (r is shared: a correlation of |z| would show a bad transform);
    # an odd frame is the next even one without its last pixel (same pairs)
    np.testing.assert_array_equal(noise_field(3, 2, (1, 7)), noise_field(3, 2, (1, 8))[..., :7])
    z = noise_field(3, 1, (400, 400)).ravel()
    h = z.size // 2
    assert abs(np.corrcoef(z[:h], z[h:])[0, 1]) < 0.01
    assert abs(np.corrcoef(z[:h] ** 2, z[h:] ** 2)[0, 1]) < 0.01
    # the lanes' words: neighbouring pixels come from different generators
    assert abs(np.corrcoef(z[:-1], z[1:])[0, 1]) < 0.01
    for lag in (NOISE_LANES, 2 * NOISE_LANES):
        assert abs(np.corrcoef(z[:-lag], z[lag:])[0, 1]) < 0.01


def test_noise_generator_is_jsf32_as_randomgen_has_it():
    """The lanes are JSF32 (Jenkins' small fast generator, 32-bit, rotations 27/17), checked
    word for word against randomgen's implementation from the same state."""
    import randomgen  # a dev dependency (pyproject): the reference JSF32
    st = np.random.default_rng(0).integers(0, 2**32, (4, NOISE_LANES)).astype(np.uint32)
    words = np.empty(50 * NOISE_LANES, np.uint32)
    start = st.copy()
    _jsf_words(st, words)
    for lane in (0, 5, NOISE_LANES - 1):
        g = randomgen.JSF(0, size=32)
        state = g.state
        state["state"].update(a=int(start[0, lane]), b=int(start[1, lane]), c=int(start[2, lane]),
                              d=int(start[3, lane]), p=27, q=17, r=0)
        g.state = state
        np.testing.assert_array_equal(words[lane::NOISE_LANES], g.random_raw(50).astype(np.uint32))


def test_noise_transform_log_and_sincos_polynomials_are_float32_exact():
    """The transform's log and (sin, cos) of 2 pi u, numba polynomials without libm, against
    numpy's float64 functions: within a few float32 ulps over their whole input range."""
    u = np.concatenate([(np.arange(1, 2**24, 97, dtype=np.float64) + 0.5) * 2.0**-24,
                        2.0 ** -np.arange(1, 26), [1 - 2.0**-24]]).astype(np.float32)
    ln = _vec_ln32(u)
    ref = np.log(u.astype(np.float64))
    assert np.max(np.abs(ln - ref) / np.maximum(np.abs(ref), 1e-3)) < 1e-6
    t = (np.arange(0, 2**24, 89, dtype=np.float64) * 2.0**-24).astype(np.float32)
    s, c = _vec_sincos(t)
    assert np.max(np.abs(s - np.sin(2 * np.pi * t.astype(np.float64)))) < 4e-7
    assert np.max(np.abs(c - np.cos(2 * np.pi * t.astype(np.float64)))) < 4e-7


@numba.njit(cache=True)
def _vec_ln32(x):
    out = np.empty(x.shape[0], np.float64)
    for i in range(x.shape[0]):
        out[i] = _ln32(x[i])
    return out


@numba.njit(cache=True)
def _vec_sincos(x):
    s = np.empty(x.shape[0], np.float64)
    c = np.empty(x.shape[0], np.float64)
    for i in range(x.shape[0]):
        s[i], c[i] = _sincos_turn(x[i])
    return s, c


def test_noisy_v2v_matches_float64_transcription(real_clip):
    """With noise and hot pixels, the kernel equals the paper's equations transcribed in float64
    with the same noise (replayed with noise_field), except at exact-threshold ties."""
    frames = real_clip[:26]
    h, w = frames.shape[1:]
    cp, cn, sigma = 0.15, 0.22, 0.07
    hot = np.zeros((h, w), np.float32)
    hot[3, 4], hot[50, 60] = 0.9, -0.5
    pot0 = np.random.default_rng(0).uniform(-cn, cp, (h, w))
    vox, pot = simulate_voxels(frames, SensorParams(cp, cn, sigma, hot), 5, initial_potential=pot0,
                               noise_seed=99, compute_dtype=np.float64)
    logi = np.log(1e-3 + (frames.astype(np.float64) / 255.0) ** 2.2)
    noise = noise_field(99, 25, (h, w)) * sigma
    p = pot0.copy()
    tie = np.full((h, w), np.inf)
    ref = []
    for i in range(25):
        dl = p + (logi[i + 1] - logi[i]) + noise[i] + hot
        npos = np.maximum(np.floor(dl / cp), 0)
        nneg = np.maximum(np.floor(-dl / cn), 0)
        for q in (dl / cp, -dl / cn):
            tie = np.minimum(tie, np.abs(q - np.round(q)))
        p = dl - cp * npos + cn * nneg
        ref.append(npos - nneg)
    ref = np.stack(ref).reshape(5, 5, h, w)
    clean = tie > 1e-9
    assert clean.mean() > 0.99 and np.abs(ref).sum() > 1000
    np.testing.assert_array_equal(vox[:, :, clean], ref[:, :, clean])
    np.testing.assert_allclose(pot[clean], p[clean], atol=1e-6)
    assert vox[:, :, 3, 4].sum() > 25 * 0.9 / cp - 2  # the hot pixel fires every pair


def test_refinement_and_nonidealities_compose():
    clip = read_luma_clip("bikes.mp4", 11, (48, 64))
    p = SensorParams(0.1, 0.15, 0.03)
    # refined + all non-idealities off == refined alone (same noise seed, same path)
    a, pa, ia = simulate_voxels_refined(clip, p, 5, "uniform:3", rng=np.random.default_rng(5), flow_fn=_zero_flow)
    b, pb, ib = simulate_voxels_nonideal(clip, p, 5, NonIdealities(), fps=30.0, rng=np.random.default_rng(5),
                                         refine="uniform:3", flow_fn=_zero_flow)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(pa, pb)
    assert ia["events"] == ib["events"] and ib["refine"] == "uniform:3"
    # refined + a refractory cap: the cap binds per frame pair, on the summed sub-interval counts
    c, _, ic = simulate_voxels_nonideal(clip, p, 5, NonIdealities(refractory_max_events=1), fps=30.0,
                                        rng=np.random.default_rng(5), refine="uniform:3", flow_fn=_zero_flow)
    assert np.abs(c).max() <= 1 and ic["events_lost_refractory"] > 0
    # refined + per-pixel thresholds: pixels with a larger c+ fire fewer ON events
    ni = NonIdealities(threshold_sigma=0.03)
    st = draw_pixel_state(ni, p, (48, 64), np.random.default_rng(1))
    d, _, _ = simulate_voxels_nonideal(clip, p, 5, ni, fps=30.0, pixel_state=st, rng=np.random.default_rng(5),
                                       refine="uniform:3", flow_fn=_zero_flow)
    on = np.clip(d, 0, None).sum(axis=(0, 1)).astype(float)
    assert np.corrcoef(on.ravel(), st.pos_threshold.ravel())[0, 1] < -0.05
    assert (d != a).any()


def _zero_flow(a, b):
    return np.zeros(a.shape + (2,), np.float32)


def test_kernel_events_add_up_to_counts():
    frames = read_luma_clip("bikes.mp4", 6, (20, 30))
    lut = log_intensity_lut(full_scale_of(frames)).astype(np.float64)
    pot = np.zeros((20, 30))
    res = run_kernel(frames, pot, 0.05, 0.08, lut=lut, noise_std=0.02, noise_seed=3, events=True, split=True)
    assert res.events == len(res.event_step) > 100
    per_pair = np.zeros((5, 600))
    np.add.at(per_pair, (res.event_step, res.event_pixel), res.event_polarity)
    np.testing.assert_array_equal(per_pair.reshape(5, 20, 30), res.net)
    assert ((res.event_fraction >= 0) & (res.event_fraction <= 1)).all()
    np.testing.assert_array_equal(res.pos - res.neg, res.net)


def test_kernel_rejects_bad_inputs():
    frames = np.zeros((3, 4, 4), np.uint8)
    lut = np.zeros(256)
    with pytest.raises(ValueError, match="threshold"):
        run_kernel(frames, np.zeros((4, 4)), 0.0, 0.1, lut=lut)
    with pytest.raises(ValueError, match="potential"):
        run_kernel(frames, np.zeros((4, 5)), 0.1, 0.1, lut=lut)
    with pytest.raises(ValueError, match="pos_threshold"):
        run_kernel(frames, np.zeros((4, 4)), np.ones(3), 0.1, lut=lut)
    with pytest.raises(ValueError, match="uint8 or uint16"):
        full_scale_of(frames.astype(np.int16))


@pytest.mark.parametrize("c, hot, dtype", [(0.2, 0.0, np.int8), (1e-3, 0.0, np.int16), (1e-3, 100.0, np.int32)])
def test_narrow_output_has_the_same_counts_in_the_narrowest_dtype(c, hot, dtype):
    # int8 from the kernel's int16 output and tracked range; int16 as written; int32 by a
    # re-run from the same potential after the int16 attempt overflowed (counts > 32767)
    rng = np.random.default_rng(4)
    frames = rng.integers(0, 256, (9, 6, 7)).astype(np.uint8)
    frames[1::2, :2] = 255
    frames[0::2, :2] = 0
    params = SensorParams(c, c * 1.3, 0.05, np.full((6, 7), hot))
    pot0 = rng.uniform(-c, c, (6, 7))
    wide, pot_w = simulate_voxels(frames, params, 2, initial_potential=pot0, noise_seed=9)
    narrow, pot_n = simulate_voxels(frames, params, 2, initial_potential=pot0, noise_seed=9, narrow=True)
    assert wide.dtype == np.int32 and narrow.dtype == dtype
    np.testing.assert_array_equal(narrow, wide)
    np.testing.assert_array_equal(pot_n, pot_w)
    lo, hi = np.iinfo(dtype).min, np.iinfo(dtype).max
    if dtype != np.int8:  # and it is the narrowest: a narrower type would not hold the counts
        narrower = np.int8 if dtype == np.int16 else np.int16
        assert wide.min() < np.iinfo(narrower).min or wide.max() > np.iinfo(narrower).max
    assert lo <= wide.min() and wide.max() <= hi


@pytest.mark.parametrize("c, amplitude, written", [(0.2, 255, [np.int8]), (0.045, 20, [np.int16])])
def test_narrow_writes_int8_in_one_pass_when_the_bound_allows(monkeypatch, c, amplitude, written):
    """Plain V2V whose thresholds bound every count under 128 (log range + extra dL + the
    largest noise draw + twice the largest of potential and threshold, over the smaller
    threshold) is written int8 by one kernel call; below that bound the kernel writes int16
    and the result is narrowed afterwards. Both equal the int32 counts."""
    import v2v_server.simulation.kernel as kernel_mod

    calls = []
    real = kernel_mod._kernel

    def spy(*args):
        calls.append(args[13].dtype)  # the net array the kernel writes
        return real(*args)

    rng = np.random.default_rng(5)
    frames = (rng.integers(0, amplitude + 1, (9, 6, 7)) + (128 - amplitude // 2)).clip(0, 255).astype(np.uint8)
    params = SensorParams(c, c * 1.2, 0.05, np.zeros((6, 7)))
    pot0 = rng.uniform(-c, c, (6, 7))
    wide, _ = simulate_voxels(frames, params, 2, initial_potential=pot0, noise_seed=3)
    monkeypatch.setattr(kernel_mod, "_kernel", spy)
    narrow, _ = simulate_voxels(frames, params, 2, initial_potential=pot0, noise_seed=3, narrow=True)
    assert calls == written and narrow.dtype == np.int8
    np.testing.assert_array_equal(narrow, wide)


def test_noise_transform_compiles_without_fused_multiply_add():
    """The noise's float32 polynomials are plain IEEE multiplies and adds (numba's default, no
    fastmath), so their bits do not depend on whether the host has FMA: no fused instruction in
    the compiled transform (compiled afresh here: a function loaded from numba's cache keeps
    no assembly to inspect)."""
    from v2v_server.simulation.kernel import _box_muller

    fresh = numba.njit(error_model="numpy")(_box_muller.py_func)
    words = np.arange(64, dtype=np.uint32) * np.uint32(2654435761)
    out = np.empty(64, np.float32)
    fresh(words, 32, out)
    ref = np.empty(64, np.float32)
    _box_muller(words, 32, ref)
    np.testing.assert_array_equal(out, ref)  # the same function as the kernel's
    asm = fresh.inspect_asm(fresh.signatures[0])
    assert "mulss" in asm or "mulps" in asm  # the transform is in there
    assert "vfmadd" not in asm and "vfmsub" not in asm and "vfnmadd" not in asm
