"""A noise trial's findings: a ``GaussianMixture``'s weights and a ``UniformBox``'s bounds
were checked when built only. Weights fitted as an ``nn.Parameter`` (or written in place)
to a sum of 5.51 gave a density integrating to 5.51 (``log_prob`` and ``mean`` read them
raw, ``sample`` normalised them); bounds written to ``high = low`` gave +inf densities, and
``high < low`` −inf, NaN under a mask. Both are checked again where written since."""

from __future__ import annotations

import pytest
import torch

from difffilter.noise import GaussianMixture, UniformBox

F64 = torch.float64


def _mixture(weights):
    locs = torch.tensor([[-1.0], [1.0]], dtype=F64)
    covs = torch.tensor([[[0.5]], [[0.3]]], dtype=F64)
    return GaussianMixture(weights, locs, covs)


@pytest.mark.parametrize("member", ["log_prob", "mean", "cov", "sample"])
def test_mixture_weights_written_off_the_simplex_are_refused_by_every_member(member):
    mix = _mixture(torch.nn.Parameter(torch.tensor([0.4, 0.6], dtype=F64)))
    with torch.no_grad():
        mix.weights.mul_(3.0)  # an optimiser's step with no softmax: sum 3
    use = {"log_prob": lambda: mix.log_prob(torch.zeros(1, dtype=F64)),
           "mean": lambda: mix.mean, "cov": lambda: mix.cov,
           "sample": lambda: mix.sample((4,), torch.Generator().manual_seed(0))}[member]  # fmt: skip
    with pytest.raises(ValueError, match="weights must be finite, non-negative and sum to 1"):
        use()


def test_mixture_weights_written_on_the_simplex_are_followed():
    mix = _mixture(torch.tensor([0.4, 0.6], dtype=F64))
    mix.weights.copy_(torch.tensor([0.9, 0.1], dtype=F64))
    fresh = _mixture(torch.tensor([0.9, 0.1], dtype=F64))
    v = torch.linspace(-2, 2, 5, dtype=F64)[:, None]
    torch.testing.assert_close(mix.log_prob(v), fresh.log_prob(v), rtol=0, atol=0)
    torch.testing.assert_close(mix.mean, fresh.mean, rtol=0, atol=0)
    # the documented way to learn them: softmax of a parameter, the mixture built at each use
    logits = torch.zeros(2, dtype=F64, requires_grad=True)
    _mixture(torch.softmax(logits, 0)).log_prob(v).sum().backward()
    assert logits.grad is not None and bool(torch.isfinite(logits.grad).all())


@pytest.mark.parametrize("high", [0.0, -1.0])
def test_box_bounds_written_out_of_order_are_refused(high):
    box = UniformBox(torch.zeros(2, dtype=F64), torch.ones(2, dtype=F64))
    inside = torch.full((3, 2), 0.5, dtype=F64)
    assert bool((box.log_prob(inside) == 0).all())  # its log-lengths cached
    box.load_state_dict({"low": torch.zeros(2, dtype=F64),
                         "high": torch.tensor([1.0, high], dtype=F64)})  # fmt: skip
    with pytest.raises(ValueError, match="high must be strictly greater than low"):
        box.log_prob(inside)
    with pytest.raises(ValueError, match="high must be strictly greater than low"):
        box.sample((2,), torch.Generator().manual_seed(0))


def test_box_bounds_written_in_order_are_followed():
    box = UniformBox(torch.zeros(2, dtype=F64), torch.ones(2, dtype=F64))
    box.high.mul_(2.0)
    torch.testing.assert_close(box.log_prob(torch.full((1, 2), 1.5, dtype=F64)),
                               torch.tensor([-2 * torch.log(torch.tensor(2.0, dtype=F64))],
                                            dtype=F64))  # fmt: skip


def test_mixture_weights_of_softmax_run_under_torch_func():
    # a review: the once-per-write check read data_ptr(), which a torch.func wrapper lacks
    v = torch.linspace(-2, 2, 5, dtype=F64)[:, None]

    def total(logits):
        return _mixture(torch.softmax(logits, 0)).log_prob(v).sum()

    logits = torch.tensor([0.3, -0.2], dtype=F64)
    grad = torch.func.grad(total)(logits)
    leaf = logits.clone().requires_grad_(True)
    total(leaf).backward()
    torch.testing.assert_close(grad, leaf.grad, rtol=1e-12, atol=0)


def test_every_box_member_refuses_bounds_written_out_of_order():
    box = UniformBox(torch.zeros(2, dtype=F64), torch.ones(2, dtype=F64))
    box.high.fill_(-1.0)
    for member in ("cov", "mean", "log_volume"):
        with pytest.raises(ValueError, match="high must be strictly greater than low"):
            getattr(box, member)


def test_glint_cov_refuses_weights_written_off_the_simplex():
    from difffilter.models.tracking import GlintNoise

    noise = GlintNoise(torch.tensor([0.8, 0.2], dtype=F64),
                       torch.tensor([[4.0, 1e-3], [25.0, 1e-3]], dtype=F64), sensors=2)  # fmt: skip
    with torch.no_grad():
        noise.weights.mul_(3.0)
    with pytest.raises(ValueError, match="weights must be finite, non-negative and sum to 1"):
        _ = noise.cov


def _linear():
    import difffilter as df

    eye = torch.eye(2, dtype=F64)
    return df.LinearGaussianModel(torch.tensor([[1.0, 0.1], [0.0, 1.0]], dtype=F64), eye,
                                  0.1 * eye, 0.5 * eye, torch.zeros(2, dtype=F64), eye)  # fmt: skip


@pytest.mark.parametrize("consumer", ["kalman_filter", "particle_filter", "simulate", "pcrb"])
def test_a_covariance_written_asymmetric_or_a_noise_of_other_dimension_is_named(consumer):
    # a covariance-write trial: an asymmetric R written in place was read as its average by
    # the Kalman filters and as one triangle by the particle filter (0.44 apart); a 1-dim
    # noise assigned to two states ran as a broadcast, singular Q
    import difffilter as df
    from difffilter.noise import Gaussian

    def run(model):
        gen = torch.Generator().manual_seed(0)
        xs = torch.zeros(1, 4, 2, dtype=F64)
        ys = torch.zeros(1, 4, 2, dtype=F64)
        return {"kalman_filter": lambda: df.kalman_filter(model, ys),
                "particle_filter": lambda: df.particle_filter(model, ys, num_particles=50,
                                                              generator=gen),
                "simulate": lambda: model.simulate(4, (1,), generator=gen),
                "pcrb": lambda: df.posterior_crb(model, xs, torch.zeros(1, 2, dtype=F64))}[
            consumer]()  # fmt: skip

    model = _linear()
    with torch.no_grad():
        model.measurement_noise.cov[0, 1] += 0.3
    with pytest.raises(ValueError, match="must be symmetric"):
        run(model)
    model = _linear()
    model.process_noise = Gaussian(torch.zeros(1, dtype=F64), 0.1 * torch.eye(1, dtype=F64))
    with pytest.raises(ValueError, match="model.process_noise has dimension 1 and the model 2"):
        run(model)
