"""Findings of a trial of the library's caches: each cached value is served only for the
inputs it was computed from."""

from __future__ import annotations

import copy
import pickle

import pytest
import torch

from difffilter.noise import Gaussian, UniformBox

F64 = torch.float64


def _forge_key(noise, attr: str, *tensors) -> None:
    """Give ``noise``'s cache entry ``attr`` the key its new ``tensors`` have, as when the
    allocator puts a new tensor at a freed one's address with the same version."""
    entry = getattr(noise, attr)
    key = []
    for t in tensors:
        key += [t.data_ptr(), t._version]
    if attr == "_log_len_cache":
        key = (*key, tensors[0].dtype, tensors[0].device)
    else:
        t = tensors[0]
        key = (t.data_ptr(), t._version, t.dtype, t.device, tuple(t.shape))
    setattr(noise, attr, (tuple(key), *entry[1:]))


def test_a_factor_is_served_for_its_own_covariance_not_one_at_its_address():
    """The Cholesky factor was cached under the covariance's address and version alone: a
    new covariance allocated where a freed one had been (``load_state_dict(assign=True)``
    twice, no density between) was served the old factor (a log-density 10 nats off at
    d = 16 on this CPU; on CUDA's caching allocator such reuse is the rule)."""
    d = 4
    g = Gaussian(torch.zeros(d, dtype=F64), torch.eye(d, dtype=F64))
    x = torch.ones(1, d, dtype=F64)
    g.log_prob(x)  # the factor of I, cached
    g.load_state_dict({"loc": g.loc, "_cov": 9.0 * torch.eye(d, dtype=F64)}, assign=True)
    _forge_key(g, "_factor_cache", g._cov)
    expected = Gaussian(torch.zeros(d, dtype=F64), 9.0 * torch.eye(d, dtype=F64)).log_prob(x)
    torch.testing.assert_close(g.log_prob(x), expected, rtol=0, atol=1e-12)

    loc = Gaussian(torch.zeros(d, dtype=F64), torch.eye(d, dtype=F64))
    assert loc._zero_loc()
    loc.load_state_dict({"loc": torch.ones(d, dtype=F64), "_cov": loc._cov}, assign=True)
    _forge_key(loc, "_zero_loc_cache", loc.loc)
    assert not loc._zero_loc()


def test_a_uniforms_lengths_are_served_for_its_own_bounds():
    u = UniformBox(torch.zeros(2, dtype=F64), torch.ones(2, dtype=F64))
    u._log_lengths()
    u.low, u.high = torch.zeros(2, dtype=F64), 4.0 * torch.ones(2, dtype=F64)
    _forge_key(u, "_log_len_cache", u.low, u.high)
    torch.testing.assert_close(u._log_lengths(), torch.log(4.0 * torch.ones(2, dtype=F64)))


@pytest.mark.parametrize("how", ["pickle", "deepcopy"])
def test_a_noise_with_its_caches_filled_copies_and_pickles(how):
    """The caches hold weak references, which do not pickle: a copy leaves them out and
    computes them again, for its own tensors."""
    g = Gaussian(torch.zeros(3, dtype=F64), 2.0 * torch.eye(3, dtype=F64))
    x = torch.randn(5, 3, generator=torch.Generator().manual_seed(0), dtype=F64)
    before = g.log_prob(x)
    g._zero_loc()
    copied = pickle.loads(pickle.dumps(g)) if how == "pickle" else copy.deepcopy(g)
    assert torch.equal(copied.log_prob(x), before)
    with torch.no_grad():
        copied._cov.mul_(4.0)
    assert not torch.equal(copied.log_prob(x), before) and torch.equal(g.log_prob(x), before)


def test_the_plant_fingerprint_sees_partials_bound_methods_slots_and_plain_values():
    """A plant's function given as ``functools.partial(f, mu=…)``, a bound method of an
    object holding ``mu``, or a ``__slots__`` callable had the same fingerprint for every
    ``mu`` (the CUSUM τ of ``mu = 1`` served for ``mu = 3``); complex, Fraction, Decimal and
    set values were hashed by type alone."""
    import decimal
    import fractions
    import functools

    from difffilter.models.calibration_cache import model_fingerprint

    def step(x, mu):
        return x * mu

    class Params:
        def __init__(self, mu):
            self.mu = mu

        def step(self, x):
            return x * self.mu

    class Slotted:
        __slots__ = ("mu",)

        def __init__(self, mu):
            self.mu = mu

        def __call__(self, x):
            return x * self.mu

    pairs = [
        (functools.partial(step, mu=1.0), functools.partial(step, mu=3.0)),
        (Params(1.0).step, Params(3.0).step),
        (Slotted(1.0), Slotted(3.0)),
        (1 + 2j, 1 + 3j), (fractions.Fraction(1, 3), fractions.Fraction(1, 4)),
        (decimal.Decimal("0.1"), decimal.Decimal("0.2")), ({1, 2}, {1, 3}),
    ]  # fmt: skip
    for a, b in pairs:
        assert model_fingerprint(a) != model_fingerprint(b), (a, b)
    assert model_fingerprint(Params(2.0).step) == model_fingerprint(Params(2.0).step)
    assert model_fingerprint({3, 1, 2}) == model_fingerprint({2, 3, 1})


def test_a_method_replaced_on_a_class_is_a_new_class_digest():
    """The digest of a class's code was kept per class for the process: a method replaced
    on it (a notebook, a monkeypatch) kept the old digest and the old calibration."""
    from difffilter.models.calibration_cache import _class_code

    class Plant:
        def observe(self, x):
            return x

    before = _class_code(Plant)
    Plant.observe = lambda self, x: x**3
    after = _class_code(Plant)
    assert after != before and _class_code(Plant) == after


def test_a_filters_key_holds_its_settings():
    """A filter class without a ``repr`` of its own was keyed by its name: a UKF of other
    sigma points was handed the default UKF's CUSUM τ, in memory and on disk."""
    import difffilter as df
    from difffilter.models.estimators import _filter_key

    default = _filter_key(df.UnscentedKalmanFilter())
    others = [_filter_key(df.UnscentedKalmanFilter(df.SigmaPoints(*p)))
              for p in ((0.5, 2.0, 0.0), (1.0, 0.0, 0.0), (1.0, 2.0, 1.0))]  # fmt: skip
    assert len({default, *others}) == 4  # each setting its own key
    assert _filter_key(df.UnscentedKalmanFilter()) == default


PLANT = """
import torch
import difffilter as df
from difffilter.models.scenario import CustomScenario
from difffilter.threats import Bias
NOISE = {noise}
def model(dtype):
    e = torch.eye(2, dtype=dtype)
    F = torch.tensor([[1.0, 0.1], [0.0, 1.0]], dtype=dtype)
    return df.LinearGaussianModel(F, e, 1e-3 * e, NOISE * e, torch.zeros(2, dtype=dtype), 1e-2 * e)
scenario = CustomScenario(name="{name}", family="cache_trial", description="x", model_fn=model,
    attack=Bias(0.3, entries=(0,), onset=10, share=0.5), runs=4, steps=30, dt=0.1,
    num_particles=20, false_alarm_rate=0.05)
"""


def test_a_sweeps_baselines_follow_an_edited_plant(tmp_path, monkeypatch, isolated_registry):
    """The sweep's baselines were keyed by name, runs, rate, seed and a YAML file's digest:
    a plant given as ``module:object`` and edited was judged against the old plant's
    baselines. Now its fingerprint is in the key (and the library's)."""
    import importlib
    import sys

    import train.sweep as sweep

    computed = []

    def metrics(scenario, analytic, runs, far, progress):
        noise = float(scenario.system().measurement_noise.cov[0, 0])
        computed.append(noise)
        return {"cusum_kf": {"state_rmse": noise}}, {}

    # the registry loaded, then a copy for this test (a copy of the unloaded registry had
    # taken the built-in scenarios away with it: the robot's were unknown to later tests)
    registry = isolated_registry
    monkeypatch.setattr(sweep, "_calibrated_metrics", metrics)
    monkeypatch.syspath_prepend(str(tmp_path))
    module = "cache_trial_plant"
    folder = tmp_path / "baselines"
    for noise in (0.01, 0.01, 0.1):
        (tmp_path / f"{module}.py").write_text(PLANT.format(noise=noise, name="cache_trial_lin"))
        sys.modules.pop(module, None)
        registry._REGISTRY.pop("cache_trial_lin", None)
        registry._ORIGINS.pop("cache_trial_lin", None)
        importlib.invalidate_caches()
        table, _ = sweep._baseline(f"{module}:scenario", 4, 0.05, False, folder)
        assert table["cusum_kf"]["state_rmse"] == pytest.approx(noise)
    assert computed == [pytest.approx(0.01), pytest.approx(0.1)]  # the second one read
    sys.modules.pop(module, None)


def test_a_suites_checkpoint_cache_holds_one_network_per_dtype():
    """The network loaded for a study was kept under its checkpoint's path alone: a float64
    study sharing the cache of a float32 one ran the float32 network (and the reverse)."""
    from pathlib import Path
    from types import SimpleNamespace

    from difffilter.models.estimators import SkipEstimator
    from difffilter.models.learned_estimator import _trained_network

    path = Path(__file__).resolve().parents[1] / "checkpoints" / "four_tank_nn_grad.ckpt"
    cache: dict = {}
    dtypes = []
    for dtype in (torch.float32, torch.float64):
        ctx = SimpleNamespace(checkpoint_for=lambda name: path, cache=cache, dtype=dtype,
                              scenario=SimpleNamespace(family="four_tank"),
                              checkpoint_users=[])  # fmt: skip
        try:
            _trained_network(ctx, "pf_nn_grad", ("pf",), "grad")
        except SkipEstimator:  # (a card of other settings: the network is cached all the same)
            pass
        net = [v[0] for k, v in cache.items() if k[0] == "checkpoint"][-1]
        dtypes.append(next(net.parameters()).dtype)
    assert dtypes == [torch.float32, torch.float64]


def test_a_repeat_is_named_so_what_repeats_changes_the_fingerprint():
    """A repeated object had been hashed as a bare mark: ``(a, b, a)`` and ``(a, b, b)``
    read alike, so a plant whose transition reads ``STAGES = [SLOW, FAST, SLOW]``, edited to
    ``[SLOW, FAST, FAST]``, kept its cached CUSUM threshold (a trial)."""
    from difffilter.models.calibration_cache import model_fingerprint

    slow, fast = {"rate": 0.1}, {"rate": 0.9}
    assert model_fingerprint([slow, fast, slow]) != model_fingerprint([slow, fast, fast])
    assert model_fingerprint((slow, slow)) != model_fingerprint((slow,))
    # equal values in other objects, repeated alike, are the same fingerprint (by value)
    again = {"rate": 0.1}
    assert model_fingerprint([slow, fast, slow]) == model_fingerprint([again, {"rate": 0.9}, again])


def test_the_plant_fingerprint_sees_class_constants_builtins_and_deep_networks():
    """Three plants' edits that had kept the old fingerprint, and so the old cached CUSUM
    τ (a cache trial): a constant kept on the class (``G = 9.81`` read as ``self.G``), a
    torch builtin read as a function (``torch.sin`` edited to ``torch.cos``: hashed by their
    type alone), and a network nested deeper than the fingerprint's walk (blocks of blocks of
    layers: its weights had never been hashed)."""
    from difffilter.models.calibration_cache import model_fingerprint

    def plant_class(g):
        class Pendulum:
            G = g

            def transition(self, x):
                return x - self.G * x

        return Pendulum

    assert model_fingerprint(plant_class(9.81)()) != model_fingerprint(plant_class(3.0)())
    assert model_fingerprint(plant_class(9.81)()) == model_fingerprint(plant_class(9.81)())
    assert model_fingerprint((torch.sin,)) != model_fingerprint((torch.cos,))
    assert model_fingerprint((torch.sin,)) == model_fingerprint((torch.sin,))
    assert model_fingerprint((torch.ones(2).add,)) != model_fingerprint((torch.zeros(2).add,))

    def deep(seed):
        torch.manual_seed(seed)
        net = torch.nn.Linear(2, 2)
        for _ in range(12):  # each Sequential two levels deeper (the module, its _modules)
            net = torch.nn.Sequential(net)
        return net

    assert model_fingerprint((deep(0),)) != model_fingerprint((deep(1),))
    assert model_fingerprint((deep(0),)) == model_fingerprint((deep(0),))


@pytest.mark.parametrize("nesting", range(9))
def test_a_networks_weights_are_hashed_at_every_nesting(nesting):
    """At one nesting (a Linear met at walk depth 15-16) the deep walk's cut-off read the
    module's ``_parameters`` dict, whose values are tensors, and dropped them: a plant's
    network of blocks kept its fingerprint, and its cached CUSUM τ, after its weights
    changed (a trial of the cache)."""
    from difffilter.models.calibration_cache import model_fingerprint

    def net(scale):
        torch.manual_seed(0)
        layer = torch.nn.Linear(2, 2)
        with torch.no_grad():
            layer.weight.mul_(scale)
        for _ in range(nesting):
            layer = torch.nn.Sequential(layer)
        return torch.nn.ModuleList([torch.nn.Sequential(layer)])

    assert model_fingerprint((net(1.0),)) != model_fingerprint((net(10.0),))
    assert model_fingerprint((net(1.0),)) == model_fingerprint((net(1.0),))


def test_a_class_constant_edited_in_place_changes_the_fingerprint():
    """The class digest was kept while the class's members were the same objects: a tensor
    constant edited in place (``Plant.A[0, 0] = 0.5``) kept the fingerprint, and the suite's
    in-process CUSUM τ; now that of the class built with the edited value."""
    from difffilter.models.calibration_cache import model_fingerprint

    def plant_class(a):
        class Plant:
            A = torch.tensor([[a, 0.0], [0.0, 1.0]])

            def transition(self, x):
                return x @ self.A.T

        return Plant

    edited = plant_class(1.0)
    before = model_fingerprint(edited())
    edited.A[0, 0] = 0.5
    assert model_fingerprint(edited()) != before
    assert model_fingerprint(edited()) == model_fingerprint(plant_class(0.5)())


def test_a_cusum_cache_file_out_of_the_detectors_range_is_computed_again():
    """A cached CUSUM calibration with a bias of 0 or a negative threshold is not a
    calibration (the evaluation had failed in the detector's words, naming no file)."""
    from difffilter.models.estimators import _is_cusum_calibration

    assert _is_cusum_calibration({"bias": 6.0, "threshold": 3.4})
    assert _is_cusum_calibration({"bias": 6.0, "threshold": 0.0})
    for bad in ({"bias": 0.0, "threshold": 3.4}, {"bias": 6.0, "threshold": -1.0},
                {"bias": -2.0, "threshold": 1.0}):  # fmt: skip
        assert not _is_cusum_calibration(bad)


def test_the_plant_fingerprint_reads_tensors_numpy_cannot_hold():
    """A plant holding a bfloat16 tensor had crashed the fingerprint (numpy has no
    bfloat16), and with it the evaluation; its values are hashed as its bytes."""
    from difffilter.models.calibration_cache import model_fingerprint

    half = torch.tensor([1.0, 2.0], dtype=torch.bfloat16)
    assert model_fingerprint((half,)) == model_fingerprint((half.clone(),))
    assert model_fingerprint((half,)) != model_fingerprint((half + 1,))
    assert model_fingerprint((half,)) != model_fingerprint((half.float(),))  # (the dtype)
    assert model_fingerprint((torch.tensor(0.5, dtype=torch.bfloat16),)) != model_fingerprint(
        (torch.tensor(0.25, dtype=torch.bfloat16),)
    )


@pytest.mark.parametrize("what", ["train", "versions"])
def test_the_library_fingerprint_covers_the_sweep_and_the_numeric_libraries(monkeypatch, what):
    """The sweep's cached baselines are computed by ``train/sweep.py``: an edit there had
    kept the baselines of before; and another torch or numpy can round otherwise."""
    from pathlib import Path

    import difffilter.train.sweep as sweep
    from difffilter.models import calibration_cache as cc

    monkeypatch.setattr(cc, "_LIBRARY_FINGERPRINT", None)
    before = cc.library_fingerprint()
    if what == "train":
        edited, read = Path(sweep.__file__).resolve(), Path.read_bytes

        def read_edited(path):
            data = read(path)
            return data + b"\n# edited\n" if Path(path).resolve() == edited else data

        monkeypatch.setattr(Path, "read_bytes", read_edited)
    else:
        monkeypatch.setattr(torch, "__version__", torch.__version__ + ".other")
    monkeypatch.setattr(cc, "_LIBRARY_FINGERPRINT", None)
    assert cc.library_fingerprint() != before
