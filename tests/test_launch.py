"""kernels/launch.py: kernels called with numpy arrays launch by the short path with the same
results as Taichi's own path, and everything the short path does not handle still goes through
Taichi's, checks and errors included."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import taichi as ti
from taichi.lang import kernel_impl

from kernels import launch
from kernels.launch import _launch

vec3 = ti.types.vector(3, ti.f64)


@ti.kernel
def _scaled_sum(a: ti.types.ndarray(dtype=ti.f64, ndim=1),
                v: ti.types.ndarray(dtype=vec3, ndim=1),
                out: ti.types.ndarray(dtype=ti.f32, ndim=2), k: ti.i32, s: ti.f64) -> ti.f64:
    total = 0.0
    for i in range(a.shape[0]):
        x = a[i] * s + v[i][0] - v[i][2] + k
        out[i, 0] = ti.cast(x, ti.f32)
        out[i, 1] = ti.cast(x * x, ti.f32)
        total += x
    return total


@ti.kernel
def _either(a: ti.types.ndarray(dtype=ti.f64, ndim=1), out: ti.types.ndarray(dtype=ti.f64, ndim=1),
            square: ti.template(), power: ti.template()):
    for i in range(a.shape[0]):
        x = a[i]
        if ti.static(square):
            x = x * x
        out[i] = x ** power


def _arguments(rng, n=1000):
    return (rng.standard_normal(n), rng.standard_normal((n, 3)), np.zeros((n, 2), np.float32),
            3, 0.25)


def _taichi_path(fn, *args):
    """``fn`` called through Taichi's own ``Kernel.__call__`` (the one the wrapper wraps)."""
    return kernel_impl.Kernel.__call__.__wrapped__(fn._primal, *args)


def test_installed_by_bftaichi_init():
    assert getattr(kernel_impl.Kernel.__call__, "_bftaichi_short", False)
    assert launch.install()  # a second install keeps the one wrapper
    assert not hasattr(kernel_impl.Kernel.__call__.__wrapped__, "_bftaichi_short")


def test_short_path_gives_taichi_paths_results():
    rng = np.random.default_rng(0)
    a, v, out, k, s = _arguments(rng)
    expected_out = out.copy()
    expected = _taichi_path(_scaled_sum, a, v, expected_out, k, s)
    _scaled_sum(a, v, out, k, s)  # first call of this signature: Taichi's path, then planned
    plans = _scaled_sum._primal._bftaichi_plans
    assert list(plans.values())[0] != launch._SKIP
    for _ in range(3):  # the short path, onto arrays written before
        out[:] = -1
        got = _scaled_sum(a, v, out, k, s)
    assert got == expected  # the returned float64, bit for bit
    assert np.array_equal(out, expected_out)
    # other arrays of the same features take the same plan: new pointers and shapes each call
    a2, v2, out2, _, _ = _arguments(rng, n=17)
    ref2 = out2.copy()
    assert _scaled_sum(a2, v2, out2, 5, -2.0) == _taichi_path(_scaled_sum, a2, v2, ref2, 5, -2.0)
    assert np.array_equal(out2, ref2)
    assert len(plans) == 1  # a's length is not a feature, the vector's is


def test_template_values_select_their_own_compiled_kernel():
    """A bool or int template argument is part of the signature: each value launches the
    specialisation Taichi compiled for it."""
    a = np.random.default_rng(5).standard_normal(100)
    for square, power in ((True, 1), (False, 1), (True, 3), (False, 2), (True, 1)):
        for _ in range(2):  # planned, then launched by the short path
            out = np.zeros_like(a)
            _either(a, out, square, power)
        ref = np.zeros_like(a)
        _taichi_path(_either, a, ref, square, power)
        assert np.array_equal(out, ref)
        assert np.allclose(out, (a * a if square else a) ** power)
    plans = _either._primal._bftaichi_plans
    assert len(plans) == 4 and launch._SKIP not in plans.values()


def test_what_the_short_path_leaves_to_taichi():
    rng = np.random.default_rng(1)
    a, v, out, k, s = _arguments(rng, n=50)
    ref = out.copy()
    want = _taichi_path(_scaled_sum, a, v, ref, k, s)
    # a Fortran-ordered output: Taichi's path copies it in and back
    fortran = np.asfortranarray(np.zeros_like(out))
    assert _scaled_sum(a, v, fortran, k, s) == want
    assert np.array_equal(fortran, ref)
    # keywords
    out_kw = np.zeros_like(out)
    assert _scaled_sum(a, v, out_kw, k=k, s=s) == want
    assert np.array_equal(out_kw, ref)
    # a wrong dtype still fails as Taichi fails it, planned signature or not
    _scaled_sum(a, v, out, k, s)
    with pytest.raises(ValueError, match="dtype"):
        _scaled_sum(a.astype(np.float32), v, out, k, s)
    # a byte-swapped array has its own signature: Taichi's path decides, not the plan of the
    # native one (whose bytes it would misread)
    swapped = a.astype(a.dtype.newbyteorder())
    try:
        got = _scaled_sum(swapped, v, out, k, s)
    except Exception:
        pass  # refused by Taichi, as before
    else:
        assert got == want
    # a non-contiguous view is refused by Taichi, not launched on the wrong elements
    with pytest.raises(ValueError, match="contiguous"):
        _scaled_sum(np.repeat(a, 2)[::2], v, out, k, s)


def test_a_new_taichi_program_is_planned_again():
    rng = np.random.default_rng(2)
    a, v, out, k, s = _arguments(rng, n=64)
    _scaled_sum(a, v, out, k, s)
    plans = _scaled_sum._primal._bftaichi_plans
    sig = launch._features((a, v, out, k, s), launch._slots(_scaled_sum._primal))
    stale = (object(),) + plans[sig][1:]  # as after ti.reset(): another program
    plans[sig] = stale
    ref = np.zeros_like(out)
    assert _scaled_sum(a, v, out, k, s) == _taichi_path(_scaled_sum, a, v, ref, k, s)
    assert plans[sig][0] is not stale[0]
    assert np.array_equal(out, ref)


def test_solvers_give_the_same_bits_with_and_without_the_short_path(monkeypatch):
    """The MAP solve (compact layout, float64) and a block of probes (27-point gather, float32
    vector lanes): hundreds of small launches each, compared to the bit."""
    from kernels.pcg import pcg, pcg_batched
    from test_pcg import nbr_reference, posterior, shell_band

    ijk, dist = shell_band(6.0, 3.0)
    nbr = nbr_reference(ijk)
    S, _, h = posterior(ijk, dist, nbr, seed=3)
    B = np.random.default_rng(4).choice([-1.0, 1.0], size=(len(h), 5)).astype(np.float32)

    def solve():
        x, info = pcg(S, nbr, h, tol=1e-8, maxiter=500)
        X, binfo = pcg_batched(S, nbr, B, tol=1e-4, maxiter=500)
        return x, info, X, binfo

    short = []
    monkeypatch.setattr(launch, "_launch", lambda *a: short.append(1) or _launch(*a))
    fast = solve()
    assert len(short) > 100  # most of the solves' launches took the short path
    monkeypatch.setattr(kernel_impl.Kernel, "__call__", kernel_impl.Kernel.__call__.__wrapped__)
    slow = solve()
    assert fast[1]["iterations"] == slow[1]["iterations"] > 5
    assert fast[1]["residual_history"] == slow[1]["residual_history"]
    assert np.array_equal(fast[0], slow[0])
    assert fast[3]["iterations"] == slow[3]["iterations"]
    assert np.array_equal(fast[2], slow[2])


@pytest.mark.parametrize("setting, expected", [(None, "True"), ("taichi", "False")])
def test_the_short_path_can_be_turned_off(setting, expected):
    """BFTAICHI_TAICHI_LAUNCH=taichi keeps Taichi's own launch path (for debugging a kernel)."""
    env = {k: v for k, v in os.environ.items() if k != "BFTAICHI_TAICHI_LAUNCH"}
    if setting is not None:
        env["BFTAICHI_TAICHI_LAUNCH"] = setting
    code = ("import bftaichi\n"
            "from taichi.lang import kernel_impl\n"
            "bftaichi.init()\n"
            "print(getattr(kernel_impl.Kernel.__call__, '_bftaichi_short', False))\n")
    res = subprocess.run([sys.executable, "-c", code], cwd=Path(__file__).resolve().parents[1],
                         capture_output=True, text=True, timeout=120, env=env)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip().splitlines()[-1] == expected
