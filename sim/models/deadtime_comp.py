# Ref: hdl/deadtime_comp.py (module docstring: the trapezoid); hdl/gates.py (dead time)
"""Bit-true golden model of :class:`foc_servo.hdl.deadtime_comp.DeadTimeComp` (numpy int64), and
an independent physical model of what a dead time does to a leg's high time.

:func:`trapezoid` and :func:`apply` are the block's arithmetic, vectorised; :func:`deadtime_comp`
runs it clock by clock (the sequential shifter's timing included). :func:`terminal_high_clocks`
is the physics the compensation answers, computed from the gate waveforms of
:func:`foc_servo.sim.models.gates.gates` and the freewheeling-diode rule, not from the block's
formula.
"""

import numpy as np

from .gates import gates

__all__ = ["trapezoid", "apply", "deadtime_comp", "terminal_high_clocks"]


def _int(x):
    return np.asarray(x, dtype=np.int64)


def trapezoid(current, clocks, shift, symmetric):
    """The corrections ``comp`` (compare counts) for phase currents ``current`` (raw Q1.(w−1)).

    ``k = shift + sym``, ``L = (C + 1) >> 1`` if ``sym`` else ``C``, ``u = i`` for ``i ≥ 0``,
    ``−1 − i`` below, ``comp = ±min(u >> k, L)`` with the sign of ``i``; arrays broadcast.
    """
    i = _int(current)
    k = _int(shift) + _int(symmetric).astype(bool)
    c = _int(clocks)
    lim = np.where(_int(symmetric).astype(bool), (c + 1) >> 1, c)
    neg = i < 0
    mag = np.minimum(np.where(neg, -1 - i, i) >> k, lim)
    return np.where(neg, -mag, mag)


def apply(duty, comp, *, count_width=16):
    """``clip(duty + comp, 0, 2**count_width − 1)`` (the timer clamps to its full scale)."""
    return np.clip(_int(duty) + _int(comp), 0, (1 << count_width) - 1)


def deadtime_comp(phase_valid, phase, duty, symmetric, clocks, shift, *, shift_width=4,
                  count_width=16):
    """The block clock by clock.

    Parameters
    ----------
    phase_valid : array (T,) of 0/1
    phase : array (T, 3) of int
        Phase currents a, b, c during each clock.
    duty : array (T, 3) of int
        ``i.payload`` during each clock.
    symmetric, clocks, shift : array (T,) of int
        Inputs during each clock.
    shift_width, count_width : int
        The block's parameters.

    Returns
    -------
    comp, o : arrays (T, 3) of int64
        ``comp`` and ``o.payload`` during each clock (``comp`` 0 at reset).
    """
    phase_valid = _int(phase_valid)
    phase = _int(phase).reshape(-1, 3)
    duty = _int(duty).reshape(-1, 3)
    t_len = len(phase_valid)
    symmetric, clocks, shift = (np.broadcast_to(_int(x), (t_len,))
                                for x in (symmetric, clocks, shift))
    comp = np.zeros((t_len, 3), dtype=np.int64)
    cur = np.zeros(3, dtype=np.int64)
    pending = []                    # (clock from which comp[phase] takes value, phase, value)
    for t in range(t_len):
        for when, ph, value in pending:
            if when == t:
                cur[ph] = value
        comp[t] = cur
        if phase_valid[t]:
            sym = int(symmetric[t])
            k = int(shift[t]) + sym
            # Loaded at t, k shifts in t+1 … t+k, phase a clamped at t+1+k, b at t+2+k, c at
            # t+3+k (one shared clamp), each negated and loaded a clock later, visible from the
            # clock after that. A new transfer cancels the phases not yet loaded.
            values = trapezoid(phase[t], clocks[t], shift[t], sym)
            pending = [(t + 3 + k + ph, ph, values[ph]) for ph in range(3)]
    o = apply(duty, comp, count_width=count_width)
    return comp, o


def terminal_high_clocks(compare, current_sign, *, half_period, symmetric, dead_time,
                         periods=3):
    """Clocks per period the terminal of a leg is at +U_dc/2, from the gate model.

    A :class:`~foc_servo.hdl.svpwm.PWMTimer` level (``compare`` active every period) drives
    :func:`~foc_servo.sim.models.gates.gates`; while both switches are off the leg current's
    diode sets the terminal: the low one for ``current_sign > 0`` (out of the leg), the high one
    for ``< 0``. Returns the high clocks of the last of ``periods`` periods (the first starts from
    reset).
    """
    n = half_period
    pos = np.arange(2 * n)
    c = int(compare)
    if symmetric:
        c = min(c, n)
        level = (pos + c >= n) & (pos < n + c)
    else:
        level = pos < min(c, 2 * n)
    pwm = np.tile(level.astype(np.int64), periods)
    t_len = len(pwm)
    high, low = gates(np.stack([pwm, pwm, pwm], axis=1), np.full(t_len, dead_time),
                      np.ones(t_len), np.zeros(t_len))
    h, lo = high[:, 0], low[:, 0]
    term = np.where(h == 1, 1, np.where(lo == 1, 0, 1 if current_sign < 0 else 0))
    return int(term[-2 * n:].sum())
