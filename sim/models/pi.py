# Ref: paper eq. (7)–(9); SPEC.md §2.2
"""Bit-true golden model of :class:`foc_servo.hdl.pi.PI` (equations in ``hdl/pi.py``).

The regulator is stateful (integrator, previous error), so the model steps one sample at a time;
it uses the numpy helpers of ``hdl/fixed.py`` (``saturate_np``, ``clamp_np``, ``round_shift_np``)
so rounding and saturation are those of the gateware, and checks every intermediate value against
the widths the gateware declares (:func:`foc_servo.hdl.pi.pi_widths`), so a too-narrow register
shows up as an :exc:`OverflowError` here rather than as a silent wrap there.
"""

from amaranth.hdl import signed

from ...hdl.fixed import UQ, clamp_np, round_shift_np, saturate_np, shape_range
from ...hdl.pi import pi_widths

__all__ = ["PIModel"]


class PIModel:
    """Tustin PI regulator, bit-true to :class:`foc_servo.hdl.pi.PI`.

    Parameters
    ----------
    width, kp_format, kx_format, int_guard
        As for :class:`foc_servo.hdl.pi.PI` (same validation and messages).

    Attributes
    ----------
    integrator : int
        Integrator state ``I``, raw Q1.(width-1+int_guard).
    e_prev : int
        Previous error ``E[n−1]``, raw Q1.(width-1).
    last : dict
        Details of the last :meth:`step`: ``e``, ``p``, ``di``, ``u``, ``out``, ``sat``,
        ``clamped`` (``I + dI`` was outside the limits), ``held`` (conditional integration kept
        ``I``).
    """

    def __init__(self, *, width=16, kp_format=UQ(16, 8), kx_format=UQ(16, 16), int_guard=8):
        widths = pi_widths(width, kp_format, kx_format, int_guard)
        # Ranges of the inputs and of every intermediate value (checked on each step).
        self._ranges = {name: shape_range(signed(bits)) for name, bits in widths.items()}
        self._ranges.update({name: shape_range(signed(width))
                             for name in ("ref", "fb", "lim_lo", "lim_hi")})
        self._ranges["kp"] = shape_range(kp_format.shape)
        self._ranges["kx"] = shape_range(kx_format.shape)
        self._shape = signed(width)
        self.width = width
        self.kp_format = kp_format
        self.kx_format = kx_format
        self.int_guard = int_guard
        self.integrator = 0
        self.e_prev = 0
        self.last = None

    def clear(self):
        """Model of the ``clear`` input: integrator and previous error to zero."""
        self.integrator = 0
        self.e_prev = 0
        self.last = None

    def _fits(self, name, value):
        lo, hi = self._ranges[name]
        if not lo <= value <= hi:
            raise OverflowError(f"PI {name} {value} is outside [{lo}, {hi}]")
        return value

    def step(self, ref, fb, kp, kx, lim_lo, lim_hi):
        """One accepted sample; returns ``(out, sat)`` as the gateware's ``o.payload``, ``sat``.

        All arguments are raw integers: ``ref``, ``fb``, ``lim_lo``, ``lim_hi`` signed(width),
        ``kp`` and ``kx`` in their formats.
        """
        g, sw = self.int_guard, self._shape
        ref, fb = self._fits("ref", int(ref)), self._fits("fb", int(fb))
        lim_lo, lim_hi = self._fits("lim_lo", int(lim_lo)), self._fits("lim_hi", int(lim_hi))
        kp, kx = self._fits("kp", int(kp)), self._fits("kx", int(kx))

        e = saturate_np(ref - fb, sw)
        prod_p = self._fits("prod_p", kp * e)
        prod_x = self._fits("prod_x", kx * (e + self.e_prev))
        self.e_prev = e
        p = self._fits("p", round_shift_np(prod_p, self.kp_format.frac - g))
        di = self._fits("di", round_shift_np(prod_x, self.kx_format.frac - g))
        lo_g, hi_g = lim_lo << g, lim_hi << g
        i_sum = self._fits("sum_i", self.integrator + di)
        i_c = self._fits("integrator", clamp_np(i_sum, lo_g, hi_g))
        u_c = self._fits("u", round_shift_np(p + i_c, g))
        hold = (u_c > lim_hi and di > 0) or (u_c < lim_lo and di < 0)
        if not hold:
            self.integrator = i_c
        u = self._fits("u", round_shift_np(p + self.integrator, g))
        out = saturate_np(clamp_np(u, lim_lo, lim_hi), sw)
        sat = int(u > lim_hi or u < lim_lo)
        self.last = {"e": e, "p": p, "di": di, "u": u, "out": out, "sat": sat,
                     "clamped": i_sum != i_c, "held": hold}
        return out, sat
