"""The data-independent gains of a time-invariant linear model, shared by every run.

Without lost measurements the Kalman covariance recursion

    P⁻_k = F P_{k−1} Fᵀ + Q,   S_k = H P⁻_k Hᵀ + R,   K_k = P⁻_k Hᵀ S_k⁻¹,
    P_k  = (I − K_k H) P⁻_k (I − K_k H)ᵀ + K_k R K_kᵀ

does not depend on the data: :class:`GainSchedule` runs it once, on unbatched ``[dx, dx]``
matrices (the Gaussian core's blocks of :mod:`difffilter.gaussian` written out with fewer
operations, equal up to round-off), and keeps every step's moments. It computes a chunk of
steps at a time (:func:`riccati_chunk`): with the data-independent part ``(A, C, J)`` of the
parallel-in-time filter's element of one step (Särkkä & García-Fernández 2021,
:mod:`difffilter.parallel_kalman`) and its ``j``-fold combinations ``E(j)``, ``j ≤ 16``,
made once by doubling, ``P_{s+j} = A_j (I + P_s J_j)⁻¹ P_s A_jᵀ + C_j`` gives each block of
16 covariances from the block's first (and the next block's first), and the rest of the
recursion runs batched over the chunk: about 40 operations on ``[n, d, d]`` batches per
chunk instead of 25 per step on ``[d, d]`` matrices, whose cost at ``d = 4`` is their
dispatch (a Kalman filter's cold start at B = 1: its first hundred steps; the
whole-sequence filter at B = 1). :class:`CovarianceChunks` holds that recursion. What
remains per run is linear in the data,

    m⁻_k = F m_{k−1} + B u_{k−1}                                    (:meth:`GainSchedule.predict`)
    ν_k  = y_k − H m⁻_k,   m_k = m⁻_k + K_k ν_k                    (:meth:`GainSchedule.update`)

and is the Kalman filter's exactly (tested against :func:`difffilter.kalman_filter`), for
any batch of runs, differentiably with respect to ``m``, ``y`` and ``u``. The online
counterpart of the whole-sequence shared-covariance path of
:func:`difffilter.kalman_filter`: :class:`~difffilter.KalmanFilter` uses it by itself
for an unbatched time-invariant model, so a closed loop (where ``u_k`` depends on the
estimate) pays the covariance recursion once, not once per step of every loop. Once the
gain and the covariance have converged (relative changes at most ``tol``, each entry of
``P`` against its own scale and tighter for a slow recursion:
:meth:`CovarianceChunks._steps_to_keep`) the last moments are reused for every later step.
:meth:`GainSchedule.filter_step` is the whole step of
every run fused (about eight tensor operations: the online Kalman step at B = 1 costs
little more than the Python call).
"""

from __future__ import annotations

import numbers
import threading
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from ._assignments import assignments
from ._riccati_host import (
    chained_steps,
    finite_steps,
    host_arrays,
    host_chunk,
    host_step_maps,
    steps_to_keep,
)
from .linalg import INNOVATION_COV, LOG_2PI, NumericalBreakdown, matvec, safe_cholesky
from .parallel_kalman import combine_covariance, covariance_elements

__all__ = [
    "CovarianceChunks",
    "GainSchedule",
    "SharedMoments",
    "half_log_det",
    "riccati_chunk",
    "riccati_step",
    "riccati_steps",
    "shared_gains_apply",
]


class SharedMoments(NamedTuple):
    """The moments of measurement ``k`` shared by every run: ``pred_cov`` ``P⁻_k``, ``cov``
    ``P_k`` ``[dx, dx]``, ``gain`` ``K_k [dx, dy]``, ``innovation_cov`` ``S_k``, its
    Cholesky factor ``chol`` ``L_k``, the whitening ``whiten = L_k⁻¹`` ``[dy, dy]`` and
    ``log_norm = Σ log diag L_k + (dy/2) log 2π`` (so ``log N(ν; 0, S_k) =
    −½‖L_k⁻¹ν‖² − log_norm``: one product per step for all runs)."""

    pred_cov: Tensor
    cov: Tensor
    gain: Tensor
    innovation_cov: Tensor
    chol: Tensor
    whiten: Tensor
    log_norm: Tensor


def shared_gains_apply(model) -> bool:
    """Whether ``model`` is a time-invariant linear model whose matrices and prior carry no
    batch dimension (its gains are then the same for every run) and none of them requires
    gradients (the schedule is computed once, outside autograd: a model being trained
    takes the general, differentiable update instead)."""
    needed = ("transition_matrix", "observation_matrix", "control_matrix", "process_cov")
    if not all(hasattr(model, name) for name in needed) or getattr(model, "time_varying", False):
        return False
    B = model.control_matrix(0)
    mats = (model.transition_matrix(0), model.observation_matrix(1), model.initial.cov,
            model.process_cov(0), model.measurement_cov(1), *(() if B is None else (B,)))  # fmt: skip
    # every one unbatched (a per-run Q, R or B is per-run covariances or a per-run map)
    if not (all(m.dim() == 2 for m in mats) and model.initial.mean.dim() == 1):
        return False
    every = (*mats, model.initial.mean)
    return not any(m.requires_grad for m in every)


class GainSchedule:
    """The data-independent moments (:class:`SharedMoments`) of a linear model's Kalman
    filter, computed on first use and cached.

    Args:
        model: a time-invariant linear model (``transition_matrix``, ``observation_matrix``,
            ``process_cov``, ``measurement_cov``, ``control_matrix``; e.g.
            :class:`~difffilter.LinearGaussianModel`) whose matrices and prior carry no batch
            dimension.
        tol: relative change of ``K`` and of each entry of ``P`` below which the recursion
            counts as converged (at least 16 ε of the matrices' dtype: a chunk's steps are
            computed from its first by different products, so below that the change is
            round-off; 1.9e-6 in float32; :meth:`CovarianceChunks._steps_to_keep`).
    """

    def __init__(self, model, *, tol: float = 1e-12):
        needed = ("transition_matrix", "observation_matrix", "control_matrix", "process_cov")
        missing = [name for name in needed if not hasattr(model, name)]
        if missing:
            raise ValueError(f"model must be linear (it lacks {', '.join(missing)})")
        if getattr(model, "time_varying", False):
            raise ValueError("model must be time-invariant (its gains are shared by every step)")
        if not shared_gains_apply(model):
            raise ValueError(
                "model's matrices and prior must carry no batch dimension and require no "
                "gradient (the schedule is computed outside autograd: a model being trained "
                "takes KalmanFilter's general update)"
            )
        if isinstance(tol, bool) or not isinstance(tol, numbers.Real) or not tol >= 0:
            raise ValueError(f"tol must be a number >= 0; got {tol!r}")
        self.model, self.tol = model, float(tol)
        # held by a Kalman filter's step that uses the schedule: the carries branched from
        # one start carry share it, and stepped from several threads their handing out and
        # trimming had interleaved (IndexError, or means 1.6 off: a concurrency trial)
        self.lock = threading.RLock()
        # the count before the model is read: an assignment while it is read counts as after
        self._assignments = assignments()
        self.F, self.H, self.B = (
            model.transition_matrix(0),
            model.observation_matrix(1),
            model.control_matrix(0),
        )
        self.Q, self.R = model.process_cov(0), model.measurement_cov(1)
        # the prior covariance the recursion starts from, as the carries at k = 0 hold it (a
        # prior given by its factor makes a new `cov` tensor at every read)
        self.initial_cov = model.initial.cov
        mats = (self.F, self.H, self.B, self.Q, self.R, self.initial_cov)
        self._sources = _source_versions(model, mats)
        self._own_sources = self._sources  # what it computes with, as first read
        dy, dx = self.H.shape
        eye = torch.eye(dx, dtype=self.H.dtype, device=self.H.device)
        # H = I (a fully measured state) saves a product per step
        self._identity_h = dx == dy and bool(torch.equal(self.H, eye))
        # transposed views, made once: the per-run products are `rows @ Aᵀ` (one GEMM)
        self.Ft, self.Ht = self.F.transpose(0, 1), self.H.transpose(0, 1)
        self.Bt = None if self.B is None else self.B.transpose(0, 1)
        # the handed-out moments of measurements _dropped + 1, _dropped + 2, …: a recursion
        # that never converges drops the oldest (_trim), or an online filter's memory grew
        # by 4.8 kB a step (1 GB in 200,000 steps of an unobserved random walk)
        self._dropped = 0
        self._moments: list[SharedMoments] = []
        self._cov_versions: list[int] = []  # each handed-out covariance's version then
        # and of its P⁻ and S, which a step's output hands out as they are (shared: a write
        # through one, `out.innovation_cov += …`, had changed every later step's S)
        self._out_versions: list[tuple[int, int]] = []
        self._row_maps: list[tuple[Tensor, Tensor, Tensor]] = []
        self._neg_log_norms: list[Tensor] = []  # −log_norm of each k: the one-run step's
        self._chunks = CovarianceChunks(self.F, self.H, self.Q, self.R, self.initial_cov, tol)
        # the last chunk's moments [n, ...] (and log-norms and their negatives [n]) not yet
        # handed out, from index _ahead_next, and the block of rows unbound from it (each
        # step's SharedMoments of views and its −log_norm, made BLOCK steps at a time: one
        # `unbind` per moment instead of an index per step), of which _block_next is next: a
        # filter keeps the tensors of the steps it ran and of at most one block ahead, not of
        # the whole chunk computed ahead
        self._ahead: tuple[Tensor, ...] | None = None
        self._ahead_next = 0
        self._block: list[tuple[SharedMoments, Tensor]] = []
        self._block_next = 0

    # the watched tensors and their stamps as a list (:meth:`current`), of `_sources` then
    _stamps_of: tuple | None = None
    _stamps: tuple | None = None

    def __getstate__(self) -> dict:
        """A copy (``copy.deepcopy``, ``pickle``, ``torch.save``) makes new tensors whose
        version counters start again: each stamp is replaced by what it said at the copy
        (unchanged or not), and :meth:`__setstate__` stamps the copies anew from that. A
        restored carry had been refused as "written in place" at its next step, though
        nothing had written to it (a serialisation trial)."""
        state = self.__dict__.copy()
        for name in ("_stamps_of", "_stamps", "lock"):  # (remade: at the next use, a new lock)
            state.pop(name, None)
        for name in ("_sources", "_own_sources"):
            state[name] = tuple((t, _unchanged(t, stamp)) for t, stamp in state[name])
        state["_cov_versions"] = [
            _version(m.cov) == v for m, v in zip(self._moments, self._cov_versions)
        ]
        state["_out_versions"] = [
            _out_versions(m) == v for m, v in zip(self._moments, self._out_versions)
        ]
        return state

    def __setstate__(self, state: dict) -> None:
        for name in ("_sources", "_own_sources"):
            state[name] = tuple((t, _stamp(t) if ok else _STALE) for t, ok in state[name])
        state["_cov_versions"] = [
            _version(m.cov) if ok else _STALE
            for m, ok in zip(state["_moments"], state["_cov_versions"])
        ]
        state["_out_versions"] = [
            _out_versions(m) if ok else (_STALE, _STALE)
            for m, ok in zip(state["_moments"], state["_out_versions"])
        ]
        # the count of assignments is this process's, from 0: the stored one could equal it
        # after a first `model.F = …` here, which then went unseen (a KF trial: the old gains
        # and a mean 0.17 off); -1 has the model read again at the first use
        state["_assignments"] = -1
        state["lock"] = threading.RLock()
        self.__dict__.update(state)

    @property
    def converged(self) -> bool:
        """Whether the gain has converged (every later step reuses the last moments)."""
        return self._chunks.converged

    def current(self) -> bool:
        """Whether the model's matrices, noise and prior are as they were when the schedule
        was made (no tensor of them, nor any parameter or buffer of the model, written in
        place since: the moments computed ahead would mix the old model with the new). A
        Kalman filter's step drops a schedule that is not and goes on with the general
        update, which reads the model at every step. A tensor or noise model assigned anew
        (``model.F = …``, ``model.to(…)``: any assignment to any model since,
        :mod:`difffilter._assignments`) has the model's matrices read again and compared
        with the schedule's (an online KF had gone on with the old ones)."""
        # the tensors it watches first: an in-place write, then an assignment anywhere, had the
        # re-read compare the written tensor with itself and forget the write (a review)
        sources = self._sources
        if sources is not self._stamps_of:  # (made anew: a re-read, a copy)
            self._stamps_of, self._stamps = sources, _plain_stamps(sources)
        plain = self._stamps
        if plain is not None:  # every stamp a (version, memory, requires_grad): one list
            if [(t._version, t.data_ptr(), t.requires_grad) for t in plain[0]] != plain[1]:
                return False
        elif not all(_unchanged(t, stamp) for t, stamp in sources):
            return False
        count = assignments()  # (read first: an assignment from now on moves it again)
        if self._assignments != count:
            if not self._reads_the_same():
                return False
            self._assignments = count
        return True

    def _reads_the_same(self) -> bool:
        """Whether the model's matrices and noise covariances now are the schedule's (the
        same dtype, device, shape and values) and still take a schedule (none requires a
        gradient: a parameter assigned in place of a tensor is to be trained, through the
        general update). If so, the schedule watches the tensors the model now holds as well
        as those it computes with (a later in-place write into either is then seen: another
        model sharing the old F could change it under the schedule)."""
        model = self.model
        if not shared_gains_apply(model):
            return False
        now = (model.transition_matrix(0), model.observation_matrix(1), model.control_matrix(0),
               model.process_cov(0), model.measurement_cov(1), model.initial.cov)  # fmt: skip
        had = (self.F, self.H, self.B, self.Q, self.R, self.initial_cov)
        if not all(_same(a, b) for a, b in zip(now, had)):
            return False
        # its own tensors (their versions checked unchanged just before) and the model's now:
        # not every tensor the model ever held (a review: one more per re-read, 4,000 after
        # 4,000 steps of a covariance rebuilt at each read, 2.8 ms a step)
        own = self._own_sources
        watched = {id(t): (t, v) for t, v in (*own, *_source_versions(model, now))}
        self._sources = tuple(watched.values())
        return True

    #: How many handed-out steps' moments a schedule whose recursion has not converged
    #: keeps at least (at most :attr:`TRIM` more): a carry more than that many steps behind
    #: the newest step of its schedule is no longer :meth:`held`, and a Kalman filter's step
    #: from it goes on with the general update, from the covariance the carry holds. Kept
    #: small and trimmed often: dropping 4,096 steps at once made a step of 11–13 ms, and
    #: the tensors of 8,192 steps made Python's garbage collector pause 117–146 ms every
    #: 8,800 steps (a user trial timing a 10 ms loop).
    KEEP, TRIM = 1024, 128

    def held(self, k: int) -> bool:
        """Whether the moments of measurement ``k ≥ 1`` are kept or still to come (not
        dropped: :attr:`KEEP`)."""
        return k > self._dropped

    def moments(self, k: int) -> SharedMoments:
        """The :class:`SharedMoments` of measurement ``k ≥ 1`` (:meth:`held`)."""
        known = self._moments
        if type(k) is int and k > self._dropped:
            i = k - self._dropped  # its position in `known`, from 1
            if i <= len(known):  # handed out already: every step after the first
                return known[i - 1]
            if i == len(known) + 1 and self._block_next < len(self._block):
                return self._hand_out()  # the next one, unbound already (a step's first call)
            if self._all_handed_out():  # every later step: the last ones
                return known[-1]
        if isinstance(k, bool) or not isinstance(k, int) or k < 1:
            raise ValueError(f"k must be an integer >= 1 (the measurement index); got {k!r}")
        if k <= self._dropped:
            raise ValueError(
                f"the moments of measurement {k} were dropped: a schedule that has not "
                f"converged keeps those of its last {self.KEEP} to {self.KEEP + self.TRIM} steps "
                f"(it has handed out {self._dropped + len(known)}); check held(k) first"
            )
        while self._dropped + len(known) < k and not self._all_handed_out():
            if self._block_next == len(self._block):
                self._next_block()
            self._hand_out()
        return known[min(k - self._dropped, len(known)) - 1]

    def _index(self, k: int) -> int:
        """The list position of measurement ``k``'s handed-out moments (the last ones for a
        ``k`` past them: every later step of a converged schedule)."""
        return min(k - self._dropped, len(self._moments)) - 1

    def _hand_out(self) -> SharedMoments:
        """Hand out the block's next moments (and their ``−log_norm``)."""
        moments, neg_log_norm = self._block[self._block_next]
        self._block_next += 1
        self._moments.append(moments)
        self._cov_versions.append(_version(moments.cov))
        self._out_versions.append(_out_versions(moments))
        self._neg_log_norms.append(neg_log_norm)
        if len(self._moments) > self.KEEP + self.TRIM:
            self._trim()
        return moments

    def _trim(self) -> None:
        """Drop the oldest :attr:`TRIM` handed-out steps (a schedule that never converges
        would keep every step's tensors)."""
        n = self.TRIM
        for kept in (self._moments, self._cov_versions, self._out_versions, self._neg_log_norms,
                     self._row_maps):  # fmt: skip
            del kept[:n]  # (the row maps are made up to some step, perhaps none)
        self._dropped += n

    def intact(self, k: int) -> bool:
        """Whether the covariance of measurement ``k ≥ 1`` (handed out) is as it was handed
        out: not written in place since (an inference tensor keeps no version: assumed)."""
        if not self.held(k):
            return True  # dropped: a step from it does not use the schedule (KEEP)
        index = self._index(k)
        return _version(self._moments[index].cov) == self._cov_versions[index]

    def outputs_intact(self, k: int) -> bool:
        """Whether the ``P⁻`` and ``S`` that measurement ``k ≥ 1`` (held) uses are as they
        were handed out: a step's output holds them as they are, shared by every run and,
        once the gain has converged, by every later step (a write through one, ``S +=
        …``, had become every later step's ``S``). Moments not handed out yet are."""
        i = k - self._dropped  # its position in the handed-out list, from 1
        known = self._moments
        if i > len(known):
            if not self._all_handed_out():
                return True  # still to come: nobody has had them
            i = len(known)  # converged: the last ones, reused
        return _out_versions(known[i - 1]) == self._out_versions[i - 1]

    def _all_handed_out(self) -> bool:
        return (self.converged and self._ahead is None
                and self._block_next == len(self._block))  # fmt: skip

    def _next_block(self) -> None:
        """Unbind the next ``BLOCK`` steps' moments from the chunk ahead (computing the next
        chunk first if none is left), each with its ``−log_norm``: plain tensors without
        autograd history, also under ``torch.inference_mode()`` (inference tensors could
        not be saved for the backward of a later step that records gradients)."""
        with torch.inference_mode(False), torch.no_grad():
            self._unbind_next_block()

    def _unbind_next_block(self) -> None:
        if self._ahead is None:
            *moments, half_logdet = self._chunks.next()
            log_norms = half_logdet + 0.5 * self.H.shape[0] * LOG_2PI
            # −log_norm too (what the fused step adds), negated once per chunk, not per step
            self._ahead, self._ahead_next = (*moments, log_norms, log_norms.neg()), 0
        start, ahead = self._ahead_next, self._ahead
        stop = min(start + CovarianceChunks.BLOCK, len(ahead[0]))
        rows = zip(*(t[start:stop].unbind(0) for t in ahead))
        self._block = [(SharedMoments(*row[:-1]), row[-1]) for row in rows]
        self._block_next, self._ahead_next = 0, stop
        if stop == len(ahead[0]):
            self._ahead = None

    def gain(self, k: int) -> tuple[Tensor, Tensor]:
        """``(K_k [dx, dy], S_k [dy, dy])`` of measurement ``k ≥ 1``."""
        m = self.moments(k)
        return m.gain, m.innovation_cov

    def predict(self, mean: Tensor, u: Tensor | None = None) -> Tensor:
        """``m⁻ = F m + B u``: ``mean [..., dx]``, ``u [..., du]`` or ``None`` → ``[..., dx]``."""
        pred = matvec(self.F, mean)
        if u is not None and self.B is not None:
            pred = pred + matvec(self.B, u)
        return pred

    def innovation(self, pred_mean: Tensor, y: Tensor) -> Tensor:
        """``ν = y − H m⁻`` ``[..., dy]``."""
        return y - (pred_mean if self._identity_h else matvec(self.H, pred_mean))

    def filter_step(
        self, mean: Tensor, y: Tensor, u: Tensor | None, k: int
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, SharedMoments]:
        """The whole Kalman step of measurement ``k ≥ 1`` for every run, fused:
        ``(m_k, m⁻_k, ν_k, log N(ν_k; 0, S_k), SharedMoments)``.

        ``m⁻ = F m + B u``, ``ν = y − H m⁻``, ``m_k = m⁻ + K_k ν`` and
        ``log N = −½‖L_k⁻¹ν‖² − log_norm`` with the moments' transposed maps made once per
        ``k``: about eight tensor operations in all, the same numbers as :meth:`predict`,
        :meth:`update` and the moments' whitening. ``mean [..., dx]``, ``y [..., dy]``, ``u
        [..., du]`` or ``None`` → ``[..., dx]``, ``[..., dx]``, ``[..., dy]``, ``[...]``.
        Unchecked (the lean step's inner call: :meth:`KalmanFilter.step
        <difffilter.KalmanFilter.step>` checks ``y`` and ``u`` first): a ``y`` of one entry
        broadcasts over ``dy`` here without a word (a trial of the gain schedule).
        """
        m = self.moments(k)
        index = self._index(k)
        try:
            seen = (m.pred_cov._version, m.innovation_cov._version)
        except RuntimeError:  # inference tensors (a copy made under inference mode)
            seen = _out_versions(m)
        if seen != self._out_versions[index]:
            raise OutputsWritten(k)  # (:meth:`outputs_intact`, here where the index is known)
        control = u is not None and self.B is not None
        if mean.dim() == 1 and y.dim() == 1 and (not control or u.dim() == 1):
            # one run: matrix-vector products, the subtraction and addition fused in
            neg_log_norm = self._neg_log_norm(index)
            pred = torch.mv(self.F, mean)
            if control:
                pred = torch.addmv(pred, self.B, u)
            innovation = y - pred if self._identity_h else torch.addmv(y, self.H, pred, alpha=-1.0)
            white = torch.mv(m.whiten, innovation)
            log_lik = torch.add(neg_log_norm, torch.dot(white, white), alpha=-0.5)
            return torch.addmv(pred, m.gain, innovation), pred, innovation, log_lik, m
        gain_t, whiten_t, neg_log_norm = self._row_map(index)
        pred = mean @ self.Ft  # rows [..., dx]: one GEMM for all runs
        if control:
            pred = pred + u @ self.Bt
        innovation = y - (pred if self._identity_h else pred @ self.Ht)
        white = innovation @ whiten_t
        log_lik = torch.add(neg_log_norm, torch.linalg.vecdot(white, white), alpha=-0.5)
        return pred + innovation @ gain_t, pred, innovation, log_lik, m

    def _row_map(self, index: int) -> tuple[Tensor, Tensor, Tensor]:
        """What the fused step multiplies rows by at moments ``index``: ``Kᵀ``, ``L⁻ᵀ``
        (views) and ``−log_norm``, made on the fused step's first use of them (a loop that
        steps through :meth:`predict`/:meth:`update` keeps no extra tensor per step)."""
        maps = self._row_maps
        while len(maps) <= index:
            m = self._moments[len(maps)]
            maps.append((m.gain.mT, m.whiten.mT, self._neg_log_norm(len(maps))))
        return maps[index]

    def _neg_log_norm(self, index: int) -> Tensor:
        """``−log_norm`` of moments ``index`` (handed out with them: the one-run step needs
        no transposed maps)."""
        return self._neg_log_norms[index]

    def update(self, pred_mean: Tensor, y: Tensor, k: int) -> tuple[Tensor, Tensor, Tensor]:
        """``(m_k, ν_k, S_k)``: ``pred_mean [..., dx]``, ``y [..., dy]`` → ``[..., dx]``,
        ``[..., dy]``, ``[dy, dy]`` (shared by the runs)."""
        m = self.moments(k)
        dy = m.innovation_cov.shape[-1]
        if y.dim() < 1 or y.shape[-1] != dy:  # (a y [1] had broadcast over dy = 2, unsaid)
            raise ValueError(f"y must have shape [..., {dy}]; got {tuple(y.shape)}")
        innovation = self.innovation(pred_mean, y)
        return pred_mean + matvec(m.gain, innovation), innovation, m.innovation_cov


class CovarianceChunks:
    """The covariance recursion of one unbatched time-invariant model a chunk of steps at a
    time (:func:`riccati_chunk`; step by step where ``H Q Hᵀ + R`` is singular), each chunk
    cut at the first step whose gain converged: what :class:`GainSchedule` hands out step
    by step and the whole-sequence shared-covariance path (:mod:`difffilter._shared_cov`)
    stacks. Matrices in CPU memory in float32 or float64 take the same equations on host
    arrays (:mod:`difffilter._riccati_host`: half the torch recursion's time on ``4 × 4``
    matrices, the same numbers up to round-off); other devices and dtypes, and
    whatever the host cannot factorise, the torch recursion.

    Args:
        F, H, Q, R: ``[dx, dx]``, ``[dy, dx]``, ``[dx, dx]``, ``[dy, dy]``.
        cov: the prior covariance ``P_0 [dx, dx]``.
        tol: the convergence test's relative change (:meth:`_steps_to_keep`), at least
            16 ε of the dtype (:class:`GainSchedule`).
    """

    #: Blocks of ``BLOCK`` steps (the maps ``E(1 … BLOCK)``); the first chunk one block (a
    #: filter run for a few steps computes little ahead), each later one ``GROWTH`` times
    #: the steps done, at most ``MAX_BLOCKS`` blocks (the benchmark's model converges in 110
    #: steps, 123 since the per-entry test of 2026-11-30: two chunks; one chunk of 128 steps
    #: measured no faster).
    BLOCK, GROWTH, MAX_BLOCKS = 16, 7, 8

    def __init__(self, F: Tensor, H: Tensor, Q: Tensor, R: Tensor, cov: Tensor, tol: float):
        dy, dx = H.shape
        self._mats = (
            F, F.transpose(0, 1), H, H.transpose(0, 1), Q, R,
            torch.eye(dx, dtype=H.dtype, device=H.device),
            torch.eye(dy, dtype=H.dtype, device=H.device),
        )  # fmt: skip
        self._cov = cov
        self._tol = max(float(tol), 16 * torch.finfo(H.dtype).eps)
        self._maps: tuple[Tensor, ...] | None = None  # E(1 … BLOCK), () if none: _step_maps
        # numpy views of F, H, Q, R in CPU memory (the recursion on host arrays,
        # :mod:`difffilter._riccati_host`) and their maps, made on the first chunk; None:
        # the torch recursion (another device, half precision, or what the host cannot
        # factorise, from then on)
        self._host = host_arrays(F, H, Q, R) if H.device.type == "cpu" else None
        self._host_maps: tuple | None = None
        self._last_gain: Tensor | None = None  # K of the last step done (P: self._cov)
        self.steps = 0  # steps done
        self.converged = False
        self._stepwise = False  # the maps broke the chain once: one step at a time from then

    def next(self) -> tuple[Tensor, ...]:
        """The next chunk's ``(P⁻, P, K, S, L, L⁻¹)`` (each ``[n, ·, ·]``, as
        :func:`riccati_step` returns them) and ``Σ log diag L`` ``[n]``, up to and
        including the first step whose gain converged (then :attr:`converged`)."""
        # an overflowing covariance is named below (_finite_steps), not in numpy's warnings
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            return self._next()

    def _next(self) -> tuple[Tensor, ...]:
        blocks = min(max(self.GROWTH * self.steps // self.BLOCK, 1), self.MAX_BLOCKS)
        moments = None if self._stepwise else self._host_chunk(blocks)
        if moments is not None:  # the same tests on the host arrays, in one pass
            return self._checked_host(moments)
        maps = None if self._stepwise else self._step_maps()
        if maps is not None:
            moments = riccati_chunk(self._cov, maps, blocks, *self._mats)
        else:  # no scan element (H Q Hᵀ + R singular), or the maps broke the chain
            moments = riccati_steps(self._cov, blocks * self.BLOCK, *self._mats)
        finite = self._finite_steps(moments[0], moments[1], moments[3], moments[4])
        if finite < len(moments[0]):  # the finite steps now; the next chunk raises
            moments = tuple(m[:finite] for m in moments)
        if not self._stepwise:
            chained = self._chained_steps(moments[0], moments[1])
            if chained < len(moments[0]):  # the steps the chain holds; then step by step
                moments, self._stepwise = tuple(m[:chained] for m in moments), True
        keep = self._steps_to_keep(moments[2], moments[1])
        return self._accepted(tuple(m[:keep] for m in moments))

    def _accepted(self, moments: tuple) -> tuple[Tensor, ...]:
        """A chunk's kept steps ``moments``: the recursion goes on from its last covariance
        and gain, and they come back with their ``½ log det S``."""
        self._cov, self._last_gain = moments[1][-1], moments[2][-1]
        self.steps += len(moments[0])
        return (*moments, half_log_det(moments[4]))

    def _checked_host(self, moments: tuple) -> tuple[Tensor, ...]:
        """:meth:`_next`'s tests (:meth:`_finite_steps`, :meth:`_chained_steps`,
        :meth:`_steps_to_keep`: the same tests, tolerances and cuts) on a host chunk's
        arrays before they become tensors: a few numpy calls instead of about 40 torch ones
        on ``[n, d, d]`` batches."""
        finite = finite_steps(moments[0], moments[1], moments[3], moments[4])
        if finite == 0:
            raise self._overflow(torch.from_numpy(moments[1][:0]).dtype)
        if finite < len(moments[0]):  # the finite steps now; the next chunk raises
            moments = tuple(m[:finite] for m in moments)
        F, _, Q, _ = self._host
        chained = chained_steps(moments[0], moments[1], F, Q, self.chain_tol(F.dtype))
        if chained < len(moments[0]):  # the steps the chain holds; then step by step
            moments, self._stepwise = tuple(m[:chained] for m in moments), True
        K, P = moments[2], moments[1]
        last = (None, None) if self._last_gain is None else (self._last_gain, self._cov)
        keep = steps_to_keep(K, P, *map(_host_view, last), F, self._host[1], self._tol)
        if keep is None:
            keep = K.shape[0]
        else:
            self.converged = True
        return self._accepted(tuple(torch.from_numpy(m[:keep]) for m in moments))

    def _overflow(self, dtype) -> NumericalBreakdown:
        """The error of a chunk whose first step has no finite covariance."""
        step = self.steps + 1
        return NumericalBreakdown(
            f"the Kalman filter's state covariance P (or the innovation covariance S = H P⁻ "
            f"Hᵀ + R made from it) is not finite at step {step}: "
            f"a variance grew past the largest {str(dtype).removeprefix('torch.')} "
            f"number ({torch.finfo(dtype).max:.2g}), most often an unstable mode of F "
            "(an eigenvalue of modulus above 1) that the measurements do not observe, "
            "whose uncertainty grows without bound; no filter can go on from an "
            "infinite variance: make that mode observable or stable, or filter in "
            "float64 (a larger range: the same model overflows later)"
        )

    def _finite_steps(self, pred_cov: Tensor, cov: Tensor, *more: Tensor) -> int:
        """How many of a chunk's first steps have finite covariances ``P⁻, P [n, dx, dx]``
        (and ``more``: ``S``, ``L``, where an ``S`` overflowed beside a finite ``P⁻`` had
        been taken; all ``n`` in the common case; one read); raises
        :class:`NumericalBreakdown` where the chunk's first step has none: the recursion
        cannot go on from it. A chunk is computed ahead of the steps asked for, so its
        finite steps are handed out first and the error comes with the step that
        overflowed, not a chunk before it."""
        if cov.device.type == "meta":
            return cov.shape[0]
        ok = torch.isfinite(pred_cov).flatten(1).all(1) & torch.isfinite(cov).flatten(1).all(1)
        for m in more:
            ok &= torch.isfinite(m).flatten(1).all(1)
        if bool(ok.all()):
            return ok.shape[0]
        finite = int(ok.int().argmin())
        if finite == 0:
            raise self._overflow(cov.dtype)
        return finite

    #: The chain test's tolerance per entry, against ``√(P⁻ᵢᵢ P⁻ⱼⱼ)``, times ``√ε`` of the
    #: dtype (3.5e-3 in float32): round-off of the maps is far below it on a
    #: well-conditioned model, their breakdown far above it. In float64 :data:`CHAIN_TOL_FLOAT64`.
    CHAIN_TOL = 10.0
    #: The same in float64 (1.5e-11 relative): the maps' round-off reaches 2.5e-14 on the
    #: LFC plant and 1e-15 on random and constant-velocity models, while 10 (1.5e-7) had
    #: let a chain 3.7e-9 off through, whose covariances, near cancelling in ``P⁻Hᵀ``, gave
    #: gains 2.4 % off the recursion (three random walks seen through their sum: means
    #: 2.7e-4 off; a trial of the gain schedule). Steps it refuses run one at a time.
    CHAIN_TOL_FLOAT64 = 1e-3

    @classmethod
    def chain_tol(cls, dtype: torch.dtype) -> float:
        """The chain test's tolerance of ``dtype`` (:data:`CHAIN_TOL`, :data:`CHAIN_TOL_FLOAT64`)."""
        wide = dtype == torch.float64 or dtype == np.float64  # (a torch or a host dtype)
        return cls.CHAIN_TOL_FLOAT64 if wide else cls.CHAIN_TOL

    def _chained_steps(self, pred_cov: Tensor, cov: Tensor) -> int:
        """How many of a chunk's first steps form one chain of the recursion: ``P⁻_t =
        F P_{t−1} Fᵀ + Q`` for each step ``t`` after the first, per entry within
        :meth:`chain_tol` ``·√ε·√(P⁻ᵢᵢ P⁻ⱼⱼ)`` (``P⁻, P [n, dx, dx]``). A chunk starts its
        steps from the ``j``-step maps ``E(j)``, whose ``(I + P J)⁻¹`` is ill-conditioned
        on a strongly non-normal ``F`` with small ``Q`` and ``R``: each step then began from
        another covariance than its predecessor's (``S`` 6.5 % off, ``P`` 3.8 %, the
        log-likelihood 0.034 nats, against a 50-digit filter; a red-team trial), while the
        means, checked, held. The first step starts from the exact ``P_s``."""
        n = pred_cov.shape[0]
        if n < 2 or cov.device.type == "meta":
            return n
        F, Ft, Q = self._mats[0], self._mats[1], self._mats[4]
        with torch.no_grad():  # a test of the numbers, not part of any gradient
            again = F.detach() @ cov[:-1].detach() @ Ft.detach() + Q.detach()
        pred = pred_cov[1:].detach()
        root = pred.diagonal(dim1=-2, dim2=-1).clamp_min(0.0).sqrt()
        finfo = torch.finfo(pred.dtype)
        bound = (self.chain_tol(pred.dtype) * finfo.eps**0.5) * (
            root.unsqueeze(-1) * root.unsqueeze(-2)
        )
        # (plus round-off of the largest entry: a state of zero variance has no scale)
        bound = bound + 64 * finfo.eps * pred.abs().amax(dim=(-2, -1), keepdim=True)
        broken = ((again - pred).abs() > bound).flatten(1).any(1)
        if not bool(broken.any()):
            return n
        return int(broken.int().argmax()) + 1

    def _host_chunk(self, blocks: int) -> tuple | None:
        """The next chunk's moments as :func:`riccati_chunk` computes them, on host arrays
        (:func:`~difffilter._riccati_host.host_chunk`), or ``None``: the torch recursion
        (the matrices are not on the host, or the host could not factorise them, from then
        on: the torch recursion's jitter or clear error decides)."""
        host = self._host
        if host is None:
            return None
        F, H, Q, R = host
        if self._host_maps is None:
            self._host_maps = host_step_maps(F, H, Q, R, self.BLOCK)
        cov = None if self._host_maps is None else host_arrays(self._cov)
        moments = None if cov is None else host_chunk(cov[0], self._host_maps, blocks, *host)
        if moments is None:
            self._host = None
        return moments

    def _steps_to_keep(self, K: Tensor, P: Tensor) -> int:
        """How many of a chunk's steps (gains ``K [n, dx, dy]``, covariances ``P [n, dx,
        dx]``) to keep: up to the first step whose gain and covariance both converged (then
        :attr:`converged`), else all; one read. Converged at step ``k``:

            max |K_k − K_{k−1}| ≤ tol_ρ · max |K_{k−1}|,
            |P_k − P_{k−1}|_ij ≤ tol_ρ · √(P_{k−1,ii} P_{k−1,jj})   for every i, j,
            tol_ρ = tol · min(1, (1 − ρ²)/ρ²),  ρ = spectral radius of (I − K_k H) F.

        The gain alone is not enough: the variance of a state that no measurement reaches
        (zero rows of ``K``) keeps moving after the gain has settled. Each entry of ``P``
        against its own correlation scale, not the largest entry: a small variance beside
        large ones had counted as settled while it moved (a user trial: 58 % off in float64
        with one state in units 100× smaller, a filter that is not scale-equivariant). And
        ``ρ``: the covariance's error contracts by about ``ρ²`` a step, so a step's change
        ``c`` leaves ``c ρ²/(1 − ρ²)`` to go; a slow mode (``ρ`` near 1) had stopped far from
        the fixed point (0.7 posterior standard deviations off in float32). In float32,
        where ``tol_ρ`` falls below 16 ε, the test must hold for
        :data:`~difffilter._riccati_host.STEADY_WINDOW` steps in a row (a step's change
        rounded to 0 had passed alone). Where round-off keeps a slow recursion moving the
        test may never hold: every step is computed."""
        n = K.shape[0]
        if K.device.type == "meta":  # shapes only: never converged
            return n
        # one test for both recursions, on host arrays (views of a host chunk's moments; a
        # copy from another device, one per chunk)
        last = (None, None) if self._last_gain is None else (self._last_gain, self._cov)
        F, H = self._mats[0], self._mats[2]
        keep = steps_to_keep(*map(_host_view, (K, P, *last, F, H)), self._tol)
        if keep is None:
            return n
        self.converged = True
        return keep

    def _step_maps(self) -> tuple[Tensor, Tensor, Tensor] | None:
        """The ``j``-step maps ``E(j) = e ⊗ … ⊗ e`` (``j`` times) of the scan element ``e``
        of one step (:func:`~difffilter.parallel_kalman.covariance_elements`) for ``j = 1 …
        BLOCK``: ``(A, C, J)``, each ``[BLOCK, dx, dx]``; made once, by doubling, ``E(i + m)
        = E(i) ⊗ E(m)`` for ``i = 1 … m`` (the elements are all equal, so any grouping is
        theirs). ``None`` where ``H Q Hᵀ + R`` is not positive definite (the element needs
        its inverse; the recursion's ``S_k`` may still be, through ``P⁻_k``)."""
        if self._maps is None:
            F, _, H, Ht, Q, R, _, _ = self._mats
            S = H @ Q @ Ht + R
            if S.device.type != "meta" and torch.linalg.cholesky_ex(S).info.item():
                self._maps = ()
                return None
            maps = tuple(m.unsqueeze(0) for m in covariance_elements(F, Q, H, R)[0])
            while maps[0].shape[0] < self.BLOCK:
                more, _, _ = combine_covariance(maps, tuple(m[-1] for m in maps))
                maps = tuple(torch.cat(pair) for pair in zip(maps, more))
            self._maps = tuple(m[: self.BLOCK] for m in maps)
        return self._maps or None


def riccati_step(
    cov: Tensor, F: Tensor, Ft: Tensor, H: Tensor, Ht: Tensor, Q: Tensor, R: Tensor,
    eye_x: Tensor, eye_y: Tensor,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:  # fmt: skip
    """One step of the covariance recursion of one unbatched model (module docstring):
    ``P_{k−1} → (P⁻_k, P_k, K_k, S_k, L_k, L_k⁻¹)``, every matrix ``[d, d]`` (``Ft``, ``Ht``:
    the transposes; ``eye_x``, ``eye_y``: identities of ``dx`` and ``dy``), or the same
    step from each of a batch ``P [n, dx, dx]`` (:func:`riccati_chunk`).

    The Gaussian core's blocks (:func:`~difffilter.gaussian.predict_covariance`,
    :func:`~difffilter.gaussian.kalman_gain`, :func:`~difffilter.gaussian.joseph_covariance`)
    written out: fused multiply-adds (``addmm``), one symmetrisation per covariance, the
    Cholesky factor checked with one read (the jittered factorisation, or a clear error,
    only when it fails), and the gain from the whitening ``L⁻¹`` that the evidence needs
    anyway (``K = P⁻Hᵀ L⁻ᵀ L⁻¹``: two products instead of a Cholesky solve). On ``4 × 4``
    matrices each call is a few microseconds of dispatch, so their number is the cost (180
    → about 75 µs per step on the 2-core CPU); the numbers equal the blocks' up to
    round-off (tests: 1e-12). Differentiable.
    """
    pred_cov = _symmetric(_add_product(Q, F @ cov, Ft))  # F P Fᵀ + Q
    cross = pred_cov @ Ht  # P⁻ Hᵀ
    S = _symmetric(_add_product(R, H, cross))  # H P⁻ Hᵀ + R
    chol, info = torch.linalg.cholesky_ex(S)
    if S.device.type != "meta" and (info.item() if info.dim() == 0 else info.any().item()):
        # not numerically positive definite: jitter, or a clear error
        chol = safe_cholesky(S, name=INNOVATION_COV)
    whiten = torch.linalg.solve_triangular(chol, eye_y.expand_as(chol), upper=False)  # L⁻¹
    K = (cross @ whiten.mT) @ whiten  # P⁻ Hᵀ S⁻¹ with S⁻¹ = L⁻ᵀ L⁻¹
    i_kh = _add_product(eye_x, K, H, subtract=True)  # I − K H
    # Joseph form (I − K H) P⁻ (I − K H)ᵀ + K R Kᵀ
    cov = _symmetric(_add_product((K @ R) @ K.mT, i_kh @ pred_cov, i_kh.mT))
    return pred_cov, cov, K, S, chol, whiten


def riccati_chunk(
    cov: Tensor, maps: tuple[Tensor, Tensor, Tensor], blocks: int, F: Tensor, Ft: Tensor,
    H: Tensor, Ht: Tensor, Q: Tensor, R: Tensor, eye_x: Tensor, eye_y: Tensor,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:  # fmt: skip
    """``n = blocks · m`` steps of the covariance recursion at once (module docstring): from
    ``P_s`` (``cov [dx, dx]``) and the ``j``-step maps ``E(1), …, E(m)`` (``maps``, each of
    ``A, C, J`` ``[m, dx, dx]``: :meth:`GainSchedule._step_maps`), the moments of steps
    ``s+1 … s+n`` as :func:`riccati_step` returns them, each with a leading ``[n]``::

        E(j)(P) = A_j (I + P J_j)⁻¹ P A_jᵀ + C_j                (P_{s+j} = E(j)(P_s))
        P_{s+im} = E(m)(P_{s+(i−1)m})                          i = 1 … blocks − 1 (in turn)
        P_{s+im+j} = E(j)(P_{s+im})                            all i, j = 1 … m − 1 (at once)
        (P⁻, P, K, S, L, L⁻¹)_{s+t} = riccati_step(P_{s+t−1})  t = 1 … n (batched)

    The same numbers as ``n`` calls of :func:`riccati_step` up to round-off (tests:
    1e-12), in about 40 operations on batches and ``6 (blocks − 1)`` on ``[d, d]``
    matrices instead of ``25 n`` of them."""
    A, C, J = maps
    starts = [cov]
    for _ in range(blocks - 1):  # the blocks' first covariances, one map of m steps each
        starts.append(_apply_map(starts[-1], A[-1], C[-1], J[-1], eye_x))
    starts = torch.stack(starts).unsqueeze(1)  # [blocks, 1, dx, dx]
    inner = _apply_map(starts, A[:-1], C[:-1], J[:-1], eye_x)
    previous = torch.cat([starts, inner], 1).flatten(0, 1)
    return riccati_step(previous, F, Ft, H, Ht, Q, R, eye_x, eye_y)


def riccati_steps(
    cov: Tensor, n: int, F: Tensor, Ft: Tensor, H: Tensor, Ht: Tensor, Q: Tensor, R: Tensor,
    eye_x: Tensor, eye_y: Tensor,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:  # fmt: skip
    """``n`` steps of :func:`riccati_step` from ``P_s`` (``cov [dx, dx]``), one at a time
    (differentiable step by step), stacked as :func:`riccati_chunk` returns them."""
    steps = []
    for _ in range(n):  # the covariance recursion: small unbatched steps, not an estimator loop
        steps.append(riccati_step(cov, F, Ft, H, Ht, Q, R, eye_x, eye_y))
        cov = steps[-1][1]
    return tuple(torch.stack(field) for field in zip(*steps))


def half_log_det(chol: Tensor) -> Tensor:
    """``Σ log diag L`` ``[...]`` of Cholesky factors ``L [..., d, d]`` (``½ log det S``)."""
    return chol.diagonal(dim1=-2, dim2=-1).log().sum(-1)


def _apply_map(cov: Tensor, A: Tensor, C: Tensor, J: Tensor, eye_x: Tensor) -> Tensor:
    """``E(P) = A (I + P J)⁻¹ P Aᵀ + C``, symmetrised (broadcasting ``[..., d, d]``)."""
    lhs = eye_x + cov @ J  # of the broadcast shape (``torch.broadcast_shapes`` costs more)
    if cov.shape != lhs.shape:
        cov = cov.expand(lhs.shape)
    return _symmetric(A @ torch.linalg.solve_ex(lhs, cov)[0] @ A.mT + C)


def _add_product(c: Tensor, a: Tensor, b: Tensor, *, subtract: bool = False) -> Tensor:
    """``c ± a b``: one fused ``addmm`` for matrices (the one-step recursion, where each
    call is dispatch), a product and a sum for a batch of them (a chunk)."""
    if a.dim() == 2 and b.dim() == 2:
        return torch.addmm(c, a, b, alpha=-1.0 if subtract else 1.0)
    return c - a @ b if subtract else c + a @ b


def _source_versions(model, mats) -> tuple[tuple[Tensor, tuple | Tensor], ...]:
    """``(tensor, stamp)`` of every tensor the schedule's moments may be made from: the
    matrices and the prior covariance as the model gave them, every parameter and buffer
    of the model itself (its submodules' too) and the tensors of its noise models and
    prior. The model's own: a subclass may make a matrix from a tensor of its own at every
    read (``F = expm(A dt)`` of a buffer ``A``), which the returned matrix is not, and an
    in-place write into it had gone unseen (a KF trial: the old ``F``, the mean 0.1 and the
    covariance 0.40 off). The prior: a ``k = 0`` carry kept as a start point holds its
    covariance, and after ``model.initial.cov.copy_(…)`` stepped with the schedule of the
    old one (8.9 off). A tensor kept as a plain attribute, not registered, and a number
    (``model.dt = 0.3``) go unseen. The stamp is the tensor's version, or, for an inference
    tensor (a model built under ``torch.inference_mode()``), which keeps none, a copy of
    its values (:func:`_unchanged`): such tensors had been left out, and a model built so
    and written in place (``model.F.copy_(…)``) kept its old gains without a word (a
    core-filter trial: a covariance 0.26 off)."""
    tensors = [m for m in mats if m is not None]
    # (a Module's parameters and buffers hold its noise models' and prior's, submodules)
    parts = [model] if isinstance(model, torch.nn.Module) else [
        getattr(model, name, None) for name in ("process_noise", "measurement_noise", "initial")
    ]  # fmt: skip
    for part in parts:
        if isinstance(part, torch.nn.Module):
            tensors += [*part.parameters(), *part.buffers()]
    unique = {id(t): t for t in tensors}
    return tuple((t, _stamp(t)) for t in unique.values())


def _stamp(t: Tensor) -> tuple | Tensor:
    """``(version, memory, requires_grad)`` of ``t``, or for an inference tensor (it keeps no
    version) a copy of its values. The memory: a new tensor under the old object
    (``F.data = new``, ``torch.nn.utils.vector_to_parameters``) keeps the version counter,
    and its old gains had gone on (0.67 off a Kalman filter's mean); ``requires_grad``: a
    tensor made to require one since (``F.requires_grad_()``) is to be differentiated
    through the covariances, which a schedule computed without autograd is not (a
    gradient 1.5 off). A write in place through ``.data`` (``F.data.copy_(new)``) moves
    neither: write through the tensor itself under ``torch.no_grad()``, or assign it."""
    if t.is_inference():
        return t.detach().clone()
    return t._version, t.data_ptr(), t.requires_grad


#: A stamp no tensor matches (a version below any counter's, and below the ``-1`` of an
#: inference tensor's :func:`_version`): what a copy stamps where the original had changed.
_STALE = -2


def _plain_stamps(sources) -> tuple[tuple[Tensor, ...], list[tuple]] | None:
    """``(tensors, stamps)`` of ``(tensor, stamp)`` pairs where every stamp is a ``(version,
    memory, requires_grad)`` tuple (:func:`_stamp`; compared as one list), else ``None``."""
    if not all(type(stamp) is tuple for _, stamp in sources):
        return None
    return tuple(t for t, _ in sources), [stamp for _, stamp in sources]


def _unchanged(t: Tensor, stamp: tuple | int | Tensor) -> bool:
    """Whether ``t`` is as it was stamped (:func:`_stamp`): the same version, memory and
    ``requires_grad``, or for an inference tensor the same values (a comparison: it has no
    version to read)."""
    if isinstance(stamp, tuple):  # (an inference tensor has no version to read)
        return (t._version, t.data_ptr(), t.requires_grad) == stamp
    if isinstance(stamp, int):  # _STALE
        return False
    return t.shape == stamp.shape and bool(torch.equal(t, stamp))


def _same(a: Tensor | None, b: Tensor | None) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return (a.dtype == b.dtype and a.device == b.device and a.shape == b.shape
            and bool(torch.equal(a.detach(), b.detach())))  # fmt: skip


class OutputsWritten(Exception):
    """:meth:`GainSchedule.filter_step` of measurement ``k`` (its ``args[0]``) would use a
    ``P⁻`` or ``S`` written in place since a step's output handed it out
    (:meth:`GainSchedule.outputs_intact`): the Kalman filter's step takes the general update."""


def _out_versions(m: SharedMoments) -> tuple[int, int]:
    """The versions of the moments' ``P⁻`` and ``S`` (what a step's output hands out besides
    ``P``)."""
    return _version(m.pred_cov), _version(m.innovation_cov)


def _version(t: Tensor) -> int:
    """``t``'s autograd version counter, ``-1`` for an inference tensor (it keeps none)."""
    return -1 if t.is_inference() else t._version


def _host_view(t: Tensor | None):
    """``t``'s values as a host array (a view in CPU memory; half precision as float32; a
    copy of a tensor a ``torch.func`` transform wraps), or ``None``."""
    if t is None:
        return None
    t = t.detach().cpu()
    t = t if t.dtype in (torch.float32, torch.float64) else t.float()
    try:
        return t.numpy()
    except RuntimeError:  # wrapped by a torch.func transform (no storage): its values
        return np.array(t.tolist(), dtype=np.float64 if t.dtype == torch.float64 else np.float32)


def _symmetric(matrix: Tensor) -> Tensor:
    """``(A + Aᵀ) / 2`` of a ``[d, d]`` matrix (:func:`~difffilter.linalg.symmetrize`'s
    numbers: the product by ½ is exact in either order)."""
    return (matrix + matrix.mT).mul_(0.5)
