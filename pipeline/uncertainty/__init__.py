"""Uncertainty per voxel: the standard error of every voxel's refractivity, temperature and
density (beyond the paper; docs/uncertainty.md).

:func:`frame_uncertainty` (:mod:`.frame`) adds four terms in quadrature: the flows'
measured noise (:mod:`.noise`) propagated through the frame's tomography solve and
integration by an ensemble of perturbation solves (:mod:`.ensemble`,
:mod:`.linear_integration`); the regularisation's bias, from the share of smooth random
fields the solve's resolution operator loses (:mod:`.bias`); the integration's sensitivity
to its boundary condition (:mod:`.boundary`); and the estimate's fine structure
(:mod:`.structure`), the last three scaled on the realistic family's tune cases. With ``UncertaintyParams.prior_samples`` the ensemble's samples are posterior samples
of the linear-Gaussian model the solve's normal equations define (the priors perturbed
too, :func:`prior_perturbation`).
"""

from schlieren.pipeline.uncertainty.bias import ResolutionLoss, bias_solve, regulariser_pull, resolution_loss, smooth_probe
from schlieren.pipeline.uncertainty.boundary import boundary_sensitivity, natural_integration
from schlieren.pipeline.uncertainty.ensemble import NoiseEnsemble, noise_ensemble, perturbation_solve, prior_perturbation
from schlieren.pipeline.uncertainty.frame import (FrameUncertainty, density_sigma, frame_rng, frame_uncertainty,
                                                  temperature_sigma)
from schlieren.pipeline.uncertainty.linear_integration import LinearisedIntegration
from schlieren.pipeline.uncertainty.local import masked_mean
from schlieren.pipeline.uncertainty.noise import correlated_flow_noise, flow_noise_level, noise_correlation
from schlieren.pipeline.uncertainty.params import UncertaintyParams
from schlieren.pipeline.uncertainty.structure import curvature_rms

__all__ = ["UncertaintyParams", "FrameUncertainty", "frame_uncertainty", "frame_rng", "temperature_sigma", "density_sigma",
           "NoiseEnsemble", "noise_ensemble", "perturbation_solve", "prior_perturbation", "LinearisedIntegration",
           "ResolutionLoss", "resolution_loss", "smooth_probe", "bias_solve", "regulariser_pull", "boundary_sensitivity", "natural_integration", "masked_mean", "curvature_rms", "flow_noise_level",
           "correlated_flow_noise", "noise_correlation"]
