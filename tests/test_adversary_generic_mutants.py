"""Mutation review of train/adversarial.py and models/generic_estimators.py.

Each test pins a behaviour a small bug left unpinned, against an independent truth: a
hand-written schedule, the augmented batch recomputed in numpy, ``scipy.stats.chi2.ppf``,
a float64 numpy Kalman recursion, or the lists of the module docstrings and
docs/your-own-plant.md. The crafting and the filters are mocked where only the arguments
they get are at stake.
"""

from __future__ import annotations

import types

import numpy as np
import pytest
import torch
from scipy.stats import chi2

from difffilter.train.adversarial import Adversary

F32, F64 = torch.float32, torch.float64


# -- train/adversarial.py -----------------------------------------------------------------
def test_the_adversary_is_due_at_first_and_then_every_every_steps():
    """No attack yet: due at any step; then due exactly at the multiples of ``every``
    (a hand-written schedule for every = 5 over steps 0…19)."""
    a = Adversary(runs=1, every=5)
    assert all(a.due(s) for s in (0, 1, 3, 7, 13)), "no attack yet: due at every step"
    a.attack = torch.ones(4, 2)
    got = [s for s in range(20) if a.due(s)]
    assert got == [0, 5, 10, 15], f"due at {got}, want [0, 5, 10, 15]"


@pytest.mark.parametrize(
    ("kwargs", "ok"),
    [
        ({"runs": 1, "iterations": 1, "every": 1, "crafting_runs": 1}, True),
        ({"runs": True}, False),
        ({"every": True}, False),
        ({"runs": 0}, False),
        ({"crafting_runs": 2.0}, False),
        ({"onsets": (3, 3)}, True),
        ({"onsets": (1, 1)}, True),
        ({"onsets": (0, 4)}, False),
        ({"onsets": (4, 3)}, False),
    ],
)
def test_the_adversarys_settings_are_integers_at_least_one_and_onsets_first_le_last(kwargs, ok):
    """``runs, iterations, every, crafting_runs`` are integers ≥ 1 (a bool is not one),
    ``onsets = (first, last)`` with ``1 ≤ first ≤ last``, both included (docstring)."""
    kwargs = {"runs": 1, **kwargs}
    if ok:
        Adversary(**kwargs)
    else:
        with pytest.raises(ValueError, match="adversarial_"):
            Adversary(**kwargs)


def _batch(scenario, runs, seed):
    from difffilter.train.task import training_batch

    return training_batch(scenario, runs, seed, F32)


def test_the_augmented_runs_are_recomputed_in_numpy():
    """``ỹ = y + a``, ``attack = a``, ``flags = (k ≥ onset)`` with k = 1…T, on fresh
    attack-free runs appended after the batch's own (module docstring), recomputed in
    numpy: an attack on channels 1 and 3 only, from onset 7, over a 2-run batch."""
    from difffilter.models import registry

    scenario = registry.get("four_tank_bias")
    T, dy = scenario.steps, 4
    a_np = np.zeros((T, dy))
    a_np[6:, 1], a_np[6:, 3] = 0.25, -0.5
    adv = Adversary(runs=3)
    adv.attack, adv.onset = torch.tensor(a_np, dtype=F32), 7
    batch = _batch(scenario, 2, 1)
    out = adv.augment(batch, scenario, 9, F32)
    free = _batch(scenario.with_threat(None), 3, 9)
    assert out["y_recv"].shape == (5, T, dy)
    np.testing.assert_array_equal(out["y_recv"][:2].numpy(), batch["y_recv"].numpy())
    want_y = free["y_recv"].numpy().astype(np.float64) + a_np
    np.testing.assert_allclose(out["y_recv"][2:].numpy(), want_y, rtol=0, atol=1e-6)
    np.testing.assert_allclose(out["attack"][2:].numpy(), np.broadcast_to(a_np, (3, T, dy)))
    np.testing.assert_array_equal(out["x"][2:].numpy(), free["x"].numpy())
    k = np.arange(1, T + 1)
    np.testing.assert_array_equal(out["flags"][2:].numpy(), np.broadcast_to(k >= 7, (3, T)))
    assert out["flags"].dtype == batch["flags"].dtype


def test_per_entry_flags_flag_the_attacked_entries_from_the_onset_only():
    """A batch of per-entry flags ``[R, T, dy]``: an appended run's entry is flagged where
    ``k ≥ onset`` and its attack is nonzero (numpy); an attack of one nonzero entry is
    still an attack (the runs are added)."""
    from difffilter.models import registry

    scenario = registry.get("four_tank_bias")
    T, dy = scenario.steps, 4
    a_np = np.zeros((T, dy))
    a_np[2:, 2] = 0.3  # nonzero from step k = 3, before the onset k = 10
    adv = Adversary(runs=2)
    adv.attack, adv.onset = torch.tensor(a_np, dtype=F32), 10
    batch = _batch(scenario, 2, 1)
    batch["flags"] = batch["attack"] != 0
    out = adv.augment(batch, scenario, 4, F32)
    k = np.arange(1, T + 1)[:, None]
    want = (k >= 10) & (a_np != 0)
    assert out["flags"].shape == (4, T, dy)
    np.testing.assert_array_equal(out["flags"][2:].numpy(), np.broadcast_to(want, (2, T, dy)))


def test_an_attack_of_other_width_than_the_batchs_is_refused_by_name():
    """The adversary's attack covers every sensor channel; a batch whose attack has
    another width is refused with the reason (a ValueError, not a failed concatenation)."""
    from difffilter.models import registry

    scenario = registry.get("four_tank_bias")
    adv = Adversary(runs=1)
    adv.attack, adv.onset = torch.ones(scenario.steps, 4), 3
    batch = _batch(scenario, 1, 1)
    batch["attack"] = batch["attack"][..., :2]
    with pytest.raises(ValueError, match="sensor attack on every channel"):
        adv.augment(batch, scenario, 2, F32)


class _Param:
    def __init__(self, flag):
        self.requires_grad = flag

    def requires_grad_(self, flag):
        self.requires_grad = flag


def _fake_task(steps=30, dy=2, threshold=1.25, far=0.03):
    """What :meth:`Adversary.craft` reads of a task, its attack-free runs drawn by seed."""

    def simulate(runs, gens, dtype=None):  # runs drawn from the plant stream given
        y = torch.randn(runs, steps, dy, generator=gens["plant"], dtype=F64)
        return types.SimpleNamespace(y_true=y, x=y.clone(), us=y[..., :1] + 1.0, mask=None)

    scenario = types.SimpleNamespace(
        steps=steps, with_threat=lambda t: types.SimpleNamespace(simulate=simulate)
    )
    params = [_Param(True), _Param(False), _Param(True)]
    return types.SimpleNamespace(
        scenario_of_data=lambda: scenario, hparams=types.SimpleNamespace(model_seed=3),
        estimator_object=lambda training: "estimator",
        estimator=types.SimpleNamespace(parameters=lambda: params), device="cpu",
        system="system", current_threshold=lambda: threshold, false_alarm_rate=far,
        _dtype=F32,
    )  # fmt: skip


def test_a_crafting_passes_the_tasks_settings_and_keeps_what_it_crafted(monkeypatch):
    """The crafting gets the current threshold, the task's false-alarm rate, the drawn
    onset (the one kept), ``crafting_runs`` runs and their known inputs, ``iterations`` Adam steps, the weights
    frozen during it and restored after (a frozen one stays frozen); it logs the best
    error within the alarm budget and ``budget − ε``; its history holds
    ``(step, onset, kept)`` (the crafting mocked, its history written by hand)."""
    import difffilter.train.adversarial as adv
    from difffilter.stealthy import CraftedAttack, StealthySettings

    seen = {}
    task = _fake_task()

    def fake(est, system, ys, xs, tau, *, far, us, mask, onset, settings, generator, **kw):
        seen.update(tau=tau, far=far, onset=onset, runs=ys.shape[0], it=settings.iterations,
                    us_is_input=us is not None and torch.equal(us, ys[..., :1] + 1.0),
                    frozen=[p.requires_grad for p in task.estimator.parameters()])  # fmt: skip
        history = [(0, 1.5, 0.0, 0.01), (1, 4.0, 0.0, 0.2), (2, 3.0, 0.0, 0.04)]
        values = torch.zeros(ys.shape[-2:], dtype=F64)
        values[onset - 1 :] = 0.7
        return CraftedAttack(values, onset, history, None, budget=0.05)

    monkeypatch.setattr(adv, "craft_stealthy_attack", fake)
    a = Adversary(runs=1, iterations=3, crafting_runs=5, onsets=(4, 9))
    logs = a.craft(task, step=12)
    assert seen["tau"] == 1.25 and seen["far"] == 0.03
    assert seen["runs"] == 5 and seen["it"] == 3 and seen["us_is_input"]
    assert 4 <= seen["onset"] <= 9 and a.onset == seen["onset"]
    assert seen["frozen"] == [False, False, False]
    assert [p.requires_grad for p in task.estimator.parameters()] == [True, False, True]
    assert logs["adversarial_error"] == 3.0  # J = 4 broke the budget 0.05
    assert logs["adversarial_onset"] == float(a.onset)
    slack = StealthySettings().slack
    assert logs["adversarial_attack_free_alarm_rate"] == pytest.approx(0.05 - slack, abs=1e-15)
    assert a.history == [(12, a.onset, 3.0)]
    assert a.attack.dtype == F32 and not a.attack[: a.onset - 1].any()


def test_craftings_at_other_steps_draw_other_onsets_and_runs(monkeypatch):
    """Each crafting draws its onset and its runs from a seed of its own step: over 12
    steps with onsets (1, 30) the onsets are not all equal, and no two steps' crafting runs
    coincide."""
    import difffilter.train.adversarial as adv
    from difffilter.stealthy import CraftedAttack

    seen = []

    def fake(est, system, ys, xs, tau, *, onset, **kw):
        seen.append((onset, ys.clone()))
        return CraftedAttack(torch.zeros(ys.shape[-2:]), onset, [], None, budget=0.05)

    monkeypatch.setattr(adv, "craft_stealthy_attack", fake)
    task = _fake_task()
    a = Adversary(runs=1, onsets=(1, 30))
    for step in range(12):
        a.craft(task, step)
    assert len({o for o, _ in seen}) > 1, "one onset for every step"
    for i in range(len(seen)):
        for j in range(i):
            assert not torch.equal(seen[i][1], seen[j][1]), f"steps {j} and {i}: same runs"


def test_onsets_past_the_horizon_are_clipped_or_refused(monkeypatch):
    """``onsets = (25, 50)`` on a horizon of T = 30 steps: the last onset is clipped to the
    horizon (onsets the runs have, 25 … 30); ``(40, 50)`` starts after it and is refused by
    name (clipped to k = 30, an attack of one row, a crafting an epoch later had failed on
    too few attacked steps: a red-team trial)."""
    import difffilter.train.adversarial as adv
    from difffilter.stealthy import CraftedAttack

    seen = []

    def fake(est, system, ys, xs, tau, *, onset, **kw):
        seen.append(onset)
        return CraftedAttack(torch.zeros(ys.shape[-2:]), onset, [], None, budget=0.05)

    monkeypatch.setattr(adv, "craft_stealthy_attack", fake)
    a = Adversary(runs=1, onsets=(25, 50))
    for step in range(6):
        a.craft(_fake_task(steps=30), step)
    assert all(25 <= k <= 30 for k in seen) and len(seen) == 6
    with pytest.raises(ValueError, match="first onset is after the scenario's last step"):
        Adversary(runs=1, onsets=(40, 50)).craft(_fake_task(steps=30), 0)


def test_the_adversarys_state_is_a_snapshot_and_restores_attack_onset_history():
    """``state_dict`` is what a resumed run needs, as it was when saved (a later crafting
    does not rewrite it); ``load_state_dict`` restores the attack, the onset and the
    history (the resumed run is due on the original schedule)."""
    a = Adversary(runs=1, every=4)
    a.attack, a.onset, a.history = torch.arange(6.0).reshape(3, 2), 2, [(4, 2, 0.5)]
    state = a.state_dict()
    a.history.append((8, 3, 0.7))
    assert state["history"] == [(4, 2, 0.5)]
    b = Adversary(runs=1, every=4)
    b.load_state_dict({"attack": state["attack"], "onset": 2, "history": [[4, 2, 0.5]]})
    assert torch.equal(b.attack, torch.arange(6.0).reshape(3, 2)) and b.onset == 2
    assert b.history == [(4, 2, 0.5)]
    assert [s for s in range(1, 10) if b.due(s)] == [4, 8]


# -- models/generic_estimators.py ---------------------------------------------------------
#: The generic suite by its module docstring and docs/your-own-plant.md: the filters
#: gated by χ² or CUSUM, the UDP-like pair, the PoA PFs, the modified PFs, the mixture PF,
#: and the learned estimators.
SUITE = {
    "normal_pf_attack_free", "normal_pf", "modified_pf", "modified_pf_est",
    "mixture_likelihood_pf", "chi_square_kf", "cusum_kf", "chi_square_ekf", "cusum_ekf",
    "chi_square_ukf", "cusum_ukf", "chi_square_udp_kf", "cusum_udp_kf", "pf_nn_grad",
    "gaussian_nn_grad",
}  # fmt: skip


def test_the_default_suite_is_the_documented_list():
    """DEFAULT_SUITE is every generic estimator with detection and the learned ones, each
    once (module docstring; docs/your-own-plant.md)."""
    from difffilter.models.generic_estimators import DEFAULT_SUITE

    assert len(DEFAULT_SUITE) == len(set(DEFAULT_SUITE)) and set(DEFAULT_SUITE) == SUITE


def test_each_generic_estimator_declares_the_needs_of_its_docstring():
    """The KF-based ones need a linear model (the UDP-like ones also unacknowledged input
    loss), the EKF/UKF ones nothing; the oracle modified PF an attack on the measurements,
    the estimated one assumes it, the mixture PF a deception density, the attack-free
    reference attack-free y and the true measurements (module docstring, needs.py)."""
    from difffilter.models.estimators import get
    from difffilter.models.needs import (
        ASSUMES_DECEPTION_DENSITY,
        ASSUMES_SENSOR_ATTACK,
        ATTACK_FREE_MEASUREMENTS,
        LINEAR_MODEL,
        SENSOR_ATTACK,
        UNACKNOWLEDGED_INPUT_LOSS,
    )

    want = {
        "kf": {LINEAR_MODEL}, "ekf": set(), "ukf": set(), "bootstrap_pf": set(),
        "chi_square_kf": {LINEAR_MODEL}, "cusum_kf": {LINEAR_MODEL},
        "chi_square_ekf": set(), "cusum_ekf": set(), "chi_square_ukf": set(),
        "cusum_ukf": set(), "udp_kf": {LINEAR_MODEL, UNACKNOWLEDGED_INPUT_LOSS},
        "chi_square_udp_kf": {LINEAR_MODEL, UNACKNOWLEDGED_INPUT_LOSS},
        "cusum_udp_kf": {LINEAR_MODEL, UNACKNOWLEDGED_INPUT_LOSS}, "normal_pf": set(),
        "normal_pf_attack_free": {ATTACK_FREE_MEASUREMENTS}, "modified_pf": {SENSOR_ATTACK},
        "modified_pf_est": {ASSUMES_SENSOR_ATTACK},
        "mixture_likelihood_pf": {ASSUMES_DECEPTION_DENSITY},
    }  # fmt: skip
    for name, needs in want.items():
        assert set(get(name).needs) == needs, f"{name}: {get(name).needs}"
    ref = get("normal_pf_attack_free")
    assert ref.clean_input and ref.reference and get("modified_pf").oracle


@pytest.mark.parametrize(("name", "far"), [("chi_square_kf", 0.05), ("chi_square_ukf", 0.001)])
def test_a_chi_square_gate_threshold_is_the_scipy_quantile(name, far):
    """``τ = F⁻¹_{χ²(dy)}(1 − α)`` (scipy), α the scenario's false-alarm rate, dy = 3."""
    from difffilter.models.generic_estimators import GATED, gated_estimator

    ctx = types.SimpleNamespace(model=types.SimpleNamespace(dim_x=2, dim_y=3),
                                scenario=types.SimpleNamespace(false_alarm_rate=far))  # fmt: skip
    thr = float(gated_estimator(ctx, name).detector.threshold)
    assert abs(thr - chi2.ppf(1 - far, 3)) < 1e-8, f"{thr} vs {chi2.ppf(1 - far, 3)}"
    assert GATED[name][0] == name.removeprefix("chi_square_")


def test_the_gated_filters_are_the_named_filter_and_detector():
    """``cusum_<f>`` is <f> gated by the context's calibrated CUSUM, ``<f>`` the library's
    filter of that name; an unknown name is refused by name."""
    from difffilter import fdi
    from difffilter.extended import ExtendedKalmanFilter, UnscentedKalmanFilter
    from difffilter.kalman import KalmanFilter
    from difffilter.models.generic_estimators import gated_estimator

    cusum = fdi.CusumDetector(3.0, threshold=5.0)
    ctx = types.SimpleNamespace(cusum=lambda filt: cusum)
    for kind, cls in (("kf", KalmanFilter), ("ekf", ExtendedKalmanFilter),
                      ("ukf", UnscentedKalmanFilter)):  # fmt: skip
        gated = gated_estimator(ctx, f"cusum_{kind}")
        assert gated.detector is cusum and type(gated.filter) is cls
    with pytest.raises(ValueError, match="not a gated Gaussian filter"):
        gated_estimator(ctx, "kf")


def test_the_plain_kf_gives_the_numpy_kalman_means_and_covariances():
    """``kf`` (no attack handling): means and covariances of a float64 numpy Kalman
    recursion (predict, then update, from the prior) on a scalar model, T = 4."""
    import difffilter as df
    from difffilter.models.estimators import get

    F, H, Q, R, m0, P0 = 0.9, 2.0, 0.1, 0.5, 0.3, 1.0
    t = lambda v: torch.tensor([[v]], dtype=F64)  # noqa: E731
    model = df.LinearGaussianModel(t(F), t(H), t(Q), t(R), torch.tensor([m0], dtype=F64), t(P0))
    ys = np.array([1.0, -0.5, 2.0, 0.25])
    m, P, means, covs = m0, P0, [], []
    for y in ys:
        m, P = F * m, F * P * F + Q
        S = H * P * H + R
        K = P * H / S
        m, P = m + K * (y - H * m), (1 - K * H) * P
        means.append(m)
        covs.append(P)
    tr = types.SimpleNamespace(y_recv=torch.tensor(ys, dtype=F64)[None, :, None], us=None,
                               mask=None)  # fmt: skip
    out = get("kf").factory(types.SimpleNamespace(model=model))(tr)
    np.testing.assert_allclose(out.means.numpy().ravel(), means, rtol=1e-10)
    assert out.covs is not None
    np.testing.assert_allclose(out.covs.numpy().ravel(), covs, rtol=1e-10)


def test_the_kalman_proposal_pf_gets_its_proposal_and_the_bootstrap_none(monkeypatch):
    """``kalman_proposal_pf`` runs the PF with a KalmanProposal, ``bootstrap_pf`` with the
    default (bootstrap) proposal (their registry descriptions)."""
    import difffilter as df
    from difffilter.models.estimators import get
    from difffilter.particle import KalmanProposal

    seen = {}

    def fake(model, ys, us, mask=None, **kw):
        seen["proposal"] = kw.get("proposal")
        return types.SimpleNamespace(means=ys, covs=None)

    monkeypatch.setattr(df, "particle_filter", fake)
    ctx = types.SimpleNamespace(model=None, particle_kwargs=lambda n: {})
    tr = types.SimpleNamespace(y_recv=torch.zeros(1, 2, 1), us=None, mask=None)
    get("kalman_proposal_pf").factory(ctx)(tr)
    assert isinstance(seen["proposal"], KalmanProposal)
    get("bootstrap_pf").factory(ctx)(tr)
    assert seen["proposal"] is None


def _gated_ctx(scenario):
    from difffilter import fdi

    det = fdi.CusumDetector(3.0, threshold=5.0)
    return types.SimpleNamespace(model="model", scenario=scenario, cusum=lambda f: det), det


def test_a_gated_filter_runs_on_the_study_with_its_mask_or_in_its_own_loop(monkeypatch):
    """On the study's trajectories (receptions ``mask`` passed) unless an adaptive attack
    (``reads_view``) meets it in a closed loop, where it runs in ``scenario.loop``; an
    adaptive attack on an open loop, or a closed loop without one, is not met."""
    from difffilter import fdi
    from difffilter.models.estimators import get
    from difffilter.models.generic_estimators import meets_adaptive_attack

    reads = types.SimpleNamespace(reads_view=True)
    blind = types.SimpleNamespace()
    sc = lambda closed, attack: types.SimpleNamespace(  # noqa: E731
        closed_loop=closed, simulated_attack=lambda: attack,
        loop=lambda step, info: ("loop", step, info))  # fmt: skip
    assert meets_adaptive_attack(sc(True, reads))
    assert not meets_adaptive_attack(sc(False, reads))
    assert not meets_adaptive_attack(sc(True, blind))
    assert not meets_adaptive_attack(sc(True, None))

    seen = {}
    monkeypatch.setattr(fdi, "gated_gaussian_filter",
                        lambda model, ys, us, mask=None, **kw: seen.update(mask=mask) or "study")  # fmt: skip
    mask = torch.ones(1, 3, 2, dtype=torch.bool)
    tr = types.SimpleNamespace(y_recv=torch.zeros(1, 3, 2), us=None, mask=mask, info={"i": 1})
    ctx, det = _gated_ctx(sc(False, reads))
    assert get("cusum_ekf").factory(ctx)(tr) == "study" and seen["mask"] is mask
    ctx, det = _gated_ctx(sc(True, reads))
    out = get("cusum_ekf").factory(ctx)(tr)
    assert out[0] == "loop" and out[1].detector is det and out[2] == {"i": 1}


class _Loss:
    def __init__(self, schedule, acknowledged=False, on_loss="zero"):
        self.schedule, self.acknowledged, self.on_loss = schedule, acknowledged, on_loss


def _loss_scenario(loss):
    return types.SimpleNamespace(input_loss_schedule=lambda: loss)


def test_the_udp_like_filter_takes_the_arrival_rate_packets_and_on_loss_of_the_scenario():
    """Arrival rate ``1 −`` the loss rate; one packet per actuator (or none listed) is
    independent with more than one actuator, one packet for all is not (with one
    actuator the two are the same filter: not pinned); the
    scenario's ``on_loss``; refused: no loss, acknowledged packets, bursts, a rate that is
    not a number (a bool), packets grouping some actuators but not all (docstring)."""
    from difffilter.expected_input import OnLoss
    from difffilter.models.generic_estimators import expected_input_filter
    from difffilter.models.schedules import BurstLoss

    one, three = types.SimpleNamespace(dim_u=1), types.SimpleNamespace(dim_u=3)
    rated = lambda rate, packets=None: types.SimpleNamespace(rate=rate, packets=packets)  # noqa: E731
    f = expected_input_filter(_loss_scenario(_Loss(rated(0.3), on_loss="zero")), one)
    assert abs(float(f.arrival_rate) - 0.7) < 1e-12
    assert f.on_loss is OnLoss.ZERO
    f = expected_input_filter(_loss_scenario(_Loss(rated(0.25), on_loss="hold")), three)
    assert f.independent is True and f.on_loss is OnLoss.HOLD
    f = expected_input_filter(_loss_scenario(_Loss(rated(0.2, [[0], [1], [2]]))), three)
    assert f.independent is True
    f = expected_input_filter(_loss_scenario(_Loss(rated(0.2, [[0, 1, 2]]))), three)
    assert f.independent is False
    burst = BurstLoss.__new__(BurstLoss)
    for loss, why in (
        (None, "loses none"),
        (_Loss(rated(0.3), acknowledged=True), "acknowledged"),
        (_Loss(burst), "in bursts"),
        (_Loss(rated(True)), "random arrival rate"),
        (_Loss(rated(0.2, [[0], [1, 2]])), "one packet for every actuator"),
    ):
        with pytest.raises(ValueError, match=why):
            expected_input_filter(_loss_scenario(loss), three)


def test_the_attack_free_reference_reads_the_true_y_and_the_normal_pf_the_received(monkeypatch):
    """``normal_pf_attack_free`` runs on ``y``, ``normal_pf`` on ``ỹ`` (their descriptions),
    both with the context's PoA detector."""
    from difffilter import fdi
    from difffilter.models.estimators import get

    seen = []
    monkeypatch.setattr(fdi, "particle_filter_poa",
                        lambda model, ys, us, mask=None, detector=None, **kw:
                        seen.append((ys, detector)))  # fmt: skip
    det = object()
    ctx = types.SimpleNamespace(model=None, poa_detector=lambda: det, particle_kwargs=lambda n: {})
    tr = types.SimpleNamespace(y_true=torch.zeros(1, 2, 1), y_recv=torch.ones(1, 2, 1),
                               us=None, mask=None)  # fmt: skip
    get("normal_pf_attack_free").factory(ctx)(tr)
    get("normal_pf").factory(ctx)(tr)
    assert seen[0][0] is tr.y_true and seen[1][0] is tr.y_recv
    assert seen[0][1] is det and seen[1][1] is det


def test_the_modified_pfs_take_a_given_detector_and_the_attack_models_tau(monkeypatch):
    """``modified_pf(ctx, γ̂, detector=d)`` runs with ``d`` (the PoA detector only when none
    is given); ``modified_pf_est`` estimates γ̂ by eq. 4 with ``dy`` and the attack model's
    τ (0.9 for a model without one, and for an attack that is not the paper's, whatever
    field of that name it has)."""
    from difffilter import fdi
    from difffilter.models import generic_estimators as ge
    from difffilter.models.attacks import SensorBias
    from difffilter.models.estimators import get

    seen = {}
    monkeypatch.setattr(fdi, "modified_particle_filter",
                        lambda model, ys, us, mask=None, detector=None, gamma_hat=None, **kw:
                        seen.update(detector=detector, gamma=gamma_hat))  # fmt: skip
    monkeypatch.setattr(fdi, "BiasAttackEstimator",
                        lambda dim, tau, dtype=None: ("est", dim, tau))  # fmt: skip
    poa, mine = object(), object()
    paper = SensorBias(gamma_bar=(1.0, 1.0, 1.0), tau=0.6)
    for attack, tau in ((paper, 0.6), (types.SimpleNamespace(tau=0.6), 0.9),
                        (types.SimpleNamespace(), 0.9)):  # fmt: skip
        ctx = types.SimpleNamespace(
            model=types.SimpleNamespace(dim_y=3, dim_x=5), poa_detector=lambda: poa,
            particle_kwargs=lambda n: {}, dtype=F64,
            scenario=types.SimpleNamespace(attack_model=lambda a=attack: a),
        )  # fmt: skip
        tr = types.SimpleNamespace(y_recv=torch.zeros(1, 2, 3), us=None, mask=None)
        get("modified_pf_est").factory(ctx)(tr)
        assert seen["detector"] is poa and seen["gamma"] == ("est", 3, tau)
    ge.modified_pf(ctx, lambda tr: "g", detector=mine)(tr)
    assert seen["detector"] is mine and seen["gamma"] == "g"


def test_the_deception_density_and_rate_of_a_bias_and_a_replacement_attack():
    """A bias attack: its additive ``γ̄`` at rate ``p_l``; a replacement attack: the box
    ``U(low, high)`` at its ``rate`` (docstring); any other attack is refused."""
    from difffilter.models.generic_estimators import deception_of

    bias = types.SimpleNamespace(gamma_bar=[0.5, -1.0], p_l=0.2)
    p_a, rate = deception_of(bias, F64)
    assert rate == 0.2 and p_a.rho.tolist() == [0.5, -1.0]
    box = types.SimpleNamespace(low=[-1.0, 0.0], high=[2.0, 3.0], rate=0.35)
    p_a, rate = deception_of(box, F64)
    assert rate == 0.35
    assert p_a.density.low.tolist() == [-1.0, 0.0] and p_a.density.high.tolist() == [2.0, 3.0]
    with pytest.raises(ValueError, match="no deception density"):
        deception_of(types.SimpleNamespace(), F64)


def test_the_oracle_of_an_actuator_attack_is_zero_and_a_small_variance_is_noise():
    """An actuator attack changes nothing at the receiver: γ̂ = 0 (docstring), whatever its
    values; a variance of 1e-4 adds noise of that variance (not exact): 4000 draws, the
    sample variance within 10 % of 1e-4 (standard error 2.2 %)."""
    from difffilter.attack import Channel
    from difffilter.models.generic_estimators import oracle_attack

    class Ctx:
        def __init__(self, var):
            self.var = var

        def option(self, key, default):
            return self.var if key == "gamma_hat_noise_var" else default

        def streams(self, name):
            return torch.Generator().manual_seed(5)

    y = torch.ones(1, 3, 2, dtype=F64)
    info = {"attack_values": torch.full((1, 3, 2), 4.0, dtype=F64),
            "attack_channel": Channel.ACTUATOR}  # fmt: skip
    tr = types.SimpleNamespace(info=info, y_recv=y + 2.0, y_true=y)
    assert oracle_attack(Ctx(0.0), tr).abs().max() == 0
    # an entry not received may hold anything, NaN included: γ̂ is still 0 there
    y_lost = (y + 2.0).index_put_(
        (torch.tensor([0]), torch.tensor([1])), torch.tensor(torch.nan, dtype=F64)
    )
    tr = types.SimpleNamespace(info=info, y_recv=y_lost, y_true=y)
    assert oracle_attack(Ctx(0.0), tr).abs().max() == 0
    info = {"attack_values": torch.zeros(1, 2000, 2, dtype=F64), "attack_channel": Channel.SENSOR}
    tr = types.SimpleNamespace(info=info, y_recv=torch.zeros(1, 2000, 2, dtype=F64),
                               y_true=torch.zeros(1, 2000, 2, dtype=F64))  # fmt: skip
    v = float(oracle_attack(Ctx(1e-4), tr).var())
    assert abs(v / 1e-4 - 1) < 0.1, f"var {v}"


def test_the_oracle_of_an_attack_on_a_share_of_the_runs_is_zero_on_the_others():
    """A library attack on a ``share`` of the runs records its values in every run; the
    oracle's γ̂ is those values in the runs it flags at some step (also before and between
    its flags: the paper's γ) and zero in the runs it never flags (a trial: the ramp's
    values had been subtracted there, the oracle modified PF's error 7× the attack-free
    reference's on runs that carried no attack). Truth: the flags written here."""
    from difffilter.attack import Channel
    from difffilter.models.generic_estimators import oracle_attack

    ctx = types.SimpleNamespace(option=lambda key, default: default)
    values = torch.arange(1.0, 3 * 4 * 2 + 1, dtype=F64).reshape(3, 4, 2)
    for flags in (torch.tensor([[False, True, False, True], [False] * 4, [True] + [False] * 3]),
                  torch.zeros(3, 4, 2, dtype=torch.bool).index_put_(
                      (torch.tensor([0, 2]), torch.tensor([3, 0]), torch.tensor([1, 0])),
                      torch.tensor(True))):  # per run, then per entry  # fmt: skip
        info = {"attack_values": values, "attack_channel": Channel.SENSOR, "attack_flags": flags}
        tr = types.SimpleNamespace(info=info, y_recv=None, y_true=None)
        got = oracle_attack(ctx, tr)
        torch.testing.assert_close(got[0], values[0])
        torch.testing.assert_close(got[2], values[2])
        assert got[1].abs().max() == 0


def test_default_estimators_judges_the_needs_with_the_model_given(isolated_registry):
    """A nonlinear plant's suite leaves out the KF ones (docs/your-own-plant.md); the same
    scenario judged with a linear model given keeps the χ² and CUSUM KFs."""
    import difffilter as df
    from difffilter.models.generic_estimators import default_estimators
    from difffilter.models.scenario import CustomScenario
    from difffilter.threats import Ramp

    eye = torch.eye(2, dtype=F64)

    def vdp(dtype):
        step = lambda x: torch.stack([x[..., 0] + 0.05 * x[..., 1], x[..., 1]], -1)  # noqa: E731
        return df.NonlinearGaussianModel(step, lambda x: x, 1e-4 * eye, 1e-2 * eye,
                                         torch.zeros(2, dtype=F64), 1e-2 * eye)  # fmt: skip

    sc = CustomScenario(name="vdp_review141", family="review141", description="d",
                        model_fn=vdp, attack=Ramp(slope=0.01, entries=(0,), onset=5, share=0.5),
                        runs=2, steps=10, dt=0.05, num_particles=10)  # fmt: skip
    names = set(default_estimators(sc))
    assert not names & {"chi_square_kf", "cusum_kf", "chi_square_udp_kf", "cusum_udp_kf",
                        "mixture_likelihood_pf"}  # fmt: skip
    assert {"chi_square_ekf", "cusum_ukf", "normal_pf", "modified_pf"} <= names
    lin = df.LinearGaussianModel(eye, eye, 1e-4 * eye, 1e-2 * eye, torch.zeros(2, dtype=F64),
                                 1e-2 * eye)  # fmt: skip
    assert {"chi_square_kf", "cusum_kf"} <= set(default_estimators(sc, lin))
