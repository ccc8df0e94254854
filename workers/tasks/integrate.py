"""The ``integrate`` task: one frame's refractivity and the quantities derived from it.

The gradient is integrated inside the hull by the (anisotropic) Poisson solver (paper
eq. 8 and Appendix, :func:`~schlieren.pipeline.poisson.integrate`); density and
temperature follow from the Gladstone-Dale relation (:mod:`schlieren.pipeline.derived`).
"""

from __future__ import annotations

import numpy as np

from schlieren.pipeline import derived, poisson
from schlieren.workers.tasks.run_context import RunContext, solver_receipt

__all__ = ["integrate_task"]


def integrate_task(ctx: RunContext, k: int) -> dict:
    """Frame ``k``'s ``refractivity`` (unless the solve made it), ``density`` and ``temperature``."""
    grad = np.asarray(ctx.store.read("gradient", (k,)), dtype=np.float64)
    hull = ctx.store.read("hull", (k,))
    medium = ctx.session.medium
    if ctx.config.reconstruction == "direct":  # refractivity came out of the solve already
        r = ctx.store.read("refractivity", (k,)).astype(np.float64)
        info = None
    else:
        r, info = poisson.integrate(grad, hull, ctx.session.grid,
                                    r_ambient=medium.refractivity_ambient, params=ctx.config.poisson)
        ctx.store.write("refractivity", (k,), np.asarray(r, dtype=np.float32))
    ctx.store.write("density", (k,), np.asarray(derived.density(r, medium), dtype=np.float32))
    ctx.store.write("temperature", (k,), np.asarray(derived.temperature(r, medium), dtype=np.float32))
    return solver_receipt(info)
