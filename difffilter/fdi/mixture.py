"""Attack-aware mixture likelihood for particle filters under randomly occurring deception.

Song, Wang, Wang & Shan (RRP particle filter with deception attacks, eqs 14–15; the
"method [31]" the modified-PF paper compares with): with a Bernoulli attack indicator
of known rate ``p`` the likelihood of a received measurement marginalises it out::

    p(ỹ_k | x_k) = (1 − p) p_v(ỹ_k − h(x_k)) + p · p_a(ỹ_k | x_k)

where ``p_a`` is the measurement density under attack:

* :class:`ReplacementDeception` — the measurement is replaced by ``ξ_k ~ p_ξ``
  (the RRP paper, eq. 5): ``p_a(ỹ | x) = p_ξ(ỹ)``, independent of ``x``;
* :class:`BiasDeception` — an additive deception ``ỹ = y + ρ`` (the extension to the
  bias attack that the modified-PF paper makes in Sec. V-B, ``ρ = γ̄``):
  ``p_a(ỹ | x) = p_v(ỹ − h(x) − ρ)``.

Everything is evaluated in log space (``logaddexp``). :meth:`DeceptionMixtureLikelihood.
attack_probability` gives the filter's posterior probability that the current packet is
attacked, ``P(l_k = 1 | ỹ_{1:k})``, a detection score.
"""

from __future__ import annotations

import math
from itertools import chain

import torch
from torch import Tensor

from .._assignments import assignments
from .._checks import check_filter_inputs, real_number
from ..estimator import Detection, EstimatorOutput
from ..loop import _step_through, open_loop
from ..noise import NoiseModel
from ..particle import BootstrapProposal, ParticleFilter, ParticleState
from ..resampling import Systematic
from .modified_pf import _attach, _generators

__all__ = [
    "BiasDeception",
    "ReplacementDeception",
    "DeceptionMixtureLikelihood",
    "MixtureParticleFilter",
    "mixture_likelihood_particle_filter",
]


class BiasDeception:
    """Additive deception ``ỹ = y + ρ``: ``log p_a(ỹ | x) = log p_v(ỹ − ρ − h(x))``.

    Args:
        rho: the deception vector ``ρ`` ``[..., dy]`` (``γ̄`` for the bias attack).
    """

    def __init__(self, rho):
        self.rho = rho

    @property
    def rho(self) -> Tensor:
        return self._rho

    @rho.setter
    def rho(self, rho) -> None:
        # checked whenever set: a 0-d ρ assigned after construction had met a bare
        # IndexError in the likelihood (a red-team trial)
        # numbers and lists in float64, cast at use (under a float32 default they had been
        # rounded first: means 6e-9 off a float64 filter's; a default-dtype trial)
        rho = rho if isinstance(rho, Tensor) else torch.as_tensor(rho, dtype=torch.float64)
        if rho.dim() < 1 or not bool(torch.isfinite(rho).all()):
            raise ValueError(f"rho must be a finite vector [..., dy]; got {rho!r}")
        self._rho = rho

    def __call__(self, model, y: Tensor, particles: Tensor, k: int, mask) -> Tensor:
        if self.rho.shape[-1] != model.dim_y:  # one entry would broadcast to every channel
            raise ValueError(f"rho must have shape [..., {model.dim_y}] (the model's dim_y); "
                             f"got {tuple(self.rho.shape)}")  # fmt: skip
        rho = self.rho.to(dtype=y.dtype, device=y.device)
        try:
            fits = torch.broadcast_shapes(rho.shape, y.shape) == y.shape
        except RuntimeError:
            fits = False
        if not fits:
            # (a ρ per run for another number of runs had failed in torch's "size of tensor
            # a (2) must match … (3)", naming neither; a trial)
            raise ValueError(
                f"rho {tuple(rho.shape)} must broadcast to the measurements {tuple(y.shape)} "
                "(one deception vector, or one per run)"
            )
        m = None if mask is None else mask.unsqueeze(-2)
        return model.measurement_log_prob((y - rho).unsqueeze(-2), particles, k, m)


class ReplacementDeception:
    """Replacement deception ``ỹ = ξ``, ``ξ ~ p_ξ``: ``log p_a(ỹ | x) = log p_ξ(ỹ)``.

    Args:
        density: a :mod:`difffilter.noise` model of ``ξ`` (e.g. ``UniformBox``).
    """

    def __init__(self, density: NoiseModel):
        if not isinstance(density, NoiseModel):
            raise ValueError(
                f"density must be a difffilter.noise model; got {type(density).__name__}"
            )
        self.density = density
        self._last = None

    def __call__(self, model, y: Tensor, particles: Tensor, k: int, mask) -> Tensor:
        return self.log_density(y, mask).unsqueeze(-1).expand(particles.shape[:-1])

    def _check_dim(self, y: Tensor) -> None:
        """The density's dimension against the measurements' (checked on every path to the
        density: the mixture likelihood's and the particle filter's tabulated one had met
        torch's size mismatch)."""
        dim = getattr(self.density, "dim", None)
        if dim is not None and dim != y.shape[-1]:
            raise ValueError(f"density has dimension {dim}; the model's measurements have "
                             f"dim_y = {y.shape[-1]}: they must be the same")  # fmt: skip

    def log_density(self, y: Tensor, mask=None) -> Tensor:
        """``log p_ξ(ỹ)`` of the received entries ``[...]`` (the same for every particle).

        The last value is kept for the same ``y`` and ``mask`` tensors (unmodified) and the
        same density (its tensors unmodified, none learned) in the same grad mode: the
        filter step and its detection hook ask for the same packet once each. (Keyed on
        ``y`` and ``mask`` alone, a density changed by ``load_state_dict`` answered with its
        old values, one learned crashed the second ``backward``, and a value made under
        ``no_grad`` carried no gradient to the next training step: a red-team trial.) The
        density follows the measurements to their device (the first call on a GPU moves it
        there).
        """
        self._check_dim(y)
        self._follow(y.device)
        tensors = list(chain(self.density.parameters(), self.density.buffers()))
        if (y.is_inference() or (mask is not None and mask.is_inference())
                or any(t.requires_grad or t.is_inference() for t in tensors)):  # fmt: skip
            # inference tensors have no version counter, and a learned density's value belongs
            # to one graph: no cache
            self._last = None
            return self._log_prob(y, mask)
        key = (y, mask, y._version, None if mask is None else mask._version,
               assignments(), torch.is_grad_enabled(),
               tuple((t.data_ptr(), t._version) for t in tensors))  # fmt: skip
        cached = self._last
        if cached is not None and all(a is b for a, b in zip(cached[0][:2], key[:2])):
            if cached[0][2:] == key[2:]:
                return cached[1]
        lp = self._log_prob(y, mask)
        self._last = (key, lp)
        return lp

    def _follow(self, device: torch.device) -> None:
        here = next(chain(self.density.buffers(), self.density.parameters()), None)
        if here is not None and here.device != device:
            self.density.to(device)

    def _log_prob(self, y: Tensor, mask) -> Tensor:
        """``log p_ξ(y)``, in ``y``'s dtype or refused: a float64 density on a float32 model
        failed in the particle filter, which blamed the likelihood's dtype (a fuzzing
        trial). The density's answer is checked, not its buffers: one that answers in the
        caller's dtype runs whatever it holds (a review)."""
        lp = self.density.log_prob(y, mask=mask) if mask is not None else self.density.log_prob(y)
        if lp.dtype != y.dtype:
            raise ValueError(
                f"the deception density ({type(self.density).__name__}) returned log-densities "
                f"of {lp.dtype} for measurements of {y.dtype}: make it in theirs (e.g. "
                f"deception_of(attack, {y.dtype})[0])"
            )
        return lp


def _clean_log_prob(model, y, particles, k, mask) -> Tensor:
    """``log p_v(ỹ − h(x^i))`` of ``particles [..., N, dx]`` on the received entries → ``[..., N]``."""
    m = None if mask is None else mask.unsqueeze(-2)
    return model.measurement_log_prob(y.unsqueeze(-2), particles, k, m)


class DeceptionMixtureLikelihood:
    """``log[(1 − p) p_v(ỹ − h(x)) + p p_a(ỹ | x)]``, a particle-filter ``Likelihood``.

    Args:
        attack_probability: ``p ∈ [0, 1]`` (``η̄`` of the RRP paper, ``p_l`` here).
        attack: :class:`BiasDeception` or :class:`ReplacementDeception` (any callable
            ``(model, y, particles, k, mask) → [..., N]``).

    ``__call__(model, y [..., dy], particles [..., N, dx], k, mask)`` → ``[..., N]``.
    """

    def __init__(self, attack_probability: float, attack):
        self.p = attack_probability
        self.attack = attack

    @property
    def attack(self):
        """The attacked density ``log p_a(ỹ | x)``; checked whenever assigned (one assigned
        after construction had been read unchecked, a ``TypeError`` at the first step)."""
        return self._attack

    @attack.setter
    def attack(self, attack) -> None:
        if not callable(attack):
            raise ValueError("attack must be a callable (model, y, particles, k, mask) -> [..., N]")
        self._attack = attack

    @property
    def p(self) -> float:
        """``p``, the attack probability; assigned, it is checked and its logs made again (the
        weighting adds ``log p`` and ``log(1 − p)`` made once: ``likelihood.p = 0.5`` had
        weighed with the old ``p`` while its ``p == 0`` branch read the new one, and 1.5
        was taken: a red-team trial)."""
        return self._p

    @p.setter
    def p(self, attack_probability: float) -> None:
        p = float(attack_probability)
        if not 0.0 <= p <= 1.0:
            raise ValueError(f"attack_probability must lie in [0, 1]; got {attack_probability!r}")
        self._p = p
        self._log_p = math.log(p) if p > 0 else -math.inf
        self._log_q = math.log1p(-p) if p < 1 else -math.inf

    def components(self, model, y, particles, k, mask) -> tuple[Tensor, Tensor]:
        """``(log[(1−p) p_v], log[p p_a])`` per particle, each ``[..., N]``."""
        clean = _clean_log_prob(model, y, particles, k, mask) + self._log_q
        attacked = self.attack(model, y, particles, k, mask) + self._log_p
        return clean, attacked

    def replacement_term(self, y: Tensor, mask: Tensor | None) -> Tensor:
        """``log[p p_ξ(ỹ)]`` of a :class:`ReplacementDeception` ``[...]``: it does not depend
        on the state, so ``y [..., dy]`` and ``mask`` may hold whole sequences."""
        return self.attack.log_density(y, mask) + self._log_p

    def __call__(self, model, y, particles, k, mask, *, attacked=None) -> Tensor:
        """``attacked``: ``log[p p_a(ỹ)]`` ``[..., 1]`` when the caller has it (a replacement
        attack: one number per run, e.g. tabulated for a whole sequence)."""
        if self._p == 0.0:  # log(1 − p) = 0 and p p_a = 0: the clean density, exactly
            return _clean_log_prob(model, y, particles, k, mask)
        if attacked is None and isinstance(self.attack, ReplacementDeception):
            attacked = self.replacement_term(y, mask).unsqueeze(-1)
        if attacked is None:
            clean, attacked = self.components(model, y, particles, k, mask)
        else:
            # p p_ξ(ỹ) is one number per run ([..., 1]): broadcast in the logaddexp instead
            # of a pass over the particles
            clean = _clean_log_prob(model, y, particles, k, mask) + self._log_q
        return torch.logaddexp(clean, attacked)

    def attack_probability(
        self, model, y, particles, log_weights, k, mask=None, *, evidence=None
    ) -> Tensor:
        """``P(l_k = 1 | ỹ_{1:k})`` ``[...]`` from predictive ``log_weights [..., N]``.

        ``= Σ_i w^i p p_a^i / Σ_i w^i [(1−p) p_v^i + p p_a^i]`` (log space).

        ``evidence``: the denominator's log, ``log Σ_i w^i p(ỹ | x^i)`` ``[...]``, when the
        caller has it (the log-likelihood increment of a bootstrap-proposal step, whose
        weights before the update are these ``log_weights``). With an attack density
        that does not depend on the state (:class:`ReplacementDeception`) the numerator
        is then ``p p_ξ(ỹ)`` and no particle is visited again (``particles``,
        ``log_weights`` and ``k`` are not read: ``y [..., dy]``, ``mask`` and ``evidence``
        may then hold whole sequences, e.g. ``[B, T, dy]`` and ``[B, T]``); equal to the
        full sum up to round-off.
        """
        if evidence is not None and isinstance(self.attack, ReplacementDeception):
            return _attack_posterior(self.replacement_term(y, mask), evidence)
        clean, attacked = self.components(model, y, particles, k, mask)
        lw = torch.log_softmax(log_weights, dim=-1)
        num = torch.logsumexp(lw + attacked, dim=-1)
        den = torch.logsumexp(lw + torch.logaddexp(clean, attacked), dim=-1)
        return _attack_posterior(num, den)


def _attack_posterior(log_attacked: Tensor, log_evidence: Tensor) -> Tensor:
    """``exp(log_attacked − log_evidence)``, the attack's posterior probability, clamped to
    at most 1 (≤ 1 in exact arithmetic; round-off had given 1 + 9e-16: a trial), and 1 where
    the evidence is 0 (``−∞``): a reading that no hypothesis of the model can explain is an
    alarm. There ``−∞ − (−∞)`` had been NaN, which never alarms (an FDI trial: a float32
    reading of 1e20 under a bias deception, certainly attacked, scored NaN)."""
    p = torch.exp((log_attacked - log_evidence).clamp(max=0.0))
    return torch.where(log_evidence == -math.inf, torch.ones_like(p), p)


class MixtureParticleFilter(ParticleFilter):
    """A particle filter weighted by the mixture likelihood, with its attack posterior as score.

    Args:
        num_particles: ``N``.
        likelihood: the :class:`DeceptionMixtureLikelihood`.
        threshold: alarm where the score exceeds it [DEF 0.5: the maximum-a-posteriori
            decision].
        proposal: default the bootstrap proposal (the score then reads the step's
            evidence; another proposal recomputes the sum).
        resampler, ess_threshold: default systematic resampling at every step.
        innovations: compute the predictive measurement moments (default no).

    The score of step ``k`` is the posterior probability that the packet is a deception,
    ``P(l_k = 1 | ỹ_{1:k})`` (:meth:`DeceptionMixtureLikelihood.attack_probability`, from
    the predictive weights). With a :class:`ReplacementDeception` (a density that does not
    depend on the state) whole sequences take a private fast path: ``log[p p_ξ(ỹ_k)]`` of
    every step is one table for the sequence, and the score ``p p_ξ(ỹ_k) / p̂(ỹ_k |
    ỹ_{1:k−1})`` comes from the evidence increments after the loop (equal to the steps'
    up to round-off).
    """

    def __init__(
        self,
        num_particles: int,
        likelihood: DeceptionMixtureLikelihood,
        *,
        threshold: float = 0.5,
        proposal=None,
        resampler=None,
        ess_threshold: float = 1.0,
        innovations: bool = False,
    ):
        if not isinstance(likelihood, DeceptionMixtureLikelihood):
            raise ValueError(
                f"likelihood must be a DeceptionMixtureLikelihood; got {type(likelihood).__name__}"
            )
        self.threshold = threshold  # (checked by __setattr__)
        super().__init__(
            num_particles, likelihood=likelihood, hooks=(self._responsibility,),
            resampler=resampler if resampler is not None else Systematic(), proposal=proposal,
            ess_threshold=ess_threshold, innovations=innovations,
        )  # fmt: skip

    @property
    def mixture(self) -> DeceptionMixtureLikelihood:
        """The mixture likelihood: the filter's ``likelihood`` (one object: kept twice, one
        assigned later had left the other weighing or scoring with the old ``p``, 0.6-0.8
        off a filter built with the new one; a trial)."""
        return self.likelihood

    @mixture.setter
    def mixture(self, value) -> None:
        self.likelihood = value

    def __setattr__(self, name, value):
        # checked whenever set, not at __init__ alone: a NaN threshold assigned later never
        # alarmed (0 of 24 where the attack probability reached 0.996), −1 alarmed at every
        # step (a trial)
        if name == "threshold":
            number = real_number(value)
            if number is None or not 0.0 <= number <= 1.0:
                raise ValueError(f"threshold must lie in [0, 1] (a probability); got {value!r}")
            value = number
        elif name == "likelihood" and not isinstance(value, DeceptionMixtureLikelihood):
            raise ValueError(
                f"likelihood must be a DeceptionMixtureLikelihood; got {type(value).__name__}"
            )
        elif name == "hooks" and "hooks" in self.__dict__:
            # the filter's own hook (the attack posterior, its score) stays: hooks assigned
            # later had dropped it, and the next step failed on a bare KeyError 'p'
            value = (*(h for h in value if h != self._responsibility), self._responsibility)
        super().__setattr__(name, value)

    def _responsibility(self, model, y, m, state, out):  # P(l_k = 1 | ỹ_{1:k}) from w_{k−1}
        prior = out.extras["prior_log_weights"]
        bootstrap = type(self.proposal) is BootstrapProposal
        evidence = out.log_likelihood if bootstrap else None
        p = self.mixture.attack_probability(
            model, y, state.particles, prior, state.k, m, evidence=evidence
        )
        return {"p": p}

    def _step(self, carry, y, u, mask):
        carry, out = super()._step(carry, y, u, mask)
        x = dict(out.extras)
        p = x.pop("p")
        return carry, out._replace(score=p, alarm=p > self.threshold, threshold=self.threshold,
                                   extras=x)  # fmt: skip

    def _run(self, carry, ys, us, mask):
        if not isinstance(self.mixture.attack, ReplacementDeception):
            return None
        if type(self.proposal) is not BootstrapProposal:
            return None
        attacked = self.mixture.replacement_term(ys, mask)
        # the settings as they are now (those of the constructor had been kept here: a
        # resampler, ESS threshold, proposal or hook assigned later ran in the steps alone,
        # means up to 2.09 off; a trial)
        hooks = tuple(h for h in self.hooks if h != self._responsibility)
        tabulated = ParticleFilter(
            self.num_particles, likelihood=_Tabulated(self.mixture, attacked.unsqueeze(-1), carry.k),
            resampler=self.resampler, proposal=self.proposal, ess_threshold=self.ess_threshold,
            innovations=self.innovations, hooks=hooks, record_prior=self.record_prior,
            cov_dims=self.cov_dims,  # (dropped before: covs [T, 2, 2] for cov_dims = 1, a trial)
        )  # fmt: skip
        batch = self.batch_of(carry)
        out = _step_through(tabulated, carry, ys, us, mask, batch, None)
        score = _attack_posterior(attacked, out.extras["log_likelihood_increments"])
        out.detection = Detection(score, score > self.threshold, self.threshold)
        return out


def mixture_likelihood_particle_filter(
    model,
    ys: Tensor,
    us: Tensor | None = None,
    *,
    mask: Tensor | None = None,
    num_particles: int,
    likelihood: DeceptionMixtureLikelihood,
    threshold: float = 0.5,
    resampler=None,
    ess_threshold: float = 1.0,
    generator: torch.Generator | None = None,
    resample_generator: torch.Generator | None = None,
    initial_state: ParticleState | None = None,
) -> EstimatorOutput:
    """:class:`MixtureParticleFilter` in the open loop.

    Shapes: ``ys [..., T, dy]``, ``us [..., T, du]``, ``mask [..., T, dy]``. Returns an
    :class:`~difffilter.EstimatorOutput` (``attack`` is ``None``; detection scores
    ``P(l_k = 1 | ỹ_{1:k})``) with ``extras``: ``ess [..., T]`` and ``log_likelihood [...]``.
    Other arguments as in :func:`~difffilter.particle_filter` (default systematic
    resampling at every step).
    """
    ys, us, mask = check_filter_inputs(
        model, ys, us, mask, resampler=resampler, ess_threshold=ess_threshold
    )
    pf = MixtureParticleFilter(
        num_particles, likelihood, threshold=threshold, resampler=resampler,
        ess_threshold=ess_threshold,
    )  # fmt: skip
    gens = _generators(generator, resample_generator)
    carry = _attach(pf, model, initial_state, gens)
    if carry is not None:  # open_loop takes the fast path only from the prior
        out = pf._run(carry, ys, us, mask)
        if out is not None:
            return out
    return open_loop(pf, model, ys, us, mask=mask, generator=gens, carry=carry)


class _Tabulated:
    """``likelihood`` (a replacement-attack mixture) with ``log[p p_ξ(ỹ_k)]`` read from a
    table ``[..., T, 1]`` of the sequence: the driver asks for state ``k`` at step
    ``t = k − k0 − 1`` of a run started from state ``k0``."""

    def __init__(self, likelihood: DeceptionMixtureLikelihood, table: Tensor, k0: int):
        self.likelihood, self.table, self.k0 = likelihood, table, k0

    def __call__(self, model, y, particles, k, mask):
        attacked = self.table[..., k - self.k0 - 1, :]
        return self.likelihood(model, y, particles, k, mask, attacked=attacked)
