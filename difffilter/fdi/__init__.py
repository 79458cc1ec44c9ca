"""Attack detectors and attack-aware filters of the FDI literature.

Every estimator here takes ``(model, ys, us=None, *, mask=None, ...)`` and returns one
:class:`~difffilter.EstimatorOutput` (means, covariances, attack estimate, detection).

* :mod:`~difffilter.fdi.detectors` — chi-square and CUSUM on filter innovations;
* :mod:`~difffilter.fdi.gated` — those detectors run online on a KF/EKF/UKF, gating its update;
* :mod:`~difffilter.fdi.poa` — the probability-of-attack (PoA) detector on weighted
  particle sets with the thresholds of Theorem 1 and eqs (46)/(53), Remark 6's running
  ``p_l``, and the literal-density diagnostic;
* :mod:`~difffilter.fdi.modified_pf` — the normal PF with PoA and the modified PF of
  Table 2 (Sadeghzadeh-Nokhodberiz et al. 2022), composed from the PF parts;
* :mod:`~difffilter.fdi.attack_estimation` — a Kalman estimator of the bias attack γ_k;
* :mod:`~difffilter.fdi.mixture` — the attack-aware mixture likelihood (RRP-PF-DA) and the
  particle filter that scores attacks with it;
* :mod:`~difffilter.fdi.fused` — a fused, low-overhead modified PF (benchmarks, real time);
* :mod:`~difffilter.fdi.adaptive_kf` — Zhang's adaptive Kalman filter (joint state and
  actuator-attack estimate, extended form, forgetting factor λ);
* :mod:`~difffilter.fdi.mdpf` — the lidar-robot paper's local estimator, a particle filter
  whose particles each carry an adaptive Kalman filter (A1)–(A8);
* :mod:`~difffilter.fdi.fusion` — covariance intersection and naive information fusion;
* :mod:`~difffilter.fdi.neural` — the LFC paper's learned attack compensation (a network of
  eqs 8–9 around any filter, optionally learning online).
"""

from .adaptive_kf import AdaptiveKalmanFilter, adaptive_kalman_filter, adaptive_kalman_step
from .attack_estimation import BiasAttackEstimator
from .detectors import (
    ChiSquareDetector,
    CusumDetector,
    chi_square_equivalent,
    chi_square_quantile,
    chi_square_upper_quantile,
    missing_entries_counted,
    normalized_innovation_squared,
)
from .fused import FusedModifiedPF
from .fusion import covariance_intersection, information_fusion
from .gated import (
    GatedFilter,
    cusum_detector_for,
    gated_extended_kalman_filter,
    gated_gaussian_filter,
)
from .mdpf import AdaptiveParticleFilter, adaptive_particle_filter, adaptive_particle_step
from .mixture import (
    BiasDeception,
    DeceptionMixtureLikelihood,
    MixtureParticleFilter,
    ReplacementDeception,
    mixture_likelihood_particle_filter,
)
from .modified_pf import (
    AttackCompensatedLikelihood,
    FlatLikelihood,
    LiteralGaussianLikelihood,
    ModifiedParticleFilter,
    ModifiedPFWeighting,
    PoAParticleFilter,
    corrected_residuals,
    kalman_corrected_particles,
    modified_particle_filter,
    particle_filter_poa,
    reweight,
)
from .neural import NeuralCompensation, OnlineLearning, Residual
from .poa import (
    AttackRateState,
    InfeasibleThreshold,
    PoADetector,
    RunningAttackRate,
    attack_threshold,
    attack_threshold_factor,
    detection_threshold,
    literal_gaussian_density,
    literal_probability_of_attack,
    modified_pf_gain,
    poa_detector_for,
    probability_of_attack,
)

__all__ = [
    "GatedFilter",
    "AdaptiveKalmanFilter",
    "AdaptiveParticleFilter",
    "ModifiedParticleFilter",
    "PoAParticleFilter",
    "MixtureParticleFilter",
    "NeuralCompensation",
    "OnlineLearning",
    "Residual",
    "ChiSquareDetector",
    "CusumDetector",
    "chi_square_equivalent",
    "chi_square_quantile",
    "chi_square_upper_quantile",
    "missing_entries_counted",
    "normalized_innovation_squared",
    "gated_gaussian_filter",
    "cusum_detector_for",
    "gated_extended_kalman_filter",
    "PoADetector",
    "InfeasibleThreshold",
    "poa_detector_for",
    "RunningAttackRate",
    "AttackRateState",
    "attack_threshold",
    "attack_threshold_factor",
    "detection_threshold",
    "modified_pf_gain",
    "probability_of_attack",
    "literal_gaussian_density",
    "literal_probability_of_attack",
    "kalman_corrected_particles",
    "corrected_residuals",
    "FlatLikelihood",
    "AttackCompensatedLikelihood",
    "LiteralGaussianLikelihood",
    "ModifiedPFWeighting",
    "reweight",
    "modified_particle_filter",
    "particle_filter_poa",
    "BiasAttackEstimator",
    "BiasDeception",
    "ReplacementDeception",
    "DeceptionMixtureLikelihood",
    "mixture_likelihood_particle_filter",
    "FusedModifiedPF",
    "adaptive_kalman_filter",
    "adaptive_kalman_step",
    "adaptive_particle_filter",
    "adaptive_particle_step",
    "covariance_intersection",
    "information_fusion",
]
