"""One training task for any registered scenario: the neural FDI estimator inside
difffilter's own filter, trained by gradient descent through it or by the EKF over its
weights.

:class:`ScenarioDataModule` simulates the scenario (its plant, attack and schedule) from
seeded named streams: training batch ``i`` of epoch ``e`` from seed ``(train_seed, e, i)``,
one fixed validation batch from ``val_seed`` (the scenario's attack distribution on
unseen draws: the operating threshold is chosen there), and ``test`` on exactly the runs
``difffilter-eval <scenario> --seed test_seed`` scores.

:class:`FilterEstimatorTask` runs :func:`~difffilter.models.learned_estimator.
neural_particle_filter` (``filter="pf"``, with a differentiable resampler) or
:func:`~difffilter.models.learned_estimator.neural_gaussian_filter` (``"kf"``, ``"ekf"``,
``"ukf"``) on each batch and minimises::

    attack_weight·mean‖â_k − a_k‖² + bce_weight·BCE(logit_k, l_k) + state_weight·mean‖x̂_k − x_k‖²/σ_x²

(``a_k`` the injected attack, ``l_k`` its flag, ``σ_x²`` the prior variance of the state):
the attack loss back-propagates through the filter too, since ``â_k`` reads innovations
that earlier estimates shaped. A replacement attack (the tracking deception, ``a_k = ξ_k −
y_k`` with ``ξ`` anywhere in a box) has no additive signal to subtract: the PF weighs the
particles with the mixture likelihood of the network's probability
(:mod:`difffilter.models.learned_estimator`, ``channel="replacement"``), ``â_k = p_k ν_k``,
and ``attack_weight = 0`` leaves the training to the BCE and the state loss through the
filter. Validation and test run the filter as the evaluation does
(systematic resampling at every step) and pick the alarm threshold on the validation
batch: the ``1 − target_false_alarm_rate`` quantile of ``p_k`` over its attack-free steps.

``trainer="ekf"`` trains the weights ``ζ = [W, V]`` (eq. 10) by the EKF of eqs (11)–(14)
instead (:class:`~difffilter.param_ekf.EKFOptimizer`, Lightning's manual optimisation):
the filter runs on the batch with the current weights (no gradients, systematic
resampling), records every step's network input ``δ_k``, and then, step by step in time,
one EKF update takes the batch's ``B`` samples ``(δ_k, a_k)`` as one measurement of the
network's output, ``H_k = ∂f(ζ, δ_k)/∂ζ`` in closed form (eq. 13; unreceived entries
carry no information). The measurement is the injected attack of the simulated runs
(the paper's online rule measures the residual, having no attack to learn from at run
time). Such a network has no detection head; it alarms on its standardised attack
estimate (:mod:`difffilter.models.learned_estimator`).
"""

from __future__ import annotations

import math

import lightning.pytorch as pl
import torch

from difffilter import resampling
from difffilter.metrics import roc_auc
from difffilter.models import registry
from difffilter.models.attacks import Replacement
from difffilter.models.estimators import poa_detector_for_scenario
from difffilter.models.generic_estimators import GAUSSIAN_FILTERS, deception_of
from difffilter.models.learned_estimator import (
    feature_dim,
    neural_gaussian_filter,
    neural_particle_filter,
)
from difffilter.models.neural_estimator import NeuralFDIEstimator
from difffilter.models.streams import Streams
from difffilter.param_ekf import EKFOptimizer

from .common import dtype_of, mix_seed

__all__ = ["ScenarioDataModule", "FilterEstimatorTask", "RESAMPLERS"]

#: Training resamplers (``resampler=``): gradients through resampling or around it.
RESAMPLERS = {
    "stop_gradient": lambda alpha: resampling.StopGradient(),
    "soft": lambda alpha: resampling.Soft(alpha),
    "ot": lambda alpha: resampling.OptimalTransport(),
}
_FIELDS = ("x", "y_recv", "us", "mask", "attack", "flags")


def simulate_batch(scenario, runs: int, seed: int, dtype: torch.dtype) -> dict:
    """``runs`` runs of ``scenario`` from the named streams of ``seed`` (as ``difffilter-eval``):
    ``{"x", "y_recv", "attack", "flags"}`` and, where the scenario has them, ``"us"``, ``"mask"``."""
    streams = Streams(seed)
    tr = scenario.simulate(
        runs, {k: streams(k) for k in ("plant", "attack", "schedule")}, dtype=dtype
    )
    return {k: getattr(tr, k) for k in _FIELDS if getattr(tr, k) is not None}


class _Keys(torch.utils.data.Dataset):
    def __init__(self, indices):
        self.indices = list(indices)

    def __len__(self):
        return len(self.indices)

    def __getitem__(self, i):
        return {"index": torch.tensor(self.indices[i])}


class ScenarioDataModule(pl.LightningDataModule):
    """Trajectories of one registered scenario, simulated on the fly from seeds.

    Args:
        scenario: a registered scenario name (``difffilter-eval --list``).
        batch_size, batches_per_epoch: training runs per batch and batches per epoch.
        val_runs, val_seed: the fixed validation batch.
        train_seed: master seed of the training batches (differs from ``val_seed``).
        test_runs, test_seed: ``test``/``predict`` runs (default the scenario's ``runs``)
            and seed: the draws of ``difffilter-eval <scenario> --seed test_seed``.
        dtype: ``"float32"`` or ``"float64"``.
    """

    def __init__(
        self,
        scenario: str = "four_tank_bias",
        batch_size: int = 16,
        batches_per_epoch: int = 8,
        val_runs: int = 64,
        train_seed: int = 1,
        val_seed: int = 2,
        test_runs: int | None = None,
        test_seed: int = 0,
        dtype: str = "float32",
    ):
        super().__init__()
        self.scenario = registry.get(scenario)  # ValueError listing the known names
        for name, val in (
            ("batch_size", batch_size),
            ("batches_per_epoch", batches_per_epoch),
            ("val_runs", val_runs),
            ("test_runs", 1 if test_runs is None else test_runs),
        ):
            if isinstance(val, bool) or not isinstance(val, int) or val < 1:
                raise ValueError(f"{name} must be a positive integer; got {val!r}")
        if train_seed == val_seed:
            raise ValueError("train_seed and val_seed must differ (validation data must be unseen)")
        if test_seed in (train_seed, val_seed):
            raise ValueError("test_seed must differ from train_seed and val_seed")
        self.save_hyperparameters()
        self._dtype = dtype_of(dtype)
        self._val = None

    def train_dataloader(self):
        n, trainer = self.hparams.batches_per_epoch, getattr(self, "trainer", None)
        # DDP: each process simulates its share of the epoch's seeded batches (our own
        # split, so the data stay a function of (train_seed, epoch, batch) across resumes)
        rank, world = (trainer.global_rank, trainer.world_size) if trainer else (0, 1)
        return torch.utils.data.DataLoader(_Keys(range(rank, n, world)), batch_size=None)

    def on_after_batch_transfer(self, batch, dataloader_idx):
        # drawn here, from the trainer's epoch (right after a resume too)
        if isinstance(batch, dict) and "index" in batch:
            epoch = self.trainer.current_epoch if getattr(self, "trainer", None) else 0
            seed = mix_seed(self.hparams.train_seed, epoch, int(batch["index"]))
            return simulate_batch(self.scenario, self.hparams.batch_size, seed, self._dtype)
        return batch

    def val_dataloader(self):
        if self._val is None:
            hp = self.hparams
            self._val = simulate_batch(self.scenario, hp.val_runs, hp.val_seed, self._dtype)
        return torch.utils.data.DataLoader([self._val], batch_size=None)

    def test_dataloader(self):
        hp = self.hparams
        runs = hp.test_runs or self.scenario.runs
        return torch.utils.data.DataLoader(
            [simulate_batch(self.scenario, runs, hp.test_seed, self._dtype)], batch_size=None
        )

    def predict_dataloader(self):
        return self.test_dataloader()


class FilterEstimatorTask(pl.LightningModule):
    """The neural FDI estimator trained through difffilter's filter on one scenario.

    Args:
        scenario: the registered scenario (its model is the filter's).
        filter: ``"pf"`` (particle filter) or ``"kf"``, ``"ekf"``, ``"ukf"``.
        resampler: PF training resampler, ``"soft"`` (``soft_alpha``), ``"stop_gradient"``
            or ``"ot"`` (entropy-regularised optimal transport); validation, test and
            evaluation resample systematically.
        num_particles: PF particles (default: the scenario's).
        a, b, hidden, init_scale, init, attack_scale, resid_scale: the network
            (:class:`~difffilter.models.neural_estimator.NeuralFDIEstimator`, one area of
            ``dy`` channels; ``model_seed`` seeds its weights and the training filter).
        features: the filter's statistics the network reads beside its innovations and
            past estimates (:data:`~difffilter.models.learned_estimator.FEATURES`:
            ``"mask"``, ``"log_likelihood"``, ``"poa"``; the PoA threshold η is the
            scenario's, as the evaluation's PoA detector uses it).
        trainer: ``"grad"`` (AdamW through the filter) or ``"ekf"`` (the EKF over the
            weights; module docstring).
        lr, weight_decay: AdamW.
        ekf_lr, ekf_init_cov, ekf_init_noise, ekf_process_noise: ``η``, ``ρ(0)``, ``Υ(0)``
            and ``Q_ρ`` of the EKF (:class:`~difffilter.param_ekf.EKFOptimizer`).
        attack_weight, bce_weight, state_weight: loss weights (module docstring).
        target_false_alarm_rate: of the operating threshold (default: the scenario's).
        dtype: ``"float32"`` or ``"float64"``.
    """

    def __init__(
        self,
        scenario: str = "four_tank_bias",
        filter: str = "pf",
        resampler: str = "soft",
        soft_alpha: float = 0.5,
        num_particles: int | None = None,
        a: int = 3,
        b: int = 3,
        hidden: int = 16,
        init_scale: float = 0.1,
        init: str = "symmetric",
        attack_scale: float = 1.0,
        resid_scale: float = 10.0,
        features: list[str] | None = None,
        trainer: str = "grad",
        lr: float = 3e-3,
        weight_decay: float = 0.0,
        ekf_lr: float = 1.0,
        ekf_init_cov: float = 1.0,
        ekf_init_noise: float = 1e-2,
        ekf_process_noise: float = 0.0,
        attack_weight: float = 1.0,
        bce_weight: float = 0.1,
        state_weight: float = 1.0,
        target_false_alarm_rate: float | None = None,
        model_seed: int = 0,
        dtype: str = "float32",
    ):
        super().__init__()
        sc = registry.get(scenario)
        if filter != "pf" and filter not in GAUSSIAN_FILTERS:
            raise ValueError(
                f"filter must be 'pf' or one of {sorted(GAUSSIAN_FILTERS)}; got {filter!r}"
            )
        if resampler not in RESAMPLERS:
            raise ValueError(f"resampler must be one of {sorted(RESAMPLERS)}; got {resampler!r}")
        if trainer not in ("grad", "ekf"):
            raise ValueError(f"trainer must be 'grad' or 'ekf'; got {trainer!r}")
        features = tuple(features or ())
        attack = sc.attack_model()
        self.channel = "replacement" if isinstance(attack, Replacement) else attack.channel
        if self.channel == "actuator" and filter == "pf":
            raise ValueError(
                f"filter: {scenario} has an actuator attack, which the learned estimator "
                "compensates in the input of a Gaussian filter: use kf, ekf or ukf"
            )
        if self.channel == "replacement" and (filter != "pf" or trainer != "grad"):
            raise ValueError(
                f"{scenario} replaces measurements: the learned estimator weighs them with the "
                "mixture likelihood of its attack probability, in the PF (filter: pf, trainer: grad)"
            )
        self.deception = (
            deception_of(attack, dtype_of(dtype))[0] if self.channel == "replacement" else None
        )
        if "poa" in features and filter != "pf":
            raise ValueError("features: 'poa' needs particles (filter='pf')")
        far = sc.false_alarm_rate if target_false_alarm_rate is None else target_false_alarm_rate
        if not 0 < far < 1:
            raise ValueError(f"target_false_alarm_rate must be in (0, 1); got {far!r}")
        self.save_hyperparameters()
        self.scenario, self._dtype, self.false_alarm_rate = sc, dtype_of(dtype), float(far)
        self.system = sc.system(self._dtype)
        self.num_particles = num_particles or sc.num_particles
        self.features, self.poa_eta = features, None
        if "poa" in features:
            self.poa_eta = float(poa_detector_for_scenario(sc, self.system).eta)
        dy = self.system.dim_y
        self.estimator = NeuralFDIEstimator(
            num_areas=1,
            area_dim=self.system.dim_u if self.channel == "actuator" else dy,
            resid_dim=dy,
            a=a,
            b=b,
            hidden=hidden,
            init_scale=init_scale,
            init=init,
            attack_scale=attack_scale,
            resid_scale=resid_scale,
            extra_inputs=feature_dim(features, dy),
            detection_head=trainer == "grad",  # the EKF fits the attack estimate alone
            seed=model_seed,
            dtype=self._dtype,
        )
        # the operating threshold on p, chosen at every validation; saved with the weights
        self.register_buffer("alarm_threshold", torch.tensor(0.5, dtype=torch.float64))
        self._state_scale = torch.diagonal(self.system.initial.cov, dim1=-2, dim2=-1).mean()
        self.automatic_optimization = trainer == "grad"

    def configure_optimizers(self):
        hp = self.hparams
        if hp.trainer == "ekf":
            return EKFOptimizer(
                [self.estimator.W, self.estimator.V], lr=hp.ekf_lr, init_cov=hp.ekf_init_cov,
                init_noise=hp.ekf_init_noise, process_noise=hp.ekf_process_noise,
            )  # fmt: skip
        return torch.optim.AdamW(
            self.estimator.parameters(), lr=hp.lr, weight_decay=hp.weight_decay
        )

    # -- the filter --------------------------------------------------------------------
    def run_filter(
        self, batch: dict, *, training: bool, seed: int, threshold: float = 0.5, record=False
    ):
        """The estimator on ``batch`` (an :class:`~difffilter.EstimatorOutput`; ``record``:
        with the network's inputs in ``extras["network_inputs"]``)."""
        kw = {"network": self.estimator, "mask": batch.get("mask"), "threshold": threshold}
        kw.update(features=self.features, record_inputs=record)
        training = training and self.hparams.trainer == "grad"  # the EKF needs no gradients
        if self.hparams.filter != "pf":
            return neural_gaussian_filter(
                self.system, batch["y_recv"], batch.get("us"), kind=self.hparams.filter,
                channel=self.channel, **kw,
            )  # fmt: skip
        hp = self.hparams
        resampler = RESAMPLERS[hp.resampler](hp.soft_alpha) if training else resampling.Systematic()
        gens = Streams(seed)
        return neural_particle_filter(
            self.system,
            batch["y_recv"],
            batch.get("us"),
            num_particles=self.num_particles,
            resampler=resampler,
            ess_threshold=1.0,
            generator=gens("particles/propagate"),
            resample_generator=gens("particles/resample"),
            poa_eta=self.poa_eta,
            channel=self.channel,
            deception=self.deception,
            **kw,
        )

    def _losses(self, out, batch) -> dict:
        flags = batch["flags"].to(out.attack.dtype)
        losses = {
            "attack_mse": (out.attack - batch["attack"]).square().mean(),
            "bce": torch.nn.functional.binary_cross_entropy_with_logits(
                out.extras["attack_logit"], flags
            ),
            "state_mse": (out.means - batch["x"]).square().mean() / self._state_scale,
        }
        hp = self.hparams
        losses["loss"] = (
            hp.attack_weight * losses["attack_mse"]
            + hp.bce_weight * losses["bce"]
            + hp.state_weight * losses["state_mse"]
        )
        return losses

    def training_step(self, batch, batch_idx):
        seed = mix_seed(self.hparams.model_seed, self.global_step)
        runs = batch["y_recv"].shape[0]
        if self.hparams.trainer == "ekf":
            return self._ekf_step(batch, seed, runs)
        out = self.run_filter(batch, training=True, seed=seed)
        losses = self._losses(out, batch)
        for k, v in losses.items():
            self.log(f"train/{k}", v.detach(), prog_bar=k == "loss", batch_size=runs)
        return losses["loss"]

    def _ekf_step(self, batch, seed: int, runs: int):
        """The EKF over ``ζ = [W, V]``: one update per time step from the batch's samples."""
        with torch.no_grad():
            out = self.run_filter(batch, training=True, seed=seed, record=True)
            deltas, template = out.extras["network_inputs"], self.estimator.area_template()
            received = batch.get("mask") if self.channel == "sensor" else None
            if received is None:
                received = torch.ones_like(batch["attack"], dtype=torch.bool)
            optimizer, sq_err = self.optimizers(), []
            for t in range(deltas.shape[-2]):
                params = {"W": self.estimator.W[0].expand(runs, -1, -1),
                          "V": self.estimator.V[0].expand(runs, -1, -1)}  # fmt: skip
                pred, jac = template.batched_jacobian(params, deltas[:, t].to(self.estimator.V))
                keep = received[:, t].to(pred.dtype)
                residual = (batch["attack"][:, t].to(pred.dtype) - pred) * keep
                sq_err.append(optimizer.step(jacobian=jac * keep[..., None], residual=residual))
        mse = torch.stack(sq_err).mean() / batch["attack"].shape[-1]  # per entry, before updates
        self.log("train/attack_mse", mse, prog_bar=True, batch_size=runs)

    # -- validation, test, predict -------------------------------------------------------
    def _scores(self, stage: str, batch, threshold: float | None) -> dict:
        """Evaluate on ``batch``; with ``threshold=None`` choose it (validation)."""
        with torch.no_grad():
            out = self.run_filter(batch, training=False, seed=mix_seed(self.hparams.model_seed, 7))
        prob, flags = out.detection.scores, batch["flags"]
        if threshold is None:
            quiet = prob[~flags]
            q = 1.0 - self.false_alarm_rate
            threshold = float(torch.quantile(quiet.double(), q)) if quiet.numel() else 0.5
            self.alarm_threshold.fill_(threshold)
        alarms = prob > threshold
        err = out.attack - batch["attack"]
        scores = {
            "attack_rmse": float(err.square().mean().sqrt()),
            "state_rmse": float((out.means - batch["x"]).square().mean().sqrt()),
            "auc": roc_auc(prob, flags),
            "tpr": float(alarms[flags].double().mean()) if bool(flags.any()) else float("nan"),
            "fpr": float(alarms[~flags].double().mean()) if bool((~flags).any()) else float("nan"),
            "threshold": threshold,
        }
        runs = flags.shape[0]
        for k, v in scores.items():
            if math.isfinite(v):
                self.log(
                    f"{stage}/{k}", v, prog_bar=k == "attack_rmse", batch_size=runs, sync_dist=True
                )
        return scores

    def validation_step(self, batch, batch_idx):
        self._scores("val", batch, None)

    def test_step(self, batch, batch_idx):
        self._scores("test", batch, float(self.alarm_threshold))

    def predict_step(self, batch, batch_idx):
        with torch.no_grad():
            out = self.run_filter(
                batch,
                training=False,
                seed=mix_seed(self.hparams.model_seed, 7),
                threshold=float(self.alarm_threshold),
            )
        return {
            "attack_estimate": out.attack,
            "attack_probability": out.detection.scores,
            "alarms": out.detection.alarms,
            "means": out.means,
        }

    # -- export (difffilter.train.export.ExportEstimator) --------------------------------
    def export_name(self) -> str:
        return f"{self.scenario.family}_nn_{self.hparams.trainer}"

    def export_observer(self) -> dict:
        """What evaluation needs beside the weights (the filter, its threshold, the scenario)."""
        hp = self.hparams
        return {
            "kind": hp.filter,
            "scenario": self.scenario.name,
            "scenario_family": self.scenario.family,
            "num_particles": int(self.num_particles),
            "threshold": float(self.alarm_threshold),
            "target_false_alarm_rate": self.false_alarm_rate,
            "dt": float(self.scenario.dt),
            "features": list(self.features),
            "poa_eta": self.poa_eta,
            "trainer": self.hparams.trainer,
            "channel": self.channel,
        }

    def check_exported(self, observer: dict, path) -> None:
        """``ValueError`` unless an exported estimator was trained for this filter and
        scenario family; its operating threshold becomes this module's."""
        mine = self.export_observer()
        for key in ("kind", "scenario_family", "features", "trainer"):
            theirs = observer.get(key, {"features": [], "trainer": "grad"}.get(key))
            if theirs != mine[key]:
                raise ValueError(
                    f"--ckpt_path: {path} was trained with {key} = {theirs!r}, the "
                    f"configured model has {mine[key]!r}"
                )
        self.alarm_threshold.fill_(float(observer.get("threshold", 0.5)))

    def export_card(self, trainer, estimator=None) -> dict:
        hp = self.hparams
        return {
            "scenario_family": self.scenario.family,
            "estimator": f"{'pf' if hp.filter == 'pf' else 'gaussian'}_nn_{hp.trainer}",
            "description": (
                "Neural FDI estimator (eqs 8-9, one area of dy channels) trained "
                + (
                    f"through difffilter's {hp.filter.upper()} (resampler for training: "
                    f"{hp.resampler})"
                    if hp.trainer == "grad"
                    else f"by the EKF over its weights inside difffilter's {hp.filter.upper()}"
                )
                + f" on {self.scenario.name}"
            ),
        }

    def on_save_checkpoint(self, checkpoint):
        # a Lightning checkpoint of this task loads as an estimator (difffilter-eval --ckpt)
        checkpoint["difffilter_observer"] = self.export_observer()
        checkpoint["difffilter_estimator_config"] = self.estimator.config()
