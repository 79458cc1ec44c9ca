"""The generic estimators: they run on any scenario whose model fits them.

The library's filters as they are (``kf`` for a linear model, ``ekf``, ``ukf``,
``bootstrap_pf``, ``kalman_proposal_pf``: state estimates, no detection); KF/EKF/UKF
gated by a χ² test or by CUSUM (τ calibrated on attack-free runs), the bootstrap PF with
the probability-of-attack detector (and its attack-free reference), the modified PF with
the oracle or an estimated attack, and the PF with the deception mixture likelihood.
Detector thresholds come from the model (:meth:`SuiteContext.poa_detector`,
:meth:`SuiteContext.cusum`), so a new plant needs no paper-specific arithmetic.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable

import torch

import difffilter as df
from difffilter import fdi
from difffilter.attack import Channel
from difffilter.estimator import EstimatorOutput
from difffilter.expected_input import ExpectedInputKalmanFilter
from difffilter.extended import ExtendedKalmanFilter, UnscentedKalmanFilter
from difffilter.kalman import KalmanFilter
from difffilter.noise import UniformBox
from difffilter.particle import KalmanProposal

from .attacks import SensorBias
from .estimators import Run, SuiteContext, register
from .needs import (
    ASSUMES_DECEPTION_DENSITY,
    ASSUMES_SENSOR_ATTACK,
    ATTACK_FREE_MEASUREMENTS,
    LINEAR_MODEL,
    SENSOR_ATTACK,
    TRANSITION_IS_PROCESS_NOISE,
    UNACKNOWLEDGED_INPUT_LOSS,
)
from .schedules import BurstLoss

__all__ = [
    "GAUSSIAN_FILTERS",
    "oracle_attack",
    "gated_estimator",
    "meets_adaptive_attack",
    "modified_pf",
    "deception_of",
    "expected_input_filter",
    "default_estimators",
    "DEFAULT_SUITE",
]


def _plain(run_filter):
    """A factory of ``run_filter(ctx, traj)``'s means and covariances, without detection."""

    def factory(ctx: SuiteContext) -> Run:
        def run(tr):
            res = run_filter(ctx, tr)
            return EstimatorOutput(res.means, res.covs)

        return run

    return factory


for _name, _filter in (("kf", df.kalman_filter), ("ekf", df.extended_kalman_filter),
                       ("ukf", df.unscented_kalman_filter)):  # fmt: skip
    register(
        _name,
        f"the library's {_name.upper()}, no attack handling (a linear model for kf)",
        needs=(LINEAR_MODEL,) if _name == "kf" else (),
    )(_plain(lambda ctx, tr, f=_filter: f(ctx.model, tr.y_recv, tr.us, mask=tr.mask)))
for _name, _proposal in (("bootstrap_pf", None), ("kalman_proposal_pf", KalmanProposal())):
    register(_name, f"the library's particle filter, {_name[:-3].replace('_', ' ')} proposal",
             needs=(TRANSITION_IS_PROCESS_NOISE,) if _proposal else ())(
        _plain(lambda ctx, tr, p=_proposal: df.particle_filter(
            ctx.model, tr.y_recv, tr.us, mask=tr.mask, **({"proposal": p} if p else {}),
            **ctx.particle_kwargs(len(tr.y_recv))))
    )  # fmt: skip


#: The library's Gaussian filters by the names configs use (the gated filters here, the
#: learned estimator): names are translated to objects here, once.
GAUSSIAN_FILTERS = {
    "kf": KalmanFilter(),
    "ekf": ExtendedKalmanFilter(),
    "ukf": UnscentedKalmanFilter(),
}


def _gated(kind: str, detector: Callable):
    """A factory of the ``kind`` filter gated by ``detector(ctx, filter)``: on the study's
    trajectories, or, where an adaptive attack meets it in a closed-loop scenario
    (:func:`meets_adaptive_attack`), in a loop of its own (``scenario.loop``): there the
    attack reads this filter's outputs, not those of the loop the trajectories came from."""
    filt = GAUSSIAN_FILTERS[kind]

    def factory(ctx: SuiteContext) -> Run:
        return _gated_run(ctx, filt, detector(ctx, filt))

    return factory


def _gated_run(ctx: SuiteContext, filt, det) -> Run:
    """``filt`` gated by ``det`` on the study's trajectories, or in a loop of its own where an
    adaptive attack meets it (:func:`_gated`)."""
    if meets_adaptive_attack(ctx.scenario):
        step = fdi.GatedFilter(det, filt)
        return lambda tr: ctx.scenario.loop(step, tr.info)
    return lambda tr: fdi.gated_gaussian_filter(
        ctx.model, tr.y_recv, tr.us, mask=tr.mask, detector=det, filter=filt
    )


def meets_adaptive_attack(scenario) -> bool:
    """The attack of ``scenario`` reads the estimator's output (``reads_view``) and the
    scenario is a closed loop, which runs an estimator that has a step object in a loop of
    its own (:meth:`~difffilter.models.scenario.Scenario.loop`): an estimator scored on the
    study's shared trajectories would be judged against an attack that adapted to another
    estimator (:func:`difffilter.eval.suite.run_suite` skips those)."""
    attack = scenario.simulated_attack()
    return bool(scenario.closed_loop and getattr(attack, "reads_view", False))


def _chi_square(ctx: SuiteContext, filt) -> fdi.ChiSquareDetector:
    return fdi.ChiSquareDetector(ctx.model.dim_y, ctx.scenario.false_alarm_rate)


def _cusum(ctx: SuiteContext, filt) -> fdi.CusumDetector:
    return ctx.cusum(filt)  # τ calibrated on the scenario's attack-free runs


#: The gated Gaussian filters by registry name: ``(filter kind, detector builder)``.
GATED: dict[str, tuple[str, Callable]] = {}

for _kind, _label in (("kf", "KF"), ("ekf", "EKF"), ("ukf", "UKF")):
    GATED[f"chi_square_{_kind}"] = (_kind, _chi_square)
    GATED[f"cusum_{_kind}"] = (_kind, _cusum)
    _needs = (LINEAR_MODEL,) if _kind == "kf" else ()
    register(f"chi_square_{_kind}", f"{_label} gated by a χ² test on its innovations",
             needs=_needs)(_gated(_kind, _chi_square))  # fmt: skip
    register(f"cusum_{_kind}", f"{_label} gated by CUSUM on its innovations (τ calibrated)",
             needs=_needs)(_gated(_kind, _cusum))  # fmt: skip


def expected_input_filter(scenario, model) -> ExpectedInputKalmanFilter:
    """The UDP-like Kalman filter of ``scenario``'s input loss on ``model``: arrival rate
    ``1 −`` its schedule's loss rate, one packet for
    every actuator or one per actuator as the schedule's ``packets`` say, and the
    scenario's ``on_loss``. ``ValueError`` with the reason where there is no such filter:
    no input loss, acknowledged packets (the Kalman filter on the acknowledged inputs is
    then the optimal filter), a schedule without a rate (a round robin), losses in bursts
    (the filter takes the arrivals independent) or packets that group some actuators but
    not all (a nonlinear model: the registry's LINEAR_MODEL need, and the filter's init)."""
    loss = scenario.input_loss_schedule()
    if loss is None:
        raise ValueError("estimates lost input packets, and this scenario loses none")
    if loss.acknowledged:
        raise ValueError(
            "estimates the inputs of unacknowledged (UDP-like) packets; this scenario's are "
            "acknowledged, where the Kalman filter on the acknowledged inputs is optimal"
        )
    if isinstance(loss.schedule, BurstLoss):
        raise ValueError(
            "takes the arrivals independent from step to step, and this scenario loses its "
            "input packets in bursts (the filter's variance is then too small: NEES 3.5–37 "
            "for dx = 2 in a review)"
        )
    rate = getattr(loss.schedule, "rate", None)
    if isinstance(rate, bool) or not isinstance(rate, numbers.Real):
        raise ValueError(
            "needs a random arrival rate (packet_loss); this scenario's input "
            f"packets follow a {type(loss.schedule).__name__}"
        )
    packets = getattr(loss.schedule, "packets", None)
    if packets is None or all(len(p) == 1 for p in packets):
        independent = model.dim_u > 1
    elif len(packets) == 1:
        independent = False
    else:
        raise ValueError(
            f"models one packet for every actuator or one per actuator; this scenario's "
            f"input packets are {packets}"
        )
    return ExpectedInputKalmanFilter(1.0 - float(rate), independent=independent,
                                     on_loss=loss.on_loss)  # fmt: skip


def _expected_input(detector: Callable):
    """A factory of the scenario's :func:`expected_input_filter` gated by
    ``detector(ctx, filter)`` (as :func:`_gated`)."""

    def factory(ctx: SuiteContext) -> Run:
        filt = expected_input_filter(ctx.scenario, ctx.model)
        return _gated_run(ctx, filt, detector(ctx, filt))

    return factory


_UDP_NEEDS = (LINEAR_MODEL, UNACKNOWLEDGED_INPUT_LOSS)
register("udp_kf", "UDP-like KF: the expected input and its variance (input loss unacknowledged)",
         needs=_UDP_NEEDS)(_plain(lambda ctx, tr: df.open_loop(
             expected_input_filter(ctx.scenario, ctx.model), ctx.model, tr.y_recv, tr.us,
             mask=tr.mask)))  # fmt: skip
register("chi_square_udp_kf", "UDP-like KF gated by a χ² test on its innovations",
         needs=_UDP_NEEDS)(_expected_input(_chi_square))  # fmt: skip
register("cusum_udp_kf", "UDP-like KF gated by CUSUM on its innovations (τ calibrated)",
         needs=_UDP_NEEDS)(_expected_input(_cusum))  # fmt: skip


def gated_estimator(ctx: SuiteContext, name: str) -> fdi.GatedFilter:
    """The step object of the registered gated filter ``name`` (``chi_square_ekf``, …): what
    an attacker differentiates through (:mod:`difffilter.stealthy`)."""
    if name not in GATED:
        raise ValueError(f"{name!r} is not a gated Gaussian filter; valid: {', '.join(GATED)}")
    kind, detector = GATED[name]
    filt = GAUSSIAN_FILTERS[kind]
    return fdi.GatedFilter(detector(ctx, filt), filt)


def _poa_pf(ctx: SuiteContext, clean: bool) -> Run:
    det = ctx.poa_detector()

    def run(tr):
        ys = tr.y_true if clean else tr.y_recv
        return fdi.particle_filter_poa(
            ctx.model, ys, tr.us, mask=tr.mask, detector=det, **ctx.particle_kwargs(len(ys))
        )

    return run


@register("normal_pf", "bootstrap PF on ỹ with the probability-of-attack (PoA) detector")
def _normal_pf(ctx: SuiteContext) -> Run:
    return _poa_pf(ctx, clean=False)


@register(
    "normal_pf_attack_free",
    "bootstrap PF + PoA on the true y (the attack-free reference)",
    clean_input=True,
    reference=True,
    needs=(ATTACK_FREE_MEASUREMENTS,),
)
def _normal_pf_attack_free(ctx: SuiteContext) -> Run:
    return _poa_pf(ctx, clean=True)


def oracle_attack(ctx: SuiteContext, tr, noise_var: float | None = None):
    """``γ̂ = γ + e``: the attack values with ``e ~ N(0, var I)`` from stream ``"gamma_noise"``
    (``var`` = the scenario's ``gamma_hat_noise_var`` option unless given; 0 → exact).

    ``γ`` is the sensor attack's value at every step (injected or not) of a run it attacks
    at some step, zero in a run it never does (an attack on a ``share`` of the runs: the
    oracle knows which, and its values there had been subtracted as well, the oracle's
    state error 7× the attack-free reference's on those runs, a trial); for a replacement
    attack (replay) it is what changed at the receiver, ``ỹ − y``; attack-free or on the
    actuator, zero."""
    values, channel = tr.info["attack_values"], tr.info.get("attack_channel", Channel.SENSOR)
    if channel is not Channel.SENSOR:  # what reached the receiver: ỹ − y (zero attack-free)
        # zeros, not ỹ·0: a lost step's NaN must not reach the oracle's γ̂
        replaced = channel is Channel.REPLACEMENT
        values = tr.y_recv - tr.y_true if replaced else torch.zeros_like(tr.y_recv)
    elif "attack_flags" in tr.info:  # the runs the attack never flags (its own flags)
        own = tr.info["attack_flags"]
        runs = values.shape[:-2]
        attacked = own.reshape(*runs, -1).any(-1)
        values = torch.where(attacked[..., None, None], values, torch.zeros_like(values))
    var = ctx.option("gamma_hat_noise_var", 0.0) if noise_var is None else noise_var
    if var == 0:
        return values
    gen = ctx.streams("gamma_noise")
    noise = torch.randn(values.shape, generator=gen, dtype=values.dtype)
    return values + math.sqrt(var) * noise


def modified_pf(ctx: SuiteContext, gamma_hat, **kwargs) -> Run:
    """The modified PF of Table 2 with ``gamma_hat(tr)`` (a tensor or an estimator)."""
    det = kwargs.pop("detector", None) or ctx.poa_detector()

    def run(tr):
        return fdi.modified_particle_filter(
            ctx.model, tr.y_recv, tr.us, mask=tr.mask, detector=det,
            gamma_hat=gamma_hat(tr), **ctx.particle_kwargs(len(tr.y_recv)), **kwargs,
        )  # fmt: skip

    return run


@register(
    "modified_pf",
    "modified PF (Table 2) with the oracle γ̂ (the paper's tables)",
    needs=(SENSOR_ATTACK,),
    oracle=True,
)
def _modified_pf(ctx: SuiteContext) -> Run:
    return modified_pf(ctx, lambda tr: oracle_attack(ctx, tr))


@register(
    "modified_pf_est",
    "modified PF with γ̂ from a Kalman filter on the attack model (eq. 4)",
    needs=(ASSUMES_SENSOR_ATTACK,),
)
def _modified_pf_est(ctx: SuiteContext) -> Run:
    tau = _eq4_tau(ctx.scenario.attack_model())
    return modified_pf(
        ctx, lambda tr: fdi.BiasAttackEstimator(ctx.model.dim_y, tau, dtype=ctx.dtype)
    )


def _eq4_tau(attack) -> float:
    """τ of eq. (4) for ``modified_pf_est``: the paper's attack's (:class:`SensorBias`),
    else 0.9 [DEF]. Another attack's ``tau`` is its own (a trial: the docs' ``Drift`` with a
    time constant of 20 stopped every study, and one of 0.5 ran as τ)."""
    return float(attack.tau) if isinstance(attack, SensorBias) else 0.9


def deception_of(attack, dtype: torch.dtype):
    """``(p_a, rate)``: the attacked-measurement density of a scenario's attack for the
    mixture likelihood (a bias attack's additive ``γ̄``, or a replacement attack's box
    ``U(low, high)``) and its per-step rate."""
    if hasattr(attack, "gamma_bar"):
        return fdi.BiasDeception(torch.tensor(attack.gamma_bar, dtype=dtype)), attack.p_l
    if hasattr(attack, "low"):
        box = UniformBox(
            torch.tensor(attack.low, dtype=dtype), torch.tensor(attack.high, dtype=dtype)
        )
        return fdi.ReplacementDeception(box), attack.rate
    raise ValueError(f"no deception density for an attack of type {type(attack).__name__}")


@register(
    "mixture_likelihood_pf",
    "PF with the deception mixture likelihood (RRP method)",
    needs=(ASSUMES_DECEPTION_DENSITY,),
)
def _mixture_pf(ctx: SuiteContext) -> Run:
    likelihood = fdi.DeceptionMixtureLikelihood(
        *reversed(deception_of(ctx.scenario.attack_model(), ctx.dtype))
    )
    return lambda tr: fdi.mixture_likelihood_particle_filter(
        ctx.model, tr.y_recv, tr.us, mask=tr.mask, likelihood=likelihood,
        **ctx.particle_kwargs(len(tr.y_recv)),
    )  # fmt: skip


#: The default suite of a scenario that does not list its estimators: every generic
#: estimator, and the learned ones (they run with a checkpoint trained on the scenario's
#: family, ``--ckpt``). Those whose needs a scenario does not meet are skipped with the
#: reason (:mod:`difffilter.models.needs`).
DEFAULT_SUITE = (
    "normal_pf_attack_free", "normal_pf", "modified_pf", "modified_pf_est",
    "mixture_likelihood_pf", "chi_square_kf", "cusum_kf", "chi_square_udp_kf", "cusum_udp_kf",
    "chi_square_ekf", "cusum_ekf", "chi_square_ukf", "cusum_ukf", "pf_nn_grad",
    "gaussian_nn_grad",
)  # fmt: skip


def default_estimators(scenario, model=None) -> tuple[str, ...]:
    """The estimators of :data:`DEFAULT_SUITE` whose needs ``scenario`` meets (with its
    estimators' ``model``, by default ``scenario.system()``): the KF pair only for a
    linear model, the attack-free reference only where the true measurements are
    attack-free, … The learned ones are among them; they still need a checkpoint."""
    from .estimators import get

    model = scenario.system() if model is None else model
    return tuple(n for n in DEFAULT_SUITE if get(n).unmet(scenario, model) is None)
