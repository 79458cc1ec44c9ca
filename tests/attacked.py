"""A four-tank plant under the bias attack for the FDI filters' tests: the scenario's
simulation (the loop without an estimator) with the attack's values beside it."""

from __future__ import annotations

from types import SimpleNamespace

from difffilter.models.attacks import SensorBias
from difffilter.models.scenario import simulate


def simulate_attacked(model, attack: SensorBias, runs: int, steps: int, *, plant_generator,
                      attack_generator, random_initial: bool = False) -> SimpleNamespace:  # fmt: skip
    """``x, y_true, y_recv, flags`` and ``gammas`` (``γ_k`` at every step) and ``x0``."""
    tr = simulate(model, runs, steps, generators={"plant": plant_generator,
                  "attack": attack_generator}, attack=attack, random_initial=random_initial)  # fmt: skip
    return SimpleNamespace(x=tr.x, y_true=tr.y_true, y_recv=tr.y_recv, flags=tr.flags,
                           gammas=tr.info["attack_values"], x0=tr.info["x0"])  # fmt: skip
