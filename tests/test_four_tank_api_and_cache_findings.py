"""Findings of a four-tank Python-API trial and a cache red-team run, each checked.

- the fused modified PF from a given particle set steps where its fast path declines
  (it returned ``None``);
- Theorem 1's ``ς``: the paper's ``|σ̄ − 1|`` and the guaranteed ``σ_min(I − G K)``,
  equal where ``G K`` is symmetric PSD, not where it is not;
- a per-run ``η`` of the wrong shape, a ``BiasAttackEstimator`` of the wrong size: named;
- ``p_l`` with no threshold of eq. (53): the PoA estimators skipped, the others run;
- numpy integers taken where a count is asked for;
- the calibration cache: a file of the wrong shape is computed again, and a calibration
  computed by other library code is not reused.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from difffilter import fdi
from difffilter.models import calibration_cache, registry
from difffilter.models.four_tank import FourTankModel, FourTankScenario
from difffilter.models.streams import Streams
from difffilter.particle import particle_init

F64 = torch.float64


@pytest.fixture(scope="module")
def four_tank():
    sc = registry.get("four_tank_bias").with_steps(30)
    runs = sc.simulate(3, Streams(0).simulation())
    return sc.system(), runs


def _gen(seed):
    return torch.Generator().manual_seed(seed)


# ------------------------------------------------------------ fused PF from a given state


@pytest.mark.parametrize("batched", [True, False])
def test_the_fused_modified_pf_from_a_given_state_steps_where_its_fast_path_declines(
    four_tank, batched
):
    model, runs = four_tank
    ys, gh = runs.y_recv, runs.info["attack_values"]
    if not batched:  # unbatched ys: the fused path declines
        ys, gh = ys[0], gh[0]
    batch = ys.shape[:-2]
    det = fdi.PoADetector(0.2333, 0.5)

    def run(fused):
        # one generator without resample_generator: the fused path declines too
        return fdi.modified_particle_filter(
            model, ys, num_particles=40, detector=det, gamma_hat=gh, fused=fused,
            generator=_gen(1), initial_state=particle_init(model, 40, batch, _gen(0)),
        )  # fmt: skip

    fused, stepped = run(True), run(False)
    assert fused is not None
    torch.testing.assert_close(fused.means, stepped.means, rtol=0, atol=0)
    assert torch.equal(fused.detection.alarms, stepped.detection.alarms)


# --------------------------------------------------------------------- Theorem 1's ς


def test_the_two_rules_agree_where_gk_is_symmetric_psd_the_papers_case():
    G = torch.eye(4, dtype=F64)
    R = torch.diag(torch.tensor([1e-3, 1e-3, 0.5e-3, 0.5e-3], dtype=F64))
    K = fdi.modified_pf_gain(G, 1e-4 * torch.eye(4, dtype=F64), R)
    for rule in ("paper", "guaranteed"):
        assert float(fdi.attack_threshold_factor(G, K, rule=rule)) == pytest.approx(5 / 6, 1e-12)
        assert float(fdi.attack_threshold(G, K, 0.28, rule=rule)) == pytest.approx(0.23333, 1e-4)
    with pytest.raises(ValueError, match="rule must be one of"):
        fdi.attack_threshold_factor(G, K, rule="nearest")


def test_the_guaranteed_factor_bounds_every_attack_where_the_papers_does_not():
    """A correlated R and an anisotropic Q (both accepted by FourTankModel): G K is not
    symmetric. Every attack γ leaves ‖(I − G K) γ‖ ≥ σ_min ‖γ‖ (eq. 41, what the proof
    needs); the paper's |σ̄ − 1| is larger than that bound, and an attack of norm γ_min in
    the worst direction stays below its η."""
    Q = torch.diag(torch.tensor([1e-4, 1e-2, 1e-4, 1e-4], dtype=F64))
    R = torch.tensor(
        [[1e-3, 9e-4, 0, 0], [9e-4, 1e-3, 0, 0], [0, 0, 5e-4, 0], [0, 0, 0, 5e-4]], dtype=F64
    )
    model = FourTankModel(R=R, Q=Q, dtype=F64)
    G = model.observation_matrix(1)
    K = fdi.modified_pf_gain(G, model.process_cov(0), model.measurement_cov(1))
    A = torch.eye(4, dtype=F64) - G @ K
    paper = float(fdi.attack_threshold_factor(G, K))
    guaranteed = float(fdi.attack_threshold_factor(G, K, rule="guaranteed"))
    assert guaranteed == pytest.approx(0.0140, abs=5e-4) and paper == pytest.approx(0.261, 1e-2)
    gammas = torch.randn(2000, 4, generator=_gen(3), dtype=F64)
    gains = (gammas @ A.T).norm(dim=-1) / gammas.norm(dim=-1)
    assert bool((gains >= guaranteed * (1 - 1e-9)).all())
    worst = torch.linalg.svd(A).Vh[-1] * 0.28  # ‖γ‖ = γ_min in the direction A shrinks most
    det = fdi.poa_detector_for(model, gamma_min=0.28, p_l=0.5, num_particles=100)
    safe = fdi.poa_detector_for(
        model, gamma_min=0.28, p_l=0.5, num_particles=100, rule="guaranteed"
    )
    assert float((A @ worst).norm()) < float(det.eta)
    assert float((A @ worst).norm()) >= float(safe.eta) * (1 - 1e-9)


def test_an_undetectable_direction_has_a_guaranteed_factor_of_zero():
    G = torch.eye(2, dtype=F64)
    K = torch.tensor([[0.0, 2.0], [0.5, 0.0]], dtype=F64)  # (I − K)(2, 1) = 0
    assert float(fdi.attack_threshold_factor(G, K)) == pytest.approx(0.5, 1e-12)
    assert float(fdi.attack_threshold_factor(G, K, rule="guaranteed")) == pytest.approx(
        0, abs=1e-12
    )


# ------------------------------------------------------------- per-run η, γ̂'s dimension


@pytest.mark.parametrize("modified", [False, True])
def test_a_per_run_eta_of_another_count_is_named(four_tank, modified):
    model, runs = four_tank
    det = fdi.PoADetector(torch.tensor([0.1, 0.2]), 0.5)  # 2 thresholds, 3 runs
    kw = {"num_particles": 20, "detector": det, "generator": _gen(0)}
    with pytest.raises(ValueError, match=r"detector.eta has shape \(2,\).*batch shape \(3,\)"):
        if modified:
            fdi.modified_particle_filter(
                model, runs.y_recv, gamma_hat=runs.info["attack_values"], **kw
            )
        else:
            fdi.particle_filter_poa(model, runs.y_recv, **kw)


def test_a_per_run_eta_needs_the_batch_dims_and_then_applies_per_run(four_tank):
    model, runs = four_tank
    ys = runs.y_recv[:2].unsqueeze(1).expand(2, 2, *runs.y_recv.shape[1:])  # batch (2, 2)
    kw = {"num_particles": 20, "generator": _gen(0)}
    flat = fdi.PoADetector(torch.tensor([0.0, 1e9]), 0.5)  # fewer dims: torch would align
    with pytest.raises(ValueError, match=r"shape \(2,\).*batch shape \(2, 2\)"):  # it last
        fdi.particle_filter_poa(model, ys, detector=flat, **kw)
    per_row = fdi.PoADetector(torch.tensor([[0.0], [1e9]]), 0.5)  # [B, 1]: one per outer run
    out = fdi.particle_filter_poa(model, ys, detector=per_row, **kw)
    rate = out.detection.alarms.double().mean(-1)
    assert torch.equal(rate, torch.tensor([[1.0, 1.0], [0.0, 0.0]], dtype=F64))


def test_a_bias_estimator_of_another_size_than_the_measurement_is_named(four_tank):
    model, runs = four_tank
    with pytest.raises(ValueError, match="gamma_hat is a BiasAttackEstimator of dim 3.*4"):
        fdi.modified_particle_filter(
            model, runs.y_recv, num_particles=20, detector=fdi.PoADetector(0.2, 0.5),
            gamma_hat=fdi.BiasAttackEstimator(3, 0.9), generator=_gen(0),
        )  # fmt: skip


# --------------------------------------------------------------- eq. (53) with no ζ


def test_an_attack_on_every_step_skips_the_poa_estimators_and_runs_the_others():
    from difffilter.eval.suite import run_suite

    sc = FourTankScenario(name="four_tank_every_step", p_l=1.0, steps=30)
    with pytest.raises(fdi.InfeasibleThreshold, match=r"eq. \(53\)"):
        fdi.detection_threshold(1.0, sc.num_particles)
    result = run_suite(
        sc, runs=2, estimators=["chi_square_ekf", "normal_pf", "modified_pf_est"],
        progress=False,
    )  # fmt: skip
    assert set(result.metrics) == {"chi_square_ekf"}
    for name in ("normal_pf", "modified_pf_est"):
        assert "no PoA threshold" in result.skipped[name] and "eq. (53)" in result.skipped[name]
    assert result.metrics["chi_square_ekf"]["tpr"] > 0.5


# --------------------------------------------------------------------- numpy counts


def test_numpy_integers_are_counts_where_python_ints_are():
    from difffilter.eval.suite import run_suite

    assert Streams(np.int64(7)).seed_of("x") == Streams(7).seed_of("x")
    assert type(Streams(np.int64(7)).seed) is int
    assert fdi.BiasAttackEstimator(np.int64(4), 0.9).dim == 4
    assert fdi.detection_threshold(0.5, np.int32(100)) == 0.5
    rate = fdi.RunningAttackRate(np.int64(100), warmup=np.int64(5))
    assert rate.init((2,)) is not None
    sc = registry.get("four_tank_bias").with_steps(5)
    a = sc.simulate(np.int64(2), Streams(0).simulation())
    b = sc.simulate(2, Streams(0).simulation())
    assert torch.equal(a.y_recv, b.y_recv)
    for bad in (True, 2.0, np.float64(2.0), 0):
        with pytest.raises(ValueError, match="runs must be an integer >= 1"):
            run_suite(sc, runs=bad, estimators=["chi_square_ekf"], progress=False)


# ------------------------------------------------------------------ calibration cache


@pytest.mark.parametrize(
    "body",
    ["null", "[]", '{"value": null}', '{"value": {"bias": 6.0}}',
     '{"value": {"bias": 6.0, "threshold": NaN}}', '{"value": {"bias": 6.0, "threshold": "9"}}'],
)  # fmt: skip
def test_a_cusum_calibration_file_of_the_wrong_shape_is_computed_again(tmp_path, monkeypatch, body):
    from difffilter.models.estimators import _is_cusum_calibration

    monkeypatch.setenv("DIFFFILTER_CACHE", str(tmp_path))
    good = {"bias": 6.0, "threshold": 10.5}
    calls = []

    def compute():
        calls.append(1)
        return good

    args = ("cusum", ("s", 0, 50), {"Q": torch.eye(2, dtype=F64)})
    assert calibration_cache.cached(*args, compute, valid=_is_cusum_calibration) == good
    (path,) = (tmp_path / "calibrations").glob("cusum-*.json")
    path.write_text(body)
    assert calibration_cache.cached(*args, compute, valid=_is_cusum_calibration) == good
    assert len(calls) == 2  # computed again, not read
    assert json.loads(path.read_text())["value"] == good  # and the file replaced
    assert calibration_cache.cached(*args, compute, valid=_is_cusum_calibration) == good
    assert len(calls) == 2


def test_a_calibration_of_other_library_code_is_not_reused(tmp_path, monkeypatch):
    monkeypatch.setenv("DIFFFILTER_CACHE", str(tmp_path))
    args = ("cusum", ("s", 0, 50), {"Q": torch.eye(2, dtype=F64)})
    assert calibration_cache.cached(*args, lambda: {"tau": 1.0}) == {"tau": 1.0}
    assert calibration_cache.cached(*args, lambda: {"tau": 2.0}) == {"tau": 1.0}  # same code
    fingerprint = calibration_cache.library_fingerprint()
    assert len(fingerprint) == 64 and fingerprint == calibration_cache.library_fingerprint()
    monkeypatch.setattr(calibration_cache, "_LIBRARY_FINGERPRINT", "0" * 64)  # an upgrade
    assert calibration_cache.cached(*args, lambda: {"tau": 3.0}) == {"tau": 3.0}
    assert len(list((tmp_path / "calibrations").glob("cusum-*.json"))) == 2


def test_the_library_fingerprint_reads_the_models_package_too(monkeypatch, tmp_path):
    """It hashes every .py file of difffilter and difffilter.models: one byte more in a
    file of either gives another fingerprint."""
    import difffilter
    import difffilter.models

    def fingerprint_of(roots):
        monkeypatch.setattr(calibration_cache, "_LIBRARY_FINGERPRINT", None)
        monkeypatch.setattr(difffilter, "__path__", [str(roots[0])])
        monkeypatch.setattr(difffilter.models, "__path__", [str(roots[1])])
        return calibration_cache.library_fingerprint()

    core, models = tmp_path / "core", tmp_path / "models"
    for root in (core, models):
        (root / "sub").mkdir(parents=True)
        (root / "sub" / "a.py").write_text("x = 1\n")
    first = fingerprint_of((core, models))
    (models / "sub" / "a.py").write_text("x = 2\n")
    second = fingerprint_of((core, models))
    (core / "b.txt").write_text("not code")
    assert first != second == fingerprint_of((core, models))
