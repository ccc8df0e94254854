"""The ``spacetime`` task: one frame's gradient from the per-frame solutions of its window.

Beyond the paper (its stage is in a run when ``spacetime.window > 0``): the tomography
tasks then write each frame's own solve to ``gradient_frame``, and this task moves the
solutions of frames ``k - W .. k + W`` onto frame ``k`` along their motion and averages them
(:func:`~schlieren.pipeline.spacetime.motion_compensated_mean`) into ``gradient``, which the
integration reads as it reads a per-frame gradient.
"""

from __future__ import annotations

from schlieren.pipeline import spacetime
from schlieren.pipeline.tomography.solve import basis_set, block_support
from schlieren.workers.tasks.run_context import RunContext

__all__ = ["spacetime_task", "per_frame_array"]


def per_frame_array(ctx: RunContext) -> str:
    """The array the tomography tasks write each frame's own solve to: ``gradient_frame``
    when a space-time stage averages them into ``gradient``, else ``gradient`` itself."""
    return "gradient_frame" if ctx.config.spacetime.window > 0 else "gradient"


def spacetime_task(ctx: RunContext, k: int) -> dict:
    """Frame ``k``'s gradient (stored ``gradient``) from ``gradient_frame`` of its window."""
    params = ctx.config.spacetime
    frames = list(spacetime.window_frames(k, ctx.n_frames, params.window))
    volumes = ctx.read_upstream_many("gradient_frame", [(j,) for j in frames])
    dilation = ctx.config.tomography.hull_dilation
    support = basis_set(ctx.store.read("hull", (k,)), dilation)
    region = block_support(ctx.read_upstream_many("hull", [(j,) for j in frames]), dilation)
    grad, info = spacetime.motion_compensated_mean(volumes, [j - k for j in frames], support, params=params,
                                                   region=region)
    ctx.store.write("gradient", (k,), grad)
    return {"frames": list(info.frames), "mean_motion": [round(v, 3) for v in info.mean_motion]}
