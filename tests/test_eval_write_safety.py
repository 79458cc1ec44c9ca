"""``difffilter-eval`` writes its reports safely (a red-team run's findings): a write that
fails midway (a full disk) leaves the earlier file and says which file in one line, not a
traceback; two evaluations do not write into one ``--out`` at once; and one stopped midway
leaves ``INCOMPLETE.md`` where its files may be mixed with an earlier evaluation's."""

from __future__ import annotations

import errno
import io
import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import matplotlib.figure
import matplotlib.pyplot as plt
import pytest

from difffilter.eval import cli
from difffilter.eval.report import INCOMPLETE
from difffilter.models.atomic_write import write_atomically

ROOT = Path(__file__).resolve().parents[1]
SCENARIO = "four_tank_bias"
#: The smallest evaluation that writes every kind of report file: two runs, one estimator.
SMALL = ["--runs", "2", "--no-progress", "--far", "off", "--estimators", "chi_square_ekf"]
TOO_LARGE = os.strerror(errno.EFBIG)  # "File too large", as a full disk or `ulimit -f` says


def _evaluate(out: Path, seed: int) -> int:
    return cli.main([SCENARIO, *SMALL, "--out", str(out), "--seed", str(seed)])


@pytest.fixture(autouse=True)
def _close_figures():
    """Any figure a test leaves open (an evaluation closes its own, also where it stops)."""
    yield
    plt.close("all")


@pytest.fixture(scope="module")
def earlier(tmp_path_factory) -> Path:
    """An ``--out`` holding a finished evaluation of seed 0."""
    out = tmp_path_factory.mktemp("earlier") / "out"
    assert _evaluate(out, 0) == 0
    return out


@pytest.fixture
def out(earlier, tmp_path) -> Path:
    """A copy of :func:`earlier` to write into again."""
    return Path(shutil.copytree(earlier, tmp_path / "out"))


def _files(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes()
            for p in folder.rglob("*") if p.is_file() and "tb" not in p.parts}  # fmt: skip


def _fail_writing(monkeypatch, name: str) -> None:
    """Every write of a file called ``name`` (or of its temporary file) writes half of its
    content, then fails as on a full disk: text, bytes and matplotlib's figures."""

    def targeted(path) -> bool:
        base = Path(path).name
        return base == name or base.startswith(f".{name}.")

    def half_then_full(path, data: bytes) -> None:
        with open(path, "wb") as fh:
            fh.write(data[: len(data) // 2])
        raise OSError(errno.EFBIG, TOO_LARGE)  # (a failed write() names no file)

    write_text, write_bytes = Path.write_text, Path.write_bytes
    savefig = matplotlib.figure.Figure.savefig

    def patched_text(self, data, *args, **kwargs):
        if targeted(self):
            half_then_full(self, data.encode())
        return write_text(self, data, *args, **kwargs)

    def patched_bytes(self, data):
        if targeted(self):
            half_then_full(self, bytes(data))
        return write_bytes(self, data)

    def patched_savefig(self, fname, *args, **kwargs):
        if isinstance(fname, (str, os.PathLike)) and targeted(fname):
            buffer = io.BytesIO()
            savefig(self, buffer, *args, **kwargs)
            half_then_full(fname, buffer.getvalue())
        return savefig(self, fname, *args, **kwargs)

    monkeypatch.setattr(Path, "write_text", patched_text)
    monkeypatch.setattr(Path, "write_bytes", patched_bytes)
    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", patched_savefig)


@pytest.mark.parametrize(
    "name",
    [
        f"{SCENARIO}/metrics.json",
        f"{SCENARIO}/report.md",
        f"{SCENARIO}/roc.png",
        "leaderboard.json",
        "leaderboard.md",
        "leaderboard.png",
    ],
)
def test_a_write_that_fails_midway_keeps_the_earlier_file_and_names_it(
    out, name, monkeypatch, capsys
):
    """A write of ``ulimit -f 20`` had left a truncated, unparsable metrics.json in place of
    the earlier good one, and the command died with a traceback. Now each file is replaced
    whole or not at all, and the command exits 2 with one line naming the file."""
    before = _files(out)
    capsys.readouterr()
    _fail_writing(monkeypatch, Path(name).name)
    assert _evaluate(out, 1) == 2
    assert capsys.readouterr().err == (
        f"difffilter-eval: error: could not write {out / name}: {TOO_LARGE}\n"
    )
    assert (out / name).read_bytes() == before[name]  # the earlier evaluation's, whole
    assert not [p for p in out.rglob("*") if p.name.endswith(".partial")]
    assert (out / INCOMPLETE).is_file()  # the folder may now mix seed 0 and seed 1
    if name == f"{SCENARIO}/metrics.json":  # (nothing of the scenario's was replaced)
        assert json.loads((out / name).read_text())["seed"] == 0
        assert _files(out / SCENARIO) == {
            **{k.split("/", 1)[1]: v for k, v in before.items() if k.startswith(SCENARIO)},
            INCOMPLETE: (out / SCENARIO / INCOMPLETE).read_bytes(),
        }
    monkeypatch.undo()
    assert _evaluate(out, 1) == 0  # run again to its end: whole, and no marker left
    assert json.loads((out / f"{SCENARIO}/metrics.json").read_text())["seed"] == 1
    assert {row["seed"] for row in json.loads((out / "leaderboard.json").read_text())} == {1}
    assert not list(out.rglob(INCOMPLETE))


def test_a_full_disk_under_ulimit_keeps_the_earlier_metrics(out):
    """The finding itself: ``ulimit -f`` (RLIMIT_FSIZE) in a process of its own, the limit
    set after the imports so that it meets the reports alone."""
    before = (out / SCENARIO / "metrics.json").read_bytes()
    script = textwrap.dedent(f"""
        import resource, sys
        from difffilter.eval import cli
        resource.setrlimit(resource.RLIMIT_FSIZE, (2048, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))
        sys.exit(cli.main({[SCENARIO, *SMALL, "--out", str(out), "--seed", "1"]!r}))
    """)  # fmt: skip
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          cwd=ROOT, timeout=120, env={**os.environ, "OMP_NUM_THREADS": "1"})  # fmt: skip
    assert done.returncode == 2, done.stderr
    assert done.stderr.splitlines()[-1] == (
        f"difffilter-eval: error: could not write {out / SCENARIO / 'metrics.json'}: {TOO_LARGE}"
    )
    assert "Traceback" not in done.stderr
    assert (out / SCENARIO / "metrics.json").read_bytes() == before
    assert not [p for p in out.rglob("*") if p.name.endswith(".partial")]


def test_an_error_naming_no_file_says_the_reports_may_be_incomplete(out, monkeypatch, capsys):
    """An ``OSError`` of a writer that names no file (TensorBoard's) is one line too."""

    def no_space(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr("difffilter.eval.tensorboard.log_suite", no_space)
    capsys.readouterr()
    assert _evaluate(out, 1) == 2
    assert capsys.readouterr().err == (
        f"difffilter-eval: error: {os.strerror(errno.ENOSPC)} (the reports under {out} may "
        "be incomplete)\n"
    )


def test_an_interrupted_evaluation_leaves_incomplete_where_its_files_may_be_mixed(
    out, monkeypatch, capsys
):
    """Stopped after the new metrics.json, before the leaderboard, an evaluation had left
    seed 1's metrics.json beside seed 0's leaderboard.json with nothing to say so."""
    assert not list(out.rglob(INCOMPLETE))  # a finished evaluation leaves none

    def interrupted(*args, **kwargs):  # after metrics.json and report.md, before the events
        raise KeyboardInterrupt

    monkeypatch.setattr("difffilter.eval.tensorboard.log_suite", interrupted)
    assert _evaluate(out, 1) == 130
    assert json.loads((out / SCENARIO / "metrics.json").read_text())["seed"] == 1
    assert {row["seed"] for row in json.loads((out / "leaderboard.json").read_text())} == {0}
    for folder in (out, out / SCENARIO):
        text = (folder / INCOMPLETE).read_text()
        assert "has not ended" in text and "may mix its results with an earlier" in text
    monkeypatch.undo()
    assert _evaluate(out, 1) == 0
    assert not list(out.rglob(INCOMPLETE))


def test_sigterm_ends_an_evaluation_as_an_interrupt_does_with_one_line_and_143(
    out, monkeypatch, capsys
):
    """SIGTERM (a scheduler's stop) had ended difffilter-eval silently with 143; it now
    closes what it holds, leaves INCOMPLETE.md, says so in one line and restores the
    caller's SIGTERM handler."""
    import signal

    def terminated(*args, **kwargs):  # the signal arrives while the study writes its events
        os.kill(os.getpid(), signal.SIGTERM)
        raise AssertionError("SIGTERM was not raised where the study was")

    before = signal.getsignal(signal.SIGTERM)
    monkeypatch.setattr("difffilter.eval.tensorboard.log_suite", terminated)
    assert _evaluate(out, 1) == 143
    assert capsys.readouterr().err.splitlines()[-1] == (
        "difffilter-eval: terminated (SIGTERM): the reports under --out may be incomplete; "
        "rerun the same command to evaluate again"
    )
    assert (out / INCOMPLETE).exists()
    assert signal.getsignal(signal.SIGTERM) == before


HOLDER = """
import sys
from pathlib import Path
from difffilter.eval.cli import hold_output_folder
with hold_output_folder(Path(sys.argv[1])):
    print("held", flush=True)
    sys.stdin.read()  # till the test closes it
"""


def test_a_second_evaluation_into_an_out_being_written_is_refused(out, capsys):
    """Two evaluations into one ``--out`` at once had both exited 0, one's metrics.json
    beside both's TensorBoard events. The second is now refused before any work, with one
    line; once the first has ended, the folder is free again."""
    shutil.rmtree(out / SCENARIO)
    holder = subprocess.Popen([sys.executable, "-c", HOLDER, str(out)], cwd=ROOT,
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)  # fmt: skip
    try:
        assert holder.stdout.readline() == "held\n"
        capsys.readouterr()
        assert _evaluate(out, 1) == 2
        assert capsys.readouterr().err == (
            f"difffilter-eval: error: --out {out}: another difffilter-eval (process "
            f"{holder.pid}) is writing into this folder; wait for it to end, or give "
            "another --out\n"
        )
        assert not (out / SCENARIO).exists()  # refused before the study
    finally:
        holder.communicate("", timeout=60)
    assert _evaluate(out, 1) == 0
    assert json.loads((out / SCENARIO / "metrics.json").read_text())["seed"] == 1
    with cli.hold_output_folder(out):  # released when the command ended
        with pytest.raises(ValueError, match=rf"another difffilter-eval \(process {os.getpid()}\)"):
            with cli.hold_output_folder(out):
                pass


def test_the_lock_is_a_no_op_without_fcntl(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "fcntl", None)  # import fcntl: ImportError
    with cli.hold_output_folder(tmp_path), cli.hold_output_folder(tmp_path):
        pass
    assert list(tmp_path.iterdir()) == []


def test_write_atomically_replaces_whole_or_not_at_all_and_names_its_file(tmp_path):
    path = tmp_path / "metrics.json"
    write_atomically(path, '{"seed": 0}\n')

    def half(partial: Path) -> None:
        partial.write_text('{"se')
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    with pytest.raises(OSError) as raised:
        write_atomically(path, half)
    assert raised.value.filename == str(path) and raised.value.errno == errno.ENOSPC
    assert path.read_text() == '{"seed": 0}\n' and [p.name for p in tmp_path.iterdir()] == [
        "metrics.json"
    ]
    write_atomically(path, b"\x89PNG")
    assert path.read_bytes() == b"\x89PNG"


def test_write_atomically_keeps_two_threads_writing_one_path_apart(tmp_path):
    """Two threads of one process writing the same path: each has its own partial file, so
    the one that finishes first does not move the other's half-written file into place
    (with one partial file per process, the other's replace then found no file)."""
    import threading

    path = tmp_path / "report.md"

    def slow(partial: Path) -> None:
        with partial.open("w") as f:
            f.write("first half, ")
            f.flush()
            other = threading.Thread(target=write_atomically, args=(path, "the other thread\n"))
            other.start()
            other.join()
            f.write("second half\n")

    write_atomically(path, slow)
    assert path.read_text() == "first half, second half\n"
    assert [p.name for p in tmp_path.iterdir()] == ["report.md"]


def test_an_evaluation_stopped_by_a_failing_write_leaves_no_figure_open(out, monkeypatch):
    # they had stayed open in pyplot: a process meeting such writes gathered 20 and more
    plt.close("all")
    _fail_writing(monkeypatch, "report.md")
    assert _evaluate(out, 1) == 2
    assert plt.get_fignums() == []
