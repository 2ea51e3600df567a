# Ref: paper eq. (4)–(6) (vector rotation), SPEC.md §2.1; issue 7
"""Gateware :class:`~foc_servo.hdl.rotator.Rotator` against its golden model and the float ideal.

As :mod:`.cordic`: the stimulus lives in a ROM inside a simulation-only wrapper that feeds the
rotator one vector every ``spacing`` clocks (at least the rotator's ``interval``) and writes
every output into a RAM, so the testbench only waits; the outputs are read back once at the end
and compared, bit for bit, with :func:`foc_servo.sim.models.rotator.rotate`, and against
:func:`~foc_servo.sim.models.rotator.rotate_ideal` for the error figures. The corner set is the
CORDIC's (:func:`.cordic.corner_cases`).
"""

from ...hdl.rotator import Rotator
from ..models.rotator import rotate, rotate_ideal
from .cordic import corner_cases, run_rotation

__all__ = ["run", "corner_cases"]


def run(count=100_000, *, seed=0, spacing=None, progress=False, **params):
    """Simulate :class:`Rotator` on the corner cases plus ``count`` seeded random vectors (x, y,
    θ uniform over their full ranges) fed one every ``spacing`` clocks; compare with the golden
    model.

    Parameters
    ----------
    count : int
        Number of random vectors (the corner cases come on top).
    seed : int
        Seed of the random stimulus.
    spacing : int or None
        Clocks between vectors, at least the rotator's ``interval`` (default).
    progress : bool
        Progress line on stderr.
    **params
        Passed to :class:`Rotator` (``width``, ``angle_width``, ``table_bits``, ``tag_width``).

    Returns
    -------
    dict
        The figures of :func:`.cordic.run` (``mismatches``, ``outputs_missing``, ``vectors``,
        ``clocks``, ``sim_s``, ``clk_per_s``, ``latency_clk``, ``throughput_per_clk``,
        ``max_err_lsb``, ``rms_err_lsb``).
    """
    dut = Rotator(**params)
    p = dut.params
    spacing = p.interval if spacing is None else spacing
    if not isinstance(spacing, int) or spacing < p.interval:
        raise ValueError(f"spacing must be an integer of at least the interval {p.interval}, "
                         f"not {spacing!r}")
    model = {k: v for k, v in params.items() if k != "tag_width"}
    return run_rotation(dut, rotate, rotate_ideal, model, count=count, seed=seed,
                        spacing=spacing, name="rotator", progress=progress)
