"""Findings of a trial of docs/adding-a-scenario.md: a module path written as a file's
(``./my_plants:scenario`` in ``--scenario``, ``--import`` or a YAML plant's
``transition:``) ended in importlib's ``TypeError`` traceback, naming no file or field; a
single need without the tuple's comma (``needs=(LINEAR_MODEL)``) in "'Need' object is
not iterable", naming neither the estimator nor ``needs``."""

from __future__ import annotations

import pytest

from difffilter._imports import import_object, import_plugin
from difffilter.models import estimators
from difffilter.models.estimators import register
from difffilter.models.needs import LINEAR_MODEL

PATH_HINT = r"a file's path, not a module's name\); give a module's name, not a file's path"


@pytest.mark.parametrize("name", ["./my_plants", "../plants/my_plants", "plants/my_plants"])
def test_a_files_path_is_named_as_one_where_a_module_goes(name):
    with pytest.raises(ValueError, match=rf"plant.yaml: plant.transition: cannot import .*"
                                         rf"{PATH_HINT}.*'my_plants'"):  # fmt: skip
        import_object(f"{name}:step", "plant.yaml: plant.transition")
    with pytest.raises(ValueError, match=rf"--import {name}: cannot import .*{PATH_HINT}"):
        import_plugin(name, f"--import {name}")


def test_the_dotted_name_suggested_is_the_paths_own():
    with pytest.raises(ValueError, match=r"from the file's folder 'my_plants', or a dotted "
                                         r"name from the working folder \(plants.my_plants\)"):  # fmt: skip
        import_object("./plants/my_plants.py:scenario", "scenario")


def test_one_need_alone_is_a_need_and_anything_else_is_named(monkeypatch):
    estimators.names()  # the built-ins loaded first: a copy of the unloaded registry takes them away
    monkeypatch.setattr(estimators, "ESTIMATORS", dict(estimators.ESTIMATORS))

    @register("trial_single_need", "one need, no comma", needs=(LINEAR_MODEL))
    def _factory(ctx):
        return lambda tr: None

    assert estimators.ESTIMATORS["trial_single_need"].needs == (LINEAR_MODEL,)
    for bad in (3, ("linear",)):
        with pytest.raises(TypeError, match=r"estimator 'trial_bad': needs must be a Need of "
                                            r"difffilter.models.needs or a tuple"):  # fmt: skip
            register("trial_bad", "bad needs", needs=bad)
