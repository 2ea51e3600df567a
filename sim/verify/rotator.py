# Ref: paper eq. (4)–(6) (vector rotation), SPEC.md §2.1; issue 7
"""Gateware :class:`~foc_servo.hdl.rotator.Rotator` against its golden model and the float ideal.

As :mod:`.cordic`: the stimulus lives in a ROM inside a simulation-only wrapper that feeds the
rotator one vector every ``spacing`` clocks (at least the rotator's ``interval``) and writes
every output into a RAM, so the testbench only waits; the outputs are read back once at the end
and compared, bit for bit, with :func:`foc_servo.sim.models.rotator.rotate`, and against
:func:`~foc_servo.sim.models.rotator.rotate_ideal` for the error figures. The corner set is the
CORDIC's (:func:`.cordic.corner_cases`).
"""

import math

import numpy as np

from ...hdl.rotator import Rotator
from ..models.rotator import rotate, rotate_ideal
from .cordic import RotationBench, corner_cases, run_capture

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
        ``mismatches`` (gateware outputs, tag included, differing from the golden model),
        ``vectors``, ``clocks``, ``sim_s`` (wall seconds of simulation), ``clk_per_s``,
        ``latency_clk`` (measured: clocks from the first ``i.valid`` to the first ``o.valid``),
        ``throughput_per_clk`` (outputs per clock between the first and the last output),
        ``max_err_lsb`` and ``rms_err_lsb`` (gateware outputs against the float rotation by the
        quantized angle, clipped to the output range; x and y pooled), ``outputs_missing``.
    """
    dut = Rotator(**params)
    p = dut.params
    spacing = p.interval if spacing is None else spacing
    if not isinstance(spacing, int) or spacing < p.interval:
        raise ValueError(f"spacing must be an integer of at least the interval {p.interval}, "
                         f"not {spacing!r}")
    w, aw, tw = p.width, p.angle_width, p.tag_width
    rng = np.random.default_rng(seed)
    cx, cy, ct = corner_cases(w, aw)
    fs = 1 << (w - 1)
    x = np.concatenate([cx, rng.integers(-fs, fs, count)])
    y = np.concatenate([cy, rng.integers(-fs, fs, count)])
    theta = np.concatenate([ct, rng.integers(0, 1 << aw, count)])
    vectors = len(x)
    tag = rng.integers(0, 1 << tw, vectors) if tw else np.zeros(vectors, dtype=np.int64)

    mask = (1 << w) - 1
    words = [(int(a) & mask) | (int(b) & mask) << w | int(t) << 2 * w | int(g) << (2 * w + aw)
             for a, b, t, g in zip(x, y, theta, tag)]
    bench = RotationBench(dut, words, spacing)

    clocks = (vectors - 1) * spacing + p.latency + 2
    result, gx, gy, gt, sim_s = run_capture(bench, vectors, clocks, w, tw, name="rotator",
                                            progress=progress)
    model = {k: v for k, v in params.items() if k != "tag_width"}
    ex, ey = rotate(x, y, theta, **model)
    produced = result["outputs"]
    mismatches = int(np.count_nonzero((gx != ex) | (gy != ey) | (gt != tag)))
    ix, iy = rotate_ideal(x, y, theta, width=w, angle_width=aw)
    err = np.concatenate([gx - ix, gy - iy])
    span = result["last_out"] - result["first_out"] + spacing
    return {
        "mismatches": mismatches,
        "outputs_missing": vectors - produced,
        "vectors": vectors,
        "clocks": clocks,
        "sim_s": sim_s,
        "clk_per_s": clocks / sim_s,
        "latency_clk": result["first_out"],
        "throughput_per_clk": produced / span if produced else 0.0,
        "max_err_lsb": float(np.max(np.abs(err))),
        "rms_err_lsb": float(math.sqrt(np.mean(err ** 2))),
    }
