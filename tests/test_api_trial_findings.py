"""A new user's API trial: the errors that named no argument or gave a silent wrong answer.

``score`` of an output of other runs than the trajectories (torch's "size of tensor a"),
the metrics given numpy arrays (a missing ``.bool()``), ``roc_auc`` with its arguments
swapped (``nan``, "one class absent"), and a stateful likelihood whose record replaced
the filter's own ESS or whose ``weigh`` broke its contract on a bare unpacking error.
Each test checks the fixed behaviour against numbers computed here, not by the library.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from conftest import constant_velocity

import difffilter as df
from difffilter import metrics as dm
from difffilter.estimator import EstimatorOutput
from difffilter.eval.scoring import score

D = torch.float64


# --- score and rmse: an output of other runs than the truth ---------------------------


def _traj(B=4, T=6, dx=2):
    g = torch.Generator().manual_seed(0)
    x = torch.randn(B, T, dx, generator=g, dtype=D)
    flags = torch.zeros(B, T, dtype=torch.bool)
    return SimpleNamespace(x=x, flags=flags, attack=torch.zeros(B, T, 1, dtype=D), info={})


@pytest.mark.parametrize(
    "means_of", [lambda x: x[:2], lambda x: x[0]], ids=["2 of 4 runs", "one run"]
)
def test_score_refuses_an_output_of_other_runs_naming_both(means_of):
    """An output of 2 of the 4 runs, or of one run ``[T, dx]``, is a ValueError naming
    ``output.means``, ``traj.x`` and both shapes (it failed inside torch, or on a mask's
    IndexError)."""
    traj = _traj()
    means = means_of(traj.x) + 0.1
    with pytest.raises(ValueError, match=r"output\.means .* and traj\.x \(4, 6, 2\)") as info:
        score(EstimatorOutput(means), traj, dt=0.1, wall_s=0.0)
    assert str(tuple(means.shape)) in str(info.value)
    with pytest.raises(ValueError, match=r"reference_means \(2, 6, 2\) and traj\.x"):
        score(EstimatorOutput(traj.x), traj, dt=0.1, wall_s=0.0, reference_means=traj.x[:2])


def test_score_of_the_same_runs_gives_the_pooled_rmse():
    """The check passes an output of the trajectories' runs: its state RMSE is the pooled
    root-mean-square error, computed here with numpy."""
    traj = _traj()
    means = traj.x + torch.linspace(-1.0, 1.0, 48, dtype=D).reshape(traj.x.shape)
    got = score(EstimatorOutput(means), traj, dt=0.1, wall_s=0.0)["state_rmse"]
    err = means.numpy() - traj.x.numpy()
    assert got == pytest.approx(math.sqrt(float(np.mean(err**2))), rel=1e-12)


def test_rmse_refuses_shapes_that_do_not_broadcast_and_keeps_broadcasting():
    """``rmse`` of 4 runs against 8 is a ValueError naming ``estimate`` and ``truth``; one
    run ``[T, d]`` against ``[B, T, d]`` still broadcasts (the documented behaviour)."""
    truth = torch.arange(24, dtype=D).reshape(2, 4, 3)
    with pytest.raises(ValueError, match=r"estimate \(1, 4, 2\) and truth \(2, 4, 3\)"):
        dm.rmse(torch.zeros(1, 4, 2, dtype=D), truth)
    got = float(dm.rmse(torch.zeros(4, 3, dtype=D), truth))
    assert got == pytest.approx(math.sqrt(sum(v * v for v in range(24)) / 24), rel=1e-12)


# --- the metrics given numpy arrays ---------------------------------------------------

_A = np.zeros((2, 5), bool)
_F = np.array([[0, 0, 1, 1, 1]] * 2, bool)
_S = np.linspace(0.0, 1.0, 10).reshape(2, 5)
_T = torch.as_tensor


@pytest.mark.parametrize(
    "name, call",
    [
        ("alarms", lambda: dm.detection_rates(_A, _T(_F))),
        ("attacked", lambda: dm.detection_rates(_T(_A), _F)),
        ("valid", lambda: dm.detection_counts(_T(_A), _T(_F), _F)),
        ("scores", lambda: dm.roc_auc(_S, _T(_F))),
        ("labels", lambda: dm.roc_auc(_T(_S), _F)),
        ("scores", lambda: dm.roc_curve(_S, _T(_F))),
        ("estimate", lambda: dm.rmse(_S, _T(_S))),
        ("truth", lambda: dm.rmse(_T(_S), _S)),
        ("alarms", lambda: dm.detection_delay(_A, _T(_F))),
        ("scores", lambda: dm.threshold_for(_S, 0.1)),
        ("scores", lambda: dm.nan_as_lowest(_S)),
        ("flags", lambda: dm.steps_since_attack(_F)),
        ("alarms", lambda: dm.alarm_rate_since_attack(_A, _T(_F))),
    ],
)
def test_metrics_given_a_numpy_array_name_the_argument(name, call):
    """Every metric given a numpy array raises a TypeError that names the argument and
    the fix (``torch.as_tensor``), as ``threshold_for`` did alone."""
    with pytest.raises(TypeError, match=rf"^{name} must be a torch\.Tensor.*torch\.as_tensor"):
        call()


# --- roc_auc: labels bool or 0/1 -------------------------------------------------------


def _pairwise_auc(scores: np.ndarray, labels: np.ndarray) -> float:
    """AUC as the Mann–Whitney statistic: P(score of a positive > a negative's), ties ½."""
    pos, neg = scores[labels], scores[~labels]
    diff = pos[:, None] - neg[None, :]
    return float(((diff > 0) + 0.5 * (diff == 0)).mean())


def test_roc_auc_refuses_swapped_arguments_and_takes_0_1_labels():
    """``roc_auc(flags, scores)`` (swapped) is a ValueError naming ``labels`` and the
    likely swap (it returned ``nan``); float 0/1 labels give the bool labels' AUC, the
    pairwise statistic computed here."""
    g = torch.Generator().manual_seed(0)
    flags = torch.zeros(4, 50, dtype=torch.bool)
    flags[:, 25:] = True
    scores = torch.randn(4, 50, generator=g, dtype=D) + 2.0 * flags
    truth = _pairwise_auc(scores.numpy().ravel(), flags.numpy().ravel())
    for swapped in (lambda: dm.roc_auc(flags, scores), lambda: dm.roc_curve(flags, scores)):
        with pytest.raises(ValueError, match=r"^labels must be bool .*swapped"):
            swapped()
    assert dm.roc_auc(scores, flags) == pytest.approx(truth, abs=1e-12)
    assert dm.roc_auc(scores, flags.double()) == pytest.approx(truth, abs=1e-12)
    with pytest.raises(ValueError, match=r"^labels must be bool"):  # a 2 is no label
        dm.roc_auc(scores, flags.long() * 2)


# --- a stateful likelihood's contract ---------------------------------------------------


class _Lik:
    """A stateful likelihood of the model's density; ``returns`` shapes what weigh gives."""

    def __init__(self, returns=lambda state, lp: (state, lp, {"mystat": state + 7.0})):
        self.returns = returns

    def init(self, model, batch_shape, dtype, device):
        return torch.zeros(batch_shape, dtype=dtype, device=device)

    def weigh(self, state, model, y, particles, k, mask, predictive):
        return self.returns(state, model.measurement_log_prob(y.unsqueeze(-2), particles, k))


def _pf(likelihood, T=4, **kw):
    model = constant_velocity()
    _, ys, _ = model.simulate(T, (2,), generator=torch.Generator().manual_seed(1))
    return df.particle_filter(model, ys, num_particles=32, likelihood=likelihood,
                              generator=torch.Generator().manual_seed(0), **kw)  # fmt: skip


@pytest.mark.parametrize("key", ["ess", "resampled", "degenerate", "log_likelihood", "particles"])
def test_a_record_of_a_key_the_filter_reports_is_refused(key):
    """A record named like the filter's own extras (it replaced ``result.ess`` with the
    plug-in's numbers) is a ValueError naming the likelihood, the step and the key."""
    lik = _Lik(lambda state, lp: (state, lp, {key: torch.full(lp.shape[:-1], 7.0, dtype=D)}))
    with pytest.raises(ValueError, match=rf"the likelihood _Lik recorded '{key}' at step 1:"):
        _pf(lik)


def test_a_record_of_its_own_keys_is_reported_beside_the_filters_ess():
    """A record of another name comes back in ``records``, and ``result.ess`` is the ESS
    ``1 / Σ w²`` of the filter's own weights (recomputed here from the log-weights)."""
    out = _pf(_Lik(), return_particles=True)
    w = out.log_weights.exp()
    np.testing.assert_allclose(out.ess.numpy(), (1.0 / (w * w).sum(-1)).numpy(), rtol=1e-10)
    np.testing.assert_array_equal(out.records["mystat"].numpy(), np.full((2, 4), 7.0))


@pytest.mark.parametrize(
    "returns, error, match",
    [
        (lambda s, lp: (s, lp), TypeError, r"_Lik's weigh returned a tuple of 2 at step 1; .*triple"),
        (lambda s, lp: lp, TypeError, r"_Lik's weigh returned a tensor \(2, 32\) at step 1"),
        (lambda s, lp: (s, lp, [lp]), TypeError, r"the likelihood _Lik's weigh's record is a list at step 1"),
    ],
    ids=["pair", "tensor", "list record"],
)  # fmt: skip
def test_weigh_that_breaks_its_contract_is_named_at_its_step(returns, error, match):
    """``weigh`` returning a pair, a bare tensor or a list record is named with the step
    (they failed as "not enough values to unpack" or "'list' object is not a mapping")."""
    with pytest.raises(error, match=match):
        _pf(_Lik(returns))


class _NoInit:
    def weigh(self, state, model, y, particles, k, mask, predictive):
        raise AssertionError("never called: the filter is refused when it is made")


class _ShortWeigh(_Lik):
    def weigh(self, state, model, y, particles, k, mask):  # no predictive
        raise AssertionError("never called: the filter is refused when it is made")


@pytest.mark.parametrize(
    "likelihood, match",
    [
        (_NoInit(), r"the likelihood _NoInit has a weigh.*no init method: it implements init\("),
        (_ShortWeigh(), r"the likelihood _ShortWeigh's weigh is called as weigh\(state, .*predictive\)"),
        (_Lik, r"likelihood must be an instance, not the class _Lik"),
    ],
    ids=["no init", "weigh without predictive", "a class"],
)  # fmt: skip
def test_a_stateful_likelihood_is_checked_when_the_filter_is_made(likelihood, match):
    """A ``weigh`` without ``init`` (an AttributeError at init), a ``weigh`` that cannot take
    the step's arguments, or the class for an instance: a TypeError naming the plug-in,
    raised by the constructor before any step."""
    with pytest.raises(TypeError, match=match):
        df.ParticleFilter(8, likelihood=likelihood)


def test_a_step_hooks_record_is_checked_as_a_likelihoods():
    """A step hook's ``"ess"`` replaced the filter's in ``extras`` and the result, and a
    list failed in ``dict.update``, naming no hook (left over from the likelihood's fix)."""

    def ess_hook(model, y, mask, carry, out):
        return {"ess": torch.full(carry.log_weights.shape[:-1], 7.0, dtype=D)}

    def list_hook(model, y, mask, carry, out):
        return [out.mean]

    def own_hook(model, y, mask, carry, out):
        return {"spread": carry.particles.std(-2)}

    with pytest.raises(ValueError, match=r"the step hook .*ess_hook recorded 'ess' at step 1"):
        _pf(None, hooks=[ess_hook])
    with pytest.raises(TypeError, match=r"the step hook .*list_hook's record is a list at step 1"):
        _pf(None, hooks=[list_hook])
    out = _pf(None, hooks=[own_hook], return_particles=True)
    w = out.log_weights.exp()
    np.testing.assert_allclose(out.ess.numpy(), (1.0 / (w * w).sum(-1)).numpy(), rtol=1e-10)
    np.testing.assert_allclose(out.records["spread"].numpy(), out.particles.std(-2).numpy())


def test_detection_metrics_refuse_scores_for_decisions():
    """``detection_rates(scores, flags)`` read every nonzero score as an alarm (``.bool()``),
    a TPR and FPR of 1 without a word; so did a score given for ``attacked``."""
    flags = torch.tensor([[False, False, True, True]])
    scores = torch.tensor([[0.2, 0.0, 3.0, 0.4]], dtype=D)
    for call in (
        lambda: dm.detection_rates(scores, flags),
        lambda: dm.detection_delay(scores, flags),
    ):
        with pytest.raises(ValueError, match="alarms must be bool .* against a threshold"):
            call()
    with pytest.raises(ValueError, match="attacked must be bool .* are the arguments swapped"):
        dm.detection_counts(flags, scores)
    # decisions as bool or 0/1: one TP, one FN, no FP, by hand
    alarms = scores > 1.0
    for a in (alarms, alarms.double()):
        r = dm.detection_rates(a, flags.int())
        assert (r["tp"], r["fn"], r["fp"], r["tn"]) == (1, 1, 0, 2) and r["tpr"] == 0.5


def test_binary_checks_read_the_scored_entries_alone_and_rmse_takes_a_number():
    """From a review of the fix: labels or alarms that mark unscored steps with −1 or NaN
    and leave them out by ``valid`` were refused as "swapped"; ``rmse(errors, 0.0)`` was a
    TypeError. The AUC of scores 0.9 > 0.8 > 0.1 against labels 1, 1, 0 is 1 by hand."""
    scores = torch.tensor([0.9, 0.8, 0.1, 0.5], dtype=D)
    valid = torch.tensor([True, True, True, False])
    for unscored in (-1.0, math.nan):
        labels = torch.tensor([1.0, 1.0, 0.0, unscored], dtype=D)
        assert dm.roc_auc(scores, labels, valid) == 1.0
        c = dm.detection_counts(labels.nan_to_num(-1.0) > 0.5, labels, valid)
        assert (c["tp"], c["fp"], c["tn"], c["fn"]) == (2, 0, 1, 0)
    with pytest.raises(ValueError, match="labels must be bool"):  # scored: refused
        dm.roc_auc(scores, torch.tensor([1.0, 1.0, 0.0, -1.0], dtype=D))
    errors = torch.tensor([[3.0, 4.0]], dtype=D)
    assert float(dm.rmse(errors, 0.0)) == pytest.approx(math.sqrt(12.5))
