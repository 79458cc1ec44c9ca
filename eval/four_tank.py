"""Monte Carlo evaluation of the four-tank FDI scenarios (docs/scenarios.md, four-tank; issue 3).

One batched tensor program per scenario: every run is simulated at once, and every
estimator sees the same runs and the same random numbers (common random numbers): the
same initial particles, propagation noise and resampling uniforms, each stream from its
own identically seeded ``torch.Generator``. With a correct detection (``l̂_k = l_k``) and
``γ̂_k = γ_k`` the modified PF then reproduces the attack-free normal PF exactly, which
is what "RMSE against the attack-free normal PF" measures.

Estimators (stable names, ``metrics.json``):

==========================  =====================================================================
``normal_pf_attack_free``   bootstrap PF on the true measurements ``y`` (the reference)
``normal_pf``               bootstrap PF on ``ỹ`` with the PoA detector, log-space weights
``normal_pf_literal``       the same with the Gaussian density evaluated literally in float64
``modified_pf``             Table 2 with oracle ``γ̂ = γ`` (``γ + e`` in the noisy scenario)
``modified_pf_est``         Table 2 with ``γ̂`` from a Kalman filter on eq. (4)
``modified_pf_unknown_pl``  Table 2 with Remark 6's running ``p̂_l`` (oracle ``γ̂``)
``modified_pf_noisy_gamma`` Table 2 with ``γ̂ = γ + e``, ``e ~ N(0, 1e-2 I)`` (Table 3, column 3)
``modified_pf_eta_theorem1`` Table 2 with ``η`` recomputed by Theorem 1 for this ``R`` (if ≠ paper's)
``mixture_likelihood_pf``   bootstrap PF with the deception mixture likelihood (method [31], ρ = γ̄)
``open_loop_pf``            all weights 1/N: the paper's account of [31] with binary sensors
``chi_square_ekf``          EKF gated by a χ² test on its innovations (target false-alarm rate)
``cusum_ekf``               EKF gated by CUSUM on its innovations (τ calibrated on attack-free runs)
==========================  =====================================================================

RMSE (every estimator, both references): ``√(mean over runs, steps and the four
levels of (x̂_k − x_ref,k)²)`` in cm, over all steps ``k = 1 … T`` and over ``k > 20``;
``x_ref`` is the simulated truth or the attack-free normal PF's estimate.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from difffilter import fdi, metrics
from difffilter.extended import extended_kalman_filter
from difffilter.fdi.fused import FusedModifiedPF
from difffilter.models import registry
from difffilter.models.four_tank import FourTankScenario, simulate_attacked
from difffilter.particle import particle_filter, particle_init
from difffilter.resampling import Systematic

from .report import estimator_entry, write_metrics

__all__ = ["run_four_tank", "evaluate_scenario", "PAPER", "STREAMS"]

#: The paper's reference numbers (one realisation each; RMSE against the attack-free normal PF).
PAPER: dict[str, Any] = {
    "source": "Sadeghzadeh-Nokhodberiz, Meskin, Hasanzadeh, IEEE Access 2022, Tables 3-4",
    "realisations": 1,
    "rmse_reference": "attack-free normal PF estimate (Sec. V-B)",
    "table3": {
        "trR_0.003_oracle": {"rmse": 2.8e-3, "false_alarms": 0, "stealthy_attacks": 2},
        "trR_0.015_oracle": {"rmse": 4.6e-3, "false_alarms": 5, "stealthy_attacks": 2},
        "trR_0.003_noisy_gamma": {"rmse": 8e-3, "false_alarms": 0, "stealthy_attacks": 2},
    },
    "table4": {
        "normal_pf": {"rmse": 1.3e-2, "cpu_time_per_step_s": 1.9593e-4},
        "method_31": {"rmse": 8.2e-3, "cpu_time_per_step_s": 6.1460e-5},
        "modified_pf": {"rmse": 2.8e-3, "cpu_time_per_step_s": 6.9782e-4},
    },
    "eta": 0.233,
    "gamma_min": 0.28,
    "fig9": "normal PF with gamma_bar = 1*[1,1,1,1] misses small and large attacks, detects those in between",
}

#: Random streams; each estimator gets fresh generators seeded identically per stream.
STREAMS = {
    "plant": 1,
    "flags": 2,
    "gamma_noise": 3,
    "init": 4,
    "propagate": 5,
    "resample": 6,
    "calibration": 7,
}

#: Edges of the attack-size bins (‖γ_k‖, cm) of the detection-rate curve.
SIZE_BINS = (0.0, 0.1, 0.2, 0.28, 0.4, 0.6, 0.8, 1.0, 1.25, 1.5, 2.0, 3.0, 4.0)

_NOISY_GAMMA_VAR = 1e-2  # Table 3, column 3: γ̂ = γ + e, e ~ N(0, 1e-2 I) [P, text]


def _gen(seed: int, stream: str) -> torch.Generator:
    # one 64-bit seed per (master seed, stream): streams never overlap for different seeds
    return torch.Generator().manual_seed((seed * 1_000_003 + STREAMS[stream]) % (2**63))


def run_four_tank(
    names: Sequence[str],
    *,
    out: Path,
    seed: int = 0,
    progress: bool = True,
    runs: int | None = None,
) -> dict[str, dict]:
    """Evaluate each four-tank scenario in ``names``; writes ``<out>/<scenario>/...``.

    Returns ``{scenario: metrics}`` (the content of each ``metrics.json``).
    """
    if runs is not None and (isinstance(runs, bool) or not isinstance(runs, int) or runs < 1):
        raise ValueError(f"runs must be an integer >= 1; got {runs!r}")
    results = {}
    for name in names:
        sc = registry.get(name)
        if not isinstance(sc, FourTankScenario):
            raise ValueError(
                f"scenario {name!r} is not a four-tank scenario (family {sc.family!r})"
            )
        results[name] = evaluate_scenario(
            sc, out=Path(out) / name, seed=seed, progress=progress, runs=runs
        )
    return results


# ----------------------------------------------------------------------------- runners


class _Runner:
    """Runs estimators on one batch of trajectories under common random numbers."""

    def __init__(self, sc: FourTankScenario, model, seed: int):
        self.sc, self.model, self.seed = sc, model, seed
        self.N = sc.num_particles

    def pf_kwargs(self, batch: int) -> dict[str, Any]:
        """Identically seeded streams: initial particles, propagation noise, resampling."""
        return {
            "num_particles": self.N,
            "initial_state": particle_init(self.model, self.N, (batch,), _gen(self.seed, "init")),
            "generator": _gen(self.seed, "propagate"),
            "resample_generator": _gen(self.seed, "resample"),
            "resampler": Systematic(),
            "ess_threshold": 1.0,
        }


def _timed(fn: Callable[[], Any]) -> tuple[Any, float]:
    start = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - start


def _single_run_step_time(fn: Callable[[], Any], steps: int, repeats: int = 3) -> float:
    """Best wall time per step of ``fn`` (one run) over ``repeats`` rounds."""
    fn()  # warm-up
    return min(_timed(fn)[1] for _ in range(repeats)) / steps


# ----------------------------------------------------------------------------- metrics


def _rmse(est: Tensor, ref: Tensor, from_step: int = 0) -> float:
    return float(metrics.rmse(est[:, from_step:], ref[:, from_step:]))


def _state_metrics(means: Tensor, truth: Tensor, ref: Tensor | None) -> dict[str, Any]:
    """RMSE against the truth and the attack-free PF; ``t ≥ 20`` is ``k > 20``."""
    out: dict[str, Any] = {
        "state_rmse": _rmse(means, truth),
        "state_rmse_k_gt_20": _rmse(means, truth, 20),
        "state_rmse_per_component": metrics.rmse(means, truth, dim=(0, 1)).tolist(),
    }
    if ref is not None:
        per_run = (means - ref).square().mean(dim=(1, 2)).sqrt()
        out.update(
            state_rmse_vs_attack_free=_rmse(means, ref),
            state_rmse_vs_attack_free_k_gt_20=_rmse(means, ref, 20),
            state_rmse_vs_attack_free_per_component=metrics.rmse(means, ref, dim=(0, 1)).tolist(),
            state_rmse_vs_attack_free_median_run=float(per_run.median()),
            state_rmse_vs_attack_free_run_quantiles=torch.quantile(
                per_run, torch.tensor([0.1, 0.5, 0.9], dtype=per_run.dtype)
            ).tolist(),
            # runs in which the estimate equals the attack-free PF's (common random numbers)
            runs_identical_to_attack_free=float((per_run < 1e-9).double().mean()),
        )
    return out


def _detection_metrics(
    alarms: Tensor,
    scores: Tensor,
    flags: Tensor,
    gamma_norm: Tensor,
    gamma_min: float,
    *,
    attacked_input: bool = True,
) -> dict[str, Any]:
    """Per-step detection figures (docs/metrics.md) pooled over runs and steps."""
    B = alarms.shape[0]
    if not attacked_input:  # a filter fed the clean measurements: every alarm is false
        fa = int(alarms.sum())
        return {
            "tpr": None,
            "fpr": fa / alarms.numel(),
            "false_alarms": fa,
            "missed_attacks": None,
            "false_alarms_per_run": fa / B,
            "auc": None,
            "detection_delay": None,
        }
    rates = metrics.detection_rates(alarms, flags)
    detectable = flags & (gamma_norm > gamma_min)
    small = flags & ~(gamma_norm > gamma_min)
    # NaN scores (literal densities that all underflowed) never alarm: rank them lowest
    clean_scores = torch.nan_to_num(scores.double(), nan=-1.0)
    delay = metrics.detection_delay(alarms, flags)
    return {
        "tpr": rates["tpr"],
        "tpr_detectable": float(alarms[detectable].double().mean())
        if bool(detectable.any())
        else None,
        "fpr": rates["fpr"],
        "false_alarms": rates["false_alarms"],
        "missed_attacks": rates["missed_attacks"],
        "missed_detectable": int((detectable & ~alarms).sum()),
        "missed_small": int((small & ~alarms).sum()),
        "detectable_attacks": int(detectable.sum()),
        "false_alarms_per_run": rates["false_alarms"] / B,
        "missed_attacks_per_run": rates["missed_attacks"] / B,
        "auc": metrics.roc_auc(clean_scores, flags),
        "detection_delay": delay["mean_delay"],
        "attack_episodes": delay["episodes"],
        "episodes_detected": delay["detected"],
    }


def _attack_rmse(gamma_hat: Tensor, gammas: Tensor, flags: Tensor) -> float:
    """``√mean((γ̂_k − γ_k)²)`` over attacked steps and the four channels."""
    return float((gamma_hat - gammas)[flags].square().mean().sqrt())


def _binned_rates(alarms: Tensor, flags: Tensor, gamma_norm: Tensor) -> list[dict[str, Any]]:
    rows = []
    for lo, hi in zip(SIZE_BINS[:-1], SIZE_BINS[1:]):
        m = flags & (gamma_norm > lo) & (gamma_norm <= hi)
        n = int(m.sum())
        rows.append(
            {
                "lo": lo,
                "hi": hi,
                "steps": n,
                "rate": float(alarms[m].double().mean()) if n else None,
            }
        )
    return rows


# -------------------------------------------------------------------------- evaluation


def evaluate_scenario(
    sc: FourTankScenario,
    *,
    out: Path,
    seed: int = 0,
    progress: bool = True,
    runs: int | None = None,
) -> dict[str, Any]:
    """Run every estimator on ``runs`` Monte Carlo runs of ``sc`` and write the report.

    Runs with one intra-op thread (restored afterwards): the tensors here are at most
    B·N·dx = 4e4 elements, too small to gain from threading, and on a shared 2-core
    machine two threads made the evaluation 5× slower (3.5 min against 40 s).
    """
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with torch.no_grad():
            return _evaluate(sc, out=out, seed=seed, progress=progress, runs=runs)
    finally:
        torch.set_num_threads(threads)


def _evaluate(
    sc: FourTankScenario, *, out: Path, seed: int, progress: bool, runs: int | None
) -> dict[str, Any]:
    from tqdm.auto import tqdm

    from .four_tank_report import write_outputs

    B = runs if runs is not None else sc.runs
    T = sc.steps
    model = sc.model(torch.float64)
    attack = sc.attack()
    traj = simulate_attacked(
        model,
        attack,
        B,
        T,
        plant_generator=_gen(seed, "plant"),
        attack_generator=_gen(seed, "flags"),
    )
    gamma_norm = traj.gammas.norm(dim=-1)
    noise_gen = _gen(seed, "gamma_noise")
    gamma_noise = torch.randn(traj.gammas.shape, generator=noise_gen, dtype=traj.gammas.dtype)
    oracle = traj.gammas + math.sqrt(sc.gamma_hat_noise_var) * gamma_noise
    noisy_gamma = traj.gammas + math.sqrt(_NOISY_GAMMA_VAR) * gamma_noise

    G, Q = model.G, model.process_cov(0)
    eta_paper = float(
        fdi.attack_threshold(
            G,
            fdi.modified_pf_gain(
                G, Q, torch.diag(torch.tensor(sc.eta_design_R, dtype=torch.float64))
            ),
            sc.gamma_min,
        )
    )
    eta_thm1 = float(
        fdi.attack_threshold(G, fdi.modified_pf_gain(G, Q, model.measurement_cov(1)), sc.gamma_min)
    )
    zeta = fdi.detection_threshold(sc.p_l, sc.num_particles)
    detector = fdi.PoADetector(eta_paper, zeta)
    runner = _Runner(sc, model, seed)

    # CUSUM threshold τ: calibrated on separately seeded attack-free runs of the plant
    calib_model = sc.model(torch.float64)
    calib = simulate_attacked(
        calib_model,
        attack,
        max(B, 50),
        T,
        plant_generator=_gen(seed, "calibration"),
        attack_generator=_gen(seed, "flags"),
    )
    calib_ekf = extended_kalman_filter(model, calib.y_true)
    g_calib = fdi.normalized_innovation_squared(calib_ekf.innovations, calib_ekf.innovation_covs)
    cusum = fdi.CusumDetector(sc.cusum_bias)
    cusum.calibrate(g_calib, sc.false_alarm_rate)
    chi2 = fdi.ChiSquareDetector(model.dim_y, sc.false_alarm_rate)

    mixture = fdi.DeceptionMixtureLikelihood(
        sc.p_l, fdi.BiasDeception(torch.tensor(sc.gamma_bar, dtype=torch.float64))
    )

    def normal_pf(ys, literal=False):
        def run(b=B, y=ys):
            return fdi.particle_filter_poa(
                model, y[:b], detector=detector, literal=literal, **runner.pf_kwargs(b)
            )

        return run

    def modified(gamma_hat, *, eta=eta_paper, estimator=False, unknown_pl=False):
        def run(b=B):
            gh = fdi.BiasAttackEstimator(model.dim_y, sc.tau) if estimator else gamma_hat[:b]
            return fdi.modified_particle_filter(
                model,
                traj.y_recv[:b],
                detector=fdi.PoADetector(eta, zeta),
                gamma_hat=gh,
                attack_rate=fdi.RunningAttackRate(sc.num_particles) if unknown_pl else None,
                **runner.pf_kwargs(b),
            )

        return run

    def mixture_pf(b=B):
        kw = runner.pf_kwargs(b)
        res = particle_filter(
            model, traj.y_recv[:b], likelihood=mixture, return_particles=True, **kw
        )
        prior = fdi.prior_log_weights(res, kw["initial_state"].log_weights)
        score = mixture.attack_probability(model, traj.y_recv[:b], res.particles, prior, 1)
        return res, score

    def open_loop(b=B):
        return particle_filter(
            model, traj.y_recv[:b], likelihood=fdi.FlatLikelihood(), **runner.pf_kwargs(b)
        )

    def gated(det):
        def run(b=B):
            return fdi.gated_extended_kalman_filter(model, traj.y_recv[:b], detector=det)

        return run

    tasks: list[tuple[str, Callable, str]] = [
        ("normal_pf_attack_free", normal_pf(traj.y_true), "poa_clean"),
        ("normal_pf", normal_pf(traj.y_recv), "poa"),
        ("normal_pf_literal", normal_pf(traj.y_recv, literal=True), "poa"),
        ("modified_pf", modified(oracle), "modified"),
        ("modified_pf_est", modified(None, estimator=True), "modified"),
        ("modified_pf_unknown_pl", modified(oracle, unknown_pl=True), "modified"),
    ]
    if sc.gamma_hat_noise_var == 0:
        tasks.append(("modified_pf_noisy_gamma", modified(noisy_gamma), "modified"))
    if abs(eta_thm1 - eta_paper) > 1e-9:
        tasks.append(("modified_pf_eta_theorem1", modified(oracle, eta=eta_thm1), "modified"))
    tasks += [
        ("mixture_likelihood_pf", mixture_pf, "mixture"),
        ("open_loop_pf", open_loop, "plain"),
        ("chi_square_ekf", gated(chi2), "gated"),
        ("cusum_ekf", gated(cusum), "gated"),
    ]

    raw: dict[str, dict[str, Any]] = {}
    bar = tqdm(total=len(tasks) + 3, desc=sc.name, disable=not progress, leave=False)
    for name, run, kind in tasks:
        bar.set_postfix_str(name)
        result, wall = _timed(run)
        single = _single_run_step_time(lambda run=run: run(1), T)
        raw[name] = {"result": result, "kind": kind, "wall": wall, "single": single}
        bar.update()

    ref = raw["normal_pf_attack_free"]["result"].filter.means
    estimators: dict[str, dict[str, Any]] = {}
    series: dict[str, dict[str, Tensor]] = {}
    for name, item in raw.items():
        res, kind = item["result"], item["kind"]
        attack_rmse = None
        if kind in ("poa", "poa_clean"):
            means, alarms, scores = res.filter.means, res.alarms, res.beta
        elif kind == "modified":
            means, alarms, scores = res.means, res.alarms, res.beta
            attack_rmse = _attack_rmse(res.gamma_hat, traj.gammas, traj.flags)
        elif kind == "mixture":
            means, scores = res[0].means, res[1]
            alarms = scores > 0.5
        elif kind == "gated":
            means, alarms, scores = res.means, res.alarms, res.scores
        else:
            means, alarms, scores = res.means, None, None
        entry = _state_metrics(means, traj.x, ref)
        if alarms is not None:
            entry.update(
                _detection_metrics(
                    alarms,
                    scores,
                    traj.flags,
                    gamma_norm,
                    sc.gamma_min,
                    attacked_input=kind != "poa_clean",
                )
            )
        entry.update(
            attack_rmse=attack_rmse,
            time_per_step_s=item["wall"] / (B * T),
            time_per_step_batch_s=item["wall"] / T,
            time_per_step_single_run_s=item["single"],
        )
        if kind == "modified" and res.attack_rate is not None:
            entry["p_l_estimate_mean"] = float(res.attack_rate.mean())
        estimators[name] = estimator_entry(**entry)
        series[name] = {"means": means, "alarms": alarms, "scores": scores}

    # χ² and CUSUM on the clean measurements: their false-alarm rate without any attack
    # (the calibration target) beside the rate on the attack-free steps of attacked runs.
    for name, det in (("chi_square_ekf", chi2), ("cusum_ekf", cusum)):
        clean = fdi.gated_extended_kalman_filter(model, traj.y_true, detector=det)
        estimators[name]["fpr_on_attack_free_data"] = float(clean.alarms.double().mean())

    # The fused path (benchmarks) must agree with the composed reference.
    fused = FusedModifiedPF(model, num_particles=sc.num_particles, eta=eta_paper, zeta=zeta)
    kw = runner.pf_kwargs(B)
    fres, fwall = _timed(
        lambda: fused.run(
            traj.y_recv,
            oracle,
            generator=kw["generator"],
            resample_generator=kw["resample_generator"],
            initial_particles=kw["initial_state"].particles,
        )
    )
    ref_mod = raw["modified_pf"]["result"]

    def fused_single():
        kw1 = runner.pf_kwargs(1)
        return fused.run(
            traj.y_recv[:1],
            oracle[:1],
            generator=kw1["generator"],
            resample_generator=kw1["resample_generator"],
            initial_particles=kw1["initial_state"].particles,
        )

    estimators["modified_pf"].update(
        fused_max_abs_diff=float((fres.means - ref_mod.means).abs().max()),
        fused_alarms_identical=bool(torch.equal(fres.alarms, ref_mod.alarms)),
        time_per_step_fused_s=fwall / (B * T),
        time_per_step_single_run_fused_s=_single_run_step_time(fused_single, T, repeats=5),
    )
    bar.update()

    # Detection rate versus attack size: γ̄ = s·[1,1,1,1], same plant, flags and streams.
    bar.set_postfix_str("attack-size sweep")
    sweep = _attack_size_sweep(sc, model, traj, runner, detector, chi2, eta_paper)
    bar.update()

    # R × 5 false alarms with the paper's η and with η from Theorem 1 for that R.
    bar.set_postfix_str("high-noise check")
    high = (
        _high_noise_check(sc, seed, B, runner, eta_paper, zeta)
        if tuple(sc.R) == tuple(sc.eta_design_R)
        else None
    )
    bar.update()
    bar.close()

    extra = {
        "description": sc.description,
        "settings": {k: v for k, v in asdict(sc).items() if k not in ("notes",)},
        "notes": list(sc.notes),
        "gamma_hat": "oracle gamma_k"
        if sc.gamma_hat_noise_var == 0
        else f"oracle gamma_k + N(0, {sc.gamma_hat_noise_var} I)",
        "thresholds": {
            "eta_paper": eta_paper,
            "eta_theorem1_for_this_R": eta_thm1,
            "zeta": zeta,
            "gamma_min": sc.gamma_min,
            "cusum_bias": sc.cusum_bias,
            "cusum_threshold": cusum.threshold,
            "chi_square_threshold": chi2.threshold,
            "false_alarm_target": sc.false_alarm_rate,
        },
        "rmse_definition": (
            "sqrt of the mean over runs, steps and the four levels of (estimate - reference)^2, in cm; "
            "'all' = steps k = 1..T, 'k_gt_20' = steps k = 21..T; reference = simulated truth "
            "(state_rmse) or the attack-free normal PF's estimate under common random numbers "
            "(state_rmse_vs_attack_free); *_median_run = median over runs of the per-run RMSE"
        ),
        "detection_vs_attack_size": sweep["summary"],
        "high_noise_false_alarms": high,
        "attacked_steps": int(traj.flags.sum()),
        "attack_free_steps": int((~traj.flags).sum()),
    }
    doc_path = write_metrics(
        out / "metrics.json",
        scenario=sc.name,
        runs=B,
        steps=T,
        seed=seed,
        paper=PAPER,
        estimators=estimators,
        **extra,
    )
    from .report import read_metrics

    doc = read_metrics(doc_path)
    write_outputs(out, doc, traj=traj, series=series, sweep=sweep, ref=ref)
    return doc


def _times(R: tuple[float, ...], factor: float) -> tuple[float, ...]:
    return tuple(factor * r for r in R)


def _attack_size_sweep(
    sc, model, traj, runner: _Runner, detector, chi2, eta_paper
) -> dict[str, Any]:
    """Alarms of the normal PF (log and literal), the modified PF and the χ² EKF for each γ̄."""
    variants = ("normal_pf", "normal_pf_literal", "modified_pf", "chi_square_ekf")
    alarms: dict[str, list[Tensor]] = {v: [] for v in variants}
    norms, flags, per_scale, runs0 = [], [], [], {}
    B = traj.x.shape[0]
    for s in sc.sweep_scales:
        att = sc.attack(gamma_bar=(s,) * model.dim_y)
        real = att.apply(traj.y_true, flags=traj.flags)
        outs = {
            "normal_pf": fdi.particle_filter_poa(
                model, real.y_recv, detector=detector, **runner.pf_kwargs(B)
            ),
            "normal_pf_literal": fdi.particle_filter_poa(
                model, real.y_recv, detector=detector, literal=True, **runner.pf_kwargs(B)
            ),
            "modified_pf": fdi.modified_particle_filter(
                model, real.y_recv, detector=detector, gamma_hat=real.gammas, **runner.pf_kwargs(B)
            ),
            "chi_square_ekf": fdi.gated_extended_kalman_filter(model, real.y_recv, detector=chi2),
        }
        gn = real.gammas.norm(dim=-1)
        row = {"scale": s, "gamma_bar_norm": s * math.sqrt(model.dim_y)}
        detectable = real.flags & (gn > sc.gamma_min)
        for v in variants:
            a = outs[v].alarms
            alarms[v].append(a)
            row[v] = {
                "tpr_detectable": float(a[detectable].double().mean())
                if bool(detectable.any())
                else None,
                "fpr": float(a[~real.flags].double().mean()),
            }
        if abs(s - 1.0) < 1e-12:  # Figs 9-10: γ̄ = [1, 1, 1, 1]
            runs0 = {
                "gamma_norm": gn[0],
                "flags": real.flags[0],
                "normal_pf": outs["normal_pf"].alarms[0],
                "normal_pf_literal": outs["normal_pf_literal"].alarms[0],
                "modified_pf": outs["modified_pf"].alarms[0],
                "literal_nan_steps": int(outs["normal_pf_literal"].beta[0].isnan().sum()),
            }
            nan_rate = float(outs["normal_pf_literal"].beta.isnan().double().mean())
            row["literal_beta_nan_rate"] = nan_rate
        per_scale.append(row)
        norms.append(gn)
        flags.append(real.flags)
    gn_all, fl_all = torch.cat(norms), torch.cat(flags)
    binned = {v: _binned_rates(torch.cat(alarms[v]), fl_all, gn_all) for v in variants}
    return {
        "summary": {"per_scale": per_scale, "binned": binned, "bins": list(SIZE_BINS)},
        "fig9_run0": runs0,
    }


def _high_noise_check(sc, seed, B, runner: _Runner, eta_paper, zeta) -> dict[str, Any]:
    """Modified PF on the same runs with R × 5: false alarms with the paper's η and Theorem 1's."""
    R5 = _times(sc.R, 5.0)
    model5 = sc.model(torch.float64, R=R5)
    # same plant noise draws (scaled by the larger R) and the same attack flags
    traj5 = simulate_attacked(
        model5,
        sc.attack(),
        B,
        sc.steps,
        plant_generator=_gen(seed, "plant"),
        attack_generator=_gen(seed, "flags"),
    )
    G, Q = model5.G, model5.process_cov(0)
    eta5 = float(
        fdi.attack_threshold(G, fdi.modified_pf_gain(G, Q, model5.measurement_cov(1)), sc.gamma_min)
    )
    run5 = _Runner(sc, model5, runner.seed)
    free = fdi.particle_filter_poa(
        model5, traj5.y_true, detector=fdi.PoADetector(eta_paper, zeta), **run5.pf_kwargs(B)
    )
    out: dict[str, Any] = {
        "R": list(R5),
        "trace_R": sum(R5),
        "eta_paper": eta_paper,
        "eta_theorem1": eta5,
    }
    gn = traj5.gammas.norm(dim=-1)
    for label, eta in (("eta_paper", eta_paper), ("eta_theorem1", eta5)):
        res = fdi.modified_particle_filter(
            model5,
            traj5.y_recv,
            detector=fdi.PoADetector(eta, zeta),
            gamma_hat=traj5.gammas,
            **run5.pf_kwargs(B),
        )
        det = _detection_metrics(res.alarms, res.beta, traj5.flags, gn, sc.gamma_min)
        out[label] = {
            "eta": eta,
            "fpr": det["fpr"],
            "false_alarms": det["false_alarms"],
            "false_alarms_per_run": det["false_alarms_per_run"],
            "tpr_detectable": det["tpr_detectable"],
            "missed_attacks_per_run": det["missed_attacks_per_run"],
            "state_rmse_vs_attack_free": _rmse(res.means, free.filter.means),
            "state_rmse_vs_attack_free_k_gt_20": _rmse(res.means, free.filter.means, 20),
        }
    return out
