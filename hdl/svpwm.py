# Ref: SPEC.md §2.4 (paper Fig. 7, SVPWM with a/symmetric config bit) and §2.5 (DC-bus compensation)
"""DC-bus compensation, space-vector modulation and the PWM timer with shadowed duties.

Signal chain (one computation per PWM period)::

    u_α, u_β ──► DCBusCompensation ──► SVPWM ──► PWMTimer ──► Gates (hdl/gates.py)
                 × U_rated / U_dc        duties    shadowed      dead time, enable, trip
                                         (counts)  compares

**Modulation method.** :class:`SVPWM` uses *min–max zero-sequence injection*, which is
mathematically identical to the textbook sector + dwell-time (T1, T2, T0/2 split) formulation; the
golden model implements both in integers and the tests assert they agree bit for bit. With
``A = u_α`` and ``S = u_β/√3`` (modulation indices as fractions of (2/3)·U_dc), the phase voltages,
in units of U_dc and up to a common mode that does not matter, are ``q = (A, S, −S)``: their
differences are the line-to-line voltages ``A − S``, ``2S``, ``A + S``. With
``spread = max(q) − min(q)`` (the largest line-to-line voltage, equal to the textbook ``T1 + T2``)
and ``D = max(spread, 1)``, the duty of phase ``x`` is ``1/2 + (q_x − (max + min)/2) / D``: plain
min–max injection inside the hexagon (``spread ≤ 1``, ``D = 1``), and outside it the whole vector
divided by ``spread``, which puts it on the hexagon's edge *along its own angle* (no phase error).
In counts of the full scale ``scale``::

    count_x = floor((scale · N_x + D) / (2·D)),   N_x = D + 2·q_x − max(q) − min(q) ∈ [0, 2·D]

i.e. ``scale · N_x / (2·D)`` rounded half up, in ``[0, scale]``. Each duty is within half a count
of the exact value for the represented command, so every duty difference (the line-to-line
volt-seconds) is within one count of it; against the real-valued command add at most
``scale · 2**-22`` for the rounding of ``u_β/√3`` (0.0006 count at ``scale = 2500``).
"""

import math

from amaranth.hdl import Assert, Cat, Const, Module, Mux, Signal, Value, signed, unsigned
from amaranth.lib import data, stream, wiring
from amaranth.lib.wiring import In, Out

from .fixed import check_bool, check_param
from .divider import Divider
from .dsp import MUL_WIDTH, check_mul_width, partial_products, partial_sum, saturate_bits

__all__ = ["svpwm_constants", "SVPWM", "DCBusCompensation", "PWMTimer", "pwm_half_period"]


#: Guard bits below the input LSB in the SVPWM's internal phase-voltage format.
SVPWM_GUARD_BITS = 8


def svpwm_constants(width, frac=None):
    """Internal constants of :class:`SVPWM` for inputs of ``width`` bits with ``frac``
    fractional bits (default ``width − 1``: Q1.(width−1)).

    Returns ``(F, k_frac, k)``: ``F = frac + 8``, fractional bits of ``A``, ``S`` and ``D`` (so
    ``1.0 = 2**F``); ``k = round(2**(8 + k_frac) / √3)`` with ``k_frac = width + 2``, so that
    ``S = round_shift(u_β · k, k_frac)`` (half away from zero) is ``u_β/√3`` in that format.
    ``k`` is exact in integers: ``isqrt`` then the nearest of the two candidates (never a tie).
    Its error is at most ``2**(width−1) · 0.5 / 2**k_frac = 1/16`` LSB of ``S``.
    """
    frac = width - 1 if frac is None else frac
    k_frac = width + 2
    e = 2 * (SVPWM_GUARD_BITS + k_frac)         # k = round(sqrt(2**e / 3))
    n = math.isqrt((1 << e) // 3)
    k = n + 1 if 3 * (2 * n + 1) ** 2 < (1 << (e + 2)) else n
    return frac + SVPWM_GUARD_BITS, k_frac, k


def _check_hz(owner, name, value):
    if (not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value)
            or value <= 0):
        raise TypeError(f"{owner} {name} must be a positive number of Hz, not {value!r}")
    return float(value)


def _duty_layout(count_width):
    return data.StructLayout({"a": unsigned(count_width), "b": unsigned(count_width),
                              "c": unsigned(count_width)})


def _vector_layout(width):
    return data.StructLayout({"alpha": signed(width), "beta": signed(width)})


class SVPWM(wiring.Component):
    """Space-vector modulator: (u_α, u_β) → three duties in counts, with overmodulation.

    Min–max zero-sequence injection (equivalent to sector + dwell times with T0 split equally
    between 000 and 111), constant latency, one command at a time (one per PWM period). See the
    module docstring for the arithmetic; all of it is exact integer arithmetic except ``u_β/√3``
    (rounded half away from zero to ``F = frac + 8`` fractional bits) and the final division
    (rounded half up to a count).

    **Pipeline** (one carry chain or one multiplier per clock, for 100 MHz on an ECP5). With
    ``T = |S|``, ``max(q) = max(A, T)`` and ``min(q) = min(A, −T)``, so ``spread`` and
    ``max + min`` are selected from the four sums ``±A ± S`` by three sign bits instead of being
    computed after the comparisons. In the linear range (``D = 2**F``) the division by ``2·D`` is
    a shift: ``count_x = (scale·N_x + 2**F) >> (F + 1)``. Over-modulating (``D = spread``) the
    largest phase has ``N_x = 2·D`` (``count = scale``) and the smallest ``N_x = 0``
    (``count = 0``): only the middle phase divides, on one restoring divider of radix
    ``2**radix_bits``. The result waits for the division in both cases (constant latency)::

        clock  1  A = α·2**8, partial products of β·k          (k = round(2**(8 + k_frac)/√3))
               2  S = round_shift(β·k, k_frac)
               3  −S, A + S, A − S, S − A, −A − S
               4  spread, max + min, overmod (selected by the signs of S, A − T, −A − T);
                  which phase holds the max, which the middle
               5  D = overmod ? spread : 2**F;  N_x = D + 2·q_x − max − min (over-modulating,
                  lane a takes the middle phase's N)
               6  partial products of scale·N_x; j·2·D for the divider
               7  x_x = scale·N_x + D; duties: linear x_x >> (F + 1), else scale (max) or 0;
                  lane a's x into the divider
               8 … 7 + ⌈cw / radix_bits⌉   division by 2·D, the quotient into the middle
                                          phase's duty (all duties registered)

    Parameters
    ----------
    width : int
        Width ``w`` of u_α and u_β, 8 … 24 bits: fractions of (2/3)·U_dc (hexagon vertices at
        1.0, linear range up to √3/2).
    frac : int or None
        Fractional bits of u_α and u_β, ``w − 2`` or ``w − 1`` (default): Q1.(w−1), or Q2.(w−2)
        for the 1-bit-wider output of :class:`DCBusCompensation` (``out_width = width + 1``),
        whose LSB is the input's.
    count_width : int
        Width ``cw`` of the scale and of the duties, 4 … 24 bits.
    radix_bits : int
        Quotient bits per clock of the over-modulation divider, 1 … 4 (radix 2 … 16; radix
        ``2**r`` compares with ``2**r − 1`` multiples of the divisor in parallel).
    mul_width : int
        Signed operand width of the target's hard multiplier, 8 … 25, or ``None`` (:mod:`~.dsp`:
        18 ECP5 / Xilinx; ``None`` iCE40: products not split). The products are split into
        partial products that fit it; the results do not depend on it.

    Members
    -------
    i : In(stream.Signature(data.StructLayout({"alpha": signed(w), "beta": signed(w)})))
        Command. ``i.ready`` is high while idle; a transfer starts a computation.
    scale : In(unsigned(cw))
        Count of a 100 % duty (``PWMTimer.full_scale``), sampled with the command.
    o : Out(stream.Signature(data.StructLayout({"a", "b", "c": unsigned(cw), "overmod": 1})))
        Duties in counts, ``0 … scale``, each ``scale · duty`` rounded half up; ``overmod`` is set
        when the command was outside the hexagon and was scaled back along its angle. Valid
        :attr:`latency` clocks after the transfer, held until ``o.ready``.

    Attributes
    ----------
    latency : int
        Clocks from the transfer on ``i`` to ``o.valid``: ``7 + ⌈count_width / radix_bits⌉``
        (15 at ``count_width = 16``, ``radix_bits = 2``), whatever the command. The block is idle
        again the clock after ``o`` is taken: one command per ``latency + 1`` clocks.
    frac : int
        ``F``, fractional bits of the internal phase voltages (``1.0 = 2**F``).
    in_frac : int
        Fractional bits of the inputs (the ``frac`` parameter).

    Raises
    ------
    TypeError
        A width of the wrong type or outside its range.
    """

    #: Clocks before the division (clock 7 above holds x_x).
    PREPARE = 7

    def __init__(self, *, width=16, frac=None, count_width=16, radix_bits=2, mul_width=MUL_WIDTH):
        self._mul_width = check_mul_width("SVPWM", mul_width)
        check_param("SVPWM", "width", width, 8, 24)
        check_param("SVPWM", "count_width", count_width, 4, 24)
        check_param("SVPWM", "radix_bits", radix_bits, 1, 4)
        if frac is None:
            frac = width - 1
        if not isinstance(frac, int) or isinstance(frac, bool) or frac not in (width - 2,
                                                                                width - 1):
            raise TypeError(f"SVPWM frac must be width − 2 ({width - 2}) or width − 1 "
                            f"({width - 1}), not {frac!r}")
        self._width = width
        self._count_width = count_width
        self._radix_bits = radix_bits
        self._int_bits = width - frac           # 1: Q1.(w−1), 2: Q2.(w−2)
        self._frac, self._k_frac, self._k = svpwm_constants(width, frac)
        out = data.StructLayout({"a": unsigned(count_width), "b": unsigned(count_width),
                                 "c": unsigned(count_width), "overmod": 1})
        super().__init__({
            "i": In(stream.Signature(_vector_layout(width))),
            "scale": In(unsigned(count_width)),
            "o": Out(stream.Signature(out)),
        })

    width = property(lambda self: self._width)
    count_width = property(lambda self: self._count_width)
    radix_bits = property(lambda self: self._radix_bits)
    mul_width = property(lambda self: self._mul_width)
    frac = property(lambda self: self._frac)
    in_frac = property(lambda self: self._frac - SVPWM_GUARD_BITS)

    @property
    def divide_steps(self):
        """Clocks of the over-modulation division, ``⌈count_width / radix_bits⌉``."""
        return -(-self._count_width // self._radix_bits)

    @property
    def latency(self):
        return self.PREPARE + self.divide_steps

    def elaborate(self, platform):
        m = Module()
        F, cw, r = self._frac, self._count_width, self._radix_bits
        # G integer bits of the input (sign included): |u| ≤ 2**(G−1) (2**(F+G−1) internally).
        G = self._int_bits
        W = F + G + 1               # A, S, their sums, N_x ∈ [0, 2·D], 2·D: all fit W bits
        one = 1 << F
        kf = self._k_frac
        phases = "abc"
        steps = self.divide_steps
        nq = r * steps              # quotient bits the divider produces (≥ cw)
        lat = self.latency

        # Sequencing: clock 0 takes the command, stage k's registers load in clock k − 1.
        # ``i.ready`` and ``o.valid`` come straight from flip-flops (they steer the neighbours'
        # pipeline enables).
        cyc = Signal(range(lat + 1))
        idle = Signal(init=1)
        done = Signal()
        take = self.i.valid & idle
        m.d.comb += [self.i.ready.eq(idle), self.o.valid.eq(done)]
        with m.If(take):
            m.d.sync += [cyc.eq(1), idle.eq(0)]
        with m.Elif((cyc != 0) & (cyc != lat)):
            m.d.sync += cyc.eq(cyc + 1)
            with m.If(cyc == lat - 1):
                m.d.sync += done.eq(1)
        with m.Elif(done & self.o.ready):
            m.d.sync += [cyc.eq(0), idle.eq(1), done.eq(0)]

        # 1: A (as u_α), partial products of u_β·k, the rounding's sign.
        alpha1 = Signal(signed(self._width))
        neg1 = Signal()
        scale = Signal(unsigned(cw))
        k = Const(self._k, unsigned(self._k.bit_length()))
        pp1 = []
        for n, (p, s) in enumerate(partial_products(self.i.payload.beta, k,
                                                       mul_width=self._mul_width)):
            reg = Signal(p.shape(), name=f"pp_s{n}")
            pp1.append((reg, s))
            with m.If(take):
                m.d.sync += reg.eq(p)
        with m.If(take):
            m.d.sync += [alpha1.eq(self.i.payload.alpha), neg1.eq(self.i.payload.beta[-1]),
                         scale.eq(self.scale)]

        # 2: S = round_shift(u_β·k, k_frac), half away from zero (k > 0: sign(β·k) = sign(β)).
        a2 = Signal(signed(W))
        s2 = Signal(signed(W))
        with m.If(cyc == 1):
            m.d.sync += [
                a2.eq(alpha1 << SVPWM_GUARD_BITS),
                s2.eq((partial_sum(pp1) + (1 << (kf - 1)) - neg1) >> kf),
            ]

        # 3: the four sums ±A ± S and −S.
        a3, s3, ns3 = (Signal(signed(W), name=n) for n in ("a3", "s3", "ns3"))
        up3, um3, nup3, num3 = (Signal(signed(W), name=n) for n in ("up3", "um3", "nup3", "num3"))
        with m.If(cyc == 2):
            m.d.sync += [a3.eq(a2), s3.eq(s2), ns3.eq(-s2),
                         up3.eq(a2 + s2), um3.eq(a2 - s2), nup3.eq(-a2 - s2), num3.eq(s2 - a2)]

        # 4: T = |S|; case 1 A ≥ T: max = A, min = −T; case 2 A ≤ −T: max = T, min = A;
        # else max = T, min = −T. The phases holding the max, the min and the middle (with S
        # and −S ordered by the sign of S); on a tie any choice is right, see 7.
        neg = s3[-1]
        t = Mux(neg, ns3, s3)
        u = Mux(neg, um3, up3)              # A + T
        v = Mux(neg, up3, um3)              # A − T
        nv = Mux(neg, nup3, num3)           # T − A
        nu = Mux(neg, num3, nup3)           # −A − T
        case1 = ~v[-1]
        case2 = ~nu[-1] & ~case1
        case3 = ~case1 & ~case2
        hi_bc = {"b": ~neg, "c": neg}       # the phase of T among b (S) and c (−S)
        q4 = {p: Signal(signed(W), name=f"q4_{p}") for p in phases}
        spread4 = Signal(unsigned(W - 1))
        sum4 = Signal(signed(W))            # max(q) + min(q)
        om4 = Signal()
        top4 = {p: Signal(name=f"max4_{p}") for p in phases}
        mid4 = {p: Signal(name=f"mid4_{p}") for p in phases}
        with m.If(cyc == 3):
            m.d.sync += [
                q4["a"].eq(a3), q4["b"].eq(s3), q4["c"].eq(ns3),
                spread4.eq(Mux(case1, u, Mux(case2, nv, t << 1))),
                sum4.eq(Mux(case1, v, Mux(case2, u, 0))),
                om4.eq(Mux(case1, u > one, Mux(case2, nv > one, (t << 1) > one))),
                top4["a"].eq(case1), mid4["a"].eq(case3),
            ]
            for p in "bc":                  # case 1: min −T; case 2: max T; case 3: mid A
                m.d.sync += [top4[p].eq(~case1 & hi_bc[p]),
                             mid4[p].eq((case1 & hi_bc[p]) | (case2 & ~hi_bc[p]))]

        # 5: D and the numerators N_x = D + 2·q_x − max − min ∈ [0, 2·D]. Over-modulating,
        # lane a computes the middle phase's numerator instead of phase a's: the extremes need
        # none (7) and the divider then always takes lane a.
        d5 = Signal(unsigned(W - 1))
        om = Signal()
        top = {p: Signal(name=f"max_{p}") for p in phases}
        mid = {p: Signal(name=f"mid_{p}") for p in phases}
        n5 = {p: Signal(unsigned(W), name=f"n5_{p}") for p in phases}
        d = Mux(om4, spread4, one)
        q_lane = {"a": Mux(om4 & mid4["b"], q4["b"], Mux(om4 & mid4["c"], q4["c"], q4["a"])),
                  "b": q4["b"], "c": q4["c"]}
        with m.If(cyc == 4):
            m.d.sync += [d5.eq(d), om.eq(om4)]
            m.d.sync += [n5[p].eq((d + (q_lane[p] << 1) - sum4)[:W]) for p in phases]
            m.d.sync += [top[p].eq(top4[p]) for p in phases]
            m.d.sync += [mid[p].eq(mid4[p]) for p in phases]

        # 6: partial products of scale·N_x; multiples of 2·D.
        d6 = Signal(unsigned(W - 1))
        mult = [None] + [Signal(unsigned(W + r), name=f"div_m{j}") for j in range(1, 1 << r)]
        pp6 = {}
        with m.If(cyc == 5):
            m.d.sync += d6.eq(d5)
            for p in phases:
                pp6[p] = []
                for n, (prod, s) in enumerate(partial_products(scale, n5[p],
                                                                 mul_width=self._mul_width)):
                    reg = Signal(prod.shape(), name=f"pp_{p}{n}")
                    pp6[p].append((reg, s))
                    m.d.sync += reg.eq(prod)
            for j in range(1, 1 << r):     # shifts and adds (a constant product takes a DSP)
                m.d.sync += mult[j].eq(sum(d5 << (1 + b) for b in range(r) if j >> b & 1))

        # 7: x_x = scale·N_x + D < 2·D·2**cw. Linear range: the duty is x_x >> (F + 1).
        # Over-modulating (D = spread), the max phase has N = 2·D: its duty is scale; the min
        # phase N = 0: duty 0; the middle phase divides (any N ∈ [0, 2·D] gives the right duty
        # through the division, so on a tie any choice of max/min/middle is right). Lane a's x
        # (the middle phase's when over-modulating) goes to the divider: remainder x >> nq
        # (< 2·D) and low bits, which shift out as the quotient bits shift in.
        duty = {p: Signal(unsigned(cw), name=f"duty_{p}") for p in phases}
        rem = Signal(unsigned(W))
        low = Signal(unsigned(nq))
        with m.If(cyc == 6):
            for p in phases:
                lin = (partial_sum(pp6[p]) + d6)[F + 1:F + 1 + cw]
                m.d.sync += duty[p].eq(Mux(om, Mux(top[p], scale, 0), lin))
            m.d.sync += Cat(low, rem).eq(partial_sum(pp6["a"]) + d6)

        # 8 …: restoring division by 2·D, radix 2**r; the last step also writes the quotient
        # into the middle phase's duty.
        trial = Cat(low[nq - r:], rem)                              # < 2**r · 2·D
        val = trial
        digit = 0
        for j in range(1, 1 << r):
            diff = Signal(signed(W + r + 1), name=f"div_d{j}")
            m.d.comb += diff.eq(trial - mult[j])
            fits = ~diff[-1]                # multiples increase with j: a thermometer code
            val = Mux(fits, diff, val)
            digit = digit + fits
        low_next = Cat(Value.cast(digit)[:r], low[:nq - r])
        with m.If((cyc >= self.PREPARE) & (cyc < lat)):
            m.d.sync += [rem.eq(val[:W]), low.eq(low_next)]
        with m.If((cyc == lat - 1) & om):
            for p in phases:
                with m.If(mid[p]):
                    m.d.sync += duty[p].eq(low_next[:cw])

        # Output: the duty registers.
        for p in phases:
            m.d.comb += [
                self.o.payload[p].eq(duty[p]),
                Assert(~self.o.valid | (duty[p] <= scale), "SVPWM duty above the full scale"),
            ]
        m.d.comb += self.o.payload.overmod.eq(om)
        return m


class DCBusCompensation(wiring.Component):
    """DC-bus voltage compensation: ``u · U_rated / U_dc``, saturated.

    A new bus measurement on ``u_dc`` starts one division on the foundation :class:`Divider`:
    ``gain = min(round(U_rated · 2**gf / U_dc), gain_limit)`` (half up; ``U_dc = 0`` gives the
    limit), UQ2.gf with ``gf = 16``. The gain register starts at 1.0. Each command is multiplied
    by the gain in force when it arrives: ``o = sat(round_shift(u · gain, gf))`` (half away from
    zero, saturated to ``signed(out_width)``, never wrapped).

    A component saturating changes the vector's angle; that only happens for commands already
    outside the hexagon (``|u_α| > 1`` or ``|u_β| > 1``). ``out_width = width + 1`` (Q2.(w−1)) with
    ``SVPWM(width=width + 1, frac=width − 1)`` removes even that, up to ``gain · |u| < 2``.

    Parameters
    ----------
    width : int
        Width ``w`` of the input commands, Q1.(w−1), 8 … 24 bits.
    out_width : int or None
        Width of the outputs, ``w`` (default) or ``w + 1``; same LSB as the inputs.
    adc_width : int
        Width of the raw bus-voltage codes ``U_dc`` and ``U_rated`` (unsigned, same units),
        4 … 24 bits.
    gain_limit : float
        Largest gain, 1.0 ≤ limit < 4.0 (rounded to 2**-16): the compensation stops when the bus
        drops below ``U_rated / gain_limit``.
    mul_width : int
        Signed operand width of the target's hard multiplier, 8 … 25, or ``None`` (:mod:`~.dsp`:
        18 ECP5 / Xilinx; ``None`` iCE40: products not split). The products are split into
        partial products that fit it; the results do not depend on it.

    Members
    -------
    u_rated : In(unsigned(adc_width))
        Rated bus voltage register, sampled when a division starts.
    u_dc : In(stream.Signature(unsigned(adc_width), always_ready=True))
        Bus-voltage measurements. The latest one is kept if the divider is busy.
    i : In(stream.Signature(data.StructLayout({"alpha", "beta": signed(w)})))
    o : Out(stream.Signature(data.StructLayout({"alpha", "beta": signed(out_width)})))
        :attr:`latency` clocks after each transfer on ``i``; a two-stage pipeline that moves
        while ``i.ready = ~o.valid | o.ready``.
    gain : Out(unsigned(18))
        Gain in force, UQ2.16.
    limited : Out(1)
        The last gain computation hit ``gain_limit`` (bus too low, or zero).

    Attributes
    ----------
    latency : int
        Clocks from a transfer on ``i`` to ``o.valid``: 2 (the partial products of ``u · gain``
        registered, then their sum rounded and saturated: 100 MHz on an ECP5).
    gain_latency : int
        Clocks from a ``u_dc`` transfer (divider idle) until ``gain`` holds its result:
        ``divider.latency + 2``: one clock into the pending register, the division, one into
        ``gain``.
    gain_frac : int
        16.
    gain_limit_raw : int
        ``gain_limit`` in UQ2.16.

    Raises
    ------
    TypeError
        A parameter of the wrong type or outside its basic range.
    ValueError
        ``out_width`` other than ``width`` or ``width + 1``; ``gain_limit`` outside [1, 4).
    """

    latency = 2
    gain_frac = 16

    def __init__(self, *, width=16, out_width=None, adc_width=16, gain_limit=2.0,
                 mul_width=MUL_WIDTH):
        self._mul_width = check_mul_width("DCBusCompensation", mul_width)
        check_param("DCBusCompensation", "width", width, 8, 24)
        if out_width is None:
            out_width = width
        elif not isinstance(out_width, int) or isinstance(out_width, bool):
            raise TypeError(f"DCBusCompensation out_width must be None or an integer, "
                            f"not {out_width!r}")
        if out_width not in (width, width + 1):
            raise ValueError(f"DCBusCompensation out_width must be width ({width}) or "
                             f"width + 1, not {out_width!r}")
        check_param("DCBusCompensation", "adc_width", adc_width, 4, 24)
        if (not isinstance(gain_limit, (int, float)) or isinstance(gain_limit, bool)
                or not math.isfinite(gain_limit)):
            raise TypeError(f"DCBusCompensation gain_limit must be a number, not {gain_limit!r}")
        limit_raw = round(gain_limit * (1 << self.gain_frac))
        if not (1 << self.gain_frac) <= limit_raw < (4 << self.gain_frac):
            raise ValueError(f"DCBusCompensation gain_limit must be at least 1.0 and below 4.0, "
                             f"not {gain_limit!r}")
        self._width = width
        self._out_width = out_width
        self._adc_width = adc_width
        self._limit_raw = limit_raw
        self._div = Divider(width=adc_width + self.gain_frac + 2, divisor_width=adc_width + 1,
                            signed=False)
        super().__init__({
            "u_rated": In(unsigned(adc_width)),
            "u_dc": In(stream.Signature(unsigned(adc_width), always_ready=True)),
            "i": In(stream.Signature(_vector_layout(width))),
            "o": Out(stream.Signature(_vector_layout(out_width))),
            "gain": Out(unsigned(2 + self.gain_frac), init=1 << self.gain_frac),
            "limited": Out(1),
        })

    width = property(lambda self: self._width)
    out_width = property(lambda self: self._out_width)
    mul_width = property(lambda self: self._mul_width)
    adc_width = property(lambda self: self._adc_width)
    gain_limit_raw = property(lambda self: self._limit_raw)

    @property
    def gain_latency(self):
        return self._div.latency + 2

    def elaborate(self, platform):
        m = Module()
        m.submodules.divider = div = self._div
        gf = self.gain_frac

        # Bus measurements: keep the latest until the divider takes it.
        pending = Signal()
        u_dc = Signal(unsigned(self._adc_width))
        with m.If(self.u_dc.valid):
            m.d.sync += [u_dc.eq(self.u_dc.payload), pending.eq(1)]
        with m.Elif(div.i.valid & div.i.ready):
            m.d.sync += pending.eq(0)
        m.d.comb += [
            div.i.valid.eq(pending),
            # round(R·2**gf / U) = floor((R·2**(gf+1) + U) / (2·U))
            div.i.payload.dividend.eq((self.u_rated << (gf + 1)) + u_dc),
            div.i.payload.divisor.eq(u_dc << 1),
            div.o.ready.eq(1),
        ]
        with m.If(div.o.valid):
            q = div.o.payload.quotient
            over = div.o.payload.div0 | (q > self._limit_raw)
            m.d.sync += [
                self.gain.eq(Mux(over, self._limit_raw, q)),
                self.limited.eq(over),
            ]

        # Commands, two register stages: partial products of u·gain, then rounded and saturated.
        m.d.comb += self.i.ready.eq(~self.o.valid | self.o.ready)
        valid1 = Signal()
        parts = {}
        with m.If(self.i.ready):
            m.d.sync += [valid1.eq(self.i.valid), self.o.valid.eq(valid1)]
        for f in ("alpha", "beta"):
            # round_shift(u·gain, gf): the product's sign is u's (gain ≥ 0; 0 rounds to 0), so
            # the rounding term is 2**(gf−1) − [u < 0], a concatenation of u's sign bit, < 2**gf.
            # When a partial product has a shift ≥ gf (at mul_width 18: the gain's top bit,
            # shift 17), the term fills that product's zero low bits as it is registered: the
            # sum behind the registers is then one adder per extra product (one at 18), with
            # nothing added for the rounding. Else (mul_width None) it is one more addend.
            neg = self.i.payload[f][-1]
            rounding = Cat(neg.replicate(gf - 1), ~neg)         # 2**(gf−1) − neg, gf bits
            products = partial_products(self.i.payload[f], self.gain, mul_width=self._mul_width)
            host = next((n for n, (_, s) in enumerate(products) if s >= gf), None)
            parts[f] = []
            for n, (prod, s) in enumerate(products):
                if n == host:
                    merged = Cat(rounding, Const(0, s - gf), prod)
                    prod, s = (merged.as_signed() if prod.shape().signed else merged), 0
                reg = Signal(prod.shape(), name=f"pp_{f}{n}")
                parts[f].append((reg, s))
                with m.If(self.i.ready & self.i.valid):
                    m.d.sync += reg.eq(prod)
            if host is None:
                neg_q = Signal(name=f"neg_{f}")
                with m.If(self.i.ready & self.i.valid):
                    m.d.sync += neg_q.eq(neg)
                parts[f].append((Cat(neg_q.replicate(gf - 1), ~neg_q), 0))
            rounded = partial_sum(parts[f]) >> gf
            with m.If(self.i.ready & valid1):
                m.d.sync += self.o.payload[f].eq(
                    saturate_bits(rounded, signed(self._out_width)))
        return m


def pwm_half_period(clk_hz, pwm_hz):
    """Half period ``N = round(clk_hz / (2·pwm_hz))`` in clocks (ties to even)."""
    return round(clk_hz / (2 * pwm_hz))


class PWMTimer(wiring.Component):
    """Three-phase PWM timer with shadowed compares, symmetric or asymmetric, and ADC strobe.

    Every period lasts ``2·N`` clocks, ``N = round(clk_hz / (2·pwm_hz))``, in both modes; the
    position ``pos`` runs ``0 … 2N−1``. Phase ``x`` with active compare ``c_x`` is high:

    * symmetric (centre-aligned; an up/down counter ``0 … N … 1``): for ``N − c ≤ pos < N + c``,
      i.e. ``2·c`` clocks centred on the middle of the period (``c ∈ 0 … N``, full scale ``N``);
    * asymmetric (edge-aligned sawtooth): for ``pos < c`` (``c ∈ 0 … 2N``, full scale ``2N``).

    Compares above the full scale saturate to it (and, with ``signed_duty``, those below 0 act
    as 0). ``duty`` writes go to shadow registers at any
    time; at the period boundary (``pos = 2N−1 → 0``) the shadowed duties and the ``symmetric``
    bit become active together, so a write never changes the current period.

    Parameters
    ----------
    clk_hz : float
        System clock, Hz.
    pwm_hz : float
        PWM (switching) frequency, Hz; the actual one is :attr:`pwm_hz_actual`.
    count_width : int
        Width of the compares and of ``sample_point``, 4 … 24 bits; ``2·N`` must fit in it.
    signed_duty : bool
        ``True``: the compares are ``signed(count_width + 2)`` (the unclamped sums of
        :class:`~.deadtime_comp.DeadTimeComp` ``clamp=False``) and those below 0 act as 0: the
        clamp in the shadow's and the active register's LUTs (the iCE40's form,
        ``Top(timer_clamp)``; the same levels as the clamped sums). Default ``False``.
    sample_split : bool
        ``True``: the ``sample`` strobe as the custom position's equality and the centre's
        (a compare of ``pos`` with a constant) selected by ``sample_custom`` after them, not
        one equality behind a multiplexer of the two positions (the iCE40's form,
        ``Top(timer_sample_split)``: the timer −8 logic cells, docs/AREA.md §7.79; +18 LUT6
        on the Arty S7). The same strobes. Default ``False``.
    one_adder : bool
        ``True``: the triangle counter steps both ways on one adder (``k_n + 1`` or ``k_n +``
        all ones), not two chains and a multiplexer (the iCE40's and the Spartan-7's form,
        ``Top(timer_one_adder)``: the timer −24 logic cells alone, docs/AREA.md §7.79;
        ``False`` the ECP5's netlist of before, §7.80). The same outputs. Default ``True``.

    Members
    -------
    duty : In(stream.Signature(data.StructLayout({"a", "b", "c": unsigned(count_width)})))
        Compares for the next period (``duty.ready`` is always high); ``signed(count_width + 2)``
        fields with ``signed_duty``.
    symmetric : In(1)
        Configuration bit (paper Fig. 7): 1 centre-aligned, 0 asymmetric; loaded at the boundary.
    full_scale : Out(unsigned(count_width))
        Count of a 100 % duty in the mode set on ``symmetric`` (``N`` or ``2N``): the SVPWM scale.
    sample_custom : In(1)
        0: ``sample`` at ``pos = N``, the centre of the period (centre of the high pulses in
        symmetric mode); 1: at ``pos = sample_point`` (never if ``≥ 2N``).
    sample_point : In(unsigned(count_width))
        With ``sample_custom``, read one clock ahead: ``sample`` is high when ``pos`` equals
        the sample position of the clock before, so a change acts from the clock after it
        (the register file changes it at ``period_start``, ``pos = 0``: the same sample
        unless the old or the new position is 1).
    pwm : Out(data.StructLayout({"a", "b", "c": 1}))
        Phase levels (from registers through comparators; :class:`Gates` registers them).
    period_start : Out(1)
        High during ``pos = 0``, the first clock with the new duties: the loop tick. Straight
        from a flip-flop (set in the clock before), so its fan-out starts at a register.
    sample : Out(1)
        One-clock ADC conversion-start strobe, straight from a flip-flop.
    position : Out(range(2N))
        ``pos``.

    Attributes
    ----------
    half_period : int
        ``N``.
    period : int
        ``2·N`` clocks.
    pwm_hz_actual : float
        ``clk_hz / (2·N)``.

    Raises
    ------
    TypeError
        A parameter of the wrong type (``signed_duty``, ``sample_split`` or ``one_adder`` not
        a bool).
    ValueError
        ``N < 4`` or ``2·N ≥ 2**count_width``.
    """

    def __init__(self, *, clk_hz=50e6, pwm_hz=10e3, count_width=16, signed_duty=False,
                 sample_split=False, one_adder=True):
        clk_hz = _check_hz("PWMTimer", "clk_hz", clk_hz)
        check_bool("PWMTimer", "signed_duty", signed_duty)
        check_bool("PWMTimer", "sample_split", sample_split)
        check_bool("PWMTimer", "one_adder", one_adder)
        pwm_hz = _check_hz("PWMTimer", "pwm_hz", pwm_hz)
        check_param("PWMTimer", "count_width", count_width, 4, 24)
        n = pwm_half_period(clk_hz, pwm_hz)
        if n < 4:
            raise ValueError(f"PWMTimer pwm_hz {pwm_hz:g} Hz is too high for clk_hz {clk_hz:g} Hz: "
                             f"the half period must be at least 4 clocks, not {n}")
        if 2 * n >= 1 << count_width:
            raise ValueError(f"PWMTimer pwm_hz {pwm_hz:g} Hz is too low for clk_hz {clk_hz:g} Hz "
                             f"and count_width {count_width}: the period of {2 * n} clocks must "
                             f"be below {1 << count_width}")
        self._clk_hz = clk_hz
        self._pwm_hz = pwm_hz
        self._count_width = count_width
        self._n = n
        self._signed_duty = signed_duty
        self._sample_split = sample_split
        self._one_adder = one_adder
        duties = (data.StructLayout({p: signed(count_width + 2) for p in "abc"}) if signed_duty
                  else _duty_layout(count_width))
        super().__init__({
            "duty": In(stream.Signature(duties)),
            "symmetric": In(1),
            "full_scale": Out(unsigned(count_width)),
            "sample_custom": In(1),
            "sample_point": In(unsigned(count_width)),
            "pwm": Out(data.StructLayout({"a": 1, "b": 1, "c": 1})),
            "period_start": Out(1),
            "sample": Out(1),
            "position": Out(range(2 * n)),
        })

    clk_hz = property(lambda self: self._clk_hz)
    pwm_hz = property(lambda self: self._pwm_hz)
    count_width = property(lambda self: self._count_width)
    half_period = property(lambda self: self._n)
    signed_duty = property(lambda self: self._signed_duty)
    sample_split = property(lambda self: self._sample_split)
    one_adder = property(lambda self: self._one_adder)

    @property
    def period(self):
        return 2 * self._n

    @property
    def pwm_hz_actual(self):
        return self._clk_hz / (2 * self._n)

    def elaborate(self, platform):
        m = Module()
        n = self._n
        pos = self.position
        last = pos == 2 * n - 1
        # The compares are kept saturated to kw bits (kw: the width of 2N): every level compare
        # is then against a counter of at most 2N, so any value from 2N up acts alike.
        kw = (2 * n).bit_length()

        def sat(c):
            return c[:kw] | c[kw:].any().replicate(kw) if len(c) > kw else c

        shadow = Signal(data.StructLayout({p: unsigned(kw) for p in "abc"}))
        active = Signal(data.StructLayout({p: unsigned(kw) for p in "abc"}))
        sym = Signal()                          # active mode
        first = Signal(init=1)                  # pos = 0: the period's first clock
        sample = Signal()                       # pos = the previous clock's target

        m.d.comb += self.duty.ready.eq(1)
        if not self._signed_duty:
            with m.If(self.duty.valid):
                m.d.sync += [shadow[p].eq(sat(self.duty.payload[p])) for p in "abc"]
            m.d.sync += [pos.eq(Mux(last, 0, pos + 1)), first.eq(last)]
            with m.If(last):
                # A write on the boundary clock itself still makes this period.
                m.d.sync += [active[p].eq(Mux(self.duty.valid, sat(self.duty.payload[p]),
                                              shadow[p])) for p in "abc"]
                m.d.sync += sym.eq(self.symmetric)
        else:
            # Signed duties (``signed_duty``): below 0 act as 0, from 2**kw up as all ones.
            # Two select bits a phase, (force, value) = (0, 0) hold the shadow, (0, 1) take the
            # duty's bit, (1, v) all v: the shadow's LUT takes 3 inputs (the selects and the
            # duty's bit; valid is its enable), the active register's 4 (and the shadow's bit),
            # so neither has a LUT output shared with the other: each flip-flop packs with its
            # LUT (iCEBreaker: the timer 242 → 209 logic cells, docs/AREA.md §7.72). The selects
            # are kept wires: without them abc reuses the shadow's LUT in the active one's (a
            # LUT output with two loads, so the shadow flip-flop alone again).
            for p in "abc":
                d = self.duty.payload[p]
                neg = d[-1]
                over = d[kw:-1].any()
                keep = {"keep": 1}
                take_force = Signal(name=f"take_force_{p}", attrs=keep)
                take_value = Signal(name=f"take_value_{p}", attrs=keep)
                m.d.comb += [take_force.eq(self.duty.valid & (neg | over)),
                             take_value.eq(self.duty.valid & ~neg)]
                with m.If(self.duty.valid):
                    m.d.sync += shadow[p].eq(Mux(neg, 0, Mux(over, (1 << kw) - 1, d[:kw])))
                with m.If(last):
                    # A write on the boundary clock itself still makes this period
                    # (take_force | take_value is valid).
                    m.d.sync += active[p].eq(Mux(take_force, take_value.replicate(kw),
                                                 Mux(take_value, d[:kw], shadow[p])))
            m.d.sync += [pos.eq(Mux(last, 0, pos + 1)), first.eq(last)]
            with m.If(last):
                m.d.sync += sym.eq(self.symmetric)

        # The level of a phase with compare c is `k ≤ c` for one counter k shared by the three
        # phases: asymmetric k = pos + 1 (1 … 2N; high for pos < c), symmetric the triangle
        # k = N − pos in the first half, pos − N + 1 in the second (N … 1, 1 … N; high for
        # N − c ≤ pos < N + c). Both saturate by themselves (k ≤ N resp. 2N, k ≥ 1 so c = 0
        # is never high), so the levels are those of the window compares clock for clock with
        # one carry chain per phase. k is kept inverted (k_n = ~k) so that `c ≥ k` is
        # `c + k_n + 1` carrying out: no inverter in front of the chains. `down`: the
        # triangle's first half (k steps down to 1, stays there one clock, then steps up).
        ones = (1 << kw) - 1
        k_n = Signal(kw, init=ones ^ 1)
        down = Signal()
        k = ~k_n
        with m.If(last):
            m.d.sync += [k_n.eq(Mux(self.symmetric, ones ^ n, ones ^ 1)), down.eq(1)]
        with m.Else():
            with m.If(k == 1):
                m.d.sync += down.eq(0)
            if self._one_adder:
                # One adder for both directions: k_n + 1 (k − 1, the triangle's first half,
                # held at k = 1) or k_n + all ones (k + 1), not two chains and a multiplexer
                # (iCE40: the timer −24 logic cells alone, docs/AREA.md §7.79).
                dec = sym & down
                with m.If(~dec | (k != 1)):
                    m.d.sync += k_n.eq(k_n + Cat(Const(1, 1), (~dec).replicate(kw - 1)))
            else:
                # Two chains and a multiplexer (the ECP5's netlist of before, docs/AREA.md §7.80).
                with m.If(sym & down):
                    with m.If(k != 1):
                        m.d.sync += k_n.eq(k_n + 1)     # k − 1
                with m.Else():
                    m.d.sync += k_n.eq(k_n - 1)         # k + 1

        m.d.comb += self.full_scale.eq(Mux(self.symmetric, n, 2 * n))
        for p in "abc":
            m.d.comb += self.pwm[p].eq(active[p] >= k)

        m.d.comb += [
            # `first` is pos = 0, registered: the period event leaves a flip-flop, not a compare
            # of the counter (it fans out across the die: M/T, the register file, the loops).
            self.period_start.eq(first),
            self.sample.eq(sample),
        ]
        # The ADC strobe from a flip-flop too: the compare of the next clock's position with
        # the sample position of this clock (pos + 1 = target, or target = 0 after the last
        # clock), so the counter's and the register file's paths end here, not at the ADC.
        if self._sample_split:
            # The selection after the two equalities, not a multiplexer in front of one: the
            # custom one takes two bits a LUT, the centre is a compare of pos with a constant
            # (the timer alone on the iCE40: −8 logic cells, docs/AREA.md §7.79).
            m.d.sync += sample.eq(Mux(self.sample_custom,
                                      Mux(last, 0, pos + 1) == self.sample_point,
                                      pos == n - 1))
        else:
            target = Mux(self.sample_custom, self.sample_point, n)
            m.d.sync += sample.eq(Mux(last, target == 0, pos + 1 == target))
        return m
