"""The one-run particle-filter step on host arrays, for steps that record no gradient.

On one run of ``N = 100`` particles a torch operation on the CPU costs 2–4 µs of dispatch
for well under a microsecond of arithmetic; the same operation on a numpy array costs about
1 µs. The written-out one-run step (:mod:`difffilter._pf_single_run`) is a few dozen such
operations, so its dispatch is its cost. When autograd records nothing (under
``torch.no_grad()`` or ``torch.inference_mode()``: an estimator deployed on one plant) and
the run lives in CPU memory, :func:`host_step` computes that step's arithmetic on numpy
views of the same memory (``Tensor.numpy()`` and ``torch.from_numpy``: no copies) and
calls the model through torch as every other step does (``transition``, ``observe``,
``measurement_residual``, the noise's factor)::

    resample   if ESS_{k−1} < ess_threshold · N:  a_j = F⁻¹((j + U)/N),  x ← x[a],
               log w ← −log N
    propose    x_k^i = f(x^i, u) + ε^i                 (torch: the model and the draw)
    predict    x̄_k = Σᵢ wᵢ x_k^i;  ŷ = Σᵢ wᵢ h(x_k^i),  S = Σᵢ wᵢ (h − ŷ)(h − ŷ)ᵀ + R
    weight     log w_k^i = log w^i − ½ r_iᵀ R⁻¹ r_i − log p̂,   r_i = y_k − h(x_k^i)
               (under a mask of received entries, the density of those entries alone,
               and the predictive moments of :func:`~difffilter.linalg.masked_measurement`,
               as the general step's: a lossy network's measurement)
    report     x̂_k = Σᵢ w_k^i x_k^i,  P_k = Σᵢ w_k^i (x_k^i − x̂_k)(x_k^i − x̂_k)ᵀ,
               ESS_k = 1 / Σᵢ (w_k^i)²,  log p̂(y_k | y_{1:k−1}) (the evidence)

The same draws from the same generators in the same order as the torch step (the uniform
offset of the systematic resampler and the process noise are drawn by torch), so the same
numbers up to round-off (tests: against the general step, float64 and float32). One
round-off matters in float32: ``np.cumsum`` and ``torch.cumsum`` add in other orders (6e-6
apart at N = 1,000), so a target within that of a boundary of the cumulative weights takes
the neighbouring ancestor (about two of 1,000 per resampling there). That is a draw of the
same resampling law, and from it on the particles go apart as two filters' do (3e-3 in the
four-tank mean after 10 steps at N = 1,000); float64 and N = 100 stay within round-off. A
measurement every particle finds impossible is reset as there (the evidence ``−∞``, the
predictive weights kept, the step flagged ``"degenerate"``), and a NaN particle or density
is named in the general step's error (:func:`~difffilter.particle._blame_degenerate`), not
taken for one. Left to the torch step: a
measurement noise other than a zero-mean diagonal Gaussian of the particles' dtype,
half-precision dtypes, other devices, and any step that could record a gradient.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

# the module, not its function: importing _pf_single_run imports particle, which imports this
from . import _pf_single_run as _single_run
from .estimator import Generators
from .linalg import LOG_2PI, under_transform
from .noise import Gaussian
from .particle import ParticleState, _blame_degenerate, _ess
from .results import StepOutput
from .ssm import StateSpaceModel, inputs_per_point, wrapped_spread

__all__ = ["density", "host_step"]

_NO_GENERATORS = Generators()
_HOST_DTYPES = (torch.float32, torch.float64)


def density(carry, y: Tensor, u: Tensor | None) -> tuple[np.ndarray, np.generic, np.ndarray] | None:
    """The measurement density's diagonal terms (:func:`_diagonal_density`) when
    :func:`host_step` may compute a one-run step from ``carry``, else ``None``: no gradient
    can be recorded (grad mode off, no input that requires one), the particles live in
    CPU memory in float32 or float64, and the measurement noise is a diagonal zero-mean
    Gaussian of the particles' dtype (a noise of another dtype is refused by the step's
    full validation, :func:`~difffilter._checks.check_model`; the others keep the torch
    step), and no forward-mode level or ``torch.func`` transform is active."""
    particles = carry.particles
    if torch.is_grad_enabled() or particles.device.type != "cpu":
        return None
    # forward mode under no_grad (a dual model reports requires_grad=False): numpy would
    # drop its tangents silently (a gradients trial's online particle filter had none)
    if under_transform():
        return None
    if particles.dtype not in _HOST_DTYPES or particles.requires_grad:
        return None
    if carry.log_weights.requires_grad or y.requires_grad or (u is not None and u.requires_grad):
        return None
    return _diagonal_density(carry.model.measurement_noise, particles.dtype)


def _diagonal_density(
    noise, dtype: torch.dtype
) -> tuple[np.ndarray, np.generic, np.ndarray] | None:
    """``(1/σ² [dy], Σ log σ + (dy/2) log 2π, log σ [dy])`` as host arrays of a zero-mean
    Gaussian with a diagonal factor ``σ``, else ``None`` (``log σ``: the constant of the
    received entries alone, under a mask). The noise model caches its factor against
    the covariance's version (a changed covariance is a new factor); the host terms are
    kept against the very factor they were computed from. ``None`` too for a factor not
    of ``dtype``."""
    global _LAST_TERMS
    if type(noise) is not Gaussian:
        return None
    _, diag = noise._factor()
    if diag is None or diag.dim() != 1 or diag.dtype != dtype or not noise._zero_loc():
        return None
    last = _LAST_TERMS
    if last is not None and last[0] is diag:
        return last[1]
    inv_var, constant = (t.detach() for t in noise._diagonal_terms(diag))
    host = (inv_var.numpy().copy(), constant.numpy()[()], torch.log(diag.detach()).numpy())
    _LAST_TERMS = (diag, host)  # held: its identity stays its own
    return host


#: ``(σ, host terms)`` of the last density read (one entry: an online filter's one plant).
_LAST_TERMS: tuple | None = None


def host_step(
    pf, carry, y: Tensor, u: Tensor | None, density, mask: Tensor | None = None
) -> tuple[ParticleState, StepOutput]:
    """One step of ``pf`` from ``carry`` on host arrays (module docstring):
    ``(ParticleState, StepOutput)`` as the torch step returns them. ``density``: what
    :func:`density` returned for these inputs.

    Shapes: particles ``[N, dx]``, log-weights ``[N]``, ``y [dy]`` (zero where unreceived),
    ``u [du]`` or ``None``, ``mask [dy]`` (bool, the received entries) or ``None``.
    """
    model, gens, k = carry.model, carry.generators or _NO_GENERATORS, carry.k
    # (views of torch's negative bit, `z.conj().imag`, resolved: numpy reads none, and the
    # step had failed in torch's "negative bit set": a memory-layout trial)
    x_t, log_w = carry.particles, carry.log_weights.resolve_neg().numpy()
    w = None if carry.weights is None else carry.weights.resolve_neg().numpy()
    n, dtype = log_w.shape[0], log_w.dtype.type
    # a carry without its ESS (from init): torch's, so that the first decision to resample
    # is the torch steps' (a host log-sum-exp rounds otherwise: ess_threshold = 1 split them)
    ess = (carry.ess if carry.ess is not None else _ess(carry.log_weights)).item()
    # the torch step compares in the weights' dtype: so does this one
    resampled = ess < float(dtype(pf.ess_threshold * n))
    if resampled:
        gen = gens.resample if gens.resample is not None else gens.propagate
        ancestors = _systematic_ancestors(w if w is not None else np.exp(log_w), gen)
        x_t = torch.from_numpy(x_t.numpy()[ancestors])
        log_w, w = _uniform(n, log_w.dtype)[0], None

    new_t = _single_run._propagate(model, x_t, inputs_per_point(u, x_t), k, gens.propagate)
    new = new_t.numpy()
    obs_t = model.observe(new_t, k + 1)
    plain = type(model).measurement_residual is StateSpaceModel.measurement_residual
    y_np = y.resolve_neg().numpy()
    obs = obs_t.numpy()
    if resampled:  # equal weights (the torch step averages: the same up to round-off)
        pred_w = _uniform(n, log_w.dtype)[1]
    else:
        pred_w = np.exp(log_w) if w is None else w
    pred_mean = pred_w @ new
    innovation = innovation_cov = None
    received = _received(mask)
    if pf.innovations:
        innovation, innovation_cov = _predictive(model, y, y_np, k, obs, pred_w, plain, received)
    # y − h(x): the host's subtraction where the model wraps no angles
    residual = np.subtract(y_np, obs) if plain else model.measurement_residual(y, obs_t).numpy()
    inv_var, constant, log_sigma = density
    weighed = residual
    if received is not None:  # the density of the received entries alone (their marginal)
        weighed, inv_var = residual[:, received], inv_var[received]
        constant = log_sigma[received].sum() + dtype(0.5 * received.size * LOG_2PI)
    increment, log_w_new, w_new, degenerate = _weigh(weighed, log_w, inv_var, constant)
    if degenerate:  # a NaN particle or density is named, as the general step names it
        # (log w copied: equal log-weights are a shared read-only array)
        log_lik = model.measurement_noise.log_prob(
            torch.from_numpy(residual), mask=None if received is None else mask
        )
        _blame_degenerate(pf, new_t, log_lik, None, torch.tensor(log_w), k + 1)
    mean = w_new @ new
    dev = new - mean
    cov = (dev.T * w_new) @ dev
    # ESS by torch's dot, as the torch steps take it: equal weights (a reset, a step that
    # lost every entry, a measurement too far or too noisy to tell the particles apart) have
    # an ESS of N up to round-off, and at ess_threshold = 1 that round-off decides the next
    # resampling: numpy's 1/(w·w) gave 100.00000000000001 where torch's gave
    # 99.999999999999957, and the two paths resampled apart from there (a fuzzing trial)
    w_t = torch.from_numpy(w_new)
    ess_new = torch.dot(w_t, w_t).reciprocal()
    out = StepOutput(
        torch.from_numpy(mean), torch.from_numpy(_symmetrize(cov)), torch.from_numpy(pred_mean),
        None, innovation, innovation_cov, torch.from_numpy(increment),
        extras={"ess": ess_new, "resampled": _flag(resampled), "degenerate": _flag(degenerate)},
    )  # fmt: skip
    new_carry = ParticleState(new_t, torch.from_numpy(log_w_new), k + 1, ess_new,
                              torch.from_numpy(w_new), model, carry.aux, carry.generators)  # fmt: skip
    return new_carry, out


def _received(mask: Tensor | None) -> np.ndarray | None:
    """The indices of the received entries of ``mask [dy]`` (bool), ``None`` where every
    entry is received (no mask, or one of all ``True``: the unmasked step's numbers)."""
    if mask is None:
        return None
    m = mask.numpy()
    return None if m.all() else np.flatnonzero(m)


def _predictive(model, y, y_np, k: int, obs, pred_w, plain: bool, received=None):
    """``(innovation [dy], S [dy, dy])`` as torch tensors from the predicted measurements
    ``obs [N, dy]`` under the predictive weights ``pred_w [N]``:
    ``ŷ = Σᵢ wᵢ h_i``, ``y − ŷ``, ``S = sym(Σᵢ wᵢ (h_i − ŷ)(h_i − ŷ)ᵀ + R)``. With the
    indices of the ``received`` entries, the general step's masked moments
    (:func:`~difffilter.linalg.masked_measurement`, ``M = diag(mask)``): ``M (y − ŷ)`` and
    ``sym(M Σᵢ wᵢ (h_i − ŷ)(h_i − ŷ)ᵀ M + M R M + (I − M))``."""
    if plain:
        y_hat = pred_w @ obs
        dev = obs - y_hat
    else:  # angles: averaged as residuals about one particle's (the torch step's way)
        # (a copy of the weights: equal ones are a shared read-only array)
        y_hat_t, dev_t = wrapped_spread(model, torch.from_numpy(obs), torch.tensor(pred_w))
        y_hat, dev = y_hat_t.numpy(), dev_t.numpy()
    y_cov = (dev.T * pred_w) @ dev
    # (a learnable R: its values; a negative-bit view resolved, which numpy cannot read)
    R = model.measurement_cov(k + 1).detach().resolve_neg().numpy()
    if plain:
        innovation = np.subtract(y_np, y_hat)
    else:
        innovation = model.measurement_residual(y, torch.from_numpy(y_hat)).numpy()
    if received is not None:
        m = np.zeros(R.shape[-1], dtype=R.dtype)
        m[received] = 1.0
        outer = np.outer(m, m)
        innovation = innovation * m
        y_cov = y_cov * outer
        R = R * outer + np.diag(1.0 - m)
    return torch.from_numpy(innovation), torch.from_numpy(_symmetrize(y_cov + R))


def _weigh(residual, log_w, inv_var: np.ndarray, constant):
    """``(log p̂ [] array, log w_k [N], w_k [N], degenerate)`` from the residuals
    ``[N, dy]`` and the predictive log-weights ``[N]`` under a diagonal zero-mean Gaussian
    (``inv_var = 1/σ²``, ``constant = Σ log σ + (dy/2) log 2π``):
    ``log w + log α = log w − ½ Σ_j r_j²/σ_j² − c``, normalised. A step where every weight
    underflowed (or a NaN) keeps the predictive weights, its evidence ``−∞`` (or NaN), as
    the torch step's reset."""
    dtype = log_w.dtype.type
    with np.errstate(over="ignore", invalid="ignore"):  # a far-off y: torch's inf, silently
        joint = np.subtract(log_w, ((residual * residual) @ inv_var) * dtype(0.5))
    top = joint.max()
    if not math.isfinite(top):
        # the reset's weights by torch's exp, as the torch steps' (numpy's rounds otherwise)
        kept = log_w.copy()  # (equal log-weights are a shared read-only array)
        return np.asarray(top - constant), kept, torch.exp(torch.from_numpy(kept)).numpy(), True
    e = np.exp(joint - top)
    total = e.sum()
    increment = np.log(total) + top
    joint -= increment
    e /= total
    return np.asarray(increment - constant), joint, e, False


def _symmetrize(a: np.ndarray) -> np.ndarray:
    """``(A + Aᵀ)/2`` (in place into ``A + Aᵀ``)."""
    out = a + a.T
    out *= out.dtype.type(0.5)
    return out


def _uniform(n: int, dtype) -> tuple[np.ndarray, np.ndarray]:
    """``(log w, w)`` of ``N`` equal weights in ``dtype`` (cached, read-only: a carry never
    holds these arrays themselves)."""

    def make():
        log_w = np.full(n, dtype.type(0.0 - math.log(n)))
        return log_w, np.exp(log_w)

    return _cached(("uniform", n, dtype), make)


def _flag(value: bool) -> Tensor:
    """A 0-dimensional bool tensor (a new one: callers may stack or modify it)."""
    return torch.from_numpy(np.array(value))


def _systematic_ancestors(weights: np.ndarray, generator) -> np.ndarray:
    """``a_j = F⁻¹((j + U)/N)`` ``[N]`` for non-negative ``weights [N]``, ``U`` drawn by torch
    from ``generator`` as the torch step draws it: the targets ``(j + U)·W/N`` searched in
    the cumulative weights (right side), clamped to the last particle of positive weight."""
    n, dtype = weights.shape[0], weights.dtype
    offset = torch.rand((1,), generator=generator, dtype=_TORCH_DTYPES[dtype.type]).item()
    cdf = np.cumsum(weights)
    total = cdf[-1]
    targets = _arange(n, dtype) + offset  # in the weights' dtype, as the torch step's
    targets *= total / dtype.type(n)
    ancestors = cdf.searchsorted(targets, side="right")
    return np.minimum(ancestors, cdf.searchsorted(total), out=ancestors)


_TORCH_DTYPES = {np.float32: torch.float32, np.float64: torch.float64}


def _arange(n: int, dtype) -> np.ndarray:
    """``[0, 1, …, N−1]`` in ``dtype`` (cached, read-only)."""
    return _cached(("arange", n, dtype), lambda: (np.arange(n, dtype=dtype),))[0]


#: The constant arrays of the host step by ``(kind, N, dtype)``, read-only.
_CONSTANTS: dict = {}


def _cached(key, make) -> tuple[np.ndarray, ...]:
    """``make()``'s arrays for ``key``, made once and frozen (``writeable = False``)."""
    arrays = _CONSTANTS.get(key)
    if arrays is None:
        arrays = make()
        for arr in arrays:
            arr.flags.writeable = False
        _CONSTANTS[key] = arrays
    return arrays
