"""Input validation that names the offending argument and says what was expected."""

from __future__ import annotations

import inspect
import math
import numbers
import operator
from collections.abc import Sequence
from enum import Enum

import numpy as np
import torch
from torch import Tensor

from .linalg import under_transform

__all__ = [
    "Choice",
    "as_tensor",
    "values_known",
    "check_vector_last",
    "check_square",
    "check_positive_definite",
    "cholesky_fails",
    "check_finite",
    "check_symmetric",
    "check_sequence",
    "check_mask",
    "check_positive_int",
    "check_finite_number",
    "check_rate",
    "model_dtype_device",
    "check_strategy",
    "check_callable_as",
    "check_ess_threshold",
    "check_sequence_inputs",
    "check_step_inputs",
    "check_filter_inputs",
    "check_model",
    "check_carry_batch",
    "check_carry_tensor",
    "check_semidefinite",
    "NonFinite",
]


class Choice(str, Enum):
    """Base of the library's named options (``Channel``, ``Method``, ``Reading``, …): built
    once from a name at the edge (``Channel("sensor")``), compared by identity inside; a
    name that is none of them is a ``ValueError`` listing the choices."""

    @classmethod
    def _missing_(cls, value):
        if isinstance(value, str):  # its name in any case ("HOLD", "Hold": the member's name)
            for member in cls:
                if value.lower() in (member.value.lower(), member.name.lower()):
                    return member
        names = ", ".join(repr(m.value) for m in cls)
        raise ValueError(f"{value!r} is not a {cls.__name__}: one of {names}")


def version_stamp(t: Tensor):
    """``t``'s autograd version counter, for a cache kept while a tensor is unwritten; for
    an inference tensor (``torch.inference_mode()``: no counter to read, and writable in
    place unseen) a new object equal to no other, so the cache is made again (caches keyed
    on ``t._version`` had failed in torch's "Inference tensors do not track version
    counter" on a model built under inference mode: a four-tank trial)."""
    return object() if t.is_inference() else t._version


def values_known(t: Tensor) -> bool:
    """Whether ``t`` holds values: ``False`` on the ``meta`` device (shapes and dtypes
    only), where value checks (finiteness, symmetry, definiteness) are skipped so that a
    filter can be traced there; shape, dtype and device checks still apply. A tensor
    batched by ``torch.func.vmap`` is refused here, naming the way that works (vmap forbids
    reading values: a system-identification trial got torch's "data-dependent control
    flow" error alone)."""
    if _vmapped(t):
        raise ValueError(
            "torch.func.vmap over a model's parameters, data or an estimator's (or detector's) "
            "state is not supported: the filters and detectors check values (finiteness, "
            "symmetry, definiteness, signs) and choose paths by them. "
            "Batch instead: a model of per-run matrices (e.g. Q [B, d, d]) runs B parameter "
            "sets in one call, and measurements ys [B, T, dy] B data sets; gradients flow to "
            "each (docs/gradients.md)"
        )
    return t.device.type != "meta"


def host_array(t: Tensor) -> np.ndarray:
    """``t``'s values as a numpy array on the host (float32 and float64 kept, other dtypes
    as float64), for reading values only (a check): also inside the ``torch.func``
    transforms ``grad``, ``jvp``, ``jacrev``, ``jacfwd``, whose wrappers have no storage
    (``.numpy()`` raised "Cannot access data pointer of Tensor that doesn't have storage"
    in an online step's value checks under ``torch.func.grad``: a gradients trial)."""
    *_, t = _functorch_levels(t)  # the innermost: the values themselves
    with torch._C._DisableFuncTorch():  # (the unwrapped value read outside the transform)
        c = t.detach().resolve_neg()  # (numpy reads no view of torch's negative bit)
        return (c if c.dtype in (torch.float32, torch.float64) else c.double()).cpu().numpy()


def _functorch_levels(t: Tensor):
    """``t`` and, one ``torch.func`` level down at a time, what each wrapper wraps (the last
    a plain tensor)."""
    functorch = torch._C._functorch
    yield t
    while functorch.is_functorch_wrapped_tensor(t):
        t = functorch.get_unwrapped(t)
        yield t


def _vmapped(t: Tensor) -> bool:
    """Whether ``t`` is batched by ``torch.func.vmap`` at any of its functorch levels."""
    return any(torch._C._functorch.is_batchedtensor(level) for level in _functorch_levels(t))


#: torch's floating dtype of a numpy floating dtype, by its size in bytes.
_NUMPY_FLOATS = {2: torch.float16, 4: torch.float32, 8: torch.float64}


def as_tensor(value, name: str, *, dtype=None, device=None) -> Tensor:
    """Convert ``value`` to a floating tensor, keeping autograd history of tensors.

    Without ``dtype``: a floating tensor or numpy floating array keeps its dtype (a model
    built from scipy's float64 matrices stays float64, as ``torch.as_tensor`` keeps it; it
    was rounded to float32, and then refused float64 measurements); anything else (lists,
    numbers, integer arrays) takes torch's default dtype."""
    if isinstance(value, Tensor):
        if isinstance(value, torch.nn.Parameter) and (
            (dtype is not None and value.dtype != dtype)
            or (device is not None and value.device != torch.device(device))
        ):  # fmt: skip
            # a cast copy is no parameter: the model would list none, and an optimiser
            # built from model.parameters() would leave it untrained (a user trial)
            where = f"{value.dtype} on {value.device}"
            raise ValueError(
                f"{name} is an nn.Parameter of {where}, but the model is "
                f"{dtype or value.dtype} on {device or value.device}: converting it would make "
                "a copy that is no parameter of the model (an optimiser of "
                "model.parameters() would not train it); make the Parameter in the model's "
                "dtype and device"
            )
        if value.is_complex():  # (a cast drops the imaginary part: diag(0.9 ± 0.5j), |λ| 1.03,
            # had become diag(0.9, 0.9) with torch's warning alone: a review)
            raise ValueError(
                f"{name} is {value.dtype}: the models are real (give {name}.real where its "
                "real part is meant)"
            )
        if not value.is_floating_point():
            value = value.to(dtype or torch.get_default_dtype())
        elif dtype is not None and value.dtype != dtype:
            value = value.to(dtype)
        if device is not None:
            value = value.to(device)
        return value
    if isinstance(value, (list, tuple)) and value and all(isinstance(v, Tensor) for v in value):
        return torch.stack([as_tensor(v, name, dtype=dtype, device=device) for v in value])
    array_dtype = getattr(value, "dtype", None)  # a numpy array's or number's
    if dtype is None and getattr(array_dtype, "kind", None) == "f":
        dtype = _NUMPY_FLOATS.get(array_dtype.itemsize)
    try:
        return torch.as_tensor(value, dtype=dtype or torch.get_default_dtype(), device=device)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise ValueError(
            f"{name} must be a tensor or array of numbers; got {type(value).__name__}"
        ) from exc


def check_vector_last(t: Tensor, name: str, dim: int) -> None:
    """``t`` must have shape ``[..., dim]``."""
    if t.dim() < 1 or t.shape[-1] != dim:
        raise ValueError(f"{name} must have shape [..., {dim}]; got {tuple(t.shape)}")


def check_square(t: Tensor, name: str, dim: int | None = None) -> None:
    """``t`` must have shape ``[..., d, d]`` (and ``d == dim`` when given)."""
    if t.dim() < 2 or t.shape[-1] != t.shape[-2] or (dim is not None and t.shape[-1] != dim):
        want = f"[..., {dim}, {dim}]" if dim is not None else "[..., d, d]"
        raise ValueError(f"{name} must have shape {want}; got {tuple(t.shape)}")


def broadcast_shapes(*shapes) -> torch.Size:
    """``torch.broadcast_shapes(*shapes)`` (shapes: sizes or tuples), at once where every
    non-empty one is the same shape: the common case of one run's or one batch's tensors.
    torch's function is written in Python and checks its arguments at length, about 8 µs
    a call on the 2-core CPU: 16 calls were 40 % of a Kalman filter's ``init``."""
    first = None
    for shape in shapes:
        if len(shape):
            if first is None:
                first = shape
            elif shape != first:
                return torch.broadcast_shapes(*shapes)  # (its error where they do not fit)
    return torch.Size(() if first is None else first)


def broadcast_or_none(*shapes) -> torch.Size | None:
    """``torch.broadcast_shapes(*shapes)``, or ``None`` where they do not broadcast: for
    the checks that name what does not fit instead of torch's "The size of tensor a …"."""
    try:
        return broadcast_shapes(*shapes)
    except RuntimeError:
        return None


def check_batch_shapes(whose: str = "the model's parameters", /, **shapes: torch.Size) -> None:
    """A model's parameters' batch shapes (one set per run) must broadcast together: F for
    3 runs and Q for 4 failed later, deep in a filter ("The size of tensor a (3) …").
    ``whose`` names the parameters in the message (a noise model's own, e.g.)."""
    if broadcast_or_none(*shapes.values()) is None:
        listed = ", ".join(f"{name} {tuple(shape)}" for name, shape in shapes.items())
        raise ValueError(
            f"{whose} must share one batch shape (one set per run) or broadcast "
            f"to one; got the batch shapes {listed}"
        )


def add_note(error: BaseException, note: str) -> None:
    """``error.add_note(note)`` where Python has it (3.11 on); nothing on 3.10, which the
    package supports (the call had replaced an estimator's own error by an
    ``AttributeError`` there: a packaging trial)."""
    if hasattr(error, "add_note"):
        error.add_note(note)


def check_finite_at(t: Tensor, name: str) -> None:
    """``ValueError`` naming ``name`` and the index of its first NaN or ±Inf entry (a filter
    result handed to a smoother, whose entries a user may have edited)."""
    if values_known(t) and not bool(torch.isfinite(t).all()):
        raise ValueError(
            f"{name} contains NaN or Inf values (first at {first_index(~torch.isfinite(t))})"
        )


def check_same_result(t: Tensor, name: str, ref: Tensor, ref_name: str) -> None:
    """``ValueError`` where ``t`` (``name``) is not of ``ref``'s (``ref_name``'s) dtype and
    device: two fields of one filter result."""
    if t.dtype != ref.dtype or t.device != ref.device:
        raise ValueError(
            f"{name} is {t.dtype} on {t.device}, and {ref_name} {ref.dtype} on {ref.device}: "
            "fields of one result of one filter"
        )


def check_finite(t: Tensor, name: str) -> None:
    if values_known(t) and not bool(torch.isfinite(t).all()):
        raise ValueError(f"{name} contains NaN or Inf values; every entry must be finite")


#: The largest ``|C_ij − C_ji| / √(C_ii C_jj)`` a covariance may hold: a correlation
#: written in one triangle only (0.9 between two variances of 1e-2 beside one of 1e6) had
#: passed ``rtol`` of the largest entry, and sampling (Cholesky: the lower triangle, 0.9) and
#: the filters (symmetrised: 0.45) then used two noise models (a linalg trial). Round-off
#: stays orders of magnitude below it.
CORRELATION_ASYMMETRY = 1e-3


def check_symmetric(t: Tensor, name: str, rtol: float = 1e-6) -> None:
    """``t [..., d, d]`` must be symmetric up to ``rtol`` relative to its largest entry, and
    each pair off the diagonal to :data:`CORRELATION_ASYMMETRY` of ``√(t_ii t_jj)`` (where
    that is not 0)."""
    if t.numel() == 0 or not values_known(t):
        return
    t = t.detach()
    scale = t.abs().amax(dim=(-1, -2), keepdim=True).clamp_min(1e-30)
    gap = (t - t.transpose(-1, -2)).abs()
    asym = gap / scale
    if bool((asym > rtol).any()):
        raise ValueError(
            f"{name} must be symmetric; max relative asymmetry {float(asym.max()):.3g}"
        )
    var = t.diagonal(dim1=-2, dim2=-1).abs()
    pair = (var.unsqueeze(-1) * var.unsqueeze(-2)).sqrt()
    corr = torch.where(pair > 0, gap / pair.clamp_min(1e-300), torch.zeros_like(gap))
    if bool((corr > CORRELATION_ASYMMETRY).any()):
        d = t.shape[-1]
        i, j = divmod(int(corr.reshape(-1, d * d).amax(0).argmax()), d)
        raise ValueError(
            f"{name} must be symmetric: its entries ({i}, {j}) and ({j}, {i}) differ by "
            f"{float(corr.max()):.3g} of √({name}[{i},{i}] · {name}[{j},{j}]) (a correlation "
            "written in one triangle only?)"
        )


def check_positive_definite(
    t: Tensor, name: str, dim: int | None = None, *, resolved: bool = True
) -> None:
    """``t`` must be a finite, symmetric, positive-definite ``[..., d, d]`` matrix, of float32
    or float64 (a float16 covariance had failed in torch's Cholesky: a review); with
    ``resolved`` (a covariance given to build on) also one float32 resolves
    (:func:`cholesky_fails`). ``resolved=False`` for a filter's own output: definite as its
    values are, decided in float64 (a float32 filter's predicted covariance, a correlation
    within 1e-6 of 1 after a precise first reading, had been refused by the smoother)."""
    if t.is_floating_point():
        check_model_dtype(t.dtype, name)
    check_square(t, name, dim)
    check_finite(t, name)
    check_symmetric(t, name)
    if not values_known(t):
        return
    # a variance below the dtype's normal range: its Cholesky factorisation failed or not by
    # where it sat on the diagonal (float32 diag(1e-39, 1) refused, diag(1, 1e-39) taken: a
    # docs trial), so it is refused wherever it is
    diagonal = t.detach().diagonal(dim1=-2, dim2=-1)
    tiny = torch.finfo(t.dtype).tiny
    below = (diagonal > 0) & (diagonal < tiny)
    if bool(below.any()):
        index = first_index(below)
        raise ValueError(
            f"{name} has a variance of {float(diagonal[index]):.3g} (diagonal entry "
            f"{index[-1]}), below {str(t.dtype).removeprefix('torch.')}'s normal range "
            f"({tiny:.3g}), which its factorisation does not resolve: build the model in "
            "float64 or choose units that bring the variances closer"
        )
    failing = cholesky_fails(t, resolved=resolved)
    if bool(failing.any()):
        raise ValueError(_not_definite(t, failing, name))


def cholesky_fails(t: Tensor, *, resolved: bool = True) -> Tensor:
    """Where the Cholesky factorisation of ``t [..., d, d]`` fails (bool ``[...]``), alike on
    every CPU. float32's factorisation of a matrix at float32's precision passes or fails by
    the CPU's kernels: MKL's AVX2 ones left the rank-one ``[[1, 1], [1, 1]]`` a last pivot of
    3e-4 (their reciprocal square roots are inexact), its AVX-512 ones 0, and the rounded
    ``g gᵀ`` of g = (0.1, 0.3) a pivot of float32's round-off on one and none on the other
    (a review: one float32 rank-one matrix in ten decided so), so a model, a pair of local
    estimates or an error's explanation was taken on one machine and refused on another.

    A float32 matrix is decided in float64, from the same values (about 20 µs): it fails
    where float64's factorisation fails or where the smallest eigenvalue of its correlation
    matrix ``D^-½ t D^-½`` (``D`` its variances) is below :data:`FLOAT32_CORRELATION_FLOOR`
    · d · ε₃₂ (4.8e-7 for d = 4: near that, whatever its scales, float32's own factorisation
    is round-off and the kernels part). The eigenvalue, not the factor's pivots,
    so that the order of the states does not decide (a review: a pivot floor refused a Q in
    one order and took it in another). float64 matrices are decided by their own
    factorisation (its kernels agree across CPUs where float32's did not, a review's sweep).
    ``resolved=False``: float64's factorisation of a float32 matrix's values alone decides
    (definite as its values are, however near singular)."""
    t = t.detach()
    if t.dtype != torch.float32:
        return torch.linalg.cholesky_ex(t).info != 0
    t, d = t.double(), t.shape[-1]
    factor, info = torch.linalg.cholesky_ex(t)
    failing = info != 0
    if not resolved:
        return failing
    floor = FLOAT32_CORRELATION_FLOOR * d * torch.finfo(torch.float32).eps
    # the correlation matrix's determinant is the product of the pivots over the variances
    # and of its eigenvalues; the other d − 1 sum to under d, so their product is under
    # (d / (d − 1))^(d−1) < e: where det over that clears the floor, so does the smallest
    # eigenvalue, and none is computed (most matrices: 2 µs, not 25; a review had d^(d−1),
    # 27 times looser at d = 4, send most of a batch of condition 1e4 to the eigenvalues)
    variances = t.diagonal(dim1=-2, dim2=-1)
    ratios = factor.diagonal(dim1=-2, dim2=-1).square() / variances
    bound = (d / (d - 1)) ** (d - 1) if d > 1 else 1.0
    unsure = ~failing & ~(ratios.prod(-1) >= floor * bound)
    if bool(unsure.any()):
        # (where it factorised, the variances are > 0: the scaling is defined)
        scale = variances[unsure].rsqrt()
        correlation = t[unsure] * scale.unsqueeze(-1) * scale.unsqueeze(-2)
        failing = failing.clone()
        failing[unsure] = torch.linalg.eigvalsh(correlation)[..., 0] < floor
    return failing


#: The smallest eigenvalue of a float32 matrix's correlation matrix must be at least this
#: many times d·ε₃₂ (:func:`cholesky_fails`). Measured (2026-12-08, 3,000 random correlation
#: matrices per point, d = 2, 4, 6): float32's factorisation failed with either MKL kernels
#: up to a smallest eigenvalue of about 1.2e-7 (≈ ε₃₂) and never from 3e-7 (a review: d = 2
#: to 12, 130,000 matrices of several shapes, never above half the floor), so
#: d·ε₃₂ (2.4e-7 to 7.2e-7) keeps a margin above where the kernels part. (4·d·ε₃₂ had
#: refused a 6-state integrator chain's exact discretised Q, 8.5e-7, which float32 factorises
#: on both: a review.)
FLOAT32_CORRELATION_FLOOR = 1.0


def first_index(flags: Tensor) -> tuple[int, ...]:
    """The index of the first ``True`` of a bool tensor with one (row-major order): where
    an error names the first bad entry."""
    return tuple(int(i) for i in flags.nonzero()[0])


def _indefinite(member: Tensor, eps: float) -> tuple[str | None, float | None]:
    """``(why, lowest)``: why the float64 ``member [d, d]`` is indefinite beyond the
    round-off of a matrix of relative precision ``eps`` (its dtype's), or ``None``: a
    negative variance, a zero variance with a covariance beside it, or its correlation
    matrix's smallest eigenvalue below −10·d·ε (scale-free: in mixed units the raw
    eigenvalues hid an indefinite block, and float32's rounding of a rank-deficient g gᵀ
    moves its zero eigenvalue by about ε₃₂, past a float64 threshold: two reviews).
    ``lowest``: that eigenvalue, of the states whose variance is not 0 (``None`` where it
    was not computed), for :func:`_not_definite` to read again."""
    var = member.diagonal()
    if bool((var < 0).any()):
        return f"a negative variance, {float(var.min()):.3g}", None
    zero = var == 0
    if bool((member[zero].abs().sum(-1) > 0).any()):
        return "a variance of 0 beside a covariance that is not 0", None
    keep = ~zero
    scale = var[keep].rsqrt()
    correlation = member[keep][:, keep] * scale[:, None] * scale[None, :]
    if correlation.numel() == 0:
        return None, None
    lowest = float(torch.linalg.eigvalsh(correlation)[0])
    if lowest < -10 * member.shape[-1] * eps:
        return f"its correlation matrix's smallest eigenvalue is {lowest:.3g}", lowest
    return None, lowest


def _not_definite(t: Tensor, failing: Tensor, name: str) -> str:
    """Why ``t`` (its first member whose Cholesky factorisation failed) is refused, and what
    to do: a rank-deficient covariance needs a variance added, one definite in exact
    arithmetic but beyond the dtype's precision float64 (or the variance). The suggested
    variance is one the dtype resolves (1e-12 of the largest was below float32's spacing:
    the "fixed" matrix was the same, bit for bit)."""
    index = first_index(failing) if failing.dim() else ()
    member = t.detach()[index].double()
    where = f" (batch index {index})" if index else ""
    indefinite, correlation_lowest = _indefinite(member, torch.finfo(t.dtype).eps)
    if indefinite is not None:
        # no variance added makes it a covariance, and it was told to add one (a review: −1
        # raised by 1e-4 of itself to −1.0001; [[1, 2], [2, 1]] called rank-deficient)
        return (
            f"{name}{where} must be positive definite, and it is indefinite ({indefinite}): "
            "not a covariance (a sign, a transposition or a square root missing?)"
        )
    dtype, eps = str(t.dtype).replace("torch.", ""), torch.finfo(t.dtype).eps
    # a variance that lifts the correlation matrix's smallest eigenvalue to about `size`,
    # ten times float32's floor d·ε₃₂ at any d (1e-4 had been refused again from d = 839)
    d = member.shape[-1]
    size = 1e-12 if t.dtype == torch.float64 else max(1e3 * eps, 10 * d * eps)
    var = member.diagonal()
    zeros = [i for i, v in enumerate(var.tolist()) if v == 0]
    if len(zeros) == d:  # (Q = 0: any multiple of its variances is 0 again, a review)
        jitter = f"a variance of its own on each state ({name} = 0 has no scale to take one from)"
    elif zeros:  # (max(diag) had raised a variance of 1e-8 to 1e4 beside one of 1e8)
        jitter = (f"{name} + {size:.0e} · diag({name}) (each variance raised by {size:.0e} of "
                  f"itself) and a variance of its own on state{'s' * (len(zeros) > 1)} "
                  f"{', '.join(map(str, zeros))}, whose variance is 0")  # fmt: skip
    elif float(var.max()) > 1e4 * float(var.min()):
        # variances in mixed units: each raised by that much of itself (a variance of the
        # largest had added 1e-4 to a variance of 1e-12: a review), which lifts the
        # correlation matrix's smallest eigenvalue to about that much whatever the units
        jitter = (
            f"{name} + {size:.0e} · diag({name}) (each variance raised by {size:.0e} of itself)"
        )
    else:
        jitter = f"{name} + {size:.0e} · max(diag) · I"
    # definite beyond float64's round-off of its correlation matrix's eigenvalues (a
    # rank-one matrix's smallest came out 3e-21 for 0), whatever its units (judged on the
    # unscaled eigenvalues, variances 1e6 apart had read as rank-deficient: a review): then
    # too near singular for its own dtype alone
    lowest = correlation_lowest if not zeros and correlation_lowest is not None else -1.0
    if lowest > 10 * d * d * torch.finfo(torch.float64).eps:
        # (its correlation matrix's eigenvalue, not the unscaled ones: in mixed units those
        # read −3e-20 in round-off beside "positive definite", a review)
        return (
            f"{name}{where} is positive definite in exact arithmetic (its correlation matrix's "
            f"smallest eigenvalue {lowest:.3g}; variances from {float(var.min()):.3g} to "
            f"{float(var.max()):.3g}) but "
            + (
                f"too near singular for float32 (its factorisation there is round-off, taken "
                f"by some CPUs' kernels and refused by others; relative precision {eps:.2g})"
                if t.dtype == torch.float32
                else f"its Cholesky factorisation fails in {dtype} (relative precision {eps:.2g})"
            )
            + f": build the model in float64, or add a variance ({jitter}) if it was meant to "
            "be singular"
        )
    return (
        f"{name}{where} must be positive definite (all eigenvalues > 0; its smallest is "
        f"{float(torch.linalg.eigvalsh(member)[0]):.3g}): a rank-deficient covariance (Q = 0, P0 = 0, the textbook q g gᵀ of a "
        "constant-velocity model) needs a small variance added to make it definite, e.g. "
        f"{jitter}, or the full-rank discretised noise (README, Numerical limits)"
    )


def check_sequence(t: Tensor, name: str, dim: int, *, allow_nan: Tensor | None = None) -> None:
    """``t`` must be ``[..., T, dim]`` with finite entries.

    ``allow_nan`` is an optional boolean tensor broadcastable to ``t`` marking entries
    whose value is ignored (unreceived measurements), which may then be NaN.
    """
    if t.dim() < 2 or t.shape[-1] != dim:
        raise ValueError(
            f"{name} must have shape [..., T, {dim}] (batch first, time second to last); got {tuple(t.shape)}"
        )
    bad = ~torch.isfinite(t)
    if allow_nan is not None:
        bad = bad & ~allow_nan
    if bool(bad.any()):
        hint = (
            " (pass mask=... to mark lost entries, which may then be NaN)"
            if allow_nan is None
            else ""
        )
        raise ValueError(
            f"{name} contains NaN or Inf values{hint}; received entries must be finite"
        )


def check_one_dtype_device(data: Tensor, data_name: str, covs: Tensor, covs_name: str) -> None:
    """``ValueError`` where ``covs`` are of another dtype or device than ``data`` (a
    statistic whitened by covariances of another dtype came out in theirs, or promoted,
    without a word: float32 covariances of float64 innovations, 1.5e-5 off)."""
    if covs.dtype != data.dtype or covs.device != data.device:
        raise ValueError(
            f"{covs_name} are {covs.dtype} on {covs.device} and {data_name} {data.dtype} on "
            f"{data.device}: give them one dtype and device"
        )


def check_mask(mask: Tensor, name: str, shape: torch.Size) -> Tensor:
    """``mask`` must be boolean (or 0/1) and broadcast to ``shape``; returns it as bool."""
    if not isinstance(mask, Tensor):
        mask = torch.as_tensor(mask)
    if mask.dtype != torch.bool:
        if not bool(((mask == 0) | (mask == 1)).all()):
            raise ValueError(f"{name} must be boolean (True = entry received)")
        mask = mask.bool()
    # to it, not with it: a [2, 3] mask for a [3] shape had passed (a mutation review)
    if broadcast_or_none(mask.shape, shape) != torch.Size(shape):
        raise ValueError(f"{name} must broadcast to {tuple(shape)}; got {tuple(mask.shape)}")
    return mask


def real_number(value) -> float | None:
    """``float(value)`` for a real number (NumPy's, or a one-entry tensor, too), ``None`` for
    anything else (``True``, ``"0.5"``): for settings checked whenever they are set."""
    if isinstance(value, Tensor) and value.numel() == 1:
        value = value.item()
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        return None
    return float(value)


def check_finite_number(
    value, name: str, *, positive: bool = False, nonnegative: bool = False
) -> float:
    """``value`` must be a finite real number (``> 0`` / ``>= 0`` when asked); returns a ``float``."""
    if isinstance(value, Tensor) and value.numel() == 1:
        value = value.item()
    # numbers.Real: numpy's numbers too (np.float32 is no float, np.int64 no int)
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise TypeError(f"{name} must be a real number; got {type(value).__name__}")
    value = float(value)
    ok = math.isfinite(value) and (not positive or value > 0) and (not nonnegative or value >= 0)
    if not ok:
        need = " > 0" if positive else " >= 0" if nonnegative else ""
        raise ValueError(f"{name} must be a finite number{need}; got {value!r}")
    return value


def check_fraction(value, name: str) -> float:
    """``value`` must be a real number in ``[0, 1)`` (a probability threshold, a share);
    returns it as ``float`` (NaN fails the range)."""
    number = real_number(value)
    if number is None or not 0.0 <= number < 1.0:
        raise ValueError(f"{name} must be a number in [0, 1); got {value!r}")
    return number


def check_rate(
    value, name: str, *, unset: str | None = None, kind: str = "a false-alarm rate"
) -> float:
    """``value`` must be a false-alarm rate (or the ``kind`` of probability it is: a
    confidence level is none), a number in (0, 1) (``unset``: how the caller spells "no
    rate", where it takes one, for the message); returns it as ``float``.
    Numpy's numbers and a one-element tensor count as numbers, as in
    :func:`check_finite_number`."""
    if isinstance(value, Tensor) and value.numel() == 1:
        value = value.item()
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not 0 < value < 1:
        alternative = "" if unset is None else f" or {unset}"
        raise ValueError(f"{name} must be {kind} in (0, 1){alternative}; got {value!r}")
    return float(value)


def check_flag(value, name: str) -> bool:
    """``value`` as a bool: ``True``/``False`` (NumPy's too) or the integers 1/0; anything
    else (``"no"``, ``None``, ``0.5``) a ``ValueError`` naming ``name``, where ``bool()`` had
    read it truthy or falsy."""
    if isinstance(value, bool | np.bool_) or (isinstance(value, numbers.Integral)
                                              and value in (0, 1)):  # fmt: skip
        return bool(value)
    raise ValueError(f"{name} must be True or False; got {value!r}")


def check_integer(value, name: str, minimum: int = 0) -> int:
    """``int(value)`` for an integer ``>= minimum`` (numpy's integers too: a count read from
    an array); ``ValueError`` naming ``name`` else (``True`` is not a count)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}; got {value!r}")
    return int(value)


def check_batch_shape(batch_shape, least: int = 1, name: str = "batch_shape") -> torch.Size:
    """``batch_shape`` (a sequence of integers, an integer array or tensor, or one integer;
    numpy's too) as a ``torch.Size``, each entry at least ``least`` (the function forms
    ``gaussian_init`` and ``particle_init``, and ``simulate``, take 0: no runs);
    ``ValueError`` naming it otherwise. A bool is no size (``simulate(T, True)`` had simulated one run, ``False``
    none, without a word; a numpy integer had failed as "not iterable": an ssm trial)."""
    expect = f"{name} must be a tuple of integers >= {least} (or one integer)"
    if isinstance(batch_shape, (bool, np.bool_)):
        raise ValueError(f"{expect}; got {batch_shape!r}")
    iterable = isinstance(batch_shape, Sequence) or (
        isinstance(batch_shape, (np.ndarray, Tensor)) and batch_shape.ndim > 0
    )
    if not iterable:  # one integer (numpy's, a 0-d array or tensor too)
        try:
            batch_shape = (operator.index(batch_shape),)
        except TypeError:
            raise ValueError(f"{expect}; got {batch_shape!r}") from None
    entries = []
    for size in batch_shape:
        if isinstance(size, (bool, np.bool_)):
            raise ValueError(f"{expect}; got {tuple(batch_shape)!r}")
        try:
            entries.append(operator.index(size))
        except TypeError:
            raise ValueError(f"{expect}; got {batch_shape!r}") from None
    if any(size < least for size in entries):
        raise ValueError(f"{expect}; got {tuple(entries)}")
    return torch.Size(entries)


def check_positive_int(value, name: str) -> int:
    # numbers.Integral: numpy's integers too (a count read from an array)
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 1:
        raise ValueError(f"{name} must be a positive integer (>= 1); got {value!r}")
    return int(value)


# ------------------------------------------------------------------ filter inputs ----
# One set of checks shared by every public filter and online step (kalman, extended,
# unscented, particle, and the FDI filters): each failure names the argument and says
# what was expected, before any tensor work (a raw torch error deep inside a filter names
# neither).


class NonFinite(Choice):
    """What a whole-sequence filter does with a NaN or ±Inf in a received entry of ``ys``:
    raise (default) or treat the entry as unreceived (counted per run)."""

    RAISE = "raise"
    SKIP = "skip"


def model_dtype_device(model) -> tuple[torch.dtype | None, torch.device | None]:
    """dtype and device of a model's tensors (``(None, None)`` when it holds none).

    The prior mean when the model has one (every built-in model does), else its first
    floating parameter or buffer.
    """
    initial = getattr(model, "initial", None)
    mean = getattr(initial, "mean", None)
    if isinstance(mean, Tensor) and mean.is_floating_point():
        return mean.dtype, mean.device
    tensors = getattr(model, "parameters", None)
    if tensors is not None:
        for t in list(model.parameters()) + list(model.buffers()):
            if t.is_floating_point():
                return t.dtype, t.device
    return None, None


def _check_float_tensor(t, name: str, want: str, dtype, device) -> None:
    if not isinstance(t, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor of shape {want}; got {type(t).__name__}")
    if not t.is_floating_point():
        expect = dtype if dtype is not None else "a floating dtype"
        raise ValueError(f"{name} must have a floating dtype ({expect}); got {t.dtype}")
    if dtype is not None and t.dtype != dtype:
        raise ValueError(
            f"{name} must have the model's dtype {dtype}; got {t.dtype} "
            f"(convert with {name}.to({dtype}) or build the model in {t.dtype})"
        )
    if device is not None and t.device != device:
        raise ValueError(f"{name} must be on the model's device {device}; got {t.device}")


def check_filtered_dtype(model, filtered: Tensor, what: str) -> None:
    """``ValueError`` where a filter's result tensor ``filtered`` (its ``what``), given to a
    smoother, is not of the model's dtype and device: a float32 model given a float64
    filter's result had failed in torch ("expected scalar type Double but found Float"),
    naming neither. (No conversion is offered: a model converted to the result's dtype
    keeps its own rounding, 0.95f is no 0.95, and is then refused as not the result's.)"""
    dtype, device = model_dtype_device(model)
    if dtype is not None and filtered.dtype != dtype:
        raise ValueError(
            f"filtered holds {filtered.dtype} {what} and the model is {dtype}: smooth with the "
            "model the filter ran on, or run the filter again on this one"
        )
    if device is not None and filtered.device != torch.device(device):
        raise ValueError(
            f"filtered holds {what} on {filtered.device} and the model is on {device}: smooth "
            "with the model the filter ran on, or run the filter again on this one"
        )


def _check_bool_mask(mask, name: str, shape: torch.Size, of: str, device=None) -> Tensor:
    if not isinstance(mask, Tensor):
        raise TypeError(
            f"{name} must be a bool torch.Tensor of shape {tuple(shape)}; got {type(mask).__name__}"
        )
    if mask.dtype != torch.bool:
        # a 0/1 float mask would be ambiguous (a 0.5 is not "half received"): bool only
        raise ValueError(
            f"{name} must have dtype torch.bool (True = entry received); got {mask.dtype}"
        )
    if mask.shape != shape:
        raise ValueError(
            f"{name} must have the shape of {of} {tuple(shape)}; got {tuple(mask.shape)}"
        )
    if device is not None and mask.device != device:  # (torch's error named no argument)
        raise ValueError(f"{name} is on {mask.device} and {of} on {device}: put {name} on "
                         f"{of}'s device")  # fmt: skip
    return mask


def check_strategy(obj, name: str, example: str, params: Sequence[str] = ()) -> None:
    """``obj`` must be ``None`` or a callable strategy object, never its name as a string;
    with ``params``, callable with those positional arguments, as the filter calls it (a
    resampler's ``__call__`` written without ``generator`` failed at its first resampling
    with Python's bare "takes 3 positional arguments but 4 were given")."""
    if obj is None:
        return
    if isinstance(obj, str):
        raise TypeError(
            f"{name} must be an object, not the string {obj!r}: pass e.g. {name}={example}"
        )
    if isinstance(obj, type):
        raise TypeError(
            f"{name} must be an instance, not the class {obj.__name__}: pass "
            f"{name}={obj.__name__}(...) (e.g. {name}={example})"
        )
    if not callable(obj):
        raise TypeError(
            f"{name} must be a callable object (e.g. {example}); got {type(obj).__name__}"
        )
    if params:
        check_callable_as(obj, f"{name} {type(obj).__name__}", name, params)


def check_callable_as(fn, who: str, call: str, params: Sequence[str],
                      keywords: Sequence[str] = ()) -> None:  # fmt: skip
    """``fn`` can be called with the positional arguments ``params`` (and the keyword
    arguments ``keywords``), as the filter calls it (``call(params…)``), else a
    ``TypeError`` naming ``who``: checked when the filter is made, not at the first call,
    where Python's bare "takes 3 positional arguments but 4 were given" named neither the
    plug-in nor its contract."""
    try:
        signature = inspect.signature(fn)
    except (TypeError, ValueError):  # no signature to read (a builtin): the call will say
        return
    try:
        signature.bind(*params, **dict.fromkeys(keywords))
    except TypeError as error:
        args = ", ".join((*params, *(f"{k}=" for k in keywords)))
        raise TypeError(
            f"{who} is called as {call}({args}); its call takes {signature} "
            f"({error}): docs/plugins.md, The contracts"
        ) from None


def check_ess_threshold(value) -> float:
    """``ess_threshold`` must be a finite real number in ``[0, 1]``; returns it as ``float``."""
    if isinstance(value, Tensor) and value.numel() == 1:
        value = float(value)
    # numbers.Real: numpy's scalars too, as check_finite_number and check_rate take them
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise TypeError(f"ess_threshold must be a number in [0, 1]; got {type(value).__name__}")
    if not (math.isfinite(float(value)) and 0.0 <= value <= 1.0):
        raise ValueError(f"ess_threshold must lie in [0, 1] (a finite number); got {value!r}")
    return float(value)


def _all_finite(t: Tensor) -> bool:
    """Whether every entry of ``t`` is finite, cheaply in the common case.

    A finite sum proves it (a NaN or ±Inf entry makes the sum NaN or ±Inf); the sum is
    one reduction without a ``[..]``-sized boolean temporary (65 → 10 ms on a 160 MB
    ``ys``). Only when the sum is not finite (a bad entry, or an overflow of large finite
    values) is every entry tested.
    """
    if bool(torch.isfinite(t.detach().sum())):
        return True
    return bool(torch.isfinite(t).all())


def check_sequence_inputs(
    model,
    ys,
    us=None,
    mask=None,
    *,
    nonfinite: NonFinite | str = NonFinite.RAISE,
) -> tuple[Tensor, Tensor | None, Tensor | None, Tensor | None]:
    """Validate the inputs of a whole-sequence filter; returns ``(ys, us, mask, skipped)``.

    Checks, each raising an error that names the argument:

    * ``ys`` a floating tensor ``[..., T, dy]`` of the model's dtype and device, ``T ≥ 1``;
    * ``mask`` ``None`` or a ``torch.bool`` tensor of exactly ``ys``'s shape;
    * ``us`` ``None`` (or required absent when ``model.dim_u = 0``) or a finite floating
      tensor ``[..., T, du]`` of the model's dtype whose batch broadcasts with ``ys``'s;
    * received entries of ``ys`` finite. ``nonfinite="raise"`` (default) raises on a NaN
      or ±Inf there; ``nonfinite="skip"`` treats such entries as unreceived: they are
      folded into the mask and counted in ``skipped [...]`` (per run, summed over time and
      entries; ``None`` with ``"raise"``).

    The returned ``ys`` has its unreceived entries replaced by 0 (they are never read, but
    ``0 · NaN`` would still be NaN in the masked update).
    """
    try:
        nonfinite = NonFinite(nonfinite)
    except ValueError as exc:
        raise ValueError(f"nonfinite: {exc}") from None
    dy = model.dim_y
    dtype, device = model_dtype_device(model)
    _check_float_tensor(ys, "ys", f"[..., T, {dy}]", dtype, device)
    if ys.dim() < 2 or ys.shape[-1] != dy:
        raise ValueError(
            f"ys must have shape [..., T, {dy}] (batch first, time second to last); got {tuple(ys.shape)}"
        )
    if ys.shape[-2] == 0:
        raise ValueError(
            f"ys must hold at least one time step (T >= 1); got shape {tuple(ys.shape)}"
        )
    check_model_batch(model, ys.shape[:-2], "the batch of ys")
    if mask is not None:
        mask = _check_bool_mask(mask, "mask", ys.shape, "ys", ys.device)
    # on the meta device nothing is known to be non-finite
    bad = None
    if values_known(ys) and not _all_finite(ys):
        finite = torch.isfinite(ys)
        bad = ~finite if mask is None else ~finite & mask
    skipped = None
    if nonfinite is NonFinite.SKIP:
        no_skips = ys.new_zeros(ys.shape[:-2], dtype=torch.long)
        skipped = no_skips if bad is None else bad.sum((-1, -2))
        if bad is not None and bool(bad.any()):
            mask = finite if mask is None else mask & finite
    elif bad is not None and bool(bad.any()):
        where = first_index(bad)
        raise ValueError(
            f"ys contains NaN or Inf values at received entries (first at index {where}); "
            "every received measurement must be finite. Pass mask=torch.isfinite(ys) to treat "
            "them as unreceived (nonfinite='skip' does so where the function takes it: "
            "open_loop, the plain filters and smoothers, the gated filters)"
        )
    if mask is not None:
        ys = torch.where(mask, ys, torch.zeros((), dtype=ys.dtype, device=ys.device))
    if us is not None:
        us = _check_us(model, us, ys.shape[:-2], ys.shape[-2], dtype, device)
        # (us for 4 runs on a model of 3 parameter sets had been blamed on a batch_shape
        # never passed; a trial of the input checks)
        check_model_batch(model, us.shape[:-2], "the runs of us")
    return ys, us, mask, skipped


def _check_us(
    model, us, batch: torch.Size, num_steps: int | None, dtype, device, against: str = ""
) -> Tensor:
    """``us [..., T, du]`` (``num_steps``; ``None``: one step's ``u [..., du]``) fits the
    model, the dtype and device, and its batch broadcasts with ``batch`` (``against``: whose
    batch, possessive, for the message; default ``ys's`` or ``y's``)."""
    du = model.dim_u
    seq = num_steps is not None
    name = "us" if seq else "u"
    if du == 0:
        raise ValueError(
            f"{name} was given but the model has no input (dim_u = 0); pass {name}=None, "
            "or give the model its input width (dim_u=…) where its transition takes u"
        )
    want = f"[..., T, {du}]" if seq else f"[..., {du}]"
    _check_float_tensor(us, name, want, dtype, device)
    if us.dim() < (2 if seq else 1) or us.shape[-1] != du:
        raise ValueError(f"{name} must have shape {want}; got {tuple(us.shape)}")
    if seq and us.shape[-2] != num_steps:
        raise ValueError(f"us must have T = {num_steps} steps, one per measurement; "
                         f"got {us.shape[-2]}")  # fmt: skip
    lead = us.shape[:-2] if seq else us.shape[:-1]
    if broadcast_or_none(lead, batch) is None:
        whose = against or ("ys's" if seq else "y's")
        raise ValueError(
            f"{name}'s batch shape {tuple(lead)} does not broadcast with {whose} {tuple(batch)}"
        )
    if values_known(us) and not bool(torch.isfinite(us).all()):
        # where, as ys's are named (a recorded log's gap in its inputs: a trial)
        where = first_index(~torch.isfinite(us))
        raise ValueError(
            f"{name} contains NaN or Inf values (first at index {where}); every input must be "
            "finite: an input the plant received is known (a gap in a recorded log's inputs "
            "has to be filled, e.g. with the input held, before filtering)"
        )
    return us


def check_inputs_given(model, us, who: str, why: str) -> None:
    """A second pass over a filter's result (a smoother, a bound) whose numbers depend on
    the inputs (``why``: how) is given them on a model that takes some (``dim_u > 0``).

    The filters read ``us=None`` as zero inputs; a smoother called without the ``us`` its
    filter ran on had smoothed silently wrong (a core-filter trial: the particle smoother
    5.3 smoothed standard deviations off the RTS smoother, the extended RTS smoother 0.58)
    or met a check that blamed the filter result. Zero inputs are said with zeros."""
    du = getattr(model, "dim_u", 0)
    if us is None and du:
        raise ValueError(
            f"us: {who} reads the inputs ({why}) and this model takes {du} (dim_u = {du}): "
            f"pass the us [..., T, {du}] the filter ran on (torch.zeros(..., T, {du}) if it "
            "ran without: the filters read us=None as zero inputs)"
        )


def check_step_inputs(
    model, state_mean, y, u=None, mask=None
) -> tuple[Tensor, Tensor | None, Tensor | None]:
    """Validate the inputs of one online filter step; returns ``(y, u, mask)``.

    ``state_mean [..., dx]`` (the state's mean or particles), ``y [..., dy]`` finite on
    the received entries (a non-finite one raises: a single NaN would poison every later
    state), ``u [..., du]`` or ``None``, ``mask`` ``None`` or bool of exactly ``y``'s
    shape. Unreceived entries of ``y`` come back as 0.
    """
    dy, dx = model.dim_y, model.dim_x
    dtype, device = model_dtype_device(model)
    _check_float_tensor(y, "y", f"[..., {dy}]", dtype, device)
    if y.dim() < 1 or y.shape[-1] != dy:
        raise ValueError(
            f"y must have shape [..., {dy}] (one measurement per run); got {tuple(y.shape)}"
        )
    if state_mean is not None and (
        not isinstance(state_mean, Tensor) or state_mean.dim() < 1 or state_mean.shape[-1] != dx
    ):
        raise ValueError(
            f"state must hold a mean [..., {dx}]; got {getattr(state_mean, 'shape', type(state_mean).__name__)}"
        )
    if mask is not None:
        mask = _check_bool_mask(mask, "mask", y.shape, "y", y.device)
    finite = torch.isfinite(y)
    bad = ~finite if mask is None else ~finite & mask
    if values_known(y) and bool(bad.any()):
        raise ValueError(
            "y contains NaN or Inf values at received entries; every received measurement "
            "must be finite (pass mask=... with False at lost entries)"
        )
    if mask is not None:
        y = torch.where(mask, y, torch.zeros((), dtype=y.dtype, device=y.device))
    if u is not None:
        u = _check_us(model, u, y.shape[:-1], None, dtype, device)
    return y, u, mask


#: A linear model's matrices, which act on the state inside ``f`` and ``h``.
_MATRICES = ("F", "B", "H")


def model_batch_shape(model, *, matrices_only: bool = False) -> torch.Size:
    """The batch shape of ``model``'s parameters (one set per run where it is not ``()``):
    the broadcast of its prior's, its noise covariances' and a linear model's ``F``,
    ``B``, ``H`` leading dimensions (``matrices_only``: of those matrices alone)."""
    shapes = []
    for name in _MATRICES:
        t = getattr(model, name, None)
        if isinstance(t, Tensor) and t.dim() >= 2:
            shapes.append(t.shape[:-2])
    if not matrices_only:
        initial = getattr(model, "initial", None)
        for t, event in ((getattr(initial, "mean", None), 1), (getattr(initial, "cov", None), 2),
                         (_noise_cov(getattr(model, "process_noise", None)), 2),
                         (_noise_cov(getattr(model, "measurement_noise", None)), 2)):  # fmt: skip
            if isinstance(t, Tensor) and t.dim() >= event:
                shapes.append(t.shape[: t.dim() - event])
    try:
        return broadcast_shapes(*shapes)
    except RuntimeError:  # its own parameters disagree: the model's constructor is the judge
        return torch.Size()


def _noise_cov(noise):
    """``noise.cov``, or ``None`` for a noise that has none (a Cauchy noise of one's own,
    which the particle filters run; its missing ``cov`` had stopped them in the checks)."""
    try:
        return getattr(noise, "cov", None)
    except NotImplementedError:
        return None


def method_matrices_batch(model) -> torch.Size:
    """The batch shape of a linear model's ``F``, ``H``, ``B`` as its methods give them at
    the first step (a time-varying model of per-run matrices holds none as attributes: its
    ``[B, n, n]`` had met the sigma points ``[B, 2n+1, n]``, each run's matrix applied to a
    sigma point where B = 2n + 1, 3 to 5 off the Kalman filter; and the particles
    ``[B, N, n]`` where N = B, 0.5 off)."""
    shapes = []
    for name, k in (("transition_matrix", 0), ("observation_matrix", 1), ("control_matrix", 0)):
        method = getattr(model, name, None)
        if callable(method):
            m = method(k)
            if isinstance(m, Tensor) and m.dim() > 2:
                shapes.append(m.shape[:-2])
    try:
        return broadcast_shapes(*shapes) if shapes else torch.Size()
    except RuntimeError:  # its methods disagree: the filters' own checks name it
        return max(shapes, key=lambda shape: shape.numel())


def check_one_model(model, what: str, instead: str) -> None:
    """``model`` holds one parameter set (no batch): ``what`` (e.g. "the particle filter")
    takes one model for all runs; ``instead`` says what to do with a sweep. A matrix or
    covariance per run from a method override counts (:func:`method_matrices_batch`)."""
    own = model_batch_shape(model)
    methods = method_matrices_batch(model)
    if methods.numel() > 1:  # ([1, n, n]: one)
        own = broadcast_or_none(own, methods) or methods
    varying = getattr(model, "_varying_noise", None)
    for method, k in (("process_cov", 0), ("measurement_cov", 1)):
        if varying is not None and varying(method):  # a covariance per run from an override
            cov = getattr(model, method)(k)
            if isinstance(cov, Tensor) and cov.shape[:-2].numel() > 1:  # ([1, d, d]: one)
                own = broadcast_or_none(own, cov.shape[:-2]) or cov.shape[:-2]
    if own:  # (raw shape errors in torch, or particles of the wrong shape, before; a per-run
        # covariance from an override was applied along the particles where N = B)
        raise ValueError(
            f"{what} takes one model for all runs, and this model's parameters have batch shape "
            f"{tuple(own)} (one set per run): {instead}"
        )


def check_model_batch(model, batch: torch.Size, what: str) -> torch.Size:
    """``batch`` (the runs' batch shape, from ``what``) broadcasts with the model's own
    (:func:`model_batch_shape`): a model of 3 parameter sets given 4 runs failed deep in
    torch ("The size of tensor a (3) must match …"). Returns the runs: their broadcast (a
    model of B parameter sets makes B runs of one shared sequence)."""
    own = model_batch_shape(model)
    runs = broadcast_or_none(own, torch.Size(batch))
    if runs is None:
        raise ValueError(
            f"{what} {tuple(batch)} does not broadcast with the batch shape {tuple(own)} of the "
            "model's parameters (one set per run): give one model for all runs, or one per run"
        )
    return runs


def check_filter_inputs(
    model, ys, us=None, mask=None, *, resampler=None, ess_threshold=None, gamma_hat=None
) -> tuple[Tensor, Tensor | None, Tensor | None]:
    """The plain filters' checks for the FDI filters; returns ``(ys, us, mask)``.

    ``ys``/``us``/``mask`` as in :func:`check_sequence_inputs` (a non-finite received
    measurement raises); ``resampler`` an object, not a string; ``ess_threshold`` (when
    given) finite in ``[0, 1]``; ``gamma_hat`` (when a tensor) finite.
    """
    ys, us, mask, _ = check_sequence_inputs(model, ys, us, mask)
    check_strategy(resampler, "resampler", "difffilter.resampling.Systematic()")
    from .resampling import check_resampler_hooks  # (resampling imports this module)

    check_resampler_hooks(resampler)
    if ess_threshold is not None:
        check_ess_threshold(ess_threshold)
    if isinstance(gamma_hat, Tensor) and not bool(torch.isfinite(gamma_hat).all()):
        raise ValueError(
            "gamma_hat contains NaN or Inf values; every attack estimate must be finite"
        )
    return ys, us, mask


def check_model(model, *, prior: bool = True) -> None:
    """``model`` must be a state-space model (``dim_x``, ``dim_y``, ``transition``, ``observe``)
    whose noise models are of its prior's dtype and device, and (``prior``: where a run
    starts from it) whose prior mean is finite (written NaN in place after construction, it
    had been refused by ``init`` and run to NaN means by the whole-sequence filters: a trial
    of models changed under the filters), as are the tensors its ``_matrices_read()``
    names, where it has one (a linear model's ``F``, ``H``, ``B``; the robot's sensor
    positions): written NaN in place, they had run to NaN means without an error."""
    needed = ("dim_x", "dim_y", "dim_u", "transition", "observe", "initial")
    missing = [name for name in needed if not hasattr(model, name)]
    if missing:
        raise TypeError(
            "model must be a difffilter.StateSpaceModel (e.g. difffilter.LinearGaussianModel); "
            f"{type(model).__name__} lacks {', '.join(missing)}"
        )
    _check_noise_dtypes(model)
    _check_noise_fits(model)
    for name, matrix in getattr(model, "_matrices_read", list)():
        # a linear model's F, H or B written NaN in place after construction (a NaN B had
        # run to NaN means without an error, a NaN F or H blamed on Q, R and P0: a trial)
        if matrix.is_floating_point() and values_known(matrix) and not _all_finite(matrix):
            raise ValueError(f"model.{name} contains NaN or Inf values; every entry must be finite")
    mean = getattr(model.initial, "mean", None) if prior else None
    if isinstance(mean, Tensor) and mean.is_floating_point() and mean.device.type != "meta":
        if not bool(torch.isfinite(mean).all()):
            raise ValueError("model.initial.mean (the prior mean m0) contains NaN or Inf values")


def check_model_dtype(dtype: torch.dtype, what: str) -> None:
    """``ValueError`` where ``dtype`` (``what``'s) is no float32 or float64: a model made
    ``.half()`` or ``.bfloat16()`` had failed at its first draw or filter in torch's
    '"cholesky_cpu" not implemented for 'Half'' (a module-operations trial)."""
    if dtype not in (torch.float32, torch.float64):
        raise ValueError(
            f"{what} is {dtype}: the filters and simulate run in torch.float32 or "
            "torch.float64 (convert with .float() or .double())"
        )


def _check_noise_fits(model) -> None:
    """The noise models and the prior of the model's dimensions, and a Gaussian covariance
    written since still symmetric (``Gaussian.check_written``): a noise of another
    dimension assigned after construction had run (a 1-dim process noise on two states
    broadcast to a singular ``Q`` in the EKF, UKF and particle filter) or failed in torch's
    words, and an asymmetric ``R`` written in place was read as its average by the Kalman
    filters and as one triangle by the particle filter (a covariance-write trial)."""
    from .ssm import LinearGaussianModel, NonlinearGaussianModel

    # the dimensions where the noise is added to the state and the measurement as they are
    # (the library's two models; a model of its own, e.g. an augmented state, may differ)
    additive = isinstance(model, (LinearGaussianModel, NonlinearGaussianModel))
    for name, want, what in (("process_noise", "dim_x", "states"),
                             ("measurement_noise", "dim_y", "measurement entries")):  # fmt: skip
        noise = getattr(model, name, None)
        dim, size = getattr(noise, "dim", None), getattr(model, want, None)
        if additive and isinstance(dim, int) and isinstance(size, int) and dim != size:
            raise ValueError(
                f"model.{name} has dimension {dim} and the model {size} {what} ({want}): give "
                f"it a noise of dimension {size}"
            )
        check = getattr(noise, "check_written", None)
        if callable(check):
            check(f"model.{name}")
    prior = getattr(model, "initial", None)
    dim, size = getattr(prior, "dim", None), getattr(model, "dim_x", None)
    if additive and isinstance(dim, int) and isinstance(size, int) and dim != size:
        # (a prior assigned since built, as the models' own errors advise, had been
        # broadcast over the states or failed in torch's words: an ssm trial)
        raise ValueError(
            f"model.initial has dimension {dim} and the model {size} states (dim_x): give it a "
            f"prior of dimension {size} (mean [..., {size}])"
        )
    check = getattr(prior, "check_written", None)
    if callable(check):  # (its mean is check_model's to check, where the prior is read)
        check("model.initial", loc=False)


def _check_noise_dtypes(model) -> None:
    """The process and measurement noise models' floating tensors are of the prior mean's
    dtype and device: every filter adds or multiplies them with the states (a float64
    measurement noise on a float32 model failed in torch's words, "addmv input tensors must
    have the same dtype", in every filter; a trial). That dtype float32 or float64
    (:func:`check_model_dtype`)."""
    ref = getattr(model.initial, "mean", None)
    if not isinstance(ref, Tensor) or not ref.is_floating_point():
        return
    check_model_dtype(ref.dtype, "the model (its prior mean)")
    for name in ("process_noise", "measurement_noise"):
        noise = getattr(model, name, None)
        if not isinstance(noise, torch.nn.Module):
            continue
        for part, t in (*noise.named_parameters(), *noise.named_buffers()):
            if t.is_floating_point() and (t.dtype != ref.dtype or t.device != ref.device):
                where = "" if t.device == ref.device else f" on {t.device}"
                model_where = "" if t.device == ref.device else f" on {ref.device}"
                raise ValueError(
                    f"model.{name}.{part} is {t.dtype}{where} and the model is "
                    f"{ref.dtype}{model_where} (its prior mean): give the noise the model's "
                    f"dtype and device (model.{name} = model.{name}.to({ref.dtype}), or "
                    "model.to(...) for every tensor)"
                )


def check_carry_batch(batch: torch.Size, y: Tensor, u: Tensor | None, mask: Tensor | None) -> None:
    """``y [..., dy]`` (and ``u``, ``mask``) must broadcast with the carry's runs ``batch``."""
    for name, value in (("y", y), ("u", u), ("mask", mask)):
        if value is None:
            continue
        lead = value.shape[:-1]
        try:
            full = broadcast_shapes(lead, batch)
        except RuntimeError:
            full = None
        if full != batch:
            raise ValueError(
                f"{name}'s batch shape {tuple(lead)} does not broadcast to the carry's "
                f"runs {tuple(batch)}: pass one {name} per run "
                f"({list((*batch, value.shape[-1]))})"
            )


def check_carry_fits_model(model, **tensors) -> None:
    """The carry's floating tensors are of the model's dtype and device: a model moved with
    ``.to()`` after ``init`` (the carry keeps the old tensors) failed inside torch, "expected
    m1 and m2 to have the same dtype" (a deployment trial)."""
    dtype, device = model_dtype_device(model)
    if dtype is None:
        return
    for name, t in tensors.items():
        # (an integer one too: an int64 mean of the right values had made the UKF's sigma
        # weights int64, rounded to 0, and the other filters fail in torch: a carries trial)
        if isinstance(t, Tensor) and (t.dtype, t.device) != (dtype, device):
            raise ValueError(
                f"carry.{name} is {t.dtype} on {t.device} and its model's tensors {dtype} on "
                f"{device} (a model moved with .to() after init keeps its carries as they "
                "were): start a new carry with init(model, …)"
            )


def check_carry_tensor(t, name: str, *, dim: int | None = None, covariance: bool = False) -> None:
    """A tensor of a carry built outside its estimator: finite (a NaN would poison every
    later step), of last dimension ``dim``, and with ``covariance`` symmetric and positive
    semi-definite (:func:`check_semidefinite`)."""
    if not isinstance(t, Tensor):
        raise TypeError(f"carry.{name} must be a torch.Tensor; got {type(t).__name__}")
    if dim is not None and (t.dim() < 1 or t.shape[-1] != dim):
        raise ValueError(f"carry.{name} must have shape [..., {dim}]; got {tuple(t.shape)}")
    if covariance and (t.dim() < 2 or t.shape[-1] != t.shape[-2]):  # (check_symmetric's
        raise ValueError(  # IndexError had named nothing: a carries trial)
            f"carry.{name} must be a covariance [..., d, d]; got {tuple(t.shape)}"
        )
    if not t.is_floating_point():  # (before torch.finfo's TypeError on an integer one)
        raise ValueError(f"carry.{name} must be a floating tensor; got {t.dtype}")
    if values_known(t) and not _all_finite(t):
        raise ValueError(
            f"carry.{name} contains NaN or Inf values; a carry must come from the "
            "estimator's init (or an earlier step) with finite values"
        )
    if covariance and values_known(t):
        check_symmetric(t, f"carry.{name}")
        check_semidefinite(t, f"carry.{name}")


#: What :func:`check_semidefinite` advises by default: a carry's covariance.
_CARRY_ADVICE = (
    "a carry rebuilt by hand needs the covariance its filter returned (or one built as L Lᵀ)"
)


def step_covariance(model, method: str, k: int) -> Tensor:
    """``model.process_cov(k)`` or ``model.measurement_cov(k)`` (``method``) as the Gaussian
    filters read it, checked where the model's class overrides the method (time-varying
    noise, :meth:`~difffilter.StateSpaceModel._varying_noise`; the constructor checked the
    noise modules' own covariances): finite, symmetric and positive semi-definite (a
    singular covariance runs in the Gaussian filters; ``simulate`` and the particle
    filters, which draw from it, need it definite). A negative-definite ``R_k`` had given
    the EKF, the adaptive KF and the time-varying KF a posterior covariance with negative
    eigenvalues and no error, while ``simulate`` refused the same model (a numerics
    trial). It costs an overriding model a host factorisation per read (about 20 µs); the
    others nothing."""
    cov = getattr(model, method)(k)
    varying = getattr(model, "_varying_noise", None)
    if varying is None or not varying(method):
        return cov
    name = f"{type(model).__name__}.{method}({k})"
    if not isinstance(cov, Tensor):
        raise TypeError(f"{name} must return a torch.Tensor; got {type(cov).__name__}")
    if cov.dim() < 2 or cov.shape[-1] != cov.shape[-2]:
        raise ValueError(f"{name} must return a square matrix [..., d, d]; got {tuple(cov.shape)}")
    if not under_transform(cov):  # (values a transform cannot read)
        check_covariance(cov, name, advice=f"return a covariance from {method}(k), e.g. L Lᵀ")
    return cov


def check_covariance(t: Tensor, name: str, *, advice: str) -> None:
    """``t [..., d, d]`` is a covariance: finite, symmetric (:func:`check_symmetric`) and
    positive semi-definite (:func:`check_semidefinite`, whose error ends with ``advice``)."""
    if not values_known(t):
        return
    if not _all_finite(t):
        raise ValueError(f"{name} contains NaN or Inf values; every entry must be finite")
    check_symmetric(t, name)
    check_semidefinite(t, name, advice=advice)


def check_semidefinite(t: Tensor, name: str, *, advice: str = _CARRY_ADVICE) -> None:
    """``t [..., d, d]`` (symmetric) has no clearly negative eigenvalue: its Cholesky
    factorisation succeeds after a jitter of ``√eps`` (of ``t``'s dtype) times its largest
    variance, so the round-off of a filter's own covariances passes and so does ``P = 0``
    (a known state). A hand-built indefinite carry covariance had stepped silently to a
    negative posterior variance and a finite log-likelihood (a new user's trial).
    Factorised by numpy on the host (a third of torch's time for a 4 × 4: a restored
    carry's first step and every step under ``full_checks`` pay it; another device's
    covariance is read to the host once)."""
    if t.numel() == 0 or not values_known(t):
        return
    a = host_array(t)
    scale = np.abs(np.diagonal(a, axis1=-2, axis2=-1)).max(-1)
    jitter = scale * math.sqrt(torch.finfo(t.dtype).eps) + torch.finfo(t.dtype).tiny
    try:
        np.linalg.cholesky(a + jitter[..., None, None] * np.eye(a.shape[-1], dtype=a.dtype))
        return
    except np.linalg.LinAlgError:
        pass
    eig = np.linalg.eigvalsh(a.reshape(-1, *a.shape[-2:]))  # the failure's message alone
    first = int(np.argmin(eig[:, 0] / np.maximum(eig[:, -1], np.finfo(a.dtype).tiny)))
    where = "" if a.ndim == 2 else " (of a run)"
    raise ValueError(
        f"{name} must be a covariance, positive semi-definite; its eigenvalues{where} run "
        f"from {float(eig[first, 0]):.3g} to {float(eig[first, -1]):.3g}: {advice}"
    )
