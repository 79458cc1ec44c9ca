"""Findings on which run a figure shows and on sensor groups. A figures trial: the
training's TensorBoard attack figure drew run 0 of the batch, where a scenario attacking a
share of its runs may leave run 0 clean (an injected signal of zeros beside a noisy
estimate); it draws the first attacked run, as the evaluation's figures do, and says which.
A robot-estimators trial: a sensor group's index past the sensors failed in torch's
IndexError at the estimator's init, and -1 was read as the last sensor."""

from __future__ import annotations

from types import SimpleNamespace

import matplotlib
import pytest
import torch

from difffilter.train.task import FilterEstimatorTask

matplotlib.use("Agg")


def test_the_training_attack_figure_shows_the_first_attacked_run():
    drawn = []

    class Task(FilterEstimatorTask):
        @property
        def logger(self):
            return SimpleNamespace(experiment=SimpleNamespace(
                add_figure=lambda tag, fig, global_step=None: drawn.append(fig)))  # fmt: skip

    task = Task("four_tank_bias", filter="ekf", hidden=4)
    B, T, d = 4, 10, 2
    attack = torch.zeros(B, T, d)
    attack[2, 5:, 1] = 0.5  # run 2 alone attacked
    truth = {"attack": attack, "flags": attack.abs().sum(-1) > 0}
    estimate = attack + 0.01
    task._figure("val/attack_estimate", SimpleNamespace(dt=1.0),
                 SimpleNamespace(attack=estimate), truth)  # fmt: skip
    (fig,) = drawn
    axis = fig.axes[0]
    assert axis.get_title() == "run 2"
    curves = {line.get_label(): line.get_ydata() for line in axis.get_lines()}
    assert max(abs(float(v)) for v in curves["attack ch2"]) == 0.5


def test_a_robot_sensor_group_past_the_sensors_is_named():
    from difffilter.models.robot import RobotModel

    model = RobotModel()
    for groups in (((0, 1, 2), (3, 4, 9)), ((0, 1, 2), (3, 4, -1))):
        with pytest.raises(ValueError, match=r"groups: indices must lie in 0 … 5"):
            model.groups_share_noise(groups)
    assert model.groups_share_noise(((0, 1, 2), (3, 4, 5))) is True  # the paper's two groups


def test_robot_sensor_groups_of_numpy_or_tensor_integers_are_taken():
    # a review: the group check above had refused the integer types group() takes
    import numpy as np

    from difffilter.models.robot import RobotModel

    model = RobotModel()
    for groups in (np.array([[0, 1, 2], [3, 4, 5]]), torch.tensor([[0, 1, 2], [3, 4, 5]]),
                   [[np.int64(0), 1, 2], [3, 4, np.int64(5)]]):  # fmt: skip
        assert model.groups_share_noise(groups) is True
    with pytest.raises(ValueError, match="groups: indices must lie in 0 … 5"):
        model.groups_share_noise([[True, 1, 2], [3, 4, 5]])
