# Ref: paper eq. (1); SPEC.md §1 (Clarke transform) and §2 (current scaling, host-set gain/offset)
"""Phase-current scaling and Clarke transform, fully pipelined.

Per sample, with ``x`` each measured phase::

    i_x   = sat(round_shift(gain_x · (code_x − offset_x), gain_format.frac))
    two-phase:    α = i_a,  β = sat(round_shift((i_a + 2·i_b) · K, F)),  c = sat(−i_a − i_b)
    three-phase:  α = sat(round_shift((2·i_a − i_b − i_c) · K3, F)),
                  β = sat(round_shift((i_b − i_c) · K, F))

with ``K = round(2**F / √3)``, ``K3 = round(2**F / 3)`` and ``F = width + 2``; ``round_shift``
rounds half away from zero and ``sat`` clamps to ``signed(width)`` (see :mod:`.fixed`).
"""

import math

from amaranth.hdl import Const, Module, Shape, Signal, signed
from amaranth.lib import data, stream, wiring
from amaranth.lib.wiring import In, Out

from .dsp import MUL_WIDTH, check_mul_width, partial_sum, registered_products, saturate_bits
from .fixed import Q, QFormat, check_bool, round_shift

__all__ = ["Clarke", "clarke_constants"]


def clarke_constants(width):
    """Fixed-point constants of the Clarke transform for outputs of ``width`` bits.

    Returns ``(frac, k_beta, k_alpha)``: ``frac = F = width + 2``, ``k_beta = round(2**F / √3)``
    and ``k_alpha = round(2**F / 3)``, both computed exactly in integers (neither quotient is
    ever a tie). With ``F = width + 2`` the constants' error is below 0.25 output LSB over the
    whole input range. For β, ``|i_a + 2·i_b| ≤ 3·2**(width-1)`` gives at most
    ``3·2**(width-1) · 0.5 / 2**F = 3/16`` LSB; for the three-phase α,
    ``|2·i_a − i_b − i_c| ≤ 2**(width+1)`` gives at most ``2**(width+1) · (1/3) / 2**F = 1/6``
    LSB (``2**F mod 3`` is 1 or 2, so the rounding error of ``K3`` is exactly 1/3); for the
    three-phase β, ``|i_b − i_c| ≤ 2**width`` gives at most 1/8 LSB.
    """
    frac = width + 2
    # Nearest integer to sqrt(4**F / 3): n = floor, then n + 1 if (n + 1/2)**2 < 4**F / 3.
    n = math.isqrt((1 << (2 * frac)) // 3)
    k_beta = n + 1 if 3 * (2 * n + 1) ** 2 < (1 << (2 * frac + 2)) else n
    k_alpha = ((1 << frac) + 1) // 3
    return frac, k_beta, k_alpha


class Clarke(wiring.Component):
    """Phase-current scaling (gain and offset per phase) followed by the Clarke transform.

    One sample per clock; each stage's data registers load only when that stage holds a valid
    sample, so ``o.payload`` keeps the last valid result between samples. The gains and offsets
    are sampled together with the codes, on the clock ``i.valid`` is high: changing them never
    corrupts a sample already in the pipeline.

    Parameters
    ----------
    width : int
        Width ``w`` of the output currents, 8 … 28 bits. All outputs are Q1.(w−1) of the current
        full scale.
    adc_shape : Shape
        Shape ``signed(n)`` (two's complement codes) or ``unsigned(n)`` (straight binary codes) of
        the raw ADC codes, ``n`` = 2 … 24 bits.
    gain_format : QFormat
        Signed format of the gains, in current LSB per ADC LSB (``Q(18, 15)``: −4 … 4 − 2**−15),
        2 … 32 bits, ``0 ≤ frac ≤ 62``.
    three_phase : bool
        Three measured phases (α from all three, zero sequence rejected) instead of two
        (``i_c = −i_a − i_b``).
    mul_width : int
        Signed operand width of the target's hard multiplier, 8 … 25, or ``None`` (:mod:`~.dsp`:
        18 ECP5 / Xilinx; ``None`` iCE40: products not split). The products are split into
        partial products that fit it; the results do not depend on it.

    Members
    -------
    i : In(stream.Signature(data.StructLayout({"a": adc_shape, "b": adc_shape[, "c": adc_shape]}),
        always_ready=True))
        Raw ADC codes; ``"c"`` only when ``three_phase``.
    gain_a, gain_b[, gain_c] : In(gain_format.shape)
        Scale of each phase, ``gain_format`` (signed: a negative gain inverts a sensor's polarity).
    offset_a, offset_b[, offset_c] : In(signed(n + 1))
        Zero-current code of each phase, in ADC LSB (covers every code of a signed or unsigned ADC).
    o : Out(stream.Signature(data.StructLayout({"a", "b", "c", "alpha", "beta": signed(w)}),
        always_ready=True))
        Scaled phase currents ``a``, ``b``, ``c`` (in two-phase mode ``c = sat(−a − b)``, in
        three-phase mode the scaled measurement) for the over-current protection, and i_α, i_β.
        All Q1.(w−1), rounded half away from zero, saturated (never wrapped).

    Attributes
    ----------
    latency : int
        Clocks from ``i.valid`` to the matching ``o.valid`` (6).
    const_frac : int
        ``F = width + 2``, fractional bits of the Clarke constants.
    k_beta : int
        ``round(2**F / √3)``.
    k_alpha : int or None
        ``round(2**F / 3)`` in three-phase mode, else ``None``.

    Raises
    ------
    TypeError
        A parameter of the wrong type or outside its basic range.
    ValueError
        An unsigned ``gain_format``.
    """

    latency = 6

    def __init__(self, *, width=16, adc_shape=signed(16), gain_format=Q(18, 15),
                 three_phase=False, mul_width=MUL_WIDTH):
        if not isinstance(width, int) or isinstance(width, bool) or not 8 <= width <= 28:
            raise TypeError(f"Clarke width must be an integer from 8 to 28, not {width!r}")
        if not isinstance(adc_shape, Shape):
            raise TypeError(f"Clarke adc_shape must be a Shape such as signed(16), "
                            f"not {adc_shape!r}")
        adc = adc_shape
        if not 2 <= adc.width <= 24:
            raise TypeError(f"Clarke adc_shape must be 2 to 24 bits wide, not {adc_shape!r}")
        if not isinstance(gain_format, QFormat):
            raise TypeError(f"Clarke gain_format must be a QFormat, not {gain_format!r}")
        if not gain_format.signed:
            raise ValueError(f"Clarke gain_format must be signed, not {gain_format!r}")
        if not 2 <= gain_format.width <= 32 or not 0 <= gain_format.frac <= 62:
            raise TypeError(f"Clarke gain_format must be 2 to 32 bits wide with 0 to 62 "
                            f"fractional bits, not {gain_format!r}")
        check_bool("Clarke", "three_phase", three_phase)

        self._mul_width = check_mul_width("Clarke", mul_width)
        self._width = width
        self._adc_shape = adc
        self._gain_format = gain_format
        self._three_phase = three_phase
        self._const_frac, self._k_beta, k_alpha = clarke_constants(width)
        self._k_alpha = k_alpha if three_phase else None

        phases = self.phases
        members = {
            "i": In(stream.Signature(data.StructLayout({p: adc for p in phases}),
                                     always_ready=True)),
            "o": Out(stream.Signature(
                data.StructLayout({n: signed(width) for n in ("a", "b", "c", "alpha", "beta")}),
                always_ready=True)),
        }
        for p in phases:
            members[f"gain_{p}"] = In(gain_format.shape)
        for p in phases:
            members[f"offset_{p}"] = In(signed(adc.width + 1))
        super().__init__(members)

    width = property(lambda self: self._width)
    adc_shape = property(lambda self: self._adc_shape)
    gain_format = property(lambda self: self._gain_format)
    three_phase = property(lambda self: self._three_phase)
    mul_width = property(lambda self: self._mul_width)
    const_frac = property(lambda self: self._const_frac)
    k_beta = property(lambda self: self._k_beta)
    k_alpha = property(lambda self: self._k_alpha)

    @property
    def phases(self):
        """Names of the measured phases: ``"ab"`` or ``"abc"``."""
        return "abc" if self._three_phase else "ab"

    def elaborate(self, platform):
        m = Module()
        w = self._width
        n = self._adc_shape.width
        out = signed(w)
        phases = self.phases
        frac_c = self._const_frac

        valid = [self.i.valid]
        for k in range(1, self.latency + 1):
            v = Signal(name=f"valid{k}")
            m.d.sync += v.eq(valid[-1])
            valid.append(v)
        m.d.comb += self.o.valid.eq(valid[-1])

        # Stage 1: exact offset removal (n + 2 bits); gain sampled with the code.
        d1 = {p: Signal(signed(n + 2), name=f"diff_{p}") for p in phases}
        g1 = {p: Signal(self._gain_format.shape, name=f"gain1_{p}") for p in phases}
        with m.If(valid[0]):
            for p in phases:
                m.d.sync += [
                    d1[p].eq(self.i.payload[p] - getattr(self, f"offset_{p}")),
                    g1[p].eq(getattr(self, f"gain_{p}")),
                ]

        # Stage 2: exact product (gain width + n + 2 bits) as registered partial products, each
        # one hard multiplier (hdl/dsp.py): their sum is left to stage 3.
        p2 = {p: registered_products(m, g1[p], d1[p], enable=valid[1], name=f"prod_{p}",
                                     mul_width=self._mul_width)
              for p in phases}

        # Stage 3: scaled phase currents, Q1.(w-1), rounded and saturated.
        i3 = {p: Signal(out, name=f"i_{p}") for p in phases}
        with m.If(valid[2]):
            m.d.sync += [i3[p].eq(saturate_bits(round_shift(partial_sum(p2[p]),
                                                            self._gain_format.frac), out))
                         for p in phases]

        # Stage 4: the Clarke sums (exact), and i_c.
        a4, b4, c4 = (Signal(out, name=f"{p}4") for p in "abc")
        s_beta4 = Signal(signed(w + 2))
        with m.If(valid[3]):
            m.d.sync += [a4.eq(i3["a"]), b4.eq(i3["b"])]
            if self._three_phase:
                m.d.sync += [c4.eq(i3["c"]), s_beta4.eq(i3["b"] - i3["c"])]
            else:
                m.d.sync += [c4.eq(saturate_bits(-i3["a"] - i3["b"], out)),
                             s_beta4.eq(i3["a"] + (i3["b"] << 1))]
        if self._three_phase:
            s_alpha4 = Signal(signed(w + 2))
            with m.If(valid[3]):
                m.d.sync += s_alpha4.eq((i3["a"] << 1) - i3["b"] - i3["c"])

        # Stage 5: products by the constants (registered partial products).
        a5, b5, c5 = (Signal(out, name=f"{p}5") for p in "abc")
        with m.If(valid[4]):
            m.d.sync += [a5.eq(a4), b5.eq(b4), c5.eq(c4)]
        m_beta5 = registered_products(m, s_beta4, Const(self._k_beta), enable=valid[4],
                                      name="m_beta", mul_width=self._mul_width)
        if self._three_phase:
            m_alpha5 = registered_products(m, s_alpha4, Const(self._k_alpha), enable=valid[4],
                                           name="m_alpha", mul_width=self._mul_width)

        # Stage 6: sum, round and saturate to Q1.(w-1).
        a6, b6, c6, alpha6, beta6 = (Signal(out, name=f"{p}6")
                                     for p in ("a", "b", "c", "alpha", "beta"))
        with m.If(valid[5]):
            m.d.sync += [a6.eq(a5), b6.eq(b5), c6.eq(c5),
                         beta6.eq(saturate_bits(round_shift(partial_sum(m_beta5), frac_c), out))]
            if self._three_phase:
                m.d.sync += alpha6.eq(saturate_bits(round_shift(partial_sum(m_alpha5), frac_c),
                                                    out))
            else:
                m.d.sync += alpha6.eq(a5)

        m.d.comb += [
            self.o.payload.a.eq(a6),
            self.o.payload.b.eq(b6),
            self.o.payload.c.eq(c6),
            self.o.payload.alpha.eq(alpha6),
            self.o.payload.beta.eq(beta6),
        ]
        return m
