"""docs/python-api.md: the snippet runs as written and gives difffilter-eval's metrics on
the same runs; the loader names what it needs."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import torch

import difffilter
from difffilter.eval.suite import run_suite
from difffilter.models import registry

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "python-api.md"
COMPARED = ("state_rmse", "attack_rmse", "auc", "tpr", "fpr", "tpr_at_1pct_fpr",
            "detection_delay_steps")  # fmt: skip


def test_the_documented_snippet_gives_the_metrics_of_difffilter_eval(monkeypatch):
    monkeypatch.chdir(ROOT)  # the snippet's paths are the repository's
    blocks = re.findall(r"```python\n(.*?)```", DOC.read_text(), flags=re.S)
    assert len(blocks) == 4
    namespace: dict = {}
    exec(compile(blocks[0], str(DOC), "exec"), namespace)  # noqa: S102
    out, metrics = namespace["out"], namespace["metrics"]
    assert not out.means.requires_grad and out.detection.alarms.dtype == torch.bool
    assert "ekf filter, actuator channel" in repr(namespace["estimator"])
    sc = registry.get("robot_actuator_attack")
    suite = run_suite(sc, runs=8, seed=0, estimators=["gaussian_nn_ekf"], progress=False)
    expected = suite.metrics["gaussian_nn_ekf"]
    for key in COMPARED:
        if expected.get(key) is None:
            assert metrics.get(key) is None, key
        else:
            assert metrics[key] == pytest.approx(expected[key], rel=1e-12, abs=1e-12), key
    torch.testing.assert_close(out.means, suite.outputs["gaussian_nn_ekf"].means, rtol=0, atol=0)


def test_a_trained_estimator_steps_like_any_estimator_and_can_give_gradients():
    sc = registry.get("robot_actuator_attack")
    est = difffilter.load_estimator(sc.shipped_checkpoint())
    model = sc.system()
    gens = {k: torch.Generator().manual_seed(i) for i, k in enumerate(("plant", "attack"))}
    tr = sc.simulate(2, gens)
    whole = est.run(model, tr.y_recv, tr.us, mask=tr.mask)
    carry, means = est.init(model, (2,)), []
    for t in range(5):
        mask = None if tr.mask is None else tr.mask[:, t]
        carry, step = est.step(carry, tr.y_recv[:, t], tr.us[:, t], mask)
        means.append(step.mean)
    torch.testing.assert_close(torch.stack(means, 1), whole.means[:, :5])
    ys = tr.y_recv.clone().requires_grad_(True)
    est.run(model, ys, tr.us, mask=tr.mask, grad=True).means.sum().backward()
    assert ys.grad is not None and bool(ys.grad.abs().sum() > 0)


def test_the_loader_names_what_it_needs():
    lfc = registry.get("lfc_step").shipped_checkpoint()
    with pytest.raises(ValueError, match="LFC closed loop"):
        difffilter.load_estimator(lfc)
    tracking = registry.get("tracking_rrp_deception").shipped_checkpoint()
    with pytest.raises(ValueError, match="deception"):
        difffilter.load_estimator(tracking)
    with pytest.raises(FileNotFoundError):
        difffilter.load_estimator("no/such.ckpt")


def test_the_loader_and_the_online_step_name_what_does_not_fit():
    """An online deployment's trial: a dtype given by name was blamed on the file and
    float16 slipped by; CUDA without CUDA was a bare AssertionError; run() with another
    model than its carry's filtered silently with the carry's; a plain particle filter's
    carry, a network of another plant, and an EKF's carry in a Kalman filter failed inside
    the step (AttributeError), or at the first step."""
    robot = registry.get("robot_actuator_attack").shipped_checkpoint()
    tank = registry.get("four_tank_bias")
    net = difffilter.load_estimator(robot, dtype="float32")
    assert next(net.estimator.network.parameters()).dtype == torch.float32
    with pytest.raises(ValueError, match="dtype must be torch.float32 or torch.float64"):
        difffilter.load_estimator(robot, dtype=torch.float16)
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="device 'cuda': this machine's torch has no CUDA"):
            difffilter.load_estimator(robot, device="cuda")
    with pytest.raises(ValueError, match="resid_dim is 12 .* dim_y = 4: the network was made for"):
        net.init(tank.system(), (1,))
    learned = difffilter.load_estimator(tank.shipped_checkpoint())
    model, other = tank.system(), tank.system()
    ys = torch.zeros(1, 3, 4, dtype=torch.float64)
    carry = learned.init(model, (1,), torch.Generator().manual_seed(0))
    with pytest.raises(ValueError, match="carry holds another model than the model given"):
        learned.run(other, ys, carry=carry)
    plain = difffilter.ParticleFilter(100).init(model, (1,), torch.Generator().manual_seed(0))
    with pytest.raises(ValueError, match="without this estimator's network state"):
        learned.step(plain, ys[:, 0])
    with pytest.raises(ValueError, match="carry.aux holds a stateful likelihood's state"):
        difffilter.ParticleFilter(100).step(carry, ys[:, 0])  # (the reverse: stepped silently)
    ekf = difffilter.ExtendedKalmanFilter().init(model, (1,))
    with pytest.raises(TypeError, match="the Kalman filter needs a linear model"):
        difffilter.KalmanFilter().step(ekf, ys[:, 0])
    linear = difffilter.LinearGaussianModel(
        torch.eye(4, dtype=torch.float64), torch.eye(4, dtype=torch.float64),
        torch.eye(4, dtype=torch.float64), torch.eye(4, dtype=torch.float64),
        torch.zeros(4, dtype=torch.float64), torch.eye(4, dtype=torch.float64),
    )  # fmt: skip
    one = difffilter.KalmanFilter().init(linear, ())
    with pytest.raises(ValueError, match=r"pass one y per run \(\[4\]\)"):
        difffilter.KalmanFilter().step(one, ys[:, 0])


def test_a_chi_square_quantile_is_computed_once():
    """A gated filter's online step asked scipy for the same quantile twice a step (about
    150 µs each, more than the EKF's step)."""
    from difffilter.fdi.detectors import _chi2_ppf, chi_square_quantile

    first = chi_square_quantile(7, 0.99)
    hits = _chi2_ppf.cache_info().hits
    assert chi_square_quantile(7.0, 0.99) == first and _chi2_ppf.cache_info().hits == hits + 1
    from scipy.stats import chi2

    assert first == float(chi2.ppf(0.99, 7))


def test_the_documented_judgement_and_its_intervals(monkeypatch):
    monkeypatch.chdir(ROOT)
    block = next(b for b in re.findall(r"```python\n(.*?)```", DOC.read_text(), flags=re.S)
                 if "study" in b)  # fmt: skip
    namespace: dict = {}
    exec(compile(block, str(DOC), "exec"), namespace)  # noqa: S102
    study, checks, sure = namespace["study"], namespace["checks"], namespace["sure"]
    m = study.metrics
    analytic = [n for n, r in namespace["role"].items() if r == "analytic"]
    best = min(m[n]["state_rmse"] for n in analytic)
    state = next(c for c in checks if c.metric == "state_rmse")
    assert state.holds == (m["gaussian_nn_ekf"]["state_rmse"] <= 1.05 * best)
    mine = sure["estimators"]["gaussian_nn_ekf"]["state_rmse"]
    assert mine["estimate"] == pytest.approx(m["gaussian_nn_ekf"]["state_rmse"] / best, rel=1e-9)
    assert mine["low"] <= mine["high"] and 0.0 <= mine["holds_share"] <= 1.0


def test_the_documented_tensors_only_restore_continues_the_run_bit_for_bit(tmp_path):
    """The two restore snippets of "Online, across restarts" (a deployment trial's route to
    ``weights_only=True``): a Kalman filter stepped with masks and a particle filter with a
    generator of its own, cut at step 6, saved, rebuilt and stepped on, give the
    uninterrupted run's means exactly."""
    blocks = [b for b in re.findall(r"```python\n(.*?)```", DOC.read_text(), flags=re.S)
              if "weights_only=True" in b]  # fmt: skip
    assert len(blocks) == 2
    model = difffilter.LinearGaussianModel(
        F=torch.tensor([[1.0, 0.1], [0.0, 0.9]], dtype=torch.float64),
        H=torch.eye(2, dtype=torch.float64), Q=0.01 * torch.eye(2, dtype=torch.float64),
        R=0.1 * torch.eye(2, dtype=torch.float64), m0=torch.zeros(2, dtype=torch.float64),
        P0=torch.eye(2, dtype=torch.float64),
    )  # fmt: skip
    ys = torch.randn(12, 3, 2, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    masks = torch.rand(12, 3, 2, generator=torch.Generator().manual_seed(5)) > 0.2
    for block, est in zip(blocks, (difffilter.KalmanFilter(), difffilter.ParticleFilter(50))):

        def run(carry, start, stop, est=est):
            means = []
            for t in range(start, stop):
                carry, out = est.step(carry, ys[t], mask=masks[t])
                means.append(out.mean)
            return carry, torch.stack(means)

        g = torch.Generator().manual_seed(7)
        _, whole = run(est.init(model, (3,), g), 0, 12)
        g = torch.Generator().manual_seed(7)
        carry, _ = run(est.init(model, (3,), g), 0, 6)
        namespace = {"torch": torch, "difffilter": difffilter, "c": carry, "g": g,
                     "model": model, "path": tmp_path / "carry.pt"}  # fmt: skip
        exec(compile(block, str(DOC), "exec"), namespace)  # noqa: S102
        assert type(namespace["c"]) is type(carry) and namespace["c"] is not carry
        _, rest = run(namespace["c"], 6, 12)
        torch.testing.assert_close(rest, whole[6:], rtol=0, atol=0)


def test_a_loaded_estimators_arguments_are_named_from_a_fuzzing_trial():
    """``num_particles=2.5`` had run with 2 particles (``True`` with 1, ``"50"`` with 50); a
    ``deception`` on a checkpoint that reads none was ignored; ``run`` advised
    ``nonfinite='skip'`` for a NaN in ``ys`` and then refused the option."""
    from difffilter.models.learned_estimator import load_estimator

    for wrong in (2.5, True, "50", 0):
        with pytest.raises(ValueError, match="num_particles must be a positive integer"):
            load_estimator("checkpoints/four_tank_nn_grad.ckpt", num_particles=wrong)
    with pytest.raises(ValueError, match="deception: this checkpoint's network compensates the "
                                         "sensor channel and reads no deception density"):  # fmt: skip
        load_estimator("checkpoints/four_tank_nn_ekf.ckpt", deception="garbage")
    te = load_estimator("checkpoints/four_tank_nn_grad.ckpt", num_particles=20)
    scenario = registry.get("four_tank_bias")
    model = scenario.system()
    gens = {k: torch.Generator().manual_seed(i) for i, k in enumerate(("plant", "attack"))}
    traj = scenario.simulate(2, gens)
    ys = traj.y_recv[:, :12].clone()
    ys[0, 3, 1] = float("nan")
    with pytest.raises(ValueError, match="nonfinite='skip'"):
        te.run(model, ys, generator=torch.Generator().manual_seed(1))
    skipped = te.run(model, ys, nonfinite="skip", generator=torch.Generator().manual_seed(1))
    masked = te.run(model, ys.nan_to_num(0.0), mask=torch.isfinite(ys),
                    generator=torch.Generator().manual_seed(1))  # fmt: skip
    assert torch.equal(skipped.means, masked.means)  # the entry read as unreceived


@pytest.mark.parametrize("dtype", [torch.float16, torch.complex64, torch.int64, "half"])
def test_the_checkpoint_loader_names_a_dtype_it_cannot_build_before_reading_the_file(dtype):
    """``load_estimator_checkpoint(path, dtype=…)`` (the loader under ``load_estimator``,
    which the train commands call) refuses a dtype other than float32 and float64 by name:
    float16 and complex64 had built a network of that dtype, a name or an integer dtype had
    been blamed on the file ("does not match its own configuration"). Names of the two work."""
    from difffilter.models.neural_estimator import load_estimator_checkpoint

    ckpt = registry.get("robot_actuator_attack").shipped_checkpoint()
    with pytest.raises(ValueError, match="dtype must be torch.float32 or torch.float64"):
        load_estimator_checkpoint(ckpt, dtype=dtype)
    est, _ = load_estimator_checkpoint(ckpt, dtype="float32")
    assert {p.dtype for p in est.parameters()} == {torch.float32}
