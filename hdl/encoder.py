# Ref: SPEC.md §2.3 (encoder A/B/Z + Hall, ×4 position counter); §4 (synchronisers, glitch filters);
#      issue 6 item 7 (encoder A line broken at speed: encoder/Hall plausibility check)
"""Encoder and Hall front end: synchronisers, glitch filters, ×4 quadrature decoder with Z index,
Hall sector decoder, the exact electrical angle and an encoder/Hall plausibility check
(:class:`HallPlausibility`).

The electrical position ``e`` counts in 1/cpr of an electrical turn (``cpr = 4·lines``): a
mechanical count moves it by ``pole_pairs`` modulo ``cpr``. The angle is kept exact, never
accumulated from a rounded increment: with the constants ``pole_pairs·2**16 = Qp·cpr + Rp``
(computed with the foundation :class:`~.divider.Divider` whenever ``lines`` or ``pole_pairs``
change) the decoder holds ``(θm, rm)`` with ``em·2**16 = θm·cpr + rm (mod 2**16·cpr)``,
``0 ≤ rm < cpr``, and steps them Bresenham-style::

    up:    rm += Rp; c = rm ≥ cpr; rm −= c·cpr; θm += Qp + c   (mod 2**16)
    down:  rm −= Rp; b = rm < 0;   rm += b·cpr; θm −= Qp + b   (mod 2**16)

so ``θm = floor(em·2**16 / cpr) mod 2**16`` after any number of counts in either direction. The
Z offset ``z = Qz·cpr + Rz`` is added at the output: ``θ = θm + Qz + (rm + Rz ≥ cpr)``, which is
``floor(((em + z) mod cpr)·2**16 / cpr)`` exactly.
"""

from amaranth.hdl import Cat, Const, Module, Mux, Signal, signed
from amaranth.lib import enum, wiring
from amaranth.lib.cdc import FFSynchronizer
from amaranth.lib.wiring import In, Out

from .divider import Divider
from .fixed import check_param, BinaryAngle

__all__ = [
    "GlitchFilter", "QuadratureDecoder", "HallSensor", "HallPlausibility", "EncoderFrontEnd",
    "HALL_CODES", "hall_centres", "hall_boundaries", "quadrature_phase", "angle_constants",
    "ANGLE", "DIVIDER_WAIT", "LINES_WIDTH", "POLE_PAIRS_WIDTH", "CPR_WIDTH",
]

#: The electrical angle format of the whole design.
ANGLE = BinaryAngle(16)
#: Widths of the run-time configuration inputs.
LINES_WIDTH = 16
POLE_PAIRS_WIDTH = 8
#: ``cpr = 4·lines`` fits in ``LINES_WIDTH + 2`` bits.
CPR_WIDTH = LINES_WIDTH + 2

#: Hall code (bit 0 = H_a, bit 1 = H_b, bit 2 = H_c) of 60° sector ``k`` = 0 … 5, for three
#: sensors 120° apart: H_a high for θ_e ∈ [0°, 180°), H_b for [120°, 300°), H_c for [240°, 420°).
#: Sector ``k`` spans θ_e ∈ [60°·k, 60°·(k + 1)); forward rotation runs 5, 1, 3, 2, 6, 4.
HALL_CODES = (0b101, 0b001, 0b011, 0b010, 0b110, 0b100)


def hall_centres(width=16):
    """Sector-centre angles ``round((2k + 1)·2**width / 12)`` (ties up), k = 0 … 5, as raw binary
    angles of ``width`` bits."""
    return tuple(((2 * k + 1) * (1 << (width + 1)) + 12) // 24 for k in range(6))


def hall_boundaries(width=16):
    """Sector-boundary angles ``round(k·2**width / 6)`` (ties up), k = 0 … 5, as raw binary angles
    of ``width`` bits: boundary ``k`` is the start of sector ``k`` (the edge between sectors
    ``k − 1`` and ``k``)."""
    return tuple(((k << (width + 1)) + 6) // 12 for k in range(6))


def quadrature_phase(a, b):
    """Position of the quadrature state within one line: (A, B) = 00 → 0, 10 → 1, 11 → 2,
    01 → 3. Forward (A leads B) increases it by 1 modulo 4. Works on Amaranth values and on
    integers / numpy arrays alike."""
    return (a ^ b) | (b << 1)


def angle_constants(lines, pole_pairs, z_offset):
    """``(Qp, Rp, Qz, Rz, valid)`` for a configuration, as the decoder's divider computes them.

    ``Qp, Rp = divmod(pole_pairs·2**16, cpr)``, ``Qz, Rz = divmod(z_offset·2**16, cpr)``, with the
    quotients kept modulo ``2**16`` and the remainders modulo ``2**CPR_WIDTH`` (the register
    widths); a zero ``cpr`` gives the divider's division-by-zero result (all-ones quotient, zero
    remainder). ``valid`` is the condition under which the decoder counts and may align:
    ``lines ≥ 1``, ``1 ≤ pole_pairs < cpr`` and ``z_offset < cpr``.
    """
    cpr = 4 * lines
    q_mask, r_mask = (1 << ANGLE.width) - 1, (1 << CPR_WIDTH) - 1

    def div(n):
        if cpr == 0:
            return q_mask, 0
        q, r = divmod(n << ANGLE.width, cpr)
        return q & q_mask, r & r_mask

    qp, rp = div(pole_pairs)
    qz, rz = div(z_offset)
    valid = lines >= 1 and 1 <= pole_pairs < cpr and z_offset < cpr
    return qp, rp, qz, rz, bool(valid)


def _divider():
    """The decoder's divider: ``pole_pairs·2**16`` or ``z_offset·2**16`` by ``cpr``."""
    return Divider(width=CPR_WIDTH + ANGLE.width, divisor_width=CPR_WIDTH, signed=False)


def _divider_latency():
    div = _divider()
    div._MustUse__silence = True        # only asked for its latency, never elaborated
    return div.latency


#: Clocks from the start of each of the decoder's divisions to taking its result (the divider's
#: latency + 1: the result is held until taken, so a divider up to 1 clock slower still works).
DIVIDER_WAIT = _divider_latency() + 1


class GlitchFilter(wiring.Component):
    """Per-bit glitch filter with a run-time length.

    Each bit of ``o`` follows the same bit of ``i`` once ``i`` has differed from ``o`` on
    ``length`` consecutive clocks: it has a counter that counts the clocks with ``i ≠ o`` and is
    cleared whenever ``i = o``; when the count reaches ``length`` the output takes the input.
    ``length`` 0 and 1 both make ``o`` a one-clock register of ``i``.

    So a pulse (on the clocked input) shorter than ``length`` clocks never reaches ``o``, a pulse
    of ``length`` clocks or more always does, ``length`` clocks after its start (``max(length,
    1)``). An asynchronous pulse of ``d`` clock periods is sampled on ``floor(d)`` or
    ``ceil(d)`` clocks, so after the synchroniser pulses shorter than ``length − 1`` are always
    rejected and pulses of ``length + 1`` or more are always passed; to reject glitches of up to
    ``n`` clocks, set ``length = n + 1``. A change of ``length`` applies from the next clock on,
    to counts in progress too.

    Parameters
    ----------
    width : int
        Number of independent bits, 1 … 64.
    max_length : int
        Largest ``length``, 1 … 65535 clocks (sets the counter width).

    Members
    -------
    i : In(unsigned(width))
        Synchronised inputs.
    length : In(range(max_length + 1))
        Filter length, in clocks.
    o : Out(unsigned(width))
        Filtered outputs, registered (0 at reset).

    Attributes
    ----------
    latency : int
        Clocks from a change of ``i`` to ``o`` at ``length`` ≤ 1 (1); ``max(length, 1)`` in
        general.
    """

    latency = 1

    def __init__(self, *, width=1, max_length=255):
        self._width = check_param("GlitchFilter", "width", width, 1, 64)
        self._max_length = check_param("GlitchFilter", "max_length", max_length, 1, 65535)
        super().__init__({
            "i": In(width),
            "length": In(range(max_length + 1)),
            "o": Out(width),
        })

    width = property(lambda self: self._width)
    max_length = property(lambda self: self._max_length)

    def elaborate(self, platform):
        m = Module()
        for k in range(self._width):
            cnt = Signal(range(self._max_length + 1), name=f"cnt{k}")
            with m.If(self.i[k] == self.o[k]):
                m.d.sync += cnt.eq(0)
            with m.Elif(cnt + 1 >= self.length):
                m.d.sync += [self.o[k].eq(self.i[k]), cnt.eq(0)]
            with m.Else():
                m.d.sync += cnt.eq(cnt + 1)
        return m


def _add(a, b, cin):
    """``(a + b + cin) mod 2**len(a)`` on one carry chain (the carry-in as a low bit)."""
    return (Cat(cin, a) + Cat(cin, b))[1:len(a) + 1]


def _step(up, x, step, comp, ge_comp, lt_step):
    """One modular step of ``x`` (``0 ≤ x < cpr``) by ``±step``, with ``comp = cpr − step``:
    up ``x ≥ comp ? x − comp : x + step``, down ``x < step ? x + comp : x − step``, on one adder.
    Returns the new value and the carry-in taken (up: the wrap; down: no wrap)."""
    wrap = Mux(up, ge_comp, lt_step)
    neg = up == wrap                    # up and wrapping, or down and not wrapping: subtract
    operand = Mux(wrap, comp, step)
    mask = (1 << len(x)) - 1
    return _add(x, operand ^ Mux(neg, mask, 0), neg), neg


class _Config(enum.Enum, shape=3):
    IDLE = 0
    START_P = 1
    WAIT_P = 2
    START_Z = 3
    WAIT_Z = 4


def _check_z_gate(owner, z_gate):
    if z_gate is not None and (not isinstance(z_gate, int) or isinstance(z_gate, bool)
                               or not 0 <= z_gate <= 3):
        raise TypeError(f"{owner} z_gate must be None or an integer from 0 to 3, not {z_gate!r}")
    return z_gate


class QuadratureDecoder(wiring.Component):
    """×4 quadrature decoder with Z index, position counter and exact electrical position.

    Every clock the (filtered) A/B state is compared with the previous one (see
    :func:`quadrature_phase`): a change by +1 is a forward count (A leads B), by −1 a backward
    count, by 2 (A and B both changed) an illegal transition, which counts nothing.

    **Index.** The index event is the rising edge of ``z`` (``z_gate=None``) or of ``z`` while
    (A, B) is in the quadrature state ``z_gate`` (``(A << 1) | B``): with a gated Z the event marks
    the same quadrature state in both directions, so the position is exact in both; with a plain
    Z edge it may differ by a count between the two directions. When not ``aligned`` (after reset,
    after ``realign``, after a change of ``lines`` or ``pole_pairs``), the next index event sets
    ``aligned``, clears ``count`` and loads the electrical position with ``z_offset``. Later
    index events only strobe ``index``.

    **Configuration.** ``lines``, ``pole_pairs`` and ``z_offset`` are run-time inputs. A change is
    taken in by a sequence of two divisions (``busy`` high for ``config_latency − 1`` clocks)
    and then committed at once. A commit that changes ``lines`` or ``pole_pairs``, or makes
    the configuration invalid, clears ``aligned``, ``count`` and the electrical position; a
    commit that only changes ``z_offset`` moves ``e`` and ``theta`` to the new offset at once. The
    configuration is valid when ``lines ≥ 1``, ``1 ≤ pole_pairs < 4·lines`` and ``z_offset <
    4·lines`` (``config_error`` low); while invalid, nothing counts and nothing aligns.

    Parameters
    ----------
    z_gate : int or None
        Quadrature state (0 … 3, ``(A << 1) | B``) that gates Z, or ``None`` for the plain rising
        edge of Z.

    Members
    -------
    a, b, z : In(1)
        Filtered encoder signals.
    hold : In(1)
        While high the decoder only samples its inputs (no count, no strobe): for the settling
        of the synchronisers and filters after reset.
    lines : In(unsigned(16), init=5000)
        Encoder lines per mechanical turn; ``cpr = 4·lines`` counts per turn.
    pole_pairs : In(unsigned(8), init=4)
        Motor pole pairs.
    z_offset : In(unsigned(18), init=0)
        Electrical position at the index, in 1/cpr of an electrical turn (0 … cpr − 1): a Z
        offset of ``n`` mechanical counts from the rotor's d axis is ``n·pole_pairs mod cpr``.
    realign : In(1)
        Strobe: clear ``aligned`` (the next index event realigns).
    count : Out(unsigned(18))
        Mechanical position, 0 … cpr − 1 counts, wrapping at exactly cpr; 0 at the aligning
        index.
    e : Out(unsigned(18))
        Electrical position ``(pole_pairs·count + z_offset) mod cpr`` once aligned.
    theta : Out(BinaryAngle(16))
        Encoder electrical angle ``floor(e·2**16 / cpr)``, exact (no rounding, no drift).
    step : Out(1)
        Strobe: one count, in the direction ``up`` (the M/T speed counter's edges in the
        default ×4 build, ``Top(mt_edges="x4")``).
    up : Out(1)
        Direction of the last count: 1 forward (A leads B), 0 backward.
    a_rise : Out(1)
        Strobe: the count was a rising edge of A (the M/T speed counter's edges with
        ``Top(mt_edges="a_rising")``; direction ``up``).
    illegal : Out(1)
        Strobe (one clock per event): A and B changed together. The protection block latches it.
    index : Out(1)
        Strobe: an index event (every one, aligning or not).
    aligned : Out(1)
        The encoder position is referred to the index (``e``, ``theta`` valid).
    busy : Out(1)
        A configuration change is being taken in.
    config_error : Out(1)
        The committed configuration is invalid.

    All outputs are registers or sums of registers: :attr:`latency` clocks after the inputs.

    Attributes
    ----------
    latency : int
        Clocks from ``a``/``b``/``z`` to the outputs (1).
    config_latency : int
        Clocks from a change of the configuration inputs (decoder idle) to the new configuration
        being visible on the outputs: ``2·divider_wait + 5`` (79).
    divider_wait : int
        Clocks from the start of each division to taking its result (37).
    """

    latency = 1

    def __init__(self, *, z_gate=None):
        self._z_gate = _check_z_gate("QuadratureDecoder", z_gate)
        super().__init__({
            "a": In(1), "b": In(1), "z": In(1), "hold": In(1),
            "lines": In(LINES_WIDTH, init=5000),
            "pole_pairs": In(POLE_PAIRS_WIDTH, init=4),
            "z_offset": In(CPR_WIDTH, init=0),
            "realign": In(1),
            "count": Out(CPR_WIDTH),
            "e": Out(CPR_WIDTH),
            "theta": Out(ANGLE.shape),
            "step": Out(1), "up": Out(1), "a_rise": Out(1), "illegal": Out(1), "index": Out(1),
            "aligned": Out(1), "busy": Out(1), "config_error": Out(1),
        })

    z_gate = property(lambda self: self._z_gate)

    @property
    def divider_wait(self):
        """Clocks from the start of a division to taking its result (divider latency + 2)."""
        return DIVIDER_WAIT

    @property
    def config_latency(self):
        return 2 * self.divider_wait + 5

    def elaborate(self, platform):
        m = Module()
        m.submodules.divider = div = _divider()
        aw = ANGLE.width

        # --- configuration: committed values and their angle constants ----------------------
        lines0 = self.lines.init
        pp0 = self.pole_pairs.init
        z0 = self.z_offset.init
        qp0, rp0, qz0, rz0, valid0 = angle_constants(lines0, pp0, z0)
        pp_q = Signal(POLE_PAIRS_WIDTH, init=pp0)
        z_q = Signal(CPR_WIDTH, init=z0)
        qp = Signal(aw, init=qp0)
        rp = Signal(CPR_WIDTH, init=rp0)
        qz = Signal(aw, init=qz0)
        rz = Signal(CPR_WIDTH, init=rz0)
        valid = Signal(init=valid0)
        # cpr − Rz, cpr − z, cpr − Rp, cpr − pole_pairs, cpr − 1: the wrap tests of the
        # position steps and of the output sums as one comparison each, on registers. The
        # remainders Rz, Rp are below cpr (0 for cpr = 0), but z and pole_pairs may exceed cpr
        # in an invalid configuration: cpr − z and cpr − pole_pairs are signed, so that
        # em ≥ cpr − z stays em + z ≥ cpr there too (an unsigned difference would wrap).
        cpr_rz = Signal(CPR_WIDTH + 1, init=4 * lines0 - rz0)
        cpr_z = Signal(signed(CPR_WIDTH + 2), init=4 * lines0 - z0)
        cpr_rp = Signal(CPR_WIDTH + 1, init=4 * lines0 - rp0)
        cpr_pp = Signal(signed(CPR_WIDTH + 2), init=4 * lines0 - pp0)
        cpr_m1 = Signal(CPR_WIDTH, init=4 * lines0 - 1)
        # Pending configuration and its first quotient while the divisions run. When idle the
        # pending values equal the committed ones (a commit copies them; they start equal), so
        # the inputs are compared with them alone; whether ``lines`` or ``pole_pairs`` change is
        # noted when the change is taken in (``lp_changed``) for the commit.
        lines_p = Signal(LINES_WIDTH, init=lines0)
        pp_p = Signal(POLE_PAIRS_WIDTH, init=pp0)
        z_p = Signal(CPR_WIDTH, init=z0)
        lp_changed = Signal()
        qp_p = Signal(aw)
        rp_p = Signal(CPR_WIDTH)
        state = Signal(_Config)
        cpr_p = Cat(Const(0, 2), lines_p)

        # The divider's result is taken a fixed `wait` clocks after each division starts (its
        # output is held until taken), so the commit time does not depend on the divider's exact
        # timing as long as it is at most `wait + 1` clocks.
        wait = self.divider_wait
        timer = Signal(range(wait + 1))
        m.d.comb += [
            self.busy.eq(state != _Config.IDLE),
            self.config_error.eq(~valid),
            div.i.payload.divisor.eq(cpr_p),
            div.i.payload.dividend.eq(Mux(state == _Config.START_P, pp_p, z_p) << aw),
            div.i.valid.eq((state == _Config.START_P) | (state == _Config.START_Z)),
        ]
        commit = Signal()
        take = Signal()
        m.d.comb += [
            take.eq(((state == _Config.WAIT_P) | (state == _Config.WAIT_Z)) &
                    (timer == wait) & div.o.valid),
            div.o.ready.eq(take),
        ]
        quotient = div.o.payload.quotient[:aw]
        remainder = div.o.payload.remainder
        with m.Switch(state):
            with m.Case(_Config.IDLE):
                lp_change = (self.lines != lines_p) | (self.pole_pairs != pp_p)
                with m.If(lp_change | (self.z_offset != z_p)):
                    m.d.sync += [lines_p.eq(self.lines), pp_p.eq(self.pole_pairs),
                                 z_p.eq(self.z_offset), lp_changed.eq(lp_change),
                                 state.eq(_Config.START_P)]
            with m.Case(_Config.START_P, _Config.START_Z):
                with m.If(div.i.ready):
                    m.d.sync += [timer.eq(0), state.eq(state.as_value() + 1)]
            with m.Case(_Config.WAIT_P, _Config.WAIT_Z):
                with m.If(timer != wait):
                    m.d.sync += timer.eq(timer + 1)
                with m.If(take):
                    with m.If(state == _Config.WAIT_P):
                        m.d.sync += [qp_p.eq(quotient), rp_p.eq(remainder),
                                     state.eq(_Config.START_Z)]
                    with m.Else():
                        m.d.comb += commit.eq(1)
                        m.d.sync += state.eq(_Config.IDLE)
        # The pending configuration's validity and whether the commit restarts the counters,
        # both from registers: lines_p, pp_p, z_p and lp_changed change only in IDLE, at least
        # 2·divider_wait clocks before the commit that reads these, so their registered copies
        # are the same values there (cycle-identical; the compares and the fan-out of `restart`
        # into the counters' resets were in one clock before, an ECP5 near-critical path).
        new_valid = Signal(init=valid0)
        restart_cause = Signal(init=not valid0)
        valid_now = (lines_p != 0) & (pp_p != 0) & (pp_p < cpr_p) & (z_p < cpr_p)
        m.d.sync += [new_valid.eq(valid_now), restart_cause.eq(lp_changed | ~valid_now)]
        restart = Signal()
        m.d.comb += restart.eq(commit & restart_cause)
        with m.If(commit):
            m.d.sync += [
                pp_q.eq(pp_p), z_q.eq(z_p),
                qp.eq(qp_p), rp.eq(rp_p), qz.eq(quotient), rz.eq(remainder),
                valid.eq(new_valid), cpr_rz.eq(cpr_p - remainder), cpr_z.eq(cpr_p - z_p),
                cpr_rp.eq(cpr_p - rp_p), cpr_pp.eq(cpr_p - pp_p), cpr_m1.eq(cpr_p - 1),
            ]

        # --- quadrature decoding ------------------------------------------------------------
        a_prev = Signal()
        b_prev = Signal()
        zc_prev = Signal()
        m.d.sync += [a_prev.eq(self.a), b_prev.eq(self.b)]
        delta = Signal(2)
        m.d.comb += delta.eq(quadrature_phase(self.a, self.b) - quadrature_phase(a_prev, b_prev))
        fwd = ~self.hold & (delta == 1)
        bwd = ~self.hold & (delta == 3)
        if self._z_gate is None:
            zc = self.z
        else:
            zc = self.z & (Cat(self.b, self.a) == self._z_gate)
        m.d.sync += zc_prev.eq(zc)
        index = ~self.hold & zc & ~zc_prev

        m.d.sync += [
            self.step.eq(fwd | bwd),
            self.a_rise.eq((fwd | bwd) & self.a & ~a_prev),
            self.illegal.eq(~self.hold & (delta == 2)),
            self.index.eq(index),
        ]
        with m.If(fwd | bwd):
            m.d.sync += self.up.eq(fwd)

        # --- position counters --------------------------------------------------------------
        em = Signal(CPR_WIDTH)          # pole_pairs·count mod cpr
        thm = Signal(aw)                # floor(em·2**16 / cpr) mod 2**16
        rm = Signal(CPR_WIDTH)          # em·2**16 − thm·cpr (mod 2**16·cpr), 0 ≤ rm < cpr
        # Each wrap test compares a register with a per-configuration constant, side by side
        # with the candidate sums (em + p ≥ cpr ⇔ em ≥ cpr − p; rm − Rp < 0 ⇔ rm < Rp). One adder
        # per counter serves both directions: the wrap test picks the operand (the step or
        # cpr − step) and whether it is subtracted (see _step). Counting only happens with a
        # valid configuration, where cpr − pole_pairs and cpr − Rp lie in 1 … cpr − 1.
        fwd_c = Signal()
        m.d.comb += fwd_c.eq(fwd)
        c_wrap = Mux(fwd_c, self.count == cpr_m1, self.count == 0)
        count_next = Mux(c_wrap, Mux(fwd_c, 0, cpr_m1),
                         (self.count + Mux(fwd_c, 1, Const(-1, CPR_WIDTH)))[:CPR_WIDTH])
        em_next, _ = _step(fwd_c, em, pp_q, cpr_pp[:CPR_WIDTH], em >= cpr_pp[:CPR_WIDTH],
                           em < pp_q)
        rm_next, cin = _step(fwd_c, rm, rp, cpr_rp[:CPR_WIDTH], rm >= cpr_rp, rm < rp)
        # up: θm + Qp + carry; down: θm − Qp − borrow = θm + ~Qp + (1 − borrow).
        thm_next = _add(thm, qp ^ Mux(fwd_c, 0, (1 << aw) - 1), cin)
        with m.If(valid & (fwd | bwd)):
            m.d.sync += [self.count.eq(count_next), em.eq(em_next), rm.eq(rm_next),
                         thm.eq(thm_next)]
        arm = ~self.aligned | self.realign
        with m.If(valid & index & arm):
            m.d.sync += [self.aligned.eq(1), self.count.eq(0), em.eq(0), thm.eq(0), rm.eq(0)]
        with m.Elif(self.realign):
            m.d.sync += self.aligned.eq(0)
        with m.If(restart):
            m.d.sync += [self.aligned.eq(0), self.count.eq(0), em.eq(0), thm.eq(0), rm.eq(0)]

        # --- outputs: the Z offset added to the electrical position -------------------------
        # e = (em + z) mod cpr and θ = θm + Qz + (rm + Rz ≥ cpr), with the wrap tests made on
        # the registers alone (em ≥ cpr − z, rm ≥ cpr − Rz): one carry chain before the sums,
        # not two. θ's wrap test is the low part of the same carry chain as its sum: rm − (cpr −
        # Rz) (as rm + ~(cpr − Rz) + 1) carries out exactly when rm ≥ cpr − Rz, and that carry
        # goes on into θm + Qz. (A compare's carry chain feeding the sum's carry-in through a
        # LUT was the whole ECP5 top's critical path, docs/AREA.md.)
        wz = len(cpr_rz)
        m.d.comb += [
            self.e.eq(Mux(em >= cpr_z, em - cpr_z, em + z_q)),
            self.theta.eq(_add(Cat(rm, Const(0, wz - len(rm)), thm), Cat(~cpr_rz, qz), 1)[wz:]),
        ]
        return m


class HallSensor(wiring.Component):
    """Three Hall switches → 60° sector, sector-centre angle and Hall fault.

    Codes follow :data:`HALL_CODES` (120° sensor placement). The codes 000 and 111 cannot occur
    with healthy sensors: they raise ``fault`` (a level, as long as the code lasts) and leave
    ``sector`` and ``theta`` at their last valid value.

    Members
    -------
    h : In(unsigned(3))
        Filtered Hall signals, bit 0 = H_a, bit 1 = H_b, bit 2 = H_c.
    offset : In(BinaryAngle(16))
        Added to the sector-centre angle (sensor placement correction), modulo a turn.
    hold : In(1)
        While high no ``fault`` (settling after reset).
    sector : Out(range(6))
        60° sector 0 … 5: θ_e ∈ [60°·sector, 60°·(sector + 1)) + offset.
    theta : Out(BinaryAngle(16))
        Sector centre ``hall_centres()[sector] + offset`` (mod 2**16); before the first valid
        code, the centre of sector 0 without offset.
    valid : Out(1)
        A valid code has been seen since reset.
    fault : Out(1)
        The code is 000 or 111.

    Attributes
    ----------
    latency : int
        Clocks from ``h`` to the outputs (1).
    """

    latency = 1

    def __init__(self):
        super().__init__({
            "h": In(3),
            "offset": In(ANGLE.shape),
            "hold": In(1),
            "sector": Out(range(6)),
            "theta": Out(ANGLE.shape, init=hall_centres()[0]),
            "valid": Out(1),
            "fault": Out(1),
        })

    def elaborate(self, platform):
        m = Module()
        centres = hall_centres(ANGLE.width)
        m.d.sync += self.fault.eq(~self.hold & ((self.h == 0) | (self.h == 7)))
        with m.Switch(self.h):
            for k, code in enumerate(HALL_CODES):
                with m.Case(code):
                    m.d.sync += [
                        self.sector.eq(k),
                        self.theta.eq(centres[k] + self.offset),
                        self.valid.eq(1),
                    ]
        return m


class HallPlausibility(wiring.Component):
    """Encoder/Hall plausibility check: the encoder's electrical angle against the Hall edges.

    A broken encoder line (say A held) does not make illegal transitions: B still toggles, the
    count dithers by ±1 and the encoder angle stops while the rotor turns. The Hall sensors keep
    advancing, and every Hall edge marks a known electrical angle, the boundary between two
    sectors. At each **Hall edge** (``sector`` changes; adjacent sectors only, see below) the
    block forms the signed difference, modulo a turn,

    ``d = theta − (hall_boundaries()[j] + offset)``,  ``j`` = the new sector going forward, the
    old one going backward,

    and applies two checks:

    * **absolute** (``aligned``): the encoder angle is referred to the rotor, so ``|d|`` must be
      at most ``tolerance``;
    * **relative** (not ``aligned``: before the first Z index the encoder angle has an unknown
      offset): if the previous Hall edge went the same way (the rotor crossed a whole sector)
      and the encoder angle's reference did not move since (no configuration change, no
      alignment in between), the encoder must have advanced by one sector too:
      ``|d − d_prev|`` at most ``tolerance``. A stuck encoder line advances by nothing.

    A Hall edge that fails a check, or that skips a sector (from ``k`` to ``k ± 2`` or ``k + 3``:
    impossible for a turning rotor with sound sensors), is a **miss**; one that passes every
    check that applies is a **pass**; an edge to which no check applies (before alignment: the
    first edge, or one that reverses the direction) leaves the count alone. ``misses``
    consecutive misses (0 acts as 1) raise ``fault``, a one-clock strobe on that miss and on
    every further one until a pass: the protection block latches it. Hall edges from a reversal
    near a boundary (bouncing ``k → k+1 → k …``) are all at the same boundary and reverse the
    direction each time, so they pass the absolute check and skip the relative one.

    Detection after the encoder stops at an angle ``φ`` past a boundary (sector 60°, tolerance
    ``tol`` < 60°, N = ``misses``): every later edge in the direction of rotation misses, the
    first one only if ``60° − φ > tol``; so the fault comes at the N-th (``φ < 60° − tol``) or
    (N + 1)-th edge after the stop, after ``N·60° − φ`` or ``(N + 1)·60° − φ`` of rotation: at
    most 105° (1.75 sectors) for N = 1 and ``tol`` = 45°, 165° for N = 2.

    Why N = 1 by default: a second miss costs a whole sector of rotation (2.5 ms at 1000 r/min)
    and buys little immunity — a Hall glitch that passes the filter makes two edges at the same
    boundary with the same ``d``, both misses or both passes. In the closed loop (issue 6 item 7
    scenario, 1000 r/min) the frozen angle drives the phase currents past the over-current limit
    about 4 ms after the break: N = 1 trips on ``encoder_hall`` first (2.7 ms), N = 2 does not.

    Cost: a 16-bit addition and subtraction for ``d``, one subtraction for ``d − d_prev``, two
    magnitude tests (a comparison and the carry out of ``x + tolerance``), a 6-entry constant
    table and ≈ 135 flip-flops, no multiplier or divider. Pipelined in three clocks (the edge,
    the inputs and ``boundary + offset`` registered; ``d`` and ``d − d_prev`` registered; the
    checks) for 100 MHz on an ECP5: the Hall edges are thousands of clocks apart, the two
    clocks cost nothing.

    Members
    -------
    theta : In(BinaryAngle(16))
        Encoder electrical angle (the :class:`QuadratureDecoder`'s, aligned or not).
    aligned : In(1)
        ``theta`` is referred to the rotor: the absolute check applies, else the relative one.
    restart : In(1)
        ``theta``'s reference may move (a configuration change in progress, or an invalid
        configuration): forget the previous edge for the relative check.
    sector : In(range(6))
        Hall sector (the :class:`HallSensor`'s; a change is a Hall edge).
    valid : In(1)
        A valid Hall code has been seen (``sector`` means something).
    hold : In(1)
        While high no edge is taken (settling after reset).
    offset : In(BinaryAngle(16))
        Hall offset, as the :class:`HallSensor`'s.
    tolerance : In(unsigned(16), init=8192)
        Largest ``|d|`` (and ``|d − d_prev|``) that is not a miss, binary angle (8192 = 45°).
    misses : In(unsigned(4), init=1)
        Consecutive misses that raise ``fault``, 1 … 15 (0 acts as 1).
    edge : Out(1)
        Strobe: a Hall edge was taken.
    miss : Out(1)
        Strobe: that edge was a miss.
    fault : Out(1)
        Strobe: a miss with ``misses`` or more consecutive misses.
    error : Out(signed(16))
        ``d`` at the last Hall edge between adjacent sectors, binary angle read as signed
        ([−180°, 180°)): once aligned, the error of ``offset`` plus the Hall sensors' own.

    Attributes
    ----------
    latency : int
        Clocks from ``sector``/``theta`` to the outputs (3). The outputs are those of the
        unpipelined check (all inputs taken in the same clock) delayed by two clocks.
    """

    latency = 3

    def __init__(self):
        super().__init__({
            "theta": In(ANGLE.shape),
            "aligned": In(1),
            "restart": In(1),
            "sector": In(range(6)),
            "valid": In(1),
            "hold": In(1),
            "offset": In(ANGLE.shape),
            "tolerance": In(ANGLE.width, init=ANGLE.turn // 8),
            "misses": In(4, init=1),
            "edge": Out(1),
            "miss": Out(1),
            "fault": Out(1),
            "error": Out(signed(ANGLE.width)),
        })

    def elaborate(self, platform):
        m = Module()
        aw = ANGLE.width
        sector_q = Signal(range(6))
        have_q = Signal()               # a valid sector was seen in the previous clock
        aligned_q = Signal()
        m.d.sync += [sector_q.eq(self.sector), have_q.eq(self.valid & ~self.hold),
                     aligned_q.eq(self.aligned)]

        # Clock 1: the edge and its direction, the boundary, the inputs, registered.
        edge = Signal()
        fwd = Signal()
        bwd = Signal()
        m.d.comb += [
            edge.eq(have_q & ~self.hold & (self.sector != sector_q)),
            fwd.eq(self.sector == Mux(sector_q == 5, 0, sector_q + 1)),
            bwd.eq(self.sector == Mux(sector_q == 0, 5, sector_q - 1)),
        ]
        bound = Signal(aw)
        with m.Switch(Mux(fwd, self.sector, sector_q)):
            for k, b in enumerate(hall_boundaries(aw)):
                with m.Case(k):
                    m.d.comb += bound.eq(b)
        edge1, fwd1, adjacent1, aligned1, restart1, jump1 = (
            Signal(name=f"{n}1") for n in ("edge", "fwd", "adjacent", "aligned", "restart",
                                           "jump"))
        theta1, bo1, tol1 = (Signal(aw, name=f"{n}1") for n in ("theta", "bo", "tol"))
        need1 = Signal(4)               # misses − 1 (0 acts as 1): the count that faults
        m.d.sync += [
            edge1.eq(edge), fwd1.eq(fwd), adjacent1.eq(fwd | bwd), aligned1.eq(self.aligned),
            restart1.eq(self.restart), jump1.eq(self.restart | (self.aligned != aligned_q)),
            theta1.eq(self.theta), bo1.eq(bound + self.offset),
            tol1.eq(self.tolerance), need1.eq(Mux(self.misses == 0, 0, self.misses - 1)),
        ]

        # Clock 2: d = θ − (boundary + offset) and dd = d − d_prev (mod a turn), both registered
        # so that clock 3's compare starts at flip-flops (the whole top's 100 MHz on the ECP5).
        # d_prev is d_q as clock 3 will hold it when this d reaches it: d2 if the edge in
        # clock 3 now updates d_q, else d_q (the block alone may see edges in consecutive
        # clocks). Clock for clock the outputs of the subtraction d2 − d_q it replaces (no
        # Assert of it here: synthesis would keep the subtractor for it, +49 iCE40 LUT4 and
        # +32 carries; tests/test_encoder.py checks it against the model in every clock).
        edge2, fwd2, adjacent2, aligned2, restart2, jump2 = (
            Signal(name=f"{n}2") for n in ("edge", "fwd", "adjacent", "aligned", "restart",
                                           "jump"))
        d2 = Signal(aw)
        dd2 = Signal(aw)
        tol2 = Signal(aw)
        need2 = Signal(4)
        dir_q = Signal()                # the previous edge went forward
        d_q = Signal(aw)                # d at the previous edge
        d_new = Signal(aw)
        m.d.comb += d_new.eq(theta1 - bo1)
        m.d.sync += [
            edge2.eq(edge1), fwd2.eq(fwd1), adjacent2.eq(adjacent1), aligned2.eq(aligned1),
            restart2.eq(restart1), jump2.eq(jump1), need2.eq(need1),
            d2.eq(d_new), dd2.eq(d_new - Mux(edge2 & adjacent2, d2, d_q)), tol2.eq(tol1),
        ]

        # Clock 3: the checks and the miss count, on the state of the previous edges.
        ref_ok = Signal()               # d_q is comparable with d now
        count = Signal(4)               # consecutive misses, saturating at 15
        # The two checks never apply together: one magnitude comparison serves both. For x
        # read as signed, |x| > tol ⇔ tol < x < 2**aw − tol with x read as unsigned (never
        # true for tol ≥ 2**(aw−1)): two carry chains side by side, no negation; the second
        # as x + tol < 2**aw (no carry out), so 2**aw − tol needs no subtractor of its own.
        x = Mux(aligned2, d2, dd2)
        over = (x > tol2) & ~(x + tol2)[aw]
        abs_miss = aligned2 & over
        rel_check = ~aligned2 & ref_ok & ~jump2 & (fwd2 == dir_q) & adjacent2
        rel_miss = rel_check & over
        miss = Signal()
        passed = Signal()
        m.d.comb += [
            miss.eq(edge2 & (~adjacent2 | abs_miss | rel_miss)),
            passed.eq(edge2 & adjacent2 & (aligned2 | rel_check) & ~abs_miss & ~rel_miss),
        ]

        with m.If(edge2):
            m.d.sync += [dir_q.eq(fwd2), ref_ok.eq(adjacent2 & ~restart2)]
            with m.If(adjacent2):
                m.d.sync += [d_q.eq(d2), self.error.eq(d2)]
        with m.Elif(jump2):
            m.d.sync += ref_ok.eq(0)
        with m.If(miss):
            m.d.sync += count.eq(Mux(count == 15, 15, count + 1))
        with m.Elif(passed):
            m.d.sync += count.eq(0)
        m.d.sync += [
            self.edge.eq(edge2),
            self.miss.eq(miss),
            self.fault.eq(miss & (count >= need2)),
        ]
        return m


class EncoderFrontEnd(wiring.Component):
    """Encoder A/B/Z and Hall inputs → position, strobes, Hall sector and electrical angle θ_e.

    Pins → two-flop :class:`~amaranth.lib.cdc.FFSynchronizer` → :class:`GlitchFilter` →
    :class:`QuadratureDecoder` and :class:`HallSensor` → :class:`HallPlausibility` (the
    decoder's angle against the Hall edges). ``theta`` is the Hall sector centre until the
    decoder is aligned by the first index (the paper's soft start), then the exact encoder
    angle. For ``length + 4`` clocks after reset (the synchronisers and filters settling) the
    decoder, the Hall sensor and the plausibility check are held (``ready`` low): no count, no
    strobe, no fault.

    Parameters
    ----------
    max_length : int
        Largest glitch filter length, clocks (1 … 65535).
    z_gate : int or None
        See :class:`QuadratureDecoder`.

    Members
    -------
    a, b, z : In(1)
        Encoder pins (asynchronous).
    hall : In(unsigned(3))
        Hall pins (asynchronous), bit 0 = H_a, bit 1 = H_b, bit 2 = H_c.
    length : In(range(max_length + 1))
        Glitch filter length for all seven inputs, clocks (0, 1: no filtering).
    lines, pole_pairs, z_offset, realign
        See :class:`QuadratureDecoder`.
    hall_offset : In(BinaryAngle(16))
        See :class:`HallSensor` ``offset``.
    hall_tolerance : In(unsigned(16), init=8192)
        See :class:`HallPlausibility` ``tolerance`` (binary angle; 8192 = 45°).
    hall_misses : In(unsigned(4), init=1)
        See :class:`HallPlausibility` ``misses``.
    count, e, step, up, a_rise, illegal, index, aligned, busy, config_error
        From the :class:`QuadratureDecoder`.
    hall_sector, hall_valid, hall_fault
        From the :class:`HallSensor` (``sector``, ``valid``, ``fault``).
    hall_edge, hall_miss, plausibility, hall_error
        From the :class:`HallPlausibility` (``edge``, ``miss``, ``fault``, ``error``), one clock
        after the Hall sector and encoder angle they compare (:attr:`plausibility_latency`).
    theta : Out(BinaryAngle(16))
        Electrical angle θ_e: the decoder's exact angle when ``aligned``, else the Hall angle.
    ready : Out(1)
        The inputs have settled since reset.

    Attributes
    ----------
    latency : int
        Clocks from a pin change to the outputs with ``length`` ≤ 1 (4: two synchroniser flops,
        the filter register, the decoder); add ``length − 1`` for a longer filter.
    plausibility_latency : int
        The same for ``hall_edge``, ``hall_miss``, ``plausibility`` and ``hall_error`` (7).
    """

    latency = 4
    plausibility_latency = latency + HallPlausibility.latency
    sync_stages = 2

    def __init__(self, *, max_length=255, z_gate=None):
        self._max_length = check_param("EncoderFrontEnd", "max_length", max_length, 1, 65535)
        _check_z_gate("EncoderFrontEnd", z_gate)   # before any child exists (no unused child)
        self._decoder = QuadratureDecoder(z_gate=z_gate)
        self._filter = GlitchFilter(width=6, max_length=max_length)
        self._hall = HallSensor()
        self._plausibility = HallPlausibility()
        super().__init__({
            "a": In(1), "b": In(1), "z": In(1), "hall": In(3),
            "length": In(range(max_length + 1)),
            "lines": In(LINES_WIDTH, init=5000),
            "pole_pairs": In(POLE_PAIRS_WIDTH, init=4),
            "z_offset": In(CPR_WIDTH, init=0),
            "hall_offset": In(ANGLE.shape),
            "hall_tolerance": In(ANGLE.width, init=ANGLE.turn // 8),
            "hall_misses": In(4, init=1),
            "realign": In(1),
            "count": Out(CPR_WIDTH), "e": Out(CPR_WIDTH), "theta": Out(ANGLE.shape),
            "step": Out(1), "up": Out(1), "a_rise": Out(1), "illegal": Out(1), "index": Out(1),
            "aligned": Out(1), "busy": Out(1), "config_error": Out(1),
            "hall_sector": Out(range(6)), "hall_valid": Out(1), "hall_fault": Out(1),
            "hall_edge": Out(1), "hall_miss": Out(1), "plausibility": Out(1),
            "hall_error": Out(signed(ANGLE.width)),
            "ready": Out(1),
        })

    max_length = property(lambda self: self._max_length)
    z_gate = property(lambda self: self._decoder.z_gate)
    config_latency = property(lambda self: self._decoder.config_latency)

    def elaborate(self, platform):
        m = Module()
        m.submodules.filter = flt = self._filter
        m.submodules.decoder = dec = self._decoder
        m.submodules.hall = hall = self._hall
        m.submodules.plausibility = plaus = self._plausibility

        pins = Signal(6)
        m.submodules.sync = FFSynchronizer(Cat(self.a, self.b, self.z, self.hall), pins,
                                           stages=self.sync_stages)
        m.d.comb += [flt.i.eq(pins), flt.length.eq(self.length)]

        settle = Signal(range(self._max_length + 5))
        with m.If(~self.ready):
            m.d.sync += settle.eq(settle + 1)
            with m.If(settle + 1 >= self.length + 4):
                m.d.sync += self.ready.eq(1)

        m.d.comb += [
            dec.a.eq(flt.o[0]), dec.b.eq(flt.o[1]), dec.z.eq(flt.o[2]), dec.hold.eq(~self.ready),
            dec.lines.eq(self.lines), dec.pole_pairs.eq(self.pole_pairs),
            dec.z_offset.eq(self.z_offset), dec.realign.eq(self.realign),
            hall.h.eq(flt.o[3:6]), hall.offset.eq(self.hall_offset), hall.hold.eq(~self.ready),
        ]
        for name in ("count", "e", "step", "up", "a_rise", "illegal", "index", "aligned", "busy",
                     "config_error"):
            m.d.comb += getattr(self, name).eq(getattr(dec, name))
        m.d.comb += [
            self.hall_sector.eq(hall.sector),
            self.hall_valid.eq(hall.valid),
            self.hall_fault.eq(hall.fault),
            self.theta.eq(Mux(dec.aligned, dec.theta, hall.theta)),
        ]
        m.d.comb += [
            plaus.theta.eq(dec.theta), plaus.aligned.eq(dec.aligned),
            plaus.restart.eq(dec.busy | dec.config_error),
            plaus.sector.eq(hall.sector), plaus.valid.eq(hall.valid), plaus.hold.eq(~self.ready),
            plaus.offset.eq(self.hall_offset), plaus.tolerance.eq(self.hall_tolerance),
            plaus.misses.eq(self.hall_misses),
            self.hall_edge.eq(plaus.edge), self.hall_miss.eq(plaus.miss),
            self.plausibility.eq(plaus.fault), self.hall_error.eq(plaus.error),
        ]
        return m
