"""The neural FDI estimator inside difffilter's filters, and the one training task."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import pytest
import torch

import difffilter as df
from difffilter.estimator import Generators
from difffilter.fdi.neural import build_delta
from difffilter.loop import open_loop
from difffilter.models.learned_estimator import NeuralCompensation, feature_dim
from difffilter.models.neural_estimator import NeuralFDIEstimator
from difffilter.particle import Predictive, particle_filter

ROOT = Path(__file__).resolve().parents[1]


def neural_gaussian_filter(model, ys, us=None, *, network, filter, **options):
    """The network around a Gaussian ``filter`` in the open loop."""
    return open_loop(NeuralCompensation(network, filter, **options), model, ys, us)


def neural_particle_filter(model, ys, us=None, *, network, num_particles, resampler=None,
                           ess_threshold=0.5, generator=None, **options):  # fmt: skip
    """The network around a bootstrap particle filter in the open loop."""
    pf = df.ParticleFilter(num_particles, resampler=resampler, ess_threshold=ess_threshold)
    est = NeuralCompensation(network, pf, **options)
    return open_loop(est, model, ys, us, generator=Generators.of(generator))


def _linear(dtype=torch.float64):
    F = torch.tensor([[1.0, 0.1], [0.0, 0.95]], dtype=dtype)
    H = torch.eye(2, dtype=dtype)
    eye = torch.eye(2, dtype=dtype)
    return df.LinearGaussianModel(F, H, 1e-3 * eye, 1e-2 * eye, torch.zeros(2, dtype=dtype), eye)


def _data(model, runs=3, steps=12, seed=0):
    xs, ys, _ = model.simulate(steps, (runs,), generator=torch.Generator().manual_seed(seed))
    ys = ys.clone()
    ys[:, 5:, 0] += 0.8  # a bias on sensor 1 from step 5
    return xs, ys


def _net(dtype=torch.float64, zero_output=False, seed=1, extra_inputs=0):
    net = NeuralFDIEstimator(
        extra_inputs=extra_inputs,
        num_areas=1,
        area_dim=2,
        a=2,
        b=2,
        hidden=5,
        init="symmetric",
        init_scale=0.5,
        resid_scale=3.0,
        seed=seed,
        dtype=dtype,
    )
    if zero_output:
        with torch.no_grad():
            net.W.zero_()
    return net


def test_a_zero_network_leaves_the_kalman_and_particle_filters_unchanged():
    model = _linear()
    _, ys = _data(model)
    net = _net(zero_output=True)
    out = neural_gaussian_filter(model, ys, network=net, filter=df.KalmanFilter())
    ref = df.kalman_filter(model, ys)
    torch.testing.assert_close(out.means, ref.means, rtol=0, atol=1e-12)
    torch.testing.assert_close(out.covs, ref.covs, rtol=0, atol=1e-12)
    assert out.attack.abs().max() == 0
    g = lambda: torch.Generator().manual_seed(3)  # noqa: E731
    pf = neural_particle_filter(model, ys, network=net, num_particles=50, generator=g())
    plain = particle_filter(model, ys, num_particles=50, generator=g())
    torch.testing.assert_close(pf.means, plain.means, rtol=0, atol=1e-12)


def test_each_kalman_step_updates_with_the_measurement_minus_the_networks_estimate():
    """One step by hand: ν, S of the plain step → δ (eq. 9, ℓ = 0) → â → KF step on y − â."""
    model, net = _linear(), _net()
    _, ys = _data(model, runs=2, steps=3)
    out = neural_gaussian_filter(model, ys, network=net, filter=df.KalmanFilter())
    state = df.kalman.gaussian_init(model, (2,))
    attack_hist, resid_hist = (
        torch.zeros(2, 2, 2, dtype=ys.dtype),
        torch.zeros(2, 2, 2, dtype=ys.dtype),
    )
    for t in range(3):
        _, probe = df.kalman_step(model, state, ys[:, t])
        e = probe.innovation / torch.diagonal(probe.innovation_cov, dim1=-2, dim2=-1).sqrt()
        resid_hist = torch.cat([e[:, None], resid_hist[:, :-1]], 1)
        a_hat, _ = net(build_delta(attack_hist, resid_hist, 1))
        a_hat = a_hat[:, 0]
        attack_hist = torch.cat([a_hat[:, None], attack_hist[:, :-1]], 1)
        state, _ = df.kalman_step(model, state, ys[:, t] - a_hat)
        torch.testing.assert_close(out.attack[:, t], a_hat, rtol=0, atol=1e-12)
        torch.testing.assert_close(out.means[:, t], state.mean, rtol=0, atol=1e-12)


def test_an_actuator_estimate_is_added_to_the_input_of_each_update_by_hand():
    """channel='actuator': â (du = 1 channel) from the dy = 2 residuals of the plain step,
    δ = [â_{k−1}, â_{k−2}, e_k, e_{k−1}], then the KF step with u + â."""
    dtype = torch.float64
    F = torch.tensor([[1.0, 0.1], [0.0, 0.95]], dtype=dtype)
    eye = torch.eye(2, dtype=dtype)
    Bm = torch.tensor([[0.0], [0.1]], dtype=dtype)
    model = df.LinearGaussianModel(F, eye, 1e-3 * eye, 1e-2 * eye, torch.zeros(2, dtype=dtype),
                                   eye, B=Bm)  # fmt: skip
    gen = torch.Generator().manual_seed(6)
    ys = torch.randn(2, 4, 2, generator=gen, dtype=dtype)
    us = torch.randn(2, 4, 1, generator=gen, dtype=dtype)
    net = NeuralFDIEstimator(num_areas=1, area_dim=1, resid_dim=2, a=2, b=2, hidden=5,
                             init="symmetric", init_scale=0.5, seed=2, dtype=dtype)  # fmt: skip
    out = neural_gaussian_filter(model, ys, us, network=net, filter=df.KalmanFilter(),
                                 channel="actuator")  # fmt: skip
    assert out.attack.shape == (2, 4, 1)
    state = df.kalman.gaussian_init(model, (2,))
    a_hist, e_hist = torch.zeros(2, 2, 1, dtype=dtype), torch.zeros(2, 2, 2, dtype=dtype)
    for t in range(4):
        _, probe = df.kalman_step(model, state, ys[:, t], us[:, t])
        e = probe.innovation / torch.diagonal(probe.innovation_cov, dim1=-2, dim2=-1).sqrt()
        e_hist = torch.cat([e[:, None], e_hist[:, :-1]], 1)
        a_hat, _ = net(torch.cat([a_hist.flatten(1), e_hist.flatten(1)], 1)[:, None])
        a_hat = a_hat[:, 0]
        a_hist = torch.cat([a_hat[:, None], a_hist[:, :-1]], 1)
        state, _ = df.kalman_step(model, state, ys[:, t], us[:, t] + a_hat)
        torch.testing.assert_close(out.attack[:, t], a_hat, rtol=0, atol=1e-12)
        torch.testing.assert_close(out.means[:, t], state.mean, rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="needs u_k"):
        neural_gaussian_filter(model, ys, network=net, filter=df.KalmanFilter(), channel="actuator")
    with pytest.raises(ValueError, match="resid_dim == area_dim"):  # a sensor estimate of 1 channel
        neural_gaussian_filter(model, ys, us, network=net, filter=df.KalmanFilter())


def test_the_task_takes_the_attack_channel_from_the_scenario():
    from difffilter.train.task import FilterEstimatorTask

    task = FilterEstimatorTask("robot_actuator_attack", filter="ekf", hidden=4)
    assert task.channel == "actuator"
    assert (task.estimator.area_dim, task.estimator.resid_dim) == (2, 12)
    with pytest.raises(ValueError, match="actuator attack"):
        FilterEstimatorTask("robot_actuator_attack", filter="pf")


def test_gradcheck_through_the_compensated_kalman_filter():
    """float64 gradcheck of the filter's outputs w.r.t. the network weights and the data."""
    model, net = _linear(), _net()
    _, ys = _data(model, runs=2, steps=6)

    def loss(W, V, y):
        plain = copy.deepcopy(net)
        del plain.W, plain.V  # plain tensors instead of parameters: the inputs of gradcheck
        plain.W, plain.V = W, V
        res = neural_gaussian_filter(model, y, network=plain, filter=df.KalmanFilter())
        return res.means.sum() + res.attack.square().sum() + res.extras["attack_logit"].sum()

    inputs = [t.detach().clone().requires_grad_() for t in (net.W, net.V, ys)]
    assert torch.autograd.gradcheck(loss, inputs, eps=1e-6, atol=1e-6)


@pytest.mark.parametrize("resampler", [df.resampling.Soft(0.5), df.resampling.StopGradient()])
def test_gradients_reach_the_network_through_the_particle_filter(resampler):
    model, net = _linear(torch.float32), _net(torch.float32)
    xs, ys = _data(model, runs=4, steps=10)
    out = neural_particle_filter(
        model,
        ys,
        network=net,
        num_particles=64,
        resampler=resampler,
        ess_threshold=1.0,
        generator=torch.Generator().manual_seed(0),
    )
    (out.means - xs).square().mean().backward()  # a state loss alone: only through the PF
    grads = torch.cat([p.grad.flatten() for p in net.parameters() if p.grad is not None])
    assert torch.isfinite(grads).all() and grads.abs().max() > 0


def test_the_network_must_fit_the_measurement():
    model = _linear()
    _, ys = _data(model)
    two = NeuralFDIEstimator(num_areas=2, area_dim=1, extra_inputs=2)
    with pytest.raises(ValueError, match="one area"):
        NeuralCompensation(two, df.KalmanFilter(), features=("mask",))
    with pytest.raises(ValueError, match="resid_dim is 3"):
        neural_gaussian_filter(model, ys, network=NeuralFDIEstimator(num_areas=1, area_dim=3),
                               filter=df.KalmanFilter())  # fmt: skip
    with pytest.raises(TypeError, match="inner must be a filter object"):
        neural_gaussian_filter(model, ys, network=_net(), filter="pf")


def _weigh(net, model, y, particles, mask, predictive, **kw):
    """One weighting of the network's particle likelihood (its state fresh)."""
    est = NeuralCompensation(net, df.ParticleFilter(particles.shape[-2]), **kw)
    lik = est.pf.likelihood
    state = lik.init(model, y.shape[:-1], y.dtype, y.device)
    return lik.weigh(state, model, y, particles, 1, mask, predictive)


def _captured_inputs(net):
    """The ``δ`` of every forward call of ``net`` (a forward pre-hook records them)."""
    seen = []
    net.register_forward_pre_hook(lambda module, args: seen.append(args[0].detach().clone()))
    return seen


def test_particle_filter_features_by_hand():
    """δ's tail: the mask, asinh(−2ℓ/m) with ℓ the log-sum-exp of predictive weights times
    the received entries' Gaussian densities, and β = Σ w over ‖z‖ > η."""
    model, gen = _linear(), torch.Generator().manual_seed(3)
    features = ("mask", "log_likelihood", "poa")
    net = _net(extra_inputs=feature_dim(features, 2))
    seen = _captured_inputs(net)
    B, N = 3, 7
    particles = torch.randn(B, N, 2, generator=gen, dtype=torch.float64)
    log_w = torch.log_softmax(torch.randn(B, N, generator=gen, dtype=torch.float64), -1)
    y = torch.randn(B, 2, generator=gen, dtype=torch.float64)
    mask = torch.tensor([[True, True], [True, False], [False, False]])
    innovation = torch.randn(B, 2, generator=gen, dtype=torch.float64) * mask
    cov = torch.eye(2, dtype=torch.float64).expand(B, 2, 2)
    pred = Predictive(log_w, y, innovation, cov)
    _weigh(net, model, y, particles, mask, pred, features=features, poa_eta=0.3)
    tail = seen[0][:, 0, -4:]
    torch.testing.assert_close(tail[:, :2], mask.double())
    sd = 0.1  # R = 1e-2 I
    for i in range(B):
        m = mask[i]
        z = (y[i] - particles[i]) * m  # H = I
        dens = torch.distributions.Normal(0.0, sd).log_prob(z[:, m]).sum(-1)
        ell = torch.logsumexp(log_w[i] + dens, 0) if bool(m.any()) else torch.tensor(0.0)
        expect = torch.asinh(-2.0 * ell / max(int(m.sum()), 1))
        beta = log_w[i].exp()[z.norm(dim=-1) > 0.3].sum()
        torch.testing.assert_close(tail[i, 2], expect.double())
        torch.testing.assert_close(tail[i, 3], beta)


@pytest.mark.parametrize("features", [("poa",), ("log_likelihood",), ("poa", "mask")])
def test_each_feature_alone_gives_its_column_of_the_full_set(features):
    """The features read only the filter's statistics: any subset (in any order) gives the
    same columns as the full set on the same step."""
    model, gen = _linear(), torch.Generator().manual_seed(5)
    B, N = 3, 6
    particles = torch.randn(B, N, 2, generator=gen, dtype=torch.float64)
    log_w = torch.log_softmax(torch.randn(B, N, generator=gen, dtype=torch.float64), -1)
    y = torch.randn(B, 2, generator=gen, dtype=torch.float64)
    mask = torch.tensor([[True, True], [True, False], [True, True]])
    pred = Predictive(log_w, y, torch.randn(B, 2, generator=gen, dtype=torch.float64),
                      torch.eye(2, dtype=torch.float64).expand(B, 2, 2))  # fmt: skip
    tails = {}
    for names in (("mask", "log_likelihood", "poa"), features):
        width = feature_dim(names, 2)
        net = _net(extra_inputs=width)
        seen = _captured_inputs(net)
        _weigh(net, model, y, particles, mask, pred, features=names, poa_eta=0.3)
        tails[names] = seen[0][:, 0, -width:]
    full = dict(zip(("mask", "log_likelihood", "poa"), tails[("mask", "log_likelihood", "poa")]
                    .split([2, 1, 1], -1)))  # fmt: skip
    torch.testing.assert_close(tails[features], torch.cat([full[n] for n in features], -1))


def test_replacement_channel_weighs_with_the_learned_attack_probability_by_hand():
    """channel='replacement': log[(1 − p) p_v(y − Hx) + p p_ξ(y)] with p = sigmoid(logit)
    (eq. 15 with the network's probability for η̄), â = p ν."""
    from difffilter import fdi
    from difffilter.noise import UniformBox

    model, gen = _linear(), torch.Generator().manual_seed(8)
    net = _net()
    with torch.no_grad():
        net.P.normal_(generator=gen)  # a head that answers something other than its init
    box = UniformBox(
        torch.full((2,), -5.0, dtype=torch.float64), torch.full((2,), 5.0, dtype=torch.float64)
    )
    particles = torch.randn(3, 6, 2, generator=gen, dtype=torch.float64)
    log_w = torch.log_softmax(torch.randn(3, 6, generator=gen, dtype=torch.float64), -1)
    y = torch.randn(3, 2, generator=gen, dtype=torch.float64)
    innovation = torch.randn(3, 2, generator=gen, dtype=torch.float64)
    cov = torch.eye(2, dtype=torch.float64).expand(3, 2, 2)
    deception = fdi.ReplacementDeception(box)
    pred = Predictive(log_w, y, innovation, cov)
    _, ll, record = _weigh(net, model, y, particles, None, pred, channel="replacement",
                           deception=deception)  # fmt: skip
    p = torch.sigmoid(record["logit"][:, 0])
    clean = torch.distributions.Normal(0.0, 0.1).log_prob(y[:, None] - particles).sum(-1)
    expect = torch.log((1 - p)[:, None] * clean.exp() + p[:, None] / 100.0)  # box area 10²
    torch.testing.assert_close(ll, expect)
    torch.testing.assert_close(record["attack"], p[:, None] * innovation)
    with pytest.raises(ValueError, match="deception="):
        NeuralCompensation(net, df.ParticleFilter(6), channel="replacement")


def test_kalman_filter_log_likelihood_feature_by_hand():
    """For the KF, ℓ_1 = log N(y_1; H F m_0, H(F P_0 Fᵀ + Q)Hᵀ + R) of the first measurement."""
    model = _linear()
    _, ys = _data(model, runs=2, steps=3)
    net = _net(extra_inputs=1)
    seen = _captured_inputs(net)
    neural_gaussian_filter(model, ys, network=net, filter=df.KalmanFilter(),
                           features=("log_likelihood",))  # fmt: skip
    F, Q, R = model.transition_matrix(0), model.process_cov(0), model.measurement_cov(1)
    S = F @ model.initial.cov @ F.T + Q + R  # H = I
    ell = torch.distributions.MultivariateNormal(F @ model.initial.mean, S).log_prob(ys[:, 0])
    torch.testing.assert_close(seen[0][:, 0, -1], torch.asinh(-ell))  # m = 2: −2ℓ/2


def test_features_must_fit_the_network():
    pf = df.ParticleFilter(8)
    with pytest.raises(ValueError, match="extra_inputs is 0"):
        NeuralCompensation(_net(), pf, features=("mask",))
    with pytest.raises(ValueError, match="distinct names"):
        feature_dim(("mask", "nis"), 2)
    with pytest.raises(ValueError, match="poa_eta"):
        NeuralCompensation(_net(extra_inputs=1), pf, features=("poa",))
    model = _linear()
    _, ys = _data(model)
    with pytest.raises(ValueError, match="needs particles"):
        neural_gaussian_filter(model, ys, network=_net(extra_inputs=1), filter=df.KalmanFilter(),
                               features=("poa",))  # fmt: skip


def test_task_fit_export_and_evaluate_round_trip(tmp_path, monkeypatch, capsys):
    """``fit`` writes only in its run; the exported file and the Lightning checkpoint give
    the same evaluation; ``test`` takes the exported file; another family's checkpoint is
    skipped with its reason."""
    from difffilter.eval.suite import run_suite
    from difffilter.models import registry
    from difffilter.train.cli import main

    shipped = {p.name: p.read_bytes() for p in (ROOT / "checkpoints").iterdir()}
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("sys.argv", ["difffilter-train"])
    config = ["--config", str(ROOT / "train" / "configs" / "four_tank.yaml")]
    tiny = [
        "--data.init_args.batch_size=2",
        "--data.init_args.batches_per_epoch=1",
        "--data.init_args.val_runs=4",
        "--data.init_args.test_runs=2",
        "--model.init_args.num_particles=20",
        "--model.init_args.hidden=4",
        "--model.init_args.features=[mask,log_likelihood,poa]",  # they reach evaluation
        "--trainer.max_epochs=1",
    ]
    assert main(["fit", *config, *tiny]) == 0
    run = tmp_path / "lightning_logs" / "four_tank_nn_grad" / "version_0"
    card = json.loads((run / "four_tank_nn_grad.json").read_text())
    assert card["observer"]["filter"] == "pf" and 0 < card["observer"]["threshold"] < 1
    # what chose the weights (the config's ModelCheckpoint): a sweep ranks its seeds by it
    assert card["monitor"] == {"metric": "val/auc", "mode": "max"}
    assert 0.0 <= card["best_val_score"] <= 1.0
    assert card["observer"]["features"] == ["mask", "log_likelihood", "poa"]
    assert card["observer"]["poa_eta"] == pytest.approx(0.233, abs=5e-4)  # the paper's η
    assert {p.name: p.read_bytes() for p in (ROOT / "checkpoints").iterdir()} == shipped
    assert not (tmp_path / "checkpoints").exists()
    # the threshold is the 1 % one of the validation's attack-free calibration runs
    # (val_runs of them, their own seed), recomputed here from the selected weights
    from difffilter.metrics import threshold_for
    from difffilter.train.task import FilterEstimatorTask, ScenarioDataModule

    assert card["observer"]["target_false_alarm_rate"] == 0.01
    assert card["metrics_last_validation"]["val/fpr_calibration"] <= 0.01
    # where the threshold came from, at the card's top level as calibrate writes it too
    assert card["calibration"] == card["observer"]["extra"]["calibration"]
    assert card["calibration"]["threshold"] == card["observer"]["threshold"]
    best_task = FilterEstimatorTask.load_from_checkpoint(
        next((run / "checkpoints").glob("best-*.ckpt"))
    )
    data = ScenarioDataModule("four_tank_bias", val_runs=4).calibration_data()
    assert data[0].threat is None and not bool(data[1]["flags"].any())
    free, _ = best_task._evaluate(*data)
    assert card["observer"]["threshold"] == pytest.approx(
        threshold_for(free.detection.scores, 0.01)
    )

    assert main(["export", str(run / "four_tank_nn_grad.ckpt"), "--out", "ship/ft.ckpt"]) == 0
    best = next((run / "checkpoints").glob("best-*.ckpt"))
    sc = registry.get("four_tank_bias")
    outs = [
        run_suite(sc, runs=2, estimators=("pf_nn_grad",), checkpoint=c, progress=False)
        for c in (tmp_path / "ship" / "ft.ckpt", best)
    ]
    assert outs[0].checkpoint["used_by"] == ["pf_nn_grad"]
    a, b = (o.outputs["pf_nn_grad"] for o in outs)
    torch.testing.assert_close(a.attack, b.attack, rtol=0, atol=1e-6)
    assert a.detection.threshold == pytest.approx(b.detection.threshold)

    capsys.readouterr()
    assert main(["test", *config, *tiny, "--ckpt_path", "ship/ft.ckpt"]) == 0
    assert "test/attack_rmse" in capsys.readouterr().out

    lfc = ROOT / "checkpoints" / "lfc_nn_grad.ckpt"
    other = run_suite(sc, runs=2, estimators=("pf_nn_grad",), checkpoint=lfc, progress=False)
    assert "pf_nn_grad" in other.skipped and "'kf'" in other.skipped["pf_nn_grad"]


def test_ekf_trainer_learns_the_attack_and_its_export_evaluates_as_pf_nn_ekf(tmp_path, monkeypatch):
    """trainer: ekf (the EKF over the weights, no gradients) on four batches of four runs
    brings the validation attack RMSE below a fifth of the attack's own RMS; the export is
    run as pf_nn_ekf (and skipped as pf_nn_grad), alarming on the standardised estimate."""
    from difffilter.eval.suite import run_suite
    from difffilter.models import registry
    from difffilter.train.cli import main

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("sys.argv", ["difffilter-train"])
    args = [
        "fit", "--config", str(ROOT / "train" / "configs" / "four_tank_ekf.yaml"),
        "--data.init_args.batch_size=4", "--data.init_args.batches_per_epoch=4",
        "--data.init_args.val_runs=16", "--model.init_args.num_particles=50",
        "--trainer.max_epochs=1",
    ]  # fmt: skip
    assert main(args) == 0
    run = tmp_path / "lightning_logs" / "four_tank_nn_ekf" / "version_0"
    card = json.loads((run / "four_tank_nn_ekf.json").read_text())
    assert card["observer"]["trainer"] == "ekf" and card["estimator"] == "pf_nn_ekf"
    assert card["model_config"]["trainer"] == "ekf"
    sc = registry.get("four_tank_bias")
    res = run_suite(sc, runs=4, estimators=("pf_nn_grad",), add=("pf_nn_ekf",),
                    checkpoint=run / "four_tank_nn_ekf.ckpt", progress=False)  # fmt: skip
    assert "by ekf" in res.skipped["pf_nn_grad"] and list(res.outputs) == ["pf_nn_ekf"]
    out, tr = res.outputs["pf_nn_ekf"], res.traj
    scale = tr.attack[tr.flags].square().mean().sqrt()
    assert res.metrics["pf_nn_ekf"]["attack_rmse"] < 0.2 * float(scale)
    assert card["metrics_last_validation"]["val/attack_rmse"] < 0.2 * float(scale)
    assert out.detection.threshold == pytest.approx(card["observer"]["threshold"])
    assert "attack_logit" not in out.extras  # no head: scores are the standardised estimate


def test_a_network_without_past_estimates_equals_one_that_gives_them_zero_weight():
    """a = 0 (δ holds the residuals alone, no recurrence) against a = 2 with the columns of
    V that read the past estimates zeroed and every other weight the same: the same states,
    attack estimates and scores through the Kalman and the particle filter."""
    model = _linear()
    _, ys = _data(model, runs=3, steps=15)
    without = NeuralFDIEstimator(num_areas=1, area_dim=2, a=0, b=2, hidden=5, init="symmetric",
                                 init_scale=0.5, resid_scale=3.0, seed=4, dtype=torch.float64)  # fmt: skip
    zeroed = _net(seed=4)  # a = 2, b = 2
    with torch.no_grad():
        for name in ("W", "P", "c"):
            getattr(zeroed, name).copy_(getattr(without, name))
        zeroed.V.zero_()[..., 2 * 2 :] = without.V  # the last b·d columns read the residuals
    runs = {
        "kf": lambda net: neural_gaussian_filter(model, ys, network=net, filter=df.KalmanFilter()),
        "pf": lambda net: neural_particle_filter(model, ys, network=net, num_particles=64,
                                                 generator=torch.Generator().manual_seed(2)),
    }  # fmt: skip
    for name, run in runs.items():
        a0, a2 = run(without), run(zeroed)
        assert a0.attack.abs().max() > 1e-3, name  # the network answers something
        torch.testing.assert_close(a0.means, a2.means, rtol=0, atol=1e-12, msg=name)
        torch.testing.assert_close(a0.attack, a2.attack, rtol=0, atol=1e-12, msg=name)
        torch.testing.assert_close(a0.detection.scores, a2.detection.scores, rtol=0, atol=1e-12)


def test_past_estimates_must_be_counted_and_kept_for_the_predicted_residual():
    with pytest.raises(ValueError, match="a must be an integer >= 0"):
        NeuralFDIEstimator(num_areas=1, area_dim=2, a=-1)
    without = NeuralFDIEstimator(num_areas=1, area_dim=2, a=0, b=2)
    with pytest.raises(ValueError, match=r"residual='predicted'.*a >= 1"):
        NeuralCompensation(without, df.KalmanFilter(), residual="predicted")
