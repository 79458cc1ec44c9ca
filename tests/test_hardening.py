"""Regression tests for issue 12 ("Hardening"): every case listed there ends in a clear
error naming the argument, or in the documented recovery."""

from __future__ import annotations

import json
import shutil
import zipfile
from pathlib import Path

import pytest
import torch
from conftest import constant_velocity

import difffilter as df
from difffilter import fdi, resampling
from difffilter.fdi.fused import FusedModifiedPF
from difffilter.models.four_tank import FourTankModel
from difffilter.models.lfc import LFCPlant
from difffilter.models.neural_estimator import (
    CHECKPOINT_FORMAT,
    NeuralFDIEstimator,
    checkpoint_sha256,
    load_estimator_checkpoint,
    save_estimator_checkpoint,
)

F64 = torch.float64
NAN, INF = float("nan"), float("inf")
CKPT = Path(__file__).resolve().parents[1] / "checkpoints" / "lfc_nn_grad.ckpt"


def cv_data(T=6, B=(2,), dtype=F64):
    model = constant_velocity(dtype=dtype)
    _, ys, _ = model.simulate(T, B, generator=torch.Generator().manual_seed(0))
    return model, ys


def poisoned(ys, value, index=(0, 2, 1)):
    ys = ys.clone()
    ys[index] = value
    return ys


def four_tank_data(B=2, T=8, dtype=F64):
    model = FourTankModel(dtype=dtype)
    _, ys, _ = model.simulate(T, (B,), generator=torch.Generator().manual_seed(1))
    return model, ys


def poa_detector():
    return fdi.PoADetector(0.2, 0.3)


# ------------------------------------------------------------- detectors fail silently


def test_chi_square_detect_raises_on_nan_innovations():
    model, ys = cv_data()
    res = df.kalman_filter(model, ys)
    innov = res.innovations.clone()
    innov[0, 3, 0] = NAN
    det = fdi.ChiSquareDetector(2)
    with pytest.raises(ValueError, match="innovations contains NaN or Inf"):
        det.detect(innov, res.innovation_covs)
    with pytest.raises(ValueError, match="innovations contains NaN or Inf"):
        det.scores(innov, res.innovation_covs)
    covs = res.innovation_covs.clone()
    covs[0, 1, 0, 0] = INF
    with pytest.raises(ValueError, match="innovation_covs contains NaN or Inf"):
        det.detect(res.innovations, covs)


def test_chi_square_online_step_raises_on_nan_statistic():
    det = fdi.ChiSquareDetector(2, window=3)
    state = det.init((2,))
    with pytest.raises(ValueError, match="g contains NaN or −inf"):  # (+inf: an alarm)
        det.step(state, torch.tensor([1.0, NAN], dtype=F64))


@pytest.mark.parametrize("dim", [0, 2.5, NAN, True])
def test_chi_square_rejects_bad_dim(dim):
    with pytest.raises(ValueError, match="dim must be an integer >= 1"):
        fdi.ChiSquareDetector(dim)


@pytest.mark.parametrize("threshold", [NAN, -1.0, INF, -INF])
def test_cusum_rejects_bad_thresholds(threshold):
    with pytest.raises(ValueError, match="threshold must be a finite number >= 0"):
        fdi.CusumDetector(3.0, threshold)
    det = fdi.CusumDetector(3.0, 1.0)
    with pytest.raises(ValueError, match="threshold must be a finite number >= 0"):
        det.run(torch.ones(2, 4, dtype=F64), threshold)


@pytest.mark.parametrize("bias", [INF, NAN, 0.0, -2.0])
def test_cusum_rejects_bad_bias(bias):
    with pytest.raises(ValueError, match="bias must be a finite number > 0"):
        fdi.CusumDetector(bias, 1.0)


def test_cusum_raises_on_nan_statistics():
    det = fdi.CusumDetector(3.0, 5.0)
    g = torch.ones(2, 5, dtype=F64)
    g[1, 2] = NAN
    for call in (det.run, det.scores):
        with pytest.raises(ValueError, match="g contains NaN or −inf"):  # (+inf: an alarm)
            call(g)
    with pytest.raises(ValueError, match="g contains NaN or −inf"):  # (+inf: an alarm)
        det.step(det.init((2,)), g[:, 2])
    with pytest.raises(ValueError, match="g_attack_free contains NaN"):
        det.calibrate(g, 0.1)
    model, ys = cv_data()
    res = df.kalman_filter(model, ys)
    innov = res.innovations.clone()
    innov[1, 0, 1] = NAN
    with pytest.raises(ValueError, match="innovations contains NaN"):
        det.detect(innov, res.innovation_covs)


def test_poa_nan_residuals_raise_instead_of_counting_below_threshold():
    residuals = torch.zeros(3, 10, 4, dtype=F64)
    residuals[1, 4, 2] = NAN
    with pytest.raises(ValueError, match="residuals contains NaN"):
        fdi.probability_of_attack(residuals, 0.2)
    with pytest.raises(ValueError, match="residuals contains NaN"):
        poa_detector()(residuals, torch.zeros(3, 10, dtype=F64))
    # ±Inf residuals exceed any eta (documented): counted, not dropped
    residuals[1, 4, 2] = INF
    beta = fdi.probability_of_attack(residuals, 0.2)
    assert beta[1] == pytest.approx(0.1) and beta[0] == 0


def test_poa_all_minus_inf_log_weights_raise():
    residuals = torch.ones(2, 5, 4, dtype=F64)
    log_w = torch.zeros(2, 5, dtype=F64)
    log_w[0] = -INF
    with pytest.raises(ValueError, match="log_weights are NaN or all -inf"):
        fdi.probability_of_attack(residuals, 0.2, log_w)


def test_non_symmetric_innovation_covariances_are_rejected():
    model, ys = cv_data()
    res = df.kalman_filter(model, ys)
    covs = res.innovation_covs.clone()
    covs[..., 0, 1] += 0.3
    with pytest.raises(ValueError, match="innovation_covs must be symmetric"):
        fdi.ChiSquareDetector(2).detect(res.innovations, covs)
    with pytest.raises(ValueError, match="innovation_covs must be symmetric"):
        fdi.normalized_innovation_squared(res.innovations, covs)


# ------------------------------------------------------- FDI filters skip the checks


def run_gated(model, ys, **kw):
    return fdi.gated_extended_kalman_filter(
        model, ys, detector=fdi.ChiSquareDetector(model.dim_y), **kw
    )


def run_modified(model, ys, **kw):
    gamma = kw.pop("gamma_hat", torch.zeros_like(ys) if isinstance(ys, torch.Tensor) else None)
    return fdi.modified_particle_filter(
        model,
        ys,
        num_particles=20,
        detector=poa_detector(),
        gamma_hat=gamma,
        generator=torch.Generator().manual_seed(0),
        **kw,
    )


def run_poa(model, ys, **kw):
    return fdi.particle_filter_poa(
        model,
        ys,
        num_particles=20,
        detector=poa_detector(),
        generator=torch.Generator().manual_seed(0),
        **kw,
    )


FDI_FILTERS = [run_gated, run_modified, run_poa]
FDI_IDS = ["gated_ekf", "modified_pf", "pf_poa"]


@pytest.mark.parametrize("run", FDI_FILTERS, ids=FDI_IDS)
@pytest.mark.parametrize("bad", [NAN, INF, -INF], ids=str)
def test_fdi_filters_reject_non_finite_measurements(run, bad):
    model, ys = four_tank_data()
    with pytest.raises(ValueError, match="ys contains NaN or Inf"):
        run(model, poisoned(ys, bad))


@pytest.mark.parametrize("run", [run_modified, run_poa], ids=FDI_IDS[1:])
@pytest.mark.parametrize("ess", [-0.1, 1.5, NAN, INF])
def test_fdi_particle_filters_reject_bad_ess_threshold(run, ess):
    model, ys = four_tank_data()
    with pytest.raises(ValueError, match="ess_threshold must lie in"):
        run(model, ys, ess_threshold=ess)


def test_modified_pf_rejects_non_finite_gamma_hat():
    model, ys = four_tank_data()
    gamma = torch.zeros_like(ys)
    gamma[0, 1, 1] = NAN
    with pytest.raises(ValueError, match="gamma_hat contains NaN or Inf"):
        run_modified(model, ys, gamma_hat=gamma)


@pytest.mark.parametrize("run", [run_modified, run_poa], ids=FDI_IDS[1:])
def test_fdi_particle_filters_reject_resampler_strings(run):
    model, ys = four_tank_data()
    with pytest.raises(TypeError, match="resampler must be an object.*Systematic"):
        run(model, ys, resampler="systematic")


# ----------------------------------------------------- online steps validate nothing


def step_kf(model, y, mask=None, u=None):
    return df.kalman_step(model, df.gaussian_init(model, y.shape[:-1]), y, u, mask)


def step_ekf(model, y, mask=None, u=None):
    return df.extended_kalman_step(model, df.gaussian_init(model, y.shape[:-1]), y, u, mask)


def step_ukf(model, y, mask=None, u=None):
    return df.unscented_kalman_step(model, df.gaussian_init(model, y.shape[:-1]), y, u, mask)


def step_pf(model, y, mask=None, u=None):
    g = torch.Generator().manual_seed(0)
    state = df.particle_init(model, 16, y.shape[:-1], g)
    return df.particle_step(model, state, y, u, mask, generator=g)


STEPS = [step_kf, step_ekf, step_ukf, step_pf]
STEP_IDS = ["kf", "ekf", "ukf", "pf"]


@pytest.mark.parametrize("step", STEPS, ids=STEP_IDS)
@pytest.mark.parametrize("bad", [NAN, INF], ids=str)
def test_online_steps_reject_non_finite_y(step, bad):
    model = constant_velocity()
    y = torch.zeros(3, 2, dtype=F64)
    y[1, 0] = bad
    with pytest.raises(ValueError, match="y contains NaN or Inf"):
        step(model, y)
    # an unreceived entry may be NaN: it is never read
    mask = torch.ones(3, 2, dtype=torch.bool)
    mask[1, 0] = False
    _, out = step(model, y, mask)
    assert torch.isfinite(out.mean).all()


@pytest.mark.parametrize("step", STEPS, ids=STEP_IDS)
def test_online_steps_reject_float_masks(step):
    model = constant_velocity()
    y = torch.zeros(3, 2, dtype=F64)
    with pytest.raises(ValueError, match="mask must have dtype torch.bool"):
        step(model, y, torch.full((3, 2), 0.5, dtype=F64))


@pytest.mark.parametrize("step", STEPS, ids=STEP_IDS)
def test_online_steps_reject_wrong_size_y(step):
    model = constant_velocity()
    with pytest.raises(ValueError, match=r"y must have shape \[\.\.\., 2\]"):
        step(model, torch.zeros(3, 3, dtype=F64))


@pytest.mark.parametrize("step", STEPS, ids=STEP_IDS)
def test_online_steps_reject_bad_u(step):
    model = constant_velocity(with_input=True)
    y = torch.zeros(3, 2, dtype=F64)
    with pytest.raises(ValueError, match="u must have a floating dtype"):
        step(model, y, u=torch.ones(3, 1, dtype=torch.int64))
    with pytest.raises(ValueError, match="u's batch shape"):
        step(model, y, u=torch.ones(4, 1, dtype=F64))


def test_particle_step_rejects_strings_and_bad_ess():
    model = constant_velocity()
    state = df.particle_init(model, 8, (2,))
    y = torch.zeros(2, 2, dtype=F64)
    with pytest.raises(TypeError, match="resampler must be an object"):
        df.particle_step(model, state, y, resampler="systematic")
    with pytest.raises(ValueError, match="ess_threshold must lie in"):
        df.particle_step(model, state, y, ess_threshold=NAN)


# ----------------------------------------------------------- edge shapes and types


def pf(model, ys, us=None, **kw):
    return df.particle_filter(
        model, ys, us, num_particles=8, generator=torch.Generator().manual_seed(0), **kw
    )


def kf_parallel(model, ys, us=None, **kw):
    return df.kalman_filter(model, ys, us, method="parallel", **kw)


FILTERS = [df.kalman_filter, kf_parallel, df.extended_kalman_filter, df.unscented_kalman_filter, pf]
FILTER_IDS = ["kf", "kf_parallel", "ekf", "ukf", "pf"]


@pytest.mark.parametrize("run", FILTERS, ids=FILTER_IDS)
def test_zero_steps_raise_a_clear_error(run):
    with pytest.raises(ValueError, match="ys must hold at least one time step"):
        run(constant_velocity(), torch.zeros(3, 0, 2, dtype=F64))


@pytest.mark.parametrize("run", FDI_FILTERS, ids=FDI_IDS)
def test_zero_steps_raise_in_fdi_filters(run):
    model = FourTankModel(dtype=F64)
    with pytest.raises(ValueError, match="ys must hold at least one time step"):
        run(model, torch.zeros(2, 0, 4, dtype=F64))


@pytest.mark.parametrize("run", FILTERS, ids=FILTER_IDS)
def test_broadcastable_mask_of_the_wrong_shape_raises(run):
    model, ys = cv_data(B=(3,))
    with pytest.raises(ValueError, match=r"mask must have the shape of ys \(3, 6, 2\)"):
        run(model, ys, mask=torch.ones(1, 6, 2, dtype=torch.bool))
    with pytest.raises(ValueError, match="mask must have dtype torch.bool"):
        run(model, ys, mask=torch.full(ys.shape, 0.5))


@pytest.mark.parametrize("run", FILTERS + FDI_FILTERS[:1], ids=FILTER_IDS + FDI_IDS[:1])
def test_float32_model_with_float64_ys_names_ys_and_dtype(run):
    model = constant_velocity(dtype=torch.float32)
    ys = torch.zeros(2, 4, 2, dtype=F64)
    with pytest.raises(ValueError, match="ys must have the model's dtype torch.float32"):
        run(model, ys)


@pytest.mark.parametrize("run", FILTERS, ids=FILTER_IDS)
@pytest.mark.parametrize("dtype", [torch.int64, torch.bool], ids=str)
def test_integer_or_bool_us_raise(run, dtype):
    model = constant_velocity(with_input=True)
    ys = torch.zeros(2, 4, 2, dtype=F64)
    with pytest.raises(ValueError, match="us must have a floating dtype"):
        run(model, ys, torch.ones(2, 4, 1, dtype=dtype))


@pytest.mark.parametrize("run", FILTERS, ids=FILTER_IDS)
def test_us_batch_must_broadcast_with_ys(run):
    model = constant_velocity(with_input=True)
    ys = torch.zeros(2, 4, 2, dtype=F64)
    with pytest.raises(ValueError, match=r"us's batch shape \(3,\) does not broadcast"):
        run(model, ys, torch.ones(3, 4, 1, dtype=F64))


@pytest.mark.parametrize("name", ["resampler", "proposal", "likelihood"])
def test_strategy_strings_raise_type_error(name):
    model, ys = cv_data()
    with pytest.raises(TypeError, match=f"{name} must be an object, not the string"):
        pf(model, ys, **{name: "systematic"})


def test_nonfinite_skip_treats_entries_as_unreceived_and_counts_them():
    model, ys = cv_data(T=8, B=(3,))
    bad = ys.clone()
    bad[0, 2, 1] = NAN
    bad[2, 5, 0] = INF
    bad[2, 6, 1] = -INF
    mask = torch.isfinite(bad)
    for run in (df.kalman_filter, kf_parallel, df.extended_kalman_filter, pf):
        res = run(model, bad, nonfinite="skip")
        ref = run(model, ys, mask=mask)
        torch.testing.assert_close(res.means, ref.means)
        assert res.nonfinite_skipped.tolist() == [1, 0, 2]
        assert ref.nonfinite_skipped is None
    with pytest.raises(ValueError, match="nonfinite: 'ignore' is not a NonFinite"):
        df.kalman_filter(model, ys, nonfinite="ignore")


def test_finiteness_check_is_not_fooled_by_an_overflowing_sum():
    """The check sums ``ys`` first; a sum that overflows must fall back to testing entries."""
    from difffilter._checks import check_sequence_inputs

    model, ys = cv_data(T=8, B=(3,))
    huge = torch.full_like(ys, 1e308)  # finite entries whose sum is +inf
    out, *_ = check_sequence_inputs(model, huge)
    assert torch.equal(out, huge)
    _, _, _, skipped = check_sequence_inputs(model, huge, nonfinite="skip")
    assert skipped.tolist() == [0, 0, 0]
    huge[1, 4, 0] = NAN
    with pytest.raises(ValueError, match=r"ys contains NaN or Inf .* index \(1, 4, 0\)"):
        check_sequence_inputs(model, huge)


# ------------------------------------------------------- dtype and reproducibility


def scaled_float32_model():
    """Float32 model whose functions multiply state components by Python floats."""
    f32 = torch.float32

    def f(x):
        return torch.stack([x[..., 0] + 0.1 * torch.sin(x[..., 1]), 0.9 * x[..., 1]], -1)

    def h(x):
        return 0.5 * x[..., :1] ** 2 + x[..., 1:]

    return df.NonlinearGaussianModel(
        f,
        h,
        0.01 * torch.eye(2, dtype=f32),
        0.1 * torch.eye(1, dtype=f32),
        torch.ones(2, dtype=f32),
        torch.eye(2, dtype=f32),
    )


def test_ekf_and_gated_ekf_on_a_float32_nonlinear_model():
    model = scaled_float32_model()
    _, ys, _ = model.simulate(6, (3,), generator=torch.Generator().manual_seed(0))
    assert model.transition_jacobian(ys.new_zeros(3, 2), None, 0).dtype == torch.float32
    res = df.extended_kalman_filter(model, ys)
    assert res.means.dtype == torch.float32 and torch.isfinite(res.means).all()
    gated = fdi.gated_extended_kalman_filter(model, ys, detector=fdi.ChiSquareDetector(1))
    assert gated.means.dtype == torch.float32 and torch.isfinite(gated.means).all()


def test_fused_pf_with_a_generator_is_reproducible_and_leaves_the_global_rng_alone():
    model, ys = four_tank_data(B=3, T=10)
    gamma = torch.zeros_like(ys)
    pf_ = FusedModifiedPF(model, num_particles=40, eta=0.2, zeta=0.3)
    torch.manual_seed(123)
    global_state = torch.get_rng_state()
    a = pf_.run(ys, gamma, generator=torch.Generator().manual_seed(7))
    assert torch.equal(torch.get_rng_state(), global_state)
    b = pf_.run(ys, gamma, generator=torch.Generator().manual_seed(7))
    assert torch.equal(a.means, b.means) and torch.equal(a.scores, b.scores)
    c = pf_.run(ys, gamma, generator=torch.Generator().manual_seed(8))
    assert not torch.equal(a.means, c.means)


# ------------------------------------------------------------- models accept poison


def cv_args():
    base = constant_velocity(with_input=True)
    return dict(
        F=base.F,
        H=base.H,
        Q=base.process_noise.cov,
        R=base.measurement_noise.cov,
        m0=base.initial.mean,
        P0=base.initial.cov,
        B=base.B,
    )


@pytest.mark.parametrize("name", ["F", "H", "Q", "R", "m0", "P0", "B"])
@pytest.mark.parametrize("bad", [NAN, INF], ids=str)
def test_linear_model_rejects_non_finite_matrices(name, bad):
    args = cv_args()
    args[name] = args[name].clone()
    args[name].view(-1)[0] = bad
    with pytest.raises(ValueError, match=f"{name} contains NaN or Inf"):
        df.LinearGaussianModel(**args)


@pytest.mark.parametrize("dim_u", [-1, 1.5, True])
def test_nonlinear_model_rejects_bad_dim_u(dim_u):
    with pytest.raises(ValueError, match="dim_u must be an integer >= 0"):
        df.NonlinearGaussianModel(
            lambda x: x, lambda x: x, torch.eye(2), torch.eye(2), torch.zeros(2), torch.eye(2),
            dim_u=dim_u,
        )  # fmt: skip


@pytest.mark.parametrize("dt", [INF, NAN, 0.0, -1.0])
def test_four_tank_rejects_bad_dt(dt):
    with pytest.raises(ValueError, match="dt must be a finite number > 0"):
        FourTankModel(dt=dt)


@pytest.mark.parametrize("name", ["process_var", "measurement_var", "dt"])
@pytest.mark.parametrize("bad", [INF, NAN, -1.0])
def test_lfc_plant_rejects_non_finite_or_negative_settings(name, bad):
    with pytest.raises(ValueError, match=f"{name} must be a finite number > 0"):
        LFCPlant(**{name: bad})


# ------------------------------------------------------ the particle filter recovers


def test_particle_filter_recovers_from_an_all_minus_inf_step():
    model, ys = four_tank_data(B=3, T=10, dtype=torch.float32)
    ys = ys.clone()
    ys[1, 4, 0] = 1e19  # its likelihood underflows for every particle in float32
    res = df.particle_filter(
        model, ys, num_particles=100, generator=torch.Generator().manual_seed(0)
    )
    expected = torch.zeros(3, 10, dtype=torch.bool)
    expected[1, 4] = True
    assert torch.equal(res.degenerate, expected)
    for t in (res.means, res.covs, res.ess, res.innovations):
        assert not torch.isnan(t).any()
    assert torch.isfinite(res.means).all() and torch.isfinite(res.ess).all()
    # the documented increment: numerically zero likelihood, -inf, never NaN
    assert res.log_likelihood_increments[1, 4] == -INF
    assert torch.isfinite(res.log_likelihood_increments[expected.logical_not()]).all()
    # the weights were reset to the predictive ones: the run keeps tracking afterwards
    clean = df.particle_filter(
        model, ys[[0, 2]], num_particles=100, generator=torch.Generator().manual_seed(0)
    )
    assert (res.means[1, 5:] - ys[1, 5:]).abs().max() < 0.5
    assert not clean.degenerate.any()


def test_particle_step_flags_the_degenerate_run_only():
    model, ys = four_tank_data(B=2, T=1, dtype=torch.float32)
    g = torch.Generator().manual_seed(0)
    state = df.particle_init(model, 50, (2,), g)
    y = ys[:, 0].clone()
    y[0, 2] = 1e19
    new, out = df.particle_step(model, state, y, generator=g, ess_threshold=0.0)
    assert out.extras["degenerate"].tolist() == [True, False]
    # reset to the predictive weights: uniform here (the prior weights were uniform)
    torch.testing.assert_close(new.log_weights[0], state.log_weights[0])
    assert torch.isfinite(new.log_weights).all() and out.extras["ess"][0] == pytest.approx(50.0)


def test_a_degenerate_run_leaves_the_other_runs_gradients_finite_and_unchanged():
    """One run's impossible measurement once turned every parameter's gradient NaN (the
    reset's graph held the degenerate run's NaN, passed back as 0 · NaN)."""
    model = constant_velocity()
    model.F.requires_grad_(True)
    _, ys, _ = model.simulate(8, (2,), generator=torch.Generator().manual_seed(3))
    ys = ys.detach()
    bad = ys.clone()
    bad[1, 3, 0] = 1e200  # run 1: every particle's likelihood underflows at step 4

    def run(data):
        res = df.particle_filter(model, data, num_particles=20,
                                 generator=torch.Generator().manual_seed(1))  # fmt: skip
        (grad,) = torch.autograd.grad(res.means[0].square().sum(), model.F)
        return res, grad

    (clean, g_clean), (res, g_bad) = run(ys), run(bad)
    assert res.degenerate[1, 3] and not res.degenerate[0].any()
    assert torch.isfinite(g_bad).all()
    # run 0 neither sees run 1's data nor its draws: the same numbers and the same gradient
    assert torch.equal(res.means[0], clean.means[0]) and torch.equal(g_bad, g_clean)
    assert res.log_likelihood_increments[1, 3] == -INF


# --------------------------------------------------------------------- checkpoints


def _data_offset(path: Path) -> int:
    """Byte offset of the largest tensor storage inside a torch zip checkpoint."""
    with zipfile.ZipFile(path) as zf:
        info = max((i for i in zf.infolist() if "/data/" in i.filename), key=lambda i: i.file_size)
    raw = path.read_bytes()
    h = info.header_offset
    name_len = int.from_bytes(raw[h + 26 : h + 28], "little")
    extra_len = int.from_bytes(raw[h + 28 : h + 30], "little")
    assert info.file_size >= 64
    return h + 30 + name_len + extra_len


def _corrupt_copy(tmp_path: Path, with_card: bool) -> Path:
    dst = tmp_path / CKPT.name
    shutil.copy(CKPT, dst)
    if with_card:
        shutil.copy(CKPT.with_suffix(".json"), dst.with_suffix(".json"))
    raw = bytearray(dst.read_bytes())
    start = _data_offset(dst)
    raw[start : start + 64] = b"\xff" * 64  # 16 float32 weights become NaN
    dst.write_bytes(bytes(raw))
    return dst


def test_shipped_card_records_the_checkpoint_sha256():
    card = json.loads(CKPT.with_suffix(".json").read_text())
    assert card["sha256"] == checkpoint_sha256(CKPT)
    load_estimator_checkpoint(CKPT)  # verified against the card


def test_corrupted_checkpoint_with_card_fails_the_sha256_check(tmp_path):
    path = _corrupt_copy(tmp_path, with_card=True)
    with pytest.raises(ValueError, match="does not match the sha256 recorded in the card"):
        load_estimator_checkpoint(path)


def test_corrupted_checkpoint_without_card_fails_the_finite_check(tmp_path):
    path = _corrupt_copy(tmp_path, with_card=False)
    with pytest.raises(ValueError, match=r"non-finite \(NaN/Inf\) weights"):
        load_estimator_checkpoint(path)


def test_well_formed_checkpoint_with_nan_weights_is_refused(tmp_path):
    net = NeuralFDIEstimator(a=2, b=2, hidden=4)
    with pytest.raises(ValueError, match="non-finite"):
        net.W.data[0, 0, 0] = NAN
        save_estimator_checkpoint(tmp_path / "refused.ckpt", net)
    # written by hand (as a corrupted export would be): refused on load
    state = {k: v.detach().clone() for k, v in net.state_dict().items()}
    path = tmp_path / "nan.ckpt"
    torch.save(
        {
            "format": CHECKPOINT_FORMAT,
            "estimator_config": net.config(),
            "observer": {"residual_lag": 0},
            "state_dict": state,
            "extra": {},
        },
        path,
    )
    with pytest.raises(ValueError, match=r"nan.ckpt holds non-finite \(NaN/Inf\) weights"):
        load_estimator_checkpoint(path)


def test_card_without_sha256_or_with_a_wrong_one_is_refused(tmp_path):
    net = NeuralFDIEstimator(a=2, b=2, hidden=4)
    path = tmp_path / "net.ckpt"
    digest = save_estimator_checkpoint(path, net)
    assert digest == checkpoint_sha256(path)
    load_estimator_checkpoint(path)  # no card: weights checked only
    path.with_suffix(".json").write_text(json.dumps({"checkpoint": path.name}))
    with pytest.raises(ValueError, match="records no sha256"):
        load_estimator_checkpoint(path)
    path.with_suffix(".json").write_text(json.dumps({"sha256": "0" * 64}))
    with pytest.raises(ValueError, match="does not match the sha256"):
        load_estimator_checkpoint(path)
    loaded, _ = load_estimator_checkpoint(path, expected_sha256=digest)  # explicit digest wins
    torch.testing.assert_close(loaded.W, net.W.detach())


def test_resampling_strings_message_names_the_object_to_pass():
    model, ys = cv_data()
    with pytest.raises(TypeError, match=r"difffilter\.resampling\.Systematic\(\)"):
        pf(model, ys, resampler="systematic")
    pf(model, ys, resampler=resampling.Systematic())


def test_eval_cli_refuses_a_bad_checkpoint_before_any_work(tmp_path, capsys):
    from difffilter.eval.cli import main as eval_main

    bad = tmp_path / "bad.ckpt"
    bad.write_bytes(b"not a checkpoint")
    out = tmp_path / "out"
    assert eval_main(["lfc_step", "--ckpt", str(bad), "--out", str(out), "--no-progress"]) == 2
    assert "bad.ckpt" in capsys.readouterr().err and not (out / "lfc_step").exists()
    missing = ["lfc_step", "--ckpt", str(tmp_path / "none.ckpt"), "--out", str(out)]
    assert eval_main(missing) == 2


def test_a_transition_input_with_a_default_still_reaches_the_function():
    """A user trial: ``f(x, u=None)`` was called as ``f(x)`` (only arguments without a
    default counted), so the known inputs were dropped without a word and every filter
    lagged the truth; ``h(x, k=0)`` never saw ``k``; ``dim_u=1`` with ``f(x)`` passed."""
    kw = dict(Q=torch.eye(1) * 0.01, R=torch.eye(1) * 0.01, m0=torch.zeros(1), P0=torch.eye(1),
              dim_u=1)  # fmt: skip
    x, u = torch.zeros(1, dtype=torch.float64), torch.tensor([5.0], dtype=torch.float64)
    kw = {k: v.double() if isinstance(v, torch.Tensor) else v for k, v in kw.items()}
    model = df.NonlinearGaussianModel(lambda x, u=None: 0.9 * x + (0.0 if u is None else u),
                                      lambda x, k=0: x * (1.0 + k), **kw)  # fmt: skip
    assert model.transition(x, u, 0).item() == 5.0
    assert model.observe(torch.ones(1, dtype=torch.float64), 3).item() == 4.0
    # a default that is not an input stays a constant of the function
    model = df.NonlinearGaussianModel(lambda x, u, dt=0.5: x + dt * u, lambda x: x, **kw)
    assert model.transition(x, u, 7).item() == 2.5
    with pytest.raises(ValueError, match=r"dim_u = 1, but transition takes x alone, so the "
                       r"input would never reach it"):  # fmt: skip
        df.NonlinearGaussianModel(lambda x: 0.9 * x, lambda x: x, **kw)


def test_the_gaussian_filters_refuse_a_noise_of_non_zero_mean():
    """A user trial: with ``UniformBox(0, 2)`` measurement noise (mean 1) the KF and UKF
    were biased by +0.87 (they read the covariance alone) while the PF was not."""
    from difffilter.noise import Gaussian, UniformBox

    model = df.LinearGaussianModel(torch.tensor([[0.9]]), torch.tensor([[1.0]]),
                                   torch.tensor([[0.1]]), torch.tensor([[0.1]]), torch.zeros(1),
                                   torch.eye(1))  # fmt: skip
    ys = torch.zeros(2, 5, 1)
    model.measurement_noise = UniformBox(torch.tensor([0.0]), torch.tensor([2.0]))
    for run in (df.kalman_filter, df.extended_kalman_filter, df.unscented_kalman_filter):
        with pytest.raises(ValueError, match=r"model.measurement_noise has mean \[1.0\], and the "
                           r"Gaussian filters"):  # fmt: skip
            run(model, ys)
    model.measurement_noise = UniformBox(torch.tensor([-1.0]), torch.tensor([1.0]))  # mean 0
    df.kalman_filter(model, ys)
    model.process_noise = Gaussian(torch.tensor([0.5]), torch.tensor([[0.1]]))
    with pytest.raises(ValueError, match=r"model.process_noise has mean \[0.5\]"):
        df.KalmanFilter().init(model, (2,))


def test_the_kalman_proposal_refuses_a_process_noise_that_is_not_gaussian():
    """A user trial: with a Gaussian-mixture process noise it ran and its log-likelihood
    was 3-6 nats off the bootstrap filter's (its weights take p = N(f, Q))."""
    from difffilter.noise import GaussianMixture

    model = df.LinearGaussianModel(torch.tensor([[0.9]]), torch.tensor([[1.0]]),
                                   torch.tensor([[0.1]]), torch.tensor([[0.1]]), torch.zeros(1),
                                   torch.eye(1))  # fmt: skip
    model.process_noise = GaussianMixture(torch.tensor([0.5, 0.5]), torch.zeros(2, 1),
                                          torch.tensor([[[0.05]], [[0.15]]]))  # fmt: skip
    with pytest.raises(ValueError, match="KalmanProposal needs a Gaussian process noise; "
                       "model.process_noise is a GaussianMixture"):  # fmt: skip
        df.particle_filter(model, torch.zeros(2, 5, 1), num_particles=10,
                           proposal=df.KalmanProposal(), generator=torch.Generator().manual_seed(0))  # fmt: skip


def test_a_model_batched_over_runs_is_named_where_it_does_not_fit():
    """A user trial: 3 parameter sets given 4 runs, and any batched model in the particle
    filter (a batched F or H in the UKF), failed in torch ("The size of tensor a (3) must
    match …") or gave particles of the wrong shape; the KF and EKF take them."""
    F = torch.tensor([[[0.9]], [[0.8]], [[0.7]]])
    model = df.LinearGaussianModel(F, torch.tensor([[1.0]]), torch.tensor([[0.1]]),
                                   torch.tensor([[0.1]]), torch.zeros(1), torch.eye(1))  # fmt: skip
    three, four = torch.zeros(3, 5, 1), torch.zeros(4, 5, 1)
    assert df.kalman_filter(model, three).means.shape == (3, 5, 1)
    assert df.extended_kalman_filter(model, three).means.shape == (3, 5, 1)
    why = r"does not broadcast with the batch shape \(3,\) of the model's parameters"
    for run in (df.kalman_filter, df.extended_kalman_filter, df.unscented_kalman_filter):
        with pytest.raises(ValueError, match=r"the batch of ys \(4,\) " + why):
            run(model, four)
    with pytest.raises(ValueError, match=r"batch_shape \(4,\) " + why):
        df.KalmanFilter().init(model, (4,))
    with pytest.raises(ValueError, match=r"the UKF evaluates f and h on sigma points, and this "
                       r"model's F, B or H have batch shape \(3,\)"):  # fmt: skip
        df.unscented_kalman_filter(model, three)
    with pytest.raises(ValueError, match=r"the particle filter takes one model for all runs, "
                       r"and this model's parameters have batch shape \(3,\)"):  # fmt: skip
        df.particle_filter(model, three, num_particles=10, generator=torch.Generator())
    # a batched prior is fine in the UKF (its sigma points carry it)
    prior = df.LinearGaussianModel(torch.tensor([[0.9]]), torch.tensor([[1.0]]),
                                   torch.tensor([[0.1]]), torch.tensor([[0.1]]),
                                   torch.zeros(3, 1), torch.eye(1))  # fmt: skip
    assert df.unscented_kalman_filter(prior, three).means.shape == (3, 5, 1)


@pytest.mark.parametrize("dtype, big", [(torch.float32, 1e20), (torch.float64, 1e155)])
def test_a_gated_filter_alarms_on_a_measurement_whose_statistic_overflows(dtype, big):
    """A huge but finite measurement overflows νᵀS⁻¹ν to +inf: the χ² and CUSUM gates
    raised "g contains NaN or Inf values" where they should alarm (a deployment trial)."""
    import difffilter.fdi as fdi

    eye = torch.eye(2, dtype=dtype)
    F = torch.tensor([[1.0, 0.01], [0.0, 1.0]], dtype=dtype)
    H = torch.tensor([[1.0, 0.0]], dtype=dtype)
    model = df.LinearGaussianModel(
        F, H, 0.01 * eye, torch.eye(1, dtype=dtype), torch.zeros(2, dtype=dtype), eye
    )
    for detector in (fdi.ChiSquareDetector(1, 0.01), fdi.CusumDetector(1, threshold=5.0)):
        gated = fdi.GatedFilter(detector, df.KalmanFilter())
        carry, _ = gated.step(gated.init(model, ()), torch.zeros(1, dtype=dtype))
        carry, out = gated.step(carry, torch.tensor([big], dtype=dtype))
        assert bool(out.alarm) and bool(torch.isfinite(out.mean).all())
        carry, out = gated.step(carry, torch.zeros(1, dtype=dtype))
        assert not bool(out.alarm)  # (the CUSUM reset after its alarm)
    with pytest.raises(ValueError, match="NaN or −inf"):
        fdi.ChiSquareDetector(1, 0.01).step(((torch.zeros(1, 0)), 0), torch.tensor([float("nan")]))


def test_the_running_attack_rate_counts_past_float32s_integers():
    """Remark 6's count took the model's dtype: in float32 it stopped at 2^24 alarms."""
    rate = fdi.RunningAttackRate(100)
    state = rate.init((), dtype=torch.float32)
    state = state._replace(count=torch.tensor(2.0**24, dtype=state.count.dtype), steps=2**25)
    for _ in range(3):
        state = rate.update(state, torch.tensor(True))
    assert float(state.count) == 2**24 + 3


def test_the_modified_pf_names_a_gamma_hat_table_that_does_not_fit():
    """A 1-D γ̂ failed at step 1 and a T-row table at step T + 1 with a bare IndexError."""
    detector = fdi.PoADetector(eta=0.2, zeta=0.5)
    with pytest.raises(ValueError, match=r"gamma_hat must be a tensor \[..., T, dy\]"):
        fdi.ModifiedPFWeighting(detector, torch.zeros(2))
    model = constant_velocity()
    _, ys, _ = model.simulate(4, (), generator=torch.Generator().manual_seed(0))
    weighting = fdi.ModifiedPFWeighting(detector, torch.zeros(3, 2, dtype=torch.float64))
    pf = df.ParticleFilter(20, likelihood=weighting)
    carry = pf.init(model, (), generator=torch.Generator().manual_seed(1))
    for k in range(3):
        carry, _ = pf.step(carry, ys[k])
    with pytest.raises(ValueError, match="gamma_hat has 3 rows .* step 4 needs"):
        pf.step(carry, ys[3])


def test_the_newer_helpers_name_bad_arguments():
    """An API trial of the newer modules: each of these failed in torch, numpy or scipy
    (or gave a number: a zero S, iterations=-1, zero steps) without naming the argument."""
    from difffilter.consistency import ensemble_test, nees, whiteness
    from difffilter.control import lqr, luenberger_gain, zoh_discretize
    from difffilter.fdi import BiasAttackEstimator, covariance_intersection
    from difffilter.gain_schedule import GainSchedule

    d = torch.float64
    A = torch.tensor([[0.0, 1.0], [-2.0, -0.3]], dtype=d)
    B = torch.tensor([[0.0], [1.0]], dtype=d)
    inn = torch.randn(5, 6, 2, dtype=d, generator=torch.Generator().manual_seed(0))
    eye = torch.eye(2, dtype=d)
    F = torch.nn.Parameter(0.9 * eye)
    trained = df.LinearGaussianModel(F, eye[:1], 0.1 * eye, 0.5 * eye[:1, :1],
                                     torch.zeros(2, dtype=d), eye)  # fmt: skip
    means = torch.zeros(2, 2, dtype=d)
    covs = torch.stack([eye, 2 * eye])
    cases = [
        (lambda: whiteness(inn, torch.zeros(2, 2, dtype=d)), "positive definite"),
        (lambda: whiteness(inn, torch.eye(3, dtype=d)), r"innovation_covs must be \[R, T, 2, 2\]"),
        (lambda: nees(torch.zeros(4, 3, dtype=d), torch.eye(3, dtype=d).expand(2, 3, 3)),
         "errors' batch"),
        (lambda: nees(torch.zeros(4, 3), torch.eye(3, dtype=d)), "one dtype"),
        (lambda: ensemble_test(torch.ones(5, 0, dtype=d), 2), "no runs or no steps"),
        (lambda: lqr(A, B[:, 0]), "B must be a two-dimensional"),
        (lambda: lqr(A, B, R=torch.eye(1)), "R is torch.float32"),
        (lambda: lqr(A, B, Q=torch.eye(3, dtype=d)), r"Q must have shape \[2, 2\]"),
        (lambda: zoh_discretize(A.tolist(), B, 0.1), "A must be a floating tensor"),
        (lambda: luenberger_gain(eye, A, 0.1, factor=0.0), "factor must be a finite number > 0"),
        (lambda: GainSchedule(trained), "require no gradient"),
        (lambda: covariance_intersection(means, covs, iterations=-1), "iterations must be"),
        (lambda: BiasAttackEstimator(2, "0.9"), "tau must lie in"),
    ]  # fmt: skip
    for call, why in cases:
        with pytest.raises(ValueError, match=why):
            call()
