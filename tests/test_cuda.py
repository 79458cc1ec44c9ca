"""The CUDA path: every estimator, the drivers and the neural estimator on ``device="cuda"``.

Each test runs the same computation on the CPU and on the GPU and compares them (float64:
the two differ only by the order of floating-point sums), or, where the GPU draws its own
random numbers (particle filters), holds the GPU run to the same Monte Carlo truths as the
CPU tests (the Kalman filter's log-likelihood). Skipped without a CUDA device; CI has none,
so these run where one is lent (``pytest tests/test_cuda.py`` on a GPU machine).
``DIFFFILTER_TEST_DEVICE`` names another device to run them on (default ``cuda``).
"""

from __future__ import annotations

import copy
import math
import os
from pathlib import Path

import pytest
import torch
from conftest import constant_velocity
from test_learned_estimator import _linear, _net
from test_particle import EVERY_RESAMPLER

import difffilter as df
from difffilter import fdi, resampling
from difffilter.estimator import Generators
from difffilter.loop import open_loop
from difffilter.models import registry
from difffilter.models.attacks import Signal
from difffilter.models.learned_estimator import NeuralCompensation
from difffilter.models.lfc import LFCPlant, lfc_loop
from difffilter.noise import Gaussian

ROOT = Path(__file__).resolve().parents[1]
CUDA = torch.device(os.environ.get("DIFFFILTER_TEST_DEVICE", "cuda"))
pytestmark = pytest.mark.skipif(
    CUDA.type == "cuda" and not torch.cuda.is_available(), reason="no CUDA device"
)
TIGHT = dict(rtol=1e-9, atol=1e-9)  # float64, CPU against GPU: summation order only


@pytest.fixture(scope="module")
def data():
    """Constant-velocity model, 16 runs × 30 steps, every third step's first sensor lost."""
    model = constant_velocity(with_input=True)
    g = torch.Generator().manual_seed(11)
    us = 0.5 * torch.randn(16, 30, 1, generator=g, dtype=torch.float64)
    _, ys, _ = model.simulate(30, (16,), us=us, generator=g)
    mask = torch.ones_like(ys, dtype=torch.bool)
    mask[:, ::3, 0] = False
    return model, ys, us, mask


def _gpu(module):
    """A copy on the GPU (``Module.to`` moves in place: the CPU original stays)."""
    return copy.deepcopy(module).to(CUDA)


def _on_cuda(*tensors):
    return [t.to(CUDA) for t in tensors]


def _close(gpu, cpu, **tol):
    assert gpu.device.type == CUDA.type
    torch.testing.assert_close(gpu.cpu(), cpu, **(tol or TIGHT))


@pytest.mark.parametrize(
    "run", [df.kalman_filter, df.extended_kalman_filter, df.unscented_kalman_filter],
    ids=["kf", "ekf", "ukf"],
)  # fmt: skip
def test_gaussian_filters_on_cuda_equal_the_cpu_and_their_gradients_too(data, run):
    model, ys, us, mask = data
    cpu_ys = ys.clone().requires_grad_()
    cpu = run(model, cpu_ys, us, mask=mask)
    cpu.log_likelihood.sum().backward()
    gpu_ys = ys.to(CUDA, copy=True).requires_grad_()
    gpu = run(_gpu(model), gpu_ys, *_on_cuda(us), mask=mask.to(CUDA))
    gpu.log_likelihood.sum().backward()
    for name in ("means", "covs", "log_likelihood"):
        _close(getattr(gpu, name), getattr(cpu, name))
    _close(gpu_ys.grad, cpu_ys.grad)


def test_the_online_step_at_one_run_on_cuda_equals_the_sequence_run(data):
    """The public online step (one run, the path a deployed estimator takes) on the GPU."""
    model, ys, us, mask = data
    gpu_model = _gpu(model)
    kf = df.KalmanFilter()
    carry = kf.init(gpu_model)
    means = []
    for t in range(ys.shape[1]):
        carry, out = kf.step(carry, ys[0, t].to(CUDA), us[0, t].to(CUDA), mask[0, t].to(CUDA))
        means.append(out.mean)
    ref = df.kalman_filter(model, ys[0], us[0], mask=mask[0])
    _close(torch.stack(means), ref.means)


@pytest.mark.parametrize("resampler", EVERY_RESAMPLER, ids=lambda r: type(r).__name__)
def test_every_resampler_runs_a_consistent_particle_filter_on_cuda(resampler):
    """On a CUDA generator: the log-likelihood's mean over runs within 4 standard errors
    of the Kalman filter's (the CPU test's criterion), reproducible from the generator,
    and a finite gradient through the resampler."""
    model = constant_velocity()
    _, ys, _ = model.simulate(20, (), generator=torch.Generator().manual_seed(7))
    kf = df.kalman_filter(model, ys)
    runs, n = (8, 200) if isinstance(resampler, resampling.OptimalTransport) else (32, 500)
    gpu_ys = ys.to(CUDA).expand(runs, -1, -1).clone().requires_grad_()

    def run(seed):
        return df.particle_filter(_gpu(model), gpu_ys, num_particles=n, resampler=resampler,
                                  generator=torch.Generator(CUDA).manual_seed(seed))  # fmt: skip

    res = run(0)
    ll = res.log_likelihood
    assert ll.device.type == CUDA.type and res.means.device.type == CUDA.type
    se = ll.std().item() / math.sqrt(runs)
    assert abs(ll.mean().item() - kf.log_likelihood.item()) < 4 * se + 0.05
    torch.testing.assert_close(run(0).means, res.means, rtol=0, atol=0)
    ll.sum().backward()
    assert bool(torch.isfinite(gpu_ys.grad).all())


def test_particle_filter_online_at_one_run_on_cuda():
    """B = 1, N = 100 through the public step (its one-run fast path) on the GPU: the
    means follow the Kalman filter's within the particle error."""
    model = constant_velocity()
    _, ys, _ = model.simulate(25, (), generator=torch.Generator().manual_seed(3))
    pf, gpu_model = df.ParticleFilter(2000), _gpu(model)
    carry = pf.init(gpu_model, (), generator=Generators.of(torch.Generator(CUDA).manual_seed(1)))
    means = []
    for t in range(25):
        carry, out = pf.step(carry, ys[t].to(CUDA))
        means.append(out.mean)
    kf = df.kalman_filter(model, ys)
    error = (torch.stack(means).cpu() - kf.means).abs()
    assert float((error / kf.covs.diagonal(dim1=-2, dim2=-1).sqrt()).max()) < 0.5


def test_a_gaussian_with_a_scalar_loc_lives_on_its_covariances_device():
    """A scalar ``loc`` is broadcast on the covariance's device (it was made on the CPU)."""
    cov = torch.tensor([[2.0, 0.5], [0.5, 1.0]], dtype=torch.float64)
    cpu = Gaussian(0.25, cov=cov)
    gpu = Gaussian(0.25, cov=cov.to(CUDA))
    assert gpu.loc.device.type == CUDA.type
    value = torch.tensor([[0.1, -0.3], [1.0, 2.0]], dtype=torch.float64)
    _close(gpu.log_prob(value.to(CUDA)), cpu.log_prob(value))
    draws = gpu.sample((3,), generator=torch.Generator(CUDA).manual_seed(0))
    assert draws.device.type == CUDA.type and draws.shape == (3, 2)


def test_chi_square_gated_filter_on_cuda_equals_the_cpu(data):
    model, ys, us, _ = data
    ys = ys.clone()
    ys[:, 12] += 6.0  # one injected packet in every run
    det = fdi.ChiSquareDetector(2, 1e-3)
    cpu = fdi.gated_extended_kalman_filter(model, ys, us, detector=det)
    gpu = fdi.gated_extended_kalman_filter(_gpu(model), *_on_cuda(ys, us), detector=det)
    _close(gpu.means, cpu.means)
    assert torch.equal(gpu.alarms.cpu(), cpu.alarms) and bool(cpu.alarms[:, 12].all())


def test_the_neural_estimator_on_cuda_equals_the_cpu_values_and_gradients():
    model = _linear()
    _, ys, _ = model.simulate(15, (4,), generator=torch.Generator().manual_seed(0))
    ys = ys.clone()
    ys[:, 5:, 0] += 0.8
    outs, grads = [], []
    for device in ("cpu", CUDA):
        net = _net().to(device)
        est = NeuralCompensation(net, df.KalmanFilter())
        out = open_loop(est, copy.deepcopy(model).to(device), ys.to(device))
        (out.means.square().sum() + out.attack.square().sum()).backward()
        outs.append(out)
        grads.append([p.grad for p in net.parameters()])
    for name in ("means", "covs", "attack"):
        _close(getattr(outs[1], name), getattr(outs[0], name))
    assert [g is None for g in grads[1]] == [g is None for g in grads[0]]
    reached = [(gpu, cpu) for gpu, cpu in zip(grads[1], grads[0]) if cpu is not None]
    assert len(reached) >= 2  # the input and output weights at least
    for gpu, cpu in reached:
        _close(gpu, cpu)


def test_the_lfc_closed_loop_on_cuda_equals_the_cpu():
    """Plant → attack → observer → secure controller, all on the GPU (the controller's LQR
    gain is solved on the CPU and follows the plant)."""
    plant = LFCPlant()
    xi, theta = plant.sample_noise(3, 80, torch.Generator().manual_seed(2))
    load = torch.tensor([[0.01, 0.0]], dtype=torch.float64)
    signal = torch.zeros(80, 10, dtype=torch.float64)
    signal[30:60, 2] = 0.5  # the scenarios' channel
    loops = [
        lfc_loop(copy.deepcopy(plant).to(device), df.KalmanFilter(), xi.to(device), theta.to(device),
                 load.to(device), attack=Signal(signal.to(device))).trajectories
        for device in ("cpu", CUDA)
    ]  # fmt: skip
    for name in ("x", "y_recv"):
        _close(getattr(loops[1], name), getattr(loops[0], name))
    assert torch.equal(loops[1].flags.cpu(), loops[0].flags)


def test_a_shipped_checkpoint_on_cuda_equals_the_cpu():
    """``load_estimator(path, device=...)``: the robot's trained network in its EKF on the
    GPU gives the CPU's estimates, attack estimates and scores."""
    sc = registry.get("robot_actuator_attack")
    gens = {k: torch.Generator().manual_seed(i) for i, k in enumerate(("plant", "attack"))}
    tr = sc.simulate(3, gens)
    mask = None if tr.mask is None else tr.mask.to(CUDA)
    cpu = df.load_estimator(sc.shipped_checkpoint()).run(sc.system(), tr.y_recv, tr.us,
                                                         mask=tr.mask)  # fmt: skip
    est = df.load_estimator(sc.shipped_checkpoint(), device=CUDA)
    gpu = est.run(_gpu(sc.system()), *_on_cuda(tr.y_recv, tr.us), mask=mask)
    for name in ("means", "attack"):
        _close(getattr(gpu, name), getattr(cpu, name))
    _close(gpu.detection.scores, cpu.detection.scores)


CONFIGS = sorted((ROOT / "train" / "configs").glob("*.yaml"))


@pytest.mark.parametrize("config", CONFIGS, ids=lambda p: p.name)
def test_every_training_config_runs_on_cuda(config, tmp_path, monkeypatch):
    """``difffilter-train fit --trainer.accelerator=gpu``: the batches (drawn on the CPU
    from their seeds) follow the weights to the GPU, the particles draw from generators
    there, and the LFC closed loop runs there too."""
    from difffilter.train.cli import main

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("sys.argv", ["difffilter-train"])
    accelerator = "gpu" if CUDA.type == "cuda" else CUDA.type
    code = main(["fit", "--config", str(config), "--trainer.fast_dev_run=1",
                 f"--trainer.accelerator={accelerator}",
                 f"--trainer.default_root_dir={tmp_path}"])  # fmt: skip
    assert code == 0


def test_an_adversarial_fit_and_its_export_run_on_cuda(tmp_path, monkeypatch):
    """Two epochs with attacks crafted by gradient on the GPU (from the second epoch on),
    the export, and the exported checkpoint loaded back on the CPU (``weights_only``)."""
    from difffilter.train.cli import main

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("sys.argv", ["difffilter-train"])
    accelerator = "gpu" if CUDA.type == "cuda" else CUDA.type
    args = [
        "fit", "--config", str(ROOT / "train" / "configs" / "four_tank.yaml"),
        f"--trainer.accelerator={accelerator}", "--trainer.max_epochs=2",
        "--data.init_args.batch_size=2", "--data.init_args.batches_per_epoch=2",
        "--data.init_args.val_runs=4", "--model.init_args.num_particles=20",
        "--model.init_args.hidden=4", "--model.init_args.adversarial_runs=2",
        "--model.init_args.adversarial_iterations=2", "--model.init_args.adversarial_every=1",
    ]  # fmt: skip
    assert main(args) == 0
    exported = sorted(tmp_path.rglob("four_tank_nn_grad.ckpt"))
    assert exported, "the fit exports its checkpoint"
    est = df.load_estimator(exported[0])
    assert all(p.device.type == "cpu" for p in est.estimator.network.parameters())
