"""One training task for every registered scenario, open or closed loop: the neural FDI
estimator inside difffilter's own filter, trained by gradient descent through it or by the
EKF over its weights.

:class:`ScenarioDataModule` draws training batches from seeded named streams: batch ``i`` of
epoch ``e`` from seed ``(train_seed, e, i)`` (so an interrupted run resumes on the same
data), one fixed validation batch from ``val_seed`` and ``test`` on exactly the runs
``difffilter-eval <scenario> --seed test_seed`` scores. A batch is what the scenario's
loop needs: the simulated trajectories of an open-loop scenario, the exogenous draws
(noise, load, attack) of a closed-loop one, which every loop replays.

:class:`FilterEstimatorTask` runs
:class:`~difffilter.models.learned_estimator.NeuralCompensation` around the configured
filter (``filter="pf"`` with a differentiable resampler for training, or ``"kf"``,
``"ekf"``, ``"ukf"``) in the scenario's loop — the open loop over the received data, or
the scenario's own closed loop (its estimate feeds back through the controller) — and
minimises, per chunk of ``tbptt_steps`` steps (truncated backpropagation through time:
the loop state is detached between chunks; the whole sequence when ``None``)::

    attack_weight·mean‖â_k − a_k‖² + bce_weight·mean(ω_k BCE(logit_k, l_k))
      + state_weight·mean‖x̂_k − x_k‖²/σ_x² + control_weight·mean‖K(â_k − a_k)‖²

(``a_k`` the injected attack, ``l_k`` its flag per area, ``σ_x²`` the prior variance of the
state, ``K`` the closed loop's feedback gain: an estimate error enters the plant through
``U = −K(Z − â)``; ``ω_k = after_attack_weight`` on the ``after_attack_steps`` steps
that follow an attacked step of the same run and area within the chunk, 1 elsewhere: the
steps where a detector with memory still alarms after the attack ended). A replacement
attack (the tracking deception) has no additive signal to subtract: the PF weighs with the
mixture likelihood of the network's probability and ``attack_weight = 0`` leaves the
training to the BCE and the state loss. Validation and test run the filter as the
evaluation does (systematic resampling at every step), and validation chooses the alarm
threshold for ``target_false_alarm_rate`` on attack-free runs of their own seed
(``calibration_runs``), as ``difffilter-train calibrate`` and the evaluation choose every
detector's; ``val/fpr`` is then the rate met on the validation batch's attack-free steps,
``val/fpr_calibration`` the one on the calibration runs.

``trainer="ekf"`` trains the weights ``ζ = [W, V]`` (eq. 10) by the EKF of eqs (11)–(14)
instead (:class:`~difffilter.param_ekf.EKFOptimizer`): the filter runs on the batch with
the current weights (no gradients), records every step's network input ``δ_k``, and then,
step by step in time, one EKF update takes the batch's ``B`` samples ``(δ_k, a_k)`` as one
measurement of the network's output (open-loop scenarios). Such a network has no
detection head; it alarms on its standardised attack estimate.
"""

from __future__ import annotations

import inspect
import math
import warnings

import lightning.pytorch as pl
import torch
from lightning.fabric.utilities.apply_func import move_data_to_device
from lightning.pytorch.loggers import TensorBoardLogger

from difffilter import resampling
from difffilter._checks import check_positive_int
from difffilter.attack import Channel, attack_dim, same_side
from difffilter.estimator import Generators
from difffilter.eval.cli import EVALUATION_SEED
from difffilter.kalman import _check_linear as check_linear
from difffilter.loop import open_loop
from difffilter.metrics import after_attack, finite_scores, nan_as_lowest, roc_auc, threshold_for
from difffilter.models import registry
from difffilter.models.estimators import poa_detector_for_scenario
from difffilter.models.generic_estimators import GAUSSIAN_FILTERS, deception_of
from difffilter.models.learned_estimator import NeuralCompensation, Residual, feature_dim
from difffilter.models.lfc_estimators import PROBABILITY, confirmed_statistic
from difffilter.models.neural_estimator import (
    EstimatorCard,
    NeuralFDIEstimator,
)
from difffilter.models.plant_match import PLANT_FINGERPRINT, plant_fingerprint
from difffilter.models.streams import Streams
from difffilter.models.yaml_scenario import SCENARIO_FILE_DIGEST, scenario_file_digest
from difffilter.param_ekf import EKFOptimizer, ekf_along_sequence
from difffilter.particle import ParticleFilter
from difffilter.threat_distribution import ThreatDistribution
from difffilter.threats import check_attack_fits, with_sampling_period

from .adversarial import Adversary
from .common import dtype_of, load_estimator_as, mix_seed
from .figures import attack_figure

__all__ = [
    "ScenarioDataModule",
    "FilterEstimatorTask",
    "RESAMPLERS",
    "training_batch",
    "threat_batch",
    "threat_draws",
]

#: Training resamplers (``resampler=``): gradients through resampling or around it.
RESAMPLERS = {
    "stop_gradient": lambda alpha: resampling.StopGradient(),
    "soft": lambda alpha: resampling.Soft(alpha),
    "ot": lambda alpha: resampling.OptimalTransport(),
}
_FIELDS = ("x", "y_recv", "us", "mask", "attack", "flags")


def training_batch(scenario, runs: int, seed: int, dtype: torch.dtype) -> dict:
    """``runs`` runs of ``scenario`` from the named streams of ``seed`` (as ``difffilter-eval
    --seed``): the trajectories' ``x, y_recv, attack, flags`` (and ``us``, ``mask``) of an
    open-loop scenario, or the exogenous draws of a closed-loop one
    (:meth:`~difffilter.models.scenario.Scenario.exogenous`)."""
    streams = Streams(seed)
    gens = streams.simulation()
    if scenario.closed_loop:
        return scenario.exogenous(runs, gens, dtype=dtype)
    tr = scenario.simulate(runs, gens, dtype=dtype)
    return {k: getattr(tr, k) for k in _FIELDS if getattr(tr, k) is not None}


def evaluation_batch(scenario, runs: int, seed: int, dtype: torch.dtype) -> dict:
    """:func:`training_batch` on exactly the runs ``difffilter-eval --seed seed`` scores:
    drawn in float64, as the evaluation draws them, then cast to ``dtype`` (torch's CPU
    ``randn`` gives other numbers in float32 from 16 draws on: a float32 test scored other
    runs, 0.42 apart on four_tank_bias)."""
    batch = training_batch(scenario, runs, seed, torch.float64)
    return {k: v.to(dtype) if v.is_floating_point() else v for k, v in batch.items()}


def threat_draws(threats: ThreatDistribution, runs: int, seed: int) -> list[tuple[str, object]]:
    """The ``(name, attack)`` of each of the ``runs`` runs of a batch of seed ``seed``: drawn
    in turn from stream ``threats`` of ``Streams(seed)``, without simulating (what
    :func:`threat_batch` simulates, and what a training records it drew)."""
    draw = Streams(seed)("threats")
    return [threats.sample(draw) for _ in range(runs)]


def threat_batch(scenario, threats: ThreatDistribution, runs: int, seed: int,
                 dtype: torch.dtype) -> dict:  # fmt: skip
    """``runs`` runs of an open-loop ``scenario``, each under its own threat drawn from
    ``threats`` (stream ``threats`` of ``Streams(seed)``; run ``i`` simulated from the
    streams of ``mix_seed(seed, i)``): :func:`training_batch`'s fields, an attack-free
    run's ``attack`` zeros."""
    if scenario.closed_loop:
        raise ValueError(
            f"threats: {scenario.name} is a closed-loop scenario, whose loop draws its own "
            "attack (train on its random-attack scenario instead); threats mix open-loop "
            "scenarios' attacks"
        )
    parts = []
    for i, (name, attack) in enumerate(threat_draws(threats, runs, seed)):
        sc = scenario if name == "own" else scenario.with_threat(attack)
        parts.append(training_batch(sc, 1, mix_seed(seed, i), dtype))
    width = max(p["attack"].shape[-1] for p in parts)
    if width == 0:  # every run attack-free: the entries the scenario's own attack takes
        channel = getattr(scenario.attack_model(), "channel", Channel.SENSOR)
        width = attack_dim(scenario.system(), channel)
    for p in parts:  # an attack-free run records an attack of no channels
        if p["attack"].shape[-1] != width:
            p["attack"] = p["attack"].new_zeros(p["attack"].shape[:-1] + (width,))
    return {k: torch.cat([p[k] for p in parts]) for k in parts[0]}


def _check_one_side(scenario, threats: ThreatDistribution) -> None:
    """Raise where a component of ``threats`` attacks the other side of the plant from
    ``scenario``'s own attack (the measurements against the inputs): the network estimates
    the attack of one channel, its own attack's, and a run of the other side had trained on
    the wrong target (zeros, or a sensor attack's values as an input attack's where the
    widths agree) with its flags set, or failed at validation with a raw IndexError (a
    trial)."""
    own = Channel(getattr(scenario.attack_model(), "channel", Channel.SENSOR))
    side = (
        "the inputs (actuator)"
        if own is Channel.ACTUATOR
        else "the measurements (sensor, replacement)"
    )
    for name, channels in threats.channels().items():
        if name == "own":  # (the side itself)
            continue
        other = sorted(c.value for c in channels if not same_side(c, own))
        if other:
            raise ValueError(
                f"threats.{name}: a{'n' if other[0][0] in 'aeiou' else ''} {' or '.join(other)} "
                f"attack, and {scenario.name}'s own attack is on {side}: the network estimates "
                "the attack of that one side, so every threat of its training must act there"
            )


def _evaluation_seed(model_seed: int) -> int:
    """The seed of the filter's own draws (particles) in validation, calibration and test
    runs: three words, which no training step's ``mix_seed(model_seed, step)`` (two) and no
    adversary's ``mix_seed(model_seed, step, 17)`` produce. It had been
    ``mix_seed(model_seed, 7)``, training step 7's own: its particles repeated the
    validation's and the attack-free calibration's (a seeds trial)."""
    return mix_seed(model_seed, 7, 1)


class _Keys(torch.utils.data.Dataset):
    def __init__(self, indices):
        self.indices = list(indices)

    def __len__(self):
        return len(self.indices)

    def __getitem__(self, i):
        return {"index": torch.tensor(self.indices[i])}


class ScenarioDataModule(pl.LightningDataModule):
    """Batches of one registered scenario, drawn on the fly from seeds.

    Args:
        scenario: a registered scenario name (``difffilter-eval --list``).
        batch_size, batches_per_epoch: training runs per batch and batches per epoch.
        val_runs, val_seed: the fixed validation batch.
        train_seed: master seed of the training batches (differs from ``val_seed``);
            ``None``: ``1 + 10 s`` under ``difffilter-train --seed_everything s``, else 1.
        threats: the threats training and validation runs are drawn from, one per run (a
            :class:`~difffilter.threat_distribution.ThreatDistribution` mapping: the
            library's threats with weights and random fields, ``own`` the scenario's attack
            (refused where it has none), ``none`` attack-free; open-loop scenarios);
            ``None``: the scenario's own attack.
            ``test`` keeps the scenario's attack (the evaluation's draws).
        calibration_runs: attack-free runs on which validation chooses the alarm threshold
            (default ``val_runs``; their own seed, ``Streams(val_seed)`` stream
            ``attack-free calibration``; 0: the validation batch's attack-free steps).
        test_runs, test_seed: ``test``/``predict`` runs (default the scenario's ``runs``)
            and seed: the draws of ``difffilter-eval <scenario> --seed test_seed``.
        steps: a shorter horizon than the scenario's (tests, quick runs); the task's
            monitored scenarios keep theirs.
        dtype: ``"float32"`` or ``"float64"``.
    """

    def __init__(
        self,
        scenario: str = "four_tank_bias",
        batch_size: int = 16,
        batches_per_epoch: int = 8,
        val_runs: int = 64,
        train_seed: int | None = None,
        val_seed: int = 2,
        test_runs: int | None = None,
        test_seed: int = 0,
        steps: int | None = None,
        calibration_runs: int | None = None,
        threats: dict | None = None,
        dtype: str = "float32",
    ):
        super().__init__()
        train_seed = 1 if train_seed is None else train_seed  # (saved as resolved)
        self.scenario = registry.get(scenario)  # ValueError listing the known names
        self.threats = None
        if threats is not None:
            own = self.scenario.threat
            # a sinusoid's or chirp's frequency in the scenario's time unit, as the scenario's
            # own attack and the robustness study read it (training had drawn them per step:
            # omega = π at dt = 0.01, a zero signal with its flags set, a review)
            dt = getattr(self.scenario, "dt", None)
            timed = {name: with_sampling_period(entry, dt) for name, entry in threats.items()} \
                if isinstance(threats, dict) else threats  # fmt: skip
            self.threats = ThreatDistribution(timed, model=self.scenario.system(), own=own)
            if self._own_weight() > 0 and self.scenario.simulated_attack() is None:
                # (it had been accepted: attack-free runs, counted on the card as "own")
                raise ValueError(
                    f"threats.own: scenario {self.scenario.name!r} has no attack of its own, so "
                    "own would be an attack-free run counted as an attacked one; give own "
                    "weight 0 (none is the attack-free run), or name the attacks to train on"
                )
            if self.scenario.closed_loop:
                threat_batch(self.scenario, self.threats, 1, 0, torch.float64)  # its error
            _check_one_side(self.scenario, self.threats)
        if calibration_runs is not None and (
            isinstance(calibration_runs, bool) or not isinstance(calibration_runs, int)
            or calibration_runs < 0
        ):  # fmt: skip
            raise ValueError(
                f"calibration_runs must be a non-negative integer; got {calibration_runs!r}"
            )
        for name, val in (
            ("batch_size", batch_size),
            ("batches_per_epoch", batches_per_epoch),
            ("val_runs", val_runs),
            ("test_runs", 1 if test_runs is None else test_runs),
            ("steps", 1 if steps is None else steps),
        ):
            if isinstance(val, bool) or not isinstance(val, int) or val < 1:
                raise ValueError(f"{name} must be a positive integer; got {val!r}")
        for name, val in (("train_seed", train_seed), ("val_seed", val_seed),
                          ("test_seed", test_seed)):  # fmt: skip
            if isinstance(val, bool) or not isinstance(val, int) or val < 0:
                raise ValueError(f"{name} must be an integer >= 0; got {val!r}")
        if train_seed == val_seed:
            raise ValueError("train_seed and val_seed must differ (validation data must be unseen)")
        if test_seed in (train_seed, val_seed):
            raise ValueError("test_seed must differ from train_seed and val_seed")
        if val_seed == EVALUATION_SEED:
            # validation chooses the checkpoint (and a sweep's median seed): on seed 0 it
            # read the very runs difffilter-eval scores, bit for bit, with test_seed moved
            # off 0 (a leakage trial; the monitors' seed was refused so already)
            raise ValueError(
                f"val_seed must differ from {EVALUATION_SEED}, the seed of difffilter-eval's "
                "default runs: validation chooses the checkpoint, and would choose it on the "
                "runs the evaluation scores; keep the default 2, or any seed no evaluation uses"
            )
        if steps is not None:
            self.scenario = self.scenario.with_steps(steps)
        if self.threats is None and steps is not None:
            # the scenario's own attack over a shorter horizon: an onset past its last step
            # trained attack-free, then failed at validation ("could not find val/auc")
            try:
                check_attack_fits(self.scenario.attack_model(), self.scenario.system(),
                                  self.scenario.steps)  # fmt: skip
            except ValueError as exc:
                raise ValueError(
                    f"steps={steps}: scenario {self.scenario.name!r}'s attack does not fit the "
                    f"shortened horizon: {exc}; give more steps, or train across threats"
                ) from None
        if self.threats is not None:
            for name, share in self._onsets_past().items():
                warnings.warn(
                    f"threats.{name}: {share:.0%} of its onsets fall after the last of the "
                    f"{self.scenario.steps} steps; those runs train attack-free"
                    + (" (all of them: a fit refuses it)" if share >= 1 else ""),
                    stacklevel=2,
                )
        self.save_hyperparameters()
        self._dtype = dtype_of(dtype)
        self._val = self._calibration = None
        #: ``{threat name: runs}`` of the training batches drawn so far (every process's
        #: share; saved in Lightning checkpoints, so a resume goes on counting): what the
        #: weights of a checkpoint met (the card's ``threats_drawn``; a trial could not
        #: tell which threats a training drew without internal helpers)
        self.threats_drawn: dict[str, int] = {}

    def _own_weight(self) -> float:
        return float(self.threats.spec.get("own", {}).get("weight", 0))

    def _onsets_past(self) -> dict[str, float]:
        """``{name: share}`` of the threats' draws whose onset falls after the horizon
        (:meth:`~difffilter.threat_distribution.ThreatDistribution.onsets_past`), ``own``
        too: the scenario's attack, all of its runs where it starts after the last step (a
        trial's ``own`` past a shortened horizon had been neither warned about nor refused,
        where the same attack as a library entry was)."""
        past = self.threats.onsets_past(self.scenario.steps)
        if self._own_weight() > 0:
            try:
                check_attack_fits(self.scenario.simulated_attack(), self.scenario.system(),
                                  self.scenario.steps)  # fmt: skip
            except ValueError as exc:
                if "after the last step" not in str(exc):
                    raise ValueError(f"threats.own: the scenario's attack: {exc}") from None
                past["own"] = 1.0
        return past

    def state_dict(self) -> dict:
        return {} if self.threats is None else {"threats_drawn": dict(self.threats_drawn)}

    def load_state_dict(self, state_dict: dict) -> None:
        self.threats_drawn = {k: int(v) for k, v in state_dict.get("threats_drawn", {}).items()}

    def _count_drawn(self, epoch: int, index: int) -> None:
        """Count the threats of training batch ``index`` of ``epoch`` and, under several
        processes, of the batches the others train beside it (``world`` consecutive indices
        from a multiple of ``world``: :meth:`train_dataloader`'s split), so that process 0,
        whose checkpoints are written, counts every batch of the step."""
        trainer = getattr(self, "trainer", None)
        world = trainer.world_size if trainer else 1
        first = index - index % world
        for i in range(first, first + world):
            seed = mix_seed(self.hparams.train_seed, epoch, i)
            for name, _ in threat_draws(self.threats, self.hparams.batch_size, seed):
                self.threats_drawn[name] = self.threats_drawn.get(name, 0) + 1

    def batch(self, runs: int, seed: int) -> dict:
        """Training or validation runs: under :attr:`threats` where given."""
        if self.threats is not None:
            return threat_batch(self.scenario, self.threats, runs, seed, self._dtype)
        return training_batch(self.scenario, runs, seed, self._dtype)

    def calibration_data(self):
        """``(attack-free scenario, batch)`` on which validation chooses the threshold, or
        ``None`` (``calibration_runs=0``)."""
        hp = self.hparams
        runs = hp.val_runs if hp.calibration_runs is None else hp.calibration_runs
        if runs == 0:
            return None
        free = self.scenario.with_threat(None)
        if self._calibration is None:
            seed = Streams(hp.val_seed).seed_of("attack-free calibration")
            self._calibration = training_batch(free, runs, seed, self._dtype)
        return free, self._calibration

    def train_batch(self, epoch: int, index: int) -> dict:
        """Training batch ``index`` of ``epoch`` (seed ``(train_seed, epoch, index)``)."""
        return self.batch(self.hparams.batch_size, mix_seed(self.hparams.train_seed, epoch, index))

    def train_dataloader(self):
        n, trainer = self.hparams.batches_per_epoch, getattr(self, "trainer", None)
        never = [name for name, share in (self._onsets_past().items()
                                          if self.threats is not None else ()) if share >= 1]  # fmt: skip
        if never:  # (a trial's such entry trained nothing and was listed on the card as trained
            # on; refused for training only: a test of a shortened horizon reads the scenario's
            # own attack, and validation stays as it was warned)
            raise ValueError(
                f"threats.{never[0]}: every onset falls after the last of the "
                f"{self.scenario.steps} steps, so it never acts (its runs would train "
                "attack-free, and the card would list it as a threat trained on): give onsets "
                "within the horizon, or weight 0"
            )
        # DDP: each process simulates its share of the epoch's seeded batches (our own
        # split, so the data stay a function of (train_seed, epoch, batch) across resumes)
        rank, world = (trainer.global_rank, trainer.world_size) if trainer else (0, 1)
        if n % world:  # a process with one batch more waited forever in the all-reduce
            raise ValueError(
                f"batches_per_epoch ({n}) must be a multiple of the {world} processes "
                f"(--trainer.devices): each takes one batch in {world}, and all must take "
                "as many, or the gradient all-reduce waits forever"
            )
        return torch.utils.data.DataLoader(_Keys(range(rank, n, world)), batch_size=None)

    def on_after_batch_transfer(self, batch, dataloader_idx):
        # drawn here, from the trainer's epoch (right after a resume too)
        if isinstance(batch, dict) and "index" in batch:
            epoch = self.trainer.current_epoch if getattr(self, "trainer", None) else 0
            if self.threats is not None:
                self._count_drawn(epoch, int(batch["index"]))
            return self.train_batch(epoch, int(batch["index"]))
        return batch

    def val_dataloader(self):
        if self._val is None:
            self._val = self.batch(self.hparams.val_runs, self.hparams.val_seed)
        return torch.utils.data.DataLoader([self._val], batch_size=None)

    def test_dataloader(self):
        hp = self.hparams
        runs = hp.test_runs or self.scenario.runs
        test = evaluation_batch(self.scenario, runs, hp.test_seed, self._dtype)
        return torch.utils.data.DataLoader([test], batch_size=None)

    def predict_dataloader(self):
        return self.test_dataloader()


def _warn_adversarial_options_unread(options: dict) -> None:
    """Warn naming the adversarial options set to other than their defaults while
    ``adversarial_runs`` is 0 (adversarial training off: none of them is read)."""
    defaults = inspect.signature(FilterEstimatorTask.__init__).parameters

    def plain(value):  # (onsets from YAML come as a list)
        return tuple(value) if isinstance(value, list) else value

    given = [f"adversarial_{name}" for name, value in options.items()
             if plain(value) != plain(defaults[f"adversarial_{name}"].default)]  # fmt: skip
    if given:
        warnings.warn(
            f"{', '.join(given)} set while adversarial_runs is 0: adversarial training is off "
            "and they are not read; give adversarial_runs > 0 to train against crafted "
            "attacks",
            stacklevel=3,
        )


def _scored_monitor_error(seed: int, what: str) -> str:
    """Why ``monitor_seed`` ``seed`` is refused: the monitors' ``val/scenario/…`` metrics,
    which a checkpoint callback may select on, would be computed on the very runs the
    evaluation scores (a seed-hygiene audit: ``monitor_seed=0`` drew them bit for bit)."""
    return (
        f"monitor_seed must differ from {seed}, {what}: the monitored scenarios' val/ metrics "
        "(which a checkpoint callback may select on) would be computed on the runs the "
        "evaluation scores; keep the default 3, or any seed no evaluation uses"
    )


class FilterEstimatorTask(pl.LightningModule):
    """The neural FDI estimator trained through difffilter's filter on one scenario.

    Args:
        scenario: the registered scenario (its model is the filter's; a closed-loop
            scenario trains in its own loop).
        filter: ``"pf"`` (particle filter) or ``"kf"``, ``"ekf"``, ``"ukf"``.
        resampler: PF training resampler, ``"soft"`` (``soft_alpha``), ``"stop_gradient"``
            or ``"ot"``; validation, test and evaluation resample systematically.
        num_particles: PF particles (default: the scenario's).
        areas, a, b, hidden, init_scale, init, attack_scale, resid_scale, detection_head:
            the network (:class:`~difffilter.models.neural_estimator.NeuralFDIEstimator`,
            ``areas`` areas of the measurement's channels; ``model_seed`` seeds it).
        residual: the residual history it reads (``"innovation"``, ``"predicted"``,
            ``"lagged"``); standardize: divide innovations by ``√diag S``.
        gating: the network may also drop a measurement with its probability of attack
            (gating and compensation both; sensor attacks, a detection head).
        compensation: ``"full"`` (the filter subtracts ``â``) or ``"detected"`` (each
            area's estimate times its probability of attack; a detection head).
        restart: ``α``: an uncompensated copy of the Gaussian filter runs beside, and on
            every step where its χ² test at false-alarm rate ``α`` is quiet the compensated
            filter restarts from it (sensor attacks); ``None`` (default): never.
        confirm: ``β``: the network's score counts only where that copy's χ² test at rate
            ``β`` alarms as well (needs ``restart``; the loss reads the logits, so training
            is the same: the validation's scores and the exported card change); ``None``
            (default): the network's score alone.
        reject: ``ρ``: where the compensated innovation ``ν_k − â_k`` fails its χ² test at
            rate ``ρ``, the compensated filter keeps its prediction (sensor attacks);
            ``None`` (default): never.
        features: the filter's statistics the network reads (``"mask"``,
            ``"log_likelihood"``, ``"poa"``: the PoA threshold is the scenario's;
            ``"plain_innovation"``: an uncompensated copy of a Gaussian filter's;
            ``"open_loop_innovation"``: the measurement against the open-loop trajectory).
        trainer: ``"grad"`` (AdamW through the filter) or ``"ekf"`` (the EKF over the
            weights; module docstring).
        lr, weight_decay, pct_start, grad_clip: AdamW, its one-cycle schedule
            (``pct_start`` warm-up share; ``None``: a constant rate) stepped after every
            chunk, and the global gradient-norm clip (``None``: none).
        tbptt_steps: chunk length of truncated backpropagation through a closed loop
            (``None``: whole sequences; open loops always run whole and refuse it).
        ekf_lr, ekf_init_cov, ekf_init_noise, ekf_process_noise: ``η``, ``ρ(0)``, ``Υ(0)``
            and ``Q_ρ`` of the EKF trainer.
        attack_weight, bce_weight, state_weight, control_weight: loss weights (module
            docstring).
        after_attack_weight, after_attack_steps: the BCE's weight ``ω`` on the steps just
            after an attack and how many (module docstring; 1.0: every step alike).
        target_false_alarm_rate: of the operating threshold (default: the scenario's).
        adversarial_runs, adversarial_iterations, adversarial_every,
        adversarial_crafting_runs, adversarial_onsets, adversarial_resample,
        adversarial_selection_runs: adversarial training
            (:class:`~difffilter.train.adversarial.Adversary`): every ``adversarial_every``
            steps an attack is crafted against the current network, and each batch gets
            ``adversarial_runs`` runs under it (0: off; gradient trainer, open-loop sensor
            attacks); ``adversarial_resample``: fresh crafting runs at every iteration,
            ``adversarial_selection_runs``: held-out runs the attack is chosen on (0: none).
        monitor_scenarios, monitor_runs, monitor_seed: other registered scenarios whose
            attack RMSE is logged at every validation (``val/scenario/<name>/…``) and
            scored by ``test``, each over its own horizon (the data module's ``steps``
            shortens the training scenario, not these: a monitored attack may start late).
        init_from: an exported estimator (or a Lightning checkpoint of a training run) whose
            network weights this training starts from instead of ``model_seed``'s draw
            (``model_seed``: the network's draw and the training's own; ``None``: the run's
            ``seed_everything`` under ``difffilter-train``, else 0):
            fine-tuning, or a curriculum's second stage (its network settings must match).
        dtype: ``"float32"`` or ``"float64"``.
    """

    def __init__(
        self,
        scenario: str = "four_tank_bias",
        filter: str = "pf",
        resampler: str = "soft",
        soft_alpha: float = 0.5,
        num_particles: int | None = None,
        areas: int = 1,
        a: int = 3,
        b: int = 3,
        hidden: int = 16,
        init_scale: float = 0.1,
        init: str = "symmetric",
        attack_scale: float = 1.0,
        resid_scale: float = 10.0,
        detection_head: bool | None = None,
        residual: str = "innovation",
        standardize: bool = True,
        gating: bool = False,
        compensation: str = "full",
        restart: float | None = None,
        confirm: float | None = None,
        reject: float | None = None,
        features: list[str] | None = None,
        trainer: str = "grad",
        lr: float = 3e-3,
        weight_decay: float = 0.0,
        pct_start: float | None = None,
        grad_clip: float | None = 1.0,
        tbptt_steps: int | None = None,
        ekf_lr: float = 1.0,
        ekf_init_cov: float = 1.0,
        ekf_init_noise: float = 1e-2,
        ekf_process_noise: float = 0.0,
        attack_weight: float = 1.0,
        bce_weight: float = 0.1,
        state_weight: float = 1.0,
        control_weight: float = 0.0,
        after_attack_weight: float = 1.0,
        after_attack_steps: int = 20,
        target_false_alarm_rate: float | None = None,
        adversarial_runs: int = 0,
        adversarial_iterations: int = 20,
        adversarial_every: int = 16,
        adversarial_crafting_runs: int = 8,
        adversarial_onsets: tuple[int, int] = (5, 60),
        adversarial_resample: bool = False,
        adversarial_selection_runs: int = 0,
        monitor_scenarios: list[str] | None = None,
        monitor_runs: int = 4,
        monitor_seed: int = 3,
        model_seed: int | None = None,
        init_from: str | None = None,
        dtype: str = "float32",
    ):
        super().__init__()
        model_seed = 0 if model_seed is None else model_seed  # (saved as resolved)
        if isinstance(model_seed, bool) or not isinstance(model_seed, int) or model_seed < 0:
            raise ValueError(f"model_seed must be an integer >= 0; got {model_seed!r}")
        # the plant's file as it is read here, not as it is when a checkpoint is saved (an edit
        # during training then resumed unseen: a review)
        self._scenario_digest = scenario_file_digest(scenario)
        sc = registry.get(scenario)
        self._plant_fingerprint = _plant_fingerprint(sc)
        self.save_hyperparameters()
        self.scenario, self._dtype = sc, dtype_of(dtype)
        self.channel = _channel(sc)
        self.false_alarm_rate = _check_options(self.hparams, sc, self.channel)
        self.system = sc.system(self._dtype)
        if filter == "kf":  # (the filter said so at the first training step, deep in Lightning)
            try:
                check_linear(self.system)
            except TypeError as exc:
                raise ValueError(f"filter: 'kf' on {sc.name}: {exc}") from None
        self.num_particles = sc.num_particles if num_particles is None else num_particles
        self.features, self.poa_eta = tuple(features or ()), None
        if "poa" in self.features:
            self.poa_eta = float(poa_detector_for_scenario(sc, self.system).eta)
        self.deception = (
            _replacement_density(sc, self._dtype) if self.channel is Channel.REPLACEMENT else None
        )
        self.estimator = self._network()
        if init_from is not None:
            self._start_from(init_from)
        self.estimator_object(training=False)  # what the wrapper refuses, refused now
        # the operating threshold on the score, chosen at every validation; saved with it,
        # beside its false-alarm rate where it was chosen (NaN: not chosen by a validation)
        self.register_buffer("alarm_threshold", torch.tensor(0.5, dtype=torch.float64))
        self.register_buffer("alarm_threshold_rate", torch.tensor(math.nan, dtype=torch.float64))
        self._state_scale = torch.diagonal(self.system.initial.cov, dim1=-2, dim2=-1).mean()
        self.monitors = [registry.get(n) for n in (monitor_scenarios or ())]
        for other in self.monitors:  # at construction time, not silently at validation
            if other.family != sc.family or abs(other.dt - sc.dt) > 1e-12:
                raise ValueError(
                    f"monitor_scenarios: {other.name!r} is not a {sc.family} scenario at "
                    f"dt = {sc.dt} s (family {other.family!r}, dt = {other.dt} s)"
                )
        if self.monitors and monitor_seed == EVALUATION_SEED:
            raise ValueError(_scored_monitor_error(monitor_seed, "the seed of difffilter-eval's "
                                                           "default runs"))  # fmt: skip
        self.automatic_optimization = False
        self.adversary = None
        self._calibrated_at: int | None = None  # the step of the last threshold chosen on
        # calibration runs (current_threshold reuses it while no step has trained since)
        options = {"iterations": adversarial_iterations, "every": adversarial_every,
                   "crafting_runs": adversarial_crafting_runs, "onsets": adversarial_onsets,
                   "resample": adversarial_resample,
                   "selection_runs": adversarial_selection_runs}  # fmt: skip
        # checked whether or not adversarial training is on (adversarial_iterations=0 had
        # been taken without a word beside adversarial_runs=0: an adversarial trial)
        adversary = Adversary(1 if adversarial_runs == 0 else adversarial_runs, **options)
        if adversarial_runs:
            self.adversary = adversary
            self.adversary.check_horizon(sc.steps)
        else:
            _warn_adversarial_options_unread(options)

    def _start_from(self, path: str) -> None:
        """Copy the network weights of the estimator at ``path`` (``init_from``)."""
        start, _ = load_estimator_as(path, "model.init_args.init_from", dtype=self._dtype)
        mine, theirs = self.estimator.state_dict(), start.state_dict()
        wrong = sorted(k for k in mine.keys() | theirs.keys()
                       if k not in mine or k not in theirs or mine[k].shape != theirs[k].shape)  # fmt: skip
        if wrong:
            raise ValueError(
                f"init_from: the network of {path} does not match this config's (a, b, hidden, "
                f"areas, features, detection head): {', '.join(wrong)} differ"
            )
        self.estimator.load_state_dict(theirs)

    def _network(self) -> NeuralFDIEstimator:
        hp, dy = self.hparams, self.system.dim_y
        if dy % hp.areas:
            raise ValueError(f"areas must divide the measurement's {dy} channels; got {hp.areas}")
        d = dy // hp.areas
        head = hp.trainer == "grad" if hp.detection_head is None else hp.detection_head
        return NeuralFDIEstimator(
            num_areas=hp.areas, area_dim=self.system.dim_u if self.channel is Channel.ACTUATOR
            else d, resid_dim=d, a=hp.a, b=hp.b, hidden=hp.hidden, init_scale=hp.init_scale,
            init=hp.init, attack_scale=hp.attack_scale, resid_scale=hp.resid_scale,
            extra_inputs=feature_dim(self.features, d), detection_head=head,
            seed=hp.model_seed, dtype=self._dtype,
        )  # fmt: skip

    def configure_callbacks(self):
        """Every run logs its learning rate per step (``lr-AdamW``, ``lr-EKFOptimizer``),
        whatever its config lists (one logging contract for every trainer); a run without
        a logger logs nothing."""
        if self._trainer is None or not self.trainer.loggers:
            return []
        return [pl.callbacks.LearningRateMonitor(logging_interval="step")]

    def configure_optimizers(self):
        hp = self.hparams
        if hp.trainer == "ekf":
            return EKFOptimizer(
                [self.estimator.W, self.estimator.V], lr=hp.ekf_lr, init_cov=hp.ekf_init_cov,
                init_noise=hp.ekf_init_noise, process_noise=hp.ekf_process_noise,
            )  # fmt: skip
        opt = torch.optim.AdamW(self.estimator.parameters(), lr=hp.lr, weight_decay=hp.weight_decay)
        if hp.pct_start is None:
            return opt
        sched = torch.optim.lr_scheduler.OneCycleLR(
            opt, max_lr=hp.lr, total_steps=self._schedule_length(), pct_start=hp.pct_start
        )
        return [opt], [{"scheduler": sched, "interval": "step"}]

    # -- the estimator in its loop --------------------------------------------------------
    def estimator_object(self, *, training: bool, threshold: float = 0.5, record=False):
        """The :class:`NeuralCompensation` of the current weights (a differentiable
        resampler for training the PF, systematic resampling otherwise)."""
        hp = self.hparams
        if hp.filter == "pf":
            train = training and hp.trainer == "grad"
            resampler = (
                RESAMPLERS[hp.resampler](hp.soft_alpha) if train else resampling.Systematic()
            )
            inner = ParticleFilter(self.num_particles, resampler=resampler, ess_threshold=1.0)
        else:
            inner = GAUSSIAN_FILTERS[hp.filter]
        return NeuralCompensation(
            self.estimator, inner, channel=self.channel, residual=Residual(hp.residual),
            standardize=hp.standardize, features=self.features, poa_eta=self.poa_eta,
            threshold=threshold, deception=self.deception, record_inputs=record,
            gating=hp.gating, compensation=hp.compensation, restart=hp.restart,
            confirm=hp.confirm, reject=hp.reject,
            evidence=False,  # no loss, metric or monitor of the task reads the density
        )  # fmt: skip

    def run(self, scenario, batch: dict, estimator, seed: int, *, steps=None, state=None):
        """``(output, truth)``: the estimator on ``batch`` of ``scenario`` in its loop (the
        closed loop's own :class:`~difffilter.loop.Trajectories`, or the batch itself), and
        the loop's final state (closed loop; ``None`` otherwise)."""
        gens, device = Streams(seed), self.device
        prop = gens("particles/propagate", device)
        generators = Generators(prop, prop, gens("particles/resample", device))
        # every batch (training, validation, calibration, monitors, crafted attacks) is
        # drawn on the CPU, the same draws on any device; the filter runs where the weights are
        batch = move_data_to_device(batch, device)
        if scenario.closed_loop:
            loop = scenario.loop(estimator, batch, generator=generators, steps=steps, state=state)
            t = loop.trajectories
            truth = {"x": t.x, "attack": t.attack, "flags": t.flags}
            return loop.output, truth, loop.state
        out = open_loop(estimator, self.system, batch["y_recv"], batch.get("us"),
                        mask=batch.get("mask"), generator=generators)  # fmt: skip
        return out, batch, None

    # -- training -------------------------------------------------------------------------
    def _losses(self, out, truth) -> dict:
        hp = self.hparams
        err = out.attack - truth["attack"]
        losses = {
            "attack_mse": err.square().mean(),
            "state_mse": (out.means - truth["x"]).square().mean() / self._state_scale,
        }
        logits = out.extras.get("area_logits", out.extras.get("attack_logit"))
        if logits is not None and hp.bce_weight > 0:
            flags = _area_flags(truth, logits)
            weight = None
            if hp.after_attack_weight != 1.0:
                after = after_attack(flags, hp.after_attack_steps)
                weight = 1.0 + (hp.after_attack_weight - 1.0) * after.to(logits.dtype)
            bce = torch.nn.functional.binary_cross_entropy_with_logits(
                logits, flags.to(logits.dtype), weight=weight
            )
            losses["bce"] = bce
        if hp.control_weight > 0:
            gain = self.scenario.feedback_gain(err.dtype).to(err.device)
            losses["control_mse"] = (err @ gain.T).square().mean()
        losses["loss"] = (
            hp.attack_weight * losses["attack_mse"]
            + hp.bce_weight * losses.get("bce", 0.0)
            + hp.state_weight * losses["state_mse"]
            + hp.control_weight * losses.get("control_mse", 0.0)
        )
        return losses

    def training_step(self, batch, batch_idx):
        seed = mix_seed(self.hparams.model_seed, self.global_step)
        if self.hparams.trainer == "ekf":
            return self._ekf_step(batch, seed)
        opt, sched = self.optimizers(), self.lr_schedulers()
        if self.adversary is not None:
            batch = self._adversarial(batch, seed)
        est = self.estimator_object(training=True)
        T = _horizon(self.scenario, batch)
        chunk = (self.hparams.tbptt_steps or T) if self.scenario.closed_loop else T
        totals, norms, state = {}, [], None
        for start in range(0, T, chunk):  # truncated backpropagation through time
            steps = min(chunk, T - start)
            out, truth, state = self.run(self.scenario, batch, est, seed, steps=steps, state=state)
            state = None if state is None else state.detach()
            losses = self._losses(out, truth)
            opt.zero_grad()
            self.manual_backward(losses["loss"])
            norms.append(self._clip())
            opt.step()
            if sched is not None:
                sched.step()
            for k, v in losses.items():
                totals[k] = totals.get(k, 0.0) + float(v.detach()) * steps / T
        runs = _runs(batch)
        for k, v in totals.items():
            self.log(f"train/{k}", v, prog_bar=k == "loss", batch_size=runs)
        self.log("train/grad_norm", max(norms), batch_size=runs)

    def _adversarial(self, batch: dict, seed: int) -> dict:
        """``batch`` with the adversary's runs (a new attack crafted when due, from the
        second epoch on, once a threshold the attacker must stay under has been chosen for
        the network: :meth:`_threshold_chosen`)."""
        adversary = self.adversary
        # (a threshold chosen for the network: without calibration runs, one validation
        # first; with check_val_every_n_epoch > 1 the crafting had run under the placeholder
        # 0.5, at which the network alarmed on none of the crafting runs' steps and the alarm
        # budget bounded nothing: an adversarial trial)
        if (adversary.due(self.global_step) and self.current_epoch >= 1
                and self._threshold_chosen()):  # fmt: skip
            logs = adversary.craft(self, self.global_step)
            # straight to the loggers, once, at the step it crafted: a value given to
            # self.log stays in the epoch's results and went to TensorBoard again at every
            # later logging step of the epoch (a trial's one crafting read as two)
            for logger in self.loggers:
                logger.log_metrics(
                    {f"train/{k}": v for k, v in logs.items()}, step=self.global_step
                )
        if adversary.attack is None:
            return batch
        return adversary.augment(batch, self.scenario_of_data(), mix_seed(seed, 23), self._dtype)

    def _clip(self) -> float:
        params = list(self.estimator.parameters())
        limit = self.hparams.grad_clip if self.hparams.grad_clip is not None else math.inf
        return float(torch.nn.utils.clip_grad_norm_(params, limit))

    def _ekf_step(self, batch, seed: int):
        """The EKF over ``ζ = [W, V]``: one update per time step from the batch's samples."""
        with torch.no_grad():
            est = self.estimator_object(training=True, record=True)
            out, truth, _ = self.run(self.scenario, batch, est, seed)
            deltas, template = out.extras["network_inputs"], self.estimator.area_template()
            received = batch.get("mask") if self.channel is Channel.SENSOR else None
            if received is None:
                received = torch.ones_like(truth["attack"], dtype=torch.bool)
            runs, net = deltas.shape[0], self.estimator

            def predict(delta):  # at the weights the last update left
                params = {"W": net.W[0].expand(runs, -1, -1), "V": net.V[0].expand(runs, -1, -1)}
                return template.batched_jacobian(params, delta.to(net.V))

            sq_err = ekf_along_sequence(self.optimizers().step, predict, deltas, truth["attack"],
                                        received)  # fmt: skip
        mse = sq_err.mean() / truth["attack"].shape[-1]  # per entry, before updates
        self.log("train/attack_mse", mse, prog_bar=True, batch_size=runs)
        self.log("train/loss", mse, batch_size=runs)  # the EKF's objective: the same tag as grad

    def _schedule_length(self) -> int:
        """Optimizer steps of the one-cycle schedule: batches × chunks (≥ its warm-up)."""
        steps = self.trainer.estimated_stepping_batches if self.trainer is not None else 1
        if not math.isfinite(steps) or steps < 1:
            raise ValueError(
                "--trainer.max_epochs (or max_steps) must give a finite number of steps >= 1: the "
                f"one-cycle learning-rate schedule needs its length; got {steps} steps"
            )
        dm = getattr(self.trainer, "datamodule", None)
        T = dm.scenario.steps if dm is not None else self.scenario.steps
        chunks = math.ceil(T / (self.hparams.tbptt_steps or T))
        return max(int(steps) * chunks, math.ceil(2.0 / self.hparams.pct_start) + 2)

    def on_train_start(self):
        # A resumed run restores the schedule of the checkpoint, whose length was fixed by
        # its max_epochs: a longer run would step past its end ("Tried to step N times").
        sched = self.lr_schedulers()
        restored = getattr(sched, "total_steps", None)
        if restored is not None and restored != self._schedule_length():
            raise ValueError(
                f"--ckpt_path: the checkpoint's learning-rate schedule has {restored} steps but "
                f"this run needs {self._schedule_length()} (its --trainer.max_epochs differs); "
                "resume with the checkpoint's max_epochs, or start a new run"
            )

    # -- validation, test, predict --------------------------------------------------------
    def _evaluate(self, scenario, batch, threshold: float = 0.5):
        with torch.no_grad():
            est = self.estimator_object(training=False, threshold=threshold)
            out, truth, _ = self.run(
                scenario, batch, est, _evaluation_seed(self.hparams.model_seed)
            )
        return out, truth

    def _choose_threshold(self, score, flags) -> tuple[float, float, bool]:
        """``(τ, its false-alarm rate where it was chosen, chosen on calibration runs)``: τ
        for ``target_false_alarm_rate`` on the data module's attack-free calibration runs
        (:func:`~difffilter.metrics.threshold_for`, as ``difffilter-train calibrate`` and
        the evaluation choose it), else on the attack-free steps of ``score``."""
        chosen = self._calibrated_threshold()
        if chosen is not None:
            return (*chosen, True)
        quiet = finite_scores(score[~flags])
        if not quiet.numel():
            return 0.5, math.nan, False
        threshold = threshold_for(quiet, self.false_alarm_rate)
        return threshold, float((quiet > threshold).double().mean()), False

    def _calibrated_threshold(self) -> tuple[float, float] | None:
        """``(τ, its false-alarm rate there)`` for ``target_false_alarm_rate`` on the data
        module's attack-free calibration runs, for the weights as they are; ``None`` without
        such runs."""
        dm = getattr(self.trainer, "datamodule", None) if self._trainer is not None else None
        data = dm.calibration_data() if hasattr(dm, "calibration_data") else None
        if data is None:
            return None
        free, _ = self._evaluate(*data)
        calibration = finite_scores(free.detection.scores)
        threshold = threshold_for(calibration, self.false_alarm_rate)
        return threshold, float((calibration > threshold).double().mean())

    def _threshold_chosen(self) -> bool:
        """Whether :meth:`current_threshold` is one chosen for the network: on the data
        module's calibration runs, or by a validation (its measured rate recorded); not the
        placeholder the task starts with."""
        dm = getattr(self.trainer, "datamodule", None) if self._trainer is not None else None
        if hasattr(dm, "calibration_data") and dm.calibration_data() is not None:
            return True
        return math.isfinite(float(self.alarm_threshold_rate))

    def current_threshold(self) -> float:
        """τ for the weights as they are now, chosen as validation chooses it, on the data
        module's attack-free calibration runs: the last validation's where the weights have
        not changed since (no training step after it), else chosen again; the last
        validation's where there are no such runs. What the adversary crafts under: a
        crafting between validations had read the threshold of older weights (a user
        trial: every 3 steps of 4 a batch, the current network alarmed on 100 % of the
        crafting runs at it, and the alarm budget constrained nothing)."""
        if self._calibrated_at == self.global_step:
            return float(self.alarm_threshold)
        chosen = self._calibrated_threshold()
        return float(self.alarm_threshold) if chosen is None else chosen[0]

    def _scores(self, stage: str, scenario, batch, threshold: float | None) -> dict:
        """Evaluate on ``batch``; with ``threshold=None`` choose it (validation)."""
        out, truth = self._evaluate(scenario, batch)
        score, flags = out.detection.scores, truth["flags"]
        calibration_fpr = None
        if threshold is None:
            threshold, rate, on_calibration_runs = self._choose_threshold(score, flags)
            # (the training step it was chosen at, for the weights of that step)
            self._calibrated_at = self.global_step if on_calibration_runs else None
            self.alarm_threshold.fill_(threshold)
            self.alarm_threshold_rate.fill_(rate)
            calibration_fpr = rate if on_calibration_runs else None
        alarms = score > threshold
        scores = {
            "attack_rmse": float((out.attack - truth["attack"]).square().mean().sqrt()),
            "state_rmse": float((out.means - truth["x"]).square().mean().sqrt()),
            "auc": roc_auc(nan_as_lowest(score), flags),  # a step without a score: lowest
            "tpr": float(alarms[flags].double().mean()) if bool(flags.any()) else float("nan"),
            "fpr": float(alarms[~flags].double().mean()) if bool((~flags).any()) else float("nan"),
            "threshold": threshold,
        }
        if calibration_fpr is not None:
            scores["fpr_calibration"] = calibration_fpr
        runs = flags.shape[0]
        for k, v in scores.items():
            if math.isfinite(v):
                self.log(f"{stage}/{k}", v, prog_bar=k == "attack_rmse", batch_size=runs,
                         sync_dist=True)  # fmt: skip
        self._figure(f"{stage}/attack_estimate", scenario, out, truth)
        return scores

    def on_fit_start(self) -> None:
        if self.adversary is not None:  # the data's horizon, shorter than the scenario's
            # (--data.init_args.steps): onsets past it had been refused an epoch later, at
            # the first crafting (an adversarial trial)
            self.adversary.check_horizon(self.scenario_of_data().steps)
        dm = getattr(self.trainer, "datamodule", None)
        test_seed = None if dm is None else dm.hparams.get("test_seed")
        if self.monitors and self.hparams.monitor_seed == test_seed:
            raise ValueError(_scored_monitor_error(test_seed, "the data module's test_seed"))

    def validation_step(self, batch, batch_idx):
        self._scores("val", self.scenario_of_data(), batch, None)
        if not getattr(self.trainer, "sanity_checking", False):
            for sc in self.monitors:
                self._monitor("val", sc, self.hparams.monitor_seed)

    def on_validation_epoch_end(self):
        # the epoch whose validation the metrics now hold (on_save_checkpoint records them
        # with the weights they scored; not the sanity check's)
        if not getattr(self.trainer, "sanity_checking", False):
            self._validated_epoch = self.current_epoch

    def test_step(self, batch, batch_idx):
        self._scores("test", self.scenario_of_data(), batch, float(self.alarm_threshold))
        for sc in self.monitors:
            self._monitor("test", sc, self.trainer.datamodule.hparams.test_seed)

    def _monitor(self, stage: str, scenario, seed: int) -> None:
        runs = self.hparams.monitor_runs
        batch = evaluation_batch(scenario, runs, seed, self._dtype)
        out, truth = self._evaluate(scenario, batch, float(self.alarm_threshold))
        rmse = float((out.attack - truth["attack"]).square().mean().sqrt())
        self.log(f"{stage}/scenario/{scenario.name}/attack_rmse", rmse, batch_size=runs,
                 sync_dist=True)  # fmt: skip
        self._figure(f"{stage}/scenario/{scenario.name}", scenario, out, truth)

    def scenario_of_data(self):
        """The data module's scenario (a shorter horizon of the configured one, in tests)."""
        dm = getattr(self.trainer, "datamodule", None) if self._trainer is not None else None
        return self.scenario if dm is None else dm.scenario

    def predict_step(self, batch, batch_idx):
        out, _ = self._evaluate(self.scenario_of_data(), batch, float(self.alarm_threshold))
        return {
            "attack_estimate": out.attack,
            "attack_probability": out.detection.scores,
            "alarms": out.detection.alarms,
            "means": out.means,
        }

    def _figure(self, tag: str, scenario, out, truth) -> None:
        experiment = getattr(self.logger, "experiment", None)
        if experiment is None or not hasattr(experiment, "add_figure"):
            return
        from difffilter.eval.plots import shown_run

        # the first attacked run, as the evaluation's figures show (run 0 of a scenario
        # attacking a share of its runs may be clean: an injected signal of zeros beside a
        # noisy estimate, a figures trial)
        run = shown_run(truth["flags"]) if "flags" in truth else 0
        fig = attack_figure(truth["attack"][run], out.attack[run].detach(), scenario.dt,
                            actuator=self.channel is Channel.ACTUATOR)  # fmt: skip
        fig.axes[0].set_title(f"run {run}", fontsize=8)
        experiment.add_figure(tag, fig, global_step=self._logged_step())

    def _logged_step(self) -> int:
        """The step Lightning logs this stage's scalars at: its count of training batches
        that stepped (a validation inside the epoch's last batch runs before that batch is
        counted), not ``global_step``, the optimizers' steps (the EKF trainer takes one per
        time step): the figure of a validation had landed a step after its scalars (a
        TensorBoard trial), the EKF trainer's far after them."""
        loop = getattr(getattr(self._trainer, "fit_loop", None), "epoch_loop", None)
        return int(getattr(loop, "_batches_that_stepped", self.global_step))

    def on_fit_end(self):
        best = None
        for cb in self.trainer.callbacks if self.trainer is not None else ():
            if isinstance(cb, pl.callbacks.ModelCheckpoint) and cb.best_model_score is not None:
                best = float(cb.best_model_score)
        if best is None:
            return
        dm = getattr(self.trainer, "datamodule", None)
        params = {**({} if dm is None else dict(dm.hparams)), **dict(self.hparams)}
        for logger in self.loggers:  # the run's settings beside its result
            if isinstance(logger, TensorBoardLogger):  # its HPARAMS view pairs them
                # at the step the run ended, on its curves' axis (a resumed run's score had
                # gone to step 0; the EKF trainer's, at its optimizer steps, one per time
                # step, far right of every curve); Lightning before 2.3 takes no step
                at = {"step": self._logged_step()} if _takes_step(logger.log_hyperparams) else {}
                logger.log_hyperparams(params, {"hp/best_val_score": best}, **at)
            else:  # the others take the settings alone (a CSV logger, a custom one)
                logger.log_hyperparams(params)
                logger.log_metrics({"hp/best_val_score": best}, step=self._logged_step())

    # -- export (difffilter.train.export.ExportEstimator) ----------------------------------
    def export_name(self) -> str:
        return f"{self.scenario.family}_nn_{self.hparams.trainer}"

    def card(self) -> EstimatorCard:
        """What evaluation needs beside the weights."""
        hp = self.hparams
        registered = {"pf": "pf_nn_"}.get(hp.filter, "gaussian_nn_") + hp.trainer
        if self.scenario.closed_loop:
            registered = f"kf_nn_{hp.trainer}"
        return EstimatorCard(
            scenario_family=self.scenario.family, scenario=self.scenario.name,
            filter=hp.filter, trainer=hp.trainer, channel=self.channel.value,
            residual=hp.residual, standardize=hp.standardize, features=self.features,
            threshold=float(self.alarm_threshold),
            target_false_alarm_rate=self.false_alarm_rate, dt=float(self.scenario.dt),
            num_particles=int(self.num_particles), poa_eta=self.poa_eta, estimator=registered,
            gating=bool(hp.gating), compensation=str(hp.compensation),
            restart=None if hp.restart is None else float(hp.restart),
            confirm=None if hp.confirm is None else float(hp.confirm),
            reject=None if hp.reject is None else float(hp.reject),
            extra=self._threshold_record(registered),
        )  # fmt: skip

    def _threshold_record(self, registered: str) -> dict:
        """``{"calibration": …}`` where a validation chose the threshold on the detection
        head's attack probability (confirmed by the gated copy where the model confirms),
        the statistic the registry's learned entries read: the entry named ``registered``
        then alarms at the card's threshold by default (an LFC entry reads a card's
        threshold only where its ``calibration`` names the entry and that statistic). Its keys
        are those of ``difffilter-train calibrate``'s record, which replaces it, where they
        apply."""
        rate = float(self.alarm_threshold_rate)
        if not getattr(self.estimator, "detection_head", False) or not math.isfinite(rate):
            return {}
        return {"calibration": {
            "target": self.false_alarm_rate, "estimator": registered,
            "score": confirmed_statistic(PROBABILITY, self.hparams.confirm),
            "restart": self.hparams.restart, "confirm": self.hparams.confirm,
            **({} if self.hparams.reject is None else {"reject": self.hparams.reject}),
            "threshold": float(self.alarm_threshold), "measured_on_calibration": rate,
            "chosen_by": "difffilter-train fit: the validation of the epoch of these weights "
            "(its attack-free calibration runs; with calibration_runs=0 its unattacked steps)",
        }}  # fmt: skip

    def check_exported(self, card: EstimatorCard, path) -> None:
        """``ValueError`` unless an exported estimator was trained with this module's filter,
        family, features, trainer, residual, standardisation, gating and compensation and
        runs with its restart, confirmation and rejection (the card's threshold was chosen
        for the score they give); its operating threshold becomes this module's."""
        mine = self.card()
        for key in ("filter", "scenario_family", "features", "trainer", "residual", "standardize",
                    "gating", "compensation", "restart", "confirm", "reject"):  # fmt: skip
            if getattr(card, key) != getattr(mine, key):
                raise ValueError(
                    f"--ckpt_path: {path} was trained with {key} = {getattr(card, key)!r}, the "
                    f"configured model has {getattr(mine, key)!r}"
                )
        self.alarm_threshold.fill_(float(card.threshold))
        measured = card.extra.get("calibration", {}).get("measured_on_calibration")
        self.alarm_threshold_rate.fill_(math.nan if measured is None else float(measured))

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        # a checkpoint written before the threshold's rate was kept: rate unknown (NaN)
        state_dict = dict(state_dict)
        state_dict.setdefault("alarm_threshold_rate", torch.tensor(math.nan, dtype=torch.float64))
        return super().load_state_dict(state_dict, strict=strict, assign=assign)

    def export_card(self, trainer, estimator=None) -> dict:
        hp = self.hparams
        how = (
            f"through difffilter's {hp.filter.upper()} (resampler for training: {hp.resampler})"
            if hp.trainer == "grad"
            else f"by the EKF over its weights inside difffilter's {hp.filter.upper()}"
        )
        loop = " in its closed loop" if self.scenario.closed_loop else ""
        # across threats: named (a trial's card said its scenario alone, the distribution
        # only under data_config)
        threats = getattr(getattr(trainer, "datamodule", None), "threats", None)
        across = ("" if threats is None else
                  f", its attacks drawn from a distribution over threats ({', '.join(threats.names)})")  # fmt: skip
        # the plant file's bytes as training read them (difffilter-eval and calibrate say
        # where the file has changed since: a trial's edit had gone unseen)
        digest = (
            {} if self._scenario_digest is None else {"scenario_file_sha256": self._scenario_digest}
        )
        # the plant as training built it, whatever the scenario's kind (a module:object plant
        # edited after training had gone unseen: the file digest covers YAML files alone)
        if self._plant_fingerprint is not None:
            digest["scenario_plant_sha256"] = self._plant_fingerprint
        return {
            **digest,
            "scenario_family": self.scenario.family,
            "estimator": self.card().estimator,
            "description": f"Neural FDI estimator (eqs 8-9) trained {how}{loop} on "
            f"{self.scenario.name}{across}",
        }

    def on_save_checkpoint(self, checkpoint):
        # a Lightning checkpoint of this task loads as an estimator (difffilter-eval --ckpt)
        checkpoint["difffilter_observer"] = self.card().to_dict()
        checkpoint["difffilter_estimator_config"] = self.estimator.config()
        if self._scenario_digest is not None:  # a resume checks the plant's file is the same
            checkpoint[SCENARIO_FILE_DIGEST] = self._scenario_digest
        if getattr(self, "_plant_fingerprint", None) is not None:  # (read by plant_match)
            checkpoint[PLANT_FINGERPRINT] = self._plant_fingerprint
        if self.adversary is not None:  # a resumed run goes on with the same crafted attack
            checkpoint["difffilter_adversary"] = self.adversary.state_dict()
        if getattr(self, "_validated_epoch", None) == self.current_epoch:
            # the validation scores of these weights, for an export's card: the checkpoint
            # callback's own current_score is its last improvement's, and an export of a
            # last.ckpt from an epoch that did not improve had reported another epoch's score
            # (a trial: 0.9875 where these weights scored 0.9803)
            metrics = self.trainer.callback_metrics
            checkpoint["difffilter_validation"] = {
                "epoch": int(self.current_epoch),
                "metrics": {k: float(v) for k, v in metrics.items() if k.startswith("val/")},
            }

    def on_load_checkpoint(self, checkpoint):
        if self.adversary is not None and "difffilter_adversary" in checkpoint:
            self.adversary.load_state_dict(checkpoint["difffilter_adversary"])


def _replacement_density(sc, dtype: torch.dtype):
    """The density of a replaced measurement that a network for a replacement-channel attack
    weighs it by (a :class:`~difffilter.models.attacks.Replacement`'s box), or a
    ``ValueError`` that says why there is none and what to train on instead (a trial's
    replay stopped with "no deception density for an attack of type Replay")."""
    attack = sc.attack_model()
    try:
        return deception_of(attack, dtype)[0]
    except ValueError:
        raise ValueError(
            f"scenario {sc.name}'s attack, a {type(attack).__name__}, replaces the "
            "measurements (Channel.REPLACEMENT), and a network for such an attack weighs a "
            "replaced measurement by the attack's density, which it has none of (a "
            "Replacement's box U(low, high) has one): train on the same plant under a "
            "sensor attack (a bias, or an attack of your own on Channel.SENSOR), then judge "
            "the network under the replay with difffilter-eval --scenario <that scenario> "
            "--threats replay --ckpt <the export> (docs/threats.md)"
        ) from None


def _plant_fingerprint(scenario) -> str | None:
    """:func:`~difffilter.models.plant_match.plant_fingerprint` of the training scenario, or
    ``None`` where its plant cannot be fingerprinted (the card then records none, as
    before: a plant of one's own holding what the fingerprint cannot read is not refused)."""
    try:
        return plant_fingerprint(scenario)
    except Exception:
        return None


def _channel(scenario) -> Channel:
    attack = scenario.attack_model()
    return Channel.SENSOR if attack is None else Channel(attack.channel)


#: Options that must be finite numbers, and whether 0 is allowed (a loss term switched off)
#: or not (``grad_clip`` 0 froze the network, and a negative one reversed every step:
#: gradient ascent; ``grad_clip`` may also be ``None``).
_FINITE_OPTIONS = {
    "attack_weight": True, "bce_weight": True, "state_weight": True, "control_weight": True,
    "weight_decay": True, "after_attack_weight": False, "grad_clip": False, "lr": False,
    "ekf_lr": False, "ekf_init_cov": False,
}  # fmt: skip


def _check_options(hp, sc, channel: Channel) -> float:
    """The option combinations the task refuses, each with the reason; returns the FAR.
    (What the estimator itself refuses, :class:`NeuralCompensation` says on construction.)"""
    if hp.filter != "pf" and hp.filter not in GAUSSIAN_FILTERS:
        raise ValueError(
            f"filter must be 'pf' or one of {sorted(GAUSSIAN_FILTERS)}; got {hp.filter!r}"
        )
    if hp.resampler not in RESAMPLERS:
        raise ValueError(f"resampler must be one of {sorted(RESAMPLERS)}; got {hp.resampler!r}")
    if hp.trainer not in ("grad", "ekf"):
        raise ValueError(f"trainer must be 'grad' or 'ekf'; got {hp.trainer!r}")
    if sc.closed_loop and hp.trainer == "ekf":
        raise ValueError(f"trainer: {sc.name} is a closed loop; the EKF trainer runs open loops")
    if sc.closed_loop and hp.filter != "kf":  # it trained to the end, then failed at export
        raise ValueError(
            f"filter: {sc.name} is a closed loop, whose learned estimator (kf_nn_{hp.trainer}) "
            f"runs the Kalman filter; got {hp.filter!r}"
        )
    check_positive_int(hp.areas, "areas")
    if hp.trainer == "ekf":
        _check_ekf_trainer_options(hp)
    check_positive_int(hp.monitor_runs, "monitor_runs")
    if not 0.0 < hp.soft_alpha <= 1.0:
        raise ValueError(f"soft_alpha must be in (0, 1] (the soft resampler's mixture "
                         f"weight); got {hp.soft_alpha!r}")  # fmt: skip
    for name, zero_allowed in _FINITE_OPTIONS.items():
        value, optional = getattr(hp, name), name == "grad_clip"
        if value is None and optional:
            continue
        if not (0.0 <= value if zero_allowed else 0.0 < value) or not value < math.inf:
            bound = ">= 0" if zero_allowed else "> 0"
            raise ValueError(f"{name} must be a finite number {bound}"
                             f"{' or None' if optional else ''}; got {value!r}")  # fmt: skip
    if hp.pct_start is not None and not 0.0 <= hp.pct_start <= 1.0:
        raise ValueError(f"pct_start must be in [0, 1] or None; got {hp.pct_start!r}")
    if hp.control_weight > 0 and not sc.closed_loop:
        raise ValueError("control_weight needs a closed-loop scenario (its feedback gain)")
    if hp.adversarial_runs and (hp.trainer != "grad" or sc.closed_loop
                                or channel is not Channel.SENSOR):  # fmt: skip
        raise ValueError(
            "adversarial_runs needs the gradient trainer on an open-loop scenario with a "
            f"sensor attack; {sc.name} is {'closed' if sc.closed_loop else 'open'}-loop with a "
            f"{channel.value} attack, trainer {hp.trainer!r}"
        )
    steps = hp.after_attack_steps
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise ValueError(f"after_attack_steps must be an integer >= 1; got {steps!r}")
    if hp.tbptt_steps is not None and hp.tbptt_steps < 1:
        raise ValueError(f"tbptt_steps must be >= 1 or None; got {hp.tbptt_steps!r}")
    if hp.tbptt_steps is not None and not sc.closed_loop:  # (it would only stretch the schedule)
        raise ValueError(f"tbptt_steps needs a closed-loop scenario; {sc.name} is open-loop and "
                         "trains on whole sequences")  # fmt: skip
    far = sc.false_alarm_rate if hp.target_false_alarm_rate is None else hp.target_false_alarm_rate
    if not 0 < far < 1:
        raise ValueError(f"target_false_alarm_rate must be in (0, 1); got {far!r}")
    return float(far)


#: The gradient trainer's options, which the EKF trainer never reads (its step is ``ekf_lr``,
#: ``ekf_init_cov``, ``ekf_init_noise``, ``ekf_process_noise``; its objective the attack's
#: squared error; the particle filter resamples systematically in its runs).
_GRAD_TRAINER_OPTIONS = (
    "resampler", "soft_alpha", "lr", "weight_decay", "pct_start", "grad_clip",
    "attack_weight", "bce_weight", "state_weight", "after_attack_weight", "after_attack_steps",
)  # fmt: skip


def _check_ekf_trainer_options(hp) -> None:
    """What ``trainer: ekf`` refuses: more than one area, and a detection head (the EKF
    trains ``W`` and ``V`` alone: the head shipped at its initial draw, and the card's
    threshold was that random head's). A gradient trainer's option set away from its
    default is said in a warning: it is recorded on the card and not read (a training
    trial's ``lr 0.5``, ``grad_clip 0.01`` and ``resampler ot`` gave the default run's very
    weights without a word). A warning, not a refusal: a config written for both trainers
    (``robot_threats.yaml``) sets the gradient's, and its comment switches to the EKF on
    the command line (a review)."""
    if hp.areas != 1:  # the EKF over the weights is one area's
        raise ValueError(f"areas: the EKF trainer trains one area's network; got {hp.areas}")
    if hp.detection_head:
        raise ValueError(
            "detection_head: the EKF trainer trains the attack estimate's weights (W, V) alone, "
            "so a head would ship at its initial draw; leave it out (the network then alarms on "
            "its squared standardised estimate) or train with trainer: grad"
        )
    defaults = inspect.signature(FilterEstimatorTask.__init__).parameters
    ignored = [name for name in _GRAD_TRAINER_OPTIONS if hp[name] != defaults[name].default]
    if ignored:
        warnings.warn(
            f"{', '.join(f'{n}={hp[n]!r}' for n in ignored)}: the gradient trainer's, which "
            "trainer: ekf does not read (it steps by ekf_lr, ekf_init_cov, ekf_init_noise and "
            "ekf_process_noise, on the attack's squared error); the card records them as "
            "given",
            stacklevel=3,
        )


def _area_flags(truth: dict, logits: torch.Tensor) -> torch.Tensor:
    """The BCE's labels: the attacked steps ``[B, T]``, or with ``J`` area logits whether any
    channel of each area is attacked ``[B, T, J]``."""
    if logits.dim() == truth["flags"].dim():
        return truth["flags"]
    attack = truth["attack"]
    J = logits.shape[-1]
    return (attack.reshape(attack.shape[:-1] + (J, -1)) != 0).any(-1)


def _runs(batch: dict) -> int:
    return next(v for v in batch.values() if isinstance(v, torch.Tensor)).shape[0]


def _horizon(scenario, batch: dict) -> int:
    return batch["xi" if scenario.closed_loop else "y_recv"].shape[1]


def _takes_step(log_hyperparams) -> bool:
    """Whether a logger's ``log_hyperparams`` takes ``step`` (Lightning ≥ 2.3)."""
    return "step" in inspect.signature(log_hyperparams).parameters
