# Ref: paper eq. (4)–(6) (Park / inverse Park as a vector rotation), SPEC.md §2.1; issue 7
"""Bit-true golden model of :class:`foc_servo.hdl.rotator.Rotator`, and the float ideal it
approximates (kept apart: :func:`rotate` is the model, :func:`rotate_ideal` the ideal).

The model follows the arithmetic of the module docstring of :mod:`foc_servo.hdl.rotator`
(fold, table, interpolation, rotation by the integer sine and cosine at scale ``2**W``), not the
gateware's two-pass schedule: the gateware's offset, sign and rounding decomposition is checked
against this plain form by the tests. Both take raw integers: x, y in ``signed(width)``, θ as a
``BinaryAngle(angle_width)`` raw value (any integer; taken modulo a full turn). The constants
come from :class:`~foc_servo.hdl.rotator.RotatorParams`, shared with the gateware.
"""

import numpy as np
from amaranth.hdl import signed

from ...hdl.fixed import round_shift_np, saturate_np, shape_range
from ...hdl.rotator import RotatorParams
from .cordic import rotate_ideal  # the same ideal rotation for both rotators

__all__ = ["rotate", "rotate_trace", "trig", "rotate_ideal"]


def trig(theta, **params):
    """The integer sine and cosine the rotator multiplies by (scale ``2**width``).

    Parameters
    ----------
    theta : array_like of int
        Raw ``BinaryAngle(angle_width)`` angles.
    **params
        ``width``, ``angle_width``, ``table_bits`` (as :class:`Rotator`; ``tag_width`` is
        accepted and does not matter).

    Returns
    -------
    dict
        ``k``, ``d`` (table index, interpolation step), ``kd``, ``s_o``, ``c_o`` (the
        multiplier operands, signed ``width``), ``s_t``, ``c_t`` (sin a and cos a of the octant
        angle at scale ``2**W``), ``sin``, ``cos`` (sinθ and cosθ at scale ``2**W``, signed),
        ``swap``, ``neg_c``, ``neg_s`` (the folding flags).
    """
    p = RotatorParams(**params)
    w, aw, mb, g = p.width, p.angle_width, p.interp_bits, p.interp_guard
    th = np.asarray(theta, dtype=np.int64) % (1 << aw)
    q = th >> (aw - 2)
    mu = (th >> (aw - 3)) & 1
    k = (th >> mb) & ((1 << p.table_bits) - 1)
    k = np.where(mu == 1, k ^ ((1 << p.table_bits) - 1), k)
    low = th & ((1 << mb) - 1)
    d = np.where(mu == 1, (1 << mb) - low, low)
    kd = np.asarray(p.kd, dtype=np.int64)[d]

    s2 = np.asarray(p.table_s, dtype=np.int64)[k]
    c2 = np.asarray(p.table_c, dtype=np.int64)[k]
    c_hi = (c2 >> 4) + (1 << (w - 2))
    s_hi = (s2 >> 3) + (1 << (w - 2))
    s_o = ((s2 << g) + ((kd * c_hi) >> p.shift_c)) >> (g + 2)
    c_o = ((c2 << g) - ((kd * s_hi) >> p.shift_s)) >> (g + 2)
    s_t = s_o + (1 << (w - 1))
    c_t = c_o + (1 << w)

    swap = (q & 1) ^ mu
    neg_c = (q & 1) ^ (q >> 1)
    neg_s = q >> 1
    cos = np.where(swap == 1, s_t, c_t) * (1 - 2 * neg_c)
    sin = np.where(swap == 1, c_t, s_t) * (1 - 2 * neg_s)
    return {"k": k, "d": d, "kd": kd, "s_o": s_o, "c_o": c_o, "s_t": s_t, "c_t": c_t,
            "sin": sin, "cos": cos, "swap": swap, "neg_c": neg_c, "neg_s": neg_s}


def rotate_trace(x, y, theta, **params):
    """Run the model and return every intermediate value (for range checks).

    Parameters
    ----------
    x, y : array_like of int
        Raw ``signed(width)`` components.
    theta : array_like of int
        Raw ``BinaryAngle(angle_width)`` angles.
    **params
        As :func:`trig`.

    Returns
    -------
    dict
        The entries of :func:`trig`, plus ``sigma_x``, ``sigma_y`` (the exact sums at scale
        ``2**W``) and the outputs ``x``, ``y``.
    """
    p = RotatorParams(**params)
    x = np.asarray(x, dtype=np.int64)
    y = np.asarray(y, dtype=np.int64)
    lo, hi = shape_range(signed(p.width))
    if np.any(x < lo) or np.any(x > hi) or np.any(y < lo) or np.any(y > hi):
        raise ValueError(f"Rotator model x and y must be within [{lo}, {hi}] "
                         f"(signed({p.width}))")
    x, y, theta = np.broadcast_arrays(x, y, np.asarray(theta, dtype=np.int64))
    t = trig(theta, **params)
    t["sigma_x"] = x * t["cos"] - y * t["sin"]
    t["sigma_y"] = x * t["sin"] + y * t["cos"]
    for name in ("x", "y"):
        t[name] = np.asarray(saturate_np(round_shift_np(t[f"sigma_{name}"], p.width),
                                         signed(p.width)), dtype=np.int64)
    return t


def rotate(x, y, theta, **params):
    """Bit-true model of :class:`~foc_servo.hdl.rotator.Rotator`: ``(x', y')`` as int64
    arrays. Same arguments as :func:`rotate_trace`."""
    t = rotate_trace(x, y, theta, **params)
    return t["x"], t["y"]
