"""Gradient training of the LFC neural FDI estimator through the Kalman observer (``kf_nn_grad``).

The estimator of eqs (8)–(9) runs inside the closed loop of
:class:`difffilter.models.attack_observer.ClosedLoop` (plant, Kalman observer that
subtracts the estimated attack, secure controller ``U = −K₁(Z − M̂)``) on trajectories
simulated on the fly from seeds, with random attacks (steps, ramps, sinusoids, pulse
trains; :func:`difffilter.models.lfc.random_attacks`), and is trained by truncated
backpropagation through time (TBPTT): the loop state is detached every ``tbptt_steps``
steps, each chunk's loss is back-propagated and followed by one optimizer step.

Loss per chunk: ``mean((M̂ − O)²) + λ_u·mean(‖K₁(M̂ − O)‖²) + bce_weight · BCE(logit,
attacked-area flag)`` with the
target ``O = α`` or, with ``noise_target=True``, ``O = α + θ``: the paper's ``Ô_s`` is "the
estimate of the summation of the FDI attack and the measurement noise" (eqs 17–18), so
that the secure controller's feedback ``Z − Ô_s`` is a denoised state measurement.

Data: :class:`LFCDataModule` draws each training batch from a seed derived from
``(train_seed, epoch, batch index)`` (so an interrupted run resumes on the same data) and
one fixed validation batch from ``val_seed``. Checkpoints are selected on the validation
attack RMSE of random attacks, never on the paper's test scenarios; those are simulated
and logged as ``val/scenario/<name>/attack_rmse`` for monitoring only.
"""

from __future__ import annotations

import math
import time

import lightning.pytorch as pl
import numpy as np
import torch
from torch.utils.data import Dataset

from difffilter.models import registry
from difffilter.models.attack_observer import AttackObserver, ClosedLoop
from difffilter.models.control import lqr
from difffilter.models.lfc import NUM_AREAS, LFCPlant, LFCScenario, random_attacks
from difffilter.models.neural_estimator import (
    NeuralFDIEstimator,
)

from .common import dtype_of, mix_seed
from .export import ExportEstimator

__all__ = [
    "LFCGradModule",
    "LFCDataModule",
    "ExportEstimator",
    "build_closed_loop",
    "check_metric",
    "simulate_batch",
]

_dtype, _seed = dtype_of, mix_seed


def simulate_batch(
    seed: int,
    runs: int,
    steps: int,
    dt: float,
    *,
    channels=None,
    max_events=3,
    amplitude=(0.1, 2.0),
    load_range=0.02,
    dtype=torch.float32,
) -> dict:
    """One batch of training/validation inputs drawn from ``seed``.

    Returns ``{"attack": [B, T, 10], "xi": [B, T, 10], "theta": [B, T, 10], "load": [B, 2]}``:
    random attacks, process and measurement noise of the plant (``LFCPlant`` defaults)
    and a constant load per area ``~ U[−load_range/2, load_range/2]`` (the test
    scenarios' 0.01 p.u. step lies inside).
    """
    g = torch.Generator().manual_seed(int(seed))
    attack = random_attacks(
        runs,
        steps,
        dt,
        generator=g,
        channels=channels,
        max_events=max_events,
        amplitude=tuple(amplitude),
        dtype=dtype,
    )
    plant = LFCPlant(dt=dt, dtype=dtype)
    xi, theta = plant.sample_noise(runs, steps, g)
    load = (torch.rand(runs, NUM_AREAS, generator=g, dtype=dtype) - 0.5) * load_range
    return {"attack": attack, "xi": xi, "theta": theta, "load": load}


class _SeededBatches(Dataset):
    """Item ``i`` is the batch drawn from seed ``(seed, epoch, i)``; with ``lazy=True`` only the
    key ``{"index": i}`` (the data module then draws the batch for the trainer's epoch)."""

    def __init__(self, seed: int, n: int, lazy: bool = False, **kwargs):
        self.seed, self.n, self.lazy, self.kwargs = seed, n, lazy, kwargs

    def __len__(self):
        return self.n

    def draw(self, epoch: int, i: int) -> dict:
        return simulate_batch(_seed(self.seed, epoch, i), **self.kwargs)

    def __getitem__(self, i):
        return {"index": torch.tensor(i)} if self.lazy else self.draw(0, i)


class LFCDataModule(pl.LightningDataModule):
    """Random-attack trajectories simulated from seeds (train and validation seeds differ).

    Args:
        batch_size: runs per training batch.
        batches_per_epoch: training batches per epoch.
        val_runs: runs in the (single, fixed) validation batch.
        steps, dt: horizon and sampling time of every trajectory (1000 × 10 ms).
        train_seed, val_seed: master seeds (must differ).
        channels: attackable channels (zero-based; ``None`` = all ten).
        max_events, amplitude, load_range: see :func:`simulate_batch`.
        dtype: ``"float32"`` or ``"float64"``.
        test_runs, test_seed: runs and master seed of ``test``/``predict``: the registered
            LFC test scenarios at this ``dt``, their noise drawn from the same named streams
            as ``difffilter-eval --seed test_seed`` (so ``test`` reproduces its draws).
    """

    def __init__(
        self,
        batch_size: int = 32,
        batches_per_epoch: int = 20,
        val_runs: int = 64,
        steps: int = 1000,
        dt: float = 0.01,
        train_seed: int = 1,
        val_seed: int = 2,
        channels: list[int] | None = None,
        max_events: int = 3,
        amplitude: tuple[float, float] = (0.1, 2.0),
        load_range: float = 0.02,
        dtype: str = "float32",
        test_runs: int = 8,
        test_seed: int = 0,
    ):
        super().__init__()
        if train_seed == val_seed:
            raise ValueError("train_seed and val_seed must differ (validation data must be unseen)")
        for name, val in (
            ("batch_size", batch_size),
            ("batches_per_epoch", batches_per_epoch),
            ("val_runs", val_runs),
            ("steps", steps),
            ("test_runs", test_runs),
        ):
            if not (isinstance(val, int) and val >= 1):
                raise ValueError(f"{name} must be a positive integer; got {val!r}")
        self.save_hyperparameters()
        common = dict(
            steps=steps,
            dt=dt,
            channels=channels,
            max_events=max_events,
            amplitude=tuple(amplitude),
            load_range=load_range,
            dtype=_dtype(dtype),
        )
        self._train = _SeededBatches(
            train_seed, batches_per_epoch, lazy=True, runs=batch_size, **common
        )
        self._val = _SeededBatches(val_seed, 1, runs=val_runs, **common)

    def train_dataloader(self):
        data = self._train
        trainer = getattr(self, "trainer", None)
        if trainer is not None and trainer.world_size > 1:
            # DDP: each process simulates its own share of the epoch's seeded batches
            # (the sampler is ours, not Lightning's, so that the data stay a function of
            # (train_seed, epoch, batch) and resuming sees the same batches)
            indices = range(trainer.global_rank, len(data), trainer.world_size)
            data = torch.utils.data.Subset(data, list(indices))
        return torch.utils.data.DataLoader(data, batch_size=None)

    def train_batch(self, epoch: int, index: int) -> dict:
        """Training batch ``index`` of ``epoch`` (seed ``(train_seed, epoch, index)``)."""
        return self._train.draw(epoch, index)

    def on_after_batch_transfer(self, batch, dataloader_idx):
        # Training batches are drawn here, from the trainer's epoch: it is right after a
        # resume too (a sampler's epoch is not), so an interrupted run sees the same data.
        if isinstance(batch, dict) and "index" in batch:
            epoch = self.trainer.current_epoch if getattr(self, "trainer", None) else 0
            return self.train_batch(epoch, int(batch["index"]))
        return batch

    def val_dataloader(self):
        return torch.utils.data.DataLoader(self._val, batch_size=None)

    def test_batches(self) -> list[dict]:
        """One batch per registered LFC headline scenario at this ``dt``: its attack and the
        noise and load of ``test_runs`` runs (``Scenario.simulate``'s draws)."""
        from difffilter.models.streams import Streams

        hp, batches = self.hparams, []
        for name in registry.names("lfc", headline_only=True):
            sc = registry.get(name)
            if abs(sc.dt - hp.dt) > 1e-12:
                continue
            gens = {"plant": Streams(hp.test_seed)("plant")}
            tr = sc.simulate(hp.test_runs, gens, dtype=_dtype(hp.dtype))
            batch = {k: tr.info[k] for k in ("xi", "theta", "load")}
            batches.append(
                {
                    "name": name,
                    "attack": tr.attack,
                    **batch,
                    "channels": torch.tensor(sc.attacked_channels),
                }
            )
        return batches

    def test_dataloader(self):
        return torch.utils.data.DataLoader(self.test_batches(), batch_size=None)

    def predict_dataloader(self):
        return self.test_dataloader()


def build_closed_loop(
    estimator: NeuralFDIEstimator | None,
    *,
    dt: float = 0.01,
    residual_lag: int = 0,
    dtype=torch.float64,
    compensate: bool = True,
):
    """Plant, LQR and the Kalman observer around ``estimator`` (frozen weights)."""
    plant = LFCPlant(dt=dt, dtype=dtype)
    K1, _ = lqr(plant.A.double(), plant.B.double())
    observer = AttackObserver(
        plant.Ad, plant.Bd, plant.Q, plant.R, network=estimator, residual_lag=residual_lag
    )
    return ClosedLoop(plant, K1.to(dtype), observer, compensate=compensate)


def _area_flags(attack: torch.Tensor) -> torch.Tensor:
    """``[B, T, 10]`` → ``[B, T, J]``: is any channel of the area attacked?"""
    B, T, _ = attack.shape
    return (attack.reshape(B, T, NUM_AREAS, -1) != 0).any(-1).to(attack.dtype)


class LFCGradModule(pl.LightningModule):
    """LightningModule of ``kf_nn_grad`` (see the module docstring).

    Args:
        a, b, hidden, init_scale, init, resid_scale, detection_head: the
            :class:`NeuralFDIEstimator` (``model_seed`` seeds its initial weights).
        residual_lag: ``ℓ`` of :class:`AttackObserver` (0: the current residual is an input).
        lr, weight_decay: AdamW; the learning rate follows a one-cycle schedule over the
            whole run (``pct_start`` warm-up), stepped after every TBPTT chunk.
        tbptt_steps: truncation length of backpropagation through time.
        grad_clip: global gradient-norm clip.
        bce_weight: weight of the attack-probability loss.
        noise_target: regress on ``α + θ`` (the paper's ``O_s``) instead of ``α``.
        control_weight: ``λ_u`` of the control-weighted term ``λ_u·mean(‖K₁(M̂ − O)‖²)``: the
            estimate enters the plant through ``U = −K₁(Z − M̂)``, whose gains differ by two
            orders of magnitude between channels (15.5 on Δf₁, 0.58 on ΔP_tu₁), so an error on a
            frequency channel disturbs the plant far more than the same error elsewhere.
        dt: sampling time.
        monitor_scenarios: test scenarios simulated at validation for monitoring.
        monitor_runs, monitor_seed: their Monte Carlo size and noise seed.
        dtype: ``"float32"`` (fast) or ``"float64"``.
    """

    def __init__(
        self,
        a: int = 3,
        b: int = 3,
        hidden: int = 16,
        init_scale: float = 0.1,
        init: str = "symmetric",
        resid_scale: float = 1.0,
        detection_head: bool = True,
        residual_lag: int = 0,
        lr: float = 1e-2,
        weight_decay: float = 0.0,
        pct_start: float = 0.1,
        tbptt_steps: int = 100,
        grad_clip: float = 1.0,
        bce_weight: float = 0.05,
        noise_target: bool = False,
        control_weight: float = 0.0,
        dt: float = 0.01,
        model_seed: int = 0,
        monitor_scenarios: list[str] | None = None,
        monitor_runs: int = 4,
        monitor_seed: int = 3,
        dtype: str = "float32",
    ):
        super().__init__()
        if tbptt_steps < 1:
            raise ValueError(f"tbptt_steps must be >= 1; got {tbptt_steps}")
        self.save_hyperparameters()
        self.automatic_optimization = False
        self._dtype = _dtype(dtype)
        self.estimator = NeuralFDIEstimator(
            a=a,
            b=b,
            hidden=hidden,
            init_scale=init_scale,
            init=init,
            resid_scale=resid_scale,
            detection_head=detection_head,
            seed=model_seed,
            dtype=self._dtype,
        )
        self.loop = build_closed_loop(
            self.estimator, dt=dt, residual_lag=residual_lag, dtype=self._dtype
        )
        if monitor_scenarios is None:
            monitor_scenarios = ["lfc_step", "lfc_sine", "lfc_simultaneous", "lfc_sawtooth"]
        for name in monitor_scenarios:  # at construction time, not silently at validation
            sc = registry.get(name)  # ValueError for unknown names
            if not isinstance(sc, LFCScenario) or abs(sc.dt - dt) > 1e-12:
                raise ValueError(
                    f"monitor_scenarios: {name!r} is not an LFC scenario at dt = {dt} s "
                    f"(family {sc.family!r}, dt = {sc.dt} s); this module trains the LFC estimator"
                )
        self.monitor_scenarios = list(monitor_scenarios)
        self._fit_start = None
        self._val_reference = None  # attack-free state-5 RMSE of the traditional loop (val batch)

    # -- optimisation -------------------------------------------------------------------
    def configure_optimizers(self):
        hp = self.hparams
        opt = torch.optim.AdamW(self.estimator.parameters(), lr=hp.lr, weight_decay=hp.weight_decay)
        total = self._schedule_length()
        sched = torch.optim.lr_scheduler.OneCycleLR(
            opt, max_lr=hp.lr, total_steps=total, pct_start=hp.pct_start
        )
        return [opt], [{"scheduler": sched, "interval": "step"}]

    def _schedule_length(self) -> int:
        """Optimizer steps of the one-cycle schedule: batches × TBPTT chunks (at least 2 warm-up)."""
        steps = self.trainer.estimated_stepping_batches if self.trainer is not None else 1
        if not math.isfinite(steps) or steps < 1:
            raise ValueError(
                "--trainer.max_epochs (or max_steps) must give a finite number of steps >= 1: the "
                f"one-cycle learning-rate schedule needs its length; got {steps} steps"
            )
        # OneCycleLR needs at least two warm-up steps (fast_dev_run has one batch).
        return max(
            int(steps) * self._chunks_per_batch(), math.ceil(2.0 / self.hparams.pct_start) + 2
        )

    def on_train_start(self):
        # A resumed run restores the schedule of the checkpoint, whose length was fixed by
        # its max_epochs: a longer run would step past its end ("Tried to step N times").
        sched = self.lr_schedulers()
        restored, wanted = getattr(sched, "total_steps", None), self._schedule_length()
        if restored is not None and restored != wanted:
            raise ValueError(
                f"--ckpt_path: the checkpoint's learning-rate schedule has {restored} steps but this "
                f"run needs {wanted} (its --trainer.max_epochs differs); resume with the checkpoint's "
                "max_epochs, or start a new run"
            )

    def _chunks_per_batch(self) -> int:
        dm = getattr(self.trainer, "datamodule", None) if self.trainer is not None else None
        steps = dm.hparams.steps if dm is not None else 1000
        return math.ceil(steps / self.hparams.tbptt_steps)

    def _loss(self, rec, attack, theta):
        target = attack + theta if self.hparams.noise_target else attack
        mse = (rec.attack_est - target).square().mean()
        loss = mse
        if self.hparams.control_weight > 0:
            du = (rec.attack_est - target) @ self.loop.K1.T  # the estimate's effect on U
            loss = loss + self.hparams.control_weight * du.square().mean()
        bce = torch.zeros((), dtype=mse.dtype)
        if rec.logit is not None and self.hparams.bce_weight > 0:
            bce = torch.nn.functional.binary_cross_entropy_with_logits(
                rec.logit, _area_flags(attack)
            )
            loss = loss + self.hparams.bce_weight * bce
        return loss, mse, bce

    def training_step(self, batch, batch_idx):
        if self._fit_start is None:
            self._fit_start = time.time()
        opt = self.optimizers()
        sched = self.lr_schedulers()
        attack, xi, theta, load = batch["attack"], batch["xi"], batch["theta"], batch["load"]
        B, T, _ = attack.shape
        state = self.loop.init(B)
        tb = self.hparams.tbptt_steps
        sums = {"loss": 0.0, "mse": 0.0, "bce": 0.0}
        norms = []
        for c0 in range(0, T, tb):
            sl = slice(c0, min(c0 + tb, T))
            state = state.detach()
            state, rec = self.loop.run(state, attack[:, sl], xi[:, sl], theta[:, sl], load)
            loss, mse, bce = self._loss(rec, attack[:, sl], theta[:, sl])
            opt.zero_grad()
            self.manual_backward(loss)
            norm = torch.nn.utils.clip_grad_norm_(
                self.estimator.parameters(), self.hparams.grad_clip
            )
            norms.append(float(norm))
            opt.step()
            sched.step()
            w = (sl.stop - sl.start) / T
            sums["loss"] += w * float(loss.detach())
            sums["mse"] += w * float(mse.detach())
            sums["bce"] += w * float(bce.detach())
        self.log("train/loss", sums["loss"], prog_bar=True, batch_size=B)
        self.log("train/target_rmse", math.sqrt(sums["mse"]), batch_size=B)
        self.log("train/bce", sums["bce"], batch_size=B)
        self.log("train/grad_norm", float(np.mean(norms)), batch_size=B)
        self.log("train/grad_norm_max", float(np.max(norms)), batch_size=B)
        # the learning rate is logged once, by the config's LearningRateMonitor (per step)

    # -- validation ---------------------------------------------------------------------
    def _simulate(self, attack, xi, theta, load):
        with torch.no_grad():
            _, rec = self.loop.run(self.loop.init(attack.shape[0]), attack, xi, theta, load)
        return rec

    def validation_step(self, batch, batch_idx):
        attack = batch["attack"]
        rec = self._simulate(attack, batch["xi"], batch["theta"], batch["load"])
        B = attack.shape[0]
        rmse = float((rec.attack_est - attack).square().mean().sqrt())
        attacked = attack != 0
        rmse_att = (
            float((rec.attack_est - attack)[attacked].square().mean().sqrt())
            if bool(attacked.any())
            else float("nan")
        )
        self.log("val/attack_rmse", rmse, prog_bar=True, batch_size=B, sync_dist=True)
        self.log("val/attack_rmse_attacked", rmse_att, batch_size=B, sync_dist=True)
        s5 = float(rec.x[..., 4].square().mean().sqrt())
        self.log("val/state5_rmse", s5, batch_size=B, sync_dist=True)
        # Reference: the traditional controller on the same noise without attack (independent
        # of the network: cached). A ratio near 1 means the secure loop under random attacks
        # is as calm as the attack-free one; estimation noise fed back through K₁ raises it.
        if self._val_reference is None:
            ref = build_closed_loop(None, dt=self.hparams.dt, dtype=self._dtype, compensate=False)
            with torch.no_grad():
                _, ref_rec = ref.run(
                    ref.init(B),
                    torch.zeros_like(attack),
                    batch["xi"],
                    batch["theta"],
                    batch["load"],
                )
            self._val_reference = float(ref_rec.x[..., 4].square().mean().sqrt())
        self.log("val/state5_excess", s5 / self._val_reference, batch_size=B, sync_dist=True)
        if rec.logit is not None:
            from difffilter.metrics import roc_auc

            auc = roc_auc(rec.logit.transpose(1, 2), _area_flags(attack).transpose(1, 2).bool())
            if math.isfinite(auc):
                self.log("val/detection_auc", auc, batch_size=B, sync_dist=True)
        self._figure("val/random_attack", attack[0], rec.attack_est[0])

    def test_step(self, batch, batch_idx):
        """One test scenario: eq. (43) over its attacked channels, state-5 RMSE, AUC."""
        attack, name = batch["attack"], batch["name"]
        rec = self._simulate(attack, batch["xi"], batch["theta"], batch["load"])
        eq43 = self._log_scenario(
            f"test/{name}", "attack_rmse_eq43", attack, rec, batch["channels"].tolist()
        )
        self._test_scores.append(eq43)

    def on_test_epoch_start(self):
        self._test_scores = []

    def on_test_epoch_end(self):
        if self._test_scores:
            mean = sum(self._test_scores) / len(self._test_scores)
            self.log("test/attack_rmse_eq43_mean", mean, sync_dist=True)

    def predict_step(self, batch, batch_idx):
        """The attack estimate ``[B, T, 10]`` (and probability, with a detection head) of
        one test scenario, in its closed loop."""
        rec = self._simulate(batch["attack"], batch["xi"], batch["theta"], batch["load"])
        prob = None if rec.logit is None else torch.sigmoid(rec.logit)
        return {
            "name": batch["name"],
            "attack_estimate": rec.attack_est,
            "attack_probability": prob,
        }

    def on_validation_epoch_end(self):
        if getattr(self.trainer, "sanity_checking", False):
            return
        for name in self.monitor_scenarios:
            sc = registry.get(name)
            if abs(sc.dt - self.hparams.dt) > 1e-12:
                continue
            R = self.hparams.monitor_runs
            plant = self.loop.plant
            xi, theta = plant.sample_noise(
                R, sc.steps, torch.Generator().manual_seed(self.hparams.monitor_seed)
            )
            attack = sc.attack_signal(self._dtype)[None].expand(R, -1, -1)
            rec = self._simulate(attack, xi, theta, sc.load_tensor(self._dtype)[None])
            channels = list(sc.attacked_channels)
            self._log_scenario(f"val/scenario/{name}", "attack_rmse", attack, rec, channels)

    def _log_scenario(self, prefix: str, key: str, attack, rec, channels: list[int]) -> float:
        """Log a test scenario's eq. (43) RMSE (as ``key``), its state-5 RMSE and a figure."""
        runs = attack.shape[0]
        eq43 = float(
            (rec.attack_est - attack)[..., channels].square().mean(1).sqrt().sum(-1).mean()
        )
        state5 = float(rec.x[..., 4].square().mean(1).sqrt().mean())
        self.log(f"{prefix}/{key}", eq43, batch_size=runs, sync_dist=True)
        self.log(f"{prefix}/state5_rmse", state5, batch_size=runs, sync_dist=True)
        self._figure(prefix, attack[0], rec.attack_est[0], channels=channels)
        return eq43

    def _figure(self, tag, attack, estimate, channels=None):
        logger = self.logger
        if (
            logger is None
            or not hasattr(logger, "experiment")
            or not hasattr(logger.experiment, "add_figure")
        ):
            return
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        if channels is None:  # the most attacked channels of a random run
            energy = attack.abs().sum(0)
            channels = [int(c) for c in torch.argsort(energy, descending=True)[:2]]
        t = self.hparams.dt * torch.arange(1, attack.shape[0] + 1)
        fig, ax = plt.subplots(figsize=(7, 3))
        for c in channels:
            ax.plot(t, attack[:, c].float().cpu(), label=f"attack ch{c + 1}")
            ax.plot(t, estimate[:, c].float().cpu(), "--", label=f"estimate ch{c + 1}")
        ax.set_xlabel("t [s]")
        ax.legend(fontsize=7, loc="upper right")
        fig.tight_layout()
        logger.experiment.add_figure(tag, fig, global_step=self.global_step)
        plt.close(fig)

    def on_fit_end(self):
        if self.logger is not None and self.trainer is not None and self._fit_start is not None:
            best = None
            for cb in self.trainer.callbacks:
                if isinstance(cb, pl.callbacks.ModelCheckpoint) and cb.best_model_score is not None:
                    best = float(cb.best_model_score)
            if best is not None:  # the model's and the data's settings, beside the result
                dm = getattr(self.trainer, "datamodule", None)
                data = {} if dm is None else dict(dm.hparams)
                params = {**data, **dict(self.hparams)}  # as Lightning merges them at start
                self.logger.log_hyperparams(params, {"hp/best_val_attack_rmse": best})

    # -- export (difffilter.train.export.ExportEstimator) --------------------------------
    def export_name(self) -> str:
        return "lfc_nn_grad"

    def export_observer(self) -> dict:
        hp = self.hparams
        return {"residual_lag": int(hp.residual_lag), "dt": float(hp.dt), "kind": "kalman"}

    def check_exported(self, observer: dict, path) -> None:
        """``ValueError`` unless an exported estimator's observer settings are this module's."""
        hp = self.hparams
        if int(observer.get("residual_lag", hp.residual_lag)) != hp.residual_lag or (
            abs(float(observer.get("dt", hp.dt)) - hp.dt) > 1e-12
        ):
            raise ValueError(
                f"--ckpt_path: {path} was trained with observer {observer}, the configured model "
                f"has residual_lag = {hp.residual_lag}, dt = {hp.dt}"
            )

    def export_card(
        self, trainer, estimator=None, check_seed: int = 20, check_runs: int = 4
    ) -> dict:
        """The card's LFC entries: the reproducibility check (``check_metric`` on
        ``check_runs`` random-attack runs of ``check_seed``) and the seeds."""
        dm, hp = trainer.datamodule, self.hparams
        channels = None if dm is None else dm.hparams.channels
        check = check_metric(
            estimator or self.estimator,
            residual_lag=int(hp.residual_lag),
            seed=check_seed,
            runs=check_runs,
            dt=float(hp.dt),
            channels=channels,
        )
        return {
            "scenario_family": "lfc",
            "estimator": "kf_nn_grad",
            "description": "Neural FDI estimator (eqs 8-9) trained by TBPTT through the Kalman "
            "observer on random attacks; Sargolzaei et al., TII 2020",
            "check": {
                "metric": "attack_rmse_random_validation",
                "seed": check_seed,
                "runs": check_runs,
                "channels": channels,
                "value": check,
            },
            "seed": {
                "model_seed": hp["model_seed"],
                "train_seed": None if dm is None else dm.hparams.train_seed,
                "val_seed": None if dm is None else dm.hparams.val_seed,
            },
        }


def check_metric(
    estimator: NeuralFDIEstimator,
    *,
    residual_lag: int,
    seed: int,
    runs: int = 4,
    steps: int = 1000,
    dt: float = 0.01,
    channels=None,
) -> float:
    """Validation attack RMSE (all channels) on ``runs`` random-attack runs drawn from ``seed``.

    Computed in float64; the checkpoint card records it and a test reproduces it.
    """
    est = estimator.double() if estimator.V.dtype != torch.float64 else estimator
    data = simulate_batch(seed, runs, steps, dt, channels=channels, dtype=torch.float64)
    loop = build_closed_loop(est, dt=dt, residual_lag=residual_lag, dtype=torch.float64)
    with torch.no_grad():
        _, rec = loop.run(loop.init(runs), data["attack"], data["xi"], data["theta"], data["load"])
    return float((rec.attack_est - data["attack"]).square().mean().sqrt())
