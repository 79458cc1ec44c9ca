"""The fingerprint's memo of class code holds no class alive (a memory trial: a plant class
made per call, 8 MB of class data each, 20 of 20 kept after ``gc.collect()``), and still
gives a class's digest again, and a new one once a method is replaced."""

import gc
import weakref

import torch

import difffilter as df
from difffilter.models import calibration_cache as cc

F64 = torch.float64


def _factory(scale: float):
    table = torch.full((4, 4), scale, dtype=F64)

    class Plant(df.LinearGaussianModel):
        lookup = table

        def observe(self, x, k):  # a super() call: a __class__ cell pointing at the class
            return super().observe(x, k)

    return Plant


def _model(cls):
    eye = torch.eye(2, dtype=F64)
    return cls(F=eye, H=eye[:1], Q=eye, R=eye[:1, :1], m0=torch.zeros(2, dtype=F64), P0=eye)


def test_a_fingerprinted_class_dropped_is_freed():
    refs = []
    for i in range(5):
        Plant = _factory(float(i))
        cc.model_fingerprint(_model(Plant))
        refs.append(weakref.ref(Plant))
        del Plant
    gc.collect()
    assert [r() for r in refs] == [None] * 5


def test_the_memo_still_serves_and_follows_a_replaced_method():
    Plant = _factory(1.0)
    first = cc.model_fingerprint(_model(Plant))
    assert Plant in cc._CLASS_CODE
    assert cc.model_fingerprint(_model(Plant)) == first

    def observe(self, x, k):
        return 2.0 * x[..., :1]

    Plant.observe = observe
    assert cc.model_fingerprint(_model(Plant)) != first
    Plant.lookup[0, 0] = 5.0  # a constant edited in place: read again at each use
    assert cc.model_fingerprint(_model(Plant)) != first
