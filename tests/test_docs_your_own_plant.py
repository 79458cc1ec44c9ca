"""docs/your-own-plant.md runs as written: its Python blocks in order in one namespace
(those headed ``# my_plants.py`` or ``# my_attacks.py`` written to that module), its YAML blocks headed
``# file: NAME`` written to NAME, and its ``difffilter-eval``/``difffilter-train`` commands
run through the command lines' ``main`` (trainings shortened to seconds)."""

from __future__ import annotations

import json
import re
import shlex
import sys
import types
from pathlib import Path

import pytest

from difffilter.eval.cli import main as eval_main
from difffilter.train.cli import main as train_main

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "your-own-plant.md"
# a training of seconds that still exports its checkpoint (fast_dev_run exports nothing)
SHORT_TRAINING = ["--trainer.max_epochs=1", "--data.init_args.batches_per_epoch=2",
                  "--data.init_args.batch_size=2", "--data.init_args.val_runs=4",
                  "--data.init_args.calibration_runs=4"]  # fmt: skip


def _blocks(text: str) -> list[tuple[str, str]]:
    return re.findall(r"```(python|yaml|sh)\n(.*?)```", text, flags=re.S)


def _commands(block: str) -> list[list[str]]:
    joined = re.sub(r"\\\n\s*", " ", block)
    return [shlex.split(line) for line in joined.splitlines() if line.strip()]


def test_every_snippet_of_the_page_runs(tmp_path, monkeypatch, capsys, isolated_registry):
    monkeypatch.chdir(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr("sys.argv", ["difffilter-train"])
    (tmp_path / "train").symlink_to(ROOT / "train")  # the page's train/configs/generic.yaml
    snippet = types.ModuleType("docs_snippet")  # a module: dataclasses look theirs up
    monkeypatch.setitem(sys.modules, "docs_snippet", snippet)
    namespace = snippet.__dict__
    ran = {"python": 0, "yaml": 0, "eval": 0, "train": 0}
    try:
        for kind, code in _blocks(PAGE.read_text()):
            first = code.splitlines()[0]
            module_file = re.match(r"# (\w+\.py)\b", first)
            if kind == "python" and module_file:  # a module of the page (my_plants, my_attacks)
                with open(module_file.group(1), "a") as module:
                    module.write(code + "\n")
            elif kind == "python":
                exec(compile(code, str(PAGE), "exec"), namespace)
                ran["python"] += 1
            elif kind == "yaml":
                name = re.match(r"# file: (\S+)", first).group(1)
                Path(name).write_text(code)
                ran["yaml"] += 1
            else:
                for argv in _commands(code):
                    if argv[0] == "difffilter-eval":
                        assert eval_main([*argv[1:], "--no-progress"]) == 0, argv
                        ran["eval"] += 1
                    elif argv[:2] == ["difffilter-train", "fit"]:
                        assert train_main([*argv[1:], *SHORT_TRAINING]) == 0, argv
                        ran["train"] += 1
        # docs/threats.md's study from Python imports my_attacks.py, written above (a course
        # trial found no page that said to write it)
        threats_page = (ROOT / "docs" / "threats.md").read_text()
        (study,) = [code for kind, code in _blocks(threats_page)
                    if kind == "python" and "from my_attacks import Drift" in code]  # fmt: skip
        exec(compile(study, "docs/threats.md", "exec"), dict(namespace))
        assert (tmp_path / "out/robustness/four_tank_bias/robustness.json").is_file()
    finally:
        sys.modules.pop("my_plants", None)
        sys.modules.pop("my_attacks", None)
    assert ran == {"python": 6, "yaml": 3, "eval": 6, "train": 2}
    # §6 prints its closed-loop study's rates: the page's figures, to round-off
    out = capsys.readouterr().out
    printed = re.findall(r"^(?:chi2|cusum) FPR .*$", out, flags=re.M)
    shown = re.search(r"This prints.*?```text\n(.*?)```", PAGE.read_text(), flags=re.S).group(1)
    numbers = [float(v) for v in re.findall(r"\d\.\d+", "\n".join(printed))]
    assert len(printed) == 2 and numbers == pytest.approx(
        [float(v) for v in re.findall(r"\d\.\d+", shown)], abs=0.003
    )
    # §7 prints its crafted attack's rates and errors on fresh runs: the page's, each to one
    # unit of its last printed digit (round-off; an absolute 0.003 let the 0.0226 error move
    # 13 %: a review)
    (printed,) = re.findall(r"^stealthy: .*$", out, flags=re.M)
    (shown,) = re.findall(r"^stealthy: .*$", PAGE.read_text(), flags=re.M)
    got, want = (re.findall(r"\d+\.\d+", line) for line in (printed, shown))
    assert len(got) == len(want) == 5, (printed, shown)
    for g, w in zip(got, want, strict=True):
        assert abs(float(g) - float(w)) <= 1.01 * 10.0 ** -len(w.split(".")[1]), (printed, shown)
    lossy = json.loads((tmp_path / "reports" / "motor_lossy_yaml" / "metrics.json").read_text())
    assert lossy["network"]["inputs"]["acknowledged"] is False
    assert lossy["network"]["sensors"] == "PacketLoss(rate=0.1, packets=None)"
    # what the page says happened, happened
    motor = json.loads((tmp_path / "reports" / "motor_actuator" / "metrics.json").read_text())
    learned = motor["estimators"]["gaussian_nn_grad"]  # the last command: the trained network
    assert learned["attack_rmse"] is not None  # an actuator-side estimate, scored as one
    assert "no attack-free reference" in motor["skipped"]["normal_pf_attack_free"]
    vdp = json.loads((tmp_path / "reports" / "vdp_ramp_yaml" / "metrics.json").read_text())
    assert "linear model" in vdp["skipped"]["chi_square_kf"]
    assert "vdp_drift" in out and "vdp_damping" in out


def test_a_module_beside_the_user_imports_as_from_a_console_script(tmp_path, monkeypatch):
    """A console script's sys.path lacks the working folder (``difffilter-eval --scenario
    my_plants:vdp`` exited 2 from the folder holding my_plants.py); it is tried last."""
    import os
    import sys

    from difffilter.models.yaml_scenario import import_object

    (tmp_path / "beside_the_user_plants.py").write_text("VALUE = 3\n")
    monkeypatch.chdir(tmp_path)
    here = os.getcwd()
    monkeypatch.setattr(sys, "path", [p for p in sys.path if p not in ("", here, str(tmp_path))])
    assert import_object("beside_the_user_plants:VALUE", "scenario") == 3
    with pytest.raises(ValueError, match="cannot import 'no_such_module_here'"):
        import_object("no_such_module_here:x", "scenario")
