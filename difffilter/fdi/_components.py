"""Small-matrix algebra on component lists: the fast path of the batched local estimators.

A ``d × e`` matrix over a batch is a list of ``d`` lists of ``e`` tensors ``[...]`` (one
tensor per entry, the batch contiguous). On CPU a batched ``matmul`` of tiny matrices
costs ~100 ns per matrix (20,000 particles: ~2 ms per product), whereas one elementwise
operation on 20,000 numbers costs ~6 µs: writing the products, Cholesky factors and
inverses entry by entry is 5–10× faster for ``d ≤ 6``. Entries may be tensors or Python
numbers (constant matrices such as ``Q⁻¹``, the constant entries of a Jacobian).

What the time goes to here is the number of elementwise kernels, so every helper counts
them: a term with a zero factor is skipped, a factor 1 costs nothing, products of numbers
are folded, and a sum is accumulated in place (``addcmul_``) into the tensor its first
term allocated (never into an input, so autograd sees no in-place change of a saved
tensor). Symmetric results are computed once per entry pair: ``out[j][i] is out[i][j]``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .._checks import broadcast_shapes

__all__ = [
    "to_components",
    "from_components",
    "lin",
    "mm",
    "mv",
    "mt",
    "add",
    "gram",
    "cholesky",
    "spd_inverse",
    "cofactors",
    "sym_inverse",
]


def to_components(t: Tensor) -> list[list[Tensor]]:
    """``[..., d, e]`` → ``d × e`` lists of contiguous ``[...]`` tensors."""
    c = t.movedim(-1, 0).movedim(-1, 0).contiguous()  # [d, e, ...]
    return [list(row.unbind(0)) for row in c.unbind(0)]


def from_components(m) -> Tensor:
    """``d × e`` lists of ``[...]`` tensors → ``[..., d, e]``."""
    return torch.stack([torch.stack(row, -1) for row in m], -2)


def _fits(acc: Tensor, t: Tensor) -> bool:
    """Whether ``acc`` can take ``t`` in place (``t`` broadcasts to ``acc``'s shape)."""
    return t.shape == acc.shape or broadcast_shapes(acc.shape, t.shape) == acc.shape


def lin(terms):
    """``Σ c·a·b`` over ``terms`` of ``(c, a, b)``: ``c`` a Python number, ``a``, ``b``
    tensors ``[...]`` (broadcasting) or numbers. Returns a tensor, or a number when no
    term has a tensor. One kernel per tensor term at most (module docstring)."""
    const, acc, owned = 0.0, None, False
    tensor_terms = []
    for c, a, b in terms:
        if not isinstance(a, Tensor):
            c, a = c * a, None
        if not isinstance(b, Tensor):
            c, b = c * b, None
        if c == 0:
            continue
        if a is None and b is None:
            const += c
        else:
            tensor_terms.append((c, a, b))
    # a product with coefficient 1 first: it starts the sum in one kernel
    tensor_terms.sort(key=lambda t: not (t[0] == 1 and t[1] is not None and t[2] is not None))
    for c, a, b in tensor_terms:
        if a is None or b is None:  # c·t
            t = a if b is None else b
            if acc is None:
                acc, owned = (t, False) if c == 1 else (t * c, True)
            elif owned and _fits(acc, t):
                acc.add_(t, alpha=c)
            else:
                acc, owned = torch.add(acc, t, alpha=c), True
        elif acc is None:
            acc, owned = (a * b if c == 1 else (a * b).mul_(c)), True
        elif owned and _fits(acc, a) and _fits(acc, b):
            acc.addcmul_(a, b, value=c)
        else:
            acc, owned = torch.addcmul(acc, a, b, value=c), True
    if acc is None:
        return const
    if const != 0:
        acc = acc.add_(const) if owned else acc + const
    return acc


def _dot(pairs):
    """``Σ a·b`` over ``pairs`` (:func:`lin` with coefficients 1)."""
    return lin((1.0, a, b) for a, b in pairs)


def mm(a, b, upper: bool = False):
    """``A B`` for component matrices ``d × k`` and ``k × e``; ``upper``: only the entries
    ``j ≥ i`` (a product known to be symmetric whose lower triangle nobody reads: ``None``)."""
    k = len(b)
    return [[_dot((row[i], b[i][j]) for i in range(k)) if not upper or j >= r else None
             for j in range(len(b[0]))] for r, row in enumerate(a)]  # fmt: skip


def mv(a, v):
    """``A v`` for a component matrix ``d × k`` and a component vector ``k``."""
    return [_dot(zip(row, v)) for row in a]


def mt(a):
    """``Aᵀ``."""
    return [list(col) for col in zip(*a)]


def add(a, b, alpha: float = 1.0):
    """``A + α B`` (entries may be numbers or ``None``, the unread lower triangle of an
    ``upper`` product; a zero entry costs nothing)."""
    return [[None if x is None or y is None else lin(((1.0, x, 1.0), (alpha, y, 1.0)))
             for x, y in zip(ra, rb)] for ra, rb in zip(a, b)]  # fmt: skip


def gram(h, weights, base):
    """``base + Hᵀ diag(w) H`` (upper triangle) for ``h`` ``m × d``, ``weights`` ``m``
    numbers or tensors, ``base`` ``d × d``: ``Σᵢ wᵢ Hᵢⱼ Hᵢₗ`` one kernel per term."""
    d = len(h[0])
    out = [[None] * d for _ in range(d)]
    for j in range(d):
        for m in range(j, d):
            terms = [(1.0, base[j][m], 1.0)]
            for i, w in enumerate(weights):
                if isinstance(w, Tensor):  # a masked weight [..., 1]: w·H first, then the product
                    terms.append((1.0, h[i][j], lin(((1.0, h[i][m], w),))))
                else:
                    terms.append((w, h[i][j], h[i][m]))
            out[j][m] = lin(terms)
    return out


def cholesky(a):
    """Lower Cholesky factor of a symmetric positive-definite component matrix (no pivoting;
    diagonals clamped at the dtype's smallest normal number before the square root, so a
    semidefinite input gives a finite factor). Only the upper triangle of ``a`` is read
    (``A_ij`` as ``a[j][i]`` for ``i > j``): the products of :func:`gram` and
    :func:`mm` with ``upper=True`` leave the lower one ``None``::

        L_jj = √(A_jj − Σ_{k<j} L_jk²),   L_ij = (A_ji − Σ_{k<j} L_ik L_jk) / L_jj  (i > j)
    """
    d = len(a)
    low = [[0.0] * d for _ in range(d)]
    for j in range(d):
        s = lin([(1.0, a[j][j], 1.0)] + [(-1.0, low[j][k], low[j][k]) for k in range(j)])
        if not isinstance(s, Tensor):
            s = _number_as_tensor(s, a)
        low[j][j] = torch.sqrt(torch.clamp_min(s, torch.finfo(s.dtype).tiny))
        for i in range(j + 1, d):
            num = lin([(1.0, a[j][i], 1.0)] + [(-1.0, low[i][k], low[j][k]) for k in range(j)])
            low[i][j] = num / low[j][j]
    return low


def spd_inverse(a):
    """``(A⁻¹, log det A)`` of a symmetric positive-definite component matrix, via its
    Cholesky factor ``L``: ``A⁻¹ = L⁻ᵀ L⁻¹``, ``log det A = 2 Σ log Lᵢᵢ``."""
    d = len(a)
    low = cholesky(a)
    inv = [[0.0] * d for _ in range(d)]  # L⁻¹, lower triangular
    for i in range(d):
        inv[i][i] = 1.0 / low[i][i]
        for j in range(i):
            inv[i][j] = -_dot((low[i][k], inv[k][j]) for k in range(j, i)) / low[i][i]
    out = [[None] * d for _ in range(d)]
    for i in range(d):
        for j in range(i, d):
            out[i][j] = out[j][i] = _dot((inv[k][i], inv[k][j]) for k in range(j, d))
    logdet = 2.0 * sum(torch.log(low[i][i]) for i in range(d))
    return out, logdet


def cofactors(a):
    """``(C, det A)`` of a symmetric component matrix ``d ≤ 3`` (upper triangle read): the
    cofactors ``C`` (upper triangle; ``A⁻¹ = C / det A``, ``tr A⁻¹ = Σ C_ii / det A``) and the
    determinant. For ``d = 2`` the off-diagonal entry is stored as ``a₀₁``, the cofactor's
    negative (the caller folds the sign into its next product: no negation kernel)::

        d = 2:  C = [[a₁₁, (−)a₀₁], [·, a₀₀]],  det = a₀₀a₁₁ − a₀₁²
        d = 3:  C_ij = the (i, j) minor with sign (−1)^(i+j),  det = a₀₀C₀₀ + a₀₁C₀₁ + a₀₂C₀₂
    """
    d = len(a)
    if d == 1:
        return [[1.0]], a[0][0]
    if d == 2:
        det = lin(((1.0, a[0][0], a[1][1]), (-1.0, a[0][1], a[0][1])))
        return [[a[1][1], a[0][1]], [None, a[0][0]]], det
    if d != 3:
        raise ValueError(f"cofactors takes d <= 3; got d = {d}")
    c00 = lin(((1.0, a[1][1], a[2][2]), (-1.0, a[1][2], a[1][2])))
    c01 = lin(((1.0, a[0][2], a[1][2]), (-1.0, a[0][1], a[2][2])))
    c02 = lin(((1.0, a[0][1], a[1][2]), (-1.0, a[1][1], a[0][2])))
    c11 = lin(((1.0, a[0][0], a[2][2]), (-1.0, a[0][2], a[0][2])))
    c12 = lin(((1.0, a[0][1], a[0][2]), (-1.0, a[0][0], a[1][2])))
    c22 = lin(((1.0, a[0][0], a[1][1]), (-1.0, a[0][1], a[0][1])))
    det = lin(((1.0, a[0][0], c00), (1.0, a[0][1], c01), (1.0, a[0][2], c02)))
    return [[c00, c01, c02], [None, c11, c12], [None, None, c22]], det


def sym_inverse(a, logdet: bool = False):
    """``(A⁻¹, log det A or None)`` of a symmetric positive-definite component matrix.

    ``d ≤ 3`` by the adjugate, ``A⁻¹ = adj(A) / det A`` (``d = 2``:
    ``[[a₁₁, −a₀₁], [−a₀₁, a₀₀]] / (a₀₀a₁₁ − a₀₁²)``; ``d = 3``: the six
    :func:`cofactors`), about half the kernels of the Cholesky route
    and no square roots; larger ``d`` by :func:`spd_inverse`. Only the upper triangle of
    ``a`` is read. The log-determinant (one ``log``) only when asked for.
    """
    d = len(a)
    if d > 3:
        out, ld = spd_inverse(a)
        return out, (ld if logdet else None)
    cof, det = cofactors(a)
    inv_det = torch.reciprocal(det) if isinstance(det, Tensor) else 1.0 / det
    out = [[None] * d for _ in range(d)]
    for i in range(d):
        for j in range(i, d):
            sign = -1.0 if (d == 2 and i != j) else 1.0
            out[i][j] = out[j][i] = lin(((sign, cof[i][j], inv_det),))
    ld = None
    if logdet:
        ld = torch.log(det) if isinstance(det, Tensor) else torch.log(_number_as_tensor(det, a))
    return out, ld


def _number_as_tensor(value: float, a) -> Tensor:
    """A number entry as a tensor of the dtype and device of ``a``'s tensor entries (float64
    where it has none): ``torch.as_tensor`` made float32, the default dtype, and a float64
    matrix with a constant leading diagonal entry came out 1e-7 off (a review)."""
    entry = next((e for row in a for e in row if isinstance(e, Tensor)), None)
    if entry is None:
        return torch.tensor(value, dtype=torch.float64)
    return torch.tensor(value, dtype=entry.dtype, device=entry.device)
