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


def test_a_plain_helper_class_a_model_holds_is_freed_too():
    # its own __dict__/__weakref__ descriptors take no weak reference and point at the
    # class: kept among the memo's members, they had held it (a review)
    refs = []
    for i in range(3):

        class Gain:  # a plain class made per call, base object
            data = [float(i)] * 10

            def __call__(self, x):
                return x

        model = _model(df.LinearGaussianModel)
        model.helper = Gain()
        cc.model_fingerprint(model)
        refs.append(weakref.ref(Gain))
        del Gain, model
    gc.collect()
    assert [r() for r in refs] == [None] * 3


def test_a_member_set_to_none_is_a_new_digest():
    # the old member's dead weak reference had read as None, and None is None had served
    # the old digest (a review: observe 8.0 -> 2.0, the fingerprint unchanged)
    class Plant(df.LinearGaussianModel):
        def squash(self, y):
            return y**3

        def observe(self, x, k):
            y = super().observe(x, k)
            return y if self.squash is None else self.squash(y)

    before = cc.model_fingerprint(_model(Plant))
    Plant.squash = None
    after = cc.model_fingerprint(_model(Plant))
    cc._CLASS_CODE.pop(Plant, None)
    assert after == cc.model_fingerprint(_model(Plant)) != before


def test_static_and_class_methods_and_properties_replaced_are_seen():
    class Plant(df.LinearGaussianModel):
        @staticmethod
        def scale():
            return 1.0

        @property
        def gain(self):
            return 1.0

    first = cc.model_fingerprint(_model(Plant))
    assert cc.model_fingerprint(_model(Plant)) == first
    Plant.scale = staticmethod(lambda: 2.0)
    second = cc.model_fingerprint(_model(Plant))
    assert second != first
    Plant.gain = property(lambda self: 2.0)
    assert cc.model_fingerprint(_model(Plant)) != second


def test_members_wrapping_objects_of_no_weak_reference_are_fingerprinted():
    # property(operator.attrgetter(...)) had failed in weakref: no plant of one could be
    # fingerprinted, calibrated or evaluated (a review)
    import operator

    class Plant(df.LinearGaussianModel):
        gain = property(operator.attrgetter("_gain"))
        first = staticmethod(operator.itemgetter(0))

    digest = cc.model_fingerprint(_model(Plant))
    assert cc.model_fingerprint(_model(Plant)) == digest
    Plant.first = staticmethod(lambda seq: seq[1])  # code now: a new digest
    assert cc.model_fingerprint(_model(Plant)) != digest
