"""Mutation review of :mod:`difffilter._checks`: the input validation of every filter.

Each test states a small illegal input that must raise (the exception type, the argument
it names and what was expected) or the nearest legal input that must pass, decided
independently of the code under test: eigenvalues and asymmetries from numpy in float64,
exact rational determinants (:class:`fractions.Fraction`), counts of NaNs by numpy, the
documented equivalence of ``nonfinite="skip"`` with an explicit mask. The checks are
reached through the public API (the model's constructor, the whole-sequence filters, the
online step) where the library reaches them, directly otherwise.
"""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest
import torch

import difffilter as df
from difffilter import _checks
from difffilter.resampling import Systematic

D = torch.float64


def _mats(dtype=D):
    """A constant-velocity model's matrices (dx = 2, dy = 1) in ``dtype``."""
    return dict(
        F=torch.tensor([[1.0, 0.1], [0.0, 1.0]], dtype=dtype),
        H=torch.tensor([[1.0, 0.0]], dtype=dtype),
        Q=0.1 * torch.eye(2, dtype=dtype),
        R=torch.tensor([[0.5]], dtype=dtype),
        m0=torch.zeros(2, dtype=dtype),
        P0=torch.eye(2, dtype=dtype),
    )


def _model(**over):
    return df.LinearGaussianModel(**{**_mats(), **over})


def _ys(*batch, T=4, dy=1, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(*batch, T, dy, generator=g, dtype=D)


# ------------------------------------------------------------------------ Choice ----


def test_choice_accepts_member_name_in_any_case():
    """A Choice is built from its value or its member's name, in any case (the
    docstring's "HOLD", "Hold"); checked on a Choice whose name differs from its value."""

    class Shade(_checks.Choice):
        DARK = "noir"

    assert Shade("DARK") is Shade.DARK
    assert Shade("dark") is Shade.DARK
    assert Shade("NOIR") is Shade.DARK
    with pytest.raises(ValueError, match=r"'grey' is not a Shade: one of 'noir'"):
        Shade("grey")


# ------------------------------------------------------------ vmap and meta device ----


def test_vmap_is_refused_with_advice():
    """A tensor batched by torch.func.vmap is refused by name (values cannot be read)."""

    def f(x):
        _checks.check_finite(x, "x")
        return x

    with pytest.raises(ValueError, match="torch.func.vmap .* is not supported"):
        torch.func.vmap(f)(torch.ones(3, 2, dtype=D))


def test_vmap_beneath_grad_is_refused_and_grad_alone_passes():
    """vmap(grad(f)): the batched tensor lies beneath a grad wrapper, and is still found;
    grad alone (no vmap) is legal and its values are known."""

    def f(x):
        _checks.check_finite(x, "x")
        return x.sum()

    with pytest.raises(ValueError, match="torch.func.vmap"):
        torch.func.vmap(torch.func.grad(f))(torch.ones(3, 2, dtype=D))

    def g(x):
        assert _checks.values_known(x)
        return x.square().sum()

    x = torch.tensor([1.0, -2.0], dtype=D)
    assert torch.equal(torch.func.grad(g)(x), 2 * x)  # d/dx Σx² = 2x


def test_meta_model_is_built_and_checked_for_shape_only():
    """On the meta device value checks are skipped (values_known False) so a model can be
    traced there, and shape checks still apply."""
    meta = {k: v.to("meta") for k, v in _mats().items()}
    model = df.LinearGaussianModel(**meta)
    assert model.F.device.type == "meta"
    assert not _checks.values_known(meta["Q"])
    bad = dict(meta, Q=torch.empty(3, 3, dtype=D, device="meta"))
    with pytest.raises(ValueError, match=r"Q must have shape \[\.\.\., 2, 2\]"):
        df.LinearGaussianModel(**bad)


# --------------------------------------------------------------------- as_tensor ----


def test_parameter_of_another_dtype_is_refused():
    """An nn.Parameter of another dtype than the model's would be copied into a
    non-parameter: refused, naming the argument and nn.Parameter."""
    Q = torch.nn.Parameter(0.1 * torch.eye(2, dtype=torch.float32))
    with pytest.raises(ValueError, match=r"Q is an nn.Parameter of torch.float32"):
        _model(Q=Q)
    same = torch.nn.Parameter(0.1 * torch.eye(2, dtype=D))
    assert any(p is same for p in _model(Q=same).parameters())


def test_other_arguments_take_the_dtype_of_F():
    """F sets the dtype: an integer H and a float32 Q become float64 (with F float64)."""
    model = _model(H=torch.tensor([[1, 0]]), Q=0.1 * torch.eye(2, dtype=torch.float32))
    assert model.H.dtype == D and model.process_noise.cov.dtype == D
    assert torch.equal(model.H, torch.tensor([[1.0, 0.0]], dtype=D))


def test_numpy_float64_matrices_make_a_float64_model():
    """A model built from numpy float64 arrays stays float64 (default dtype float32)."""
    mats = {k: v.numpy() for k, v in _mats().items()}
    assert torch.get_default_dtype() == torch.float32
    assert df.LinearGaussianModel(**mats).F.dtype == torch.float64
    mats32 = {k: v.astype(np.float32) for k, v in mats.items()}
    assert df.LinearGaussianModel(**mats32).F.dtype == torch.float32


# ------------------------------------------------------------------ shape checks ----


def test_scalar_m0_is_a_shape_error_naming_m0():
    """A 0-d m0 has no last dimension: ValueError naming m0 and [..., 2], no IndexError."""
    with pytest.raises(ValueError, match=r"m0 must have shape \[\.\.\., 2\]; got \(\)"):
        _model(m0=torch.tensor(0.0, dtype=D))


def test_non_square_F_and_Q_of_the_wrong_size_are_refused():
    """F [2, 3] is not square; Q [3, 3] is square but not dx = 2."""
    with pytest.raises(ValueError, match=r"F must have shape \[\.\.\., d, d\]; got \(2, 3\)"):
        _model(F=torch.zeros(2, 3, dtype=D), H=torch.zeros(1, 3, dtype=D))
    with pytest.raises(ValueError, match=r"Q must have shape \[\.\.\., 2, 2\]; got \(3, 3\)"):
        _model(Q=torch.eye(3, dtype=D))


def test_parameter_batches_that_do_not_broadcast_are_refused():
    """F for 3 runs and Q for 4 do not broadcast: named at construction; 3 and 1 do."""
    F = _mats()["F"].expand(3, 2, 2)
    with pytest.raises(ValueError, match=r"share one batch shape .* F \(3,\), .*Q \(4,\)"):
        _model(F=F, Q=0.1 * torch.eye(2, dtype=D).expand(4, 2, 2))
    _model(F=F, Q=0.1 * torch.eye(2, dtype=D).expand(1, 2, 2))


def test_a_non_finite_F_is_refused():
    """One NaN in F is named."""
    F = _mats()["F"].clone()
    F[1, 0] = float("nan")
    with pytest.raises(ValueError, match="F contains NaN or Inf values; every entry must be"):
        _model(F=F)


# ---------------------------------------------------------------- symmetry and PD ----


def _rel_asym(a: np.ndarray) -> float:
    """max |A - Aᵀ| / max |A|, in float64: the docstring's relative asymmetry."""
    return float(np.abs(a - a.T).max() / np.abs(a).max())


def test_symmetry_is_relative_to_the_largest_entry_of_the_whole_matrix():
    """[[1000, 0], [1e-4, 1]] is asymmetric by 1e-7 of its largest entry (<= 1e-6):
    legal, although 1e-4 is large against its own row's largest entry, 1."""
    Q = np.array([[1000.0, 0.0], [1e-4, 1.0]])
    assert _rel_asym(Q) <= 1e-6 and np.linalg.eigvalsh((Q + Q.T) / 2).min() > 0
    _model(Q=torch.tensor(Q))


def test_symmetry_tolerance_is_inclusive_at_1e_6_and_exclusive_beyond():
    """An asymmetry of exactly rtol = 1e-6 (relative) passes; 1e-5 fails with the
    message naming Q and its asymmetry."""
    at = np.array([[1.0, 1e-6], [0.0, 1.0]])
    assert _rel_asym(at) == 1e-6
    _model(Q=torch.tensor(at))
    beyond = np.array([[1.0, 1e-5], [0.0, 1.0]])
    with pytest.raises(ValueError, match=r"Q must be symmetric; max relative asymmetry 1e-05"):
        _model(Q=torch.tensor(beyond))


def test_an_asymmetric_matrix_with_a_definite_lower_triangle_is_refused():
    """Cholesky reads one triangle only: [[1, 0.5], [0, 1]] factorises, and must still
    be refused as asymmetric."""
    with pytest.raises(ValueError, match="R must be symmetric"):
        _model(H=torch.eye(2, dtype=D), R=torch.tensor([[1.0, 0.5], [0.0, 1.0]], dtype=D))


def test_a_nan_covariance_is_refused_as_non_finite():
    """A NaN in P0 is named as non-finite (not as asymmetric or indefinite)."""
    P0 = torch.eye(2, dtype=D)
    P0[0, 0] = float("nan")
    with pytest.raises(ValueError, match="P0 contains NaN or Inf values"):
        _model(P0=P0)


def test_tiny_eigenvalue_passes_and_zero_eigenvalue_fails():
    """Q = diag(1, 1e-10) is definite (numpy: smallest eigenvalue 1e-10 > 0); Q = g gᵀ
    with g = [1.125, 1.5] (exact in binary, so Q is exactly rank one: its determinant,
    in rationals, is 0) must be refused as not positive definite."""
    tiny = np.diag([1.0, 1e-10])
    assert np.linalg.eigvalsh(tiny).min() == 1e-10
    _model(Q=torch.tensor(tiny))
    g = np.array([1.125, 1.5])
    Q = np.outer(g, g)
    a, b, c = (Fraction(float(x)) for x in (Q[0, 0], Q[0, 1], Q[1, 1]))
    assert a * c - b * b == 0
    with pytest.raises(ValueError, match=r"Q must be positive definite \(all eigenvalues > 0"):
        _model(Q=torch.tensor(Q))


def test_the_first_failing_member_of_a_batch_is_named():
    """Q [3, 2, 2] with members 1 and 2 singular: the message names batch index (1,)."""
    Q = 0.1 * torch.eye(2, dtype=D).repeat(3, 1, 1)
    Q[1] = 0.0
    Q[2] = 0.0
    with pytest.raises(ValueError, match=r"Q \(batch index \(1,\)\) must be positive definite"):
        _model(Q=Q)


# ------------------------------------------------- check_sequence and check_mask ----


def test_check_sequence_shape_and_allowed_nan():
    """ys [T] (one dimension) is refused; a NaN where allow_nan is True passes, one
    where it is False is refused with the mask hint absent."""
    with pytest.raises(ValueError, match=r"ys must have shape \[\.\.\., T, 2\]"):
        _checks.check_sequence(torch.zeros(2), "ys", 2)
    t = torch.zeros(3, 2)
    t[1, 0] = float("nan")
    allow = torch.zeros(3, 2, dtype=torch.bool)
    allow[1, 0] = True
    _checks.check_sequence(t, "ys", 2, allow_nan=allow)
    with pytest.raises(ValueError, match=r"ys contains NaN or Inf values \(pass mask="):
        _checks.check_sequence(t, "ys", 2)
    with pytest.raises(ValueError, match=r"ys contains NaN or Inf values; received"):
        _checks.check_sequence(t, "ys", 2, allow_nan=~allow)


def test_check_mask_values_and_broadcast():
    """A 0/1 mask becomes bool; 0.5 or 2 is refused; a mask that does not broadcast to
    the shape is refused naming both shapes."""
    out = _checks.check_mask(torch.tensor([0.0, 1.0]), "mask", torch.Size([3, 2]))
    assert out.dtype == torch.bool and out.tolist() == [False, True]
    for bad in ([0.0, 0.5], [0, 2]):
        with pytest.raises(ValueError, match=r"mask must be boolean \(True = entry received\)"):
            _checks.check_mask(torch.tensor(bad), "mask", torch.Size([3, 2]))
    with pytest.raises(ValueError, match=r"mask must broadcast to \(3, 2\); got \(3,\)"):
        _checks.check_mask(torch.ones(3, dtype=torch.bool), "mask", torch.Size([3, 2]))
    # to the shape, not with it (the review's bug: a [2, 3] mask for [3] passed, grown)
    with pytest.raises(ValueError, match=r"mask must broadcast to \(3,\); got \(2, 3\)"):
        _checks.check_mask(torch.ones(2, 3, dtype=torch.bool), "mask", torch.Size([3]))


# ---------------------------------------------------------------- number checks ----


def test_check_finite_number_bounds_and_types():
    """bool is no number; positive refuses 0, nonnegative takes 0 and refuses -1e-300;
    ±inf and nan are refused; a one-element tensor and numpy numbers are numbers."""
    with pytest.raises(TypeError, match="alpha must be a real number; got bool"):
        _checks.check_finite_number(True, "alpha")
    with pytest.raises(ValueError, match=r"alpha must be a finite number > 0; got 0.0"):
        _checks.check_finite_number(0, "alpha", positive=True)
    assert _checks.check_finite_number(0, "alpha", nonnegative=True) == 0.0
    with pytest.raises(ValueError, match=r"alpha must be a finite number >= 0; got -1e-300"):
        _checks.check_finite_number(-1e-300, "alpha", nonnegative=True)
    for bad in (float("inf"), float("-inf"), float("nan")):
        with pytest.raises(ValueError, match=r"alpha must be a finite number; got"):
            _checks.check_finite_number(bad, "alpha")
    assert _checks.check_finite_number(torch.tensor([2.5]), "alpha", positive=True) == 2.5
    assert _checks.check_finite_number(np.float32(0.5), "alpha") == 0.5


def test_check_rate_is_the_open_interval():
    """A false-alarm rate lies in (0, 1): 0 and 1 are refused, 1e-300 and 1 - 1e-16
    pass; True is no rate."""
    for bad in (0, 1, 0.0, 1.0, True, -0.1):
        with pytest.raises(ValueError, match=r"alpha must be a false-alarm rate in \(0, 1\)"):
            _checks.check_rate(bad, "alpha")
    assert _checks.check_rate(1e-300, "alpha") == 1e-300
    assert _checks.check_rate(1 - 1e-16, "alpha") == 1 - 1e-16


def test_check_positive_int_and_num_particles():
    """0 and True are no positive integers (directly and as the particle filter's
    num_particles); 1 and numpy's int64 are."""
    for bad in (0, -1, True, 1.0):
        with pytest.raises(ValueError, match="n must be a positive integer"):
            _checks.check_positive_int(bad, "n")
    assert _checks.check_positive_int(np.int64(1), "n") == 1
    for bad in (0, True):
        with pytest.raises(ValueError, match="num_particles must be a positive integer"):
            df.particle_filter(_model(), _ys(), num_particles=bad)


def test_ess_threshold_closed_interval_through_the_particle_filter():
    """ess_threshold 0 (never resample) and 1 (always) are legal; 1.5 is refused."""
    g = torch.Generator().manual_seed(1)
    for ok in (0.0, 1.0):
        out = df.particle_filter(_model(), _ys(), num_particles=8, ess_threshold=ok,
                                 generator=g)  # fmt: skip
        assert torch.isfinite(out.means).all()
    with pytest.raises(ValueError, match=r"ess_threshold must lie in \[0, 1\]"):
        df.particle_filter(_model(), _ys(), num_particles=8, ess_threshold=1.5, generator=g)
    # numpy's numbers are numbers, as check_finite_number takes them (the review's bug: a
    # TypeError "got float32"); the same threshold as a float gives the same run
    import numpy as np

    runs = []
    for value in (np.float32(0.5), 0.5, np.float64(0.5)):
        g = torch.Generator().manual_seed(2)
        runs.append(df.particle_filter(_model(), _ys(), num_particles=8, ess_threshold=value,
                                       generator=g).means)  # fmt: skip
    torch.testing.assert_close(runs[0], runs[1], rtol=0, atol=0)
    torch.testing.assert_close(runs[2], runs[1], rtol=0, atol=0)
    with pytest.raises(TypeError, match="ess_threshold must be a number in"):
        df.particle_filter(_model(), _ys(), num_particles=8, ess_threshold=True, generator=g)


def test_resampler_given_as_string_or_class_is_refused():
    """A resampler's name or class is refused, each with its own advice."""
    with pytest.raises(TypeError, match="resampler must be an object, not the string"):
        df.particle_filter(_model(), _ys(), num_particles=4, resampler="systematic")
    with pytest.raises(TypeError, match="resampler must be an instance, not the class Syst"):
        df.particle_filter(_model(), _ys(), num_particles=4, resampler=Systematic)


# ------------------------------------------------------------- sequence inputs ----


def test_ys_dtype_device_and_length():
    """float32 ys for a float64 model, ys on another device (meta), T = 0: each named."""
    model = _model()
    with pytest.raises(ValueError, match="ys must have the model's dtype torch.float64"):
        df.kalman_filter(model, _ys().float())
    with pytest.raises(ValueError, match="ys must be on the model's device meta; got cpu"):
        df.kalman_filter(df.LinearGaussianModel(**{k: v.to("meta") for k, v in _mats().items()}),
                         _ys())  # fmt: skip
    with pytest.raises(ValueError, match=r"ys must hold at least one time step \(T >= 1\)"):
        df.kalman_filter(model, torch.zeros(0, 1, dtype=D))


def test_ys_batch_must_broadcast_with_the_model_batch_of_m0():
    """A model whose prior mean m0 [3, 2] makes 3 runs: ys for 4 runs is refused, for 3
    runs it is legal (m0's batch is its shape less its one event dimension)."""
    model = _model(m0=torch.zeros(3, 2, dtype=D))
    with pytest.raises(
        ValueError, match=r"the batch of ys \(4,\) does not broadcast with .*\(3,\)"
    ):
        df.kalman_filter(model, _ys(4))
    assert df.kalman_filter(model, _ys(3)).means.shape == (3, 4, 2)


def test_mask_must_be_bool_of_exactly_ys_shape_and_device():
    """A float mask, a broadcastable [T, 1] mask for ys [2, T, 1], a mask on meta: each
    refused, naming mask and what was expected."""
    ys = _ys(2)
    with pytest.raises(ValueError, match="mask must have dtype torch.bool"):
        df.kalman_filter(_model(), ys, mask=torch.ones_like(ys))
    with pytest.raises(ValueError, match=r"mask must have the shape of ys \(2, 4, 1\)"):
        df.kalman_filter(_model(), ys, mask=torch.ones(4, 1, dtype=torch.bool))
    meta = torch.ones(2, 4, 1, dtype=torch.bool, device="meta")
    with pytest.raises(ValueError, match="mask is on meta and ys on cpu"):
        df.kalman_filter(_model(), ys, mask=meta)


def test_nan_at_unreceived_entries_is_legal_and_never_read():
    """NaN at entries the mask marks unreceived: the filter runs, every output finite,
    and equal to the run with those entries set to any finite value (never read)."""
    ys = _ys(2)
    mask = torch.ones_like(ys, dtype=torch.bool)
    mask[0, 1, 0] = mask[1, 3, 0] = False
    nan = ys.masked_fill(~mask, float("nan"))
    big = ys.masked_fill(~mask, 1e6)
    a = df.kalman_filter(_model(), nan, mask=mask)
    b = df.kalman_filter(_model(), big, mask=mask)
    assert torch.isfinite(a.means).all() and torch.isfinite(a.log_likelihood).all()
    torch.testing.assert_close(a.means, b.means, rtol=0, atol=0)
    with pytest.raises(ValueError, match="ys contains NaN or Inf values at received"):
        df.kalman_filter(_model(), nan)


def test_skip_counts_per_run_and_equals_the_explicit_mask():
    """nonfinite='skip' with a mask: the count per run is numpy's count of non-finite
    received entries summed over time and entries, and the result equals the filter
    given mask & isfinite (the docstring: such entries are treated as unreceived)."""
    ys = _ys(2, dy=2)
    model = _model(H=torch.eye(2, dtype=D), R=0.5 * torch.eye(2, dtype=D))
    mask = torch.ones_like(ys, dtype=torch.bool)
    mask[0, 2, 1] = False
    ys[0, 0, 0] = ys[0, 3, 1] = float("nan")
    ys[0, 2, 1] = float("inf")  # unreceived: not counted
    ys[1, 1, 0] = float("-inf")
    out = df.kalman_filter(model, ys, mask=mask, nonfinite="skip")
    y, m = ys.numpy(), mask.numpy()
    want = (~np.isfinite(y) & m).sum(axis=(-1, -2))
    assert out.nonfinite_skipped.tolist() == want.tolist() == [2, 1]
    ref = df.kalman_filter(model, torch.nan_to_num(ys), mask=mask & torch.isfinite(ys))
    torch.testing.assert_close(out.means, ref.means, rtol=0, atol=0)
    assert torch.isfinite(out.means).all()


def test_us_length_batch_and_finiteness():
    """us with 3 steps for 4 measurements, us for 3 runs with ys for 4, a NaN in us:
    each named."""
    model = _model(B=torch.tensor([[0.0], [1.0]], dtype=D))
    ys = _ys(4)
    with pytest.raises(ValueError, match="us must have T = 4 steps, one per measurement; got 3"):
        df.kalman_filter(model, ys, torch.zeros(4, 3, 1, dtype=D))
    with pytest.raises(ValueError, match=r"us's batch shape \(3,\) does not broadcast with ys's"):
        df.kalman_filter(model, ys, torch.zeros(3, 4, 1, dtype=D))
    us = torch.zeros(4, 4, 1, dtype=D)
    us[2, 1, 0] = float("nan")
    # named where, as a NaN in ys is (a recorded log's gap in its inputs: a trial)
    with pytest.raises(
        ValueError, match=r"us contains NaN or Inf values \(first at index \(2, 1, 0\)\)"
    ):
        df.kalman_filter(model, ys, us)


# ------------------------------------------------------------------- online step ----


def _kf():
    kf = df.KalmanFilter()
    kf.full_checks = True
    return kf


def test_step_nan_at_unreceived_entry_is_legal_and_zeroed():
    """One step with y = [NaN] unreceived equals the step with y = [0] unreceived and is
    finite; y = [NaN] received is refused."""
    kf = _kf()
    carry = kf.init(_model())
    off = torch.tensor([False])
    a, _ = kf.step(carry, torch.tensor([float("nan")], dtype=D), mask=off)
    b, _ = kf.step(carry, torch.tensor([0.0], dtype=D), mask=off)
    assert torch.isfinite(a.mean).all() and torch.isfinite(a.cov).all()
    torch.testing.assert_close(a.mean, b.mean, rtol=0, atol=0)
    y, _, m = _checks.check_step_inputs(_model(), None, torch.tensor([float("nan")], dtype=D),
                                        mask=off)  # fmt: skip
    assert y.tolist() == [0.0] and m.tolist() == [False]
    with pytest.raises(ValueError, match="y contains NaN or Inf values at received entries"):
        kf.step(carry, torch.tensor([float("nan")], dtype=D))


def test_step_state_mean_shape_is_checked():
    """check_step_inputs given a state mean of dx = 3 for a model of dx = 2 names it."""
    with pytest.raises(ValueError, match=r"state must hold a mean \[\.\.\., 2\]; got"):
        _checks.check_step_inputs(_model(), torch.zeros(3, dtype=D), torch.zeros(1, dtype=D))


def test_step_y_of_more_runs_than_the_carry_is_refused():
    """A carry of 2 runs given y for 3 runs (or for one run, [1, dy], which broadcasts
    to but is not the carry's shape in reverse) is refused naming y and the runs."""
    kf = _kf()
    carry = kf.init(_model(), batch_shape=(2,))
    with pytest.raises(ValueError, match=r"y's batch shape \(3,\) does not broadcast to"):
        kf.step(carry, torch.zeros(3, 1, dtype=D))
    single = kf.init(_model())
    with pytest.raises(ValueError, match=r"y's batch shape \(2,\) does not broadcast to the car"):
        kf.step(single, torch.zeros(2, 1, dtype=D))
    new, _ = kf.step(carry, torch.zeros(1, dtype=D))  # y [dy] for every run: legal
    assert new.mean.shape == (2, 2)


def test_hand_built_carry_is_checked():
    """A hand-built carry: a mean of the wrong size, a NaN mean, an asymmetric cov, a
    carry on another device than its model: each named as carry.<field>."""
    kf = _kf()
    carry = kf.init(_model())
    y = torch.zeros(1, dtype=D)
    with pytest.raises(ValueError, match=r"carry.mean must have shape \[\.\.\., 2\]; got \(3,\)"):
        kf.step(carry._replace(mean=torch.zeros(3, dtype=D)), y)
    with pytest.raises(ValueError, match="carry.mean contains NaN or Inf values"):
        kf.step(carry._replace(mean=torch.tensor([0.0, float("nan")], dtype=D)), y)
    cov = torch.tensor([[1.0, 0.1], [0.0, 1.0]], dtype=D)
    with pytest.raises(ValueError, match="carry.cov must be symmetric"):
        kf.step(carry._replace(cov=cov, gains=None), y)
    meta = df.LinearGaussianModel(**{k: v.to("meta") for k, v in _mats().items()})
    with pytest.raises(ValueError, match=r"carry.mean is torch.float64 on cpu and its model"):
        _checks.check_carry_fits_model(meta, mean=carry.mean)


# ----------------------------------------------------------- the FDI filters' checks ----


def test_check_filter_inputs_gamma_hat_and_ess_threshold():
    """check_filter_inputs: a NaN gamma_hat and an ess_threshold of 2 are refused;
    finite gamma_hat and ess_threshold 1 pass."""
    model = _model()
    _checks.check_filter_inputs(model, _ys(), gamma_hat=torch.zeros(1), ess_threshold=1)
    with pytest.raises(ValueError, match="gamma_hat contains NaN or Inf values"):
        _checks.check_filter_inputs(model, _ys(), gamma_hat=torch.tensor([float("nan")]))
    with pytest.raises(ValueError, match=r"ess_threshold must lie in \[0, 1\]"):
        _checks.check_filter_inputs(model, _ys(), ess_threshold=2)


def test_check_model_names_a_missing_prior():
    """An object with every model attribute but ``initial`` is refused naming it."""

    class NoPrior:
        dim_x, dim_y, dim_u = 2, 1, 0

        def transition(self, *a):
            pass

        def observe(self, *a):
            pass

    with pytest.raises(TypeError, match="NoPrior lacks initial"):
        df.KalmanFilter().init(NoPrior())


@pytest.mark.parametrize("kind", ["kf", "ekf", "ukf", "pf"])
def test_vmap_over_an_online_step_is_refused_with_advice(kind):
    """A trial: the lean step's finiteness check read a vmap-batched ``y`` and raised
    torch's "Cannot access data pointer of Tensor that doesn't have storage" (the Gaussian
    filters; the particle filter named vmap); every online step now names it."""
    import difffilter as df

    model = df.LinearGaussianModel(torch.eye(2, dtype=D), torch.eye(2, dtype=D)[:1],
                                   0.1 * torch.eye(2, dtype=D), torch.eye(1, dtype=D),
                                   torch.zeros(2, dtype=D), torch.eye(2, dtype=D))  # fmt: skip
    est = {"kf": df.KalmanFilter(), "ekf": df.ExtendedKalmanFilter(),
           "ukf": df.UnscentedKalmanFilter(), "pf": df.ParticleFilter(10)}[kind]  # fmt: skip

    def run(y):
        carry = est.init(model)
        for k in range(y.shape[0]):
            carry, out = est.step(carry, y[k])
        return out.mean

    with pytest.raises(ValueError, match="torch.func.vmap over .* is not supported"):
        torch.func.vmap(run, randomness="different")(torch.ones(3, 4, 1, dtype=D))
