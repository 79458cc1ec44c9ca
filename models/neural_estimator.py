"""The neural FDI estimator of Sargolzaei et al. (TII 2020), eqs (8)–(9).

One small network per area ``i`` maps a window of its own past attack estimates and
residuals to the current attack estimate::

    M̂ⁱ_k = Wⁱ σ(Vⁱ δⁱ_k),   σ = tanh                                          (8)
    δⁱ_k = [M̂ⁱ_{k−1}, …, M̂ⁱ_{k−a}, eⁱ_{k−ℓ}, …, eⁱ_{k−ℓ−b+1}]                   (9)

with ``Wⁱ [d, h]``, ``Vⁱ [h, d(a+b)]`` and no biases (as in the paper). ``a = 0`` leaves the
past estimates out (no recurrence: the estimate answers from the residuals alone). ``ℓ`` (the residual
lag) is the wrapper's business (:mod:`difffilter.fdi.neural`): the paper
uses ``ℓ = 1``. Each area also has an optional detection head, a logistic read-out of the
squared hidden units, ``pⁱ_k = sigmoid(cⁱ + Pⁱ σ(Vⁱ δⁱ_k)²)``, the "attack probability";
only gradient training fits it (the EKF of eqs 10–14 trains ``ζⁱ = [Wⁱ, Vⁱ]`` alone). The
squares matter: without biases every hidden unit is an odd function of ``δ``, so a linear
read-out of them could not respond alike to an attack and its negative.

Initial weights: Algorithm 1 draws them in ``[0, 1]``; full-scale weights saturate the
tanh units and make the recurrent map (``M̂`` feeds back into ``δ``) unstable, so they are
``s·U[0, 1]`` with a configurable ``s`` (``init="uniform01"``), or ``U[−s, s]``
(``init="symmetric"``).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import numbers
import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor, nn

from difffilter._checks import Choice, check_finite_number

from .atomic_write import save_torch_atomically

__all__ = ["AreaNetwork", "WeightInit", "NeuralFDIEstimator", "EstimatorCard"]


def _check_int(value, name, minimum=1):
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}; got {value!r}")


def _bmv(M: Tensor, v: Tensor) -> Tensor:
    """``M_n v_n`` for ``M [N, a, b]``, ``v [N, b]`` → ``[N, a]`` (one batched GEMM; the
    same numbers as ``einsum("nab,nb->na")`` at half the cost per call)."""
    return torch.bmm(M, v.unsqueeze(-1)).squeeze(-1)


class AreaNetwork(nn.Module):
    """One area's ``M̂ = W tanh(V δ)``: ``δ [..., in_dim]`` → ``[..., out_dim]``.

    The template the EKF-over-parameters trainer calls functionally with one parameter set
    per run (``W [out_dim, hidden]``, ``V [hidden, in_dim]``).
    """

    def __init__(
        self,
        in_dim: int,
        hidden: int,
        out_dim: int,
        in_scale: Tensor | None = None,
        dtype=torch.float64,
    ):
        super().__init__()
        self.W = nn.Parameter(torch.zeros(out_dim, hidden, dtype=dtype))
        self.V = nn.Parameter(torch.zeros(hidden, in_dim, dtype=dtype))
        scale = torch.ones(in_dim, dtype=dtype) if in_scale is None else in_scale.to(dtype)
        self.register_buffer("in_scale", scale.clone())

    def forward(self, delta: Tensor) -> Tensor:
        return torch.tanh((delta / self.in_scale) @ self.V.T) @ self.W.T

    # Closed forms used by difffilter.param_ekf instead of torch.func (same values, a
    # fraction of the cost: the online learners call them at every step of every run).
    def batched_forward(self, params: dict[str, Tensor], delta: Tensor) -> Tensor:
        """``W_n tanh(V_n δ_n)`` for per-run weights ``W [N, m, h]``, ``V [N, h, in]``, ``δ [N, in]``."""
        h = torch.tanh(_bmv(params["V"], delta / self.in_scale))
        return _bmv(params["W"], h)

    def batched_jacobian(self, params: dict[str, Tensor], delta: Tensor) -> tuple[Tensor, Tensor]:
        """Output ``[N, m]`` and ``∂out/∂[vec W, vec V]`` ``[N, m, m·h + h·in]`` (row-major).

        ``∂out_i/∂W_kj = 1[i = k]·h_j`` and ``∂out_i/∂V_jl = W_ij (1 − h_j²) δ̃_l``: eq. (13).
        """
        W, V = params["W"], params["V"]
        N, m, hid = W.shape
        x = delta / self.in_scale
        h = torch.tanh(_bmv(V, x))
        out = _bmv(W, h)
        eye = torch.eye(m, dtype=W.dtype, device=W.device)
        d_w = (eye[None, :, :, None] * h[:, None, None, :]).reshape(N, m, m * hid)
        d_v = ((W * (1.0 - h * h)[:, None, :])[..., None] * x[:, None, None, :]).reshape(N, m, -1)
        return out, torch.cat([d_w, d_v], dim=-1)


class WeightInit(Choice):
    """Initial weights: ``s·U[0, 1]`` (Algorithm 1 of the LFC paper) or ``U[−s, s]``."""

    UNIFORM01 = "uniform01"
    SYMMETRIC = "symmetric"


class NeuralFDIEstimator(nn.Module):
    """Per-area networks ``M̂ⁱ = Wⁱ tanh(Vⁱ δⁱ)`` (eqs 8–9), stacked over areas.

    Args:
        num_areas: ``J`` (2 for the two-area LFC).
        area_dim: ``d``, measured channels per area (5).
        a, b: number of past attack estimates and residuals in ``δ`` ([DEF] 3 and 3).
        hidden: tanh units per area ([DEF] 10).
        init_scale: ``s`` of the initial weights.
        init: :class:`WeightInit` (``s·U[0,1]``, Algorithm 1, or ``U[−s, s]``).
        detection_head: add the logistic attack-probability read-out.
        attack_scale, resid_scale: fixed input normalisation, ``δ̃ = δ / scale`` for the
            attack-estimate and the residual entries (1 and 1 = the paper). Residuals are of
            the order of the measurement noise (√Θ = 0.01) while attacks are of order 1, so
            gradient training uses ``resid_scale ≈ √Θ``; it is a reparametrisation of ``V``
            (``V δ̃ = (V D⁻¹) δ``), so eq. (8) is unchanged.
        resid_dim: residual channels per area in ``δ`` (default ``area_dim``, as in
            eq. 9; another value for one area whose attack lives elsewhere than its
            measurement, e.g. an actuator attack of ``du`` channels seen through ``dy``
            residuals).
        extra_inputs: per-step inputs appended to ``δ`` beyond eq. (9) (``0`` = the
            paper; :mod:`difffilter.models.learned_estimator` feeds the filter's
            statistics there: the received-measurement mask, the step's log-likelihood,
            the probability of attack), unscaled.
        seed: seed of the weight initialisation (a private ``torch.Generator``).

    Parameters: ``V [J, h, d·a + resid_dim·b + extra_inputs]``, ``W [J, d, h]`` and, with the head, ``P [J, h]`` and
    ``c [J]``.
    """

    def __init__(
        self,
        num_areas: int = 2,
        area_dim: int = 5,
        a: int = 3,
        b: int = 3,
        hidden: int = 10,
        init_scale: float = 0.05,
        init: WeightInit | str = WeightInit.UNIFORM01,
        detection_head: bool = True,
        attack_scale: float = 1.0,
        resid_scale: float = 1.0,
        resid_dim: int | None = None,
        extra_inputs: int = 0,
        seed: int = 0,
        dtype=torch.float64,
    ):
        super().__init__()
        for name, val in (
            ("num_areas", num_areas),
            ("area_dim", area_dim),
            ("b", b),
            ("hidden", hidden),
        ):
            _check_int(val, name)
        # a = 0: no past estimates in δ (a network that answers from the current residual
        # alone, as the tracking deception's i.i.d. packets call for)
        _check_int(a, "a", minimum=0)
        _check_int(extra_inputs, "extra_inputs", minimum=0)
        resid_dim = area_dim if resid_dim is None else resid_dim
        _check_int(resid_dim, "resid_dim")
        if num_areas > 1 and resid_dim != area_dim:
            raise ValueError("resid_dim must equal area_dim with several areas (eq. 9)")
        # finite too: an infinite scale had built a network of infinite weights or one that
        # reads every input as 0 (a fuzzing trial)
        init_scale = check_finite_number(init_scale, "init_scale", positive=True)
        init = WeightInit(init)
        self.num_areas, self.area_dim, self.a, self.b = num_areas, area_dim, a, b
        self.hidden = hidden
        self.extra_inputs, self.resid_dim = extra_inputs, resid_dim
        self.in_dim = area_dim * a + resid_dim * b + extra_inputs
        self.attack_scale = check_finite_number(attack_scale, "attack_scale", positive=True)
        self.resid_scale = check_finite_number(resid_scale, "resid_scale", positive=True)
        scale = torch.cat(
            [
                torch.full((area_dim * a,), float(attack_scale), dtype=dtype),
                torch.full((resid_dim * b,), float(resid_scale), dtype=dtype),
                torch.ones(extra_inputs, dtype=dtype),
            ]
        )
        self.register_buffer("in_scale", scale)
        self.init_scale, self.init = float(init_scale), init
        g = torch.Generator().manual_seed(int(seed))

        def draw(*shape):
            u = torch.rand(*shape, generator=g, dtype=dtype)
            return init_scale * (u if init is WeightInit.UNIFORM01 else 2.0 * u - 1.0)

        self.V = nn.Parameter(draw(num_areas, hidden, self.in_dim))
        self.W = nn.Parameter(draw(num_areas, area_dim, hidden))
        self.detection_head = bool(detection_head)
        if detection_head:
            # Starts at p = sigmoid(-4) ≈ 0.018: "no attack" until trained.
            self.P = nn.Parameter(torch.zeros(num_areas, hidden, dtype=dtype))
            self.c = nn.Parameter(torch.full((num_areas,), -4.0, dtype=dtype))

    @property
    def channels(self) -> int:
        return self.num_areas * self.area_dim

    def config(self) -> dict:
        """Constructor arguments (for checkpoint cards)."""
        return {
            "num_areas": self.num_areas,
            "area_dim": self.area_dim,
            "a": self.a,
            "b": self.b,
            "hidden": self.hidden,
            "init_scale": self.init_scale,
            "init": self.init.value,
            "detection_head": self.detection_head,
            "attack_scale": self.attack_scale,
            "resid_scale": self.resid_scale,
            "resid_dim": self.resid_dim,
            "extra_inputs": self.extra_inputs,
        }

    def area_template(self) -> AreaNetwork:
        """An :class:`AreaNetwork` with this estimator's shapes and input scaling."""
        return AreaNetwork(
            self.in_dim, self.hidden, self.area_dim, in_scale=self.in_scale, dtype=self.V.dtype
        )

    def area_params(self) -> dict[str, Tensor]:
        """``{"W": [J, d, h], "V": [J, h, in]}``: the per-area ``ζⁱ`` of eq. (10)."""
        return {"W": self.W, "V": self.V}

    def hidden_units(self, delta: Tensor, V: Tensor | None = None) -> Tensor:
        """``tanh(Vⁱ δⁱ)``: ``delta [..., J, in]`` (``V [..., J, h, in]`` optional) → ``[..., J, h]``."""
        V = self.V if V is None else V
        return torch.tanh(_per_area(delta / self.in_scale, V))

    def forward(self, delta: Tensor, W: Tensor | None = None, V: Tensor | None = None):
        """Attack estimate and attack-probability logit.

        ``delta [..., J, d(a+b)]`` → ``(M̂ [..., J, d], logit [..., J])``; the logit is
        ``None`` without a detection head. ``W``/``V`` override the weights (per-run
        weights ``[..., J, d, h]``/``[..., J, h, in]`` of an online learning rule).
        """
        if delta.shape[-2:] != (self.num_areas, self.in_dim):
            raise ValueError(
                f"delta must have shape [..., {self.num_areas}, {self.in_dim}]; got {tuple(delta.shape)}"
            )
        h = self.hidden_units(delta, V)
        attack = _per_area(h, self.W if W is None else W)
        logit = (self.c + (self.P * h * h).sum(-1)) if self.detection_head else None
        return attack, logit


def _per_area(x: Tensor, M: Tensor) -> Tensor:
    """``Mⁱ xⁱ`` for every area: ``x [..., J, n]``, ``M [J, m, n]`` (shared) or
    ``[..., J, m, n]`` (per run) → ``[..., J, m]``. Shared weights take one GEMM per area
    over all runs (a broadcast batched product would expand ``M`` to every run)."""
    if M.dim() > 3 or x.dim() < 3:
        return (M @ x.unsqueeze(-1)).squeeze(-1)
    lead, (J, n) = x.shape[:-2], x.shape[-2:]
    out = torch.bmm(x.reshape(-1, J, n).transpose(0, 1), M.transpose(-1, -2))  # [J, N, m]
    return out.transpose(0, 1).reshape(lead + (J, M.shape[-2]))


# -- checkpoints -----------------------------------------------------------------------------


#: The card's options that change how the estimator runs (``difffilter-train calibrate``
#: records them beside the threshold it chose: the threshold is for them).
RUN_OPTIONS = ("restart", "confirm", "reject")


@dataclass(frozen=True)
class EstimatorCard:
    """What evaluation needs beside a trained network's weights: one typed card for
    every checkpoint (stored in the checkpoint as ``"observer"`` and in its JSON card).

    Attributes:
        scenario_family: the family it was trained for (``"four_tank"``, ``"lfc"``, …;
            ``None``: unknown, no registered estimator takes it).
        scenario: the training scenario's name.
        filter: the filter it runs in: ``"kf"``, ``"ekf"``, ``"ukf"`` or ``"pf"``.
        trainer: ``"grad"`` (gradient descent through the filter) or ``"ekf"`` (the EKF
            over its weights).
        channel: the attack channel it compensates (``"sensor"``, ``"actuator"``,
            ``"replacement"``).
        residual: the residual history it reads (``"innovation"``, ``"predicted"``,
            ``"lagged"``: :class:`~difffilter.models.learned_estimator.Residual`).
        standardize: whether it reads innovations divided by ``√diag S``.
        features: the filter statistics it reads beside them.
        threshold: its alarm threshold; target_false_alarm_rate: what it was chosen for.
        dt: the sampling time it was trained at; num_particles: the training filter's.
        poa_eta: the ``"poa"`` feature's ``η``.
        estimator: the registry name it is evaluated as (``pf_nn_grad``, ``kf_nn_grad``, …).
        gating: whether it may also drop a measurement with its probability of attack
            (:class:`~difffilter.fdi.neural.NeuralCompensation`'s ``gating``).
        compensation: what the filter subtracts, ``"full"`` (``â``) or ``"detected"``
            (each area's estimate times its probability of attack).
        restart: the false-alarm rate of the χ² test of the uncompensated copy whose quiet
            steps restart the compensated filter, or ``None``
            (:class:`~difffilter.fdi.neural.NeuralCompensation`'s ``restart``).
        confirm: the rate of the copy's χ² test that must alarm with the network for its
            score to count (``NeuralCompensation``'s ``confirm``; needs ``restart``), or
            ``None``: the network's score alone.
        reject: the rate of the χ² test of the compensated innovation ``ν_k − â_k`` where
            it fails, the compensated filter keeps its prediction
            (``NeuralCompensation``'s ``reject``), or ``None``: never.
    """

    scenario_family: str | None = None
    scenario: str | None = None
    filter: str = "pf"
    trainer: str = "grad"
    channel: str = "sensor"
    residual: str = "innovation"
    standardize: bool = True
    features: tuple[str, ...] = ()
    threshold: float = 0.5
    target_false_alarm_rate: float | None = None
    dt: float | None = None
    num_particles: int | None = None
    poa_eta: float | None = None
    estimator: str | None = None
    gating: bool = False
    compensation: str = "full"
    restart: float | None = None
    confirm: float | None = None
    reject: float | None = None
    extra: dict = field(default_factory=dict, compare=False)

    def __post_init__(self):
        # a card read from a file is what the estimator runs with: a NaN threshold had loaded
        # without a word and never alarmed, "no" had read as standardize = True (a trial)
        t = self.threshold
        if isinstance(t, bool) or not isinstance(t, numbers.Real) or math.isnan(t):
            raise ValueError(f"threshold must be a number (±inf allowed); got {t!r}")
        for name in ("standardize", "gating"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name} must be true or false; got {getattr(self, name)!r}")
        for name in ("target_false_alarm_rate", "restart", "confirm", "reject"):
            rate = getattr(self, name)
            if rate is not None and not (
                isinstance(rate, numbers.Real) and not isinstance(rate, bool) and 0 < rate < 1
            ):
                raise ValueError(f"{name} must be a rate in (0, 1) or null; got {rate!r}")
        n = self.num_particles
        if n is not None and (isinstance(n, bool) or not isinstance(n, numbers.Integral) or n < 1):
            raise ValueError(f"num_particles must be a positive integer or null; got {n!r}")
        # (a NaN dt or η was written, and the pair then refused at every load as "dt = nan
        # there, nan inside", NaN being unequal to itself: a trial of the cards)
        # (η ≥ 0, as the PoA detector takes it: −1 had been taken here and refused only where
        # the estimator was built, a review)
        for name, bound, ok in (
            ("dt", "> 0", lambda v: v > 0),
            ("poa_eta", ">= 0", lambda v: v >= 0),
        ):
            v = getattr(self, name)
            if v is not None and (isinstance(v, bool) or not isinstance(v, numbers.Real)
                                  or not math.isfinite(v) or not ok(v)):  # fmt: skip
                raise ValueError(f"{name} must be a finite number {bound} or null; got {v!r}")
        if "poa" in self.features and self.poa_eta is None:  # (refused only where the
            # estimator was built, as η = −1 had been: a review)
            raise ValueError("poa_eta must be a number >= 0 where features include 'poa' "
                             "(the PoA feature's threshold η); got null")  # fmt: skip

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["features"] = list(self.features)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> EstimatorCard:
        """A card from its dict, including the older layouts: an LFC observer
        ``{"kind": "kalman", "residual_lag": ℓ, "dt": Δt}`` (the Kalman filter, raw
        residuals, ``ℓ = 0`` → ``"predicted"``, ``1`` → ``"lagged"``) and the task's
        ``{"kind": <filter>, …}``."""
        d = dict(d)
        kind = d.pop("kind", None)
        lag = d.pop("residual_lag", None)
        if kind == "kalman" or (kind is None and lag is not None):  # the LFC module's exports
            d.setdefault("scenario_family", "lfc")
            d.setdefault("scenario", "lfc_random_attacks")
            d.setdefault("filter", "kf")
            d.setdefault("standardize", False)
            d.setdefault("residual", "predicted" if int(lag or 0) == 0 else "lagged")
            d.setdefault("estimator", "kf_nn_grad")
        elif kind is not None:
            d.setdefault("filter", kind)
        names = {f.name for f in dataclasses.fields(cls)}
        extra = {**d.pop("extra", {}), **{k: v for k, v in d.items() if k not in names}}
        d = {k: v for k, v in d.items() if k in names}
        d["features"] = tuple(d.get("features") or ())
        return cls(**d, extra=extra)


CHECKPOINT_FORMAT = "difffilter.neural_fdi_estimator/1"
_CONFIG_TYPES = {
    "num_areas": int,
    "area_dim": int,
    "a": int,
    "b": int,
    "hidden": int,
    "init_scale": float,
    "init": str,
    "detection_head": bool,
    "attack_scale": float,
    "resid_scale": float,
    "resid_dim": int,
    "extra_inputs": int,
}


def checkpoint_sha256(path) -> str:
    """Hex sha256 digest of the file at ``path`` (read in 1 MiB chunks)."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def checkpoint_training_scenario(path) -> str | None:
    """The scenario an estimator checkpoint's network was trained on: its card's
    ``scenario`` (the name its training was given: a registered scenario, or a YAML file's
    ``name:``), from an export's ``observer`` or a Lightning checkpoint's
    ``difffilter_observer``, read as :class:`EstimatorCard` reads it (an older card's
    default included); ``None`` where the file holds no card or does not load."""
    blob = None
    for mapped in (True, False):  # (a file of the legacy, non-zip format cannot be mapped)
        try:
            blob = torch.load(path, map_location="cpu", weights_only=True, mmap=mapped)
            break
        except Exception:  # (not a torch file: the loaders name it themselves)
            continue
    if not isinstance(blob, dict):
        return None
    observer = blob.get("observer") or blob.get("difffilter_observer")
    if not isinstance(observer, dict):
        return None
    try:
        scenario = EstimatorCard.from_dict(observer).scenario
    except Exception:  # (a card that does not read: the loader names it)
        scenario = observer.get("scenario")
    return None if scenario is None else str(scenario)


def weights_sha256(source) -> str:
    """Hex sha256 of a network's weights alone: each tensor's name, dtype, shape and bytes,
    in name order, as stored. ``source`` is an exported estimator's path (``ValueError``
    for a training run's Lightning checkpoint: export it first) or its ``state_dict``.

    The file's ``sha256`` also covers the card inside it (threshold, calibration), so a
    retrained network with the shipped weights has another file digest; this one is the
    same (the card's ``weights_sha256``). A network loaded in another dtype
    (:func:`load_estimator_checkpoint` gives float64) has other bytes: digest the file."""
    if isinstance(source, dict):
        state = source
    else:
        blob = torch.load(source, map_location="cpu", weights_only=True)
        if "pytorch-lightning_version" in blob:
            raise ValueError(f"ckpt: {source} is a training run's Lightning checkpoint; the "
                             "weights digest is of an exported estimator (difffilter-train "
                             "export it first)")  # fmt: skip
        state = blob["state_dict"]
    digest = hashlib.sha256()
    for name in sorted(state):
        tensor = state[name].detach().cpu().contiguous()
        digest.update(f"{name}|{tensor.dtype}|{tuple(tensor.shape)}|".encode())
        digest.update(tensor.view(torch.uint8).numpy().tobytes() if tensor.numel() else b"")
    return digest.hexdigest()


def save_estimator_checkpoint(
    path, estimator: NeuralFDIEstimator, card: EstimatorCard | dict | None = None,
    extra: dict | None = None,
) -> str:  # fmt: skip
    """Write a weights-only checkpoint: tensors and plain Python values, never a pickled module.

    Layout: ``{"format", "estimator_config", "observer" (the :class:`EstimatorCard` as a
    dict), "state_dict", "extra"}``; it loads with ``torch.load(path, weights_only=True)``.
    Returns the sha256 of the written file (for the card beside it, see
    :func:`load_estimator_checkpoint`). ``ValueError`` if a weight is not finite.
    """
    path = Path(path)
    state = {k: v.detach().cpu().clone() for k, v in estimator.state_dict().items()}
    _check_finite_weights(state, f"estimator to save at {path}")
    path.parent.mkdir(parents=True, exist_ok=True)
    blob = {
        "format": CHECKPOINT_FORMAT,
        "estimator_config": estimator.config(),
        "observer": card.to_dict() if isinstance(card, EstimatorCard) else dict(card or {}),
        "state_dict": state,
        "extra": dict(extra or {}),
    }
    # whole or not at all: ``calibrate --force`` rewrites a shipped checkpoint in place
    save_torch_atomically(path, blob)
    return checkpoint_sha256(path)


def _check_finite_weights(state: dict, what: str) -> None:
    """Every weight a finite floating-point tensor: a storage of another dtype (an int32
    ``V`` of a damaged file without a card) had been loaded as its integers, silently."""
    typed = [f"{k} ({v.dtype if isinstance(v, Tensor) else type(v).__name__})"
             for k, v in state.items()
             if not isinstance(v, Tensor) or not v.is_floating_point()]  # fmt: skip
    if typed:
        raise ValueError(f"ckpt: {what} holds weights that are no floating-point tensors: "
                         f"{', '.join(typed)}")  # fmt: skip
    bad = [
        f"{k} ({int((~torch.isfinite(v)).sum())} of {v.numel()})"
        for k, v in state.items()
        if isinstance(v, Tensor) and v.is_floating_point() and not bool(torch.isfinite(v).all())
    ]
    if bad:
        raise ValueError(f"ckpt: {what} holds non-finite (NaN/Inf) weights: {', '.join(bad)}")


def _verify_sha256(path: Path, expected_sha256: str | None) -> dict | None:
    """Compare ``path``'s sha256 with ``expected_sha256``, or with the card beside it;
    return that card (its JSON document), or ``None``."""
    source, info = "the expected_sha256 argument", None
    if expected_sha256 is None:
        card = path.with_suffix(".json")
        if not card.is_file():
            return None  # no card: nothing recorded to compare with (weights are still checked)
        try:
            info = json.loads(card.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise ValueError(
                f"ckpt: the card {card} beside {path} is not readable JSON ({exc})"
            ) from exc
        expected_sha256 = info.get("sha256") if isinstance(info, dict) else None
        if not isinstance(expected_sha256, str):
            raise ValueError(
                f"ckpt: the card {card} beside {path} records no sha256 of the checkpoint; "
                "re-export the checkpoint (its card then records one) or remove the stale card"
            )
        source = f"the card {card}"
    actual = checkpoint_sha256(path)
    if actual != expected_sha256.lower():
        raise ValueError(
            f"ckpt: {path} does not match the sha256 recorded in {source} (file corrupted or "
            f"replaced): expected {expected_sha256}, got {actual}"
        )
    return info


def _check_card_beside(path: Path, card: EstimatorCard, beside: dict | None) -> None:
    """The card beside ``path`` (its JSON document ``beside``) must say what the card inside
    the checkpoint says, which is the one that runs: a threshold edited in the JSON alone had
    been ignored without a word (a trial). ``export`` and ``calibrate`` write both."""
    observer = beside.get("observer") if isinstance(beside, dict) else None
    if not isinstance(observer, dict):
        return
    json_path = path.with_suffix(".json")
    try:
        stated = EstimatorCard.from_dict(observer)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"ckpt: the card {json_path} beside {path} is unreadable ({exc})") from exc
    if stated != card:
        differ = [f"{f.name} = {getattr(stated, f.name)!r} there, {getattr(card, f.name)!r} inside"
                  for f in dataclasses.fields(card)
                  if f.compare and getattr(stated, f.name) != getattr(card, f.name)]  # fmt: skip
        raise ValueError(
            f"ckpt: the card {json_path} beside {path} does not say what the checkpoint's own "
            f"card says ({'; '.join(differ)}); the checkpoint's card is the one that runs: "
            "change a threshold with difffilter-train calibrate (it writes both), or restore "
            "the JSON card"
        )


def is_exported_checkpoint(path) -> bool:
    """Whether ``path`` is a file written by :func:`save_estimator_checkpoint` (not a
    Lightning checkpoint); ``False`` for anything unreadable."""
    try:
        blob = torch.load(Path(path), map_location="cpu", weights_only=True)
    except Exception:  # unpickling errors come in many types
        return False
    return checkpoint_kind(blob) == "exported"


def checkpoint_kind(blob) -> str | None:
    """What a loaded checkpoint ``blob`` is: ``"exported"`` (:func:`save_estimator_checkpoint`),
    ``"lightning"`` (a training run's Lightning checkpoint) or ``None`` (neither)."""
    if not isinstance(blob, dict):
        return None
    if blob.get("format") == CHECKPOINT_FORMAT:
        return "exported"
    if "pytorch-lightning_version" in blob and "state_dict" in blob:
        return "lightning"
    return None


def _is_lightning_checkpoint(blob) -> bool:
    return checkpoint_kind(blob) == "lightning"


def _from_lightning(blob: dict, path: Path) -> dict:
    """The exported form of a Lightning checkpoint of a module holding ``self.estimator``
    (its ``hyper_parameters`` carry the estimator's settings, ``residual_lag`` and ``dt``)."""
    hp = blob.get("hyper_parameters") or {}
    prefix = "estimator."
    state = {k[len(prefix) :]: v for k, v in blob["state_dict"].items() if k.startswith(prefix)}
    if not state or not isinstance(hp, dict):
        raise ValueError(f"ckpt: the Lightning checkpoint {path} holds no neural FDI estimator")
    # A module may store its estimator's settings and what evaluation needs beside the
    # weights (difffilter.train.task does); otherwise they come from its hyperparameters.
    config = blob.get("difffilter_estimator_config") or {k: hp[k] for k in _CONFIG_TYPES if k in hp}
    observer = blob.get("difffilter_observer") or {
        "residual_lag": int(hp.get("residual_lag", 1)),
        "dt": float(hp.get("dt", 0.01)),
        "kind": "kalman",
    }
    return {
        "format": CHECKPOINT_FORMAT,
        "estimator_config": dict(config),
        "observer": dict(observer),
        "state_dict": state,
    }


def _unpickling_reason(exc: Exception) -> str:
    """torch's reason a file did not load, without its advice (to load it with
    ``weights_only=False``, which runs whatever the file holds, or to file an issue)."""
    text = str(exc)
    if "WeightsUnpickler error:" in text:
        text = text.split("WeightsUnpickler error:", 1)[1].split("Check the documentation")[0]
    reason = " ".join(text.split())
    return f"{type(exc).__name__}: {reason}" if reason else type(exc).__name__


def load_estimator_checkpoint(
    path, *, dtype=torch.float64, expected_sha256: str | None = None
) -> tuple[NeuralFDIEstimator, EstimatorCard]:
    """Load a checkpoint written by :func:`save_estimator_checkpoint`, or the estimator of
    a Lightning checkpoint of a training run (``<run>/checkpoints/*.ckpt``).

    Integrity: the file's sha256 is compared with ``expected_sha256`` when given, else
    with the ``"sha256"`` of the card beside it (``path`` with suffix ``.json``, written
    by ``ExportEstimator``) when that card exists; every weight must be finite.

    ``dtype``: the estimator's, ``torch.float32`` or ``torch.float64`` (or their names);
    ``None`` keeps the stored weights' (what an export or a recalibration writes back
    unchanged).

    Returns ``(estimator, card)`` (:class:`EstimatorCard`). ``FileNotFoundError`` if ``path`` does not
    exist; ``ValueError`` naming ``path`` if it is not such a checkpoint (wrong format,
    missing keys, shapes that do not match the stored configuration, a sha256 that does
    not match, non-finite weights).
    """
    if not isinstance(path, (str, os.PathLike)):  # (torch's words named no argument)
        raise TypeError(
            f"ckpt: the checkpoint's path must be a str or os.PathLike; got {type(path).__name__}"
        )
    # before the file is read: a name had been blamed on the file ("does not match its own
    # configuration"), and float16 or complex64 built a network of that dtype
    dtype = None if dtype is None else _weights_dtype(dtype)
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"ckpt: no checkpoint file at {path}")
    if path.suffix == ".json":  # the card beside a checkpoint: its sha256 did not match itself
        beside = path.with_suffix(".ckpt")
        raise ValueError(
            f"ckpt: {path} is a checkpoint's card (JSON), not the checkpoint: give {beside}"
            if beside.is_file()
            else f"ckpt: {path} is JSON (a card or a table) with no checkpoint beside it, not "
            "a checkpoint"
        )
    beside = _verify_sha256(path, expected_sha256)
    try:
        with warnings.catch_warnings():  # a file not saved by torch.save: its error says so
            warnings.filterwarnings("ignore", "Detected pickle protocol", UserWarning)
            blob = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # unpickling errors come in many types
        raise ValueError(
            f"ckpt: {path} is not a weights-only torch checkpoint ({_unpickling_reason(exc)})"
        ) from exc
    if _is_lightning_checkpoint(blob):
        blob = _from_lightning(blob, path)
    if not isinstance(blob, dict) or blob.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(
            f"ckpt: {path} is neither a {CHECKPOINT_FORMAT} checkpoint nor a Lightning "
            "checkpoint of a neural FDI estimator"
        )
    for key in ("estimator_config", "state_dict", "observer"):
        if key not in blob:
            raise ValueError(f"ckpt: {path} lacks the {key!r} entry")
    if not isinstance(blob["state_dict"], dict):
        raise ValueError(f"ckpt: {path} has a state_dict that is not a dict")
    # Corrupted bytes inside a tensor's storage still unpickle (as NaN or huge weights):
    # refuse non-finite ones before anything is evaluated with them.
    _check_finite_weights(blob["state_dict"], str(path))
    cfg = blob["estimator_config"]
    unknown = set(cfg) - set(_CONFIG_TYPES)
    if unknown:
        raise ValueError(f"ckpt: {path} has unknown estimator settings {sorted(unknown)}")
    try:
        kwargs = {k: _CONFIG_TYPES[k](v) for k, v in cfg.items()}
    except (TypeError, ValueError) as exc:
        raise ValueError(f"ckpt: {path} does not match its own configuration ({exc})") from exc
    for name, value in kwargs.items():  # (named with the file: the constructor would not)
        if isinstance(value, float) and not math.isfinite(value):
            raise ValueError(f"ckpt: {path} has a non-finite setting {name} = {value}")
    try:
        if dtype is None:  # the stored weights' own
            stored = [v.dtype for v in blob["state_dict"].values()
                      if isinstance(v, Tensor) and v.is_floating_point()]  # fmt: skip
            dtype = stored[0] if stored else torch.float32
        estimator = NeuralFDIEstimator(**kwargs, dtype=dtype)
        state = {
            k: v.to(dtype) if v.is_floating_point() else v for k, v in blob["state_dict"].items()
        }
        estimator.load_state_dict(state, strict=True)
    except (TypeError, RuntimeError) as exc:
        raise ValueError(f"ckpt: {path} does not match its own configuration ({exc})") from exc
    try:
        card = EstimatorCard.from_dict(blob["observer"])
    except (TypeError, ValueError) as exc:
        raise ValueError(f"ckpt: {path} has an unreadable card ({exc})") from exc
    _check_card_beside(path, card, beside)
    return estimator, card


def _weights_dtype(dtype) -> torch.dtype:
    """``dtype`` of :func:`load_estimator` as a torch floating dtype: ``torch.float32``,
    ``torch.float64`` or their names (a name was blamed on the file; float16 slipped by)."""
    named = {"float32": torch.float32, "float64": torch.float64, "double": torch.float64,
             "float": torch.float32}  # fmt: skip
    dtype = named.get(dtype, dtype) if isinstance(dtype, str) else dtype
    if dtype not in (torch.float32, torch.float64):
        raise ValueError(
            f"dtype must be torch.float32 or torch.float64 (the weights'); got {dtype!r}"
        )
    return dtype
