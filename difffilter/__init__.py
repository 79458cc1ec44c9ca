"""difffilter: differentiable, batched state estimation under false-data-injection attacks.

Models (:class:`StateSpaceModel`, :class:`LinearGaussianModel`,
:class:`NonlinearGaussianModel`), noise models (:mod:`difffilter.noise`), every estimator
as an object with a pure step over one carry (:class:`Estimator`: :class:`KalmanFilter`,
:class:`ExtendedKalmanFilter`, :class:`UnscentedKalmanFilter`, :class:`ParticleFilter`
with pluggable proposals, likelihoods and resamplers of :mod:`difffilter.resampling`) run
by the drivers of :mod:`difffilter.loop`, their whole-sequence functions
(:func:`kalman_filter`, :func:`extended_kalman_filter`, :func:`unscented_kalman_filter`,
:func:`particle_filter`), the posterior Cramér–Rao bound
(:func:`posterior_crb`), and the attack detectors and attack-aware
filters of the FDI literature (:mod:`difffilter.fdi`).

Shapes are batch first: measurements ``ys [..., T, dy]``, inputs ``us [..., T, du]``,
particles ``[..., N, dx]``. See :mod:`difffilter.ssm` for the time convention.
"""

from . import bounds, metrics, noise, resampling, threats
from ._checks import NonFinite
from .bounds import PCRBResult, posterior_crb
from .estimator import Detection, Estimator, EstimatorOutput, Generators
from .extended import (
    ExtendedKalmanFilter,
    SigmaPoints,
    UnscentedKalmanFilter,
    extended_kalman_filter,
    extended_kalman_step,
    unscented_kalman_filter,
    unscented_kalman_step,
)
from .gain_schedule import GainSchedule
from .kalman import (
    GaussianFilter,
    KalmanFilter,
    gaussian_init,
    kalman_filter,
    kalman_predict,
    kalman_step,
)
from .loop import open_loop
from .particle import (
    BootstrapProposal,
    KalmanProposal,
    ModelLikelihood,
    ParticleFilter,
    ParticleState,
    particle_filter,
    particle_init,
    particle_step,
)
from .results import (
    FilterResult,
    GaussianState,
    GaussianStepOutput,
    ParticleFilterResult,
    StepOutput,
)
from .ssm import LinearGaussianModel, NonlinearGaussianModel, StateSpaceModel

__version__ = "0.1.0"

__all__ = [
    "load_estimator",
    "NonFinite",
    "StateSpaceModel",
    "LinearGaussianModel",
    "NonlinearGaussianModel",
    "noise",
    "metrics",
    "bounds",
    "posterior_crb",
    "PCRBResult",
    "resampling",
    "threats",
    "ParticleState",
    "particle_init",
    "particle_step",
    "particle_filter",
    "BootstrapProposal",
    "KalmanProposal",
    "ModelLikelihood",
    "GaussianState",
    "GaussianStepOutput",
    "FilterResult",
    "ParticleFilterResult",
    "gaussian_init",
    "kalman_predict",
    "kalman_step",
    "kalman_filter",
    "GainSchedule",
    "extended_kalman_step",
    "extended_kalman_filter",
    "unscented_kalman_step",
    "unscented_kalman_filter",
    "SigmaPoints",
    "Detection",
    "EstimatorOutput",
    "Estimator",
    "Generators",
    "StepOutput",
    "open_loop",
    "GaussianFilter",
    "KalmanFilter",
    "ExtendedKalmanFilter",
    "UnscentedKalmanFilter",
    "ParticleFilter",
]


def load_estimator(path, **kwargs):
    """A trained neural FDI estimator from its checkpoint, ready to run
    (:func:`difffilter.models.learned_estimator.load_estimator`; docs/python-api.md)."""
    from difffilter.models.learned_estimator import load_estimator as load

    return load(path, **kwargs)
