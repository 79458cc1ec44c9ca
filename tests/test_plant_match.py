"""A checkpoint run on a scenario of its family whose plant is not the one it was trained
on is named (``difffilter.models.plant_match``): a user trial's two-mass-spring network ran
on a pendulum of the same family without a word."""

from __future__ import annotations

import hashlib
from pathlib import Path

import torch

import difffilter as df
from difffilter.models.plant_match import plant_difference, training_plant_notes
from difffilter.noise import Gaussian

ROOT = Path(__file__).resolve().parents[1]
D = torch.float64


def _linear(F, H=((1.0, 0.0),), B=None):
    t = lambda a: None if a is None else torch.tensor(a, dtype=D)  # noqa: E731
    return df.LinearGaussianModel(t(F), t(H), 0.01 * torch.eye(2, dtype=D),
                                  0.1 * torch.eye(len(H), dtype=D), torch.ones(2, dtype=D),
                                  torch.eye(2, dtype=D), B=t(B))  # fmt: skip


def test_plants_are_compared_by_dimensions_and_by_f_and_h_at_the_prior():
    F = ((1.0, 0.1), (0.0, 0.9))
    assert plant_difference(_linear(F), _linear(F)) is None
    # the noise may differ (a study of transfer to more noise, not another plant)
    noisy = _linear(F)
    noisy.measurement_noise = Gaussian(torch.zeros(1, dtype=D), torch.eye(1, dtype=D))
    assert plant_difference(_linear(F), noisy) is None
    assert "transition" in plant_difference(_linear(F), _linear(((1.0, 0.1), (0.0, 0.8))))
    assert "measurement" in plant_difference(_linear(F), _linear(F, H=((0.0, 1.0),)))
    assert "(2, 1, 0) against (2, 2, 0)" in plant_difference(
        _linear(F), _linear(F, H=((1.0, 0.0), (0.0, 1.0)))
    )
    assert "(2, 1, 1)" in plant_difference(_linear(F, B=((0.0,), (1.0,))), _linear(F))


def test_the_shipped_lfc_network_is_named_only_on_the_plant_at_another_sampling_period():
    """The shipped LFC checkpoint was trained on lfc_random_attacks (10 ms): the headline LFC
    scenarios share its plant, lfc_sine_1ms is discretised at 1 ms."""
    ckpt = ROOT / "checkpoints" / "lfc_nn_grad.ckpt"
    notes = training_plant_notes([("lfc_nn_grad.ckpt", ckpt)],
                                 ["lfc_step", "lfc_sawtooth", "lfc_sine_1ms"])  # fmt: skip
    assert len(notes) == 1 and "trained on lfc_random_attacks" in notes[0]
    assert "is not lfc_sine_1ms's (its transition differs" in notes[0]
    # a checkpoint whose training scenario cannot be read: no claim
    assert training_plant_notes([("x", ROOT / "no_such.ckpt")], ["lfc_step"]) == []


PLANT_YAML = """\
name: two_rooms
family: rooms
description: two rooms, a bias on the first sensor
dt: 1.0
runs: 4
steps: 30
num_particles: 50
false_alarm_rate: 0.01
plant:
  F: [[0.95, 0.03], [0.03, 0.96]]
  H: [[1.0, 0.0], [0.0, 1.0]]
  Q: 1.0e-3
  R: 1.0e-2
  P0: 0.1
attack: {kind: bias, value: 0.3, entries: [0], onset: 10, share: 0.5}
"""


def test_a_scenario_file_edited_after_training_is_named(isolated_registry, tmp_path,
                                                        monkeypatch, capsys):  # fmt: skip
    """The card records the sha256 of the YAML file training read; evaluating or calibrating
    after the file was edited says so (a trial changed F after export: the plant comparison
    built the "training plant" from the edited file, and both ran without a word)."""
    import hashlib
    import json

    from difffilter.train.calibrate import main as calibrate_main
    from difffilter.train.cli import main as train_main

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("sys.argv", ["difffilter-train"])
    plant = tmp_path / "rooms.yaml"
    plant.write_text(PLANT_YAML)
    config = str(ROOT / "train" / "configs" / "generic.yaml")
    assert train_main(["fit", "--config", config, "--scenario", "rooms.yaml",
                       "--trainer.max_epochs=1", "--data.init_args.batches_per_epoch=1",
                       "--data.init_args.batch_size=2", "--data.init_args.val_runs=4",
                       "--data.init_args.steps=30", "--model.init_args.hidden=4",
                       "--trainer.enable_progress_bar=false"]) == 0  # fmt: skip
    (ckpt,) = (tmp_path / "lightning_logs").rglob("*/version_0/*_nn_grad.ckpt")
    card = json.loads(ckpt.with_suffix(".json").read_text())
    assert card["scenario_file_sha256"] == hashlib.sha256(PLANT_YAML.encode()).hexdigest()
    given = [("run.ckpt", ckpt)]
    assert training_plant_notes(given, ["two_rooms"]) == []  # unchanged: nothing to say
    plant.write_text(PLANT_YAML.replace("[0.95, 0.03]", "[0.90, 0.03]"))
    (note,) = training_plant_notes(given, ["two_rooms"])
    assert note.startswith("note: --ckpt run.ckpt was trained on the scenario file rooms.yaml")
    assert "or the Python code it names, differs now" in note
    capsys.readouterr()
    # calibrate is a command of its own, a new process: the file as it is now is read anew
    # (in this process the registry refuses the edited plant under its taken name)
    isolated_registry._REGISTRY.pop("two_rooms")
    isolated_registry._ORIGINS.pop("two_rooms")
    assert calibrate_main([str(ckpt), "--out", "cal.ckpt", "--runs", "4"]) == 0
    assert "was trained on the scenario file rooms.yaml as it was then" in capsys.readouterr().err


def test_the_scenario_file_digest_covers_the_python_code_the_file_names(tmp_path):
    """A training trial edited the gravity in the module its YAML pendulum names
    (``transition: myplants:pend_step``): calibrate and the evaluation said nothing, and
    the sweep re-scored the old network against the old plant's baselines. The digest of a
    file that names Python objects covers their code (as the calibration cache's
    fingerprint reads it); a file that names none keeps the digest of its bytes. Truth:
    the same file beside two modules that differ in one constant, each digested in a
    process of its own (a module is imported once per process)."""
    import subprocess
    import sys

    from difffilter.models.yaml_scenario import scenario_file_digest

    text = (
        "name: pend\nplant:\n  transition: tplant:step\n  observe: tplant:obs\n"
        "  Q: 1.0e-4\n  R: 1.0e-2\n  m0: [0.5, 0.0]\n"
    )
    module = ("G = {g}\n\ndef step(x):\n    return x + 0.01 * G\n\n"
              "def obs(x):\n    return x[..., :1]\n")  # fmt: skip
    digests = {}
    for name, g in (("a", "9.81"), ("b", "9.81"), ("c", "30.0")):
        (tmp_path / name).mkdir()
        (tmp_path / name / "pend.yaml").write_text(text)
        (tmp_path / name / "tplant.py").write_text(module.format(g=g))
        code = ("from difffilter.models.yaml_scenario import scenario_file_digest;"
                "print(scenario_file_digest('pend.yaml'))")  # fmt: skip
        digests[name] = subprocess.run([sys.executable, "-c", code], cwd=tmp_path / name,
                                       capture_output=True, text=True, check=True).stdout  # fmt: skip
    assert digests["a"] == digests["b"] and len(digests["a"].strip()) == 64
    assert digests["a"] != digests["c"]
    plain = tmp_path / "plain.yaml"
    plain.write_text("name: lin\nplant:\n  F: [[0.9]]\n  H: [[1.0]]\n  Q: 0.1\n  R: 0.1\n")
    assert scenario_file_digest(plain) == hashlib.sha256(plain.read_bytes()).hexdigest()


def test_a_digest_recorded_before_it_covered_the_code_still_matches(tmp_path):
    """A review: a run recorded before the digest covered the Python code a file names
    held the sha256 of the file's bytes, and every such run read as "changed" (a sweep
    refused to resume). The bytes' digest still matches; another does not; text with a
    colon outside the fields that name code is not imported to digest it."""
    from difffilter.models.yaml_scenario import (
        _python_objects,
        scenario_file_digest,
        scenario_file_matches,
    )

    (tmp_path / "tplant2.py").write_text(
        "def step(x):\n    return x\n\ndef obs(x):\n    return x\n"
    )
    path = tmp_path / "pend.yaml"
    path.write_text("name: pend\ndescription: 'note:nothing'\nplant:\n  transition: tplant2:step\n"
                    "  observe: tplant2:obs\n  Q: 1.0e-4\n  R: 1.0e-2\n  m0: [0.5]\n")  # fmt: skip
    import sys

    sys.path.insert(0, str(tmp_path))
    try:
        now = scenario_file_digest(path)
        legacy = hashlib.sha256(path.read_bytes()).hexdigest()
        assert now != legacy
        assert scenario_file_matches(now, path) and scenario_file_matches(legacy, path)
        assert not scenario_file_matches("0" * 64, path)
        assert _python_objects(path.read_bytes()) == ["tplant2:obs", "tplant2:step"]
    finally:
        sys.path.remove(str(tmp_path))
