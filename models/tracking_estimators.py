"""The tracking family's estimators (RRP particle filter with deception attacks, Song et al.).

Each is a composition of the shared particle driver (:func:`difffilter.particle_filter`)
with the Round-Robin mask of the scenario, registered by name for ``difffilter-eval``:

========================  =====================================================================
name                      what it is
========================  =====================================================================
rrp_pf_da                 bootstrap PF, mixture likelihood of eq. (15) on the scheduled sensor
rrp_spf_da                bootstrap PF, glint likelihood only, on the attacked data
rrp_spf_nm                the same on the attack-free data (the reference)
pf_da                     all four sensors every step, product of per-sensor mixtures
rrp_pf_da_ekf_proposal    eq. (15) with an EKF-step proposal (Remark 2: a UKF one is future work)
ukf_chi_square            UKF gated by a χ² test (the analytic baseline)
========================  =====================================================================

The detection score of the mixture filters is the per-step posterior probability that
the received packet is a deception (the mixture responsibility under the predictive
weights). Every estimator reports its packets sent per run in
``extras["transmissions"]``. The report sections are in ``difffilter.eval.families.tracking``.
"""

from __future__ import annotations

import torch

from difffilter import fdi
from difffilter.estimator import Detection, EstimatorOutput
from difffilter.models.estimators import SuiteContext, family_register, get
from difffilter.models.tracking import (
    DeceptionEKFProposal,
    PerSensorDeception,
    TrackingScenario,
    communication_counts,
)
from difffilter.noise import UniformBox
from difffilter.particle import particle_filter

__all__ = ["mixture_likelihood"]

#: Every estimator here reads the tracking scenario (its sensors, schedule and glint).
register = family_register(TrackingScenario, "tracking")


def mixture_likelihood(ctx: SuiteContext) -> fdi.DeceptionMixtureLikelihood:
    """Eq. (15): ``(1 − η̄) p_ν(ỹ − h(x)) + η̄ p_ξ(ỹ)`` on the received entries."""
    sc, n = ctx.scenario, len(ctx.scenario.sensors)
    box = UniformBox(
        torch.tensor(sc.box_low * n, dtype=ctx.dtype),
        torch.tensor(sc.box_high * n, dtype=ctx.dtype),
    )
    return fdi.DeceptionMixtureLikelihood(sc.eta_bar, fdi.ReplacementDeception(box))


def _with_counts(out: EstimatorOutput, mask, tr) -> EstimatorOutput:
    B, T = tr.flags.shape
    out.extras["transmissions"] = communication_counts(
        mask, B, T, len(tr.info["sensor_flags"][0, 0])
    )
    return out


def _responsibility_pf(ctx, tr, *, proposal=None) -> EstimatorOutput:
    """The eq.-(15) PF through the shared driver with ``proposal``; score = mixture responsibility."""
    lik = mixture_likelihood(ctx)

    def hook(model, y, m, state, out):
        return {
            "p": lik.attack_probability(
                model, y, state.particles, out.extras["prior_log_weights"], state.k, m
            )
        }

    res = particle_filter(ctx.model, tr.y_recv, mask=tr.mask, likelihood=lik, proposal=proposal,
                          hooks=(hook,), innovations=False, **ctx.particle_kwargs(len(tr.y_recv)))  # fmt: skip
    p = res.records["p"]
    out = EstimatorOutput(
        res.means, res.covs, detection=Detection(p, p > 0.5, 0.5), extras={"ess": res.ess}
    )
    return _with_counts(out, tr.mask, tr)


@register(
    "rrp_pf_da", "RRP-PF-DA: bootstrap PF, mixture likelihood eq. (15) on the scheduled sensor"
)
def _rrp_pf_da(ctx: SuiteContext):
    lik = mixture_likelihood(ctx)

    def run(tr):
        out = fdi.mixture_likelihood_particle_filter(
            ctx.model,
            tr.y_recv,
            mask=tr.mask,
            likelihood=lik,
            **ctx.particle_kwargs(len(tr.y_recv)),
        )
        return _with_counts(out, tr.mask, tr)

    return run


def _standard(ctx: SuiteContext, clean: bool):
    def run(tr):
        ys = tr.y_true if clean else tr.y_recv
        res = particle_filter(ctx.model, ys, mask=tr.mask, innovations=False,
                              **ctx.particle_kwargs(len(ys)))  # fmt: skip
        extras = {"ess": res.ess, "degenerate": res.degenerate}
        return _with_counts(EstimatorOutput(res.means, res.covs, extras=extras), tr.mask, tr)

    return run


@register("rrp_spf_da", "RRP-SPF-DA: bootstrap PF, glint likelihood only, attacked data")
def _rrp_spf_da(ctx: SuiteContext):
    return _standard(ctx, clean=False)


@register("rrp_spf_nm", "RRP-SPF-NM: bootstrap PF, glint likelihood, normal (attack-free) data",
          clean_input=True, reference=True)  # fmt: skip
def _rrp_spf_nm(ctx: SuiteContext):
    return _standard(ctx, clean=True)


# four packets a step where the scenario's receiver gets one: a bound on what the data buys
@register("pf_da", "PF-DA: all 4 sensors every step, product of per-sensor mixtures",
          more_data=True)  # fmt: skip
def _pf_da(ctx: SuiteContext):
    sc = ctx.scenario
    lik = PerSensorDeception(sc.eta_bar, sc.box_low, sc.box_high, len(sc.sensors))

    def run(tr):
        def hook(model, y, m, state, out):
            return {"p": lik.posterior_attack(model, y, state, m)}

        ys = tr.info["y_all"]
        res = particle_filter(ctx.model, ys, likelihood=lik, hooks=(hook,), innovations=False,
                              **ctx.particle_kwargs(len(ys)))  # fmt: skip
        per_sensor = res.records["p"]  # [B, T, S]
        sched = tr.mask.reshape(per_sensor.shape + (2,)).any(-1)
        # the scheduled packet's probability: the same labels as the Round-Robin filters
        score = (per_sensor * sched).sum(-1)
        out = EstimatorOutput(res.means, res.covs, detection=Detection(score, score > 0.5, 0.5),
                              extras={"ess": res.ess, "sensor_attack_probability": per_sensor})  # fmt: skip
        return _with_counts(out, None, tr)

    return run


@register(
    "rrp_pf_da_ekf_proposal",
    "RRP-PF-DA with an EKF-step proposal (defensive mixture with the prior)",
)
def _ekf_proposal(ctx: SuiteContext):
    prop = DeceptionEKFProposal(ctx.scenario.eta_bar)
    return lambda tr: _responsibility_pf(ctx, tr, proposal=prop)


@register("ukf_chi_square", "UKF gated by a χ² test on its innovation (analytic baseline)")
def _ukf_chi_square(ctx: SuiteContext):
    run = get("chi_square_ukf").factory(ctx)
    return lambda tr: _with_counts(run(tr), tr.mask, tr)
