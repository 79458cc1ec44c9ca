"""What an API fuzzing trial found, each checked: inputs that gave silently wrong numbers
now raise or compute the right ones, and inputs that crashed deep in torch (a bare
RuntimeError, IndexError or AttributeError) get an error naming the argument."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import difffilter as df
from difffilter import fdi, metrics
from difffilter.extended import SigmaPoints
from difffilter.loop import closed_loop
from difffilter.noise import UniformBox

F64 = torch.float64
EYE = torch.eye(2, dtype=F64)
H = torch.tensor([[1.0, 0.0]], dtype=F64)


def _model(F=None, Q=None, B=None):
    F = 0.9 * EYE if F is None else F
    Q = 0.1 * EYE if Q is None else Q
    return df.LinearGaussianModel(F, H, Q, torch.eye(1, dtype=F64), torch.zeros(2, dtype=F64),
                                  EYE, B=B)  # fmt: skip


def _per_run_model():
    g = torch.Generator().manual_seed(0)
    return _model(F=0.9 * EYE + 0.05 * torch.randn(3, 2, 2, generator=g, dtype=F64))


def _data(*shape, seed=0):
    return torch.randn(*shape, generator=torch.Generator().manual_seed(seed), dtype=F64)


# -- silently wrong numbers before ------------------------------------------------------


def test_a_replacement_density_of_another_dimension_is_refused():
    """A 3-entry box on a 1-sensor model broadcast the measurement to 3 entries: attack
    probability 0.081 where the right box gives 0.263."""
    ys = _data(4, 10, 1)
    box = UniformBox(-torch.ones(3, dtype=F64), torch.ones(3, dtype=F64))
    with pytest.raises(ValueError, match=r"shape \[\.\.\., 3\]"):
        box.log_prob(torch.zeros(1, dtype=F64))
    lik = fdi.DeceptionMixtureLikelihood(0.2, fdi.ReplacementDeception(box))
    with pytest.raises(ValueError, match="dimension 3|shape"):
        fdi.mixture_likelihood_particle_filter(_model(), ys, num_particles=50, likelihood=lik)


def test_a_replacement_density_of_another_dtype_is_named():
    """A float64 box on float32 measurements failed in the particle filter, whose error
    blamed the likelihood's dtype (a fuzzing trial of a loaded checkpoint's deception=)."""
    box = UniformBox(-torch.ones(1, dtype=F64), torch.ones(1, dtype=F64))
    lik = fdi.DeceptionMixtureLikelihood(0.2, fdi.ReplacementDeception(box))
    model = _model().to(torch.float32)
    with pytest.raises(ValueError, match=r"deception density \(UniformBox\) returned log-densities "
                       r"of torch\.float64 for measurements of torch\.float32"):  # fmt: skip
        fdi.mixture_likelihood_particle_filter(
            model, _data(4, 10, 1).float(), num_particles=50, likelihood=lik
        )
    # in the measurements' dtype it runs
    box32 = UniformBox(-torch.ones(1), torch.ones(1))
    lik = fdi.DeceptionMixtureLikelihood(0.2, fdi.ReplacementDeception(box32))
    out = fdi.mixture_likelihood_particle_filter(
        model, _data(4, 10, 1).float(), num_particles=50, likelihood=lik,
        generator=torch.Generator().manual_seed(0),
    )  # fmt: skip
    assert out.means.dtype == torch.float32 and torch.isfinite(out.means).all()

    # a density that holds float64 and answers in the caller's dtype runs (a review)
    class Casting(UniformBox):
        def log_prob(self, y, mask=None):
            return super().log_prob(y.double(), mask=mask).to(y.dtype)

    lik = fdi.DeceptionMixtureLikelihood(
        0.2, fdi.ReplacementDeception(Casting(-torch.ones(1, dtype=F64), torch.ones(1, dtype=F64)))
    )
    out = fdi.mixture_likelihood_particle_filter(
        model, _data(4, 10, 1).float(), num_particles=50, likelihood=lik,
        generator=torch.Generator().manual_seed(0),
    )  # fmt: skip
    assert out.means.dtype == torch.float32


def test_a_bias_deception_of_another_width_is_refused():
    ys = _data(4, 10, 1)
    lik = fdi.DeceptionMixtureLikelihood(0.2, fdi.BiasDeception(torch.zeros(3, dtype=F64)))
    with pytest.raises(ValueError, match=r"rho must have shape \[\.\.\., 1\]"):
        fdi.mixture_likelihood_particle_filter(_model(), ys, num_particles=50, likelihood=lik)


def test_the_adaptive_filters_initial_attack_is_checked():
    """attack0 = NaN gave NaN means and scores and no alarm, without a word."""
    model = _model(B=torch.tensor([[0.0], [0.1]], dtype=F64))
    ys = _data(3, 10, 1)
    with pytest.raises(ValueError, match="attack0 contains NaN"):
        fdi.adaptive_kalman_filter(model, ys, attack0=torch.tensor([float("nan")], dtype=F64))
    with pytest.raises(ValueError, match=r"attack0 must have shape \[\.\.\., 1\]"):
        fdi.adaptive_kalman_filter(model, ys, attack0=torch.zeros(3, dtype=F64))
    with pytest.raises(ValueError, match="attack_cov0 must be a finite number"):
        fdi.adaptive_kalman_filter(model, ys, attack_cov0=float("inf"))
    # a list is a vector like any other argument's
    listed = fdi.adaptive_kalman_filter(model, ys, attack0=[0.5])
    tensor = fdi.adaptive_kalman_filter(model, ys, attack0=torch.tensor([0.5], dtype=F64))
    torch.testing.assert_close(listed.means, tensor.means)


def test_nan_scores_are_refused_by_the_roc():
    g = torch.Generator().manual_seed(0)
    scores, labels = torch.randn(3, 17, generator=g), torch.rand(3, 17, generator=g) > 0.5
    scores[0, :5] = float("nan")
    with pytest.raises(ValueError, match="nan_as_lowest"):
        metrics.roc_auc(scores, labels)
    with pytest.raises(ValueError, match="nan_as_lowest"):
        metrics.roc_curve(scores, labels)
    # marked invalid, or mapped, they are fine
    valid = ~torch.isnan(scores)
    assert 0 <= metrics.roc_auc(scores, labels, valid) <= 1
    assert 0 <= metrics.roc_auc(metrics.nan_as_lowest(scores), labels) <= 1


# -- per-run models and unbatched measurements -------------------------------------------


def test_a_gated_filter_of_a_per_run_model_on_unbatched_measurements_windows_each_run():
    model, ys = _per_run_model(), _data(8, 1)
    det = fdi.ChiSquareDetector(1, 0.05, window=3)
    one = fdi.gated_gaussian_filter(model, ys, detector=det, filter=df.KalmanFilter())
    each = fdi.gated_gaussian_filter(model, ys.expand(3, 8, 1), detector=det,
                                     filter=df.KalmanFilter())  # fmt: skip
    torch.testing.assert_close(one.means, each.means)
    torch.testing.assert_close(one.detection.scores, each.detection.scores)


def test_an_online_carry_of_a_per_run_model_takes_one_measurement_per_run():
    model, kf = _per_run_model(), df.KalmanFilter()
    carry = kf.init(model, ())
    y = torch.tensor([0.7], dtype=F64)
    _, shared = kf.step(carry, y)
    _, per_run = kf.step(carry, y.expand(3, 1))
    torch.testing.assert_close(per_run.mean, shared.mean)
    assert per_run.mean.shape == (3, 2)


def test_model_parameters_of_disagreeing_batch_shapes_are_refused_at_construction():
    with pytest.raises(ValueError, match=r"F \(3,\).*Q \(4,\)"):
        _model(F=EYE.expand(3, 2, 2), Q=0.1 * EYE.expand(4, 2, 2))
    with pytest.raises(ValueError, match="batch shape"):
        df.NonlinearGaussianModel(lambda x: x, lambda x: x[..., :1], 0.1 * EYE.expand(3, 2, 2),
                                  torch.eye(1, dtype=F64).expand(4, 1, 1),
                                  torch.zeros(2, dtype=F64), EYE)  # fmt: skip
    _model(F=EYE.expand(3, 2, 2), Q=0.1 * EYE.expand(1, 2, 2))  # broadcasting sets are fine


@pytest.mark.parametrize("method", ["sequential", "parallel"])
def test_the_kalman_filter_on_no_runs_returns_empty_results(method):
    out = df.kalman_filter(_model(), torch.zeros(0, 6, 1, dtype=F64), method=method)
    assert out.means.shape == (0, 6, 2) and out.log_likelihood.shape == (0,)


def test_a_modified_pf_table_for_other_runs_is_named():
    ys = _data(12, 15, 1)
    det = fdi.poa_detector_for(_model(), gamma_min=2.0, p_l=0.2, num_particles=50)
    with pytest.raises(ValueError, match=r"gamma_hat's runs \(5,\)"):
        fdi.modified_particle_filter(_model(), ys, num_particles=50, detector=det,
                                     gamma_hat=torch.zeros(5, 15, 1, dtype=F64))  # fmt: skip


def test_a_particle_filter_started_from_a_state_of_other_runs_is_named():
    state = df.particle_init(_model(), 50, (3,), torch.Generator().manual_seed(0))
    with pytest.raises(ValueError, match=r"carry holds runs \(3,\).*\(2,\)"):
        df.particle_filter(_model(), _data(2, 6, 1), num_particles=50, initial_state=state)


# -- arguments -------------------------------------------------------------------------------


def test_simulate_checks_its_steps_and_inputs():
    model = _model()
    for steps in (0, -1):
        with pytest.raises(ValueError, match="num_steps must be a positive integer"):
            model.simulate(steps, (3,))
    with pytest.raises(ValueError, match="no input"):  # it was silently ignored
        model.simulate(5, (3,), us=torch.ones(3, 5, 1, dtype=F64))
    with_input = _model(B=torch.tensor([[0.0], [0.1]], dtype=F64))
    with pytest.raises(ValueError, match="T = 5 steps"):
        with_input.simulate(5, (3,), us=torch.ones(3, 4, 1, dtype=F64))


def test_non_finite_or_non_numeric_settings_are_named():
    for kwargs in ({"beta": float("nan")}, {"kappa": float("inf")}, {"alpha": float("inf")}):
        with pytest.raises(ValueError, match=next(iter(kwargs))):
            SigmaPoints(**kwargs)
    with pytest.raises(TypeError, match="alpha must be a real number"):
        SigmaPoints(alpha="1")
    with pytest.raises(ValueError, match="false_alarm_rate"):
        fdi.ChiSquareDetector(1, "0.01")


def test_the_fused_modified_pf_names_nan_data_and_takes_numpy_counts():
    model, ys = _model(), _data(4, 10, 1)
    pf = fdi.FusedModifiedPF(model, num_particles=np.int64(50), eta=1.0, zeta=0.2)
    assert pf.n == 50 and type(pf.n) is int
    with pytest.raises(ValueError, match="ys contains NaN"):
        pf.run(torch.full_like(ys, float("nan")), torch.zeros_like(ys),
               generator=torch.Generator().manual_seed(0))  # fmt: skip


def test_a_transition_of_another_dtype_is_named_at_construction():
    def f(x):  # a float64 model whose transition returns float32 (the EKF failed in torch)
        return torch.stack([x[..., 0] + 0.1 * x[..., 1], x[..., 1]], -1).float()

    with pytest.raises(ValueError, match="transition returns torch.float32"):
        df.NonlinearGaussianModel(f, lambda x: x, 0.1 * EYE, 0.1 * EYE,
                                  torch.zeros(2, dtype=F64), EYE)  # fmt: skip


def test_a_closed_loop_without_noise_is_named():
    with pytest.raises(TypeError, match="noise must be a DrawnNoise"):
        closed_loop(_model(), 5, noise=None, x0=torch.zeros(3, 2, dtype=F64),
                    estimator=df.KalmanFilter())  # fmt: skip


def test_metrics_of_mismatched_shapes_are_named():
    s, y = torch.randn(3, 17), torch.rand(3, 17) > 0.5
    with pytest.raises(ValueError, match=r"labels \(3, 5\)"):
        metrics.roc_auc(s, y[:, :5])
    with pytest.raises(ValueError, match=r"attacked \(3, 5\)"):
        metrics.detection_rates(s > 0, y[:, :5])
    with pytest.raises(ValueError, match=r"attacked \(3, 5\)"):
        metrics.detection_delay(s > 0, y[:, :5])
    with pytest.raises(ValueError, match="leading dimensions"):
        fdi.normalized_innovation_squared(torch.zeros(3, 5, 1, dtype=F64),
                                          torch.ones(4, 5, 1, 1, dtype=F64))  # fmt: skip
    # labels for every run at once still broadcast: the rates of the expanded labels
    assert metrics.detection_rates(s > 0, y[:1]) == metrics.detection_rates(
        s > 0, y[:1].expand(3, 17)
    )


# -- from a nonlinear-filtering trial ----------------------------------------------------


def test_a_model_of_one_noise_covariance_per_run_simulates_each_runs_noise():
    """Per-run Q, R ([B, d, d]) run in the Kalman filters; simulate raised a raw shape error."""
    Q = torch.tensor([1.0, 4.0, 9.0, 16.0], dtype=F64).view(4, 1, 1)
    R = torch.tensor([0.5, 1.0, 2.0, 3.0], dtype=F64).view(4, 1, 1)
    one = torch.eye(1, dtype=F64)
    model = df.LinearGaussianModel(0 * one, one, Q, R, torch.zeros(1, dtype=F64), one)
    xs, ys, _ = model.simulate(20000, (4,), generator=torch.Generator().manual_seed(0))
    # x_k = w_{k-1} (F = 0): the sample variances are Q and R per run (sd of each ~1 %)
    torch.testing.assert_close(xs[..., 0].var(1), Q.flatten(), rtol=0.05, atol=0)
    torch.testing.assert_close((ys - xs)[..., 0].var(1), R.flatten(), rtol=0.05, atol=0)
    with pytest.raises(ValueError, match=r"batch_shape \(3,\)"):
        model.simulate(10, (3,))


def test_the_ekf_names_a_jacobian_that_is_nan():
    """At the sensor's own position the range-bearing Jacobian is NaN: the message blamed
    the innovation covariance and training."""
    F = torch.tensor([[1, 0, 1, 0], [0, 1, 0, 1], [0, 0, 1, 0], [0, 0, 0, 1.0]], dtype=F64)

    def h(x):
        return torch.stack([torch.linalg.vector_norm(x[..., :2], dim=-1),
                            torch.atan2(x[..., 1], x[..., 0])], -1)  # fmt: skip

    model = df.NonlinearGaussianModel(lambda x: x @ F.T, h, 1e-2 * torch.eye(4, dtype=F64),
                                      torch.diag(torch.tensor([0.01, 0.001], dtype=F64)),
                                      torch.tensor([-1.0, 0, 1, 0], dtype=F64),
                                      1e-2 * torch.eye(4, dtype=F64))  # fmt: skip
    with pytest.raises(ValueError, match="observation Jacobian .* at step 1 holds NaN"):
        df.extended_kalman_filter(model, torch.tensor([[0.5, 0.1], [0.6, 0.2]], dtype=F64))


def test_a_sweep_of_priors_simulates_one_run_per_parameter_set():
    """A prior of 4 covariances simulated 16 runs for batch_shape (4,) (sample prepends its
    shape to the batch); a model of 4 noise covariances simulated with batch_shape ()
    refused. Both give the model's 4 runs, as the filters read such a model."""
    one = torch.eye(1, dtype=F64)
    P0 = torch.tensor([1.0, 2.0, 3.0, 4.0], dtype=F64).view(4, 1, 1)
    model = df.LinearGaussianModel(0.9 * one, one, one, one, torch.zeros(1, dtype=F64), P0)
    for batch in ((4,), ()):
        xs, ys, x0 = model.simulate(5, batch, generator=torch.Generator().manual_seed(0))
        assert xs.shape == (4, 5, 1) and ys.shape == (4, 5, 1) and x0.shape == (4, 1)
    x0 = model.simulate(1, (100000, 4), generator=torch.Generator().manual_seed(1))[2]
    torch.testing.assert_close(x0.var(0)[:, 0], P0.flatten(), rtol=0.03, atol=0)
    Q = torch.tensor([1.0, 4.0, 9.0, 16.0], dtype=F64).view(4, 1, 1)
    noisy = df.LinearGaussianModel(0 * one, one, Q, one, torch.zeros(1, dtype=F64), one)
    assert noisy.simulate(3, ())[0].shape == (4, 3, 1)


def test_what_takes_one_model_refuses_a_sweep_clearly_and_the_adaptive_kf_takes_one():
    """From a parameter-sweep trial: the adaptive particle filter, cusum_detector_for and
    poa_detector_for failed on a per-run model with raw torch errors (or pooled one
    threshold over every model); the adaptive KF failed on one shared sequence with a
    per-run prior, which the other Gaussian filters take."""
    model = _per_run_model()
    with pytest.raises(ValueError, match="cusum_detector_for takes one model for all runs"):
        fdi.cusum_detector_for(model, false_alarm_rate=0.01, runs=3, steps=10)
    with pytest.raises(ValueError, match="poa_detector_for takes one model for all runs"):
        fdi.poa_detector_for(model, gamma_min=2.0, p_l=0.2, num_particles=50)
    with_input = _model(F=model.F, B=torch.tensor([[0.0], [0.1]], dtype=F64))
    with pytest.raises(ValueError, match="the adaptive particle filter takes one model"):
        fdi.AdaptiveParticleFilter(20).init(with_input, (3,))
    P0 = EYE * torch.tensor([1.0, 2.0, 3.0], dtype=F64).view(3, 1, 1)
    swept = df.LinearGaussianModel(0.9 * EYE, H, 0.1 * EYE, torch.eye(1, dtype=F64),
                                   torch.zeros(2, dtype=F64), P0,
                                   B=torch.tensor([[0.0], [0.1]], dtype=F64))  # fmt: skip
    ys = _data(10, 1)
    shared = fdi.adaptive_kalman_filter(swept, ys)
    each = fdi.adaptive_kalman_filter(swept, ys.expand(3, 10, 1))
    torch.testing.assert_close(shared.means, each.means)


def test_a_covariance_override_of_one_element_batch_is_one_model_and_init_batches_are_named():
    """A second review: an override returning [1, d, d] was refused as a sweep; the adaptive
    KF's init with runs that do not fit the model's sets raised a raw torch error."""

    class OneSet(df.LinearGaussianModel):
        time_varying = True

        def process_cov(self, k):
            return (0.1 * EYE).unsqueeze(0)

    model = OneSet(0.9 * EYE, H, 0.1 * EYE, torch.eye(1, dtype=F64), torch.zeros(2, dtype=F64),
                   EYE)  # fmt: skip
    out = df.particle_filter(model, _data(3, 6, 1), num_particles=50,
                             generator=torch.Generator().manual_seed(0))  # fmt: skip
    plain = df.particle_filter(_model(), _data(3, 6, 1), num_particles=50,
                               generator=torch.Generator().manual_seed(0))  # fmt: skip
    torch.testing.assert_close(out.log_likelihood, plain.log_likelihood)  # the same one model
    swept = df.LinearGaussianModel(0.9 * EYE, H, 0.1 * EYE, torch.eye(1, dtype=F64),
                                   torch.zeros(2, dtype=F64), EYE.expand(3, 2, 2),
                                   B=torch.tensor([[0.0], [0.1]], dtype=F64))  # fmt: skip
    with pytest.raises(ValueError, match=r"batch_shape \(4,\) does not broadcast"):
        fdi.AdaptiveKalmanFilter().init(swept, (4,))


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"attack_cov0": -1.0}, "attack_cov0 must be a finite number >= 0"),
        ({"attack_cov0": float("nan")}, "attack_cov0 must be a finite number >= 0"),
        ({"false_alarm_rate": 2.0}, r"false_alarm_rate must be a false-alarm rate in \(0, 1\)"),
        ({"false_alarm_rate": float("nan")}, "false_alarm_rate must be a false-alarm rate"),
        ({"num_particles": 0}, r"num_particles must be a positive integer \(>= 1\)"),
        ({"num_particles": 2.5}, r"num_particles must be a positive integer \(>= 1\)"),
    ],
)
def test_the_adaptive_particle_filter_checks_its_arguments_as_the_adaptive_kf(kwargs, message):
    """From a fuzzing trial of the constructors: ``AdaptiveParticleFilter`` took a negative
    ``ω`` and ran, its ``Ŝ`` negative from then on; a NaN ``ω`` failed at the first step
    as a bad carry; a bad rate failed only at the first step, naming no argument; a count of
    0 or 2.5 with a raw torch error. It checks them at construction now, as
    ``AdaptiveKalmanFilter`` does, and so does ``adaptive_particle_init``."""
    from difffilter.fdi.mdpf import adaptive_particle_init

    with pytest.raises(ValueError, match=message):
        fdi.AdaptiveParticleFilter(**{"num_particles": 20, **kwargs})
    model = df.LinearGaussianModel(0.9 * EYE, H, 0.1 * EYE, torch.eye(1, dtype=F64),
                                   torch.zeros(2, dtype=F64), EYE,
                                   B=torch.tensor([[0.0], [0.1]], dtype=F64))  # fmt: skip
    init_kwargs = {k: v for k, v in kwargs.items() if k != "false_alarm_rate"}
    if init_kwargs:
        with pytest.raises(ValueError, match=message):
            adaptive_particle_init(model, **{"num_particles": 20, **init_kwargs})
    # ω = 0 is the adaptive KF's boundary too: it runs
    out = fdi.adaptive_particle_filter(model, torch.zeros(2, 5, 1, dtype=F64),
                                       torch.zeros(2, 5, 1, dtype=F64), num_particles=20,
                                       attack_cov0=0.0, generator=torch.Generator().manual_seed(0))  # fmt: skip
    assert bool(torch.isfinite(out.means).all())


@pytest.mark.parametrize(
    ("make", "message"),
    [
        ("four_tank_g_nan", r"FourTankParameters.g must be a finite number > 0"),
        ("four_tank_g_negative", r"FourTankParameters.g must be a finite number > 0"),
        ("four_tank_outlet_negative", r"FourTankParameters.a\[3\] must be a finite number > 0"),
        ("four_tank_three_areas", r"FourTankParameters.A must be 4 finite numbers > 0"),
        (
            "four_tank_valve_at_one",
            r"FourTankParameters.gamma must be two valve splits in \(0, 1\)",
        ),
        ("lfc_tie_nan", "tie_stiffness must be a finite number >= 0"),
        ("lfc_inertia_nan", "inertia must hold 2 finite positive values"),
        ("lfc_damping_inf", "damping must hold 2 finite values"),
        ("robot_dt_nan", "dt must be a finite number > 0"),
        ("robot_dt_negative", "dt must be a finite number > 0"),
        ("tracking_dt_zero", "dt must be a finite number > 0"),
        ("tracking_sigma_omega_negative", "sigma_omega must be a finite number > 0"),
        ("tracking_kappa_nan", "kappa must be a finite number >= 0"),
        ("tracking_kappa_above_one", r"kappa \(the glint probability\) must be in \[0, 1\]"),
        ("glint_weights_negative", "weights must be finite, non-negative and sum to 1"),
        ("glint_variance_nan", "variances must be finite and positive"),
        ("network_scale_inf", "attack_scale must be a finite number > 0"),
        ("network_init_scale_inf", "init_scale must be a finite number > 0"),
    ],
)
def test_the_scenario_plants_refuse_constants_that_built_a_broken_model(make, message):
    """From a fuzzing trial of the scenario packages' constructors: each of these had built
    (a NaN ``g`` failed later as "loc contains NaN", a negative one as "clamp is not
    supported for complex types"; a NaN robot ``dt`` simulated NaN and a negative one ran;
    the tracking model's κ = NaN or −1 failed in a draw as torch's "invalid multinomial
    distribution", a zero ``dt`` or ``σ_ω`` as a raw Cholesky error; a NaN LFC constant
    built NaN matrices; an infinite network scale built). Each is refused at construction,
    naming the field."""
    from difffilter.models.four_tank import FourTankParameters
    from difffilter.models.lfc import LFCParameters
    from difffilter.models.neural_estimator import NeuralFDIEstimator
    from difffilter.models.robot import RobotModel
    from difffilter.models.tracking import GlintNoise, TrackingModel

    nan, inf = float("nan"), float("inf")
    makers = {
        "four_tank_g_nan": lambda: FourTankParameters(g=nan),
        "four_tank_g_negative": lambda: FourTankParameters(g=-981.0),
        "four_tank_outlet_negative": lambda: FourTankParameters(a=(0.071, 0.057, 0.071, -0.057)),
        "four_tank_three_areas": lambda: FourTankParameters(A=(28.0, 32.0, 28.0)),
        "four_tank_valve_at_one": lambda: FourTankParameters(gamma=(0.7, 1.0)),
        "lfc_tie_nan": lambda: LFCParameters(tie_stiffness=nan),
        "lfc_inertia_nan": lambda: LFCParameters(inertia=(nan, 12.0)),
        "lfc_damping_inf": lambda: LFCParameters(damping=(1.0, inf)),
        "robot_dt_nan": lambda: RobotModel(dt=nan),
        "robot_dt_negative": lambda: RobotModel(dt=-1.0),
        "tracking_dt_zero": lambda: TrackingModel(dt=0.0),
        "tracking_sigma_omega_negative": lambda: TrackingModel(sigma_omega=-0.055),
        "tracking_kappa_nan": lambda: TrackingModel(kappa=nan),
        "tracking_kappa_above_one": lambda: TrackingModel(kappa=1.5),
        "glint_weights_negative": lambda: GlintNoise([2.0, -1.0], [[4.0, 1e-3], [25.0, 1e-3]], 2),
        "glint_variance_nan": lambda: GlintNoise([0.8, 0.2], [[nan, 1e-3], [25.0, 1e-3]], 2),
        "network_scale_inf": lambda: NeuralFDIEstimator(attack_scale=inf),
        "network_init_scale_inf": lambda: NeuralFDIEstimator(init_scale=inf),
    }
    with pytest.raises(ValueError, match=message):
        makers[make]()


def test_the_scenario_plants_keep_their_boundary_constants():
    """The checks above leave the legal ends alone: κ = 0 and 1 (no glint, all glint), two
    LFC areas without a tie line, integer constants of the tank (read as floats)."""
    from difffilter.models.four_tank import FourTankParameters
    from difffilter.models.lfc import LFCParameters
    from difffilter.models.tracking import TrackingModel

    assert TrackingModel(kappa=0.0).measurement_noise.weights.tolist() == [1.0, 0.0]
    assert TrackingModel(kappa=1).measurement_noise.weights.tolist() == [0.0, 1.0]
    assert LFCParameters(tie_stiffness=0.0).tie_stiffness == 0.0
    tank = FourTankParameters(A=(28, 32, 28, 32), g=981)
    assert tank.A == (28.0, 32.0, 28.0, 32.0) and tank.g == 981.0
    assert tank.fixed_point() == FourTankParameters().fixed_point()


def test_a_learnable_tracking_sigma_omega_keeps_its_gradient():
    """A review: the check of ``sigma_omega`` had read it as a float, and a learnable one
    lost its gradient (the process noise no longer required one)."""
    from difffilter.models.tracking import TrackingModel

    sigma = torch.tensor(0.055, dtype=F64, requires_grad=True)
    import warnings

    with warnings.catch_warnings():  # (torch's, on the fast path's floats: as before)
        warnings.simplefilter("ignore", UserWarning)
        model = TrackingModel(sigma_omega=sigma)
    assert model.process_noise.cov.requires_grad
