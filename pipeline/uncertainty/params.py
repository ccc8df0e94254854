"""Parameters of the uncertainty stage (one params class; field names = kernel keywords)."""

from __future__ import annotations

from schlieren.pipeline.params import param, parameters

__all__ = ["UncertaintyParams"]


@parameters
class UncertaintyParams:
    """Standard error of every voxel's refractivity, temperature and density (beyond the paper)."""

    enabled: bool = param(
        False,
        help="Compute the `refractivity_sigma`, `temperature_sigma` and `density_sigma` arrays (a stage of its "
             "own after the integration, one task per frame). Off by default: it costs about `samples + bias_probes` "
             "tomography solves per frame (docs/uncertainty.md).",
        see="benchmarks/results/uncertainty_coverage.md")
    samples: int = param(
        8, unit="1", ge=0, le=256,
        help="Perturbed solves per frame for the noise term: the flows' noise measured outside the masks, drawn "
             "with the flow window's correlation, each through the frame's own tomography solve and integration. "
             "0 leaves the noise term out (the other terms cost two Poisson solves).")
    prior_samples: bool = param(
        False,
        help="Perturb the solve's priors too (the smoothness and curl terms): the samples are then posterior "
             "samples of the linear-Gaussian model the normal equations define (their variance adds the "
             "regularisation's expected bias to the noise's). Off: the noise term is the spread of the "
             "estimate under the measured noise alone.")
    smoothing: float = param(
        1.0, unit="voxels", ge=0, le=10,
        help="Gaussian width of the local average of the samples' variance (the noise term is a smooth field; "
             "averaging a few voxels lets a few samples estimate it).")
    bias_scale: float = param(
        1.88, unit="1", ge=0, le=100,
        help="Weight of the bias term: the share of a smooth random field the solve and integration lose at each "
             "voxel (`schlieren.pipeline.uncertainty.resolution_loss`) times the estimate's local `|r - r_ambient|`, "
             "larger where the views are few. Costs `bias_probes` solves per frame; 0 leaves it out.",
        see="benchmarks/results/uncertainty_fit.md", tuned=True)
    bias_probes: int = param(
        2, unit="1", ge=1, le=64,
        help="Random fields the bias term probes the regularised inverse with (one tomography solve and two "
             "Poisson solves each).")
    bias_width: float = param(
        2.0, unit="voxels", gt=0, le=20,
        help="Gaussian width of the bias term's random fields: the scale of structure whose loss it measures.")
    bias_smoothing: float = param(
        2.0, unit="voxels", ge=0, le=20,
        help="Gaussian width of the local averages of the bias term (its loss and the estimate's amplitude).")
    boundary_scale: float = param(
        2.0, unit="1", ge=0, le=100,
        help="Weight of the boundary term: the local RMS of the difference between the integration with a "
             "natural boundary on the hull and the pinned one (`schlieren.pipeline.uncertainty."
             "boundary_sensitivity`), the slowly varying error the hull's boundary hides.",
        see="benchmarks/results/uncertainty_fit.md", tuned=True)
    boundary_smoothing: float = param(
        4.0, unit="voxels", ge=0, le=20,
        help="Gaussian width of the boundary term's local RMS.")
    structure_scale: float = param(
        0.0, unit="1", ge=0, le=100,
        help="Weight of the structure term: the local RMS of the estimate's curvature `h^2 lap(r)` "
             "(`schlieren.pipeline.uncertainty.curvature_rms`), the fine structure the prior, the views and the "
             "integration lose. 0: beside the bias term it changes the tune cases' fit by under 3 %.",
        see="benchmarks/results/uncertainty_fit.md", tuned=True)
    structure_smoothing: float = param(
        1.0, unit="voxels", ge=0, le=10,
        help="Gaussian width of the structure term's local RMS.")
    seed: int = param(
        0, unit="1", ge=0, le=2 ** 31 - 1,
        help="Seed of the noise samples (each frame draws from `(seed, frame)`).")
