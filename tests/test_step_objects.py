"""The init/step objects of every estimator: validation at their boundary, purity, and
equality with the open-loop driver (property-based where the inputs are generated).

Each estimator object of the library (the Gaussian filters, the particle filter, the
attack-aware filters of ``difffilter.fdi``, the fixed-gain observer and the neural
wrapper) is built on one model with an input (``dx = 4``, ``dy = 2``, ``du = 1``) and
stepped through its public ``step``: a malformed measurement, input or mask, a carry
whose batch does not match the measurement, a carry with NaN entries or a
non-symmetric covariance, particles of another count: each ends in a ``ValueError`` or
``TypeError`` that names the argument. The old one-step functions
(``kalman_step``, …, ``particle_step``) go through the same checks.
"""

from __future__ import annotations

import importlib
import pkgutil
import subprocess
import sys

import pytest
import torch
from conftest import constant_velocity
from hypothesis import given, settings
from hypothesis import strategies as st
from test_malformed_inputs import SETTINGS, malformed_mask, malformed_us, malformed_y, raises_naming

import difffilter as df
from difffilter import fdi
from difffilter.estimator import Generators
from difffilter.fdi.neural import NeuralCompensation
from difffilter.loop import open_loop
from difffilter.models.neural_estimator import NeuralFDIEstimator
from difffilter.observers import FixedGainFilter

F64 = torch.float64
CV = constant_velocity(with_input=True)  # dx = 4, dy = 2, du = 1, float64
N = 8


def _network():
    return NeuralFDIEstimator(num_areas=1, area_dim=2, a=2, b=2, hidden=4, init="symmetric",
                              init_scale=0.3, seed=3, dtype=F64)  # fmt: skip


BUILDERS = {
    "kf": lambda: df.KalmanFilter(),
    "ekf": lambda: df.ExtendedKalmanFilter(),
    "ukf": lambda: df.UnscentedKalmanFilter(),
    "fixed_gain": lambda: FixedGainFilter(0.5 * torch.eye(4, 2, dtype=F64)),
    "gated": lambda: fdi.GatedFilter(fdi.ChiSquareDetector(2)),
    "zhang": lambda: fdi.AdaptiveKalmanFilter(),
    "neural_kf": lambda: NeuralCompensation(_network(), df.KalmanFilter()),
    # (the EKF's moments shared by its innovation and its update; the UKF and the observer
    # share none; evidence=False as the training task builds it)
    "neural_ekf": lambda: NeuralCompensation(_network(), df.ExtendedKalmanFilter()),
    "neural_ukf": lambda: NeuralCompensation(
        _network(), df.UnscentedKalmanFilter(), evidence=False
    ),
    "neural_fixed_gain": lambda: NeuralCompensation(
        _network(), FixedGainFilter(0.5 * torch.eye(4, 2, dtype=F64)), standardize=False
    ),
    "pf": lambda: df.ParticleFilter(N),
    "poa_pf": lambda: fdi.PoAParticleFilter(N, fdi.PoADetector(0.5, 0.3)),
    "modified_pf": lambda: fdi.ModifiedParticleFilter(
        N, fdi.PoADetector(0.5, 0.3), torch.zeros(8, 2, dtype=F64)
    ),
    "mixture_pf": lambda: fdi.MixtureParticleFilter(
        N, fdi.DeceptionMixtureLikelihood(0.2, fdi.BiasDeception(torch.full((2,), 0.5, dtype=F64)))
    ),
    "mdpf": lambda: fdi.AdaptiveParticleFilter(N),
    "neural_pf": lambda: NeuralCompensation(_network(), df.ParticleFilter(N)),
}
GAUSSIAN = ("kf", "ekf", "ukf", "fixed_gain", "gated", "zhang", "neural_kf", "neural_ekf",
            "neural_ukf", "neural_fixed_gain")  # fmt: skip
ALL = tuple(BUILDERS)


def _gens(seed=0):
    return Generators(*(torch.Generator().manual_seed(seed + i) for i in range(3)))


def _init(name, batch=(2,), seed=0):
    est = BUILDERS[name]()
    return est, est.init(CV, batch, _gens(seed))


def _gaussian_part(name, carry):
    """The Gaussian moments inside a carry and how to put them back."""
    for field in ("inner", "filter"):  # wrappers keep their filter's carry in a field
        inner = getattr(carry, field, None)
        if inner is not None and hasattr(inner, "cov"):
            return inner, lambda new, field=field: carry._replace(**{field: new})
    return carry, lambda new: new


def _data(batch, T, seed=0):
    g = torch.Generator().manual_seed(seed)
    ys = 0.3 * torch.randn(*batch, T, 2, generator=g, dtype=F64)
    us = 0.3 * torch.randn(*batch, T, 1, generator=g, dtype=F64)
    return ys, us


# ------------------------------------------------------------ validation at the boundary


@pytest.mark.parametrize("name", ALL)
def test_a_measurement_batch_that_does_not_broadcast_with_the_carry_is_named(name):
    est, carry = _init(name, (3,))
    u = torch.zeros(3, 1, dtype=F64)
    raises_naming("y", est.step, carry, torch.zeros(4, 2, dtype=F64), u)
    raises_naming("u", est.step, carry, torch.zeros(3, 2, dtype=F64), torch.zeros(4, 1, dtype=F64))
    mask = torch.ones(4, 2, dtype=torch.bool)
    raises_naming("mask", est.step, carry, torch.zeros(3, 2, dtype=F64), u, mask)


@pytest.mark.parametrize("name", ALL)
def test_a_carry_with_nan_entries_is_refused(name):
    est, carry = _init(name)
    y, u = torch.zeros(2, 2, dtype=F64), torch.zeros(2, 1, dtype=F64)
    if name in GAUSSIAN:
        part, put = _gaussian_part(name, carry)
        bad = put(part._replace(mean=torch.full_like(part.mean, float("nan"))))
        raises_naming("carry.mean", est.step, bad, y, u)
    else:
        bad = carry._replace(particles=carry.particles.clone().fill_(float("nan")))
        raises_naming("carry.particles", est.step, bad, y, u)


@pytest.mark.parametrize("name", [n for n in GAUSSIAN if "fixed_gain" not in n])  # reads no cov
def test_a_non_symmetric_covariance_in_the_carry_is_refused(name):
    est, carry = _init(name)
    part, put = _gaussian_part(name, carry)
    cov = part.cov.expand(2, 4, 4).clone()
    cov[..., 0, 1] += 0.5
    y, u = torch.zeros(2, 2, dtype=F64), torch.zeros(2, 1, dtype=F64)
    raises_naming("carry.cov", est.step, put(part._replace(cov=cov)), y, u)


@pytest.mark.parametrize("name", [n for n in ALL if n not in GAUSSIAN])
def test_particles_of_another_count_are_refused(name):
    est, carry = _init(name)
    fewer = carry._replace(particles=carry.particles[..., :3, :],
                           log_weights=carry.log_weights[..., :3])  # fmt: skip
    y, u = torch.zeros(2, 2, dtype=F64), torch.zeros(2, 1, dtype=F64)
    raises_naming("particles", est.step, fewer, y, u)


def test_initial_states_of_another_particle_count_are_refused_everywhere():
    state = df.particle_init(CV, 5, (2,), torch.Generator().manual_seed(0))
    ys = torch.zeros(2, 3, 2, dtype=F64)
    pf = df.ParticleFilter(N)
    raises_naming("num_particles", pf.attach, state, CV, Generators())
    raises_naming("particles", open_loop, pf, CV, ys, carry=state)
    raises_naming("particles", df.particle_filter, CV, ys, num_particles=N, initial_state=state)


def test_a_resampler_class_instead_of_an_instance_is_a_type_error():
    for build in (
        lambda: df.ParticleFilter(N, resampler=df.resampling.Systematic),
        lambda: fdi.PoAParticleFilter(N, fdi.PoADetector(0.5, 0.3), resampler=df.resampling.Soft),
        lambda: fdi.AdaptiveParticleFilter(N, resampler=df.resampling.Multinomial),
    ):
        with pytest.raises(TypeError, match="resampler"):
            build()


def test_a_carry_of_another_estimator_is_a_type_error():
    kf, carry = _init("pf")
    raises_naming("carry", df.KalmanFilter().step, carry, torch.zeros(2, 2, dtype=F64))


@settings(max_examples=120, **SETTINGS)
@given(name=st.sampled_from(ALL), which=st.sampled_from(["y", "u", "mask"]), data=st.data())
def test_malformed_step_inputs_are_named(name, which, data):
    est, carry = _init(name)
    y, u = torch.zeros(2, 2, dtype=F64), torch.zeros(2, 1, dtype=F64)
    if which == "y":
        raises_naming("y", est.step, carry, data.draw(malformed_y(2)), u)
    elif which == "mask":
        raises_naming("mask", est.step, carry, y, u, data.draw(malformed_mask((2, 2))))
    else:
        bad = data.draw(malformed_us((2,), 1))[..., 0, :]
        if bad.shape == (2, 1) and bad.dtype == F64 and bool(torch.isfinite(bad).all()):
            bad = torch.zeros(3, 1, dtype=F64)  # "steps" means nothing for one step: batch
        raises_naming("u", est.step, carry, y, bad)


STEP_FUNCTIONS = {
    "kalman_step": df.kalman_step,
    "extended_kalman_step": df.extended_kalman_step,
    "unscented_kalman_step": df.unscented_kalman_step,
}


@pytest.mark.parametrize("name", sorted(STEP_FUNCTIONS))
def test_the_one_step_functions_check_like_the_objects(name):
    step, state = STEP_FUNCTIONS[name], df.gaussian_init(CV, (3,))
    y = torch.zeros(3, 2, dtype=F64)
    raises_naming("y", step, CV, state, torch.zeros(4, 2, dtype=F64))
    raises_naming(
        "carry.mean", step, CV, state._replace(mean=torch.full((3, 4), float("nan"), dtype=F64)), y
    )
    cov = state.cov.expand(3, 4, 4).clone()
    cov[..., 1, 0] += 0.3
    raises_naming("carry.cov", step, CV, state._replace(cov=cov), y)


def test_particle_step_checks_like_the_object():
    state = df.particle_init(CV, N, (3,), torch.Generator().manual_seed(0))
    y = torch.zeros(3, 2, dtype=F64)
    raises_naming("y", df.particle_step, CV, state, torch.zeros(4, 2, dtype=F64))
    nan = state._replace(particles=torch.full_like(state.particles, float("nan")))
    raises_naming("carry.particles", df.particle_step, CV, nan, y)
    raises_naming("state", df.particle_step, CV, df.gaussian_init(CV, (3,)), y)


# ----------------------------------------------------------------------------- detectors


@pytest.mark.parametrize("detector", [fdi.ChiSquareDetector(2), fdi.ChiSquareDetector(2, window=3),
                                      fdi.CusumDetector(bias=3.0, threshold=5.0)])  # fmt: skip
def test_detectors_need_a_sequence_of_at_least_one_step(detector):
    eye = torch.eye(2, dtype=F64)
    raises_naming(
        "innovations", detector.detect, torch.zeros(3, 0, 2, dtype=F64), eye.expand(3, 0, 2, 2)
    )
    raises_naming("innovations", detector.detect, torch.zeros(2, dtype=F64), eye)  # rank 1: no T
    raises_naming("innovations", detector.detect, torch.zeros(3, 4, 2, dtype=torch.int64),
                  eye.expand(3, 4, 2, 2))  # fmt: skip


def test_cusum_sequences_need_a_time_axis():
    cusum = fdi.CusumDetector(bias=3.0, threshold=5.0)
    for call in (cusum.run, cusum.scores):
        raises_naming("g", call, torch.ones(3, 0, dtype=F64))
        raises_naming("g", call, torch.tensor(1.0, dtype=F64))
    raises_naming("g_attack_free", cusum.calibrate, torch.ones(3, 0, dtype=F64), 0.01)
    stats, alarms = cusum.run(torch.full((5,), 4.0, dtype=F64))  # one run of five steps
    assert stats.tolist() == [1.0, 2.0, 3.0, 4.0, 5.0] and not bool(alarms.any())


def test_poa_detector_needs_floating_residuals_and_particles():
    det = fdi.PoADetector(0.5, 0.3)
    raises_naming("residuals", det, torch.ones(3, 10, 2, dtype=torch.int64))
    raises_naming("residuals", fdi.probability_of_attack, torch.ones(3, 0, 2, dtype=F64), 0.5)
    raises_naming("residuals", fdi.poa.literal_probability_of_attack,
                  torch.ones(3, 10, 2, dtype=torch.int64), torch.eye(2), 0.5)  # fmt: skip


# ------------------------------------------------------------- purity and the open loop


@pytest.mark.parametrize("batch", [(), (1,), (3,), (2, 2)])
@pytest.mark.parametrize("name", ALL)
@settings(max_examples=3, **SETTINGS)
@given(T=st.integers(1, 5), seed=st.integers(0, 2**16), masked=st.booleans())
def test_steps_compose_to_the_open_loop_and_leave_the_carry_alone(name, batch, T, seed, masked):
    """``open_loop`` (fast paths included) equals the composed public steps; a step returns
    a new carry and leaves the one it was given as it was."""
    ys, us = _data(batch, T, seed)
    mask = None
    if masked:
        mask = torch.rand(*batch, T, 2, generator=torch.Generator().manual_seed(seed)) < 0.7
    est = BUILDERS[name]()
    whole = open_loop(est, CV, ys, us, mask=mask, generator=_gens(seed))
    for key, record in whole.extras.items():  # every step record is stacked per run and step
        lead = batch if key == "log_likelihood" else (*batch, T)
        assert tuple(record.shape[: len(lead)]) == lead, f"extras[{key!r}] {tuple(record.shape)}"
    carry = est.init(CV, batch, _gens(seed))
    for t in range(T):
        before = [v.clone() for v in carry if isinstance(v, torch.Tensor)]
        m = None if mask is None else mask[..., t, :]
        new, out = est.step(carry, ys[..., t, :], us[..., t, :], m)
        after = [v for v in carry if isinstance(v, torch.Tensor)]
        assert all(torch.equal(a, b) for a, b in zip(before, after)), "step modified its carry"
        torch.testing.assert_close(out.mean, whole.means[..., t, :], rtol=1e-9, atol=1e-9)
        carry = new


@settings(max_examples=20, **SETTINGS)
@given(name=st.sampled_from(GAUSSIAN), seed=st.integers(0, 2**16))
def test_a_deterministic_step_is_a_function_of_its_carry(name, seed):
    """Stepping the same carry twice gives the same result (nothing hides in the object)."""
    ys, us = _data((3,), 2, seed)
    est, carry = _init(name, (3,))
    carry, _ = est.step(carry, ys[:, 0], us[:, 0])
    first = est.step(carry, ys[:, 1], us[:, 1])[1]
    second = est.step(carry, ys[:, 1], us[:, 1])[1]
    torch.testing.assert_close(first.mean, second.mean, rtol=0, atol=0)
    torch.testing.assert_close(first.cov, second.cov, rtol=0, atol=0)


# ------------------------------------------------------------------ the lean online step


def _tensors(carry, out) -> list:
    """Every tensor of a step's carry and output, in order (nested tuples and dicts too)."""
    from difffilter._vouched import _leaves

    return [v for v in _leaves((carry, out), []) if isinstance(v, torch.Tensor)]


def _counting_carry_checks(est) -> list:
    """Count the calls of ``est._check_carry`` (the full validation of a carry)."""
    calls, check = [], est._check_carry

    def counted(carry):
        calls.append(1)
        return check(carry)

    est._check_carry = counted
    return calls


@pytest.mark.parametrize("batch", [(), (3,)])
@pytest.mark.parametrize("name", ALL)
def test_the_lean_step_equals_the_fully_checked_step(name, batch):
    """A carry is validated once, by ``init``, which vouches for it; neither it nor the
    carries the steps return are validated again: only the new inputs are; the numbers
    equal those of ``full_checks`` (every step validated in full) exactly, masked and
    unmasked steps alike."""
    T = 6
    ys, us = _data(batch, T, seed=1)
    mask = torch.rand(*batch, T, 2, generator=torch.Generator().manual_seed(1)) < 0.7
    ys = torch.where(mask, ys, torch.full_like(ys, float("nan")))  # never read where unreceived
    lean, checked = BUILDERS[name](), BUILDERS[name]()
    checked.full_checks = True
    lean_calls, checked_calls = _counting_carry_checks(lean), _counting_carry_checks(checked)
    a, b = lean.init(CV, batch, _gens(5)), checked.init(CV, batch, _gens(5))
    for t in range(T):
        y, u, m = ys[..., t, :], us[..., t, :], mask[..., t, :]
        if t % 2 == 0:  # every other step fully received
            y, m = torch.where(m, y, 0.0), None
        a, out_a = lean.step(a, y, u, m)
        b, out_b = checked.step(b, y, u, m)
        left, right = _tensors(a, out_a), _tensors(b, out_b)
        assert len(left) == len(right)
        assert all(torch.equal(x, z) for x, z in zip(left, right)), f"step {t} differs"
    assert len(lean_calls) == 1 and len(checked_calls) == 1 + T


@pytest.mark.parametrize("name", ["kf", "ukf", "gated", "pf", "modified_pf"])
def test_bad_inputs_next_to_a_vouched_carry_are_still_named(name):
    est, carry = _init(name, (3,))
    y, u = torch.zeros(3, 2, dtype=F64), torch.zeros(3, 1, dtype=F64)
    raises_naming("y", est.step, carry, torch.zeros(3, 2, dtype=torch.float32), u)  # init's
    raises_naming("y", est.step, carry, torch.full((3, 2), float("nan"), dtype=F64), u)
    carry, _ = est.step(carry, y, u)  # vouched for from here on
    raises_naming("y", est.step, carry, torch.zeros(4, 2, dtype=F64), u)  # another batch
    raises_naming("y", est.step, carry, torch.zeros(3, 3, dtype=F64), u)  # another dy
    raises_naming("y", est.step, carry, torch.zeros(3, 2, dtype=torch.float32), u)
    raises_naming("y", est.step, carry, torch.full((3, 2), float("nan"), dtype=F64), u)
    raises_naming("y", est.step, carry, torch.full((3, 2), float("inf"), dtype=F64), u)
    raises_naming("u", est.step, carry, y, torch.full((3, 1), float("nan"), dtype=F64))
    raises_naming("u", est.step, carry, y, torch.zeros(3, 2, dtype=F64))
    raises_naming("mask", est.step, carry, y, u, torch.ones(3, 2))  # a float mask
    raises_naming("mask", est.step, carry, y, u, torch.ones(3, 3, dtype=torch.bool))
    if name == "kf":  # finite entries whose sum overflows: validated in full, accepted
        est.step(carry, torch.full((3, 2), 1e308, dtype=F64), u)
    est.step(carry, y, u)  # and the carry is as good as before the errors


@pytest.mark.parametrize("name", ["kf", "ukf", "pf"])
def test_bad_inputs_of_one_run_next_to_a_vouched_carry_are_still_named(name):
    """One run's ``y [dy]`` and ``u [du]`` on the CPU are checked by summing their lists on
    the host: a NaN or an infinity anywhere is named, and finite entries whose sum
    overflows are validated in full and accepted."""
    est, carry = _init(name, ())
    y, u = torch.zeros(2, dtype=F64), torch.zeros(1, dtype=F64)
    carry, _ = est.step(carry, y, u)  # vouched for from here on
    for bad in (float("nan"), float("inf"), float("-inf")):
        for i in range(2):
            raises_naming("y", est.step, carry, y.index_fill(0, torch.tensor([i]), bad), u)
        raises_naming("u", est.step, carry, y, torch.full((1,), bad, dtype=F64))
    raises_naming("y", est.step, carry, torch.zeros(3, dtype=F64), u)
    raises_naming("y", est.step, carry, torch.zeros(1, 2, dtype=F64), u)  # a batch of one
    if name == "kf":  # finite entries whose sum overflows: validated in full, accepted
        est.step(carry, torch.full((2,), 1e308, dtype=F64), u)
    est.step(carry, y, u)


class _PriorOfTheWrongSize:
    """A user's model whose prior has three entries where the state has four."""

    def __init__(self, model):
        self.model = model
        self.initial = df.noise.Gaussian(torch.zeros(3, dtype=F64), torch.eye(3, dtype=F64))

    def __getattr__(self, name):
        return getattr(self.model, name)


@pytest.mark.parametrize("name", ["kf", "ukf", "gated"])
def test_init_names_a_prior_that_does_not_fit_the_state(name):
    """``init`` validates the carry it makes (the steps then trust it): a prior of the
    wrong size is named there, not left to a shape error deep in the first step."""
    est = BUILDERS[name]()
    raises_naming("[..., 4]", est.init, _PriorOfTheWrongSize(CV), (2,), _gens())


def test_a_vouched_carry_changed_afterwards_is_validated_again():
    kf, y = df.KalmanFilter(), torch.zeros(2, 2, dtype=F64)
    carry, _ = kf.step(kf.init(CV, (2,)), y)
    carry.mean[0, 0] = float("nan")  # in place: its version counter moves
    raises_naming("carry.mean", kf.step, carry, y)
    carry, _ = kf.step(kf.init(CV, (2,)), y)
    nan = torch.full_like(carry.mean, float("nan"))
    raises_naming("carry.mean", kf.step, carry._replace(mean=nan), y)
    carry, _ = kf.step(carry, y)
    kf.step(carry, y)  # unchanged: still fine
    # a carry vouched for by one object is validated in full by another
    pf8, pf5 = df.ParticleFilter(8), df.ParticleFilter(5)
    carry8, _ = pf8.step(pf8.init(CV, (2,), _gens()), y)
    raises_naming("particles", pf5.step, carry8, y)


@pytest.mark.parametrize("name", ["kf", "pf", "gated"])
def test_the_online_step_runs_in_inference_mode(name):
    """Inference tensors keep no version counter: the step vouches for them by identity,
    and gives the numbers of a step outside inference mode."""
    ys, us = _data((2,), 4, seed=2)
    est = BUILDERS[name]()
    with torch.inference_mode():
        a = est.init(CV, (2,), _gens(3))
        for t in range(4):
            a, out_a = est.step(a, ys[:, t], us[:, t])
    b = est.init(CV, (2,), _gens(3))
    for t in range(4):
        b, out_b = est.step(b, ys[:, t], us[:, t])
    torch.testing.assert_close(out_a.mean, out_b.mean, rtol=0, atol=0)


# ------------------------------------------------------------------------ import cycles


def _modules() -> list[str]:
    names = []
    for package in ("difffilter", "difffilter.fdi", "difffilter.models", "difffilter.train",
                    "difffilter.eval", "difffilter.eval.families"):  # fmt: skip
        path = importlib.import_module(package).__path__
        names += [package] + [f"{package}.{m.name}" for m in pkgutil.iter_modules(path)
                              if not m.ispkg]  # fmt: skip
    return sorted(set(names))


def test_every_module_imports_alone():
    """Each module imported first, in a fresh interpreter's module table (torch stays
    loaded): an import cycle fails whichever of its modules comes first."""
    script = (
        "import importlib, sys, torch, lightning\n"
        f"for name in {_modules()!r}:\n"
        "    for key in [k for k in sys.modules if k == 'difffilter' or k.startswith('difffilter.')]:\n"
        "        del sys.modules[key]\n"
        "    try:\n"
        "        importlib.import_module(name)\n"
        "    except Exception as exc:\n"
        "        print(f'{name}: {type(exc).__name__}: {exc}')\n"
    )
    run = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=600
    )
    assert run.returncode == 0, run.stderr[-2000:]
    assert run.stdout == "", run.stdout


def _swinging(x, u):
    dt = 0.05
    return torch.stack([x[..., 0] + dt * x[..., 1],
                        x[..., 1] - dt * 9.81 * torch.sin(x[..., 0]) + dt * u[..., 0]], -1)  # fmt: skip


def _sine_and_rate(x):
    return torch.stack([torch.sin(x[..., 0]), x[..., 1]], -1)


def test_one_ekf_object_steps_two_threads_carries_as_one_thread_does():
    """From a deployment trial: one ExtendedKalmanFilter, two threads, two carries and
    models with autodiff Jacobians failed ("invalid forward AD level", blamed on the model),
    or ended up to 0.85 posterior sd off without an error, or crashed the process: torch.func's
    forward-mode levels are the process's. One thread differentiates at a time now."""
    import threading

    F64 = torch.float64

    def model():
        return df.NonlinearGaussianModel(_swinging, _sine_and_rate, 1e-3 * torch.eye(2, dtype=F64),
                                         torch.diag(torch.tensor([0.01, 0.04], dtype=F64)),
                                         torch.tensor([0.3, 0.0], dtype=F64), 0.1 * torch.eye(2, dtype=F64),
                                         dim_u=1)  # fmt: skip

    models = [model(), model()]
    data = []
    for i, m in enumerate(models):
        g = torch.Generator().manual_seed(20 + i)
        us = 0.5 * torch.randn(120, 1, dtype=F64, generator=g)
        data.append((m.simulate(120, (), us=us, generator=g)[1], us))
    ekf = df.ExtendedKalmanFilter()

    def run(i, out, barrier=None):
        try:
            if barrier is not None:
                barrier.wait()
            with torch.no_grad():
                carry, means = ekf.init(models[i], ()), []
                for y, u in zip(*data[i]):
                    carry, step = ekf.step(carry, y, u)
                    means.append(step.mean)
            out[i] = torch.stack(means)
        except Exception as error:  # (reported below, with the thread's result)
            out[i] = error

    alone = {}
    run(0, alone)
    run(1, alone)
    for _ in range(3):
        out, barrier = {}, threading.Barrier(2)
        threads = [threading.Thread(target=run, args=(i, out, barrier)) for i in range(2)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        for i in range(2):
            assert not isinstance(out[i], Exception), out[i]
            assert torch.equal(out[i], alone[i])


@pytest.mark.parametrize("kind", ["kf", "ekf", "pf"])
def test_a_carry_whose_model_was_moved_to_another_dtype_is_named(kind):
    """From a deployment trial: after model.to(torch.float32) mid-stream the next step failed
    inside torch ("expected m1 and m2 to have the same dtype"); the step validates in full
    after any assignment to a model and names the carry that no longer fits it."""
    from conftest import online_pair

    F64 = torch.float64
    model, estimator, carry = online_pair(kind)
    carry, _ = estimator.step(carry, torch.ones(2, dtype=F64))
    model.to(torch.float32)
    for y in (torch.ones(2, dtype=F64), torch.ones(2)):
        with pytest.raises(ValueError, match=r"carry\.\w+ is torch.float64 on cpu and its model's "
                           r"tensors torch.float32 on cpu .*start a new carry with init"):  # fmt: skip
            estimator.step(carry, y)
    gen = torch.Generator().manual_seed(1)
    fresh = estimator.init(model, (), gen) if kind == "pf" else estimator.init(model, ())
    estimator.step(fresh, torch.ones(2))  # a new carry of the moved model steps


@pytest.mark.parametrize("kind", ["fixed_gain", "adaptive"])
def test_the_other_gaussian_filters_name_a_carry_their_moved_model_no_longer_fits(kind):
    """From a review: FixedGainFilter and AdaptiveKalmanFilter skipped the carry-against-model
    dtype check and failed inside torch after model.to(torch.float32)."""
    from difffilter.observers import FixedGainFilter

    F64 = torch.float64
    eye = torch.eye(2, dtype=F64)
    model = df.LinearGaussianModel(0.9 * eye, eye, 0.1 * eye, 0.2 * eye, torch.zeros(2, dtype=F64),
                                   eye, B=torch.ones(2, 1, dtype=F64))  # fmt: skip
    est = FixedGainFilter(0.5 * eye) if kind == "fixed_gain" else fdi.AdaptiveKalmanFilter()
    carry = est.init(model, ())
    u = torch.zeros(1, dtype=F64)
    carry, _ = est.step(carry, torch.ones(2, dtype=F64), u)
    model.to(torch.float32)
    with pytest.raises(ValueError, match=r"carry\.mean is torch.float64 on cpu and its model's"):
        est.step(carry, torch.ones(2), u.float())
