"""Small, batched linear-algebra helpers shared by every filter.

All functions broadcast over leading batch dimensions: matrices are ``[..., d, d]`` and
vectors ``[..., d]``.
"""

from __future__ import annotations

import math
import threading

import torch
from torch import Tensor

__all__ = [
    "NumericalBreakdown",
    "symmetrize",
    "safe_cholesky",
    "cholesky_solve_right",
    "gaussian_log_prob_chol",
    "mahalanobis_sq_chol",
    "matvec",
    "outer",
    "masked_measurement",
    "rowwise",
    "rowwise_addcmul",
]


class NumericalBreakdown(ValueError):
    """A filter's arithmetic cannot go on from the values it reached: a matrix it must
    factorise is not positive definite even with :func:`safe_cholesky`'s jitter (a
    covariance that overflowed or lost definiteness to round-off), or the EKF's
    linearisation is undefined at its estimate (a NaN or infinite Jacobian: a range or
    bearing measured at the sensor's own position).

    A ``ValueError`` (every ``except ValueError`` catches it), raised by the step that met
    it; its message says which matrix or Jacobian, at which step or batch member, and what
    to do. The evaluation suites catch it alone: an estimator that breaks down on a study's
    data is listed among the skipped ones with this message and the others are reported,
    where any other error (a shape, a wrong argument) stops the evaluation.
    """


#: How the filters name the innovation covariance in :func:`safe_cholesky`'s error: it is
#: made from the model's covariances, which a user's optimiser may have made indefinite.
INNOVATION_COV = ("innovation covariance S = H P⁻ Hᵀ + R (made from the model's Q, R and "
                  "P0 and the filter's covariance: each must stay positive definite and finite; "
                  "training may break Q, R or P0, docs/gradients.md, and an unstable plant's "
                  "covariance overflows over a long run of lost measurements)")  # fmt: skip

LOG_2PI = math.log(2.0 * math.pi)


def under_transform(*tensors: Tensor | None) -> bool:
    """Whether any of ``tensors`` carries a forward-mode tangent (``torch.autograd.forward_ad``)
    or is wrapped by a ``torch.func`` transform (``jvp``, ``jacfwd``, ``vmap``, ``grad``).
    Such tensors report ``requires_grad=False``, so a path chosen for "no gradient" would
    write them into preallocated outputs (``out=``, in place), which forward mode refuses:
    the whole-sequence Kalman filter steps through instead. Without tensors: whether a
    transform or a dual level is active at all (then none of them can be traced)."""
    level = torch.autograd.forward_ad._current_level
    # the dual level is the process's, not the thread's: one another thread's Jacobian
    # holds (batched_jacobian's torch.func.jacfwd) is not this thread's transform (every
    # other thread had taken its traced paths meanwhile: a one-run PF 0.73 off, a model's
    # width check skipped; a concurrency trial). torch.func's own level is per thread.
    dual = level >= 0 and not _dual_level_of_another_thread()
    active = dual or torch._C._functorch.maybe_current_level() is not None
    if not active or not tensors:
        return active
    for t in tensors:
        if not isinstance(t, Tensor):
            continue
        if torch._C._functorch.is_functorch_wrapped_tensor(t):
            return True
        if level >= 0 and torch.autograd.forward_ad.unpack_dual(t).tangent is not None:
            return True
    return False


#: The thread whose ``torch.func`` Jacobian (:func:`difffilter.ssm.batched_jacobian`, one
#: at a time) holds the process's forward-mode dual level now, or ``None``.
JACOBIAN_THREAD: list[int | None] = [None]


def _dual_level_of_another_thread() -> bool:
    owner = JACOBIAN_THREAD[0]
    return owner is not None and owner != threading.get_ident()


def symmetrize(matrix: Tensor) -> Tensor:
    """Return ``(A + Aᵀ) / 2`` for ``matrix`` of shape ``[..., d, d]``.

    Round-off makes covariance recursions drift away from symmetry; every filter
    symmetrises after each update so that Cholesky factorisations keep succeeding.
    """
    return 0.5 * (matrix + matrix.transpose(-1, -2))


#: The first and the largest jitter :func:`safe_cholesky` adds, relative to the mean
#: diagonal, by dtype (others: float32's).
JITTER_LADDER = {torch.float64: (1e-14, 1e-5), torch.float32: (1e-6, 1e-1)}


def safe_cholesky(
    matrix: Tensor,
    *,
    name: str = "matrix",
    max_tries: int | None = None,
    mask: Tensor | None = None,
) -> Tensor:
    """Lower Cholesky factor of a symmetric positive-definite ``[..., d, d]`` matrix.

    Jitter fallback: when the factorisation fails (a matrix that is positive
    semidefinite up to round-off), ``ε·mean(diag)·I`` is added with ε growing by factors of
    10 through :data:`JITTER_LADDER`, from round-off (1e-14 in float64, about 45 machine
    epsilons; 1e-6 in float32) up to 1e-5 and 1e-1 of the mean diagonal. If that still
    fails the matrix is not positive definite and a :class:`NumericalBreakdown` (a
    ``ValueError``) naming ``name`` is raised. In a batch only the members that fail are jittered, each with the first ε
    that works for it: the others keep their own factors. (The ladder began at 1e-10 in
    float64: on a state covariance with variances from 2.5e-15 to 200 that jitter was 2e6
    times the smallest variance, and a numerics trial's UKF came out 4.25 nats off with a
    5 % wrong gradient; with the ladder from round-off alone, 2.4e-3 nats; with the UKF's
    linearisation error formed as a sum too, 2.5e-9.) ``max_tries``: at most this many
    rungs of the ladder (default: all of them).

    ``mask`` ``[..., d]`` (bool, broadcasting with the batch) or ``None``: for a matrix
    made by :func:`masked_measurement`, its received entries. The jitter is then
    ``ε·mean(diag over received)·diag(mask)``: the received block gets the jitter of the
    received entries' own matrix and the unit placeholders stay 1, so the factor equals
    the sub-model's factor with unit rows added. (Scaled by the mean over all entries, a
    float32 update in units with variances near 1e-6 had 5e5 times the sub-model's
    jitter from the placeholders' 1s: its mean 20 % off, its log-likelihood 6.6 nats.)
    A matrix that factorises needs no jitter: the mask changes no number of it.
    """
    factor, info = torch.linalg.cholesky_ex(matrix)
    if matrix.device.type == "meta":
        return factor  # (meta tensors hold no values: shapes only, nothing to check)
    if not bool((info != 0).any()):
        # an infinite variance factorises (√∞ on the diagonal, no error): a covariance that
        # overflowed on its diagonal alone had passed (a linalg trial), as NaN does not
        finite = torch.isfinite(factor.diagonal(dim1=-2, dim2=-1))
        if not bool(finite.all()):
            raise NumericalBreakdown(
                f"{name} must be symmetric positive definite and finite"
                f"{_why_it_fails(matrix, ~finite.all(-1))}"
            )
        return factor
    failing = info != 0
    overflowed = ~torch.isfinite(factor.diagonal(dim1=-2, dim2=-1)).all(-1) & ~failing
    if bool(overflowed.any()):
        # a member that factorised to √∞ beside one that needs jitter: its jitter scale (its
        # mean diagonal) is ∞ and 0·∞ = NaN had reached torch's bare error (a linalg trial)
        raise NumericalBreakdown(
            f"{name} must be symmetric positive definite and finite"
            f"{_why_it_fails(matrix, overflowed)}"
        )
    if mask is not None and mask.dim() > 1:
        batch = torch.broadcast_shapes(matrix.shape[:-2], mask.shape[:-1])
        if batch != matrix.shape[:-2]:
            # one matrix shared by runs with masks of their own: each run's jitter is its
            # received entries' (the jitter's scale had been expanded to the matrix's own
            # batch: a bare expand error, only where the matrix needed jitter)
            matrix, failing = matrix.expand(batch + matrix.shape[-2:]), failing.expand(batch)
    eps, ceiling = JITTER_LADDER.get(matrix.dtype, JITTER_LADDER[torch.float32])
    eye, scale = _jitter_direction(matrix, mask)
    chosen = torch.zeros_like(scale)  # each member's ε (0: its own factor)
    tries = 0
    while eps <= ceiling * 1.0001 and (max_tries is None or tries < max_tries):
        tries += 1
        with torch.no_grad():  # (which ε works for which member: values only)
            _, info = torch.linalg.cholesky_ex(matrix + (eps * scale)[..., None, None] * eye)
        chosen = torch.where(failing & (info == 0), torch.full_like(chosen, eps), chosen)
        failing = failing & (info != 0)
        if not bool(failing.any()):
            # one factorisation of every member with its own ε (0 adds nothing: the same
            # numbers as its first factor): merging the failed factors with torch.where had
            # sent 0·∞ = NaN through their backward into the matrix's gradient (a linalg
            # trial: 35 of 89 jittered rank-2 covariances)
            return torch.linalg.cholesky(matrix + (chosen * scale)[..., None, None] * eye)
        eps *= 10.0
    raise NumericalBreakdown(
        f"{name} must be symmetric positive definite; its Cholesky factorisation failed "
        f"even with jitter{_why_it_fails(matrix, failing)}"
    )


def _jitter_direction(matrix: Tensor, mask: Tensor | None) -> tuple[Tensor, Tensor]:
    """:func:`safe_cholesky`'s jitter ``eps·scale·eye``: ``(eye, scale [...])``, ``eye`` the
    identity, or ``diag(mask)`` with ``scale`` the mean diagonal over the received entries
    alone (a run with none received has ``S = I``, which needs no jitter)."""
    diag = matrix.diagonal(dim1=-2, dim2=-1)
    if mask is None:
        eye = torch.eye(matrix.shape[-1], dtype=matrix.dtype, device=matrix.device)
        return eye, diag.mean(-1).abs().clamp_min(1e-30)
    keep = mask.to(matrix.dtype)
    received = (diag * keep).sum(-1) / keep.sum(-1).clamp_min(1.0)
    scale = received.abs().clamp_min(1e-30).expand(matrix.shape[:-2])
    return torch.diag_embed(keep), scale


def _why_it_fails(matrix: Tensor, failing: Tensor) -> str:
    """The end of :func:`safe_cholesky`'s error: which member fails first (its batch
    index and eigenvalues), and, in float32, that the precision may be the cause (a
    float32 Kalman filter with a diffuse prior, P0 = 1e8 I, made an innovation covariance
    with eigenvalues from -3.5e7 to 4.75 out of positive definite Q, R and P0)."""
    index = tuple(int(i) for i in failing.nonzero()[0]) if failing.dim() else ()
    where = f" at batch index {index}" if index else ""
    with torch.no_grad():
        member = matrix[index].detach()
        if not bool(torch.isfinite(member).all()):
            return (f"{where}: it holds NaN or inf (a covariance that overflowed: an unstable "
                    "plant left unmeasured for long, P⁻ growing as ρ(F)^2k; or a model trained "
                    "out of range).")  # fmt: skip
        eig = torch.linalg.eigvalsh(member.double())
    text = (
        f"{where} (eigenvalues from {float(eig[0]):.3g} to {float(eig[-1]):.3g}). Check the "
        "covariance you passed (all eigenvalues > 0)"
    )
    eps = torch.finfo(matrix.dtype).eps
    if eps > 1e-10:
        text += (
            f"; in {str(matrix.dtype).replace('torch.', '')} a covariance whose scales span "
            "many orders of magnitude (a diffuse prior, a tiny R beside a large P) can lose "
            "its positive definiteness to round-off: float64 may hold it"
        )
    return text + "."


def cholesky_solve_right(rhs: Tensor, chol: Tensor) -> Tensor:
    """Solve ``X S = rhs`` for ``X`` where ``S = L Lᵀ`` and ``chol = L``.

    Shapes: ``rhs [..., n, d]``, ``chol [..., d, d]`` → ``[..., n, d]``. Used for the
    Kalman gain ``K = P Hᵀ S⁻¹`` without forming ``S⁻¹``.
    """
    return torch.cholesky_solve(rhs.transpose(-1, -2), chol).transpose(-1, -2)


def mahalanobis_sq_chol(residual: Tensor, chol: Tensor) -> Tensor:
    """``rᵀ S⁻¹ r`` with ``S = L Lᵀ``; ``residual [..., d]``, ``chol [..., d, d]`` → ``[...]``."""
    if chol.dim() == 2:
        # One shared factor (the common case: covariances identical across runs and
        # particles): a single triangular solve with all residuals as columns, instead
        # of broadcasting the factor to every row.
        flat = residual.reshape(-1, residual.shape[-1]).transpose(0, 1)
        z = torch.linalg.solve_triangular(chol, flat, upper=False)
        return z.square().sum(0).reshape(residual.shape[:-1])
    z = torch.linalg.solve_triangular(chol, residual.unsqueeze(-1), upper=False)
    return z.squeeze(-1).square().sum(-1)


def gaussian_log_prob_chol(
    residual: Tensor, chol: Tensor, dim: Tensor | int | None = None
) -> Tensor:
    """Log density of ``N(residual; 0, L Lᵀ)``.

    ``log N = -½ rᵀS⁻¹r - Σ log diag L - (m/2) log 2π`` where ``m`` is ``dim`` (the
    number of observed entries; defaults to ``d``). Shapes: ``residual [..., d]``,
    ``chol [..., d, d]``, ``dim`` scalar or ``[...]`` → ``[...]``.
    """
    if dim is None:
        dim = residual.shape[-1]
    half_logdet = torch.log(chol.diagonal(dim1=-2, dim2=-1)).sum(-1)
    return -0.5 * mahalanobis_sq_chol(residual, chol) - half_logdet - 0.5 * dim * LOG_2PI


def matvec(matrix: Tensor, vector: Tensor) -> Tensor:
    """``A v`` for ``matrix [..., m, n]`` and ``vector [..., n]`` → ``[..., m]``."""
    if matrix.dim() == 2:
        # A shared matrix: one GEMM over all rows instead of a broadcast batched matmul.
        return vector @ matrix.transpose(0, 1)
    return (matrix @ vector.unsqueeze(-1)).squeeze(-1)


def outer(a: Tensor, b: Tensor) -> Tensor:
    """``a bᵀ`` for ``a [..., m]``, ``b [..., n]`` → ``[..., m, n]``."""
    return a.unsqueeze(-1) * b.unsqueeze(-2)


def masked_measurement(
    residual: Tensor, obs_matrix: Tensor, noise_cov: Tensor, mask: Tensor | None
) -> tuple[Tensor, Tensor, Tensor, Tensor | int]:
    """Remove unreceived measurement entries from a Gaussian update, exactly.

    For a mask ``M = diag(mask)`` the update uses ``r' = M r``, ``H' = M H`` and
    ``R' = M R M + (I − M)``. A masked entry then has a zero row in ``H'``, a unit,
    uncorrelated noise variance and a zero residual, so its Kalman-gain column is zero
    and it adds ``−½ log 2π`` to ``log N(r'; 0, S')``, which the returned count of
    observed entries removes again: the result equals the update with the marginal
    model of the received entries alone (Round-Robin scheduling, packet loss).

    Shapes: ``residual [..., m]`` (or ``None``: the matrices alone, ``None`` back in its
    place), ``obs_matrix [..., m, n]``, ``noise_cov [..., m, m]``, ``mask [..., m]`` (bool) or
    ``None``. Returns ``(r', H', R', observed_count)``; with
    ``mask=None`` the inputs come back unchanged and the count is ``m``.
    """
    if mask is None:
        return residual, obs_matrix, noise_cov, obs_matrix.shape[-2]
    m = mask.to(obs_matrix.dtype if residual is None else residual.dtype)
    received = mask if mask.dtype == torch.bool else m != 0
    if residual is not None:  # (not residual · m: a NaN or ∞ where nothing was received,
        # as lost values are stored, made the density NaN: a linalg trial)
        residual = torch.where(received, residual, 0.0)
    # (not H · m either: a Jacobian row NaN where nothing was received, an EKF on a silent
    # range beacon it sits on, had stopped the update of the received entries: a trial)
    obs_matrix = torch.where(received.unsqueeze(-1), obs_matrix, 0.0)
    eye = torch.eye(m.shape[-1], dtype=m.dtype, device=m.device)
    noise_cov = noise_cov * outer(m, m) + torch.diag_embed(1.0 - m) * eye
    return residual, obs_matrix, noise_cov, m.sum(-1)


def _period(rows: int) -> int:
    for k in (16, 8, 4, 2):
        if rows % k == 0:
            return k
    return 1


#: Entries of the full operand below which :func:`rowwise` broadcasts plainly: the tiling
#: costs a few fixed microseconds (a ``repeat`` and two reshapes), more than the slow
#: inner loop of a small tensor (measured on the 2-core CPU: ``[N, 4] − [4]`` plainly
#: 3 µs at N = 100 against 40 µs tiled; the two cross near 8192 entries).
_ROWWISE_MIN = 8192


def _broadcasts_to(small: torch.Size, big: torch.Size) -> bool:
    """Whether ``small`` broadcasts to ``big`` (``torch.broadcast_shapes(small, big) == big``
    without its cost: that one is written in Python and checks its arguments at length)."""
    if len(small) > len(big):
        return False
    return all(s == 1 or s == b for s, b in zip(reversed(small), reversed(big)))


def rowwise(op, a: Tensor, b: Tensor) -> Tensor:
    """``op(a, b)`` where one operand is ``[..., N, d]`` and the other a row ``[..., 1, d]`` or ``[d]``.

    Same result as plain broadcasting. Why: on CPU an elementwise kernel that broadcasts
    a short last dimension (``d`` = 2–6 state components) runs an inner loop of length
    ``d`` and is 5–7× slower than a contiguous one. Viewing the full operand as
    ``[..., N/k, k·d]`` and tiling the row ``k`` times restores a long inner loop. Falls
    back to plain broadcasting when the shapes do not fit (non-contiguous, ``N`` not
    divisible, other broadcast patterns) and below :data:`_ROWWISE_MIN` entries.
    """
    full, row, swap = (a, b, False) if a.numel() >= b.numel() else (b, a, True)
    if full.numel() < _ROWWISE_MIN or full.dim() < 2 or row.dim() == 0:
        return op(a, b)
    if not full.is_contiguous() or full.device.type != "cpu":
        return op(a, b)
    n, d = full.shape[-2:]
    if row.shape[-1] != d or (row.dim() >= 2 and row.shape[-2] != 1) or row.dim() > full.dim():
        return op(a, b)
    if row.dim() >= 2 and not _broadcasts_to(row.shape[:-2], full.shape[:-2]):
        return op(a, b)
    k = _period(n)
    if k == 1 or d * k < 8:
        return op(a, b)
    view = full.reshape(full.shape[:-2] + (n // k, d * k))
    tiled = row.repeat((1,) * (row.dim() - 1) + (k,))
    out = op(tiled, view) if swap else op(view, tiled)
    return out.reshape(full.shape)


def rowwise_addcmul(base: Tensor, full: Tensor, row: Tensor) -> Tensor:
    """``base + full ⊙ row`` for ``base``, ``full [..., N, d]`` and a row ``row [d]``.

    The fused multiply-add (one pass instead of two) with :func:`rowwise`'s period trick:
    ``base`` is viewed like ``full``. Plain broadcasting when ``base`` is not ``full``-shaped.
    """
    if base.shape != full.shape:
        return torch.addcmul(base, full, row)
    return rowwise(lambda f, r: torch.addcmul(base.reshape(f.shape), f, r), full, row)
