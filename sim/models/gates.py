# Ref: SPEC.md §4 (complementary gates, dead time, enable, trip); issue 4 item 6
"""Cycle-true golden model of :class:`foc_servo.hdl.gates.Gates`, and an independent checker of
the dead-time rules for recorded gate waveforms."""

import numpy as np

__all__ = ["gates", "check_gates"]


def gates(pwm, dead_time, enable, trip, *, dead_width=8):
    """Gate outputs, clock by clock, for the given inputs.

    Parameters
    ----------
    pwm : array (T, 3) of 0/1
        Levels of phases a, b, c during each clock.
    dead_time, enable, trip : array (T,) of int
        Inputs during each clock.

    Returns
    -------
    high, low : arrays (T, 3) of int64
        Outputs during each clock (the registers' values: the first row is the reset state).
    """
    pwm = np.asarray(pwm, dtype=np.int64).reshape(-1, 3)
    t_len = pwm.shape[0]
    dead = np.maximum(np.asarray(dead_time, dtype=np.int64), 1)
    run = np.asarray(enable, dtype=bool) & ~np.asarray(trip, dtype=bool)
    cap = (1 << dead_width) - 1
    high = np.zeros((t_len, 3), dtype=np.int64)
    low = np.zeros((t_len, 3), dtype=np.int64)
    h = [0, 0, 0]
    lo = [0, 0, 0]
    off = [0, 0, 0]
    prev = [(0, 0)] * 3                         # wanted (high, low) on the previous clock
    for t in range(t_len):
        for k in range(3):
            high[t, k], low[t, k] = h[k], lo[k]
            want = (int(run[t] and pwm[t, k]), int(run[t] and not pwm[t, k]))
            steady = want == prev[k]
            both_off = not h[k] and not lo[k]
            n_off = min(off[k] + 1, cap) if both_off and steady else 0
            if not run[t]:
                h[k], lo[k] = 0, 0
            elif h[k]:
                h[k] = want[0]
            elif lo[k]:
                lo[k] = want[1]
            elif steady and off[k] + 1 >= dead[t]:
                h[k], lo[k] = want
            off[k] = n_off
            prev[k] = want
    return high, low


def check_gates(high, low, dead_time, pwm):
    """Count dead-time rule breaks in recorded waveforms (independent of the design's logic).

    ``high``, ``low``, ``pwm``: (T, 3) per clock; ``dead_time`` (T,) the input per clock. A turn-on
    at clock t must follow at least ``max(dead_time[t−1], 1)`` clocks with both switches off
    (``short_dead``), and the pwm level it follows must have lasted at least that long, up to
    clock t−1 (else a ``runt``: a gate pulse out of a pwm pulse shorter than the dead time).

    Returns
    -------
    dict
        ``overlap`` (clocks with high and low of a phase on together), ``short_dead``, ``runts``.
    """
    high = np.asarray(high, dtype=np.int64).reshape(-1, 3)
    low = np.asarray(low, dtype=np.int64).reshape(-1, 3)
    pwm = np.asarray(pwm, dtype=np.int64).reshape(-1, 3)
    dead = np.maximum(np.asarray(dead_time, dtype=np.int64), 1)
    overlap = int(np.sum(high & low))
    short_dead = 0
    runts = 0
    for k in range(3):
        off_run = 0
        level_run = 0
        for t in range(1, high.shape[0]):
            both_off_prev = not high[t - 1, k] and not low[t - 1, k]
            off_run = off_run + 1 if both_off_prev else 0
            level_run = level_run + 1 if t >= 2 and pwm[t - 1, k] == pwm[t - 2, k] else 1
            on_h = high[t, k] and not high[t - 1, k]
            on_l = low[t, k] and not low[t - 1, k]
            if (on_h or on_l) and off_run < dead[t - 1]:
                short_dead += 1
            if (on_h and (not pwm[t - 1, k] or level_run < dead[t - 1])
                    or on_l and (pwm[t - 1, k] or level_run < dead[t - 1])):
                runts += 1
    return {"overlap": overlap, "short_dead": short_dead, "runts": runts}
