# Ref: paper eq. (4)–(6) (CORDIC vector rotation with ±90° pre-rotation), SPEC.md §2.1
"""Bit-true golden model of :class:`foc_servo.hdl.cordic.Cordic`, and the float ideal it
approximates (kept apart: :func:`rotate` is the model, :func:`rotate_ideal` the ideal).

Both take raw integers: x, y in ``signed(width)``, θ as a ``BinaryAngle(angle_width)`` raw value
(any integer; taken modulo a full turn). The constants and widths come from
:class:`~foc_servo.hdl.cordic.CordicParams`, shared with the gateware.
"""

import numpy as np
from amaranth.hdl import signed

from ...hdl.cordic import CordicParams
from ...hdl.fixed import BinaryAngle, round_shift_np, saturate_np, shape_range

__all__ = ["rotate", "rotate_trace", "rotate_ideal"]


def _dtype(p):
    # int64 unless a product x0·C or a z value could exceed it (very wide configurations).
    bits = max(p.width + 1 + p.gain_shift + 1, p.data_width + 1, p.z_width + 1)
    return np.int64 if bits <= 62 else object


def rotate_trace(x, y, theta, **params):
    """Run the model and return every intermediate value (for width checks).

    Parameters
    ----------
    x, y : array_like of int
        Raw ``signed(width)`` components.
    theta : array_like of int
        Raw ``BinaryAngle(angle_width)`` angles.
    **params
        ``width``, ``stages``, ``angle_width``, ``guard_bits`` (as :class:`Cordic`; the pipeline
        parameters ``iterations_per_stage`` and ``tag_width`` are accepted and do not matter).

    Returns
    -------
    dict
        ``x0``, ``y0`` (pre-rotated, ``width + 1`` bits), ``z0``; ``xs``, ``ys`` (lists of
        ``stages + 1`` arrays: the compensated inputs then each iteration's result, ``G`` guard
        bits), ``zs`` (``z_0 … z_{n−1}``, full turn ``2**z_width``), and the outputs ``x``, ``y``.
    """
    p = CordicParams(**params)
    dt = _dtype(p)
    x = np.asarray(x, dtype=np.int64).astype(dt)
    y = np.asarray(y, dtype=np.int64).astype(dt)
    lo, hi = shape_range(signed(p.width))
    if np.any(x < lo) or np.any(x > hi) or np.any(y < lo) or np.any(y > hi):
        raise ValueError(f"Cordic model x and y must be within [{lo}, {hi}] (signed({p.width}))")
    x, y = np.broadcast_arrays(x, y)
    turn = 1 << p.angle_width
    th = np.asarray(theta, dtype=np.int64) % turn
    th = np.where(th >= turn // 2, th - turn, th).astype(dt)       # signed reading, [−π, π)
    th = np.broadcast_to(th, x.shape)

    # Pre-rotation by s·90°, s = sgn(θ) with sgn(0) = +1.
    s = np.where(th >= 0, 1, -1).astype(dt)
    x0, y0 = -s * y, s * x
    z = (th << p.angle_guard_bits) - s * (1 << (p.z_width - 2))

    # Gain compensation: round_shift(v·C, F − G), half away from zero.
    shift = p.gain_shift - p.guard_bits
    xi = np.asarray(round_shift_np(x0 * p.gain_constant, shift), dtype=dt)
    yi = np.asarray(round_shift_np(y0 * p.gain_constant, shift), dtype=dt)
    trace = {"x0": x0, "y0": y0, "z0": z, "xs": [xi], "ys": [yi], "zs": []}

    for i in range(p.stages):
        trace["zs"].append(z)
        d = np.where(z >= 0, 1, -1).astype(dt)
        xi, yi = xi - d * (yi >> i), yi + d * (xi >> i)
        z = z - d * p.atan[i]
        trace["xs"].append(xi)
        trace["ys"].append(yi)

    trace["x"] = np.asarray(saturate_np(round_shift_np(xi, p.guard_bits),
                                        signed(p.width))).astype(np.int64)
    trace["y"] = np.asarray(saturate_np(round_shift_np(yi, p.guard_bits),
                                        signed(p.width))).astype(np.int64)
    return trace


def rotate(x, y, theta, **params):
    """Bit-true model of :class:`~foc_servo.hdl.cordic.Cordic`: ``(x', y')`` as int64 arrays.

    Same arguments as :func:`rotate_trace`.
    """
    t = rotate_trace(x, y, theta, **params)
    return t["x"], t["y"]


def rotate_ideal(x, y, theta, *, width=16, angle_width=None):
    """Float64 rotation by the quantized angle ``θ_raw·2π/2**angle_width``, clipped to the
    ``signed(width)`` range (saturation being the intended behaviour). Not rounded."""
    angle_width = width if angle_width is None else angle_width
    th = BinaryAngle(angle_width).to_rad(np.asarray(theta, dtype=np.int64))
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    c, s = np.cos(th), np.sin(th)
    lo, hi = shape_range(signed(width))
    return np.clip(x * c - y * s, lo, hi), np.clip(x * s + y * c, lo, hi)
