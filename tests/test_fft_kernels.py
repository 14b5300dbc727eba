"""Accuracy of cm2cl's own FFT kernels (backend 'cl') against numpy in float64.

Relative error (Frobenius norm over the batch) of the forward r2c transform and of the normalised
inverse: <= 5e-7 in float32 and <= 1e-14 in float64, on 2/3/5/7-smooth sizes up to 4096 per axis,
odd and even, batch 1..64.  Both paths: lines in local memory, and the pass kernels through
global memory (forced by a zero local-memory limit).
"""

import numpy as np
import pyopencl.array as cla
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from cm2cl.device import fft
from cm2cl.device.fft_kernels import ClPlan, factor
from cm2cl.errors import InputError

TOL = {np.dtype(np.float32): 5e-7, np.dtype(np.float64): 1e-14}
MAX_ELEMENTS = 4 * 2**20  # per example, to keep the test time small

SMOOTH = sorted(n for n in range(1, 4097) if fft._is_smooth(n))


def errors(rt, x, dtype, local_limit=None, group=None):
    """(forward, inverse) relative errors of a ClPlan on x (batch, py, px) against numpy."""
    x = np.asarray(x, dtype)  # the reference transforms exactly the values the device sees
    plan = ClPlan(rt, x.shape, dtype, local_limit, group)
    xd = cla.to_device(rt.queue, x)
    spec = cla.empty(rt.queue, plan.spec_shape, plan.cdtype)
    plan.forward(xd, spec)
    ref = np.fft.rfft2(x.astype(np.float64))
    e_fwd = np.linalg.norm(spec.get() - ref) / np.linalg.norm(ref)
    ref_c = ref.astype(plan.cdtype)
    spec.set(ref_c)
    back = cla.empty(rt.queue, x.shape, dtype)
    plan.inverse(spec, back)
    want = np.fft.irfft2(ref_c.astype(np.complex128), s=x.shape[1:])
    e_inv = np.linalg.norm(back.get() - want) / np.linalg.norm(want)
    return e_fwd, e_inv, plan


@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(py=st.sampled_from(SMOOTH), px=st.sampled_from(SMOOTH), batch=st.integers(1, 64),
       seed=st.integers(0, 2**32 - 1))
def test_forward_and_inverse_match_numpy(rt, dtype, py, px, batch, seed):
    batch = max(1, min(batch, MAX_ELEMENTS // (py * px)))
    x = np.random.default_rng(seed).standard_normal((batch, py, px))
    e_fwd, e_inv, _ = errors(rt, x, dtype)
    assert e_fwd <= TOL[dtype], f"forward {batch} x {py} x {px}: relative error {e_fwd:.2e}"
    assert e_inv <= TOL[dtype], f"inverse {batch} x {py} x {px}: relative error {e_inv:.2e}"


@settings(max_examples=4, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(py=st.sampled_from([n for n in SMOOTH if n <= 512]), px=st.sampled_from([n for n in SMOOTH if n <= 512]),
       batch=st.integers(1, 8), seed=st.integers(0, 2**32 - 1))
def test_pass_kernels_through_global_memory_match_numpy(rt, dtype, py, px, batch, seed):
    """Lines that do not fit in local memory (here: none may) take one kernel per radix pass."""
    x = np.random.default_rng(seed).standard_normal((batch, py, px))
    e_fwd, e_inv, plan = errors(rt, x, dtype, local_limit=0)
    assert not plan.rows_local and not plan.cols_local
    assert e_fwd <= TOL[dtype] and e_inv <= TOL[dtype], (e_fwd, e_inv)


@pytest.mark.parametrize("group", [(1, 1, 1), (8, 1, 1), (1, 64, 1), (16, 16, 1), (4, 32, 1), (1, 1, 8),
                                   (2, 1, 4), (1, 4, 2), (3, 2, 8)])
@pytest.mark.parametrize("shape", [(3, 48, 60), (2, 45, 63), (5, 7, 130)])
def test_every_work_group_shape_gives_the_same_transform(rt, shape, group):
    """(work-items per group, work-items per line, lines per work-item): several lines per
    work-group and several work-items per line (the GPU shapes), SIMD across lines (the CPU
    shapes), on this device: the butterfly loops and the partial last group or vector must not
    depend on the shape."""
    x = np.random.default_rng(5).standard_normal(shape)
    from cm2cl.device.fft_kernels import _max_lines

    e_fwd, e_inv, plan = errors(rt, x, np.float32, group=group)
    assert plan.rows_local and plan.cols_local
    v = min(group[2], _max_lines(rt.caps, np.float32))   # 8 except on PoCL before 3.1
    assert (plan.row_c, plan.row_v) == (group[0], v) and (plan.col_c, plan.col_v) == (group[0], v)
    assert e_fwd <= TOL[np.dtype(np.float32)] and e_inv <= TOL[np.dtype(np.float32)], (e_fwd, e_inv)


@pytest.mark.parametrize("shape", [(2, 9, 4096), (1, 4096, 10), (2, 3645, 7)])
def test_an_axis_of_4096_and_a_long_odd_axis(rt, dtype, shape):
    x = np.random.default_rng(sum(shape)).standard_normal(shape)
    e_fwd, e_inv, _ = errors(rt, x, dtype)
    assert e_fwd <= TOL[dtype] and e_inv <= TOL[dtype], (e_fwd, e_inv)


@pytest.mark.parametrize("shape", [(3, 48, 60), (2, 45, 63), (1, 1, 1), (4, 1, 6), (2, 7, 1)])
def test_round_trip_returns_the_input(rt, dtype, shape):
    """inverse(forward(x)) == x through the plan of the 'cl' backend (its inverse may overwrite
    the spectrum); sizes of one included."""
    x = np.random.default_rng(7).standard_normal(shape).astype(dtype)
    plan = fft.get_plan(rt, shape[1:], shape[0], dtype, "cl")
    xd = cla.to_device(rt.queue, x)
    spec = cla.empty(rt.queue, plan.spec_shape, plan.cdtype)
    back = cla.empty(rt.queue, shape, dtype)
    plan.inverse(plan.forward(xd, spec), back)
    assert np.allclose(xd.get(), x, rtol=0, atol=0)  # the forward leaves its input intact
    err = np.linalg.norm(back.get() - x) / np.linalg.norm(x)
    assert err <= TOL[np.dtype(dtype)], f"round trip relative error {err:.2e}"


def test_factor_uses_the_fewest_passes_and_refuses_large_primes():
    assert factor(4096) == [8, 8, 8, 8]
    assert factor(648) == [8, 9, 9]
    assert factor(27) == [9, 3]
    assert factor(1470) == [2, 3, 5, 7, 7]
    assert factor(1) == []
    for n in SMOOTH:
        assert int(np.prod(factor(n))) == n
    with pytest.raises(InputError, match=r"fft size: 34 has the prime factor 17 > 13"):
        factor(34)


@pytest.mark.parametrize("local_limit", [None, 0])
def test_radix_9_in_float64_on_line_and_pass_kernels(rt, local_limit):
    """bf9 (3 x 3 with its own inner twiddles) to float64 accuracy: 81 = 9 x 9 columns, 162 real
    points per row (81 complex: 9 x 9), in local memory and through the pass kernels."""
    x = np.random.default_rng(9).standard_normal((3, 81, 162))
    e_fwd, e_inv, plan = errors(rt, x, np.float64, local_limit=local_limit)
    assert plan.cols_local == (local_limit is None)
    assert e_fwd <= 1e-14 and e_inv <= 1e-14, (e_fwd, e_inv)


def test_odd_prime_radices_11_and_13(rt):
    """The generic odd butterfly (used for 7, 11 and 13) on sizes a padded_shape may bring."""
    x = np.random.default_rng(11).standard_normal((2, 13 * 4, 11 * 3))
    e_fwd, e_inv, _ = errors(rt, x, np.float64)
    assert e_fwd <= 1e-14 and e_inv <= 1e-14, (e_fwd, e_inv)


def test_lines_per_work_item_follow_the_simd_width(rt):
    """CPUs transform as many lines together as one native vector holds (at most 8); a device
    without SIMD gets one."""
    from dataclasses import replace

    from cm2cl.device.fft_kernels import _lines_per_item

    new = replace(rt.caps, platform_version="OpenCL 3.0 PoCL 3.1+debian  Linux, None+Asserts, RELOC, LLVM 15")
    caps = replace(new, vector_width_float=16, vector_width_double=8)
    assert _lines_per_item(caps, np.float32) == 8 and _lines_per_item(caps, np.float64) == 8
    caps = replace(new, vector_width_float=8, vector_width_double=4)
    assert _lines_per_item(caps, np.float32) == 8 and _lines_per_item(caps, np.float64) == 4
    caps = replace(new, vector_width_float=1, vector_width_double=3)
    assert _lines_per_item(caps, np.float32) == 1 and _lines_per_item(caps, np.float64) == 2
    # PoCL before 3.1 (PyPI's 3.0, LLVM 14) compiles without AVX-512: at most 256 bits of lines
    old = replace(rt.caps, platform_version="OpenCL 3.0 PoCL 3.0-rc2  Linux, Release, RELOC, LLVM 14.0.6",
                  vector_width_float=16, vector_width_double=8)
    assert _lines_per_item(old, np.float32) == 4 and _lines_per_item(old, np.float64) == 2


@pytest.mark.parametrize("shape,group", [((3, 24, 40), None), ((2, 30, 84), (16, 4, 1)), ((1, 18, 20), (2, 2, 4))])
def test_inverse_with_the_x_step_fused_matches_numpy(rt, dtype, shape, group):
    """ClPlan.inverse_xstep = the normalised inverse of X = (conj(H) R + T - mu_v conj(H) HX) / c
    (xstep_solve in the column pass's loads), against numpy in float64 on random T, H, R, HX: widths 21,
    43 and 11 leave partial vectors of columns for every lines-per-work-item choice; the pass path does
    not fuse."""
    b, py, px = shape
    rng = np.random.default_rng(7)
    plan = ClPlan(rt, shape, dtype, group=group)
    w = px // 2 + 1
    cplx = lambda n: (rng.standard_normal((n, py, w)) + 1j * rng.standard_normal((n, py, w))).astype(plan.cdtype)  # noqa: E731
    T, H, Rp, HX = cplx(b), cplx(b), cplx(1), cplx(1)
    c, mu_v = 1.7, 0.6
    H64 = H.astype(np.complex128)
    want = np.fft.irfft2((np.conj(H64) * Rp + T - mu_v * np.conj(H64) * HX) / c, s=(py, px))
    assert plan.fuses_xstep
    out = cla.empty(rt.queue, shape, dtype)
    dev = lambda a: cla.to_device(rt.queue, a)  # noqa: E731
    plan.inverse_xstep(dev(T), out, dev(H), dev(Rp), dev(HX), c, mu_v)
    err = np.linalg.norm(out.get() - want) / np.linalg.norm(want)
    assert err <= 2 * TOL[dtype], err
    slow = ClPlan(rt, shape, dtype, local_limit=0)
    assert not slow.fuses_xstep
    with pytest.raises(ValueError, match="fuses_xstep"):
        slow.inverse_xstep(dev(T), out, dev(H), dev(Rp), dev(HX), c, mu_v)
