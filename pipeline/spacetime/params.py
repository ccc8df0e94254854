"""Parameters of the space-time stage (one params class; field names = kernel keywords)."""

from __future__ import annotations

from schlieren.pipeline.params import param, parameters

__all__ = ["SpaceTimeParams"]


@parameters
class SpaceTimeParams:
    """Space-time reconstruction (beyond the paper): each frame from its neighbours too."""

    window: int = param(
        0, unit="frames", ge=0, le=8,
        help="Frames on each side of a frame whose per-frame gradients are moved onto it along the motion and "
             "averaged with it (`schlieren.pipeline.spacetime.average.motion_compensated_mean`); 0 solves every "
             "frame alone (the paper), and the store then holds exactly the per-frame result.",
        see="benchmarks/results/spacetime_i35_st.md")
    neighbour_weight: float = param(
        1.0, unit="1", gt=0, le=1,
        help="Weight of a neighbour at distance `d` frames relative to the frame itself: `neighbour_weight ** d` "
             "(1 = a plain mean over the window).")
    motion_scale: int = param(
        2, unit="1", ge=1, le=4,
        help="The motion between two frames' volumes is estimated on a grid this many times coarser than the "
             "reconstruction's, then interpolated back: the flow's motion is smooth at the voxel scale.")
    motion_levels: int = param(
        3, unit="1", ge=1, le=6,
        help="Pyramid levels of the 3D Lucas-Kanade motion estimate (each halves the resolution; displacements "
             "up to about `motion_scale * 2 ** (levels - 1)` voxels).")
    motion_window: float = param(
        2.0, unit="voxels", gt=0, le=20,
        help="Gaussian window of the motion estimate's structure tensor, in cells of its grid.")
    motion_iterations: int = param(
        3, unit="1", ge=1, le=20,
        help="Warp-and-update steps per pyramid level.")
    motion_reg: float = param(
        0.05, unit="1", gt=0, le=100,
        help="Damping of the motion update where the volumes carry little structure, relative to the mean "
             "structure tensor trace.")
