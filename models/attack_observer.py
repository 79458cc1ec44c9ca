"""Attack-compensating observers and the secure closed loop (Sargolzaei et al., TII 2020).

An observer (the discrete Kalman filter of eqs 5–7, or the Luenberger observer of the
paper's baseline) runs on the measurement with the estimated attack removed, and the
neural estimator of eqs (8)–(9) estimates the attack from its residuals. One step, at
time ``k`` with measurement ``z_k [B, n]`` and the previous input ``u_{k−1}``::

    x̂⁻_k = A_d x̂_{k−1} + B_d u_{k−1}                        (prediction; Σ⁻ for the KF)
    δ_k  = [M̂_{k−1}, …, M̂_{k−a}, residuals]                  (eq. 9, per area)
    M̂⁻_k = f_ζ(δ_k),   e_k = z_k − x̂⁻_k − M̂⁻_k              (eqs 5, 8: e = z − ẑ)
    [online learning: ζ ← EKF (eqs 10–14) or gradient step with e_k; M̂_k = f_ζ(δ_k)]
    x̂_k  = x̂⁻_k + G_k (z_k − M̂_k − x̂⁻_k)                    (G: Kalman gain or L_f)
    U_k  = −K₁ (z_k − M̂_k)                                    (eq. 17 with K₂ = 0)

Choices the paper leaves open (each a keyword, chosen on validation attacks):

* ``residual_lag`` ``ℓ``: which residuals ``δ`` holds. ``ℓ = 1`` is eq. (9): the last ``b``
  residuals ``e_{k−1} … e_{k−b}``. ``ℓ = 0`` adds the current a-priori residual
  ``r_k = z_k − x̂⁻_k − M̂_{k−1}`` (the residual if the attack kept its last estimate) and
  keeps ``r_k … r_{k−b+1}``: a frozen network then sees ``z_k`` before it estimates
  ``M̂_k``, which the paper's online EKF achieves through its weight update instead.
* ``subtract``: with online learning, whether the observer and controller use the
  re-evaluated estimate after the weight update (``"posterior"``, Algorithm 1's final
  "estimate the FDI attack from (8)") or the estimate before it (``"prior"``).

The controller is ``U = −K₁(Z − M̂)``: ``K₂ = L_s²/ε₂·C⁻¹`` has no given values
(docs/scenarios.md, LFC pitfalls). Without compensation (``compensate=False``) it is ``U = −K₁Z``,
the paper's "traditional controller".
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch
from torch import Tensor

from difffilter.gain_schedule import GainSchedule
from difffilter.param_ekf import OnlineGradientDescent, ParamEKF

from .neural_estimator import NeuralFDIEstimator, build_delta

__all__ = ["AttackObserver", "ObserverState", "ClosedLoop", "LoopState", "LoopRecord"]

LEARNING_RULES = (None, "ekf", "gradient")


@dataclass
class ObserverState:
    """Per-run observer state. ``mean [B, n]`` (x̂_{k−1}), ``k`` (index of the next
    measurement; the Kalman covariance Σ_k depends on ``k`` alone), ``attack_hist [B, a, n]``,
    ``resid_hist [B, b, n]`` (most recent first), ``learner`` (a :class:`ParamEKF` /
    :class:`OnlineGradientDescent` over runs × areas, or ``None``)."""

    mean: Tensor
    k: int
    attack_hist: Tensor
    resid_hist: Tensor
    learner: object | None = None

    def detach(self) -> ObserverState:
        return ObserverState(
            self.mean.detach(),
            self.k,
            self.attack_hist.detach(),
            self.resid_hist.detach(),
            self.learner,
        )


@dataclass
class StepOutput:
    """One observer step: ``attack [B, n]`` (M̂_k), ``mean [B, n]`` (x̂_k), ``pred_mean [B, n]``
    (x̂⁻_k), ``innovation [B, n]`` (z_k − M̂_k − x̂⁻_k), ``innovation_cov [n, n]`` (KF: Σ⁻+Θ;
    Luenberger: ``None``), ``logit [B, J]`` (attack-probability logit, or ``None``)."""

    attack: Tensor
    mean: Tensor
    pred_mean: Tensor
    innovation: Tensor
    innovation_cov: Tensor | None
    logit: Tensor | None


class AttackObserver:
    """Observer + neural attack estimator (+ optional online learning rule).

    Args:
        Ad, Bd: discrete plant ``[n, n]``, ``[n, m]``; the observer knows neither the load
            nor the attack ([DEF]: the load is an unknown input, as in eq. 2).
        Q, R: process and measurement noise covariances ``[n, n]`` (Kalman observer).
        kind: ``"kalman"`` (eqs 5–7 in discrete time, ``Σ(0) = init_cov·I``) or
            ``"luenberger"`` (fixed filter-form gain ``gain [n, n]``).
        network: the :class:`NeuralFDIEstimator` (``None``: no attack estimate, ``M̂ = 0``).
        learning: ``None`` (frozen network), ``"ekf"`` (eqs 10–14) or ``"gradient"``.
        learning_kwargs: passed to :class:`ParamEKF` / :class:`OnlineGradientDescent`
            (``lr``, ``init_cov``, ``init_noise``, ``process_noise``).
        residual_lag: ``ℓ ∈ {0, 1}`` (module docstring).
        subtract: ``"posterior"`` or ``"prior"`` (module docstring).
        init_cov: ``Σ(0)`` scale ([DEF] 1e-2).
    """

    def __init__(
        self,
        Ad: Tensor,
        Bd: Tensor,
        Q: Tensor,
        R: Tensor,
        *,
        kind: str = "kalman",
        gain: Tensor | None = None,
        network: NeuralFDIEstimator | None = None,
        learning: str | None = None,
        learning_kwargs: dict | None = None,
        residual_lag: int = 1,
        subtract: str = "posterior",
        init_cov: float = 1e-2,
    ):
        if kind not in ("kalman", "luenberger"):
            raise ValueError(f"kind must be 'kalman' or 'luenberger'; got {kind!r}")
        if kind == "luenberger" and gain is None:
            raise ValueError("kind='luenberger' needs gain= (the filter-form gain L_f [n, n])")
        if learning not in LEARNING_RULES:
            raise ValueError(f"learning must be one of {LEARNING_RULES}; got {learning!r}")
        if learning is not None and network is None:
            raise ValueError("learning needs a network to train")
        if residual_lag not in (0, 1):
            raise ValueError(f"residual_lag must be 0 or 1; got {residual_lag!r}")
        if subtract not in ("posterior", "prior"):
            raise ValueError(f"subtract must be 'posterior' or 'prior'; got {subtract!r}")
        if not init_cov > 0:
            raise ValueError(f"init_cov must be positive; got {init_cov!r}")
        self.Ad, self.Bd, self.Q, self.R = Ad, Bd, Q, R
        self.n = Ad.shape[0]
        self.kind, self.gain = kind, gain
        self.network, self.learning = network, learning
        self.learning_kwargs = dict(learning_kwargs or {})
        self.residual_lag, self.subtract = residual_lag, subtract
        self.init_cov = float(init_cov)
        self._gains = None  # the data-independent Kalman gains (gain_schedule)
        if network is not None and network.channels != self.n:
            raise ValueError(
                f"network estimates {network.channels} channels but the plant has {self.n}"
            )

    # -- state ---------------------------------------------------------------------------
    def init(self, num_runs: int, params: dict[str, Tensor] | None = None) -> ObserverState:
        """``x̂(0) = 0``, ``Σ(0) = init_cov·I``, empty histories, fresh per-run learner.

        ``params``: optional per-run initial weights of the learner ``{"W": [B, J, d, h],
        "V": [B, J, h, in]}`` (default: the network's own weights for every run).
        """
        dtype = self.Ad.dtype
        n = self.n
        a = self.network.a if self.network is not None else 1
        b = self.network.b if self.network is not None else 1
        learner = None
        if self.learning is not None:
            net = self.network
            template = net.area_template()
            start = {
                k: v.detach().to(dtype).expand((num_runs,) + v.shape)
                for k, v in net.area_params().items()
            }
            if params is not None:
                start.update({k: v.detach().to(dtype) for k, v in params.items()})
            cls = ParamEKF if self.learning == "ekf" else OnlineGradientDescent
            learner = cls(template, (num_runs, net.num_areas), params=start, **self.learning_kwargs)
        return ObserverState(
            mean=torch.zeros(num_runs, n, dtype=dtype),
            k=1,
            attack_hist=torch.zeros(num_runs, a, n, dtype=dtype),
            resid_hist=torch.zeros(num_runs, b, n, dtype=dtype),
            learner=learner,
        )

    # -- Kalman gains -------------------------------------------------------------------
    def observer_model(self):
        """The observer's :class:`difffilter.LinearGaussianModel` ``(A_d, I, Ξ, Θ, 0, Σ(0), B_d)``."""
        import difffilter

        n, dtype = self.n, self.Ad.dtype
        eye = torch.eye(n, dtype=dtype)
        return difffilter.LinearGaussianModel(
            self.Ad,
            eye,
            self.Q,
            self.R,
            torch.zeros(n, dtype=dtype),
            self.init_cov * eye,
            B=self.Bd,
        )

    @property
    def gain_schedule(self):
        """The observer's :class:`difffilter.gain_schedule.GainSchedule` (built on first use).

        Without lost measurements the Kalman covariance recursion (eq. 7 in discrete time)
        does not depend on the data, so difffilter runs it once and every run's mean
        update is the Kalman filter's exactly (tested against :func:`difffilter.kalman_step`).
        """
        if self._gains is None:
            self._gains = GainSchedule(self.observer_model())
        return self._gains

    def kalman_schedule(self, k: int) -> tuple[Tensor, Tensor]:
        """Kalman gain ``K_k [n, n]`` and innovation covariance ``S_k [n, n]`` of step ``k ≥ 1``."""
        return self.gain_schedule.gain(k)

    # -- one step ------------------------------------------------------------------------
    def step(
        self, state: ObserverState, z: Tensor, u_prev: Tensor
    ) -> tuple[ObserverState, StepOutput]:
        """Advance one sample: ``z [B, n]`` (measurement ``Z_k``), ``u_prev [B, m]`` (``U_{k−1}``).

        The Kalman observer predicts and updates through difffilter's
        :class:`~difffilter.gain_schedule.GainSchedule`; the Luenberger observer with its
        fixed gain."""
        kalman = self.kind == "kalman"
        if kalman:
            pred_mean = self.gain_schedule.predict(state.mean, u_prev)
        else:
            pred_mean = state.mean @ self.Ad.T + u_prev @ self.Bd.T
        net = self.network
        logit = None
        if net is None:
            attack = torch.zeros_like(z)
            resid_entry = z - pred_mean
        else:
            if self.residual_lag == 0:
                r_now = z - pred_mean - state.attack_hist[:, 0]
                resid_in = torch.cat([r_now[:, None], state.resid_hist[:, :-1]], dim=1)
            else:
                resid_in = state.resid_hist
            delta = build_delta(state.attack_hist, resid_in, net.num_areas)  # [B, J, in]
            if state.learner is None:
                attack_j, logit = net(delta)
                attack = attack_j.reshape(z.shape)
                e = z - pred_mean - attack
            else:
                target = (z - pred_mean).reshape(delta.shape[0], net.num_areas, net.area_dim)
                prior, e_j = state.learner.step(delta, target)
                e = e_j.reshape(z.shape)
                if self.subtract == "posterior":
                    attack_j = state.learner.predict(delta)
                else:
                    attack_j = prior
                attack = attack_j.reshape(z.shape)
                if net.detection_head:
                    V = state.learner.params()["V"]
                    _, logit = net(delta, V=V, W=state.learner.params()["W"])
            resid_entry = r_now if self.residual_lag == 0 else e
        y = z - attack
        if kalman:
            new_mean, innovation, innovation_cov = self.gain_schedule.update(pred_mean, y, state.k)
        else:
            innovation, innovation_cov = y - pred_mean, None
            new_mean = pred_mean + innovation @ self.gain.T
        a_hist = torch.cat([attack[:, None], state.attack_hist[:, :-1]], dim=1)
        r_hist = torch.cat([resid_entry[:, None], state.resid_hist[:, :-1]], dim=1)
        new_state = ObserverState(new_mean, state.k + 1, a_hist, r_hist, state.learner)
        return new_state, StepOutput(attack, new_mean, pred_mean, innovation, innovation_cov, logit)


@dataclass
class LoopState:
    """Closed-loop state: true plant state ``x [B, n]``, last input ``u [B, m]``, observer state,
    and the step index ``k`` of the next measurement."""

    x: Tensor
    u: Tensor
    observer: ObserverState
    k: int = 1

    def detach(self) -> LoopState:
        return LoopState(self.x.detach(), self.u.detach(), self.observer.detach(), self.k)


@dataclass
class LoopRecord:
    """Trajectories of a closed-loop run (time second): ``x, z, attack_est, mean,
    innovation [B, T, n]``, ``u [B, T, m]``, ``innovation_cov [T, n, n]`` or ``None``,
    ``logit [B, T, J]`` or ``None``."""

    x: Tensor
    z: Tensor
    u: Tensor
    attack_est: Tensor
    mean: Tensor
    innovation: Tensor
    innovation_cov: Tensor | None
    logit: Tensor | None

    @staticmethod
    def concat(records: list[LoopRecord]) -> LoopRecord:
        out = {}
        for f in fields(LoopRecord):
            vals = [getattr(r, f.name) for r in records]
            if vals[0] is None:
                out[f.name] = None
            else:
                dim = 0 if f.name == "innovation_cov" else 1
                out[f.name] = torch.cat(vals, dim=dim)
        return LoopRecord(**out)


class ClosedLoop:
    """Plant + attack + observer + secure controller, simulated batch-first.

    Args:
        plant: an :class:`~difffilter.models.lfc.LFCPlant` (``Ad, Bd, Fd, Q, R``).
        K1: LQR gain ``[m, n]``.
        observer: the :class:`AttackObserver`.
        compensate: ``U = −K₁(Z − M̂)`` (secure) or ``U = −K₁Z`` (traditional).

    ``run`` consumes externally drawn noise and attack tensors, so that every estimator
    sees the same random numbers (common random numbers).
    """

    def __init__(self, plant, K1: Tensor, observer: AttackObserver, *, compensate: bool = True):
        self.plant, self.K1, self.observer, self.compensate = plant, K1, observer, compensate

    def init(self, num_runs: int, params: dict[str, Tensor] | None = None) -> LoopState:
        """Zero plant state and input, fresh observer (``params``: per-run learner weights)."""
        dtype = self.plant.Ad.dtype
        n, m = self.plant.Bd.shape
        return LoopState(
            x=torch.zeros(num_runs, n, dtype=dtype),  # X(0) = 0 [DEF], known to the observers
            u=torch.zeros(num_runs, m, dtype=dtype),
            observer=self.observer.init(num_runs, params),
        )

    def run(
        self,
        state: LoopState,
        attack: Tensor,
        xi: Tensor,
        theta: Tensor,
        load: Tensor,
        *,
        progress=None,
    ) -> tuple[LoopState, LoopRecord]:
        """Simulate ``L`` steps from ``state``.

        ``attack [B or 1, L, n]`` (``α_k``), ``xi [B, L, n]`` (``ξ_{k−1}``, drives
        ``X_{k−1} → X_k``), ``theta [B, L, n]`` (``θ_k``), ``load [B or 1, 2]``
        (``ΔP_l``). ``progress``: an optional callable invoked once per step (tqdm.update).
        """
        B, L, n = xi.shape
        if theta.shape != xi.shape:
            raise ValueError(f"theta must have shape {tuple(xi.shape)}; got {tuple(theta.shape)}")
        if attack.dim() != 3 or attack.shape[1:] != (L, n):
            raise ValueError(
                f"attack must have shape [B or 1, {L}, {n}]; got {tuple(attack.shape)}"
            )
        x, u, obs = state.x, state.u, state.observer
        # Without autograd (evaluation) the trajectories go into buffers allocated once and
        # filled in place. Appending T small per-step tensors and stacking them at the end
        # left thousands of long-lived small blocks interleaved with each step's large
        # temporaries (the learners' Jacobians, ρ updates): the heap could not reuse or trim
        # the holes between them, so memory grew with every step and each allocation got
        # slower (time superlinear in the horizon). With autograd (TBPTT training) the
        # per-step tensors are graph nodes anyway; they are kept and stacked as before.
        keep_graph = torch.is_grad_enabled()
        keys = ("x", "z", "u", "attack_est", "mean", "innovation", "icov", "logit")
        rec: dict = {k: [] for k in keys} if keep_graph else dict.fromkeys(keys)
        for t in range(L):
            x = self.plant.step(x, u, load, xi[:, t])
            z = x + attack[:, t] + theta[:, t]
            obs, out = self.observer.step(obs, z, u)
            fb = z - out.attack if self.compensate else z
            u = -fb @ self.K1.T
            for key, val in (
                ("x", x),
                ("z", z),
                ("u", u),
                ("attack_est", out.attack),
                ("mean", out.mean),
                ("innovation", out.innovation),
                ("icov", out.innovation_cov),
                ("logit", out.logit),
            ):
                if keep_graph:
                    rec[key].append(val)
                elif val is not None:
                    if rec[key] is None:  # shapes are known at the first step
                        # innovation_cov [T, n, n] is shared by the runs; the rest [B, T, ...]
                        shape = (L, *val.shape) if key == "icov" else (B, L, *val.shape[1:])
                        rec[key] = val.new_empty(shape)
                    if key == "icov":
                        rec[key][t] = val
                    else:
                        rec[key][:, t] = val
            if progress is not None:
                progress(1)
        if keep_graph:
            rec = {
                k: None if v[0] is None else torch.stack(v, 0 if k == "icov" else 1)
                for k, v in rec.items()
            }
        record = LoopRecord(
            x=rec["x"],
            z=rec["z"],
            u=rec["u"],
            attack_est=rec["attack_est"],
            mean=rec["mean"],
            innovation=rec["innovation"],
            innovation_cov=rec["icov"],
            logit=rec["logit"],
        )
        return LoopState(x, u, obs, state.k + L), record
