# Ref: paper eq. (1); SPEC.md §1 (Clarke transform) and §2 (current scaling)
"""Bit-true golden model of :class:`foc_servo.hdl.clarke.Clarke` (numpy int64, vectorised).

The gateware samples gains and offsets together with each code, so the model is stateless: output
``k`` is a function of input ``k`` alone. Rounding (half away from zero) and saturation come from
the same helpers of :mod:`foc_servo.hdl.fixed` as the gateware's. The Clarke constants are
computed here independently of the gateware (in floating point, exact for these widths).
"""

import numpy as np
from amaranth.hdl import signed

from ...hdl.fixed import round_shift_np, saturate_np

__all__ = ["clarke_constants", "clarke"]


def clarke_constants(width):
    """``(F, K, K3)`` with ``F = width + 2``, ``K = round(2**F/√3)``, ``K3 = round(2**F/3)``."""
    frac = width + 2
    return frac, int(np.rint(2.0 ** frac / np.sqrt(3.0))), int(np.rint(2.0 ** frac / 3.0))


def clarke(code_a, code_b, code_c=None, *, gain_a, gain_b, gain_c=None,
           offset_a, offset_b, offset_c=None, width=16, gain_frac=15, three_phase=False):
    """Scaled phase currents and i_α, i_β for arrays of codes (values, not raw bits).

    Parameters
    ----------
    code_a, code_b, code_c : array of int
        ADC codes as integers (already sign-extended for a signed ADC); ``code_c`` only when
        ``three_phase``.
    gain_a, gain_b, gain_c : int or array of int
        Raw gains, ``gain_frac`` fractional bits.
    offset_a, offset_b, offset_c : int or array of int
        Offsets in ADC LSB.
    width : int
        Output width ``w``; all outputs Q1.(w−1).
    gain_frac : int
        Fractional bits of the gain format.
    three_phase : bool

    Returns
    -------
    dict
        ``"a"``, ``"b"``, ``"c"``, ``"alpha"``, ``"beta"``: int64 arrays; ``"saturated"``: bool
        array, true where any scaling or Clarke result was clamped.
    """
    out = signed(width)
    frac, k_beta, k_alpha = clarke_constants(width)
    codes = [code_a, code_b] + ([code_c] if three_phase else [])
    gains = [gain_a, gain_b] + ([gain_c] if three_phase else [])
    offsets = [offset_a, offset_b] + ([offset_c] if three_phase else [])
    saturated = np.zeros(np.broadcast(*codes).shape, dtype=bool)

    def sat(v):
        nonlocal saturated
        s = saturate_np(v, out)
        saturated = saturated | (s != v)
        return np.asarray(s, dtype=np.int64)

    i = [sat(round_shift_np(np.asarray(g, dtype=np.int64) *
                            (np.asarray(x, dtype=np.int64) - np.asarray(o, dtype=np.int64)),
                            gain_frac))
         for x, g, o in zip(codes, gains, offsets)]
    if three_phase:
        a, b, c = i
        alpha = sat(round_shift_np((2 * a - b - c) * k_alpha, frac))
        beta = sat(round_shift_np((b - c) * k_beta, frac))
    else:
        a, b = i
        c = sat(-a - b)
        alpha = a
        beta = sat(round_shift_np((a + 2 * b) * k_beta, frac))
    return {"a": a, "b": b, "c": c, "alpha": alpha, "beta": beta, "saturated": saturated}
