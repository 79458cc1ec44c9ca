"""A fused, low-overhead modified particle filter (real-time and benchmark path).

:func:`~difffilter.fdi.modified_pf.modified_particle_filter` composes the generic PF
parts and is the reference implementation. For small particle sets (a single run at
``N = 100``) its cost is the number of tensor operations per step, not arithmetic, so
this module runs the same algorithm (Table 2 with a given ``γ̂``, known ``ζ``, bootstrap
propagation, systematic resampling at every step) with about twenty kernels per step:

* the propagation noise of the whole horizon is drawn in one call (when ``B·N·dx`` is a
  multiple of 16 — torch's CPU normal sampler works in blocks of 16 — this gives exactly
  the numbers that per-step draws give, so the two paths share their random numbers);
* the resampling uniforms of the whole horizon are drawn in one call (likewise exact);
* ``G = I`` and a diagonal ``R`` skip their matrix products; weights after resampling are
  uniform, so eq. (59) is a softmax of the log-likelihoods and eq. (58) a count;
* the model's ``transition`` is called as is (the four-tank model evaluates its Euler
  step as one affine map of ``√max(x, 0)``).

With the same generators the result equals the composed filter's up to round-off
(tests check it); ties in the resampling CDF at the level of 1e-16 could in principle
pick a different ancestor.
"""

from __future__ import annotations

import math
import numbers

import torch
from torch import Tensor

from .._checks import check_finite, check_finite_number, check_fraction, version_stamp
from ..estimator import Detection, EstimatorOutput
from ..noise import Gaussian
from ..particle import _ess, particle_init
from ..resampling import systematic_ancestors
from .poa import modified_pf_gain

__all__ = ["FusedModifiedPF"]


def _check_measurement_noise(model) -> None:
    """Eq. (59)'s weights are written for ``N(y − Gx; 0, R)``: a noise of non-zero mean had
    been weighed as zero-mean, 0.124 off the composed filter, and any other noise as a
    Gaussian (a trial)."""
    noise = model.measurement_noise
    if type(noise) is not Gaussian or not noise._zero_loc():
        raise ValueError(
            "FusedModifiedPF needs a zero-mean Gaussian measurement noise "
            f"(difffilter.noise.Gaussian); got {type(noise).__name__}"
            f"{'' if type(noise) is not Gaussian else ' of non-zero mean'}: use "
            "modified_particle_filter"
        )


class FusedModifiedPF:
    """The modified PF of Table 2 with oracle (given) ``γ̂``, in few tensor ops per step.

    Args:
        model: a time-invariant model with a linear measurement (``observation_matrix``),
            Gaussian process and measurement noise, no inputs.
        num_particles: ``N``.
        eta: residual-norm threshold ``η`` (Theorem 1); zeta: PoA threshold ``ζ``.

    Equivalent to ``modified_particle_filter(model, ys, num_particles=N,
    detector=PoADetector(eta, zeta), gamma_hat=gamma_hat, ess_threshold=1.0,
    resampler=Systematic(), generator=g, resample_generator=r)``.
    """

    def __init__(self, model, *, num_particles: int, eta: float, zeta: float):
        if getattr(model, "time_varying", False):
            raise ValueError(
                "FusedModifiedPF needs a time-invariant model (model.time_varying must be False)"
            )
        if not hasattr(model, "observation_matrix"):
            raise ValueError(
                "FusedModifiedPF needs a linear measurement: model must provide observation_matrix(k)"
            )
        _check_measurement_noise(model)
        self.model, self.n, self.eta, self.zeta = model, num_particles, eta, zeta  # (checked)
        self._derived = None
        self._derive()  # (a model it cannot run is refused here, not at the first run)

    def __setattr__(self, name, value):
        # checked whenever set (zeta = 1.5 or NaN assigned later had never alarmed, eta = -1
        # acted as +1, n = 1 ran one particle: a trial), as the constructor checks them
        if name == "n":
            if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 2:
                raise ValueError(f"num_particles must be an integer >= 2; got {value!r}")
            value = int(value)
        elif name == "eta":
            value = check_finite_number(value, "eta", nonnegative=True)
        elif name == "zeta":
            value = check_fraction(value, "zeta")
        super().__setattr__(name, value)

    def _derive(self) -> None:
        """The measurement's constants (``Gᵀ``, the detector map, ``R``'s precision or
        whitening) from the model as it is now: kept while its tensors are the same and
        unwritten (made once at construction, an H, R or Q changed since had run with the
        old ones: means 0.85-1.21 off a filter built on the changed model; a trial)."""
        model = self.model
        _check_measurement_noise(model)
        G = model.observation_matrix(1)
        R, Q = model.measurement_cov(1), model.process_cov(0)
        stamp = tuple((t, version_stamp(t)) for t in (G, R, Q))
        if self._derived is not None and all(
            a is b and va == vb for (a, va), (b, vb) in zip(self._derived, stamp)
        ):
            return
        self._derive_from(G, R, Q)
        self._derived = stamp

    def _derive_from(self, G: Tensor, R: Tensor, Q: Tensor) -> None:
        model = self.model
        R = model.measurement_cov(1)
        K = modified_pf_gain(G.double(), Q.double(), R.double()).to(G.dtype)  # (float64 gain)
        dy = G.shape[-2]
        eye = torch.eye(dy, dtype=G.dtype, device=G.device)
        # r = y − x only where G is the square identity (a rectangular [I 0] measures a part)
        identity = G.shape[0] == G.shape[1] and torch.equal(G, eye)
        self.G_t = None if identity else G.transpose(0, 1)
        detect = eye - G @ K  # z̃⁺ = (I − GK) r, eqs 36, 58
        if torch.equal(detect, torch.diag(torch.diagonal(detect))):
            # ‖(I − GK) r‖² = (r ⊙ r) · diag(I − GK)²: no matrix product
            self.detect_map, self.detect_sq = None, torch.diagonal(detect).square()
        else:
            self.detect_map, self.detect_sq = (
                detect.transpose(0, 1),
                torch.ones(dy, dtype=G.dtype, device=G.device),
            )
        diag = torch.diagonal(R)
        if torch.equal(R, torch.diag(diag)):
            self.neg_half_prec, self.whiten = -0.5 / diag, None
        else:
            chol = torch.linalg.cholesky(R)
            self.neg_half_prec = -0.5 * torch.ones(dy, dtype=G.dtype, device=G.device)
            self.whiten = torch.linalg.solve_triangular(chol, eye, upper=False).transpose(0, 1)

    def _start(self, B, T, generator, resample_generator, initial_particles):
        """The particles before step 1 ``[B, N, dx]`` (resampled once if the prior weights
        ask for it), the resampling uniforms of the horizon and the resampler."""
        model, n = self.model, self.n
        if initial_particles is None:
            state = particle_init(model, n, (B,), generator)
            x, log_w0 = state.particles, state.log_weights
        else:
            if initial_particles.shape != (B, n, model.dim_x):
                raise ValueError(
                    f"initial_particles must be [{B}, {n}, {model.dim_x}]; got {tuple(initial_particles.shape)}"
                )
            x = initial_particles
            log_w0 = x.new_full((B, n), -math.log(n))
        dx, dtype, device = x.shape[-1], x.dtype, x.device
        # Resampling uniforms in the order the composed filter draws them: before step 0
        # only if the ESS of the uniform prior weights rounds below N, then after every step.
        first = bool((_ess(log_w0) < n).any())
        uniforms = torch.rand(
            (T - 1 + int(first), B, 1), generator=resample_generator, dtype=dtype, device=device
        )
        resample = _CountResampler(B, n, dtype, device)
        flat = x.reshape(B * n, dx)
        if first:
            w0 = torch.exp(log_w0 - torch.logsumexp(log_w0, -1, keepdim=True))
            flat = flat.index_select(0, resample(torch.cumsum(w0, -1), uniforms[0]))
            uniforms = uniforms[1:]
        return flat.view(B, n, dx), uniforms, resample

    def _propagation(self, B, dtype, draw):
        """``x ↦ f(x) + w_t`` for the particles ``[B, N, dx]``. Small sets: a model whose
        step is ``x + c + √max(x,0) @ M`` (the four-tank) runs as one addmm with ``c``
        folded into the noise; large sets keep the model's elementwise transition (a GEMM
        with 4 columns is slow for many rows on CPU)."""
        model, n = self.model, self.n
        affine = getattr(model, "sqrt_affine_form", None)
        affine = affine() if (affine is not None and B * n <= 2048) else None
        if affine is None:
            return lambda x, t: model.transition(x, None, t) + draw(t)
        step_matrix, offset = affine[0].to(dtype), affine[1].to(dtype)

        def propagate(x, t):
            flat = x.reshape(B * n, -1)
            s = torch.sqrt(flat.clamp_min(0.0))
            return torch.addmm(flat + draw.plus(t, offset), s, step_matrix).view(x.shape)

        return propagate

    @torch.inference_mode()
    def run(
        self,
        ys: Tensor,
        gamma_hat: Tensor,
        *,
        generator: torch.Generator | None = None,
        resample_generator: torch.Generator | None = None,
        initial_particles: Tensor | None = None,
    ) -> EstimatorOutput:
        """Filter ``ys [B, T, dy]`` with ``γ̂`` ``[B, T, dy]``.

        ``initial_particles [B, N, dx]`` (default drawn from the prior with
        ``generator``, as :func:`~difffilter.particle.particle_init` does); ``generator``
        then draws the propagation noise and ``resample_generator`` the resampling
        uniforms. Without ``resample_generator`` the uniforms come from ``generator`` too
        (never from torch's global generator when a generator is given), so two runs
        with equally seeded generators are identical; the draws are then ordered
        differently from the composed filter's, which interleaves them.
        """
        if resample_generator is None:
            resample_generator = generator
        if ys.dim() != 3 or gamma_hat.shape != ys.shape:
            raise ValueError(
                f"ys must be [B, T, dy] and gamma_hat the same shape; got {tuple(ys.shape)}, {tuple(gamma_hat.shape)}"
            )
        # (a NaN made every weight NaN and the resampler an index of −2⁶³)
        check_finite(ys, "ys")
        check_finite(gamma_hat, "gamma_hat")
        self._derive()
        n, (B, T, _) = self.n, ys.shape
        x, uniforms, resample = self._start(B, T, generator, resample_generator,
                                            initial_particles)  # fmt: skip
        dx, dtype = x.shape[-1], x.dtype
        draw = _NoiseSampler(self.model.process_noise, (B, n), T, generator)
        propagate = self._propagation(B, dtype, draw)
        ys3 = ys.unsqueeze(-2)
        G_t, dmap, dsq = self.G_t, self.detect_map, self.detect_sq
        whiten, nhp = self.whiten, self.neg_half_prec
        # eq. (59) without forming r − l̂γ̂: Σ_d p_d (r_d − c_d)² = Σ p_d r_d² − 2 Σ p_d c_d r_d + const
        # (p = −½ diag R⁻¹ after whitening); the constant cancels in the normalisation.
        gam = gamma_hat if whiten is None else gamma_hat @ whiten  # [B, T, dy]
        comp = (-2.0 * nhp) * gam
        # below float64 the expanded form's two terms cancel where γ̂ is large (the mean
        # 2.5e-3 off at γ̂ = 20, 1.3e-2 at 50, where the composed filter is 2.4e-6 off; a
        # trial): there the weights take Σ p_d (r_d − c_d)² itself
        direct = dtype != torch.float64
        eta2 = self.eta**2
        both = torch.stack([dsq, nhp], -1) if (dmap is None and whiten is None) else None
        means, counts, alarms = [], [], []
        for t in range(T):
            x = propagate(x, t)  # Step 1: x_k^i ~ p(x_k | x_{k−1}^i)
            # Step 2: Kalman-corrected residuals (36) and PoA with weights 1/N (58):
            # β = #{‖(I − GK) r^i‖ > η} / N
            r = ys3[:, t] - (x if G_t is None else x @ G_t)
            z = r if dmap is None else r @ dmap
            zz = z * z
            if both is not None:  # one product gives ‖z̃⁺‖² and Σ p_d r_d² (z = r here)
                quad = zz @ both
                count = (quad[..., 0] > eta2).sum(-1)
                rr_p = quad[..., 1:]
            else:
                count = (zz @ dsq > eta2).sum(-1)
            # β̃ = count/N > ζ in the particles' dtype, as the steps compare it (count > ζN
            # compared an int64 count with a float in float32: 99.9999998 read as 100)
            alarm = count.to(dtype) / n > self.zeta
            # Step 3-1: weights of the uncorrected particles with ỹ − l̂ γ̂ (59)
            if whiten is not None and (direct or both is None):
                r = r @ whiten
            if direct:
                d = r - (gam[:, t] * alarm.unsqueeze(-1).to(dtype)).unsqueeze(-2)
                w = torch.softmax((d * d) @ nhp, -1)
            else:
                if both is None:
                    rr_p = ((r * r) @ nhp).unsqueeze(-1)
                c = (comp[:, t] * alarm.unsqueeze(-1)).unsqueeze(-1)  # [B, dy, 1]
                w = torch.softmax(rr_p.baddbmm(r, c).squeeze(-1), -1)
            # Step 3-2: x̂_k = Σ w^i x^i (60)
            means.append((w.unsqueeze(1) @ x).squeeze(1))
            counts.append(count)
            alarms.append(alarm)
            if t < T - 1:  # systematic resampling for the next step
                ancestors = resample(torch.cumsum(w, -1), uniforms[t])
                x = x.reshape(B * n, dx).index_select(0, ancestors).view(B, n, dx)
        beta = torch.stack(counts, 1).to(dtype) / n
        alarms = torch.stack(alarms, 1)
        return EstimatorOutput(
            means=torch.stack(means, 1),
            attack=alarms.unsqueeze(-1).to(dtype) * gamma_hat,
            detection=Detection(beta, alarms, self.zeta),
            extras={"gamma_hat": gamma_hat},
        )


class _NoiseSampler:
    """Process-noise draws ``[B, N, dx]`` per step, the same numbers as ``noise.sample((B, N), g)``.

    A diagonal Gaussian is sampled as ``loc + ε ⊙ σ`` with ``ε`` from ``torch.randn`` in
    the shape ``Gaussian.sample`` uses and ``σ`` tiled to full size (broadcasting a
    length-``dx`` vector is a slow kernel); the horizon is drawn at once when that gives
    the same numbers as per-step draws (``B·N·dx`` a multiple of 16) and is small.
    Other noise models call ``noise.sample`` each step.
    """

    def __init__(self, noise, shape, T, generator):
        self.noise, self.shape, self.generator = noise, shape, generator
        # (set before the early return: plus() read it, and a full Q failed on a missing
        # attribute where the small-set propagation shifts the draws)
        self._shifted, self.all = None, None
        L = noise.scale_tril if isinstance(noise, Gaussian) else None
        self.diag = L is not None and L.dim() == 2 and torch.equal(L, torch.diag(torch.diagonal(L)))
        if not self.diag:
            return
        d = L.shape[-1]
        numel = math.prod(shape) * d
        self.full = torch.Size(shape) + (d,)
        self.std = torch.diagonal(L).repeat(numel // d).view(self.full)
        self.loc = None if not bool(noise.loc.any()) else noise.loc.expand(self.full).contiguous()
        self.all = None
        if numel % 16 == 0 and numel * T <= 400_000:
            eps = torch.randn((T,) + self.full, generator=generator, dtype=L.dtype, device=L.device)
            self.all = eps * self.std if self.loc is None else eps * self.std + self.loc

    def plus(self, t: int, offset: Tensor) -> Tensor:
        """Draw ``t`` plus ``offset`` ``[dx]``, flattened to ``[B·N, dx]`` (the horizon shifted at once)."""
        if self.all is not None:
            if self._shifted is None or self._shifted[0] is not offset:
                self._shifted = (
                    offset,
                    (self.all + offset).view(self.all.shape[0], -1, offset.shape[-1]),
                )
            return self._shifted[1][t]
        return (self(t) + offset).view(-1, offset.shape[-1])

    def __call__(self, t: int) -> Tensor:
        if not self.diag:
            return self.noise.sample(self.shape, self.generator)
        if self.all is not None:
            return self.all[t]
        eps = torch.randn(
            self.full, generator=self.generator, dtype=self.std.dtype, device=self.std.device
        )
        out = eps * self.std
        return out if self.loc is None else out + self.loc


class _CountResampler:
    """Systematic ancestors (:func:`~difffilter.resampling.systematic_ancestors`, the
    algorithm of :class:`~difffilter.resampling.Systematic`) as flat indices into the
    ``[B·N]`` particle rows; ``u`` is the row's uniform ``[B, 1]``."""

    def __init__(self, B, n, dtype, device):
        self.offset = (torch.arange(B, device=device) * n).unsqueeze(1)

    def __call__(self, cdf: Tensor, u: Tensor) -> Tensor:
        return systematic_ancestors(cdf, u).add_(self.offset).view(-1)
