"""An estimator of one's own, from a module outside the package, run beside a built-in
scenario's: ``difffilter-eval <scenario> --import <module> --add-estimators <name>``
(nothing imported the module before, so the name was unknown)."""

from __future__ import annotations

import sys
import textwrap

import pytest

from difffilter.eval.cli import main as eval_main
from difffilter.models import estimators as registry

MODULE = textwrap.dedent("""
    from difffilter.models.estimators import register


    @register("my_plugin_kf", "a plug-in author's estimator (a test)")
    def my_plugin_kf(ctx):
        raise AssertionError("not run by the test")
""")


def test_import_registers_a_plugins_estimators(tmp_path, monkeypatch, capsys):
    (tmp_path / "my_plugin_estimators.py").write_text(MODULE)
    monkeypatch.chdir(tmp_path)  # importable from the working folder, as a user runs it
    monkeypatch.setattr(sys, "path", list(sys.path))  # (the working folder is appended)
    try:
        assert eval_main(["--import", "my_plugin_estimators", "--list"]) == 0
        assert "my_plugin_kf" in registry.ESTIMATORS
    finally:  # (the registry is the process's: the families loaded meanwhile stay)
        registry.ESTIMATORS.pop("my_plugin_kf", None)
        sys.modules.pop("my_plugin_estimators", None)


def test_a_module_that_does_not_import_is_named(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit):
        eval_main(["--import", "no_such_plugin_module", "--list"])
    assert "--import no_such_plugin_module: cannot import" in capsys.readouterr().err


def test_an_output_that_does_not_fit_the_study_is_named_and_a_diverged_one_warned():
    """A one-component state estimate on a four-state plant was scored against all four
    states by broadcasting (state RMSE 7.76, silently); a NaN estimate's RMSEs turned
    null, read as "does not apply"."""
    import torch

    from difffilter.estimator import EstimatorOutput
    from difffilter.eval.suite import _check_fits
    from difffilter.loop import Trajectories

    x = torch.zeros(3, 5, 4, dtype=torch.float64)
    traj = Trajectories(x, x, x, None, None, x, torch.zeros(3, 5, dtype=torch.bool), {})
    with pytest.raises(ValueError, match=r"'mine' on plant: its means have shape \(3, 5, 1\)"):
        _check_fits("mine", "plant", EstimatorOutput(x[..., :1]), traj)
    with pytest.raises(ValueError, match=r"its means have shape \(3, 4, 4\)"):
        _check_fits("mine", "plant", EstimatorOutput(x[:, 1:]), traj)
    diverged = x.clone()
    diverged[0, 2] = float("nan")
    with pytest.warns(UserWarning, match="NaN or infinite at 1 of 15 run-steps"):
        _check_fits("mine", "plant", EstimatorOutput(diverged), traj)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # fits and finite: no error, no warning
        _check_fits("mine", "plant", EstimatorOutput(x), traj)


def test_a_plugin_whose_own_import_fails_names_the_missing_module(tmp_path, monkeypatch, capsys):
    """A re-check: found in the working folder, a module importing a missing package was
    reported as missing itself."""
    (tmp_path / "my_broken_plugin.py").write_text("import not_installed_pkg_xyz\n")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "path", list(sys.path))
    with pytest.raises(SystemExit):
        eval_main(["--import", "my_broken_plugin", "--list"])
    assert "not_installed_pkg_xyz" in capsys.readouterr().err
    sys.modules.pop("my_broken_plugin", None)


def test_a_package_found_in_the_working_folder_names_its_missing_module(
    tmp_path, monkeypatch, capsys
):
    """A trial: ``--import mine.none_such`` with a folder ``mine`` in the working folder
    said "No module named 'mine'" (the first attempt's error, from before the working
    folder was tried); it names ``mine.none_such``, the module that is missing."""
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "__init__.py").write_text("")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "path", list(sys.path))
    monkeypatch.setattr(sys, "modules", dict(sys.modules))
    with pytest.raises(SystemExit):
        eval_main(["--import", "mine.none_such", "--list"])
    err = capsys.readouterr().err
    assert "No module named 'mine.none_such'" in err, err


def test_a_nan_attack_estimate_is_warned_too():
    import torch

    from difffilter.estimator import EstimatorOutput
    from difffilter.eval.suite import _check_fits
    from difffilter.loop import Trajectories

    x = torch.zeros(2, 3, 1, dtype=torch.float64)
    traj = Trajectories(x, x, x, None, None, x, torch.zeros(2, 3, dtype=torch.bool), {})
    attack = x.clone()
    attack[1, 1] = float("nan")
    with pytest.warns(UserWarning, match="its attack estimate is NaN or infinite at 1 of 6"):
        _check_fits("mine", "plant", EstimatorOutput(x, attack=attack), traj)


def test_a_nan_attack_estimate_on_attack_free_steps_only_is_not_said_to_null_its_rmse():
    """The attack RMSE reads the attacked steps only: a NaN on an attack-free step had been
    warned as "so its attack RMSE is null" while metrics.json gave the number (a trial)."""
    import torch

    from difffilter.estimator import EstimatorOutput
    from difffilter.eval.scoring import score
    from difffilter.eval.suite import _check_fits
    from difffilter.loop import Trajectories

    x = torch.zeros(2, 3, 1, dtype=torch.float64)
    flags = torch.tensor([[False, True, True], [False, False, True]])
    traj = Trajectories(x, x, x, None, None, x, flags, {})
    attack = torch.full_like(x, 0.5)
    attack[1, 1] = float("nan")  # attack-free
    output = EstimatorOutput(x, attack=attack)
    with pytest.warns(UserWarning, match="at 1 of 6 run-steps, all attack-free") as seen:
        _check_fits("mine", "plant", output, traj)
    assert not any("is null" in str(w.message) for w in seen)
    assert score(output, traj, dt=1.0, wall_s=0.0)["attack_rmse"] == pytest.approx(0.5)
    attack[0, 1] = float("nan")  # attacked: now the RMSE is NaN, null in metrics.json
    with pytest.warns(UserWarning, match="at 2 of 6 run-steps, so its attack RMSE is null"):
        _check_fits("mine", "plant", output, traj)
