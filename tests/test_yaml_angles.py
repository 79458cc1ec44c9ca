"""YAML ``angles:``: the measurement entries of a nonlinear plant that are angles, their
residuals wrapped to (−π, π] (a robotics trial's bearings near ±π without it: a χ²
threshold of 22,958 and no detection)."""

from __future__ import annotations

import math
import textwrap

import pytest
import torch

from difffilter.models.yaml_scenario import scenario_from_dict

BEARING = textwrap.dedent("""
    import torch

    def step(x):
        return x

    def observe(x):  # range and bearing of the point x from the origin
        return torch.stack([x.norm(dim=-1), torch.atan2(x[..., 1], x[..., 0])], -1)
""")


def _plant(tmp_path, monkeypatch, **plant):
    (tmp_path / "user_bearing.py").write_text(BEARING)
    monkeypatch.syspath_prepend(str(tmp_path))
    spec = {"transition": "user_bearing:step", "observe": "user_bearing:observe", "Q": 1e-4,
            "R": [1e-2, 1e-4], "m0": [-1.0, 0.0], "P0": 1e-2, **plant}  # fmt: skip
    return scenario_from_dict({"name": "bearing", "runs": 4, "steps": 20, "plant": spec},
                              "bearing.yaml")  # fmt: skip


def test_the_angle_entries_are_wrapped_and_the_others_kept(tmp_path, monkeypatch):
    model = _plant(tmp_path, monkeypatch, angles=[1]).system(torch.float64)
    y = torch.tensor([[1.0, math.pi - 0.01], [2.0, 0.3]], dtype=torch.float64)
    y_hat = torch.tensor([[1.5, -math.pi + 0.01], [1.0, -0.2]], dtype=torch.float64)
    residual = model.measurement_residual(y, y_hat)
    expected = torch.tensor([[-0.5, -0.02], [1.0, 0.5]], dtype=torch.float64)
    torch.testing.assert_close(residual, expected, rtol=0, atol=1e-12)
    plain = _plant(tmp_path, monkeypatch).system(torch.float64)
    assert float(plain.measurement_residual(y, y_hat)[0, 1]) == pytest.approx(2 * math.pi - 0.02)


def test_an_ekf_through_the_cut_stays_consistent(tmp_path, monkeypatch):
    """The point sits at bearing π: half its measurements read near −π. With angles the EKF's
    NIS stays about its 2 degrees of freedom; with plain residuals it is in the thousands."""
    import difffilter as df

    nis = {}
    for name, plant in (("angles", {"angles": [1]}), ("plain", {})):
        model = _plant(tmp_path, monkeypatch, **plant).system(torch.float64)
        _, ys, _ = model.simulate(20, (50,), generator=torch.Generator().manual_seed(0))
        out = df.extended_kalman_filter(model, ys)
        nu = out.innovations.unsqueeze(-1)
        nis[name] = float((nu.mT @ torch.linalg.solve(out.innovation_covs, nu)).mean())
    assert nis["angles"] < 3.0 and nis["plain"] > 100.0


@pytest.mark.parametrize("plant, why", [
    ({"angles": [2]}, r"angles must be a list of distinct measurement entries in \[0, 2\)"),
    ({"angles": [1, 1]}, "distinct"),
    ({"angles": 1}, "must be a list"),
])  # fmt: skip
def test_bad_angles_are_named(tmp_path, monkeypatch, plant, why):
    with pytest.raises(ValueError, match="bearing.yaml: plant.angles"):
        _plant(tmp_path, monkeypatch, **plant).system(torch.float64)
    with pytest.raises(ValueError, match=why):
        _plant(tmp_path, monkeypatch, **plant).system(torch.float64)


def test_a_linear_plant_takes_no_angles():
    spec = {"F": [[1.0]], "H": [[1.0]], "Q": 1e-4, "R": 1e-2, "angles": [0]}
    with pytest.raises(ValueError, match="angles wraps the residuals of a nonlinear plant"):
        scenario_from_dict({"name": "lin", "plant": spec}, "lin.yaml")


def test_an_angle_of_exactly_pi_stays_pi_and_the_model_pickles(tmp_path, monkeypatch):
    """A review: the wrap gave [−π, π), −π for a difference of +π, where the docs and the
    tracking model's wrap_angle give (−π, π]."""
    import pickle

    model = _plant(tmp_path, monkeypatch, angles=[1]).system(torch.float64)
    y = torch.tensor([[0.0, math.pi], [0.0, -math.pi], [0.0, 3 * math.pi]], dtype=torch.float64)
    wrapped = model.measurement_residual(y, torch.zeros_like(y))[:, 1]
    torch.testing.assert_close(wrapped, torch.full((3,), math.pi, dtype=torch.float64),
                               rtol=0, atol=1e-12)  # fmt: skip
    again = pickle.loads(pickle.dumps(model))
    assert again.angles == (1,)
