"""Noise models: Gaussian (Cholesky), Gaussian mixture (glint) and uniform box.

Each is an ``nn.Module`` (so ``.to(device)`` and ``.double()`` move it with its model)
with the same four members:

* ``sample(sample_shape=(), generator=None)`` → ``[*sample_shape, *batch, d]``; every
  draw comes from the given ``torch.Generator`` (or the global one when ``None``);
* ``log_prob(value)`` for ``value [..., d]`` → ``[...]``;
* ``mean`` → ``[*batch, d]`` and ``cov`` → ``[*batch, d, d]`` (moments; for the
  mixture and the box these are the exact first two moments, which the Gaussian
  filters use).

Parameters given as ``nn.Parameter`` are registered as parameters (learnable); plain
tensors are buffers. A tensor with autograd history keeps it, so a covariance can be
the output of another computation (``gradcheck`` through ``Q`` and ``R``).
"""

from __future__ import annotations

import math
import weakref

import torch
from torch import Tensor, nn

from ._assignments import CountsAssignments
from ._checks import (
    as_tensor,
    broadcast_or_none,
    broadcast_shapes,
    check_batch_shapes,
    check_finite,
    check_positive_definite,
    check_square,
    check_symmetric,
    check_vector_last,
    values_known,
)
from .linalg import (
    LOG_2PI,
    gaussian_log_prob_chol,
    masked_measurement,
    matvec,
    outer,
    rowwise,
    rowwise_addcmul,
    safe_cholesky,
)

__all__ = ["NoiseModel", "Gaussian", "GaussianMixture", "UniformBox", "register_tensor"]


def register_tensor(module: nn.Module, name: str, value: Tensor) -> None:
    """Register ``value`` on ``module`` as a parameter if it is one, else as a buffer."""
    if isinstance(value, nn.Parameter):
        module.register_parameter(name, value)
    else:
        module.register_buffer(name, value)


def _registered(module: nn.Module, name: str) -> Tensor:
    """``module.<name>`` of a tensor registered by :func:`register_tensor`, read from its
    dict: ``nn.Module.__getattr__`` is a Python fallback of about a microsecond, and a
    filter step reads a noise model's tensors several times."""
    value = module._buffers.get(name)
    return value if value is not None else module._parameters[name]


def _shape(sample_shape) -> torch.Size:
    if isinstance(sample_shape, int):
        return torch.Size([sample_shape])
    return torch.Size(sample_shape)


def _uncacheable(t: Tensor) -> bool:
    """Whether what is computed from ``t`` cannot be cached against its storage and version:
    it requires a gradient (a factor is differentiated), it is an inference tensor (no
    version counter) or a ``torch.func`` wrapper (``grad``, ``jvp``: no storage, its
    ``data_ptr()`` raised in the particle filter under ``torch.func.grad``, a gradients
    trial; the factor is then differentiated through the transform)."""
    return (t.requires_grad or t.is_inference()
            or torch._C._functorch.is_functorch_wrapped_tensor(t))  # fmt: skip


def _check_once(owner, attr: str, check, *tensors: Tensor) -> None:
    """``check()`` where ``tensors`` were written (or replaced) since ``owner`` last passed
    it, recorded under ``attr`` only once it passes: a check made once per write (a
    ``torch.func`` wrapper, which has no storage to identify, and an inference tensor,
    which keeps no version, are checked at every use). ``attr`` ends in ``_cache``: a
    plant's fingerprint leaves such attributes (memory addresses) out."""
    wrapped = torch._C._functorch.is_functorch_wrapped_tensor
    if any(wrapped(t) or t.is_inference() for t in tensors):
        check()
        return
    stamp = tuple((t._version, t.data_ptr(), id(t)) for t in tensors)
    if stamp != getattr(owner, attr, None):
        check()
        setattr(owner, attr, stamp)


def _held(cached, key, *tensors: Tensor) -> bool:
    """Whether ``cached`` (a tuple ``(key, refs, …)``, refs of :func:`_refs`) was computed from
    these very ``tensors`` as they are now: the same key (storage, version, dtype, …) and
    the same live objects. The storage address alone had been reused by a new covariance
    allocated where a freed one was (two replacements with no density between them: the
    old factor served, a log-density 10 nats off; a cache trial)."""
    return (cached is not None and cached[0] == key
            and all(ref() is t for ref, t in zip(cached[1], tensors)))  # fmt: skip


def _refs(*tensors: Tensor) -> tuple:
    """Weak references to ``tensors``, the second field of a cache entry (:func:`_held`);
    a copy or a pickle of the noise model leaves the entries out (:meth:`NoiseModel.__getstate__`)."""
    return tuple(weakref.ref(t) for t in tensors)


class NoiseModel(CountsAssignments):
    """Base class: a distribution over ``R^d`` with ``sample``, ``log_prob``, ``mean``, ``cov``.

    A noise of one's own subclasses it and sets ``dim``: ``simulate`` and the particle
    filters draw with ``sample(sample_shape, generator)`` and weigh with ``log_prob(value,
    mask=None)`` (``mask``, bool ``[..., d]``: the marginal of the received entries); a noise
    with batch dimensions (one set per run, ``mean [*batch, d]``) is drawn one per run by
    ``simulate``, as ``sample`` over the runs' leading dimensions; the Gaussian filters
    (KF, EKF, UKF) read ``mean`` (which must be 0) and ``cov`` alone, a moment match, so a
    heavy-tailed or multi-modal noise gets the Gaussian of its covariance there. A noise
    without a covariance (Cauchy, Student-t with ν ≤ 2) leaves ``cov`` unimplemented and
    runs in the particle filters only: as a process noise, or as a measurement noise with
    ``innovations=False`` (the reported innovation covariance adds the noise's).
    """

    dim: int

    #: Values computed from the noise's tensors and kept against them (:func:`_held`).
    _CACHES = ("_factor_cache", "_zero_loc_cache", "_log_len_cache")

    def __getstate__(self) -> dict:
        """The module's state without the caches (their weak references neither pickle
        nor point at a copy's tensors: a copy computes them again on first use)."""
        state = super().__getstate__()
        return {k: v for k, v in state.items() if k not in self._CACHES}

    def _missing(self, member: str) -> NotImplementedError:
        return NotImplementedError(
            f"{type(self).__name__}.{member} is not implemented: a NoiseModel subclass provides "
            "sample(sample_shape, generator), log_prob(value, mask=None), mean and cov (what "
            "the estimator in use reads; difffilter.noise.NoiseModel's docstring)"
        )

    def sample(self, sample_shape=(), generator: torch.Generator | None = None) -> Tensor:
        raise self._missing("sample(sample_shape, generator)")

    def log_prob(self, value: Tensor, mask: Tensor | None = None) -> Tensor:
        """``log p(value)`` for ``value [..., d]`` → ``[...]``.

        ``mask [..., d]`` (bool) keeps only the marked entries: the result is the log
        density of the marginal distribution of those entries.
        """
        raise self._missing("log_prob(value, mask=None)")

    @property
    def mean(self) -> Tensor:
        raise self._missing("mean")

    @property
    def cov(self) -> Tensor:
        raise self._missing("cov")

    @property
    def batch_shape(self) -> torch.Size:
        return self.mean.shape[:-1]

    def has_batch(self) -> bool:
        """Whether the noise has batch dimensions (one set of parameters per run), which
        ``simulate`` then draws one per run. Read from ``mean``; a noise without one is
        taken to have none (the built-in noise models answer without computing it)."""
        try:
            mean = self.mean
        except NotImplementedError:
            return False
        return isinstance(mean, Tensor) and mean.dim() > 1


class Gaussian(NoiseModel):
    """Multivariate normal ``N(loc, cov)`` parameterised by its Cholesky factor.

    Args:
        loc: mean ``[*batch, d]`` (or a scalar ``0`` with ``cov`` given, meaning zeros).
        cov: covariance ``[*batch, d, d]``, symmetric positive definite.
        scale_tril: alternatively the lower Cholesky factor ``L`` with ``cov = L Lᵀ``
            (a positive diagonal when built; one that training later turns negative is
            read with its columns' signs normalised: the same ``cov``).

    ``log_prob(v) = −½ (v−μ)ᵀ Σ⁻¹ (v−μ) − Σᵢ log Lᵢᵢ − (d/2) log 2π``;
    ``sample = μ + L ε`` with ``ε ~ N(0, I)``.
    """

    def __init__(self, loc, cov=None, *, scale_tril=None):
        super().__init__()
        if (cov is None) == (scale_tril is None):
            raise ValueError("Gaussian needs exactly one of cov= or scale_tril=")
        mat = as_tensor(
            cov if cov is not None else scale_tril, "cov" if cov is not None else "scale_tril"
        )
        loc = as_tensor(loc, "loc", dtype=mat.dtype, device=mat.device)
        check_square(mat, "cov" if cov is not None else "scale_tril")
        d = mat.shape[-1]
        if loc.dim() == 0:
            if isinstance(loc, nn.Parameter):  # its expanded copy would be a buffer, frozen
                raise ValueError(
                    f"loc: a 0-d nn.Parameter would be copied into a [{d}] buffer that "
                    "training never moves (the parameter drifts, the model does not): give "
                    f"nn.Parameter(torch.full(({d},), value)), or a fixed scalar"
                )
            loc = (
                loc.expand(d).clone()
                if loc.requires_grad
                else torch.full((d,), float(loc), dtype=mat.dtype, device=mat.device)
            )
        check_vector_last(loc, "loc", d)
        check_finite(loc, "loc")
        # loc [2, d] beside cov [4, d, d] had been built, then failed in torch's words at
        # .mean or .sample(), or (a zero loc) densities took the covariance's batch alone
        given = "cov" if cov is not None else "scale_tril"
        check_batch_shapes(
            "a Gaussian's loc and " + given, loc=loc.shape[:-1], **{given: mat.shape[:-2]}
        )
        self.dim = d
        register_tensor(self, "loc", loc)
        if cov is not None:
            check_positive_definite(mat, "cov", d)
            register_tensor(self, "_cov", mat)
            self._given = "cov"
        else:
            check_finite(mat, "scale_tril")
            _check_lower(mat, "scale_tril")
            if bool((mat.detach().diagonal(dim1=-2, dim2=-1) <= 0).any()):
                raise ValueError("scale_tril must be lower triangular with a positive diagonal")
            register_tensor(self, "_scale_tril", mat)
            self._given = "scale_tril"

    def _factor(self) -> tuple[Tensor, Tensor | None]:
        """``(L, diag)``: the Cholesky factor and, when it is diagonal, its diagonal.

        For covariances that do not require gradients the factor is cached against the
        tensor's version counter (filters call it at every step); a diagonal factor
        lets sampling and densities skip the triangular matrix products. (So edit a
        covariance in place under ``torch.no_grad()`` or assign a new one: a write through
        ``.data`` or ``.numpy()`` bumps no version and leaves the old factor cached.)
        """
        src = _registered(self, "_cov" if self._given == "cov" else "_scale_tril")
        if _uncacheable(src):
            return self._compute_scale_tril(), None
        key = (src.data_ptr(), src._version, src.dtype, src.device, tuple(src.shape))
        cached = getattr(self, "_factor_cache", None)
        # a factor made under torch.inference_mode() is an inference tensor, which autograd
        # cannot save: outside that mode it is made again
        if _held(cached, key, src) and (
            not cached[2].is_inference() or torch.is_inference_mode_enabled()
        ):
            return cached[2], cached[3]
        L = self._compute_scale_tril()
        diag = None
        if L.dim() == 2 and bool((L == torch.diag_embed(L.diagonal())).all()):
            diag = L.diagonal()
        self._factor_cache = (key, _refs(src), L, diag)
        return L, diag

    def _zero_loc(self) -> bool:
        """Whether ``loc`` is a constant zero vector (noise models usually are): lets
        sampling and densities skip a pass over the samples. Cached like the factor."""
        loc = _registered(self, "loc")
        if loc.requires_grad:
            return False
        if _uncacheable(loc):
            return not bool(loc.any())
        key = (loc.data_ptr(), loc._version, loc.dtype, loc.device, tuple(loc.shape))
        cached = getattr(self, "_zero_loc_cache", None)
        if not _held(cached, key, loc):
            cached = (key, _refs(loc), not bool(loc.any()))
            self._zero_loc_cache = cached
        return cached[2]

    def _lower(self, name: str = "scale_tril") -> Tensor:
        """The factor given as ``scale_tril``, checked lower triangular once per write (one
        written with entries above its diagonal since built had been read as its lower
        triangle, another covariance than the one written); ``name``: how the error names it."""
        L = self._scale_tril
        _check_once(self, "_lower_checked_cache", lambda: _check_lower(L, name), L)
        return L.tril()

    def _compute_scale_tril(self) -> Tensor:
        if self._given == "scale_tril":
            L = self._lower()
            # a factor whose diagonal an optimiser step made negative is the same cov = L Lᵀ:
            # its columns' signs are normalised, so that log Lᵢᵢ exists (a user trial's
            # particle filter read NaN densities there while the Kalman filters, reading
            # cov, ran on); a zero on the diagonal is a singular cov
            diag = L.detach().diagonal(dim1=-2, dim2=-1)
            if bool((diag == 0).any()):
                raise ValueError("scale_tril has a zero on its diagonal: cov = L Lᵀ is "
                                 "singular (parameterise the diagonal through exp or "
                                 "softplus to keep it away from 0)")  # fmt: skip
            if bool((diag < 0).any()):
                L = L * torch.where(diag < 0, -1.0, 1.0).to(L.dtype).unsqueeze(-2)
            return L
        # (written asymmetric since it was built: the factor reads one triangle, the Kalman
        # filters the average, and a particle filter's means were 0.44 off a Kalman
        # filter's of the same model: a covariance-write trial)
        # (once per write: a learnable covariance's factor is made at every use, a review)
        _check_once(self, "_factor_checked_cache", lambda: check_symmetric(self._cov, "cov"),
                    self._cov)  # fmt: skip
        return safe_cholesky(self._cov, name="cov")

    def check_written(self, name: str, *, loc: bool = True) -> None:
        """What was written since it was checked (in place, a ``load_state_dict``): a
        covariance given as ``cov`` still symmetric (:func:`~difffilter._checks.check_symmetric`),
        a factor given as ``scale_tril`` still lower triangular and, with ``loc``, the mean
        finite (a NaN noise mean had been simulated as NaN runs and read as a zero mean by
        the Kalman filters: an ssm trial); one check per version. ``name``: how the error
        names it (``model.process_noise``)."""
        if loc:
            mean = self.loc
            _check_once(self, "_loc_checked_cache",
                        lambda: _check_finite_written(mean, f"{name}'s mean (loc)"), mean)  # fmt: skip
        if self._given == "cov":
            _check_once(self, "_written_checked_cache",
                        lambda: check_symmetric(self._cov, f"{name}'s covariance"), self._cov)  # fmt: skip
        else:
            self._lower(f"{name}'s scale_tril")

    @property
    def scale_tril(self) -> Tensor:
        """Lower Cholesky factor ``[*batch, d, d]``."""
        return self._factor()[0]

    @property
    def mean(self) -> Tensor:
        return self.loc.expand(broadcast_shapes(self.loc.shape, self.cov.shape[:-1]))

    @property
    def cov(self) -> Tensor:
        if self._given == "cov":
            return self._cov
        L = self._lower()
        return L @ L.transpose(-1, -2)

    def sample(self, sample_shape=(), generator=None) -> Tensor:
        """Draw ``[*sample_shape, *batch, d]`` samples: ``μ + L ε``."""
        L, diag = self._factor()
        batch = broadcast_shapes(self.loc.shape[:-1], L.shape[:-2])
        eps = torch.randn(
            _shape(sample_shape) + batch + (self.dim,),
            generator=generator,
            dtype=L.dtype,
            device=L.device,
        )
        if diag is not None:
            out = rowwise(torch.mul, eps, diag)
            return out if self._zero_loc() else rowwise(torch.add, out, self.loc)
        out = matvec(L, eps)
        return out if self._zero_loc() else self.loc + out

    def has_batch(self) -> bool:
        """Whether the mean or the covariance has batch dimensions (one per run)."""
        src = _registered(self, "_cov" if self._given == "cov" else "_scale_tril")
        return src.dim() > 2 or _registered(self, "loc").dim() > 1

    def draw_like(self, shape, generator: torch.Generator | None = None) -> Tensor:
        """Draws ``[*shape]`` (``shape = [..., d]``), independent at every entry of
        ``shape[:-1]``, whose trailing dimensions take this distribution's batch (one
        covariance per run: ``[B, d, d]`` for draws ``[B, d]``): ``μ + L ε``. ``sample``
        would prepend its shape to the batch instead."""
        shape = torch.Size(shape)
        L, batch = self.scale_tril, self.batch_shape
        if broadcast_or_none(shape[:-1], batch) != shape[:-1] or shape[-1:] != (self.dim,):
            raise ValueError(
                f"this Gaussian has a covariance per run (batch {tuple(batch)}), which does not "
                f"fit draws of shape {tuple(shape)}: its batch must match their trailing batch "
                "dimensions (a particle filter takes one model for all runs)"
            )
        eps = torch.randn(shape, generator=generator, dtype=L.dtype, device=L.device)
        out = matvec(L, eps)
        return out if self._zero_loc() else out + self.loc

    def perturb(self, value: Tensor, generator: torch.Generator | None = None) -> Tensor:
        """``value + s`` with ``s`` drawn from this distribution: ``value [..., d]`` → ``[..., d]``.

        The same draws as ``value + sample(value.shape[:-1])`` for an unbatched noise
        model; for a zero-mean diagonal one it is a single fused ``value + σ ⊙ ε`` pass
        (one fewer pass over ``[..., N, d]`` particle tensors per filter step).
        """
        L, diag = self._factor()
        loc = _registered(self, "loc")
        if self.has_batch():  # a covariance per run: one draw per entry of value
            return value + self.draw_like(value.shape, generator)
        if diag is None or diag.dim() != 1 or loc.dim() != 1 or not self._zero_loc():
            return value + self.sample(value.shape[:-1], generator).reshape(value.shape)
        eps = torch.randn(value.shape, generator=generator, dtype=L.dtype, device=L.device)
        return rowwise_addcmul(value, eps, diag)

    def log_prob(self, value: Tensor, mask: Tensor | None = None) -> Tensor:
        """``log N(value; μ, Σ)`` for ``value [..., d]`` → ``[...]`` (marginal on ``mask``)."""
        if value.shape[-1:] != (self.dim,):  # a [..., 1] value had broadcast to (v, …, v)
            raise ValueError(f"value must be [..., {self.dim}]; got {tuple(value.shape)}")
        residual = value if self._zero_loc() else rowwise(torch.sub, value, self.loc)
        if mask is not None:
            return _masked_gaussian_log_prob(residual, self.cov, mask)
        L, diag = self._factor()
        if diag is not None:
            # Σᵢ rᵢ²/σᵢ² as a matrix-vector product: a reduction over a short last
            # dimension is an order of magnitude slower on CPU.
            inv_var, log_norm = self._diagonal_terms(diag)
            maha = (residual * residual) @ inv_var
            return -0.5 * maha - log_norm
        return gaussian_log_prob_chol(residual, L)

    def _diagonal_terms(self, diag: Tensor) -> tuple[Tensor, Tensor]:
        """``(1/σ² [d], Σ log σ + (d/2) log 2π)`` of a diagonal factor ``σ = diag``: what
        every density evaluation needs, kept with the cached factor (the same numbers,
        five fewer tensor operations per call; a filter step on a hundred particles is a
        few dozen small operations, so their number is its cost)."""
        cached = getattr(self, "_factor_cache", None)
        if cached is not None and cached[3] is diag and len(cached) > 4:
            return cached[4]
        terms = (diag.square().reciprocal(), torch.log(diag).sum() + 0.5 * self.dim * LOG_2PI)
        # (not inference tensors: a later density with gradients saves 1/σ² for backward)
        if cached is not None and cached[3] is diag and not torch.is_inference_mode_enabled():
            self._factor_cache = (*cached[:4], terms)
        return terms


class GaussianMixture(NoiseModel):
    """Mixture ``Σ_c π_c N(μ_c, Σ_c)``, e.g. glint noise ``(1−κ)N(0,Σ₁) + κN(0,Σ₂)``.

    Args:
        weights: mixing probabilities ``[C]`` (non-negative, summing to one).
        locs: component means ``[C, d]``.
        covs: component covariances ``[C, d, d]``.

    ``log_prob(v) = logsumexp_c(log π_c + log N(v; μ_c, Σ_c))``; ``mean = Σ π_c μ_c``;
    ``cov = Σ π_c (Σ_c + μ_c μ_cᵀ) − mean meanᵀ``.
    """

    def __init__(self, weights, locs, covs):
        super().__init__()
        covs = as_tensor(covs, "covs")
        weights = as_tensor(weights, "weights", dtype=covs.dtype)
        locs = as_tensor(locs, "locs", dtype=covs.dtype)
        if weights.dim() != 1:
            raise ValueError(f"weights must have shape [C]; got {tuple(weights.shape)}")
        c = weights.shape[0]
        if locs.dim() != 2 or locs.shape[0] != c:
            raise ValueError(f"locs must have shape [{c}, d]; got {tuple(locs.shape)}")
        d = locs.shape[1]
        if covs.shape != (c, d, d):
            raise ValueError(f"covs must have shape [{c}, {d}, {d}]; got {tuple(covs.shape)}")
        check_positive_definite(covs, "covs", d)
        _check_mixture_weights(weights)
        if not bool(torch.isfinite(locs).all()):
            raise ValueError("locs must be finite")
        self.dim = d
        register_tensor(self, "weights", weights)
        register_tensor(self, "locs", locs)
        register_tensor(self, "covs", covs)

    def _weights(self) -> Tensor:
        """``weights``, checked again where written since (in place, a ``load_state_dict``,
        an optimiser's step on an ``nn.Parameter``): every member had read them as they
        came, ``log_prob`` and ``mean`` raw, ``sample`` normalised by ``torch.multinomial``
        (a noise trial: a density integrating to 5.51 after a fit of the weights; to learn
        them, build the mixture from ``softmax(logits)`` at each use)."""
        w = self.weights
        _check_once(self, "_weights_checked_cache", lambda: _check_mixture_weights(w), w)
        return w

    def check_written(self, name: str, *, loc: bool = True) -> None:
        """Component means (with ``loc``) written since they were checked still finite, and
        covariances still symmetric (one check per version; the weights are checked at each
        read). ``loc=False``: a prior's, whose mean ``check_model`` checks where it is read."""
        locs, covs = self.locs, self.covs
        if loc:
            _check_once(self, "_locs_checked_cache",
                        lambda: _check_finite_written(locs, f"{name}'s locs"), locs)  # fmt: skip
        _check_once(self, "_covs_checked_cache",
                    lambda: check_symmetric(covs, f"{name}'s covs"), covs)  # fmt: skip

    @property
    def mean(self) -> Tensor:
        return (self._weights()[:, None] * self.locs).sum(0)

    def has_batch(self) -> bool:
        """``False``: one mixture for all runs (``weights [C]``, ``locs [C, d]``)."""
        return False

    @property
    def cov(self) -> Tensor:
        second = (self._weights()[:, None, None] * (self.covs + outer(self.locs, self.locs))).sum(0)
        m = self.mean
        return second - outer(m, m)

    def sample(self, sample_shape=(), generator=None) -> Tensor:
        """Draw ``[*sample_shape, d]``: a component index, then its Gaussian."""
        shape = _shape(sample_shape)
        n = math.prod(shape)
        if n == 0:  # (torch.multinomial draws at least one)
            return self.locs.new_zeros(shape + (self.dim,))
        comp = torch.multinomial(self._weights(), n, replacement=True, generator=generator)
        L = safe_cholesky(self.covs, name="covs")
        eps = torch.randn(
            n, self.dim, generator=generator, dtype=self.covs.dtype, device=self.covs.device
        )
        draws = self.locs[comp] + matvec(L[comp], eps)
        return draws.reshape(shape + (self.dim,))

    def log_prob(self, value: Tensor, mask: Tensor | None = None) -> Tensor:
        """``log p(value)`` for ``value [..., d]`` → ``[...]`` (log-sum-exp over components).

        With ``mask`` each component is marginalised to the marked entries (the marginal
        of a mixture is the mixture of the marginals).
        """
        if value.shape[-1:] != (self.dim,):  # a [..., 1] value had broadcast to (v, …, v)
            raise ValueError(f"value must be [..., {self.dim}]; got {tuple(value.shape)}")
        residual = value.unsqueeze(-2) - self.locs  # [..., C, d]
        if mask is None:
            comp = gaussian_log_prob_chol(residual, safe_cholesky(self.covs, name="covs"))
        else:
            comp = _masked_gaussian_log_prob(residual, self.covs, mask.unsqueeze(-2))
        return torch.logsumexp(comp + torch.log(self._weights()), dim=-1)


def _check_finite_written(t: Tensor, name: str) -> None:
    """``check_finite`` where the values can be read (not under ``torch.func``, not meta)."""
    if values_known(t):
        check_finite(t, name)


def _check_lower(L: Tensor, name: str) -> None:
    """A Cholesky factor given as ``scale_tril`` has nothing above its diagonal: the factor
    is read as ``tril(L)``, so an upper factor (scipy's default) had given another
    covariance than ``L Lᵀ`` without a word (an ssm trial)."""
    if values_known(L) and bool(L.detach().triu(1).any()):
        raise ValueError(
            f"{name} must be lower triangular (cov = L Lᵀ with L lower): it has non-zero "
            "entries above its diagonal (an upper factor U gives L = Uᵀ, for cov = Uᵀ U)"
        )


def _check_mixture_weights(weights: Tensor) -> None:
    """Mixing probabilities: finite, non-negative, summing to 1 (to 1e-6). (Written to fail
    on NaN: NaN weights had passed both comparisons.)"""
    w = weights.detach()
    if not (bool((w >= 0).all()) and abs(float(w.sum()) - 1.0) <= 1e-6):
        raise ValueError(
            "weights must be finite, non-negative and sum to 1 (to learn them, build the "
            f"mixture from softmax(logits) of a parameter at each use); got {w.tolist()}"
        )


def check_log_prob_mask(mask: Tensor, dim: int) -> None:
    """A ``log_prob`` mask must be bool ``[..., dim]`` (True where an entry was received)."""
    if mask.dtype != torch.bool or mask.shape[-1:] != (dim,):
        # an all-True [N, 1] mask had counted one received entry of d (a density (d − 1)/2 ·
        # log 2π off), and an integer mask holding 2 weighed its entry twice (a linalg trial);
        # the box's `outside & 2` was 0, a finite density outside the box (a noise trial)
        raise ValueError(
            f"mask must be bool [..., {dim}] (True where an entry was received);"
            f" got {mask.dtype} {tuple(mask.shape)}"
        )


def _masked_gaussian_log_prob(residual: Tensor, cov: Tensor, mask: Tensor) -> Tensor:
    """Log density of the received entries of ``N(residual; 0, cov)`` (see ``masked_measurement``)."""
    check_log_prob_mask(mask, residual.shape[-1])
    eye = torch.eye(cov.shape[-1], dtype=cov.dtype, device=cov.device)
    r, _, c, count = masked_measurement(residual, eye, cov, mask)
    return gaussian_log_prob_chol(r, safe_cholesky(c, name="cov", mask=mask), count)


def _check_box(low: Tensor, high: Tensor) -> None:
    """Finite bounds with ``high > low`` in every coordinate (when built, and where written
    since)."""
    if not values_known(low):
        return
    check_finite(low, "low")
    check_finite(high, "high")
    if bool((high <= low).any()):
        raise ValueError("high must be strictly greater than low in every coordinate")


class UniformBox(NoiseModel):
    """Uniform distribution on the box ``[low, high]`` (``low, high [*batch, d]``).

    ``log_prob = −Σ log(high − low)`` inside the box and ``−inf`` outside;
    ``mean = (low + high)/2``; ``cov = diag((high − low)² / 12)``.
    """

    def __init__(self, low, high):
        super().__init__()
        low = as_tensor(low, "low")
        high = as_tensor(high, "high", dtype=low.dtype)
        if low.dim() == 0 or low.shape != high.shape:
            raise ValueError(
                f"low and high must have the same shape [..., d]; got {tuple(low.shape)}, {tuple(high.shape)}"
            )
        _check_box(low, high)
        self.dim = low.shape[-1]
        register_tensor(self, "low", low)
        register_tensor(self, "high", high)

    def _bounds(self) -> tuple[Tensor, Tensor]:
        """``(low, high)``, checked again where written since the box was built (in place,
        ``load_state_dict``): ``high = low`` had given +inf densities, ``high < low`` −inf,
        NaN under a mask, and ``cov``/``log_volume`` an empty box's (a noise trial)."""
        low, high = self.low, self.high
        _check_once(self, "_bounds_checked_cache", lambda: _check_box(low, high), low, high)
        return low, high

    @property
    def mean(self) -> Tensor:
        low, high = self._bounds()
        return 0.5 * (low + high)

    def has_batch(self) -> bool:
        """Whether ``low`` and ``high`` have batch dimensions (one box per run)."""
        return _registered(self, "low").dim() > 1

    @property
    def cov(self) -> Tensor:
        low, high = self._bounds()
        return torch.diag_embed((high - low).square() / 12.0)

    @property
    def log_volume(self) -> Tensor:
        """``Σ log(high − low)`` ``[*batch]``."""
        low, high = self._bounds()
        return torch.log(high - low).sum(-1)

    def sample(self, sample_shape=(), generator=None) -> Tensor:
        low, high = self._bounds()
        shape = _shape(sample_shape) + low.shape
        u = torch.rand(shape, generator=generator, dtype=low.dtype, device=low.device)
        return low + (high - low) * u

    def log_prob(self, value: Tensor, mask: Tensor | None = None) -> Tensor:
        """``−Σ log(high − low)`` inside the box, ``−inf`` outside (marginal on ``mask``)."""
        if value.shape[-1:] != (self.dim,):  # a shorter value would broadcast to the box
            raise ValueError(f"value must have shape [..., {self.dim}] (the box's dimension); "
                             f"got {tuple(value.shape)}")  # fmt: skip
        outside = ~((value >= self.low) & (value <= self.high))  # NaN counts as outside
        log_len = self._log_lengths()
        if mask is not None:
            check_log_prob_mask(mask, self.dim)
            outside = outside & mask
            log_len = log_len * mask
        lp = -log_len.sum(-1)
        return lp.masked_fill(outside.any(-1), -math.inf)

    def _log_lengths(self) -> Tensor:
        """``log(high − low)`` ``[*batch, d]``, kept while ``low`` and ``high`` are unchanged
        (a filter asks at every step); recomputed for learnable bounds."""
        low, high = self._bounds()
        if _uncacheable(low) or _uncacheable(high):
            return torch.log(high - low)
        key = (low.data_ptr(), low._version, high.data_ptr(), high._version, low.dtype, low.device)
        cached = getattr(self, "_log_len_cache", None)
        if not _held(cached, key, low, high):
            cached = (key, _refs(low, high), torch.log(high - low))
            self._log_len_cache = cached
        return cached[2]
