"""Stage 3: the global cadastral-line bundle adjustment (paper section 2.3, eq. 3).

``residuals`` holds the two residual kinds (corner-to-vertical-line distance
and ``dist_z`` of facade edges) with analytic Jacobians for every supported
COLMAP camera model; ``solver`` assembles them, fixes the vertical gauge per
linked component and runs a Levenberg-Marquardt with the heights eliminated
by the Schur complement; ``synthetic_problem`` makes problems with exact
ground truth for tests and the benchmark.
"""

from .solver import (
    BundleOptions,
    BundleProblem,
    BundleResult,
    BundleSummary,
    image_components,
    solve_bundle,
)

__all__ = [
    "BundleOptions",
    "BundleProblem",
    "BundleResult",
    "BundleSummary",
    "image_components",
    "solve_bundle",
]
