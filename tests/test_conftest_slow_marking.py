"""Which tests ``tests/conftest.py`` puts in the ``slow`` group (``make test`` leaves them
out, CI runs them): a listed file's tests whatever their parameters, a listed test, a
listed parameter alone (a mutation trial: reverting the node-id fix below moved three
tests of a listed file back into ``make test`` and no test failed)."""

from __future__ import annotations

from conftest import SLOW, slow_name


def test_a_listed_files_tests_are_slow_even_with_a_path_among_their_parameters():
    assert "test_user_plants.py" in SLOW
    for nodeid in ("tests/test_user_plants.py::test_a", "tests/test_user_plants.py::test_a[x]",
                   "tests/test_user_plants.py::test_a[/tmp/pytest-0/vdp.yaml]",
                   "tests/test_user_plants.py::Case::test_a[{tmp}/a/b/vdp.yaml-float32]"):  # fmt: skip
        assert slow_name(nodeid) == (nodeid.removeprefix("tests/"), True), nodeid


def test_a_listed_test_or_parameter_is_slow_and_its_neighbours_are_not():
    test = "test_sigterm.py::test_a_terminated_fit_exits_143_keeps_last_ckpt_and_resumes"
    assert test in SLOW
    assert slow_name(f"tests/{test}")[1] and slow_name(f"tests/{test}[1]")[1]
    assert not slow_name("tests/test_sigterm.py::test_something_else")[1]
    listed = "test_resampling.py::test_ot_gradient_matches_finite_differences[particles-log]"
    assert listed in SLOW
    assert slow_name(f"tests/{listed}")[1]
    assert not slow_name(f"tests/{listed.replace('-log]', '-kernel]')}")[1]
    # a parameter naming a listed file does not make an unlisted file's test slow
    assert not slow_name("tests/test_kalman.py::test_a[/x/test_user_plants.py]")[1]
