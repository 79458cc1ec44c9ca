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

from importlib import import_module as _import_module

# The package loads its modules on first use (PEP 562): ``import difffilter`` and the
# command lines' ``--help`` do not pay for torch until something needs it.
_WHERE = {
    "NonFinite": "_checks",
    "NumericalBreakdown": "linalg",
    **dict.fromkeys(("PCRBResult", "posterior_crb"), "bounds"),
    **dict.fromkeys(("Detection", "Estimator", "EstimatorOutput", "Generators"), "estimator"),
    **dict.fromkeys(
        (
            "ExtendedKalmanFilter",
            "SigmaPoints",
            "UnscentedKalmanFilter",
            "extended_kalman_filter",
            "extended_kalman_step",
            "unscented_kalman_filter",
            "unscented_kalman_step",
        ),
        "extended",
    ),  # fmt: skip
    "ExpectedInputKalmanFilter": "expected_input",
    "GainSchedule": "gain_schedule",
    **dict.fromkeys(
        (
            "GaussianFilter",
            "KalmanFilter",
            "gaussian_init",
            "kalman_filter",
            "kalman_predict",
            "kalman_step",
        ),
        "kalman",
    ),  # fmt: skip
    "open_loop": "loop",
    **dict.fromkeys(
        (
            "BootstrapProposal",
            "KalmanProposal",
            "ModelLikelihood",
            "ParticleFilter",
            "ParticleState",
            "particle_filter",
            "particle_init",
            "particle_step",
        ),
        "particle",
    ),  # fmt: skip
    **dict.fromkeys(
        (
            "FilterResult",
            "GaussianState",
            "GaussianStepOutput",
            "ParticleFilterResult",
            "StepOutput",
        ),
        "results",
    ),  # fmt: skip
    **dict.fromkeys(
        (
            "SmootherResult",
            "extended_kalman_smoother",
            "kalman_smoother",
            "rts_smoother",
            "unscented_kalman_smoother",
            "unscented_rts_smoother",
        ),
        "smoother",
    ),  # fmt: skip
    **dict.fromkeys(("ParticleSmootherResult", "particle_smoother"), "particle_smoothing"),
    **dict.fromkeys(("LinearGaussianModel", "NonlinearGaussianModel", "StateSpaceModel"), "ssm"),
}


def __getattr__(name: str):
    if name in _WHERE:
        value = getattr(_import_module(f".{_WHERE[name]}", __name__), name)
        globals()[name] = value  # looked up once
        return value
    if not name.startswith("__"):  # any submodule: difffilter.fdi, difffilter.loop, …
        try:
            return _import_module(f".{name}", __name__)
        except ModuleNotFoundError as error:
            if error.name != f"{__name__}.{name}":
                raise
    raise AttributeError(f"module 'difffilter' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(__all__))


__version__ = "0.1.0"

__all__ = [
    "load_estimator",
    "NonFinite",
    "NumericalBreakdown",
    "StateSpaceModel",
    "LinearGaussianModel",
    "NonlinearGaussianModel",
    "noise",
    "metrics",
    "consistency",
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
    "kalman_smoother",
    "extended_kalman_smoother",
    "unscented_kalman_smoother",
    "rts_smoother",
    "unscented_rts_smoother",
    "SmootherResult",
    "particle_smoother",
    "ParticleSmootherResult",
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
