"""A checkpoint run on a scenario of its family whose plant is not the one it was trained
on is named (``difffilter.models.plant_match``): a user trial's two-mass-spring network ran
on a pendulum of the same family without a word."""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest
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
    # the plant's fingerprint too, for any kind of scenario (truth: the file's plant, built
    # apart from the run)
    from difffilter.models.plant_match import plant_fingerprint
    from difffilter.models.yaml_scenario import scenario_from_yaml

    assert card["scenario_plant_sha256"] == plant_fingerprint(scenario_from_yaml(plant))
    given = [("run.ckpt", ckpt)]
    assert training_plant_notes(given, ["two_rooms"]) == []  # unchanged: nothing to say
    # calibrate and test on another plant of the family say so, as difffilter-eval does (a
    # trial: both ran unsaid on F = [[.2,.9],[-.9,.2]])
    other = tmp_path / "other.yaml"
    other.write_text(PLANT_YAML.replace("two_rooms", "two_rooms_b").replace(
        "[[0.95, 0.03], [0.03, 0.96]]", "[[0.2, 0.9], [-0.9, 0.2]]"))  # fmt: skip
    capsys.readouterr()
    assert calibrate_main([str(ckpt), "--out", "other.ckpt", "--runs", "4",
                           "--scenario", "other.yaml", "--no-progress"]) == 0  # fmt: skip
    said = "was trained on two_rooms, whose plant is not two_rooms_b's (its transition differs"
    assert f"note: {ckpt} {said}" in capsys.readouterr().err
    assert train_main(["test", "--config", config, "--scenario", "other.yaml",
                       "--ckpt_path", str(ckpt.relative_to(tmp_path)),
                       "--data.init_args.val_runs=4", "--data.init_args.steps=30",
                       "--model.init_args.hidden=4", "--trainer.enable_progress_bar=false"]) == 0  # fmt: skip
    assert f"note: --ckpt_path {ckpt.relative_to(tmp_path)} {said}" in capsys.readouterr().err
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


def _card(tmp_path, spec, **record):
    """An (empty) checkpoint with the JSON card ``difffilter-train`` writes beside it."""
    import json

    ckpt = tmp_path / "net.ckpt"
    ckpt.write_bytes(b"")
    ckpt.with_suffix(".json").write_text(json.dumps({"model_config": {"scenario": spec},
                                                     **record}))  # fmt: skip
    return ckpt


def test_a_copy_of_the_training_file_with_another_plant_and_its_name_is_named(
    isolated_registry, tmp_path
):
    """A trial: ``cp rooms.yaml other/rooms.yaml``, F edited, ``name:`` kept. Registering
    the training file raised the name clash (swallowed) and the equal names skipped the
    comparison: no note. Truth: the two files' F differ, so f(m₀) differs; the unedited
    copy (the same plant under the same name) gives none."""
    (tmp_path / "other").mkdir()
    train, same, other = (tmp_path / "rooms.yaml", tmp_path / "same.yaml",
                          tmp_path / "other" / "rooms.yaml")  # fmt: skip
    train.write_text(PLANT_YAML)
    same.write_text(PLANT_YAML)
    other.write_text(
        PLANT_YAML.replace("[[0.95, 0.03], [0.03, 0.96]]", "[[0.2, 0.9], [-0.9, 0.2]]")
    )
    ckpt = _card(tmp_path, str(train),
                 scenario_file_sha256=hashlib.sha256(PLANT_YAML.encode()).hexdigest())  # fmt: skip
    name = isolated_registry.get(str(same)).name
    assert training_plant_notes([("net.ckpt", ckpt)], [name]) == []
    isolated_registry._REGISTRY.pop(name)
    assert isolated_registry.get(str(other)).name == name == "two_rooms"
    (note,) = training_plant_notes([("net.ckpt", ckpt)], [name])
    assert note.startswith(f"note: --ckpt net.ckpt was trained on {train} (named two_rooms too), "
                           "whose plant is not two_rooms's (its transition differs")  # fmt: skip


MODULE = """
import pytest
import torch
import difffilter as df
from difffilter.models.scenario import CustomScenario
from difffilter.threats import Bias

def plant(dtype):
    e = torch.eye(2, dtype=dtype)
    return df.LinearGaussianModel(torch.tensor(FMAT, dtype=dtype), e, 1e-3 * e, 1e-2 * e,
                                  torch.zeros(2, dtype=dtype), 0.1 * e)

scenario = CustomScenario(name="rooms_mod_a", family="rooms_mod", description="two rooms",
    model_fn=plant, attack=Bias(value=0.3, entries=(0,), onset=10, share=0.5), runs=4,
    steps=30, dt=1.0, num_particles=50)
"""


def test_a_module_plant_edited_after_training_is_named_by_its_fingerprint(tmp_path):
    """A trial edited F in the module of a ``module:object`` training scenario: the card's
    file digest covers YAML files alone, and evaluating said nothing. The card's
    ``scenario_plant_sha256`` (the plant's fingerprint at training) now says it. Truth: the
    fingerprint a separate process reads from the unedited module is the recorded one (no
    note); the edited F is another plant (:func:`plant_difference` of the two)."""
    import os
    import subprocess
    import sys

    path = tmp_path / "fp_rooms_mod.py"
    before, after = "[[0.95, 0.03], [0.03, 0.96]]", "[[0.20, 0.90], [-0.9, 0.20]]"
    env = {**os.environ, "PYTHONDONTWRITEBYTECODE": "1",
           "PYTHONPATH": os.pathsep.join([str(tmp_path), str(ROOT)])}  # fmt: skip
    code = ("import sys; from pathlib import Path;"
            "from difffilter.models.plant_match import plant_fingerprint, training_plant_notes;"
            "from difffilter.models import registry;"
            "print(plant_fingerprint(registry.get('fp_rooms_mod:scenario')));"
            "print(training_plant_notes([('run.ckpt', Path(sys.argv[1]))], ['rooms_mod_a']))")  # fmt: skip

    def run(ckpt):
        out = subprocess.run([sys.executable, "-c", code, str(ckpt)], cwd=tmp_path, env=env,
                             capture_output=True, text=True, check=True).stdout  # fmt: skip
        return out.splitlines()

    path.write_text(MODULE.replace("FMAT", before))
    recorded, _ = run(tmp_path / "none.ckpt")
    ckpt = _card(tmp_path, "fp_rooms_mod:scenario", scenario_plant_sha256=recorded)
    assert run(ckpt) == [recorded, "[]"]  # unedited: the same fingerprint, no note
    path.write_text(MODULE.replace("FMAT", after))
    now, notes = run(ckpt)
    assert now != recorded
    assert notes.startswith("['note: --ckpt run.ckpt was trained on the plant of "
                            "fp_rooms_mod:scenario as it was then")  # fmt: skip
    # a card written before the field: as before, nothing to say of the module's plant
    assert run(_card(tmp_path, "fp_rooms_mod:scenario"))[1] == "[]"
    e = torch.eye(2, dtype=D)
    plants = [df.LinearGaussianModel(torch.tensor(eval(F), dtype=D), e, 1e-3 * e, 1e-2 * e,
                                     torch.zeros(2, dtype=D), 0.1 * e) for F in (before, after)]  # fmt: skip
    assert plant_difference(*plants) == "its transition differs about the prior mean"


def test_a_scenarios_own_checkpoint_of_another_plant_is_named_without_ckpt(
    isolated_registry, tmp_path
):
    """A trial: a scenario whose ``checkpoint`` (loaded without --ckpt) was trained on
    another plant of its family ran with no note; the same file as --ckpt got one. Truth:
    F [[.95,.03],[.03,.96]] against [[.2,.9],[-.9,.2]] (another f at m₀); no note where
    --ckpt gives the default (it is noted as --ckpt) or the plant is the training one."""
    from difffilter.eval.cli import _own_checkpoint_notes
    from difffilter.models.scenario import CustomScenario

    train = tmp_path / "rooms.yaml"
    train.write_text(PLANT_YAML)
    ckpt = _card(tmp_path, str(train))
    e = torch.eye(2, dtype=D)

    def scenario(name, F):
        plant = lambda dtype: df.LinearGaussianModel(  # noqa: E731
            torch.tensor(F, dtype=dtype), e.to(dtype), 1e-3 * e.to(dtype), 1e-2 * e.to(dtype),
            torch.zeros(2, dtype=dtype), 0.1 * e.to(dtype))  # fmt: skip
        return isolated_registry.register(CustomScenario(
            name=name, family="rooms", description="x", model_fn=plant, runs=4, steps=30,
            dt=1.0, num_particles=50, checkpoint=str(ckpt)))  # fmt: skip

    scenario("rooms_own_same", [[0.95, 0.03], [0.03, 0.96]])
    scenario("rooms_own_other", [[0.2, 0.9], [-0.9, 0.2]])
    (note,) = _own_checkpoint_notes(None, ["rooms_own_same", "rooms_own_other"])
    assert note.startswith(f"note: {ckpt} (the scenario's own, no --ckpt) was trained on "
                           "two_rooms, whose plant is not rooms_own_other's")  # fmt: skip
    assert _own_checkpoint_notes(str(ckpt), ["rooms_own_other"]) == []
    # --ckpt naming another estimator only: the scenario's own is the default, noted
    assert len(_own_checkpoint_notes({"gaussian_nn_grad": str(ckpt)}, ["rooms_own_other"])) == 1


def _nonlinear(f, h, m0, P0, dtype=D):
    n = len(m0)
    return df.NonlinearGaussianModel(f, h, 1e-4 * torch.eye(n, dtype=dtype),
                                     1e-2 * torch.eye(1, dtype=dtype),
                                     torch.tensor(m0, dtype=dtype),
                                     torch.tensor(P0, dtype=dtype))  # fmt: skip


def test_a_plant_outside_its_domain_at_a_probe_point_is_itself():
    """A trial: a tank's Torricelli outflow √h at m₀ − σ < 0 gives NaN in both models,
    NaN != NaN, and a plant read as another than itself. Truth: the same model (and the
    same plant built twice) agree; NaN in one alone, or another outflow, do not."""
    import math

    tank = lambda a=0.5: _nonlinear(lambda x: x + 0.1 * (0.5 - a * torch.sqrt(x)),  # noqa: E731
                                    lambda x: x, [1.0], [[1.5]])  # fmt: skip
    one = tank()
    assert plant_difference(one, one) is None and plant_difference(tank(), tank()) is None
    assert math.isnan(float(one.transition(torch.tensor([[1.0 - 1.5**0.5]], dtype=D), None, 0)))
    assert "transition" in plant_difference(tank(), tank(0.6))
    safe = _nonlinear(lambda x: x + 0.1 * (0.5 - 0.5 * torch.sqrt(x.abs())), lambda x: x,
                      [1.0], [[1.5]])  # fmt: skip
    assert "transition" in plant_difference(tank(), safe)


@pytest.mark.parametrize("dtypes", [(torch.float32, torch.float32),
                                    (torch.float64, torch.float32),
                                    (torch.float32, torch.float64)])  # fmt: skip
def test_float32_plants_are_compared_in_their_own_dtype(dtypes):
    """A trial: two identical float32 plants raised "double != float" (float64 probe
    points). Truth: the same plant agrees in any dtypes; F differing by 1e-3 (far above
    float32's rounding) does not."""

    def plant(dtype, f22=0.8):
        t = lambda a: torch.tensor(a, dtype=dtype)  # noqa: E731
        return df.LinearGaussianModel(t([[0.95, 0.04], [-0.02, f22]]), t([[1.0, 0.0]]),
                                      1e-4 * torch.eye(2, dtype=dtype),
                                      1e-3 * torch.eye(1, dtype=dtype), t([3.0, -2.0]),
                                      1e-2 * torch.eye(2, dtype=dtype))  # fmt: skip

    a, b = dtypes
    assert plant_difference(plant(a), plant(b)) is None
    assert "transition" in plant_difference(plant(a), plant(b, 0.801))


def test_plants_that_differ_after_the_first_step_are_other_plants():
    """A trial: two forced oscillators, forcing 0.1 sin(ω k Δt), ω = 1 and 5, agree at k = 0
    (sin 0 = 0) and were read as one plant. Truth: at k = 1 their velocities are
    −0.1 + 0.1 sin(0.1) and −0.1 + 0.1 sin(0.5), 0.04 apart; and h reading k likewise."""
    import math

    def plant(omega, h_omega=0.0):
        def f(x, u, k):
            return torch.stack([x[..., 0] + 0.1 * x[..., 1],
                                x[..., 1] - 0.1 * x[..., 0] + 0.1 * math.sin(omega * k * 0.1)], -1)  # fmt: skip

        def h(x, k):
            return x[..., :1] + h_omega * (k - 1)

        return _nonlinear(f, h, [1.0, 0.0], 1e-2 * torch.eye(2, dtype=D))

    assert plant_difference(plant(1.0), plant(1.0)) is None
    assert "transition" in plant_difference(plant(1.0), plant(5.0))
    assert "measurement" in plant_difference(plant(1.0), plant(1.0, h_omega=0.1))


def test_the_shipped_checkpoints_meet_their_families_plants_but_lfc_sine_1ms():
    """Every shipped checkpoint against every registered scenario of its family, as --ckpt
    and as the scenarios' own (no --ckpt): the one note is lfc_sine_1ms's (1 ms, against
    the 10 ms the LFC network was trained at; module docstring)."""
    from difffilter.eval.cli import _own_checkpoint_notes
    from difffilter.models import registry
    from difffilter.models.plant_match import training_scenario_of

    notes = []
    for ckpt in sorted((ROOT / "checkpoints").glob("*.ckpt")):
        family = registry.get(training_scenario_of(ckpt)).family
        notes += training_plant_notes([(ckpt.name, ckpt)], registry.names(family))
    assert [n.split(" was trained on ")[0] for n in notes] == ["note: --ckpt lfc_nn_grad.ckpt"]
    assert "whose plant is not lfc_sine_1ms's" in notes[0]
    (own,) = _own_checkpoint_notes(None, registry.names())
    assert own.startswith("note: checkpoints/lfc_nn_grad.ckpt (the scenario's own, no --ckpt)")
    assert "whose plant is not lfc_sine_1ms's" in own
