"""One termination status for the engine, the calibration driver and the pipeline.

Every result of pdvc that can stop for more than one reason carries a
:class:`Status` and a message. ``status.success`` is true exactly for the
members with a positive value; the command line's exit code follows it
(``pdvc calibrate`` exits 3 when the calibration did not succeed, after
writing every output).
"""

from __future__ import annotations

import enum

__all__ = ["Status"]


class Status(enum.IntEnum):
    """Why a measurement, a stage or a calibration stopped.

    Positive values are successes, zero and negative ones are not.
    """

    # -- successes ---------------------------------------------------------------
    CONVERGED = 1
    NOISE_FLOOR = 2
    MODES_STAGNATED = 3
    MAX_MODES = 4
    STOPPED_CONTRACTING = 5
    ENTROPY_GUARD = 6
    ROUNDS_DONE = 7
    FIXED_POINT = 8
    CONSISTENCY_GUARD = 9
    ROW_SUMS_GUARD = 10
    AXIS_OFFSET = 11
    NOMINAL_HOLDS = 12
    # -- failures ----------------------------------------------------------------
    MAX_ITER = 0
    NO_DESCENT = -1
    DIVERGED = -2
    WORSE_THAN_NOMINAL = -3
    MOTION_TOO_LARGE = -4
    UNDETERMINED = -5

    @property
    def success(self) -> bool:
        return self.value > 0

    @property
    def message(self) -> str:
        return _MESSAGES[self]

    def __str__(self) -> str:
        return self.name.lower()


_MESSAGES = {
    Status.CONVERGED: "converged: the last step moved the sample points by less than the tolerance on the detector",
    Status.NOISE_FLOOR: "PGD stopped: chi reached the noise floor",
    Status.MODES_STAGNATED: "PGD stopped: the last mode lowered chi by less than min_gain",
    Status.MAX_MODES: "PGD stopped: the maximum number of modes was reached",
    Status.STOPPED_CONTRACTING: "stopped: the rounds no longer contract (what still moves is weakly determined); "
    "the poses before the last round are kept",
    Status.ENTROPY_GUARD: "stopped: the entropy of the reconstruction rose (the data consistency is walking along "
    "weakly determined modes); the poses before the last round are kept",
    Status.ROUNDS_DONE: "done: the stage ran the rounds it was given",
    Status.FIXED_POINT: "stopped: no correlation step lowers chi from the current poses (a fixed point of the loop)",
    Status.CONSISTENCY_GUARD: "stopped: the data consistency of a fresh reconstruction rose above the best of the "
    "stage (the loop passed its best point); the poses with the best consistency are kept",
    Status.ROW_SUMS_GUARD: "stopped: the rounds moved the axis's tilt away from what the row sums of the views say (the "
    "loop walked along the pitch); the poses the row sums agree with best are kept",
    Status.AXIS_OFFSET: "axis offset only: the calibrated geometry could not be confirmed on this region-of-interest "
    "scan; the axis offset measured from opposite views (in parallel beam with its lean in the detector plane, where "
    "they confirm it), which match each other's mirror image better about it than about the nominal axis, is "
    "returned (no per-view motion)",
    Status.NOMINAL_HOLDS: "the nominal geometry holds: the calibration moved the sample points by less than the stages' "
    "tolerance from it, or a little more and predicts the views left out of a reconstruction no better than it (no "
    "motion the data measure); the nominal geometry is returned",
    Status.MAX_ITER: "not converged: the iteration cap was reached while the poses were still moving",
    Status.NO_DESCENT: "not converged: no damped step lowered chi any further; the last accepted poses are kept",
    Status.DIVERGED: "diverged: no round of the stage made the reconstruction fit the data better; "
    "the poses the stage started from are kept",
    Status.WORSE_THAN_NOMINAL: "failed: the calibrated geometry fits the data worse than the nominal one; "
    "the nominal geometry is returned",
    Status.MOTION_TOO_LARGE: "not converged: the motion may be too large for the linearisation",
    Status.UNDETERMINED: "failed: the data cannot tell a calibrated geometry from the nominal one (the nominal fit is "
    "already at the noise, or something the model leaves out can pass for the motion); the nominal geometry is "
    "returned",
}
