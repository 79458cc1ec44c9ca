"""Input validation that names the offending argument and says what was expected."""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = [
    "as_tensor",
    "check_vector_last",
    "check_square",
    "check_positive_definite",
    "check_finite",
    "check_sequence",
    "check_mask",
    "check_positive_int",
]


def as_tensor(value, name: str, *, dtype=None, device=None) -> Tensor:
    """Convert ``value`` to a floating tensor, keeping autograd history of tensors."""
    if isinstance(value, Tensor):
        if not value.is_floating_point():
            value = value.to(dtype or torch.get_default_dtype())
        elif dtype is not None and value.dtype != dtype:
            value = value.to(dtype)
        if device is not None:
            value = value.to(device)
        return value
    if isinstance(value, (list, tuple)) and value and all(isinstance(v, Tensor) for v in value):
        return torch.stack([as_tensor(v, name, dtype=dtype, device=device) for v in value])
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


def check_finite(t: Tensor, name: str) -> None:
    if not bool(torch.isfinite(t).all()):
        raise ValueError(f"{name} contains NaN or Inf values; every entry must be finite")


def check_positive_definite(t: Tensor, name: str, dim: int | None = None) -> None:
    """``t`` must be a finite, symmetric, positive-definite ``[..., d, d]`` matrix."""
    check_square(t, name, dim)
    check_finite(t, name)
    scale = t.detach().abs().amax(dim=(-1, -2), keepdim=True).clamp_min(1e-30)
    asym = (t.detach() - t.detach().transpose(-1, -2)).abs() / scale
    if bool((asym > 1e-6).any()):
        raise ValueError(
            f"{name} must be symmetric; max relative asymmetry {float(asym.max()):.3g}"
        )
    _, info = torch.linalg.cholesky_ex(t.detach())
    if bool((info != 0).any()):
        raise ValueError(f"{name} must be positive definite (all eigenvalues > 0)")


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


def check_mask(mask: Tensor, name: str, shape: torch.Size) -> Tensor:
    """``mask`` must be boolean (or 0/1) and broadcast to ``shape``; returns it as bool."""
    if not isinstance(mask, Tensor):
        mask = torch.as_tensor(mask)
    if mask.dtype != torch.bool:
        if not bool(((mask == 0) | (mask == 1)).all()):
            raise ValueError(f"{name} must be boolean (True = entry received)")
        mask = mask.bool()
    try:
        torch.broadcast_shapes(mask.shape, shape)
    except RuntimeError as exc:
        raise ValueError(
            f"{name} must broadcast to {tuple(shape)}; got {tuple(mask.shape)}"
        ) from exc
    return mask


def check_positive_int(value, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"{name} must be a positive integer (>= 1); got {value!r}")
    return value
