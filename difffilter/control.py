"""Controller and observer gains for linear plants: LQR (CARE; DARE for discrete-time
plants), the steady-state Kalman gain and Luenberger designs.

The closed loop of :mod:`difffilter.loop` puts a controller after the estimator; these
are the gains of the linear ones (the LFC secure controller ``U = −K₁(Z − M̂)``, the
Luenberger observer :class:`~difffilter.observers.FixedGainFilter`).

LQR (the paper's eqs 15–16): ``K₁ = R⁻¹BᵀP`` with ``PA + AᵀP + Q − PBR⁻¹BᵀP = 0``. The
continuous algebraic Riccati equation (CARE) has a stabilising solution only for a
stabilisable ``(A, B)``. The two-area LFC model is not: ``wᵀA = 0`` and ``wᵀB = 0`` for
``w = e₄ + e₉`` (the sum of the tie-line flows is conserved), an uncontrollable eigenvalue
at exactly 0. Two remedies (docs/scenarios.md, LFC):

* ``LQRMethod.REDUCED`` (default): restrict to the controllable subspace ``{x : wᵀx = 0}``,
  solve the CARE exactly on its 9 coordinates and apply the gain to the orthogonal
  projection of the state onto that subspace, so ``K₁ w = 0``: the controller ignores the
  uncontrollable direction instead of fighting it.
* ``LQRMethod.SHIFT``: solve the CARE for ``A − εI`` (every mode, the uncontrollable one
  included, becomes stable), which feeds the tie-line sum back with a gain of order one.

Observers: with ``C = I`` a Luenberger gain that places the error poles is
underdetermined (100 free entries for 10 poles). :func:`luenberger_gain` implements three
designs with the same poles; the LFC report shows how much the baseline depends on the
choice (docs/scenarios.md, LFC pitfalls).
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla
import torch
from torch import Tensor

from ._checks import Choice, check_finite_number

__all__ = [
    "zoh_discretize",
    "controllability_rank",
    "care_residual",
    "lqr",
    "dlqr",
    "dare_residual",
    "kalman_steady_state",
    "uncontrollable_direction",
    "observer_poles",
    "luenberger_gain",
    "LuenbergerDesign",
    "LQRMethod",
]


def _np(t: Tensor) -> np.ndarray:
    # (a view of torch's negative bit, `z.conj().imag`, resolved: numpy reads none)
    return t.detach().cpu().to(torch.float64).resolve_neg().numpy()


def _riccati(
    solve, A: np.ndarray, B: np.ndarray, Q: np.ndarray, R: np.ndarray, *, filtering: bool = False
) -> np.ndarray:
    """scipy's Riccati solver ``solve(A, B, Q, R)``, its failure a ``ValueError`` that says
    what the equation needs (scipy's "Failed to find a finite solution" or "symplectic
    pencil" named neither the pair nor the condition)."""
    try:
        return solve(A, B, Q, R)
    except (np.linalg.LinAlgError, ValueError) as error:
        raise ValueError(
            f"the Riccati equation has no stabilising solution here: it needs "
            f"{_need(filtering)} (scipy: {error})"
        ) from error


#: The largest Riccati residual, relative to the equation's terms, of a solution scipy
#: returns: its solutions of solvable equations reach about 1e-12; a pair that cannot be
#: stabilised, in coordinates where scipy does not see it, had come back with 0.44 (an
#: uncontrollable Jordan block at 1.2: the closed loop still at 1.2) or 2.09 (a trial).
RICCATI_RESIDUAL_TOLERANCE = 1e-6


def _check_riccati_solution(residual: np.ndarray, terms: tuple, *, filtering: bool = False) -> None:
    """``ValueError`` (as :func:`_riccati`'s) where ``‖residual‖`` exceeds
    :data:`RICCATI_RESIDUAL_TOLERANCE` times the largest of the equation's ``terms``."""
    scale = max(max(float(np.linalg.norm(t)) for t in terms), np.finfo(np.float64).tiny)
    relative = float(np.linalg.norm(residual)) / scale
    if not relative <= RICCATI_RESIDUAL_TOLERANCE:
        raise ValueError(
            f"the Riccati equation has no stabilising solution here: it needs {_need(filtering)} "
            f"(scipy returned a solution whose residual is {relative:.3g} of the equation's "
            "terms)"
        )


def _need(filtering: bool) -> str:
    """What a Riccati equation of :func:`_riccati` needs to have a stabilising solution."""
    if filtering:
        return ("(F, H) detectable and (F, Q^{1/2}) stabilisable: every unstable or marginal "
                "mode seen by the measurements, and excited by the process noise (scipy "
                "finds no solution for a measured constant state with Q = 0 on it: give it "
                "some)")  # fmt: skip
    return ("the pair stabilisable and (A, Q^{1/2}) detectable: every unstable or marginal "
            "mode reachable by the inputs and seen by the state weight")  # fmt: skip


def care_residual(A: Tensor, B: Tensor, Q: Tensor, R: Tensor, P: Tensor) -> Tensor:
    """``PA + AᵀP + Q − PBR⁻¹BᵀP`` (zero at a CARE solution) → ``[n, n]``."""
    _check_riccati_terms(A, B, Q, R, P, ("A", "B"))
    return P @ A + A.T @ P + Q - P @ B @ torch.linalg.solve(R, B.T @ P)


def _check_riccati_terms(F: Tensor, B: Tensor, Q: Tensor, R: Tensor, P: Tensor,
                         names: tuple[str, str]) -> None:  # fmt: skip
    """The arguments of :func:`care_residual` / :func:`dare_residual`: ``F [n, n]`` and
    ``B [n, m]`` as :func:`_check_pair` takes them, ``Q``, ``P`` ``[n, n]`` and ``R [m, m]`` of
    their dtype (a batch ``[b, n, n]`` had been transposed whole by ``.T``: residuals 3.3
    for 1e-7, a trial; another dtype or a numpy array failed inside torch)."""
    n, m = _check_pair(F, B, names)
    for name, t, shape in (("Q", Q, (n, n)), ("R", R, (m, m)), ("P", P, (n, n))):
        if not isinstance(t, Tensor) or t.dtype != F.dtype or tuple(t.shape) != shape:
            got = f"{t.dtype} {tuple(t.shape)}" if isinstance(t, Tensor) else type(t).__name__
            raise ValueError(f"{name} must be a {F.dtype} tensor of shape {list(shape)}; got {got}")


def uncontrollable_direction(A: Tensor, B: Tensor, tol: float = 1e-9) -> Tensor | None:
    """Unit left null vector ``w`` with ``wᵀ[A, B] = 0``, or ``None`` if there is none.

    Shapes ``A [n, n]``, ``B [n, m]`` → ``[n]``. Such a ``w`` spans an uncontrollable mode at
    eigenvalue 0 (the case of the LFC tie-line sum).
    """
    # (a NaN tol had called every pair uncontrollable: no comparison with NaN holds)
    tol = check_finite_number(tol, "tol", nonnegative=True)
    _check_pair(A, B, ("A", "B"))  # (a non-square A had returned None)
    M = _np(torch.cat([A, B], dim=1))
    _, s, vh = np.linalg.svd(M.T)
    # relative to the pair's own scale (a floor of 1 had called a controllable plant of
    # entries 1e-9 uncontrollable, and lqr solved a sub-problem of it: a trial)
    if s[-1] > tol * s[0]:
        return None
    w = vh[-1]
    w = w / np.linalg.norm(w)
    # Fix the sign so that the direction is reproducible (largest entry positive).
    w = w * np.sign(w[np.argmax(np.abs(w))])
    return torch.as_tensor(w, dtype=A.dtype, device=A.device)


class LQRMethod(Choice):
    """How :func:`lqr` treats an uncontrollable zero mode (module docstring); ``DIRECT`` is
    the plain CARE."""

    REDUCED = "reduced"
    SHIFT = "shift"
    DIRECT = "direct"


def lqr(
    A: Tensor,
    B: Tensor,
    Q: Tensor | None = None,
    R: Tensor | None = None,
    *,
    method: LQRMethod | str = LQRMethod.REDUCED,
    shift: float = 1e-3,
) -> tuple[Tensor, Tensor]:
    """Continuous-time LQR gain ``K₁ [m, n]`` and Riccati solution ``P [n, n]``.

    Args:
        A, B: ``[n, n]``, ``[n, m]`` continuous-time plant.
        Q, R: state and input weights (default ``I``; [DEF] for the LFC, the paper gives none).
        method: :class:`LQRMethod`: ``REDUCED`` (exact CARE on the controllable subspace
            when there is an uncontrollable zero mode; plain CARE otherwise), ``SHIFT``
            (CARE on ``A − shift·I``) or ``DIRECT`` (plain CARE; fails for the LFC model).
        shift: the ``ε`` of ``SHIFT``.

    For ``REDUCED`` the returned ``P`` is the reduced solution lifted back,
    ``P = Tᵀ P_r T`` with ``T`` the coordinate map of the projection, so it satisfies the
    CARE on the controllable subspace (``Vᵀ·care_residual·V = 0`` for its basis ``V``).
    """
    n, m = _check_pair(A, B, ("A", "B"))
    Q, R = _weights(Q, R, n, m, A)
    method = LQRMethod(method)
    if method is LQRMethod.SHIFT:
        shift = check_finite_number(shift, "shift", positive=True)
    w = uncontrollable_direction(A, B) if method is LQRMethod.REDUCED else None
    if method is LQRMethod.DIRECT or (method is LQRMethod.REDUCED and w is None):
        An, Bn, Qn, Rn = _np(A), _np(B), _np(Q), _np(R)
        P = _riccati(sla.solve_continuous_are, An, Bn, Qn, Rn)
        PB = P @ Bn
        _check_riccati_solution(P @ An + An.T @ P + Qn - PB @ np.linalg.solve(Rn, PB.T),
                                (P @ An, Qn, PB @ np.linalg.solve(Rn, PB.T)))  # fmt: skip
    elif method is LQRMethod.SHIFT:
        P = _riccati(sla.solve_continuous_are, _np(A) - shift * np.eye(n), _np(B), _np(Q),
                     _np(R))  # fmt: skip
    else:
        # Controllable subspace S = w⊥. Drop the coordinate where |w| is largest; on S it is
        # a linear function of the others, x_j = −Σ_{i≠j} w_i x_i / w_j.
        wn = _np(w)
        j = int(np.argmax(np.abs(wn)))
        keep = [i for i in range(n) if i != j]
        # Lift L: reduced coordinates r → full state on S, x = L r.
        L = np.zeros((n, n - 1))
        L[keep, np.arange(n - 1)] = 1.0
        L[j, :] = -wn[keep] / wn[j]
        # Projection coordinates T: x → r of the orthogonal projection onto S.
        proj = np.eye(n) - np.outer(wn, wn)
        T = proj[keep, :]
        An, Bn, Qn = _np(A), _np(B), _np(Q)
        Ar, Br = T @ An @ L, T @ Bn
        Qr = L.T @ Qn @ L  # x ∈ S ⇒ xᵀQx = rᵀ(LᵀQL)r
        Pr = _riccati(sla.solve_continuous_are, Ar, Br, Qr, _np(R))
        P = T.T @ Pr @ T
    P = torch.as_tensor(0.5 * (P + P.T), dtype=A.dtype, device=A.device)
    # detached, as dlqr's: a gradient through this product alone would hold P fixed
    K = torch.linalg.solve(R.detach(), B.detach().T @ P)
    return K, P


def _observer_spectrum(A_closed: Tensor, factor: float, zero_pole: float | None):
    """Eigen-decomposition of ``A − BK₁`` with eigenvalues scaled by ``factor``.

    Returns ``(λ_obs [n] complex, V [n, n] complex, moved [n] bool)`` (``moved``: the zero
    eigenvalues, moved as below). The closed loop of the LFC keeps the
    uncontrollable eigenvalue at 0, which "``factor`` times faster" leaves at 0 (a discrete
    pole at 1: that observer error would never decay). [DEF] it is moved to ``zero_pole``
    (default: the slowest of the other scaled eigenvalues).
    """
    factor, zero_pole = _check_observer_design(factor, zero_pole)
    if (not isinstance(A_closed, Tensor) or not A_closed.is_floating_point()
            or A_closed.dim() != 2 or A_closed.shape[0] != A_closed.shape[1]):  # fmt: skip
        # (a batch [b, n, n] had moved each member's zero modes by the whole batch's
        # eigenvalues: poles 0.86 for 0.74, an apishapes trial)
        got = tuple(A_closed.shape) if isinstance(A_closed, Tensor) else type(A_closed).__name__
        raise ValueError(f"A_closed must be a square [n, n] floating tensor; got {got}")
    _check_finite_matrix(A_closed, "A_closed")
    lam, V = np.linalg.eig(_np(A_closed))
    lam = factor * lam
    # zero relative to the spectrum's own scale (an absolute 1e-8 had taken every pole of a
    # plant in slow units for a zero mode, and missed the zero of one in fast units: a trial)
    tiny = np.abs(lam) <= 1e-8 * np.abs(lam).max()
    if tiny.all() and zero_pole is None:  # (numpy's "zero-size array" had said nothing)
        raise ValueError(
            "every eigenvalue of A_closed is zero: no other pole to move the zero "
            "ones to; give zero_pole (a continuous-time eigenvalue < 0)"
        )
    if tiny.any():
        target = lam[~tiny].real.max() if zero_pole is None else float(zero_pole)
        lam = np.where(tiny, target, lam)
    # the zero modes are moved because their error would never decay; an undamped pair
    # (±iω) or an unstable mode is as bad, and had given poles on or outside the unit
    # circle without a word (an observers trial)
    slow = ~tiny & (lam.real >= -1e-12 * np.abs(lam).max())
    if slow.any():
        raise ValueError(
            "A_closed must be stable but for zero eigenvalues (A − BK₁ of a stabilising "
            "controller): its eigenvalues "
            f"{np.array2string(lam[slow] / factor, precision=4)} have real part ≥ 0, and the "
            "observer error along them would never decay (poles exp(factor·λ·dt) on or outside "
            "the unit circle)"
        )
    return lam, V, tiny


def _check_observer_design(factor, zero_pole) -> tuple[float, float | None]:
    """``(factor, zero_pole)`` as numbers (a one-element tensor as its number): ``factor``
    finite and > 0, ``zero_pole`` ``None`` or finite and < 0 (a continuous-time eigenvalue:
    at 0 or above, that observer error would never decay). A NaN or negative factor had
    given NaN or slower poles without a word, and 0 a raw numpy error (a fuzzing trial)."""
    factor = check_finite_number(factor, "factor", positive=True)
    if zero_pole is not None and check_finite_number(zero_pole, "zero_pole") >= 0:
        raise ValueError(
            "zero_pole must be None or a finite number < 0 (a continuous-time eigenvalue: the "
            f"observer error along the zero mode decays as exp(zero_pole·t)); got {zero_pole!r}"
        )
    return factor, None if zero_pole is None else float(zero_pole)


def observer_poles(
    A_closed: Tensor, dt: float, factor: float = 3.0, zero_pole: float | None = None
) -> Tensor:
    """Discrete observer poles ``exp(factor·λᵢ·dt)`` for the eigenvalues ``λᵢ`` of ``A − BK₁``.

    See :func:`_observer_spectrum` for the zero eigenvalue. Returns a complex tensor ``[n]``.
    """
    dt = check_finite_number(dt, "dt", positive=True)
    lam, _, _ = _observer_spectrum(A_closed, factor, zero_pole)
    return torch.as_tensor(np.exp(lam * dt))


class LuenbergerDesign(Choice):
    """How :func:`luenberger_gain` chooses the eigenvectors of ``Φ`` (its docstring)."""

    MODAL = "modal"
    ROBUST = "robust"
    DIAGONAL = "diagonal"


def luenberger_gain(
    Ad: Tensor,
    A_closed: Tensor,
    dt: float,
    *,
    design: LuenbergerDesign | str = LuenbergerDesign.MODAL,
    factor: float = 3.0,
    zero_pole: float | None = None,
) -> Tensor:
    """Filter-form gain ``L_f`` for ``x̂_k = x̂⁻_k + L_f (z_k − M̂_k − x̂⁻_k)`` with ``C = I``.

    The a-priori error obeys ``ẽ⁻_{k+1} = A_d (I − L_f) ẽ⁻_k``, so ``L_f = A_d⁻¹ L_p`` where
    the predictor gain ``L_p`` places the eigenvalues of ``Φ = A_d − L_p`` at
    ``exp(factor·λᵢ(A − BK₁)·dt)`` ("observer poles three times faster than the closed
    loop"). With ``C = I`` every ``Φ`` with those eigenvalues is admissible; the designs
    choose its eigenvectors:

    * ``MODAL``: ``Φ = V diag(exp(factor λ dt)) V⁻¹`` with ``V`` the eigenvectors of
      ``A − BK₁`` (i.e. ``Φ = exp(factor (A − BK₁) dt)`` up to the moved zero pole): the
      error modes are the closed-loop modes, ``factor`` times faster.
    * ``ROBUST``: ``scipy.signal.place_poles`` (Tits–Yang), the best-conditioned
      eigenvectors — ``Φ`` close to a normal matrix.
    * ``DIAGONAL``: ``Φ`` block diagonal in the coordinate axes (a real 2×2 block per
      complex pair): every channel's error decays on its own.

    Shapes: ``Ad [n, n]``, ``A_closed [n, n]`` → ``L_f [n, n]``.
    """
    if (
        not isinstance(Ad, Tensor)
        or not Ad.is_floating_point()
        or Ad.dim() != 2
        or (Ad.shape[0] != Ad.shape[1])
    ):  # (a numpy array had failed on .shape's use, a non-square one in a broadcast)
        got = tuple(Ad.shape) if isinstance(Ad, Tensor) else type(Ad).__name__
        raise ValueError(f"Ad must be a square [n, n] floating tensor; got {got}")
    _check_finite_matrix(Ad, "Ad")
    n = Ad.shape[0]
    if not isinstance(A_closed, Tensor) or A_closed.shape != (n, n):
        raise ValueError(f"A_closed must have shape [{n}, {n}]; got {tuple(A_closed.shape)}")
    dt = check_finite_number(dt, "dt", positive=True)
    design = LuenbergerDesign(design)
    lam, V, moved = _observer_spectrum(A_closed, factor, zero_pole)
    p = np.exp(lam * dt)
    if design is LuenbergerDesign.MODAL:
        Phi = _modal_transition(_np(A_closed), V, p, moved, factor * dt)
    elif design is LuenbergerDesign.ROBUST:
        import scipy.signal as ssig  # here: importing it costs 0.7 s that --list need not pay

        res = ssig.place_poles(_np(Ad).T, np.eye(n), p, method="YT", maxiter=100)
        Phi = _np(Ad) - res.gain_matrix.T
    else:
        Phi = np.zeros((n, n))
        real = sorted(p[np.abs(p.imag) < 1e-12].real)
        upper = sorted(p[p.imag >= 1e-12], key=lambda z: z.real)
        i = 0
        for r in real:
            Phi[i, i] = r
            i += 1
        for z in upper:  # each complex pair as [[a, b], [-b, a]]
            Phi[i : i + 2, i : i + 2] = [[z.real, z.imag], [-z.imag, z.real]]
            i += 2
    Lp = _np(Ad) - Phi
    try:
        gain = np.linalg.solve(_np(Ad), Lp)
    except np.linalg.LinAlgError:  # (numpy's bare "Singular matrix": an observers trial)
        raise ValueError(
            "Ad must be invertible: the filter-form gain is L_f = Ad⁻¹ L_p, and with a "
            "singular Ad the error dynamics Ad (I − L_f) keep a pole at 0 whatever L_f is"
        ) from None
    return torch.as_tensor(gain, dtype=Ad.dtype, device=Ad.device)


def _modal_transition(A_closed: np.ndarray, V: np.ndarray, p: np.ndarray, moved: np.ndarray,
                      scale: float) -> np.ndarray:  # fmt: skip
    """``Φ = V diag(p) V⁻¹`` (``p`` the poles of :func:`_observer_spectrum`'s eigenvalues
    and ``V`` its vectors, ``moved`` its zero eigenvalues; ``scale = factor·dt``), i.e.
    ``exp(scale·A_closed)`` with each zero eigenvalue's pole moved. Where ``V`` is (nearly)
    singular, a closed loop with a repeated, defective eigenvalue (a critically damped
    design), ``V⁻¹`` is noise (the poles came out 0.29 and 0.49 for 0.55 twice, or
    unstable: a trial): ``Φ = expm(scale·A_closed) + (p₀ − 1) Π₀`` instead, ``Π₀`` the
    spectral projector onto the zero eigenvalue's null space (``V_r (V_lᵀ V_r)⁻¹ V_lᵀ``)."""
    if np.linalg.cond(V) < 1e8:  # (the LFC's: 751)
        return (V @ np.diag(p) @ np.linalg.inv(V)).real
    Phi = sla.expm(scale * A_closed)
    if moved.any():
        zero = int(moved.sum())
        _, sv, vh = np.linalg.svd(A_closed)
        _, _, uh = np.linalg.svd(A_closed.T)
        right, left = vh[-zero:].T, uh[-zero:].T  # null spaces of A and Aᵀ
        overlap = left.T @ right
        if sv[-zero] > 1e-8 * max(sv[0], 1.0) or np.linalg.cond(overlap) > 1e8:
            raise ValueError(
                "A_closed has a defective zero eigenvalue (or a defective eigenvalue beside a "
                "zero one): the modal design cannot move its pole; use design='robust' or "
                "'diagonal'"
            )
        Phi = Phi + (p[moved][0].real - 1.0) * (right @ np.linalg.solve(overlap, left.T))
    return Phi


def _check_finite_matrix(t: Tensor, name: str) -> None:
    """A plant matrix holds no NaN or inf (NaN had come out of the discretisation and the
    observer gain without a word, and numpy's "SVD did not converge" out of the others: a
    trial of the control tools)."""
    if t.device.type != "meta" and not bool(torch.isfinite(t).all()):
        raise ValueError(f"{name} contains NaN or Inf values")


def _check_pair(F: Tensor, G: Tensor, names: tuple[str, str]) -> tuple[int, int]:
    """``F [n, n]`` and ``G [n, m]`` (two-dimensional, one floating dtype, finite, ``m ≥ 1``);
    returns ``(n, m)``."""
    a, b = names
    for name, t in ((a, F), (b, G)):
        if not isinstance(t, Tensor) or not t.is_floating_point() or t.dim() != 2:
            got = tuple(t.shape) if isinstance(t, Tensor) else type(t).__name__
            raise ValueError(f"{name} must be a two-dimensional floating tensor; got {got}")
        _check_finite_matrix(t, name)
    n, m = G.shape
    if m < 1:  # (lqr had failed inside scipy on "index -1 is out of bounds")
        raise ValueError(f"{b} must have at least one column; got shape {tuple(G.shape)}")
    if F.shape[0] == F.shape[1] != n:  # square: either may be the wrong one, so name both
        k = F.shape[0]
        raise ValueError(
            f"{a} {tuple(F.shape)} and {b} {tuple(G.shape)} do not match: {b} must have {k} "
            f"rows (one per state of {a}), or {a} must have shape [{n}, {n}]"
        )
    if F.shape != (n, n):
        raise ValueError(f"{a} must have shape [{n}, {n}] to match {b} [{n}, {m}]; got "
                         f"{tuple(F.shape)}")  # fmt: skip
    if F.dtype != G.dtype:  # (torch's "expected m1 and m2 to have the same dtype" otherwise)
        raise ValueError(f"{a} is {F.dtype} and {b} {G.dtype}: give them one dtype")
    return n, m


def check_weight_values(Q: np.ndarray, R: np.ndarray, names: tuple[str, str] = ("Q", "R")):
    """``Q`` and ``R`` (host arrays) finite and symmetric, ``Q`` positive semidefinite and
    ``R`` positive definite, else a ``ValueError`` naming the matrix: a Riccati equation of
    an indefinite ``Q`` had returned a "covariance" with a negative eigenvalue (-0.11) and
    an LQR gain of ``R = -1`` without a word (a trial of the analysis tools), and where
    scipy refused, its "symplectic pencil" named neither."""
    for name, a, least in ((names[0], Q, "semidefinite"), (names[1], R, "definite")):
        if a.size == 0:  # (no state or no input: named by the caller)
            continue
        if not np.isfinite(a).all():
            raise ValueError(f"{name} contains NaN or Inf values")
        if np.abs(a - a.T).max() > 1e-10 * max(np.abs(a).max(), 1e-300):
            raise ValueError(f"{name} must be symmetric")
        low = float(np.linalg.eigvalsh(a).min())
        floor = -1e-12 * max(np.abs(a).max(), 1e-300)
        if low < floor if least == "semidefinite" else low <= 0.0:
            raise ValueError(f"{name} must be positive {least}; its least eigenvalue is {low:.3g}")


def _weights(Q, R, n: int, m: int, like: Tensor) -> tuple[Tensor, Tensor]:
    """``Q [n, n]``, ``R [m, m]`` in ``like``'s dtype (``None``: ``I``), detached, their
    values checked (:func:`check_weight_values`)."""
    Q = torch.eye(n, dtype=like.dtype, device=like.device) if Q is None else Q
    R = torch.eye(m, dtype=like.dtype, device=like.device) if R is None else R
    for name, t, d in (("Q", Q, n), ("R", R, m)):
        if not isinstance(t, Tensor) or t.shape != (d, d):
            got = tuple(t.shape) if isinstance(t, Tensor) else type(t).__name__
            raise ValueError(f"{name} must have shape [{d}, {d}]; got {got}")
        if t.dtype != like.dtype or t.device != like.device:
            raise ValueError(f"{name} is {t.dtype} on {t.device} and the plant's matrices "
                             f"{like.dtype} on {like.device}: give them one dtype and device")  # fmt: skip
    check_weight_values(_np(Q.detach()), _np(R.detach()))
    return Q.detach(), R.detach()


def dare_residual(F: Tensor, B: Tensor, Q: Tensor, R: Tensor, P: Tensor) -> Tensor:
    """``FᵀPF − P + Q − FᵀPB (R + BᵀPB)⁻¹ BᵀPF`` (zero at a DARE solution) → ``[n, n]``."""
    _check_riccati_terms(F, B, Q, R, P, ("F", "B"))
    return F.T @ P @ F - P + Q - F.T @ P @ B @ torch.linalg.solve(R + B.T @ P @ B, B.T @ P @ F)


def _check_dare(P: np.ndarray, F: np.ndarray, B: np.ndarray, Q: np.ndarray, R: np.ndarray,
                *, filtering: bool = False) -> None:  # fmt: skip
    """:func:`_check_riccati_solution` of the DARE ``FᵀPF − P + Q − FᵀPB (R + BᵀPB)⁻¹ BᵀPF``."""
    FPF, PF = F.T @ P @ F, B.T @ P @ F
    correction = PF.T @ np.linalg.solve(R + B.T @ P @ B, PF)
    _check_riccati_solution(FPF - P + Q - correction, (FPF, P, Q, correction), filtering=filtering)


def dlqr(
    F: Tensor, B: Tensor, Q: Tensor | None = None, R: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """Discrete-time LQR: the gain ``K [m, n]`` of ``u_k = −K x_k`` minimising
    ``Σ_k x_kᵀ Q x_k + u_kᵀ R u_k`` on ``x_{k+1} = F x_k + B u_k``, and ``P [n, n]``:

        P = FᵀPF + Q − FᵀPB (R + BᵀPB)⁻¹ BᵀPF     (the DARE; scipy's solver)
        K = (R + BᵀPB)⁻¹ BᵀPF

    ``Q``, ``R`` default to ``I``. Needs ``(F, B)`` stabilisable (a ``ValueError`` otherwise: scipy's,
    or where scipy returns a solution anyway, its residual, checked against
    :data:`RICCATI_RESIDUAL_TOLERANCE`).
    A marginal mode (``|λ| = 1``) that ``Q`` does not weigh is left where it is: the
    cost-optimal gain spends nothing on a mode that costs nothing (``F = diag(1, 0.5)``,
    ``Q = diag(0, 1)``: the pole stays at 1), so weigh every mode to be stabilised. The
    gain of a state-feedback controller on the estimate (:class:`difffilter.loop.StateFeedback`); with :func:`kalman_steady_state`
    the LQG design. Not differentiable (computed in numpy): the results are detached, with
    no gradient (one through the products alone held ``P`` fixed and was wrong: 1.32 for
    23.9); for a gain tuned by gradient, make ``K`` a parameter and differentiate the loop.
    """
    n, m = _check_pair(F, B, ("F", "B"))
    Q, R = _weights(Q, R, n, m, F)
    F, B = F.detach(), B.detach()
    Fn, Bn, Qn, Rn = _np(F), _np(B), _np(Q), _np(R)
    P = _riccati(sla.solve_discrete_are, Fn, Bn, Qn, Rn)
    _check_dare(P, Fn, Bn, Qn, Rn)
    P = torch.as_tensor(0.5 * (P + P.T), dtype=F.dtype, device=F.device)
    K = torch.linalg.solve(R + B.T @ P @ B, B.T @ P @ F)
    return K, P


def kalman_steady_state(
    F: Tensor, H: Tensor, Q: Tensor, R: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """The Kalman filter's limit on ``x_{k+1} = F x_k + w``, ``y_k = H x_k + v``:
    ``(gain K [n, p], pred_cov P⁻ [n, n], cov P [n, n])`` with

        P⁻ = F P⁻ Fᵀ + Q − F P⁻ Hᵀ (H P⁻ Hᵀ + R)⁻¹ H P⁻ Fᵀ     (the filtering DARE)
        K  = P⁻ Hᵀ (H P⁻ Hᵀ + R)⁻¹,   P = (I − K H) P⁻

    the gain and covariances :func:`difffilter.kalman_filter` converges to (tested), e.g.
    the fixed gain of :class:`difffilter.observers.FixedGainFilter` or of an LQG design.
    Needs ``(F, H)`` detectable (refused otherwise, :func:`_check_detectable`); a
    marginal mode the process noise does not excite (``Q = 0`` on an undisturbed rotation)
    has the limit ``P⁻ = 0`` and gain 0 along it, as the filter's variance decays to 0 there
    (slowly, as 1/k: not a stabilising gain). Computed in numpy: detached, no gradient (as
    :func:`dlqr`).
    """
    n, p = _check_pair(F, H.T if isinstance(H, Tensor) else H, ("F", "Hᵀ"))
    if Q is None or R is None:
        raise ValueError("Q and R (the process and measurement noise covariances) are needed")
    Q, R = _weights(Q, R, n, p, F)
    F, H = F.detach(), H.detach()
    _check_detectable(_np(F), _np(H))
    Ft, Ht, Qn, Rn = _np(F).T, _np(H).T, _np(Q), _np(R)
    pred = _riccati(sla.solve_discrete_are, Ft, Ht, Qn, Rn, filtering=True)
    _check_dare(pred, Ft, Ht, Qn, Rn, filtering=True)
    pred = torch.as_tensor(0.5 * (pred + pred.T), dtype=F.dtype, device=F.device)
    S = H @ pred @ H.T + R
    gain = torch.linalg.solve(S, H @ pred).T
    eye = torch.eye(n, dtype=F.dtype, device=F.device)
    cov = (eye - gain @ H) @ pred @ (eye - gain @ H).T + gain @ R @ gain.T  # Joseph form
    return gain, pred, 0.5 * (cov + cov.T)


def _check_detectable(F: np.ndarray, H: np.ndarray, tol: float = 1e-9) -> None:
    """Refuse ``(F, H)`` with a mode of ``|λ| ≥ 1`` that no measurement sees (PBH:
    ``[λI − F; H]`` of rank below ``n``, its smallest singular value at most ``tol`` times its
    largest; and the modes of ``F`` on the unobservable subspace, :func:`_unobservable_modes`).
    scipy refuses such a mode where the process noise excites it, and where it does not
    returns a covariance of 0 on it: a constant state that nothing measures, with ``Q = 0``
    on it, was given ``P⁻ = 0`` and the gain 0, where the filter keeps its prior variance on
    it for ever (a trial: the steady state depends on the prior there). The PBH test alone
    missed a Jordan block, whose eigenvalues numpy gives √ε apart (1 ± 1e-8): a constant
    position with only its velocity measured, in coordinates not triangular, had been given
    ``P⁻`` 2.8e8 (a trial of the control tools)."""
    n = F.shape[0]
    unseen = []
    for lam in np.linalg.eigvals(F):
        if abs(lam) < 1.0 - 1e-12:
            continue
        pencil = np.vstack([lam * np.eye(n) - F, H.astype(complex)])
        s = np.linalg.svd(pencil, compute_uv=False)
        if s[-1] <= tol * max(s[0], np.finfo(np.float64).tiny):
            unseen.append(lam)
    unseen += [lam for lam in _unobservable_modes(F, H, tol) if abs(lam) >= 1.0 - 1e-12]
    if unseen:
        raise ValueError(
            f"kalman_steady_state needs (F, H) detectable: the mode of F at eigenvalue "
            f"{complex(unseen[0]):.6g} (on or outside the unit circle) is seen by no "
            "measurement, so the filter's "
            "covariance along it has no steady state (it stays at the prior's, or grows): "
            "measure that mode, or leave it out of the model"
        )


def _unobservable_modes(F: np.ndarray, H: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """The eigenvalues of ``F`` on its unobservable subspace: the null space ``N`` (orthonormal)
    of ``[H; HF; …; HFⁿ⁻¹]`` (its rows scaled to unit length, singular values at most ``tol``
    times the largest), ``eig(Nᵀ F N)``; none where ``N`` is empty or, numerically, not
    invariant under ``F`` (``‖F N − N NᵀFN‖ > √tol ‖F‖``: no subspace, round-off of an
    observable one). By duality ``_unobservable_modes(Fᵀ, Bᵀ)`` are the uncontrollable modes."""
    n = F.shape[0]
    rows, block = [], H.astype(np.float64)
    for _ in range(n):
        norms = np.linalg.norm(block, axis=1, keepdims=True)
        rows.append(np.where(norms > 0, block / np.maximum(norms, np.finfo(np.float64).tiny), 0.0))
        block = rows[-1] @ F
    _, s, vh = np.linalg.svd(np.vstack(rows))
    s = np.concatenate([s, np.zeros(n - s.size)])
    null = vh[s <= tol * max(s[0], np.finfo(np.float64).tiny)].T  # [n, k]
    if null.shape[1] == 0:
        return np.zeros(0, dtype=complex)
    restricted = null.T @ F @ null
    if np.linalg.norm(F @ null - null @ restricted) > np.sqrt(tol) * max(np.linalg.norm(F), 1e-300):
        return np.zeros(0, dtype=complex)
    return np.linalg.eigvals(restricted).astype(complex)


def zoh_discretize(A: Tensor, B: Tensor, dt: float) -> tuple[Tensor, Tensor]:
    """Exact zero-order-hold discretisation of ``ẋ = A x + B u`` over ``dt`` (Van Loan).

    ``exp([[A, B], [0, 0]]·dt) = [[A_d, B_d], [0, I]]`` with ``A_d = e^{A dt}`` and
    ``B_d = ∫₀^dt e^{Aα} dα B``. Shapes: ``A [n, n]``, ``B [n, m]`` → ``(A_d [n, n], B_d [n, m])``.
    """
    # (numpy's numbers too: np.float32(0.1) had been refused; True taken for 1 s)
    dt = check_finite_number(dt, "dt (seconds)", positive=True)
    for name, t in (("A", A), ("B", B)):
        if not isinstance(t, Tensor) or not t.is_floating_point():
            raise ValueError(f"{name} must be a floating tensor; got {type(t).__name__}")
    if A.dim() != 2 or A.shape[0] != A.shape[1]:
        raise ValueError(f"A must be square [n, n]; got {tuple(A.shape)}")
    if B.dim() != 2 or B.shape[0] != A.shape[0]:
        raise ValueError(f"B must have shape [{A.shape[0]}, m]; got {tuple(B.shape)}")
    for name, t in (("A", A), ("B", B)):
        _check_finite_matrix(t, name)
    n, m = B.shape
    block = torch.zeros(n + m, n + m, dtype=A.dtype, device=A.device)
    block[:n, :n] = A
    block[:n, n:] = B
    expm = torch.linalg.matrix_exp(block * dt)
    return expm[:n, :n], expm[:n, n:]


def controllability_rank(A: Tensor, B: Tensor, tol: float | None = None) -> int:
    """Rank of ``[B, AB, …, Aⁿ⁻¹B]`` (9 for the two-area LFC: the tie-line sum is conserved).

    Each column is scaled to unit norm (the rank is the columns'), and a column of ``A M``
    within ``n ε ‖A‖`` of zero (``M``'s columns of unit norm: the product's round-off) is
    zero: scaled up, such a column of −2.8e-17 had counted as a full one, an uncontrollable
    pair given rank 2 (a trial). ``tol``: ``matrix_rank``'s ``atol`` (finite, ≥ 0)."""
    _check_pair(A, B, ("A", "B"))
    if tol is not None:  # (NaN had given rank 0, a negative tol had been taken)
        tol = check_finite_number(tol, "tol", nonnegative=True)
    n = A.shape[0]
    roundoff = n * torch.finfo(A.dtype).eps * float(torch.linalg.matrix_norm(A, 2))
    blocks, M = [], B
    for i in range(n):
        # columns of unit norm (the rank is theirs): A's entries span four orders of
        # magnitude, and Aⁿ⁻¹B unscaled overflowed float32 (a chain of ten integrators)
        norm = M.norm(dim=0, keepdim=True)
        if i > 0:  # (B's own columns are as given)
            M = torch.where(norm <= roundoff, torch.zeros_like(M), M)
        M = M / norm.clamp_min(torch.finfo(M.dtype).tiny)
        blocks.append(M)
        M = A @ M
    ctrb = torch.cat(blocks, dim=1)
    rank = (
        torch.linalg.matrix_rank(ctrb) if tol is None else torch.linalg.matrix_rank(ctrb, atol=tol)
    )
    return int(rank.item())
