# Ref: paper eq. (7)–(9); SPEC.md §2.2 (Tustin PI, output saturation, anti-windup)
"""Tustin (bilinear) PI regulator with output saturation and anti-windup.

Per accepted sample ``n`` (paper eq. (7)–(9), with the integrator kept ``g = int_guard`` fraction
bits finer than the output)::

    E[n]  = sat_sub(ref, fb, signed(W))                                    Q1.(W-1), like ref/fb
    P[n]  = round_shift(kp · E[n], kp_format.frac − g)                     integrator precision
    dI[n] = round_shift(kx · (E[n] + E[n−1]), kx_format.frac − g)          integrator precision
    I_c   = clamp(I[n−1] + dI[n], lim_lo · 2**g, lim_hi · 2**g)            (a) integrator clamp
    U_c   = round_shift(P[n] + I_c, g)                                     output candidate
    hold  = (U_c > lim_hi and dI[n] > 0) or (U_c < lim_lo and dI[n] < 0)   (b) conditional integr.
    I[n]  = I[n−1] if hold else I_c
    U     = round_shift(P[n] + I[n], g)                                    O[n] = P[n] + I[n]
    O[n]  = saturate(clamp(U, lim_lo, lim_hi), signed(W));  sat = (U > lim_hi) or (U < lim_lo)

Rounding is half away from zero (``fixed.round_shift``); nothing wraps. ``round_shift`` of a
``b``-bit signed value by ``s`` bits needs ``r(b, s) = max(b − s + 1, 2)`` bits for ``s > 0`` and
``b − s`` for ``s ≤ 0``; the register widths follow from it (``W = width``, ``g = int_guard``,
``kpw``/``kxw`` the gain widths)::

    E, E[n−1]        signed(W)
    E + E[n−1]       signed(W + 1)
    kp · E           signed(kpw + W)          (signed or unsigned gain)
    kx · (E + E[n−1]) signed(kxw + W + 1)
    P                signed(r(kpw + W, kp_format.frac − g))
    dI               signed(r(kxw + W + 1, kx_format.frac − g))
    I + dI           signed(max(W + g, width(dI)) + 1)
    I, I_c           signed(W + g)            (always within [lim_lo, lim_hi] · 2**g, see `clamp`)
    U_c, U           signed(r(max(width(P), W + g) + 1, g))

Anti-windup: (a) keeps ``I`` inside the output limits (the paper's rule); (b) stops integrating
while the output is pinned and ``dI`` would push it further, so ``I`` does not wind up behind a
large ``P`` either; since ``hold`` only blocks growth towards the violated limit, the output
leaves the limit on the first sample whose error has the other sign (as soon as
``round(P + I)`` is back inside). ``I`` is held, not clamped, by (b), and (a) is the backstop
(it binds e.g. with ``kp = 0``).

Schedule (clock 0 = the cycle ``i`` is accepted; one register stage per clock, each at most one
hard multiplier or one carry chain deep, for 100 MHz on an ECP5)::

    0  E
    1  kp·E, kx·E, kx·E[n−1] as registered partial products (hdl/dsp.py); E[n−1] ← E;
       [E + E[n−1] < 0]
    2  P, dI (rounded with the sign known from the factors); lim·2**g − I; thresholds of the
       output comparisons                                                  (limits from here)
    3  I + dI, I + dI ≷ lim·2**g (as dI ≷ lim·2**g − I); P + I for I = I[n−1], hi·2**g,
       lo·2**g, I + dI
    4  I_c (selected); U_c, U with I[n−1] and their comparisons with the limits, made on
       P + I: ``round_shift(x, g) > H ⇔ x ≥ (H + 1)·2**g − 2**(g−1) + [x < 0]``
    5  hold, I, O (clamped by selection: the saturation to signed(W) is a no-op), sat
    6  o.valid, i.ready

``lim_lo`` and ``lim_hi`` are read from clock 2 on (the speed loop updates its limits from the
feed-forward in clock 2). Pipeline invariants are asserted in the design (one sample in flight,
each stage's registers consistent with the integrator and the limits): they make the limit proof
of ``boards/prove.py`` inductive.

The unit is sequential, so one multiplier could serve all products through an operand mux
(``latency`` and ``interval`` + 2, one multiplier and a wider mux instead of three).
"""


from amaranth.hdl import Assert, Cat, Module, Mux, Signal, signed
from amaranth.lib import data, stream, wiring
from amaranth.lib.wiring import In, Out

from .dsp import (MUL_WIDTH, check_mul_width, partial_sum, registered_products,
                  round_shift_signed, saturate_bits)
from .fixed import is_int, QFormat, UQ, round_shift

__all__ = ["PI", "pi_widths", "round_shift_width"]


def round_shift_width(width, shift):
    """Width of the signed result of :func:`~.fixed.round_shift` on a ``signed(width)`` value.

    Exact: the rounded value of any operand fits (a positive value can round up to
    ``2**(width-1-shift)``)."""
    if shift <= 0:
        return width - shift
    return max(width - shift + 1, 2)


class PI(wiring.Component):
    """Tustin PI regulator with output saturation and anti-windup (module docstring: equations).

    Sequential: one sample in flight at a time, ``latency`` clocks from acceptance to ``o.valid``;
    ``i.ready`` is high while idle (and while ``clear`` is high).

    Parameters
    ----------
    width : int
        Width of ``ref``, ``fb``, the error, the limits and the output, all Q1.(width-1).
    kp_format : QFormat
        Format of the proportional gain ``kp`` (signed or unsigned); ``UQ(16, 8)`` is 0 … 255.996.
    kx_format : QFormat
        Format of the integral gain ``kx`` = K_i·T_s/2 of the Tustin form; ``UQ(16, 16)`` is
        0 … 0.99998.
    int_guard : int
        Extra fraction bits ``g`` of the integrator (and of ``P``) below the output LSB, so that
        small ``kx·E`` contributions accumulate instead of rounding away.
    mul_width : int
        Signed operand width of the target's hard multiplier, 8 … 25, or ``None`` (:mod:`~.dsp`:
        18 ECP5 / Xilinx; ``None`` iCE40: products not split). The products are split into
        partial products that fit it; the results do not depend on it.

    Members
    -------
    i : In(stream.Signature(StructLayout({"ref": signed(width), "fb": signed(width)})))
        Reference and feedback, Q1.(width-1). ``E = sat_sub(ref, fb)`` saturates to signed(width).
    o : Out(stream.Signature(signed(width), always_ready=True))
        Output ``O``, Q1.(width-1), clamped to [lim_lo, lim_hi]; ``o.payload`` holds its value
        between strobes (0 after reset and after ``clear``).
    kp : In(kp_format.shape)
        Proportional gain, raw ``kp_format``.
    kx : In(kx_format.shape)
        Integral gain, raw ``kx_format``.
    lim_lo, lim_hi : In(signed(width))
        Output limits, Q1.(width-1). With ``lim_lo > lim_hi`` the results follow
        :func:`~.fixed.clamp` (``lim_hi`` above ``lim_hi``, else ``lim_lo``): defined, not useful.
    clear : In(1)
        While high: integrator and ``E[n−1]`` are zeroed, a computation in flight is abandoned
        (no strobe), ``o.payload`` and ``sat`` become 0, and inputs are accepted and dropped.
    sat : Out(1)
        The last output was clamped to a limit; updates with ``o.valid``.
    integrator : Out(signed(width + int_guard))
        The integrator state ``I``, Q1.(width-1+int_guard), for observation.

    ``kp`` and ``kx`` are used on the first clock after acceptance, ``lim_lo``/``lim_hi`` until
    ``o.valid``: gains and limits must be stable from acceptance to ``o.valid`` (the register file
    updates them only at loop boundaries, when the regulator is idle).

    Attributes
    ----------
    latency : int
        Clocks from the cycle an input is accepted to the cycle ``o.valid`` is high.
    interval : int
        Minimum clocks between accepted inputs (``i.ready`` rises with ``o.valid``).

    Raises
    ------
    TypeError
        If ``width`` is not an integer of at least 4, a format is not a :class:`QFormat`, or
        ``int_guard`` is not a non-negative integer.
    ValueError
        If an intermediate product would exceed 62 bits (limit of the int64 golden model).
    """

    def __init__(self, *, width=16, kp_format=UQ(16, 8), kx_format=UQ(16, 16), int_guard=8,
                 mul_width=MUL_WIDTH):
        widths = pi_widths(width, kp_format, kx_format, int_guard)
        self._mul_width = check_mul_width("PI", mul_width)
        self._width = width
        self._kp_format = kp_format
        self._kx_format = kx_format
        self._int_guard = int_guard
        self._widths = widths
        super().__init__({
            "i": In(stream.Signature(data.StructLayout({
                "ref": signed(width),
                "fb": signed(width),
            }))),
            "o": Out(stream.Signature(signed(width), always_ready=True)),
            "kp": In(kp_format.shape),
            "kx": In(kx_format.shape),
            "lim_lo": In(signed(width)),
            "lim_hi": In(signed(width)),
            "clear": In(1),
            "sat": Out(1),
            "integrator": Out(signed(width + int_guard)),
        })

    width = property(lambda self: self._width)
    kp_format = property(lambda self: self._kp_format)
    kx_format = property(lambda self: self._kx_format)
    int_guard = property(lambda self: self._int_guard)
    mul_width = property(lambda self: self._mul_width)
    latency = property(lambda self: 6)
    interval = property(lambda self: 6)

    @property
    def widths(self):
        """Widths of the internal values (dict, see the module docstring for the formulas)."""
        return dict(self._widths)

    def elaborate(self, platform):
        m = Module()
        w, g = self._width, self._int_guard
        wd = self._widths
        kpf, kxf = self._kp_format, self._kx_format

        e = Signal(signed(w))
        e_prev = Signal(signed(w))
        es_neg = Signal()                   # E[n] + E[n−1] < 0
        p = Signal(signed(wd["p"]))
        di = Signal(signed(wd["di"]))
        integ = Signal(signed(w + g))
        i_c = Signal(signed(w + g))
        wx = max(wd["p"], w + g) + 1        # P + I (any I within the limits)
        hi_r = Signal(signed(w + g + 1))    # hi·2**g − I
        lo_r = Signal(signed(w + g + 1))    # lo·2**g − I
        gt = Signal()                       # I + dI > hi·2**g
        lt = Signal()                       # I + dI < lo·2**g
        x_k, x_hi, x_lo, x_s = (Signal(signed(wx), name=n) for n in ("x_k", "x_hi", "x_lo", "x_s"))
        u_c = Signal(signed(wd["u"]))
        u_k = Signal(signed(wd["u"]))
        above = {k: Signal(name=f"above_{k}") for k in "ck"}     # U > lim_hi
        below = {k: Signal(name=f"below_{k}") for k in "ck"}     # U < lim_lo
        t_hi = Signal(signed(w + g + 2))    # U > lim_hi ⇔ P + I ≥ t_hi + [P + I < 0]
        t_lo = Signal(signed(w + g + 2))    # U ≥ lim_lo ⇔ P + I ≥ t_lo + [P + I < 0]
        lo_g = Signal(signed(w + g))
        hi_g = Signal(signed(w + g))
        half = (1 << (g - 1)) if g > 0 else 0

        # One valid bit per stage; stage k's registers load when stage k-1 is valid.
        stage = [Signal(name=f"stage{k}") for k in range(1, self.latency)]
        busy = Signal()
        m.d.comb += busy.eq(Cat(*stage).any())
        m.d.comb += [
            self.i.ready.eq(~busy | self.clear),
            self.integrator.eq(integ),
            lo_g.eq(self.lim_lo << g),
            hi_g.eq(self.lim_hi << g),
        ]
        accept = self.i.valid & self.i.ready & ~self.clear
        m.d.sync += stage[0].eq(accept)
        for prev, cur in zip(stage, stage[1:]):
            m.d.sync += cur.eq(prev)
        m.d.sync += self.o.valid.eq(stage[-1])
        # Clock 0 (acceptance): saturated error.
        with m.If(accept):
            m.d.sync += e.eq(saturate_bits(self.i.payload.ref - self.i.payload.fb, signed(w)))
        # Clock 1: products as registered partial products (one hard multiplier each),
        # kx·(E + E[n−1]) as kx·E + kx·E[n−1]; E[n] becomes E[n−1] for the next sample.
        mw = self._mul_width
        prod_p = registered_products(m, self.kp, e, enable=stage[0], name="prod_p", mul_width=mw)
        prod_x = (registered_products(m, self.kx, e, enable=stage[0], name="prod_x", mul_width=mw)
                  + registered_products(m, self.kx, e_prev, enable=stage[0], name="prod_xp",
                                        mul_width=mw))
        with m.If(stage[0]):
            m.d.sync += [e_prev.eq(e), es_neg.eq((e + e_prev)[-1])]
        # Clock 2: products rounded to integrator precision (a product's sign is its factors'),
        # the integrator's distances to the limits and the thresholds of the output comparisons
        # (the limits are read from this clock on).
        t_hi_v = ((self.lim_hi + 1) << g) - half
        t_lo_v = (self.lim_lo << g) - half
        kp_neg = self.kp[-1] if kpf.signed else 0
        kx_neg = self.kx[-1] if kxf.signed else 0
        with m.If(stage[1]):
            m.d.sync += [
                p.eq(round_shift_signed(partial_sum(prod_p), kpf.frac - g, e[-1] ^ kp_neg)),
                di.eq(round_shift_signed(partial_sum(prod_x), kxf.frac - g, es_neg ^ kx_neg)),
                hi_r.eq(hi_g - integ),
                lo_r.eq(lo_g - integ),
                t_hi.eq(t_hi_v),
                t_lo.eq(t_lo_v),
            ]
        # Clock 3: I + dI and its comparisons with the limits (a): I_c = clamp(I + dI,
        # lo·2**g, hi·2**g) is selected in clock 4; P + I for each of the three cases of I_c
        # and for the kept integrator.
        i_sum = Signal(signed(wd["sum_i"]))
        with m.If(stage[2]):
            m.d.sync += [
                gt.eq(di > hi_r),
                lt.eq(di < lo_r),
                i_sum.eq(integ + di),
                x_k.eq(p + integ),
                x_hi.eq(p + hi_g),
                x_lo.eq(p + lo_g),
                x_s.eq(p + integ + di),
            ]
        # Clock 4: output candidates U = round_shift(P + I, g) with the new and with the kept
        # integrator, and their comparisons with the limits, made on P + I against thresholds
        # (u > H ⇔ x ≥ (H + 1)·2**g − 2**(g−1) + [x < 0]) so that they do not wait for U.
        x_c = Mux(gt, x_hi, Mux(lt, x_lo, x_s))
        with m.If(stage[3]):
            m.d.sync += i_c.eq(Mux(gt, hi_g, Mux(lt, lo_g, i_sum)))
        for k, x, u in (("c", x_c, u_c), ("k", x_k, u_k)):
            neg = x[-1] if g > 0 else 0
            with m.If(stage[3]):
                m.d.sync += [
                    u.eq(round_shift_signed(x, g, neg)),
                    above[k].eq(Mux(neg, x > t_hi, x >= t_hi)),
                    below[k].eq(Mux(neg, x <= t_lo, x < t_lo)),
                ]
        # Clock 5: conditional integration (b), output clamp, strobe on the next clock. A
        # clamped U is within [lim_lo, lim_hi] ⊂ signed(w): the saturation is a truncation.
        hold = (above["c"] & (di > 0)) | (below["c"] & di[-1])
        clamp_c = Mux(above["c"], self.lim_hi, Mux(below["c"], self.lim_lo, u_c[:w]))
        clamp_k = Mux(above["k"], self.lim_hi, Mux(below["k"], self.lim_lo, u_k[:w]))
        with m.If(stage[4]):
            m.d.sync += [
                integ.eq(Mux(hold, integ, i_c)),
                self.o.payload.eq(Mux(hold, clamp_k, clamp_c)),
                self.sat.eq(Mux(hold, above["k"] | below["k"], above["c"] | below["c"])),
            ]

        # Invariants of the pipeline (checked in every simulation; they make the limit proof
        # of boards/prove.py inductive): one sample in flight, and each stage's registers are
        # what the module docstring's equations give for the integrator and limits of now
        # (limits stable from clock 2 to o.valid, integrator changed only in clock 5).
        s_all = Cat(*stage)
        i_new = integ + di
        clamped = Mux(i_new > hi_g, hi_g, Mux(i_new < lo_g, lo_g, i_new))
        m.d.comb += Assert((s_all & (s_all - 1)) == 0, "PI: two samples in flight")
        with m.If(stage[2]):
            m.d.comb += [Assert((hi_r == hi_g - integ) & (lo_r == lo_g - integ),
                                "PI: limit distances stale")]
        with m.If(stage[2] | stage[3]):
            m.d.comb += Assert((t_hi == t_hi_v) & (t_lo == t_lo_v), "PI: thresholds stale")
        with m.If(stage[3] | stage[4]):
            m.d.comb += [
                Assert((gt == (i_new > hi_g)) & (lt == (i_new < lo_g)) & (i_sum == i_new),
                       "PI: integrator sum inconsistent"),
                Assert((x_k == p + integ) & (x_hi == p + hi_g) & (x_lo == p + lo_g) &
                       (gt | lt | (x_s == p + i_new)), "PI: output sums inconsistent"),
            ]
        with m.If(stage[4]):
            m.d.comb += Assert(i_c == clamped, "PI: integrator candidate inconsistent")
            for k, x, u in (("c", p + i_c, u_c), ("k", p + integ, u_k)):
                m.d.comb += Assert((u == round_shift(x, g)) & (above[k] == (u > self.lim_hi)) &
                                   (below[k] == (u < self.lim_lo)),
                                   f"PI: output candidate {k} inconsistent")

        with m.If(self.clear):
            m.d.sync += [s.eq(0) for s in stage]
            m.d.sync += [
                self.o.valid.eq(0),
                self.o.payload.eq(0),
                self.sat.eq(0),
                integ.eq(0),
                e_prev.eq(0),
            ]
        return m


def pi_widths(width, kp_format, kx_format, int_guard):
    """Validate the :class:`PI` parameters and return the widths of its internal values.

    Shared with the golden model, which checks every intermediate value against these widths.

    Returns
    -------
    dict
        ``prod_p``, ``prod_x``, ``p``, ``di``, ``integrator``, ``sum_i`` (``I + dI``) and ``u``
        (``U_c``, ``U``), in bits, all signed; formulas in the module docstring.
    """
    if not is_int(width) or width < 4:
        raise TypeError(f"PI width must be an integer of at least 4, not {width!r}")
    if not isinstance(kp_format, QFormat):
        raise TypeError(f"PI kp_format must be a QFormat, not {kp_format!r}")
    if not isinstance(kx_format, QFormat):
        raise TypeError(f"PI kx_format must be a QFormat, not {kx_format!r}")
    if not is_int(int_guard) or int_guard < 0:
        raise TypeError(f"PI int_guard must be a non-negative integer, not {int_guard!r}")
    widths = {
        "prod_p": kp_format.width + width,
        "prod_x": kx_format.width + width + 1,
        "integrator": width + int_guard,
    }
    widths["p"] = round_shift_width(widths["prod_p"], kp_format.frac - int_guard)
    widths["di"] = round_shift_width(widths["prod_x"], kx_format.frac - int_guard)
    widths["sum_i"] = max(widths["integrator"], widths["di"]) + 1
    widths["u"] = round_shift_width(max(widths["p"], widths["integrator"]) + 1, int_guard)
    widest = max(widths.values())
    if widest > 62:
        raise ValueError(f"PI parameters need a {widest}-bit intermediate value; at most 62 bits "
                         f"are supported (width {width}, kp_format {kp_format!r}, kx_format "
                         f"{kx_format!r}, int_guard {int_guard})")
    return widths
