# Ref: issue 4 item 7; AD7380-4 data sheet, transfer function (two's complement output coding,
#      LSB = 2·V_REF / 2**16 for the fully differential inputs) and serial interface.
"""Golden model of :class:`foc_servo.hdl.adc.AdcInterface`: which strobes are served and when
their codes come out, and the ideal transfer function of the part.

The interface itself does no arithmetic: the codes of the conversion started ``sample_delay``
clocks after a served strobe appear unchanged on ``o`` ``latency`` clocks after the strobe. A
strobe is served when the interface is idle, i.e. at least ``min_period`` clocks after the last
served strobe; otherwise it is dropped and ``overrun`` pulses.
"""

import numpy as np

__all__ = ["schedule_np", "code_from_volts_np", "volts_from_code_np"]


def schedule_np(strobe_clk, *, min_period, latency):
    """Cycle-true schedule of the interface for strobes at the clocks ``strobe_clk``.

    Parameters
    ----------
    strobe_clk : array of int
        Increasing clock indices of the ``sample`` strobes.
    min_period, latency : int
        The interface's attributes of the same names.

    Returns
    -------
    served : bool array
        Which strobes start a transaction (the others pulse ``overrun``).
    valid_clk : int64 array
        The clock of ``o.valid`` for each served strobe.
    """
    strobe_clk = np.asarray(strobe_clk, dtype=np.int64)
    served = np.zeros(strobe_clk.size, dtype=bool)
    free_at = np.iinfo(np.int64).min
    for k, t in enumerate(strobe_clk.tolist()):     # sequential by nature (a busy flag)
        if t >= free_at:
            served[k] = True
            free_at = t + min_period
    return served, strobe_clk[served] + latency


def code_from_volts_np(v_diff, *, vref=3.3, bits=16):
    """Ideal code of a differential input voltage: two's complement, ``LSB = 2·vref / 2**bits``,
    rounded to nearest (mid-tread), clamped to the code range (the part's output saturates)."""
    lsb = 2.0 * vref / (1 << bits)
    code = np.floor(np.asarray(v_diff, dtype=np.float64) / lsb + 0.5)
    return np.clip(code, -(1 << (bits - 1)), (1 << (bits - 1)) - 1).astype(np.int64)


def volts_from_code_np(code, *, vref=3.3, bits=16):
    """Centre voltage of a code (inverse of :func:`code_from_volts_np` inside the range)."""
    return np.asarray(code, dtype=np.float64) * (2.0 * vref / (1 << bits))
