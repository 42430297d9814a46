"""Incremental solve of a GTSAM factor graph with iSAM2: new factors and variables are folded into the Bayes tree,
and only the cliques they touch are re-eliminated, so a new keyframe costs about the same whatever the graph size
and a loop costs what the part of the graph it moves costs (Kaess et al., iSAM2, IJRR 2012).

`Sim3PoseGraph` (worker.loop.pose_graph) owns the graph and keeps the batch Levenberg-Marquardt solve as the
reference; this module only wraps the solver state.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam


@dataclass
class IncrementalStep:
    """What one `IncrementalSolver.solve` call did: iSAM2 updates run and variables relinearised in total."""

    updates: int
    relinearized: int


class IncrementalSolver:
    """iSAM2 with Gauss-Newton steps, relinearising every update any variable whose step exceeds
    `relinearize_threshold` (tangent-space norm: radians, map units, log-scale)."""

    def __init__(self, relinearize_threshold: float = 0.001) -> None:
        if relinearize_threshold <= 0:
            raise ValueError(f"relinearize_threshold must be positive, got {relinearize_threshold}")
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(relinearize_threshold)
        params.relinearizeSkip = 1
        self.isam = gtsam.ISAM2(params)
        self.keys: set[int] = set()

    def __contains__(self, key: int) -> bool:
        return key in self.keys

    def factors(self) -> gtsam.NonlinearFactorGraph:
        """Every factor added so far (iSAM2's own graph, not a copy)."""
        return self.isam.getFactorsUnsafe()

    def estimate(self) -> gtsam.Values:
        """The current estimate of every variable (empty before the first solve)."""
        return self.isam.calculateEstimate() if self.keys else gtsam.Values()

    def solve(self, factors: gtsam.NonlinearFactorGraph, values: gtsam.Values, max_updates: int = 50
              ) -> IncrementalStep:
        """Add `factors` and the new variables' initial `values`, then update until no variable needs
        relinearising (the Gauss-Newton iteration has converged) or `max_updates` updates ran."""
        if max_updates < 1:
            raise ValueError(f"max_updates must be >= 1, got {max_updates}")
        result = self.isam.update(factors, values)
        self.keys.update(int(k) for k in values.keys())
        updates, relinearized = 1, 0
        while updates < max_updates:
            result = self.isam.update()
            updates += 1
            changed = result.getVariablesRelinearized()
            relinearized += changed
            if changed == 0:
                break
        return IncrementalStep(updates, relinearized)
