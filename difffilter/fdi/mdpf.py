"""Local estimator of the lidar-robot paper: a particle filter of adaptive Kalman filters.

Tan, Weng, Chen & Yu, "Nonlinear fusion estimation for false data injection attack
signals in cyber-physical systems" (Sci. China Inf. Sci., supplementary, Theorem 1 and
(A1)–(A8)); a multi-distribution particle filter (Murata & Hiramatsu, IEEE TAC 2019)
whose particle ``j`` carries ``(x̂ʲ, âʲ, Υʲ, Sʲ)``. One step ``k−1 → k`` for every
particle, with ``u = u_{k−1}``::

    x_p = f(x̂ʲ, u + âʲ)  [= f(x̂ʲ, u) + B(k) âʲ]          P_p = Q                    (A3)–(A4)
    ε   = y − h(x_p)     Σ = H Q Hᵀ + R    K = Q Hᵀ Σ⁻¹   P = (I − KH) Q             (A4)
    Υ, Ω, Λ, Γ, S by Zhang's (5e)–(5i) (F, B at x̂ʲ, H at x_p)                        (A5)
    āʲ  = âʲ + Γ ε        x̄ʲ = x_p + (K + ΥΓ) ε                                      (A2)
    wʲ ∝ N(y; h(x_p), Σ)                                                             (A8)
    l ~ Categorical(w) (inverse CDF, one uniform per draw = multinomial resampling)
    x̂ʲ(k), âʲ(k) by the letter's eq. (5); Υʲ = Υˡ, Sʲ = Sˡ

The letter's eq. (5), which gives ``x̂ʲ(k)`` and ``âʲ(k)`` from the selected particle, is
not in the supplementary; both readings are available (``reading``):

* ``Reading.DRAW`` (default): ``x̂ʲ(k) ~ N(x̄ˡ, Pˡ)``, ``âʲ(k) = āˡ``: sample the selected
  Gaussian component of the mixture posterior, as the multi-distribution PF does. Keeps
  particle diversity (the propagation (A3) itself adds no noise).
* ``Reading.COPY``: ``x̂ʲ(k) = x̄ˡ``, ``âʲ(k) = āˡ``. Since (A3) is deterministic, the
  particles then collapse onto the descendants of a single particle within a few steps
  and the filter becomes one adaptive EKF with ``P_p = Q`` (tested).

Tensor program: a particle is the vector ``[x̄ (dx), ā (da), vec Υ (dx·da), vec S
(da·da), vec P (dx·dx)]`` (:class:`ParticleLayout`); the shared particle driver
(:func:`difffilter.particle.particle_filter`) resamples them (``Multinomial``, every
step), calls :class:`AdaptiveKalmanProposal` (which draws the ``DRAW`` reading and runs
(A2)–(A5) for all particles of all runs at once, :func:`~difffilter.fdi.adaptive_kf.adaptive_update`)
and weights them: the proposal returns ``log N(ε; 0, Σ)`` (A8) as its log-correction and
the likelihood is flat — (A8) is the optimal-proposal weight ``p(y_k | x̂ʲ_{k−1})``.
Every run and every particle, and several local estimators stacked on a leading
dimension, are one batched program; the time loop is the only Python loop.

The local estimate is the weighted mixture: ``x̂ = Σ wʲ x̄ʲ``,
``P̂ = Σ wʲ (Pʲ + (x̄ʲ − x̂)(x̄ʲ − x̂)ᵀ)``, ``â = Σ wʲ āʲ``, ``Ŝ = Σ wʲ (Sʲ + (āʲ − â)(·)ᵀ)``.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from .._assignments import note_assignment
from .._checks import (
    Choice,
    check_finite_number,
    check_one_model,
    check_positive_int,
    check_rate,
    check_step_inputs,
    check_strategy,
    version_stamp,
)
from ..estimator import Estimator, EstimatorOutput, Generators
from ..kalman import _check_zero_mean_noise
from ..linalg import NumericalBreakdown, matvec, safe_cholesky, symmetrize, under_transform
from ..loop import open_loop
from ..particle import PER_SET, ParticleFilter, ParticleState
from ..resampling import Multinomial
from ..results import StepOutput
from ..ssm import StateSpaceModel
from . import _components as C
from .adaptive_kf import (
    _check_forgetting,
    adaptive_update,
    forgetting_breakdown,
    forgetting_hint,
    input_jacobian,
    wald_statistic,
)
from .detectors import chi_square_upper_quantile
from .modified_pf import FlatLikelihood

__all__ = [
    "Reading",
    "Form",
    "ParticleLayout",
    "ParticleView",
    "AdaptiveKalmanProposal",
    "information_form_applies",
    "LocalEstimate",
    "AdaptiveParticleFilter",
    "adaptive_particle_init",
    "adaptive_particle_step",
    "adaptive_particle_filter",
]


class Reading(Choice):
    """The two readings of the letter's missing eq. (5) (module docstring)."""

    DRAW = "draw"
    COPY = "copy"


class Form(Choice):
    """How the proposal runs (A2)–(A5): the information form (time-invariant, diagonal
    ``R``), the covariance form, or the first where it applies (``AUTO``)."""

    AUTO = "auto"
    INFORMATION = "information"
    COVARIANCE = "covariance"


class ParticleLayout:
    """Packs ``(x̄ [..., dx], ā [..., da], Υ [..., dx, da], S [..., da, da], P [..., dx, dx])``
    into one particle vector ``[..., dx + da + dx·da + da² + dx²]`` and back."""

    def __init__(self, dx: int, da: int):
        self.dx, self.da = dx, da
        self.sizes = (dx, da, dx * da, da * da, dx * dx)
        self.size = sum(self.sizes)

    def pack(self, x, a, ups, S, P) -> Tensor:
        # sizes, not -1: a batch of no runs has no elements to infer -1 from
        lead, (_, _, n_ups, n_s, n_p) = x.shape[:-1], self.sizes
        parts = (
            x,
            a,
            ups.reshape(lead + (n_ups,)),
            S.reshape(lead + (n_s,)),
            P.reshape(lead + (n_p,)),
        )
        return torch.cat(parts, -1)

    def unpack(self, z: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        x, a, ups, S, P = torch.split(z, self.sizes, -1)
        lead, dx, da = z.shape[:-1], self.dx, self.da
        return (
            x,
            a,
            ups.reshape(lead + (dx, da)),
            S.reshape(lead + (da, da)),
            P.reshape(lead + (dx, dx)),
        )


class ParticleView(StateSpaceModel):
    """The base model seen through packed particles (what the particle driver calls):
    ``observe`` reads the ``x̄`` block; noise and residuals are the base model's, read at
    each use (a noise assigned to the base since is the view's too)."""

    def __init__(self, base: StateSpaceModel, layout: ParticleLayout):
        super().__init__()
        self.base, self.layout = base, layout
        self.dim_x, self.dim_y, self.dim_u = layout.size, base.dim_y, base.dim_u

    @property
    def initial(self):
        return self.base.initial

    @property
    def process_noise(self):
        return self.base.process_noise

    @property
    def measurement_noise(self):
        return self.base.measurement_noise

    def observe(self, x, k):
        return self.base.observe(x[..., : self.layout.dx], k)

    def measurement_residual(self, y, y_hat):
        return self.base.measurement_residual(y, y_hat)

    def measurement_cov(self, k):
        return self.base.measurement_cov(k)

    def process_cov(self, k):
        return self.base.process_cov(k)

    def _varying_noise(self, cov_method):
        return self.base._varying_noise(cov_method)

    def transition(self, x, u, k):
        # (another particle filter given this view's carry had failed on an empty
        # NotImplementedError: a hand-built-carries trial)
        raise ValueError(
            "carry.model is the adaptive particle filter's view of packed particles, which "
            "only its own proposal moves: step this carry with the AdaptiveParticleFilter that "
            "made it"
        )


#: The largest condition number of ``Q`` the information form takes: it inverts ``Q`` (the
#: covariance form does not), and its error grows like ``cond(Q)`` (4.8e-4 cm at 1e14
#: against a 50-digit filter, the covariance form 3e-12; a red-team trial).
INFORMATION_MAX_COND_Q = 1e8


def information_form_applies(model: StateSpaceModel) -> bool:
    """Whether ``model`` has what the information form needs: time-invariant noise (declared
    or not: a model whose ``R(k)`` varies without ``time_varying`` had been filtered with
    ``R(0)`` at every step, 6.5 off the covariance form's mean, a red-team trial), a diagonal
    ``R``, a ``Q`` positive definite with a condition number up to
    :data:`INFORMATION_MAX_COND_Q` (the form inverts it), and no gradient to ``Q`` or ``R``
    (it holds them as numbers: a loss had no gradient to either, an MDPF trial).
    ``form="auto"`` takes it in float64 alone: in float32 its error, about ``cond(Q)·ε``,
    had reached 4.6e-4 at cond 1e2 and an attack estimate 3.4 off at 1e4 where the
    covariance form is 1.6e-6 off (the same trial)."""
    if getattr(model, "time_varying", False):
        return False
    varying = getattr(model, "_varying_noise", None)
    if varying is not None and (varying("process_cov") or varying("measurement_cov")):
        return False
    R, Q = model.measurement_cov(0), model.process_cov(0)
    if R.requires_grad or Q.requires_grad or under_transform(Q, R):
        return False
    if R.dim() != 2 or bool((R - torch.diag_embed(R.diagonal())).abs().max() > 0):
        return False
    return _well_conditioned(Q)


def _well_conditioned(Q: Tensor) -> bool:
    """Whether ``Q`` is positive definite with ``cond(Q) ≤`` :data:`INFORMATION_MAX_COND_Q`."""
    if Q.dim() != 2 or Q.device.type == "meta":
        return Q.dim() == 2
    eig = torch.linalg.eigvalsh(Q.detach().double())
    return bool(eig[0] > 0) and float(eig[-1] / eig[0]) <= INFORMATION_MAX_COND_Q


class AdaptiveKalmanProposal:
    """(A2)–(A5) for every particle, with the ``DRAW`` reading of eq. (5) first.

    ``form``: :attr:`Form.INFORMATION` (where it applies) evaluates (A4)–(A5) in information form on
    component lists (:mod:`difffilter.fdi._components`, ~10× faster on CPU); it needs a
    diagonal, time-invariant ``R`` and a time-invariant ``Q``. With ``P_p = Q`` and
    ``M = Q⁻¹ + HᵀR⁻¹H``::

        P = M⁻¹,  Kε = M⁻¹ HᵀR⁻¹ε,  HᵀΣ⁻¹ = Q⁻¹K,  J = HᵀΣ⁻¹H = Q⁻¹ − Q⁻¹M⁻¹Q⁻¹
        D = FΥ + B,  Υ⁺ = (I − KH) D = M⁻¹Q⁻¹D,  S⁺ = (λS⁻¹ + DᵀJD)⁻¹,  Γε = S⁺DᵀQ⁻¹Kε
        log N(ε; 0, Σ) = −½ (εᵀR⁻¹ε − εᵀR⁻¹HKε + log det R + log det Q + log det M + m log 2π)

    (matrix inversion and determinant lemmas; ``S⁺`` is (5i) since ``Γ`` is the gain of
    the θ-filter with prior ``S/λ``). ``J`` is never formed: ``JD = Q⁻¹(D − Υ⁺)``, so
    ``DᵀJD = (Q⁻¹D)ᵀ(D − Υ⁺)``. The 2×2 and 3×3 inverses and ``log det M`` are the
    adjugate formulas (:func:`~difffilter.fdi._components.sym_inverse`); every entry of
    every matrix is one tensor over all particles of all runs, and constant entries
    (``Q⁻¹``, the unicycle's 0/1 Jacobian entries) are Python numbers that cost no
    kernel. :attr:`Form.COVARIANCE` runs :func:`~difffilter.fdi.adaptive_kf.adaptive_update`
    (the shared Kalman gain and Joseph form) on the packed tensors; the two agree to
    round-off at a step (tested, also for one ``DRAW`` step against the same noise). Over
    a run they do not: that round-off can move a resampling's pick to another ancestor,
    after which the clouds differ by the filter's own spread (a trial: 2.6e-16 after
    step 1, 3.8e-3 after step 2, with ``DRAW``), so ``form="auto"``, which switches form
    with ``R``'s structure, is another sampler of the same filter, not its copy.

    Returns ``(new packed particles [..., N, D], log N(ε; 0, Σ) [..., N])`` (A8). The
    information form returns them component-major (``[..., D, N]`` in memory, seen as
    ``[..., N, D]``): the resampler gathers each component row and keeps the layout, the
    driver's moments need no transpose copy and the next step reads its components as
    views.
    """

    def __init__(
        self,
        base: StateSpaceModel,
        forgetting: float,
        reading: Reading | str = Reading.DRAW,
        form: Form | str = Form.AUTO,
    ):
        reading, form = Reading(reading), Form(form)
        self.base, self.forgetting, self.reading = base, _check_forgetting(forgetting), reading
        self.layout = ParticleLayout(base.dim_x, base.dim_u)
        self.requested_form = form
        self._noise_key = None
        self._refresh()

    def _refresh(self) -> None:
        """Choose the form and derive the information form's constants from the model's
        ``R`` and ``Q`` as they are now. Done again whenever either is another tensor or
        was written in place since (the constants had been frozen at the first step: a
        model made noisier under the estimator was filtered with its old ``R``, 125 cm
        away from a fresh estimator's)."""
        R, Q = self.base.measurement_cov(0), self.base.process_cov(0)
        # the tensors themselves, and what they hold: their version (written in place),
        # their storage (``R.data = new`` keeps the object and its version: the old noise
        # had been filtered on, 1.56 off), and whether a gradient is wanted (the key's
        # flags had not been compared: R.requires_grad_() later kept the information form)
        traced = under_transform(Q, R)  # (wrapped tensors: no storage to read)
        state = (version_stamp(R), None if traced else R.data_ptr(), version_stamp(Q),
                 None if traced else Q.data_ptr(), R.requires_grad, Q.requires_grad, traced)  # fmt: skip
        old = self._noise_key
        if old is not None and old[0] is R and old[1] is Q and old[2] == state:
            return
        key = (R, Q, state)
        form = self.requested_form
        if form is Form.AUTO:
            fits = Q.dtype == torch.float64 and information_form_applies(self.base)
            form = Form.INFORMATION if fits else Form.COVARIANCE
        if form is Form.INFORMATION:
            if not information_form_applies(self.base):
                raise ValueError(
                    "form='information' needs time-invariant noise, a diagonal R and "
                    f"a positive definite Q of condition number up to {INFORMATION_MAX_COND_Q:g} "
                    "(it inverts Q), and no gradient to Q or R (it holds them as numbers); "
                    "use form='covariance'"
                )
            Qd = Q.detach().double()
            self._rvar = R.diagonal().detach().tolist()
            self._qinv = torch.linalg.inv(Qd).tolist()
            self._logdet_q = float(torch.logdet(Qd))
        self.form, self._noise_key = form, key

    def __call__(self, model, particles, u, y, k, mask, generator):
        if not getattr(self.base, "time_varying", False):
            self._refresh()
        if self.form is Form.COVARIANCE:
            return self._covariance(particles, u, y, k, mask, generator)
        return self._information(particles, u, y, k, mask, generator)

    @property
    def nonfinite_hint(self) -> str | None:
        """What a particle filter's error about non-finite particles adds (a 1,034-step
        outage in float64 had said only "NaN or inf": a long-run trial)."""
        return forgetting_hint(self.forgetting) if self.forgetting < 1.0 else None

    def _covariance(self, particles, u, y, k, mask, generator):
        x, a, ups, S, P = self.layout.unpack(particles)
        if self.reading is Reading.DRAW:  # x̂ʲ(k−1) ~ N(x̄ˡ, Pˡ)
            eps = torch.randn(x.shape, generator=generator, dtype=x.dtype, device=x.device)
            x = x + matvec(safe_cholesky(P, name="particle covariance P"), eps)
        u = a.new_zeros(()).expand(a.shape) if u is None else u.unsqueeze(-2)
        m = None if mask is None else mask.unsqueeze(-2)
        try:
            upd = adaptive_update(
                self.base, x, a, S, ups, y.unsqueeze(-2), u, k, forgetting=self.forgetting,
                pred_cov=self.base.process_cov(k), mask=m,
            )  # fmt: skip
        except NumericalBreakdown as error:  # (its S, grown over an outage: named)
            named = forgetting_breakdown(
                S, self.forgetting, k + 1, "the adaptive particle filter's local estimator"
            )
            if named is None:
                raise
            raise named from error
        new = self.layout.pack(upd.mean, upd.attack, upd.sensitivity, upd.attack_cov, upd.cov)
        return new, upd.log_likelihood

    def _linearized(self, x, a, u, y, k, dtype):
        """``x_p, F, Φ, ε, H`` in component form at the particles' ``x̂ʲ(k−1)`` and
        ``âʲ(k−1)``: the model's own component linearisation, or its Jacobians."""
        base = self.base
        own = getattr(base, "linearize_components", None)
        if own is not None:  # the model's component form (no AoS round trips)
            uc = list(u.movedim(-1, 0).unsqueeze(-1).unbind(0)) if u is not None else None
            ue = a if uc is None else [ai + ui for ai, ui in zip(a, uc)]
            yc = list(y.movedim(-1, 0).unsqueeze(-1).unbind(0))
            return own(x, ue, yc, k)
        xa, ua = torch.stack(x, -1), torch.stack(a, -1)
        if u is not None:
            ua = ua + u.unsqueeze(-2)
        F = C.to_components(base.transition_jacobian(xa, ua, k).to(dtype))
        phi = C.to_components(input_jacobian(base, xa, ua, k).to(dtype))
        xp = base.transition(xa, ua, k)
        H = C.to_components(base.observation_jacobian(xp, k + 1).to(dtype))
        eps_y = base.measurement_residual(y.unsqueeze(-2), base.observe(xp, k + 1))
        e = list(eps_y.movedim(-1, 0).contiguous().unbind(0))
        return list(xp.movedim(-1, 0).unbind(0)), F, phi, e, H

    def _information(self, particles, u, y, k, mask, generator):
        lay = self.layout
        dx, da = lay.dx, lay.da
        z = particles.transpose(-1, -2)  # [..., D, N]
        if not z.is_contiguous():  # row-major particles (an initial state): one copy
            z = z.contiguous()
        comp = z.unbind(-2)  # views [..., N], each contiguous along the particles
        o = dx + da
        x, a = list(comp[:dx]), list(comp[dx:o])
        ups = [list(comp[o + i * da : o + (i + 1) * da]) for i in range(dx)]
        o += dx * da
        S = [list(comp[o + i * da : o + (i + 1) * da]) for i in range(da)]
        o += da * da
        if self.reading is Reading.DRAW:  # x̂ʲ(k−1) ~ N(x̄ˡ, Pˡ)
            P = [list(comp[o + i * dx : o + (i + 1) * dx]) for i in range(dx)]
            eps = torch.randn(
                (dx,) + x[0].shape, generator=generator, dtype=z.dtype, device=z.device
            )
            low = C.cholesky(P)
            x = [C.lin(((1.0, xi, 1.0), (1.0, li, 1.0))) for xi, li in zip(x, C.mv(low, eps))]
        xpc, F, phi, e, H = self._linearized(x, a, u, y, k, z.dtype)
        dy = len(e)
        if mask is None:
            rinv = [1.0 / v for v in self._rvar]
            logdet_r = sum(math.log(v) for v in self._rvar)
            count = float(dy)
        else:
            mf = mask.to(z.dtype).unsqueeze(-1)  # [..., 1]: one mask for the N particles
            ms = list(mf.movedim(-2, 0).unbind(0))
            rinv = [ms[i] / self._rvar[i] for i in range(dy)]
            logdet_r = sum(ms[i] * math.log(self._rvar[i]) for i in range(dy))
            count = sum(ms)
        we = [C.lin(((1.0, e[i], rinv[i]),)) for i in range(dy)]  # R⁻¹ε
        g = C.mv(C.mt(H), we)  # HᵀR⁻¹ε
        quad = C._dot(zip(e, we))  # εᵀR⁻¹ε
        qi = self._qinv
        Minv, logdet_m = C.sym_inverse(C.gram(H, rinv, qi), logdet=True)  # P = M⁻¹
        ke = C.mv(Minv, g)  # Kε
        D = C.add(C.mm(F, ups), phi)  # FΥ + B
        qd = C.mm(qi, D)  # Q⁻¹D
        new_ups = C.mm(Minv, qd)  # (5e): Υ⁺ = M⁻¹Q⁻¹D
        # DᵀJD with J = Q⁻¹ − Q⁻¹M⁻¹Q⁻¹: JD = Q⁻¹(D − Υ⁺), so DᵀJD = (Q⁻¹D)ᵀ(D − Υ⁺)
        djd = C.mm(C.mt(qd), C.add(D, new_ups, -1.0), upper=True)
        if mask is not None:
            # nothing received: J = 0 and S⁺ = S/λ exactly, but D − Υ⁺ is then a difference
            # of equals whose round-off (about cond(Q)·ε) stays while λS⁻¹ shrinks: S was 10 %
            # off after 50 lost steps in float64 and indefinite after 11 in float32 (a trial)
            nothing = count == 0
            djd = [
                [None if v is None else torch.where(nothing, 0.0, v) for v in row] for row in djd
            ]
        s_inv, _ = C.sym_inverse(S)
        info_a = C.add(djd, s_inv, self.forgetting)  # λS⁻¹ + DᵀJD (upper triangle)
        new_S, _ = C.sym_inverse(info_a)  # (5i): S⁺ = (λS⁻¹ + DᵀJD)⁻¹
        step = C.mv(new_S, C.mv(C.mt(qd), ke))  # Γε = S⁺ DᵀQ⁻¹Kε
        new_a = [C.lin(((1.0, a[i], 1.0), (1.0, step[i], 1.0))) for i in range(da)]
        new_x = [
            C.lin(
                [(1.0, xpc[i], 1.0), (1.0, ke[i], 1.0)]
                + [(1.0, new_ups[i][j], step[j]) for j in range(da)]
            )
            for i in range(dx)
        ]  # fmt: skip  x⁺ = x_p + Kε + Υ⁺Γε
        gk = C._dot(zip(g, ke))
        log_lik = C.lin(((-0.5, quad, 1.0), (0.5, gk, 1.0), (-0.5, logdet_m, 1.0)))
        log_lik = log_lik - 0.5 * (logdet_r + self._logdet_q + count * math.log(2 * math.pi))
        flat = new_x + new_a + [v for row in new_ups for v in row]
        flat += [v for row in new_S for v in row] + [v for row in Minv for v in row]
        shape = torch.broadcast_shapes(*(t.shape for t in flat if isinstance(t, Tensor)))
        flat = [t.expand(shape) if isinstance(t, Tensor) else z.new_full(shape, t) for t in flat]
        # component-major particles: [..., D, N] in memory, seen as [..., N, D]; the
        # resampler gathers along each component row and keeps the layout, and the next
        # step reads the components without a copy
        return torch.stack(flat, -2).transpose(-1, -2), log_lik


class LocalEstimate(NamedTuple):
    """The weighted mixture of one step (module docstring): ``mean [..., dx]``,
    ``cov [..., dx, dx]``, ``attack [..., da]``, ``attack_cov [..., da, da]``."""

    mean: Tensor
    cov: Tensor
    attack: Tensor
    attack_cov: Tensor


def _summary(layout: ParticleLayout, mean: Tensor, cov: Tensor) -> LocalEstimate:
    """Mixture moments from the particles' weighted mean ``[..., D]`` and the covariance
    ``[..., c, c]`` of their first ``c ≥ dx + da`` components (``x̄``, ``ā``)."""
    x, a, _, S, P = layout.unpack(mean)
    dx, da = layout.dx, layout.da
    cx = cov[..., :dx, :dx]
    ca = cov[..., dx : dx + da, dx : dx + da]
    return LocalEstimate(x, symmetrize(P + cx), a, symmetrize(S + ca))


def _form_for(form: Form, attack_cov0: float) -> Form:
    """The form run for ``form`` at ``S₀ = attack_cov0 · I``: the covariance form where
    ``S₀ = 0``. The information form inverts S (S⁺ = (λ S⁻¹ + DᵀJD)⁻¹): with S₀ = 0 every
    proposed particle was NaN at step 2; the covariance form keeps â = 0."""
    if attack_cov0 != 0:
        return form
    if form is Form.INFORMATION:
        raise ValueError("attack_cov0 = 0 (S₀ = 0) needs form='covariance': the "
                         "information form inverts the attack covariance S")  # fmt: skip
    return Form.COVARIANCE


def _singular_attack_cov(state: ParticleState, layout: ParticleLayout) -> bool:
    """Whether any particle's attack covariance ``S`` of ``state`` is singular (``S₀ = 0``:
    :func:`adaptive_particle_init` with ``attack_cov0=0``)."""
    S = layout.unpack(state.particles)[3]
    return bool((torch.linalg.cholesky_ex(S.detach())[1] != 0).any())


def _form_for_state(form: Form | str, state: ParticleState, model: StateSpaceModel) -> Form:
    """The form the one-call wrappers run ``state`` with: ``"auto"`` takes the covariance
    form for a state whose ``S`` is singular, as an estimator of ``attack_cov0=0`` does
    (they had run the information form from such a state: NaN means and scores from
    :func:`adaptive_particle_step`, a failure naming neither S₀ nor the form from
    :func:`adaptive_particle_filter`; an MDPF trial)."""
    form = Form(form)
    if form is Form.AUTO and _singular_attack_cov(state, ParticleLayout(model.dim_x, model.dim_u)):
        return Form.COVARIANCE
    return form


def adaptive_particle_init(
    model: StateSpaceModel,
    num_particles: int,
    batch_shape=(),
    generator: torch.Generator | None = None,
    *,
    attack_cov0: float = 10.0,
) -> ParticleState:
    """Packed particles ``[*batch_shape, N, D]`` at ``k = 0``: ``x̄ʲ ~ p(x_0)`` (from
    ``generator``), ``āʲ = 0``, ``Υʲ = 0``, ``Sʲ = attack_cov0 · I``, ``Pʲ = 0`` (the
    components are the prior's samples), uniform log-weights."""
    check_one_model(model, "the adaptive particle filter", PER_SET)
    _check_zero_mean_noise(model)  # (its Kalman proposals read the covariances alone)
    # as the adaptive KF's (A1): a negative ω had run, Ŝ negative from then on (a trial)
    attack_cov0 = check_finite_number(attack_cov0, "attack_cov0", nonnegative=True)
    num_particles = check_positive_int(num_particles, "num_particles")
    layout = ParticleLayout(model.dim_x, model.dim_u)
    shape = torch.Size(batch_shape) + (num_particles,)
    x = model.sample_initial(shape, generator)
    dx, da = model.dim_x, model.dim_u
    eye = torch.eye(da, dtype=x.dtype, device=x.device)
    packed = layout.pack(
        x, x.new_zeros(shape + (da,)), x.new_zeros(shape + (dx, da)),
        (float(attack_cov0) * eye).expand(shape + (da, da)), x.new_zeros(shape + (dx, dx)),
    )  # fmt: skip
    log_w = x.new_full(shape, -math.log(num_particles))
    return ParticleState(packed, log_w, 0)


class AdaptiveParticleFilter(Estimator):
    """The local estimator (A1)–(A8) as an estimator object (module docstring).

    Args:
        num_particles: ``M``.
        forgetting: ``λ ∈ (0, 1]``.
        reading: :class:`Reading` (eq. 5).
        form: :class:`Form` (:class:`AdaptiveKalmanProposal`).
        attack_cov0: ``S_0 = ω I``, ``ω ≥ 0``.
        resampler: default ``Multinomial()`` (the inverse-CDF selection of App. A), at
            every step.
        false_alarm_rate: of the Wald test on ``(â, Ŝ)``.

    The model needs inputs (the attack enters through them, ``dim_a = dim_u``); its
    ``process_cov`` is the ``Q`` of (A4). Carry: a :class:`~difffilter.ParticleState` of
    packed particles (:class:`ParticleLayout`) whose ``model`` is the
    :class:`ParticleView` of the model; ``init`` draws ``x̄ʲ`` from ``generators.init``,
    the ``DRAW`` reading from ``generators.propagate``, the selection uniforms from
    ``generators.resample``. Step output: the mixture ``mean``, ``cov``, ``attack`` ``â``
    (the attack on ``u_{k−1}``), the Wald score with its alarm and threshold, and
    ``extras`` ``"attack_covs"`` ``Ŝ`` and ``"ess"`` (before resampling).
    """

    carry_type = ParticleState

    def __init__(
        self,
        num_particles: int = 100,
        *,
        forgetting: float = 0.7,
        reading: Reading | str = Reading.DRAW,
        form: Form | str = Form.AUTO,
        attack_cov0: float = 10.0,
        resampler=None,
        false_alarm_rate: float = 0.01,
    ):
        reading, form = Reading(reading), Form(form)
        check_strategy(resampler, "resampler", "difffilter.resampling.Multinomial()")
        # checked here, as the adaptive KF's: a bad rate had failed only at the first step,
        # naming no argument; a count of 0 or 2.5 with a raw torch error (a trial)
        self.num_particles = check_positive_int(num_particles, "num_particles")
        self.forgetting = _check_forgetting(forgetting)
        self.attack_cov0 = check_finite_number(attack_cov0, "attack_cov0", nonnegative=True)
        # the form asked for, kept: ``form`` is the one run, which attack_cov0 = 0 decides
        self._form_asked = form
        self.reading, self.form = reading, _form_for(form, self.attack_cov0)
        self.resampler = resampler if resampler is not None else Multinomial()
        self.false_alarm_rate = check_rate(false_alarm_rate, "false_alarm_rate")
        # (model, its packed view, the particle filter that steps it) of the last model
        # stepped: derived constants only. One, not one per model: a dict of every model
        # ever stepped had kept them all alive with the estimator and pickled them with it
        # (30 models: 5.7 → 136 kB; a serialisation trial)
        self._last: tuple | None = None

    def __getstate__(self) -> dict:
        """The options alone (the estimator holds nothing else): the last model's filter is
        made again on first use."""
        return {**self.__dict__, "_last": None}

    #: The options the particle filter of :meth:`filter_for` is made from. One replaced
    #: after ``__init__`` is checked as ``__init__`` checks it, the cached filter is made
    #: again, and the next step validates its carry in full (cached on the model alone,
    #: ``apf.forgetting = 0.99`` had never been read, and ``num_particles = 20`` had gone on
    #: stepping 50 particles: a red-team trial).
    _FILTER_OPTIONS = frozenset(
        {"num_particles", "forgetting", "reading", "form", "attack_cov0", "resampler"}
    )
    _CHECKED_OPTIONS = _FILTER_OPTIONS | {"false_alarm_rate"}

    def __setattr__(self, name, value):
        if name not in self._CHECKED_OPTIONS or name not in self.__dict__:
            super().__setattr__(name, value)
            return
        if name == "false_alarm_rate":  # read at every step: checked, nothing to make again
            super().__setattr__(name, check_rate(value, "false_alarm_rate"))
            return
        if name == "num_particles":
            value = check_positive_int(value, "num_particles")
        elif name == "forgetting":
            value = _check_forgetting(value)
        elif name == "reading":
            value = Reading(value)
        elif name == "form":  # (the asked form against the current S₀)
            asked = Form(value)
            value = _form_for(asked, self.attack_cov0)
            super().__setattr__("_form_asked", asked)
        elif name == "attack_cov0":  # (the form S₀ = 0 allows, checked before either is set)
            value = check_finite_number(value, "attack_cov0", nonnegative=True)
            form = _form_for(self.__dict__.get("_form_asked", self.form), value)
            super().__setattr__("form", form)
        else:  # resampler
            check_strategy(value, "resampler", "difffilter.resampling.Multinomial()")
            value = value if value is not None else Multinomial()
        super().__setattr__(name, value)
        super().__setattr__("_last", None)
        note_assignment()

    def filter_for(self, model: StateSpaceModel) -> tuple[ParticleView, ParticleFilter]:
        """The packed view of ``model`` and the particle filter that steps it."""
        last = self._last
        if last is None or last[0] is not model:
            layout = ParticleLayout(model.dim_x, model.dim_u)
            pf = ParticleFilter(
                self.num_particles, resampler=self.resampler,
                proposal=AdaptiveKalmanProposal(model, self.forgetting, self.reading, self.form),
                likelihood=FlatLikelihood(), ess_threshold=1.0, innovations=False,
                cov_dims=layout.dx + layout.da,
            )  # fmt: skip
            self._last = last = (model, ParticleView(model, layout), pf)
        return last[1], last[2]

    def attach(self, state: ParticleState, model, generators: Generators) -> ParticleState:
        """Packed particles (:func:`adaptive_particle_init`) as this estimator's carry.
        A state whose attack covariance ``S`` is singular in some particle (``S₀ = 0``)
        needs the covariance form: refused where the information form would step it."""
        view, pf = self.filter_for(model)
        carry = pf.attach(state, view, generators)
        if pf.proposal.form is Form.INFORMATION and _singular_attack_cov(state, view.layout):
            raise ValueError(
                "the state's attack covariance S is singular in some particle (S₀ = 0: "
                "adaptive_particle_init(attack_cov0=0)), and the information form inverts S: "
                "give the estimator attack_cov0=0 or form='covariance'"
            )
        return carry

    def _init(self, model, batch_shape, generators):
        if model.dim_u < 1:
            raise ValueError("the adaptive particle filter needs a model with inputs (dim_u >= 1)")
        state = adaptive_particle_init(
            model, self.num_particles, batch_shape, generators.init, attack_cov0=self.attack_cov0
        )
        return self.attach(state, model, generators)

    def batch_of(self, carry):
        return carry.log_weights.shape[:-1]

    def _check_carry(self, carry):
        if not isinstance(carry.model, ParticleView):
            raise ValueError("carry.model must be the ParticleView of AdaptiveParticleFilter.init")
        _check_zero_mean_noise(carry.model.base)
        view, pf = self.filter_for(carry.model.base)
        pf._check_carry(carry)
        # as attach refuses it: a hand-built S₀ = 0 state had stepped to NaN means in the
        # information form (a hand-built-carries trial)
        if pf.proposal.form is Form.INFORMATION and _singular_attack_cov(carry, view.layout):
            raise ValueError(
                "carry.particles hold an attack covariance S that is singular in some particle "
                "(S₀ = 0: adaptive_particle_init(attack_cov0=0)), and the information form "
                "inverts S: give the estimator attack_cov0=0 or form='covariance'"
            )

    def _step(self, carry, y, u, mask):
        base = carry.model.base
        _, pf = self.filter_for(base)
        carry, out = pf._step(carry, y, u, mask)
        est = _summary(pf.proposal.layout, out.mean, out.cov)
        score = wald_statistic(est.attack, est.attack_cov)
        threshold = chi_square_upper_quantile(base.dim_u, self.false_alarm_rate)
        return carry, StepOutput(
            est.mean, est.cov, attack=est.attack, score=score, alarm=score > threshold,
            threshold=threshold, extras={"attack_covs": est.attack_cov, "ess": out.extras["ess"]},
        )  # fmt: skip


def adaptive_particle_step(
    model: StateSpaceModel,
    state: ParticleState,
    y: Tensor,
    u: Tensor | None = None,
    mask: Tensor | None = None,
    *,
    forgetting: float = 0.7,
    reading: Reading | str = Reading.DRAW,
    form: Form | str = Form.AUTO,
    resampler=None,
    generator: torch.Generator | None = None,
    resample_generator: torch.Generator | None = None,
    false_alarm_rate: float = 0.01,
) -> tuple[ParticleState, StepOutput]:
    """One online step ``k−1 → k`` of :class:`AdaptiveParticleFilter`: resample, (A2)–(A8).

    ``state`` from :func:`adaptive_particle_init` (or an earlier step); ``y [..., dy]``,
    ``u [..., du]``; ``false_alarm_rate`` as in :class:`AdaptiveParticleFilter` (the step
    output's alarm; the whole-sequence function took it, this step had not). Returns the new
    state and the step output.
    """
    apf = AdaptiveParticleFilter(
        state.log_weights.shape[-1], forgetting=forgetting, reading=reading,
        form=_form_for_state(form, state, model), resampler=resampler,
        false_alarm_rate=false_alarm_rate,
    )  # fmt: skip
    y, u, mask = check_step_inputs(model, None, y, u, mask)
    gens = Generators(None, generator, resample_generator or generator)
    return apf._step(apf.attach(state, model, gens), y, u, mask)


def adaptive_particle_filter(
    model: StateSpaceModel,
    ys: Tensor,
    us: Tensor | None = None,
    *,
    mask: Tensor | None = None,
    num_particles: int = 100,
    forgetting: float = 0.7,
    reading: Reading | str = Reading.DRAW,
    form: Form | str = Form.AUTO,
    attack_cov0: float = 10.0,
    resampler=None,
    generator: torch.Generator | None = None,
    resample_generator: torch.Generator | None = None,
    initial_state: ParticleState | None = None,
    false_alarm_rate: float = 0.01,
) -> EstimatorOutput:
    """The local estimator (A1)–(A8) over a sequence: :class:`AdaptiveParticleFilter` in
    the open loop.

    Args:
        model: a :class:`~difffilter.StateSpaceModel` with inputs.
        ys: ``[..., T, dy]``; us: commanded inputs ``[..., T, du]`` or ``None``.
        mask: received entries ``[..., T, dy]`` or ``None``.
        num_particles, forgetting, reading, form, attack_cov0, resampler,
            false_alarm_rate: as in :class:`AdaptiveParticleFilter`.
        generator: initial particles and the ``DRAW`` noise; resample_generator: the
            selection uniforms (default ``generator``).
        initial_state: packed particles (:func:`adaptive_particle_init`) instead of the prior.

    Returns an :class:`~difffilter.EstimatorOutput` with the mixture ``means [..., T, dx]``,
    ``covs``, ``attack`` ``â_k [..., T, du]`` (the attack on ``u_{k−1}``), a Wald
    :class:`~difffilter.Detection` on ``(â, Ŝ)`` and ``extras`` ``"attack_covs"``
    ``Ŝ [..., T, du, du]``, ``"ess" [..., T]`` (before resampling).
    """
    if model.dim_u < 1:
        raise ValueError("the adaptive particle filter needs a model with inputs (dim_u >= 1)")
    if initial_state is not None:  # (its S, not attack_cov0, decides what "auto" can run)
        form = _form_for_state(form, initial_state, model)
    apf = AdaptiveParticleFilter(
        num_particles, forgetting=forgetting, reading=reading, form=form,
        attack_cov0=attack_cov0, resampler=resampler, false_alarm_rate=false_alarm_rate,
    )  # fmt: skip
    gens = Generators.of(generator)
    if resample_generator is not None:
        gens = gens._replace(resample=resample_generator)
    carry = None if initial_state is None else apf.attach(initial_state, model, gens)
    return open_loop(apf, model, ys, us, mask=mask, generator=gens, carry=carry)
