# Ref: SPEC.md §2.3 (paper Fig. 6), M/T speed D_n = k·ΔM/ΔT: the divider.
"""Sequential (multicycle) integer divider with stream interfaces.

Restoring shift-subtract division on magnitudes, one quotient bit per clock, then a sign fix:
the quotient is truncated toward zero and the remainder takes the dividend's sign (C99), so
``dividend == quotient * divisor + remainder`` and ``|remainder| < |divisor|``. Division by zero
and the one signed overflow (``min / -1``) saturate and are flagged; nothing wraps. The latency
is the same for every operand pair, division by zero included, so its users' timing is fixed.

An unsigned divider may compute fewer quotient bits than the dividend has (``quotient_width``):
a quotient that needs more saturates. The test for it is one comparison before the first step,
``dividend >> quotient_width >= divisor`` (the restoring division's own first ``width −
quotient_width`` steps would give zero quotient bits and leave exactly ``dividend >>
quotient_width`` as partial remainder), and the division then takes ``quotient_width`` clocks.
"""

from amaranth.hdl import Cat, Module, Mux, Signal, signed, unsigned
from amaranth.lib import data, stream, wiring
from amaranth.lib.wiring import In, Out

from .fixed import check_bool, saturate, shape_range

__all__ = ["Divider", "divider_params"]


def divider_params(*, width=32, divisor_width=None, signed=True, quotient_width=None):
    """Validate the parameters of :class:`Divider` (its golden model and verification use this
    too) and return them as a dict, ``divisor_width`` and ``quotient_width`` resolved.

    Raises
    ------
    TypeError
        If ``width`` or ``divisor_width`` is not an integer of at least 2, ``signed`` is not a
        bool, or ``quotient_width`` is not an integer from 2 to ``width``.
    ValueError
        If ``quotient_width`` is narrower than ``width`` for a signed divider.
    """
    if not isinstance(width, int) or isinstance(width, bool) or width < 2:
        raise TypeError(f"Divider width must be an integer of at least 2, not {width!r}")
    if divisor_width is None:
        divisor_width = width
    elif (not isinstance(divisor_width, int) or isinstance(divisor_width, bool)
            or divisor_width < 2):
        raise TypeError(f"Divider divisor_width must be None or an integer of at least 2, "
                        f"not {divisor_width!r}")
    check_bool("Divider", "signed", signed)
    if quotient_width is None:
        quotient_width = width
    elif (not isinstance(quotient_width, int) or isinstance(quotient_width, bool)
            or not 2 <= quotient_width <= width):
        raise TypeError(f"Divider quotient_width must be None or an integer from 2 to width "
                        f"{width}, not {quotient_width!r}")
    if signed and quotient_width != width:
        raise ValueError(f"Divider quotient_width must equal width {width} for a signed divider, "
                         f"not {quotient_width!r}")
    return {"width": width, "divisor_width": divisor_width, "signed": signed,
            "quotient_width": quotient_width}


class Divider(wiring.Component):
    """Sequential divider: ``quotient = trunc(dividend / divisor)``, C99 remainder.

    Both operands are integers (or fixed-point values with the same number of fractional bits;
    the quotient is then an integer and the remainder has the operands' format). Shapes below
    write ``S(n)`` for ``signed(n)`` if ``signed`` else ``unsigned(n)``.

    Parameters
    ----------
    width : int
        Width of the dividend and of the quotient, in bits; at least 2.
    divisor_width : int or None
        Width of the divisor and of the remainder, in bits; at least 2. ``None`` means ``width``.
    signed : bool
        Two's-complement (default) or unsigned operands and results.
    quotient_width : int or None
        Width of the quotient, 2 … ``width``; ``None`` means ``width``. Narrower only for an
        unsigned divider: quotients of ``2**quotient_width`` or more saturate (``ovf``).

    Members
    -------
    i : In(stream.Signature(data.StructLayout({"dividend": S(width), "divisor": S(divisor_width)})))
        Operands. ``i.ready`` is high while the divider is idle; a transfer starts a division.
    o : Out(stream.Signature(data.StructLayout({"quotient": S(quotient_width),
        "remainder": S(divisor_width), "div0": unsigned(1), "ovf": unsigned(1)})))
        Result, :attr:`latency` clocks after the transfer on ``i``. ``o.valid`` and the payload
        are held until ``o.ready``; the divider is idle (``i.ready``) from the next clock on.

        * ``quotient``: ``dividend / divisor`` truncated toward zero.
        * ``remainder``: ``dividend - quotient * divisor``; sign of the dividend, ``|r| < |d|``.
        * ``div0``: the divisor was zero. Then ``remainder = 0`` and ``quotient`` saturates with
          the sign of the dividend: the largest value of ``S(width)`` if ``dividend >= 0``, else
          the smallest (signed); all ones (unsigned). ``ovf`` is 0.
        * ``ovf``: the quotient does not fit ``S(quotient_width)``; ``quotient`` saturates to its
          largest value, ``remainder = 0``. Signed: only ``min(S(width)) / -1``, whose quotient
          ``2**(width-1)`` does not fit. Unsigned: a quotient of ``2**quotient_width`` or more
          (never when ``quotient_width == width``).

    Attributes
    ----------
    latency : int
        ``quotient_width + 2``, whatever the operands: with the transfer on ``i`` (``i.valid``
        and ``i.ready`` high) in clock ``t``, ``o.valid`` is high from clock ``t + latency`` (the
        project's latency convention): one clock per quotient bit, one for the sign fix, one
        for the output register. With ``o.ready`` held high and operands always offered, one
        division every ``latency + 1 = quotient_width + 3`` clocks.

    Raises
    ------
    TypeError
        If ``width`` or ``divisor_width`` is not an integer of at least 2, ``signed`` is not a
        bool, or ``quotient_width`` is not an integer from 2 to ``width``.
    ValueError
        If ``quotient_width`` is narrower than ``width`` for a signed divider.
    """

    def __init__(self, *, width=32, divisor_width=None, signed=True, quotient_width=None):
        params = divider_params(width=width, divisor_width=divisor_width, signed=signed,
                                quotient_width=quotient_width)
        width, divisor_width, signed = params["width"], params["divisor_width"], params["signed"]
        self._width = width
        self._divisor_width = divisor_width
        self._signed = signed
        self._quotient_width = params["quotient_width"]
        shape = _shape_factory(signed)
        self._i_layout = data.StructLayout({
            "dividend": shape(width),
            "divisor": shape(divisor_width),
        })
        self._o_layout = data.StructLayout({
            "quotient": shape(self._quotient_width),
            "remainder": shape(divisor_width),
            "div0": unsigned(1),
            "ovf": unsigned(1),
        })
        super().__init__({
            "i": In(stream.Signature(self._i_layout)),
            "o": Out(stream.Signature(self._o_layout)),
        })

    width = property(lambda self: self._width)
    divisor_width = property(lambda self: self._divisor_width)
    signed = property(lambda self: self._signed)
    quotient_width = property(lambda self: self._quotient_width)

    @property
    def latency(self):
        return self._quotient_width + 2

    @property
    def i_layout(self):
        """Payload layout of :attr:`i`."""
        return self._i_layout

    @property
    def o_layout(self):
        """Payload layout of :attr:`o`."""
        return self._o_layout

    def elaborate(self, platform):
        m = Module()
        w, dw = self._quotient_width, self._divisor_width     # w: quotient bits computed
        q_shape = self._o_layout["quotient"].shape
        q_min, q_max = shape_range(q_shape)

        count = Signal(range(w))         # quotient bits still to compute, minus one
        # Working register `acc` = Cat(quo, rem). `quo` starts as the low `w` bits of |dividend|,
        # `rem` as the rest (0 unless quotient_width < width); each clock shifts the top bit of
        # `quo` into the partial remainder `rem` and one quotient bit in at the bottom, so after
        # `w` clocks `quo` = |quotient| and `rem` = |remainder|. Invariant `rem < dmag` keeps `rem`
        # in `dw` bits; with dmag == 0 or a quotient too wide the partial remainder is
        # meaningless (its top bits are dropped) and the output is overridden.
        acc = Signal(w + dw)
        quo, rem = acc[:w], acc[w:]
        # What else the division needs, latched at the start.
        op = Signal(data.StructLayout({
            "dmag": dw,         # |divisor|
            "neg_n": 1,         # dividend < 0: sign of the remainder
            "neg_q": 1,         # operand signs differ: sign of the quotient
            "div0": 1,          # divisor == 0
            "wide": 1,          # (unsigned) quotient >= 2**quotient_width, or divisor == 0
        }))

        dividend = self.i.payload.dividend
        divisor = self.i.payload.divisor

        # Restoring step: trial = 2·rem + next dividend bit (< 2·dmag, dw + 1 bits).
        trial = acc[w - 1:]
        diff = trial - op.dmag                  # unsigned dw + 2 bits: top bit set iff trial < dmag
        fits = ~diff[-1]

        with m.FSM():
            with m.State("IDLE"):
                m.d.comb += self.i.ready.eq(1)
                with m.If(self.i.valid):
                    if self._signed:
                        n_neg, d_neg = dividend < 0, divisor < 0
                        m.d.sync += [
                            # -min(S(w)) = 2**(w-1) fits the unsigned w-bit magnitude; same for dw.
                            acc.eq(Mux(n_neg, -dividend, dividend)[:w]),
                            op.dmag.eq(Mux(d_neg, -divisor, divisor)),
                            op.neg_n.eq(n_neg),
                            op.neg_q.eq(n_neg ^ d_neg),
                        ]
                    else:
                        # With w < width the dividend's top bits land in `rem` (dropped beyond
                        # dw bits: then they are >= divisor and `wide` is set).
                        m.d.sync += [
                            acc.eq(dividend),
                            op.dmag.eq(divisor),
                            op.neg_n.eq(0),
                            op.neg_q.eq(0),
                        ]
                        if w < self._width:
                            m.d.sync += op.wide.eq(dividend[w:] >= divisor)
                    m.d.sync += [
                        op.div0.eq(divisor == 0),
                        count.eq(w - 1),
                    ]
                    m.next = "BUSY"

            with m.State("BUSY"):               # one quotient bit per clock, MSB first
                m.d.sync += [
                    acc.eq(Cat(fits, quo[:-1], Mux(fits, diff, trial)[:dw])),
                    count.eq(count - 1),
                ]
                with m.If(count == 0):
                    m.next = "FIX"

            with m.State("FIX"):                # signs, saturation, flags
                p = self.o.payload
                if self._signed:
                    # |quotient| <= 2**(w-1): only +2**(w-1) (min / -1) exceeds the range.
                    quotient = saturate(Mux(op.neg_q, -quo, quo), q_shape)
                    # |remainder| < |divisor| <= 2**(dw-1): the slice cannot lose bits.
                    remainder = Mux(op.neg_n, -rem, rem)[:dw]
                    ovf = ~op.neg_q & quo[-1]
                else:
                    quotient, remainder, ovf = quo, rem, op.wide
                    if w < self._width:
                        quotient = Mux(op.wide, q_max, quo)
                with m.If(op.div0):
                    m.d.sync += [
                        p.quotient.eq(Mux(op.neg_n, q_min, q_max)),
                        p.remainder.eq(0),
                        p.div0.eq(1),
                        p.ovf.eq(0),
                    ]
                with m.Else():
                    m.d.sync += [
                        p.quotient.eq(quotient),
                        p.remainder.eq(Mux(ovf, 0, remainder)),
                        p.div0.eq(0),
                        p.ovf.eq(ovf),
                    ]
                m.next = "DONE"

            with m.State("DONE"):               # hold the result until it is taken
                m.d.comb += self.o.valid.eq(1)
                with m.If(self.o.ready):
                    m.next = "IDLE"

        return m


def _shape_factory(is_signed):
    return signed if is_signed else unsigned
