# Ref: SPEC.md §2.3 (paper Fig. 6), M/T speed D_n = k·ΔM/ΔT: the divider.
"""Bit-true golden model of :class:`foc_servo.hdl.divider.Divider`.

Vectorised over numpy arrays: int64 while both widths are at most 62 bits, Python integers
(``dtype=object``) beyond. The quotient truncates toward zero (Python's ``//`` floors, so the
model divides magnitudes and fixes the signs, as the hardware does).
"""

import numpy as np
from amaranth.hdl import signed, unsigned

from ...hdl.divider import divider_params
from ...hdl.fixed import saturate_np, shape_range

__all__ = ["divide", "latency"]


def _dtype(width, divisor_width):
    return np.int64 if max(width, divisor_width) <= 62 else object


def _operand(name, value, shape, dtype):
    v = np.asarray(value)
    if v.dtype != object and not np.issubdtype(v.dtype, np.integer):
        raise TypeError(f"Divider {name} must be an integer array, not {v.dtype}")
    v = v.astype(dtype)
    lo, hi = shape_range(shape)
    if np.any(v < lo) or np.any(v > hi):
        bad = v[(v < lo) | (v > hi)].flat[0]
        raise ValueError(f"Divider {name} {int(bad)} is outside the range [{lo}, {hi}] "
                         f"of {shape!r}")
    return v


def divide(dividend, divisor, *, width=32, divisor_width=None, signed=True, quotient_width=None):
    """Model of one division per element.

    Parameters
    ----------
    dividend : int or array of int
        In the range of ``S(width)`` (``S`` = ``signed`` or ``unsigned`` per ``signed``).
    divisor : int or array of int
        In the range of ``S(divisor_width)``; broadcast against ``dividend``.
    width, divisor_width, signed, quotient_width :
        As for :class:`~foc_servo.hdl.divider.Divider`.

    Returns
    -------
    quotient, remainder, div0, ovf : arrays (or ints for scalar operands)
        The :attr:`Divider.o` payload fields; ``div0`` and ``ovf`` are 0 or 1.

    Raises
    ------
    TypeError
        If a parameter is invalid (as for :class:`Divider`) or an operand is not an integer.
    ValueError
        If an operand is outside its range.
    """
    p = divider_params(width=width, divisor_width=divisor_width, signed=signed,
                       quotient_width=quotient_width)
    width, divisor_width, signed = p["width"], p["divisor_width"], p["signed"]
    shape = _shape(signed)
    q_shape = shape(p["quotient_width"])
    dtype = _dtype(width, divisor_width)
    n = _operand("dividend", dividend, shape(width), dtype)
    d = _operand("divisor", divisor, shape(divisor_width), dtype)
    n, d = np.broadcast_arrays(n, d)

    div0 = d == 0
    n_mag = np.abs(n)
    d_mag = np.where(div0, 1, np.abs(d)).astype(dtype)
    q_mag = n_mag // d_mag                  # magnitudes: floor == truncation
    r_mag = n_mag - q_mag * d_mag
    neg_n = n < 0
    neg_q = neg_n != (d < 0)
    q = np.where(neg_q, -q_mag, q_mag).astype(dtype)
    r = np.where(neg_n, -r_mag, r_mag).astype(dtype)

    q_lo, q_hi = shape_range(q_shape)
    ovf = ~div0 & (q > q_hi)                # signed: only min / -1; unsigned: a narrow quotient
    q = np.asarray(saturate_np(q, q_shape), dtype=dtype)
    r = np.where(ovf, 0, r)
    q = np.where(div0, np.where(neg_n, q_lo, q_hi), q).astype(dtype)
    r = np.where(div0, 0, r).astype(dtype)
    out = (q, r, div0.astype(np.int64), ovf.astype(np.int64))
    if np.ndim(dividend) == 0 and np.ndim(divisor) == 0:
        return tuple(int(x) for x in out)
    return out


def latency(quotient_width):
    """Clocks from accepting the operands to a valid result (see :attr:`Divider.latency`):
    ``quotient_width + 2`` (the quotient width is the dividend width unless narrowed)."""
    return quotient_width + 2


def _shape(is_signed):
    return signed if is_signed else unsigned
