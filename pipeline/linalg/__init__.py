"""Linear solvers shared by the tomography (paper sec. 5) and the Poisson integration (eq. 8).

:class:`ConjugateGradient` is the one conjugate-gradient loop; a problem plugs in its
operator, preconditioner and vector kernels as :class:`CGVectors` (:class:`SerialVectors`:
one column with serial numba updates, :func:`pcg`; :class:`~schlieren.pipeline.linalg.cgls.
CGLSVectors`: least squares through ``A`` and ``A^T``, :func:`cgls`; the tomography's fused
three-column vectors live with its normal equations).
"""

from schlieren.pipeline.linalg.cg import CGResult, CGVectors, ConjugateGradient, SerialVectors, pcg
from schlieren.pipeline.linalg.cgls import CGLSResult, CGLSVectors, cgls

__all__ = ["ConjugateGradient", "CGVectors", "CGResult", "SerialVectors", "pcg", "cgls", "CGLSResult",
           "CGLSVectors"]
