# Ref: paper eq. (4)–(6) (Park / inverse Park as a vector rotation), SPEC.md §2.1; issue 7
#      (area), AREA.md §4 item 1 (sine table instead of the unrolled CORDIC)
"""Vector rotator from an octant sine/cosine table in block RAM and two time-shared multipliers.

A drop-in for :class:`~.cordic.Cordic` as the current loop uses it (same streams, same formats,
gain exactly 1), at a fraction of the area: ``x' = x·cosθ − y·sinθ``, ``y' = x·sinθ + y·cosθ``.

Notation: ``W`` = ``width`` (x, y and the trigonometric operands), ``AW`` = ``angle_width``,
``n`` = ``table_bits``, ``m = AW − 3 − n`` interpolation bits, ``D = 2**m``, ``Ft = W + 2``
(table precision), ``g = 4`` (interpolation guard bits), ``Δ = 2π / 2**AW`` (one angle LSB).

1. **Angle folding** (exact). θ = q·90° + r with ``q = θ[AW−2:]``, ``r = θ[:AW−2]``; the mirror
   bit ``μ = θ[AW−3]`` (r ≥ 45°). The octant angle ``a = r`` (``μ = 0``) or ``90° − r``
   (``μ = 1``) lies in [0, 45°] and is ``a = k·D + d`` LSB with::

       μ = 0:  k = θ[m:AW−3],        d = θ[:m]              ∈ [0, D − 1]
       μ = 1:  k = ~θ[m:AW−3],       d = D − θ[:m]          ∈ [1, D]

   (one's complement on the index: ``90° − r = (~r) + 1``, and the ``+1`` lands in ``d``).
2. **Table** (``2**n`` words of ``2·Ft`` bits, one synchronous read port): for
   ``a_k = k·D·Δ``, with ``S = round(sin a_k · 2**Ft)``, ``C = round(cos a_k · 2**Ft)``::

       S'' = S − 2**(Ft−1) + 2**(Ft−W−1)        signed(Ft)   (offset, + half for the rounding)
       C'' = C − 2**Ft     + 2**(Ft−W−1)        signed(Ft)   (cos 0 = 1 is exact: C'' = 2)

3. **Interpolation** ``sin(a_k + δ) ≈ S + δ·C``, ``cos(a_k + δ) ≈ C − δ·S`` with ``δ = d·Δ``,
   on the two multipliers (floor shifts)::

       kd   = round(d·Δ·2**K)               unsigned(W − 1), K the largest with kd(D) < 2**(W−1)
       C_hi = (C'' >> 4) + 2**(W−2)         unsigned(W − 1) ≈ cos a_k · 2**(W−2)  (a bit flip)
       S_hi = (S'' >> 3) + 2**(W−2)         unsigned(W − 1) ≈ sin a_k · 2**(W−1)  (a bit flip)
       s_o  = (S''·2**g + (kd·C_hi >> (K − 8))) >> (g + 2)      signed(W) = round(s·2**W) − 2**(W−1)
       c_o  = (C''·2**g − (kd·S_hi >> (K − 7))) >> (g + 2)      signed(W) = round(c·2**W) − 2**W

   ``s_T = s_o + 2**(W−1)`` ∈ [0, 0.7072·2**W] and ``c_T = c_o + 2**W`` ∈ [0.7071·2**W, 2**W]
   are sin a and cos a at scale ``2**W``, rounded half up; the offsets make both fit a signed
   ``W``-bit multiplier operand (an iCE40 ``SB_MAC16`` at ``W = 16``).
4. **Rotation**, two passes on the two multipliers. With ``w = q[0] ⊕ μ`` (``|cosθ| = s`` when
   set), the integer trigonometric values at scale ``2**W`` are::

       |cosθ|_T = s_T if w else c_T            sign negative iff q ∈ {1, 2}
       |sinθ|_T = c_T if w else s_T            sign negative iff q ∈ {2, 3}
       Σx = x·cosθ_T − y·sinθ_T                Σy = x·sinθ_T + y·cosθ_T        (exact)
       x' = saturate(round_shift(Σx, W), signed(W))       y' likewise (half away from zero)

   In hardware both multipliers read operand registers (``a1``, ``a2``: kd, then x and y;
   ``b1``, ``b2``: the table's ``C_hi``, ``S_hi`` or the interpolation products' operands, then
   ``c_o``, ``s_o``), and the products are registered. Multiplier 1 always takes ``c_o`` and
   multiplier 2 ``s_o``; the pass and ``w`` choose which of x, y feeds which, the signs go onto
   the products (``~P + 1``; the ``+1`` and the offsets' ``a·2**W``, ``a·2**(W−1)`` terms go into
   one ``base`` register, prepared over the two clocks before the sum), and ``round_shift`` is
   computed as ``(Σ1 >> W) + [Σ1[:W] all ones and Σ1 ≥ 0]`` with ``Σ1 = Σ + 2**(W−1) − 1``
   (the same integer, one short increment instead of a second wide adder); saturation tests
   whether the bits from ``W − 1`` up are all equal.

Schedule (clock 0 = the clock ``i.valid`` is high; registers written at the end of each clock;
in brackets the clocks with ``registered``, which adds a register after the table and splits the
final sum, rounding and saturation over three clocks, for clocks above ≈ 70 MHz on an ECP5)::

    0      θ folded: table address, kd; x, y, flags, tag latched
    1      table word out                                    [1: into a register]
    1 [2]  multipliers: kd·C_hi, kd·S_hi
    2 [3]  s_o, c_o
    3 [4]  pass 1 products (the x' pair), base
    4 [5]  pass 2 products (the y' pair), base; o.tag;
           x' = Σ1 of pass 1, rounded, saturated → o.x       [5: Σ1 registered; 6: rounded
                                                              (registered); 7: saturated → o.x]
    5 [6]  y' likewise → o.y; o.valid                         [6: Σ1; 7: rounded; 8: → o.y]

``latency`` 6 [9]; the multipliers are busy on clocks 1, 3, 4 [2, 4, 5] and x, y are held
until clock 4 [5], so a new vector may come every ``interval`` = 4 [5] clocks.

Error against the float rotation by the quantized angle: the integer sine and cosine are within
``0.70·2**−W`` of the true values at W = 16 (rounding to ``W`` bits 0.5, table, interpolation
and truncation the rest; checked over all 2**16 angles), so
``|x' − ideal| ≤ 0.5 + 0.70·(|x| + |y|)·2**−W`` LSB ≤ 1.2 LSB. Measured on the verification
set (10**5 random vectors and the CORDIC's corners): max 0.960 LSB, RMS 0.3025 LSB, against the
CORDIC's 0.870 and 0.296 on the same set (10**6 vectors: 1.005 and 0.303); the ``W``-bit
trigonometric operands cost ≈ 0.1 LSB of peak error.

:class:`RotatorParams` computes every constant once; :class:`Rotator` (gateware) and
:mod:`foc_servo.sim.models.rotator` (bit-true golden model) both use it.
"""

import math

from amaranth.hdl import Array, Assert, Cat, Const, Module, Mux, Signal, signed, unsigned
from amaranth.lib import wiring
from amaranth.lib.memory import Memory

from .fixed import check_bool, is_int
from .cordic import rotation_members

__all__ = ["RotatorParams", "Rotator"]

#: Table precision above the operand width (``Ft = W + TABLE_GUARD``).
TABLE_GUARD = 2
#: Guard bits of the interpolation sums below the table LSB.
INTERP_GUARD = 4
#: Largest number of interpolation bits (the ``kd`` ROM has ``2**(m+1)`` entries, in LUTs).
MAX_INTERP_BITS = 6


def _round(v):
    """Round half up (the table values are never ties)."""
    return math.floor(v + 0.5)


class RotatorParams:
    """Constants of a :class:`Rotator` configuration (validated).

    Parameters are those of :class:`Rotator` (``registered`` only sets ``latency`` and
    ``interval``: the arithmetic is the same). All attributes are plain Python integers (or lists
    of them), computed once, so that gateware and golden model cannot disagree.

    Attributes
    ----------
    width, angle_width, table_bits, tag_width : int
        The (defaulted) parameters.
    interp_bits : int
        ``m = angle_width − 3 − table_bits``; ``D = 2**m`` angle LSBs between table entries.
    table_frac : int
        ``Ft = width + 2``, fraction bits of the table entries.
    table_s, table_c : list of int
        ``S''`` and ``C''`` for ``k = 0 … 2**table_bits − 1`` (signed ``Ft``-bit values).
    table_words : list of int
        The block-RAM contents: ``S'' mod 2**Ft | (C'' mod 2**Ft) << Ft``.
    kd_shift : int
        ``K``: ``kd = round(d·Δ·2**K)``.
    kd : list of int
        ``kd`` for ``d = 0 … D``.
    kd_rom : list of int
        ``kd`` indexed by ``μ·D + θ[:m]`` (``2·D`` entries): ``kd[θ[:m]]``, then
        ``kd[D − θ[:m]]``.
    shift_c, shift_s : int
        Right shifts of ``kd·C_hi`` and ``kd·S_hi`` onto the interpolation sums (``K − 8``,
        ``K − 7``).
    registered : bool
        The parameter.
    latency : int
        Clocks from ``i.valid`` to ``o.valid``: 6, or 9 if ``registered``.
    interval : int
        Fewest clocks between two vectors: 4, or 5 if ``registered``.
    """

    interp_guard = INTERP_GUARD

    def __init__(self, *, width=16, angle_width=None, table_bits=None, tag_width=0,
                 registered=False):
        if not is_int(width) or not 8 <= width <= 24:
            raise TypeError(f"Rotator width must be an integer from 8 to 24, not {width!r}")
        if angle_width is None:
            angle_width = width
        if not is_int(angle_width) or angle_width < 4:
            raise TypeError(f"Rotator angle_width must be None or an integer of at least 4, "
                            f"not {angle_width!r}")
        # First-order interpolation leaves δ²/2 ≤ ((π/4)/2**n)²/2: keep it below 2**−(W+3).
        min_bits = 1
        while (math.pi / 4 / (1 << min_bits)) ** 2 / 2 > 2.0 ** -(width + 3):
            min_bits += 1
        if angle_width < min_bits + 3:
            raise ValueError(f"Rotator angle_width must be at least {min_bits + 3} for width "
                             f"{width}, not {angle_width!r}")
        if table_bits is None:
            table_bits = max(min_bits, angle_width - 3 - MAX_INTERP_BITS)
        if not is_int(table_bits) or table_bits < 1:
            raise TypeError(f"Rotator table_bits must be None or a positive integer, "
                            f"not {table_bits!r}")
        if not is_int(tag_width) or tag_width < 0:
            raise TypeError(f"Rotator tag_width must be a non-negative integer, "
                            f"not {tag_width!r}")
        check_bool("Rotator", "registered", registered)
        if table_bits > angle_width - 3:
            raise ValueError(f"Rotator table_bits must be at most angle_width − 3 = "
                             f"{angle_width - 3}, not {table_bits!r}")
        if table_bits < min_bits:
            raise ValueError(f"Rotator table_bits must be at least {min_bits} for width {width} "
                             f"(interpolation error), not {table_bits!r}")
        if angle_width - 3 - table_bits > MAX_INTERP_BITS:
            raise ValueError(f"Rotator table_bits must be at least angle_width − "
                             f"{3 + MAX_INTERP_BITS} = {angle_width - 3 - MAX_INTERP_BITS}, "
                             f"not {table_bits!r}")

        self.width = w = int(width)
        self.angle_width = aw = int(angle_width)
        self.table_bits = n = int(table_bits)
        self.tag_width = int(tag_width)
        self.registered = registered
        self.latency = 9 if registered else 6
        self.interval = 5 if registered else 4
        self.interp_bits = mb = aw - 3 - n
        self.table_frac = ft = w + TABLE_GUARD
        big_d = 1 << mb
        delta = 2 * math.pi / (1 << aw)

        # Table: S'' = S − 2**(Ft−1) + half, C'' = C − 2**Ft + half (half = 2**(Ft−W−1), the
        # rounding of the final >> (g + 2), pre-added).
        half = 1 << (ft - w - 1)
        self.table_s, self.table_c, self.table_words = [], [], []
        mask = (1 << ft) - 1
        for k in range(1 << n):
            a = k * big_d * delta
            s2 = _round(math.sin(a) * (1 << ft)) - (1 << (ft - 1)) + half
            c2 = _round(math.cos(a) * (1 << ft)) - (1 << ft) + half
            self.table_s.append(s2)
            self.table_c.append(c2)
            self.table_words.append((s2 & mask) | (c2 & mask) << ft)

        # kd = round(d·Δ·2**K) < 2**(W−1) for d ≤ D, K as large as possible.
        k_shift = 0
        while _round(big_d * delta * 2.0 ** (k_shift + 1)) < (1 << (w - 1)):
            k_shift += 1
        self.kd_shift = k_shift
        self.kd = [_round(d * delta * 2.0 ** k_shift) for d in range(big_d + 1)]
        self.kd_rom = self.kd[:big_d] + [self.kd[big_d - d] for d in range(big_d)]
        # kd·C_hi ≈ δ·cos·2**(K + W − 2), kd·S_hi ≈ δ·sin·2**(K + W − 1); the sums are at
        # 2**(Ft + g) = 2**(W + 6).
        self.shift_c = k_shift + w - 2 - (ft + INTERP_GUARD)
        self.shift_s = k_shift + w - 1 - (ft + INTERP_GUARD)
        if self.shift_c < 0:             # cannot happen for width ≥ 8, table_bits ≥ 1
            raise ValueError(f"Rotator configuration {self!r} leaves no interpolation shift")

    def __repr__(self):
        return (f"RotatorParams(width={self.width}, angle_width={self.angle_width}, "
                f"table_bits={self.table_bits}, tag_width={self.tag_width}, "
                f"registered={self.registered})")


class Rotator(wiring.Component):
    """Vector rotator: ``(x, y)`` rotated by θ, from a sine table and two multipliers.

    ``x' = x·cosθ − y·sinθ``, ``y' = x·sinθ + y·cosθ`` (paper eq. (4)–(6)); Park is a rotation
    by −θ, inverse Park by +θ. Gain exactly 1 (θ = 0 passes x, y through unchanged; quarter
    turns are exact swaps and negations, saturated).

    Parameters
    ----------
    width : int
        ``W``, width of x and y in and out and of the multiplier operands, 8 … 24. Any Q
        format (the rotation does not care); in the design, Q1.(W−1).
    angle_width : int or None
        Width of θ, a :class:`~foc_servo.hdl.fixed.BinaryAngle` (a full turn is
        ``2**angle_width``), at least 4; default ``W``.
    table_bits : int or None
        ``n``: the table holds ``2**n`` entries over one octant (45°). At most
        ``angle_width − 3``, at least ``angle_width − 9`` (the ``kd`` ROM) and at least the
        smallest ``n`` keeping the interpolation error ``((π/4)/2**n)²/2`` below
        ``2**−(W+3)`` (9 at W = 16, 13 at W = 24). Default: that smallest ``n``, raised to
        ``angle_width − 9`` for wide angles (W = AW = 16: 512 × 36 bits, one ECP5 DP16KD, one
        RAMB18, five iCE40 SB_RAM40_4K).
    tag_width : int
        Width of an opaque ``tag`` carried alongside the data (0: no tag field).
    registered : bool
        Register the table output, and the final sum and its rounding increment each in a
        clock of their own (latency 9 and interval 5 instead of 6 and 4), for fast clocks.
        Rotator alone on an ECP5-85 (nextpnr, seeds 1–3): 69–71 MHz without (the table's
        clock-to-output, then a multiplier), 111–120 MHz with the table register and the sum
        register (then latency 8); the rounding register (session 4) takes the sum → round →
        saturate path out of the current loop's critical path (94.4 MHz).

    Members
    -------
    i : In(stream.Signature(data.StructLayout({"x": signed(W), "y": signed(W),
        "theta": unsigned(angle_width)[, "tag": unsigned(tag_width)]}), always_ready=True))
        Vector and angle. At most one vector every ``interval`` clocks (an ``Assert`` checks
        it in simulation).
    o : Out(stream.Signature(data.StructLayout({"x": signed(W), "y": signed(W)[,
        "tag": ...]}), always_ready=True))
        Rotated vector, rounded half away from zero, saturated to signed(W) (only a vector
        longer than full scale, e.g. both components at full scale, rotated towards an axis,
        saturates). ``valid`` comes ``latency`` clocks after ``i.valid``; the payload is
        stable while ``valid`` is high.

    Attributes
    ----------
    width, angle_width, table_bits, tag_width : int
        The parameters, defaults resolved.
    registered : bool
        The parameter.
    latency : int
        Clocks from ``i.valid`` to ``o.valid``: 6 (9 if ``registered``).
    interval : int
        Fewest clocks between two vectors: 4 (5 if ``registered``).
    params : RotatorParams
        All derived constants.

    Raises
    ------
    TypeError
        A parameter of the wrong type or outside its basic range.
    ValueError
        ``table_bits`` or ``angle_width`` too small or too large for the other parameters.
    """

    def __init__(self, *, width=16, angle_width=None, table_bits=None, tag_width=0,
                 registered=False):
        p = RotatorParams(width=width, angle_width=angle_width, table_bits=table_bits,
                          tag_width=tag_width, registered=registered)
        self._params = p
        super().__init__(rotation_members(p.width, p.angle_width, p.tag_width))

    params = property(lambda self: self._params)
    width = property(lambda self: self._params.width)
    angle_width = property(lambda self: self._params.angle_width)
    table_bits = property(lambda self: self._params.table_bits)
    tag_width = property(lambda self: self._params.tag_width)
    registered = property(lambda self: self._params.registered)
    latency = property(lambda self: self._params.latency)
    interval = property(lambda self: self._params.interval)

    def elaborate(self, platform):
        m = Module()
        p = self._params
        w, aw, n, mb, ft = p.width, p.angle_width, p.table_bits, p.interp_bits, p.table_frac
        g = p.interp_guard
        sw = signed(w)
        pl = self.i.payload

        # --- Clock 0: fold the angle, address the table, latch the operands ---------------------
        th = pl.theta
        mu = th[aw - 3]
        m.submodules.table = table = Memory(shape=unsigned(2 * ft), depth=1 << n,
                                            init=p.table_words)
        rd = table.read_port(domain="sync")
        m.d.comb += [
            rd.addr.eq(th[mb:aw - 3] ^ mu.replicate(n)),
            rd.en.eq(self.i.valid),
        ]
        kd_rom = Array(Const(v, unsigned(w - 1)) for v in p.kd_rom)

        x_r = Signal(sw, reset_less=True)
        y_r = Signal(sw, reset_less=True)
        swap = Signal(reset_less=True)          # w = q[0] ⊕ μ: |cosθ| is the octant's sine
        neg_c = Signal(reset_less=True)         # cosθ < 0: q ∈ {1, 2}
        neg_s = Signal(reset_less=True)         # sinθ < 0: q ∈ {2, 3}
        with m.If(self.i.valid):
            m.d.sync += [
                x_r.eq(pl.x),
                y_r.eq(pl.y),
                swap.eq(th[aw - 2] ^ mu),
                neg_c.eq(th[aw - 2] ^ th[aw - 1]),
                neg_s.eq(th[aw - 1]),
            ]
        if p.tag_width:
            tag_r = Signal(p.tag_width, reset_less=True)
            with m.If(self.i.valid):
                m.d.sync += tag_r.eq(pl.tag)
        kd = kd_rom[Cat(th[:mb], mu)]

        # valid[j] is high during clock j; the stages' clocks (``t``: registered table output).
        t = int(p.registered)
        c_interp, c_trig, c_pass1, c_pass2 = 1 + t, 2 + t, 3 + t, 4 + t
        valid = [self.i.valid]
        for j in range(1, p.latency):
            v = Signal(name=f"valid{j}")
            m.d.sync += v.eq(valid[-1])
            valid.append(v)
        m.d.sync += self.o.valid.eq(valid[p.latency - 1])
        busy = Cat(*valid[1:p.interval]).any()
        m.d.sync += Assert(~(self.i.valid & busy),
                           f"Rotator: a new vector less than {p.interval} clocks after the "
                           f"previous one")

        # --- The table word (registered with ``registered``) -------------------------------------
        if p.registered:
            word = Signal(2 * ft, reset_less=True)
            with m.If(valid[1]):
                m.d.sync += word.eq(rd.data)
        else:
            word = rd.data
        s_tab = word[:ft].as_signed()
        c_tab = word[ft:].as_signed()

        def hi_parts(s_val, c_val):
            # C_hi = (C'' >> 4) + 2**(W−2), S_hi = (S'' >> 3) + 2**(W−2): the shifted values are
            # within [−2**(W−2), 2**(W−2)), so sign-extending to W − 1 bits and inverting the top
            # bit adds 2**(W−2).
            return Cat(s_val[3:-1], ~s_val[-1]), Cat(c_val[4:], ~c_val[-1])

        # --- The two multipliers: operand registers a1, a2 (kd, then x/y) and b1, b2 (C_hi, S_hi
        #     with ``registered``, then c_o, s_o); products registered ----------------------------
        a1 = Signal(sw, reset_less=True)
        a2 = Signal(sw, reset_less=True)
        b1 = Signal(sw, reset_less=True)        # c_o = round(c·2**W) − 2**W in the passes
        b2 = Signal(sw, reset_less=True)        # s_o = round(s·2**W) − 2**(W−1) in the passes
        if p.registered:
            kd_r = Signal(unsigned(w - 1), reset_less=True)
            with m.If(self.i.valid):
                m.d.sync += kd_r.eq(kd)
            s_hi, c_hi = hi_parts(rd.data[:ft], rd.data[ft:])
            with m.If(valid[1]):
                m.d.sync += [a1.eq(kd_r), a2.eq(kd_r), b1.eq(c_hi), b2.eq(s_hi)]
            m1b, m2b = b1, b2
        else:
            with m.If(self.i.valid):
                m.d.sync += [a1.eq(kd), a2.eq(kd)]
            s_hi, c_hi = hi_parts(s_tab, c_tab)
            m1b = Mux(valid[c_interp], c_hi, b1)
            m2b = Mux(valid[c_interp], s_hi, b2)
        # Pass 1 (x'): multiplier 1 takes x unless swapped; pass 2 (y'): the operands swap.
        # ``early`` is high the clock before pass 2 (low the clock before pass 1).
        early = valid[c_pass1]
        a1_next = Mux(early, a2, Mux(swap, y_r, x_r))
        a2_next = Mux(early, a1, Mux(swap, x_r, y_r))
        with m.If(valid[c_trig] | early):
            m.d.sync += [a1.eq(a1_next), a2.eq(a2_next)]
        p1 = Signal(signed(2 * w), reset_less=True)
        p2 = Signal(signed(2 * w), reset_less=True)
        m.d.sync += [p1.eq(a1 * m1b), p2.eq(a2 * m2b)]

        # --- Interpolated sine and cosine, offset operands ---------------------------------------
        with m.If(valid[c_trig]):
            m.d.sync += [
                b1.eq(((c_tab << g) - (p2 >> p.shift_s)) >> (g + 2)),
                b2.eq(((s_tab << g) + (p1 >> p.shift_c)) >> (g + 2)),
            ]

        # --- Passes 1, 2: signs and the offset terms, prepared over the two clocks before --------
        # Multiplier 1 holds |cosθ| (no swap) or |sinθ| (swap), multiplier 2 the other. base
        # depends on x, y and the flags only: X = sign1·2·a1 + sign2·a2 is computed the clock
        # before the pass, from the operands being loaded, and
        # base = X·2**(W−1) + n1 + n2 + 2**(W−1) − 1 in the pass's clock, registered with the
        # products.
        flip = Mux(early, neg_s, ~neg_s)        # sign of the sinθ term: −sinθ·y, +sinθ·x
        n1e = Mux(swap, flip, neg_c)
        n2e = Mux(swap, neg_c, flip)
        xsum = Signal(signed(w + 3), reset_less=True)
        n1x = Signal(reset_less=True)
        n2x = Signal(reset_less=True)
        m.d.sync += [
            xsum.eq((Mux(n1e, -a1_next, a1_next) << 1) + Mux(n2e, -a2_next, a2_next)),
            n1x.eq(n1e),
            n2x.eq(n2e),
        ]
        neg1 = Signal(reset_less=True)
        neg2 = Signal(reset_less=True)
        base = Signal(signed(2 * w + 3), reset_less=True)
        m.d.sync += [
            neg1.eq(n1x),
            neg2.eq(n2x),
            base.eq((xsum << (w - 1)) + (n1x + n2x + ((1 << (w - 1)) - 1))),
        ]

        # --- Σ1 = ±p1 ± p2 + base (registered if split), rounded, saturated ----------------------
        sigma1 = Signal(signed(2 * w + 4), reset_less=p.registered)
        sum3 = Mux(neg1, ~p1, p1) + Mux(neg2, ~p2, p2) + base
        if p.registered:
            m.d.sync += sigma1.eq(sum3)
        else:
            m.d.comb += sigma1.eq(sum3)
        # The rounding increment and the saturation test (registered between them if split).
        r = Signal(signed(w + 5), reset_less=p.registered)
        rounded = sigma1[w:].as_signed() + (sigma1[:w].all() & ~sigma1[-1])
        if p.registered:
            m.d.sync += r.eq(rounded)
        else:
            m.d.comb += r.eq(rounded)
        top = r[w - 1:]                         # in range iff these bits are all equal
        out = Mux(top.all() | ~top.any(), r[:w].as_signed(), Mux(r[-1], -(1 << (w - 1)),
                                                                 (1 << (w - 1)) - 1))
        with m.If(valid[c_pass2]):
            if p.tag_width:
                m.d.sync += self.o.payload.tag.eq(tag_r)
        with m.If(valid[c_pass2 + 2 * t]):
            m.d.sync += self.o.payload.x.eq(out)
        with m.If(valid[c_pass2 + 2 * t + 1]):
            m.d.sync += self.o.payload.y.eq(out)
        return m
