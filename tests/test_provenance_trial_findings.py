"""Findings of a red-team trial of the reproducibility records (each failed before its fix)."""

from __future__ import annotations

from pathlib import Path


def test_the_library_fingerprint_covers_the_evaluation_code(monkeypatch):
    """In a development checkout eval/ lies outside difffilter/: a fix of a metric left
    the sweep's cached baselines (keyed by this fingerprint) of before in use."""
    import difffilter.eval.scoring as scoring
    from difffilter.models import calibration_cache as cc

    monkeypatch.setattr(cc, "_LIBRARY_FINGERPRINT", None)
    before = cc.library_fingerprint()
    edited = Path(scoring.__file__).resolve()
    read = Path.read_bytes

    def read_edited(path):
        data = read(path)
        return data + b"\n# edited\n" if Path(path).resolve() == edited else data

    monkeypatch.setattr(Path, "read_bytes", read_edited)
    monkeypatch.setattr(cc, "_LIBRARY_FINGERPRINT", None)
    assert cc.library_fingerprint() != before


def test_a_copy_inside_another_work_tree_gets_no_commit_and_an_unknown_status_is_said(
    tmp_path, monkeypatch
):
    """A copy of difffilter/ inside an unrelated repository (a pip install into its .venv)
    had been given that repository's commit; a git status that failed read as clean."""
    import shutil
    import subprocess

    import difffilter
    from difffilter.eval import provenance

    repo = tmp_path / "other"
    repo.mkdir()
    git = ["git", "-C", str(repo), "-c", "user.name=t", "-c", "user.email=t@t"]
    subprocess.run([*git[:3], "init", "-q"], check=True)
    (repo / "README").write_text("x")
    subprocess.run([*git, "add", "README"], check=True)
    subprocess.run([*git, "commit", "-qm", "x"], check=True)
    copy = repo / "site" / "difffilter"
    shutil.copytree(Path(difffilter.__file__).parent, copy,
                    ignore=shutil.ignore_patterns("__pycache__"))  # fmt: skip
    monkeypatch.setattr(difffilter, "__file__", str(copy / "__init__.py"))
    provenance.software_record.cache_clear()
    try:
        record = provenance.software_record()
    finally:
        provenance.software_record.cache_clear()
    assert record["git_commit"] is None and record["git_dirty"] is None
    line = provenance.software_line({**record, "git_commit": "0123456789abcdef", "git_dirty": None})
    assert "at 0123456789ab + changes unknown" in line


def test_a_checkpoint_replaced_during_an_evaluation_is_recorded_as_the_file_that_ran(tmp_path):
    """The network is loaded once per evaluation (its cache, shared by its scenarios), and
    its sha256 had been read at each report's end: a file replaced in between (an export's
    ``--force``) was recorded while the old network ran (a trial). The digest is the file's
    when first loaded; a fresh evaluation loads and records the new one."""
    import hashlib
    import shutil

    import torch

    from difffilter.eval.suite import run_suite
    from difffilter.models import registry

    shipped = Path(__file__).resolve().parents[1] / "checkpoints" / "robot_nn_ekf.ckpt"
    used = tmp_path / "x.ckpt"
    shutil.copyfile(shipped, used)
    blob = torch.load(shipped, map_location="cpu", weights_only=True)
    blob["state_dict"] = {k: v + 0.05 for k, v in blob["state_dict"].items()}
    trained = blob["observer"]["scenario"]
    blob["observer"]["scenario"] = "retrained_elsewhere"
    other = tmp_path / "other.ckpt"
    torch.save(blob, other)

    def sha(path):
        return hashlib.sha256(Path(path).read_bytes()).hexdigest()

    first, second = sha(used), sha(other)
    scenario, cache = registry.get("robot_actuator_attack"), {}
    kw = dict(runs=2, estimators=["gaussian_nn_ekf"], progress=False, checkpoint=used)
    before = run_suite(scenario, cache=cache, **kw)
    shutil.copyfile(other, used)
    during = run_suite(scenario, cache=cache, **kw)  # the network loaded before runs
    fresh = run_suite(scenario, cache={}, **kw)
    rmse = [r.metrics["gaussian_nn_ekf"]["state_rmse"] for r in (before, during, fresh)]
    assert rmse[0] == rmse[1] != rmse[2]
    assert [r.checkpoint["sha256"] for r in (before, during, fresh)] == [first, first, second]
    # and the scenario it was trained on is that network's too (a review)
    assert [r.checkpoint.get("training_scenario") for r in (before, during, fresh)] == [
        trained, trained, "retrained_elsewhere"]  # fmt: skip
    # a study in another dtype loads the file again, as it is now, and records that (a
    # review: the digest of the first load had been kept for the path)
    single = run_suite(scenario, cache=cache, dtype=torch.float32, **kw)
    again = run_suite(scenario, cache={}, dtype=torch.float32, **kw)
    assert (
        single.metrics["gaussian_nn_ekf"]["state_rmse"]
        == again.metrics["gaussian_nn_ekf"]["state_rmse"]
    )
    assert single.checkpoint["sha256"] == second


def test_the_digests_of_checkpoints_other_processes_loaded_are_gathered(monkeypatch):
    """With ``--devices 2`` the entry using a checkpoint may run in another process: the
    report's process had hashed the file at the end, never having loaded it (a review).
    The processes' digests come with their outputs."""
    from types import SimpleNamespace

    from difffilter.eval import suite

    mine = SimpleNamespace(outputs={}, wall_s={}, skipped={}, trajectories={})
    ctx = SimpleNamespace(checkpoint_users=[], loaded_checkpoints={})
    record = {"sha256": "loaded-by-rank-1", "training_scenario": "robot"}
    other = ({}, {}, {}, ["gaussian_nn_ekf"], {}, {"net.ckpt": record})
    monkeypatch.setattr(suite, "gather_objects", lambda part, world: [part, other])
    suite._gather(mine, ctx, [SimpleNamespace(name="gaussian_nn_ekf")], 2)
    assert ctx.loaded_checkpoints == {"net.ckpt": record}
    assert ctx.checkpoint_users == ["gaussian_nn_ekf"]
