"""The training helpers: seed mixing is a fixed, well-spread function of its parts."""

from __future__ import annotations

from difffilter.train.common import mix_seed


def test_mix_seed_is_a_reproducible_63_bit_seed_on_every_numpy():
    # the values numpy's SeedSequence gives (they are part of every training run's
    # reproducibility); the shift is done on a Python int, which numpy 1.x also allows
    assert mix_seed(1, 2) == 7764949442709860949
    assert mix_seed(0) == 7896617691693857887
    seeds = {mix_seed(7, k) for k in range(100)}
    assert len(seeds) == 100 and all(0 <= s < 2**63 and isinstance(s, int) for s in seeds)
