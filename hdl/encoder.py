# Ref: SPEC.md §2.3 (encoder A/B/Z + Hall, ×4 position counter); §4 (synchronisers, glitch filters);
#      issue 6 item 7 (encoder A line broken at speed: encoder/Hall plausibility check)
"""Encoder and Hall front end: synchronisers, glitch filters, ×4 quadrature decoder with Z index,
Hall sector decoder, the exact electrical angle and an encoder/Hall plausibility check
(:class:`HallPlausibility`).

The electrical position ``e`` counts in 1/cpr of an electrical turn (``cpr = 4·lines``): a
mechanical count moves it by ``pole_pairs`` modulo ``cpr``. The angle is kept exact, never
accumulated from a rounded increment: with the constants ``pole_pairs·2**16 = Qp·cpr + Rp``
(computed by the decoder's own restoring division, :func:`divide_angle`, whenever ``lines`` or
``pole_pairs`` change) the decoder holds ``(θm, rm)`` with ``em·2**16 = θm·cpr + rm (mod 2**16·cpr)``,
``0 ≤ rm < cpr``, and steps them Bresenham-style::

    up:    rm += Rp; c = rm ≥ cpr; rm −= c·cpr; θm += Qp + c   (mod 2**16)
    down:  rm −= Rp; b = rm < 0;   rm += b·cpr; θm −= Qp + b   (mod 2**16)

so ``θm = floor(em·2**16 / cpr) mod 2**16`` after any number of counts in either direction. The
Z offset ``z = Qz·cpr + Rz`` is added at the output: ``θ = θm + Qz + (rm + Rz ≥ cpr)``, which is
``floor(((em + z) mod cpr)·2**16 / cpr)`` exactly.
"""

from amaranth.hdl import Cat, Const, Module, Mux, Signal, signed
from amaranth.lib import wiring
from amaranth.lib.cdc import FFSynchronizer
from amaranth.lib.wiring import In, Out

from .fixed import check_bool, check_param, BinaryAngle

__all__ = [
    "GlitchFilter", "QuadratureDecoder", "HallSensor", "HallPlausibility", "EncoderFrontEnd",
    "HALL_CODES", "hall_centres", "hall_boundaries", "quadrature_phase", "angle_constants",
    "divide_angle", "ANGLE", "DIVISION_STEPS", "LINES_WIDTH", "POLE_PAIRS_WIDTH", "CPR_WIDTH",
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
    """``(Qp, Rp, Qz, Rz, valid)`` for a configuration, as the decoder's divisions compute them.

    ``Qp, Rp = divmod(pole_pairs·2**16, cpr)``, ``Qz, Rz = divmod(z_offset·2**16, cpr)`` in a
    valid configuration; in an invalid one whatever :func:`divide_angle` leaves. ``valid`` is
    the condition under which the decoder counts and may align: ``lines ≥ 1``,
    ``1 ≤ pole_pairs < cpr`` and ``z_offset < cpr``.
    """
    cpr = 4 * lines
    qp, rp = divide_angle(pole_pairs, cpr)
    qz, rz = divide_angle(z_offset, cpr)
    valid = lines >= 1 and 1 <= pole_pairs < cpr and z_offset < cpr
    return qp, rp, qz, rz, bool(valid)


#: Quotient bits of the decoder's configuration divisions, one per clock: the angle's width.
DIVISION_STEPS = ANGLE.width


def divide_angle(n, cpr):
    """``(q, r)`` as the decoder's restoring division of ``n·2**16`` by ``cpr`` leaves them.

    The division runs in place on the decoder's own 16 + 18-bit working registers: the partial
    remainder starts as ``n`` (the dividend's low 16 bits are zeros) and each of the 16 steps
    doubles it and subtracts ``cpr`` if that fits, shifting the quotient bit in. For
    ``n < cpr`` (every valid configuration) this is ``divmod(n·2**16, cpr)``; otherwise (an
    invalid configuration, ``config_error``) the remainder leaves its 18 bits and ``(q, r)`` is
    whatever the 16 steps leave (for ``cpr = 0``: ``q`` all ones), reproduced here bit for bit.
    """
    q_mask, r_mask = (1 << ANGLE.width) - 1, (1 << CPR_WIDTH) - 1
    q, r = 0, n & r_mask
    for _ in range(DIVISION_STEPS):
        trial = r << 1
        fits = trial >= cpr
        r = (trial - cpr if fits else trial) & r_mask
        q = ((q << 1) | fits) & q_mask
    return q, r


class GlitchFilter(wiring.Component):
    """Per-bit glitch filter with a run-time length.

    Each bit of ``o`` follows the same bit of ``i`` once ``i`` has differed from ``o`` on
    ``length`` consecutive clocks: it has a down-counter that is loaded with ``length`` whenever
    ``i = o`` (and when ``o`` flips) and counts the clocks with ``i ≠ o`` down; in the clock it
    is at 1 or 0 with ``i ≠ o`` the output takes the input (an equality test, no comparator).
    ``length`` 0 and 1 both make ``o`` a one-clock register of ``i``.

    So a pulse (on the clocked input) shorter than ``length`` clocks never reaches ``o``, a pulse
    of ``length`` clocks or more always does, ``length`` clocks after its start (``max(length,
    1)``). An asynchronous pulse of ``d`` clock periods is sampled on ``floor(d)`` or
    ``ceil(d)`` clocks, so after the synchroniser pulses shorter than ``length − 1`` are always
    rejected and pulses of ``length + 1`` or more are always passed; to reject glitches of up to
    ``n`` clocks, set ``length = n + 1``. A change of ``length`` applies to the counts that begin
    after it: a count runs with the ``length`` of the clock before its first clock with
    ``i ≠ o`` (the counters start at 0 after reset: a first difference then passes at once).

    Parameters
    ----------
    width : int
        Number of independent bits, 1 … 64.
    max_length : int
        Largest ``length``, 1 … 65535 clocks (sets the counter width).
    fold_reload : bool
        The counter's form (the same outputs either way): ``True`` (the default, the iCE40's)
        the reload select on the decrement's own operand, ``rem + (dec repeated)`` selected by
        ``dec`` (one LUT with its carry per bit, docs/AREA.md §7.76); ``False`` ``rem − 1``
        and the reload selected by the equality (fewer LUT6 on the Spartan-7, the ECP5's
        netlist of before).

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

    def __init__(self, *, width=1, max_length=255, fold_reload=True):
        self._width = check_param("GlitchFilter", "width", width, 1, 64)
        self._max_length = check_param("GlitchFilter", "max_length", max_length, 1, 65535)
        self._fold_reload = check_bool("GlitchFilter", "fold_reload", fold_reload)
        super().__init__({
            "i": In(width),
            "length": In(range(max_length + 1)),
            "o": Out(width),
        })

    width = property(lambda self: self._width)
    max_length = property(lambda self: self._max_length)
    fold_reload = property(lambda self: self._fold_reload)

    def elaborate(self, platform):
        m = Module()
        for k in range(self._width):
            rem = Signal(range(self._max_length + 1), name=f"rem{k}")
            if not self._fold_reload:
                with m.If(self.i[k] == self.o[k]):
                    m.d.sync += rem.eq(self.length)
                with m.Elif(rem[1:] == 0):              # rem ≤ 1
                    m.d.sync += [self.o[k].eq(self.i[k]), rem.eq(self.length)]
                with m.Else():
                    m.d.sync += rem.eq(rem - 1)
                continue
            n = len(rem)
            # i ≠ o with rem ≤ 1: the output takes the input (and rem reloads); i ≠ o with
            # rem ≥ 2: rem counts down (``dec``); otherwise rem reloads. The decrement is
            # rem + (dec repeated) — rem − 1 when counting, rem when not — and the reload
            # selects on ``dec`` itself, so each bit's next value is a function of rem's bit,
            # dec, the carry and length's bit: one LUT with its carry per bit (iCE40: the
            # LUT that forms the sum also makes the reload select; rem − 1 and a select by
            # another signal took two LUTs per bit; docs/AREA.md §7.76).
            differ = self.i[k] ^ self.o[k]
            dec = Signal(name=f"dec{k}")
            m.d.comb += dec.eq(differ & (rem[1:] != 0))
            m.d.sync += rem.eq(Mux(dec, (rem + dec.replicate(n))[:n], self.length))
            with m.If(differ & (rem[1:] == 0)):     # rem ≤ 1
                m.d.sync += self.o[k].eq(self.i[k])
        return m


def _ge(a, b):
    """``a ≥ b`` (unsigned, ``b`` a value or an integer) as a chain of 2-way selects from the
    low bit up, which the iCE40 maps into a few LUTs: no carry chain, whose carries would each
    take a logic cell of their own for a compare of a few bits."""
    b = Const(b, len(a)) if isinstance(b, int) else b
    ge = Const(1, 1)
    for i in range(len(a)):
        ge = Mux(a[i] ^ b[i], a[i], ge)
    return ge


def _add(a, b, cin):
    """``(a + b + cin) mod 2**len(a)`` on one carry chain (the carry-in as a low bit)."""
    return (Cat(cin, a) + Cat(cin, b))[1:len(a) + 1]


def _step(up, x, step, ncomp, ge_comp, lt_step):
    """One modular step of ``x`` (``0 ≤ x < cpr``) by ``±step``, with ``ncomp = step − cpr``
    (negative, modulo ``2**len(x)``): up ``x ≥ cpr − step ? x + ncomp : x + step``, down
    ``x < step ? x − ncomp : x − step``, on one adder (add going up, subtract going down).
    Returns the new value and the carry-in taken (up: the wrap; down: no wrap)."""
    wrap = Mux(up, ge_comp, lt_step)
    operand = Mux(wrap, ncomp, step)
    mask = (1 << len(x)) - 1
    return _add(x, operand ^ Mux(up, 0, mask), ~up), up == wrap


def _check_z_gate(owner, z_gate):
    if z_gate is not None and (not isinstance(z_gate, int) or isinstance(z_gate, bool)
                               or not 0 <= z_gate <= 3):
        raise TypeError(f"{owner} z_gate must be None or an integer from 0 to 3, not {z_gate!r}")
    return z_gate


def _check_config_init(owner, lines, pole_pairs, z_offset):
    return (check_param(owner, "lines_init", lines, 0, (1 << LINES_WIDTH) - 1),
            check_param(owner, "pole_pairs_init", pole_pairs, 0, (1 << POLE_PAIRS_WIDTH) - 1),
            check_param(owner, "z_offset_init", z_offset, 0, (1 << CPR_WIDTH) - 1))


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

    **Configuration.** ``lines``, ``pole_pairs`` and ``z_offset`` are run-time inputs, each change
    announced by a strobe in the first clock of the new value (``lp_changed`` for ``lines`` or
    ``pole_pairs``, ``z_changed`` for ``z_offset``: the register file's ``changed`` strobes);
    the decoder keeps no copy of them and reads them during the sequence that takes a change
    in. A change is taken in by a sequence of two divisions (``busy`` high for
    ``config_latency − 1`` clocks) and then committed at once. A strobe while busy joins the
    running sequence if its input is still to be read (``lp_changed`` in the sequence's first
    busy clock, ``z_changed`` up to its 19th: a register file's copy of the three registers
    in consecutive clocks is one sequence); otherwise the sequence runs again after the commit
    (and, for ``lp_changed``, nothing counts from the clock after the strobe and that commit
    clears the position too). Between strobes the inputs must hold their values. A commit that
    changes ``lines`` or ``pole_pairs``, or makes the configuration invalid, clears
    ``aligned``, ``count`` and the electrical position (and from the clock after such a change
    is taken in until the commit nothing counts: the step constants are replaced before the
    commit); a commit that only changes ``z_offset`` moves ``e`` and ``theta`` to the new
    offset at once (counting goes on meanwhile). The
    configuration is valid when ``lines ≥ 1``, ``1 ≤ pole_pairs < 4·lines`` and ``z_offset <
    4·lines`` (``config_error`` low); while invalid, nothing counts and nothing aligns.

    Parameters
    ----------
    z_gate : int or None
        Quadrature state (0 … 3, ``(A << 1) | B``) that gates Z, or ``None`` for the plain rising
        edge of Z.
    lines_init, pole_pairs_init, z_offset_init : int
        The configuration after reset (the inputs' ``init``; 5000, 4, 0): its constants are
        the registers' reset values, so an input that holds it from reset on needs no strobe
        (the register file's reset values).

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
    lp_changed : In(1)
        Strobe: ``lines`` or ``pole_pairs`` holds a new value from this clock on.
    z_changed : In(1)
        Strobe: ``z_offset`` holds a new value from this clock on.
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
        Clocks from a change of the configuration inputs (the clock of its strobe, decoder
        idle) to the new configuration being visible on the outputs: ``2·DIVISION_STEPS + 6``
        (38): the clock that takes the change in, two divisions of 16 steps, five clocks of
        per-configuration constants on the divisions' subtractor (the last one the commit).
    """

    latency = 1

    def __init__(self, *, z_gate=None, lines_init=5000, pole_pairs_init=4, z_offset_init=0):
        self._z_gate = _check_z_gate("QuadratureDecoder", z_gate)
        init = _check_config_init("QuadratureDecoder", lines_init, pole_pairs_init,
                                  z_offset_init)
        super().__init__({
            "a": In(1), "b": In(1), "z": In(1), "hold": In(1),
            "lines": In(LINES_WIDTH, init=init[0]),
            "pole_pairs": In(POLE_PAIRS_WIDTH, init=init[1]),
            "z_offset": In(CPR_WIDTH, init=init[2]),
            "lp_changed": In(1), "z_changed": In(1),
            "realign": In(1),
            "count": Out(CPR_WIDTH),
            "e": Out(CPR_WIDTH),
            "theta": Out(ANGLE.shape),
            "step": Out(1), "up": Out(1), "a_rise": Out(1), "illegal": Out(1), "index": Out(1),
            "aligned": Out(1), "busy": Out(1), "config_error": Out(1),
        })

    z_gate = property(lambda self: self._z_gate)

    @property
    def config_latency(self):
        return 2 * DIVISION_STEPS + 6

    def elaborate(self, platform):
        m = Module()
        aw = ANGLE.width

        # --- configuration: committed values and their angle constants ----------------------
        lines0 = self.lines.init
        pp0 = self.pole_pairs.init
        z0 = self.z_offset.init
        qp0, rp0, qz0, rz0, valid0 = angle_constants(lines0, pp0, z0)
        cpr0 = 4 * lines0
        z_q = Signal(CPR_WIDTH, init=z0)
        qp = Signal(aw, init=qp0)
        qz = Signal(aw, init=qz0)
        valid = Signal(init=valid0)
        # The remainders Rp, Rz and rm (below) are multiples of 4, whatever the configuration:
        # cpr = 4·lines is one and so is n·2**16 (the divisions' dividends, also modulo 2**18,
        # the working register's width), so every remainder the divisions leave is one (an
        # invalid configuration's too: divide_angle), so are Rp − cpr and Rz − cpr, and rm
        # only ever steps by ±Rp or ±(Rp − cpr) from 0. Their registers hold the value / 4 (16
        # bits, ``rp4``: Rp = 4·rp4): the wrap tests and the step on them lose two bits whose
        # carries are 0, and the values, sums and carries are the same.
        qw = CPR_WIDTH - 2
        rp4 = Signal(qw, init=rp0 >> 2)
        # The wrap tests of the position steps and of the output sums as one carry chain each,
        # on registers: x ≥ cpr − c as the carry out of x + (c − cpr) on 18 bits (16 for the
        # quartered rm: c − cpr is −cpr … −1 modulo 2**18 in a valid configuration). In an
        # invalid one (Rz < 2**18 may then exceed cpr) the angle's carry is still that of
        # rm + ((Rz − cpr) mod 2**18), as the model has it. cpr − z for e, signed (z may
        # exceed cpr); cpr − 1 for the count's wrap.
        n_rp4 = Signal(qw, init=((rp0 - cpr0) % (1 << CPR_WIDTH)) >> 2)
        n_pp = Signal(CPR_WIDTH, init=(pp0 - cpr0) % (1 << CPR_WIDTH))
        n_rz4 = Signal(qw, init=((rz0 - cpr0) % (1 << CPR_WIDTH)) >> 2)
        cpr_z = Signal(signed(CPR_WIDTH + 2), init=cpr0 - z0)
        # cpr − 1 modulo 2**18 ends in binary 11 (also for cpr = 0): only lines − 1 is stored.
        lines_m1 = Signal(LINES_WIDTH, init=((cpr0 - 1) % (1 << CPR_WIDTH)) >> 2)
        cpr_m1 = Cat(Const(0b11, 2), lines_m1)
        # The configuration is read from the inputs themselves while the divisions run (no
        # copies): a change is announced by ``lp_changed`` / ``z_changed`` in the first clock
        # of the new value and taken in then (idle). Whether ``lines`` or ``pole_pairs``
        # changed is noted (``lp_run``): then nothing counts until the commit, which clears
        # the position (the step constants are replaced before it). For a change of
        # ``z_offset`` alone the step constants are rewritten with the values they hold.
        # A strobe while busy: taken into the running sequence if its input has not been read
        # yet (lp: in clock 1, where ``pole_pairs`` is read and the first constant is made
        # from ``lines``; z: up to t_qp, where ``z_offset`` is read), else noted (``lp_again``,
        # ``z_again``) and the sequence runs again after the commit; after an ``lp_again``
        # nothing counts and that commit clears the position too.
        lines_p = self.lines
        pp_p = self.pole_pairs
        z_p = self.z_offset
        lp_run = Signal()
        lp_again = Signal()
        z_again = Signal()
        pp_c = Signal(POLE_PAIRS_WIDTH, init=pp0)   # pole_pairs of n_pp (for e's step alone)
        pp_ok = Signal()                # pole_pairs < cpr
        z_ok = Signal()                 # z_offset < cpr
        cpr_p = Cat(Const(0, 2), lines_p)

        # One subtractor, ``t − cpr``, serves the two divisions n·2**16 / cpr (n = pole_pairs,
        # then z_offset: restoring, one quotient bit per clock, in place on the working
        # registers wq, wr: wr starts as n, each step doubles it and subtracts cpr where that
        # fits, see divide_angle) and, one per clock in between, the constants above. The
        # sequence, by ``timer`` (0: idle; the change is taken in as it goes to 1, wr = 0). The
        # operand ``t`` is always wr (its value in the first column), or 2·wr in a step:
        #   1       t = 0:             cpr − 1 = ~(0 − cpr); wr = pole_pairs
        #   2       t = pole_pairs:    pole_pairs − cpr, pole_pairs < cpr
        #   3 … 18  t = 2·wr:          the 16 steps of pole_pairs·2**16 / cpr
        #   19      t = Rp:            Rp − cpr; Qp, Rp taken; wr = z_offset
        #   20      t = z_offset:      z_offset < cpr
        #   21 … 36 t = 2·wr:          the 16 steps of z_offset·2**16 / cpr
        #   37      t = Rz:            Rz − cpr; Qz taken; commit
        steps = DIVISION_STEPS
        t_p, t_qp, t_z, t_commit = 2, steps + 3, steps + 4, 2 * steps + 5
        timer = Signal(range(t_commit + 1))
        wq = Signal(aw)
        wr = Signal(CPR_WIDTH)
        # timer in 3 … 18 or 21 … 36: a division step (a register, so that the operand's
        # select does not decode the timer in front of the subtractor)
        dividing = Signal()
        sub_t = Signal(CPR_WIDTH + 1)
        diff = Signal(signed(CPR_WIDTH + 2))
        fits = ~diff[-1]
        with m.Switch(timer):
            with m.Case(t_p, t_z):
                m.d.sync += dividing.eq(1)
            with m.Case(t_qp - 1, t_commit - 1):
                m.d.sync += dividing.eq(0)
        # diff = ~(cpr + ~t) (as −x − 1 = ~x): ``lines`` (a register, mostly init-0
        # flip-flops) on the carry's non-inverted side and the inversions folded into the
        # operand's select and the consumers' LUTs (iCE40: no inverter LUT per bit of lines).
        ndiff = Signal(CPR_WIDTH + 2)
        m.d.comb += [
            sub_t.eq(Mux(dividing, Cat(Const(0, 1), wr), wr)),
            ndiff.eq(cpr_p + ~Cat(sub_t, Const(0, 1))),
            diff.eq(~ndiff),
            self.busy.eq(timer != 0),
            self.config_error.eq(~valid),
        ]
        commit = Signal()
        req_lp = self.lp_changed | lp_again
        with m.If(~self.busy):
            with m.If(req_lp | self.z_changed | z_again):
                m.d.sync += [lp_run.eq(req_lp), lp_again.eq(0), z_again.eq(0), timer.eq(1),
                             wr.eq(0)]
        with m.Else():
            with m.If(self.lp_changed):
                with m.If(timer == 1):
                    m.d.sync += lp_run.eq(1)
                with m.Else():
                    m.d.sync += lp_again.eq(1)
            with m.If(self.z_changed & _ge(timer, t_qp + 1)):
                m.d.sync += z_again.eq(1)
            with m.If(timer == t_commit):
                m.d.comb += commit.eq(1)
                m.d.sync += timer.eq(0)
            with m.Else():
                m.d.sync += timer.eq(timer + 1)
        with m.If(dividing):
            m.d.sync += [wr.eq(Mux(fits, diff, sub_t)), wq.eq(Cat(fits, wq[:-1]))]
        with m.Switch(timer):
            with m.Case(1):
                m.d.sync += [lines_m1.eq(~diff[2:CPR_WIDTH]), wr.eq(pp_p)]
            with m.Case(t_p):
                m.d.sync += [n_pp.eq(diff), pp_c.eq(wr), pp_ok.eq(diff < 0)]
            with m.Case(t_qp):
                m.d.sync += [n_rp4.eq(diff[2:CPR_WIDTH]), qp.eq(wq), rp4.eq(wr[2:]), wr.eq(z_p)]
            with m.Case(t_z):
                m.d.sync += z_ok.eq(diff < 0)
        new_valid = (lines_p != 0) & (pp_p != 0) & pp_ok & z_ok
        restart = Signal()
        m.d.comb += restart.eq(commit & (lp_run | lp_again | ~new_valid))
        with m.If(commit):
            m.d.sync += [
                z_q.eq(z_p), qz.eq(wq), n_rz4.eq(diff[2:CPR_WIDTH]), valid.eq(new_valid),
                cpr_z.eq(cpr_p - z_p),
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
        rm4 = Signal(qw)                # rm / 4: em·2**16 − thm·cpr (mod 2**16·cpr), in [0, cpr)
        # Each wrap test is the carry out of a register plus a per-configuration constant (or
        # a comparison of two registers), side by side with the step's own adder (em + p ≥ cpr
        # ⇔ carry out of em + (p − cpr); rm − Rp < 0 ⇔ rm < Rp). One adder per counter serves
        # both directions: the wrap test picks the operand (the step or step − cpr), the
        # direction whether it is subtracted (see _step).
        fwd_c = Signal()
        m.d.comb += fwd_c.eq(fwd)
        c_wrap = Mux(fwd_c, self.count == cpr_m1, self.count == 0)
        count_next = Mux(c_wrap, Mux(fwd_c, 0, cpr_m1),
                         (self.count + Mux(fwd_c, 1, Const(-1, CPR_WIDTH)))[:CPR_WIDTH])
        # (pole_pairs from the register made with n_pp, so that e's step constants agree
        # whatever the input does; the Top uses no e: this goes with em.)
        em_next, _ = _step(fwd_c, em, pp_c, n_pp, (em + n_pp)[CPR_WIDTH], em < pp_c)
        rm_next, cin = _step(fwd_c, rm4, rp4, n_rp4, (rm4 + n_rp4)[qw], rm4 < rp4)
        # up: θm + Qp + carry; down: θm − Qp − borrow = θm + ~Qp + (1 − borrow).
        thm_next = _add(thm, qp ^ Mux(fwd_c, 0, (1 << aw) - 1), cin)
        with m.If(valid & ~(self.busy & lp_run) & ~lp_again & (fwd | bwd)):
            m.d.sync += [self.count.eq(count_next), em.eq(em_next), rm4.eq(rm_next),
                         thm.eq(thm_next)]
        arm = ~self.aligned | self.realign
        with m.If(valid & index & arm):
            m.d.sync += [self.aligned.eq(1), self.count.eq(0), em.eq(0), thm.eq(0), rm4.eq(0)]
        with m.Elif(self.realign):
            m.d.sync += self.aligned.eq(0)
        with m.If(restart):
            m.d.sync += [self.aligned.eq(0), self.count.eq(0), em.eq(0), thm.eq(0), rm4.eq(0)]

        # --- outputs: the Z offset added to the electrical position -------------------------
        # e = (em + z) mod cpr and θ = θm + Qz + (rm + Rz ≥ cpr), with the wrap tests made on
        # the registers alone (em ≥ cpr − z; the carry out of rm + (Rz − cpr)): one carry chain
        # before the sums, not two.
        m.d.comb += [
            self.e.eq(Mux(em >= cpr_z, em - cpr_z, em + z_q)),
            self.theta.eq(thm + qz + (rm4 + n_rz4)[qw]),
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
        # The centre picked by the code, then one adder (not one per code and a mux).
        centre = Signal(ANGLE.width)
        sector = Signal(range(6))
        with m.Switch(self.h):
            for k, code in enumerate(HALL_CODES):
                with m.Case(code):
                    m.d.comb += [centre.eq(centres[k]), sector.eq(k)]
        with m.If((self.h != 0) & (self.h != 7)):
            m.d.sync += [
                self.sector.eq(sector),
                self.theta.eq(centre + self.offset),
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

    Cost: a 16-bit addition and subtraction for ``d``, one subtraction for ``d − d_prev``, one
    magnitude test (the carry out of ``|x|`` in one's complement against ``tolerance``), a
    6-entry constant table and ≈ 90 flip-flops, no multiplier or divider. Pipelined in three
    clocks (the edge, the inputs and ``boundary + offset`` registered; ``d`` into ``error`` and
    the compared value, ``d`` or ``d − d_prev``, registered; the checks) for 100 MHz on an
    ECP5: the Hall edges are thousands of clocks apart, the two clocks cost nothing.
    ``tolerance`` and ``misses`` (configuration) are not pipelined: the checks take them in
    their own clock.

    Parameters
    ----------
    theta_registered : bool
        ``theta`` is already a register of the angle, one clock behind the other inputs (the
        :class:`EncoderFrontEnd`'s copy ``theta_q``): the check takes it as its clock-1 value
        instead of registering it again (16 flip-flops, each a logic cell of its own on the
        iCE40). The outputs are then those of the default block fed the undelayed angle.
    complement : bool
        The differences' form (the same outputs either way): ``False`` (the default, the
        ECP5's and the Spartan-7's) ``d = θ − (boundary + offset)`` and ``x = d − d_prev``
        behind a select of ``d_prev`` or 0 on the second subtraction's operand; ``True`` (the
        iCE40's, docs/AREA.md §7.84) ``~d = (boundary + offset) + ~θ`` on one carry chain and
        ``x = d_prev − d = d_prev + ~d + 1`` (``|x|`` is the same: ``|−x| = |x|`` also for
        −180°), the aligned case's ``x = d`` selected behind that adder (in its LUT: both read
        ``~d``): no operand select and no inverter in front of a carry. The angle register
        (``theta1``, or the caller's with ``theta_registered``) is then best one the iCE40
        stores inverted (init all ones, reset_less: its value is read only at an edge, never in
        the clock after a reset), so that the carries take ``~θ`` from its flip-flops.

    Members
    -------
    theta : In(BinaryAngle(16))
        Encoder electrical angle (the :class:`QuadratureDecoder`'s, aligned or not); with
        ``theta_registered``, that angle one clock late.
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
        Written one clock before that edge's ``edge`` strobe (``latency − 1`` clocks after the
        inputs: it is the register the next edge's ``d − d_prev`` reads).

    Attributes
    ----------
    latency : int
        Clocks from ``sector``/``theta`` to the outputs (3; ``error`` 2). The outputs are those
        of the unpipelined check delayed by two clocks (``error`` by one), with ``tolerance``
        and ``misses`` taken two clocks after the other inputs (in the clock of the check:
        their change applies two clocks sooner than a pipelined copy's would).
    """

    latency = 3

    def __init__(self, *, theta_registered=False, complement=False):
        self._theta_registered = check_bool("HallPlausibility", "theta_registered",
                                            theta_registered)
        self._complement = check_bool("HallPlausibility", "complement", complement)
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

    theta_registered = property(lambda self: self._theta_registered)
    complement = property(lambda self: self._complement)

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
        # Loaded every clock and read only at an edge (edge1, reset 0): its reset value is
        # never used, so reset_less with init all ones, which the iCE40 stores inverted and
        # so hands the subtraction below its ~bo1 without an inverter LUT per bit (the
        # complement form adds bo1 itself and takes θ inverted: the same for θ's register).
        cpl = self._complement
        theta1 = (Signal(aw, name="theta1", init=(1 << aw) - 1, reset_less=True) if cpl else
                  Signal(aw, name="theta1"))
        bo1 = Signal(aw, name="bo1", init=0 if cpl else (1 << aw) - 1, reset_less=True)
        m.d.sync += [
            edge1.eq(edge), fwd1.eq(fwd), adjacent1.eq(fwd | bwd), aligned1.eq(self.aligned),
            restart1.eq(self.restart), jump1.eq(self.restart | (self.aligned != aligned_q)),
            bo1.eq(bound + self.offset),
        ]
        if self._theta_registered:
            m.d.comb += theta1.eq(self.theta)
        else:
            m.d.sync += theta1.eq(self.theta)

        # Clock 2: d = θ − (boundary + offset) (mod a turn) and the value the check compares,
        # x = d (aligned) or d − d_prev (not aligned), registered so that clock 3's compare
        # starts at flip-flops (the whole top's 100 MHz on the ECP5; the select is on the
        # second subtraction's operand, d_q or 0, beside the first). d of an edge between
        # adjacent sectors goes straight into d_q (the ``error`` output) in this clock: so the
        # next edge's d_prev is d_q, also for edges in consecutive clocks (the block alone may
        # see them), and no copy of d waits for clock 3 (iCE40: 16 flip-flops of their own).
        # The complement form: ~d = bo1 + ~θ, and not aligned x = d_prev − d (= −(d − d_prev),
        # whose magnitude the check compares): x2's sum d_q + ~d + 1 and the select of d = ~(~d)
        # in the aligned case read the same three signals and the carry, one LUT per bit with
        # no operand select in front of the carry (iCE40: −12 logic cells, docs/AREA.md §7.84).
        edge2, fwd2, adjacent2, aligned2, restart2, jump2 = (
            Signal(name=f"{n}2") for n in ("edge", "fwd", "adjacent", "aligned", "restart",
                                           "jump"))
        x2 = Signal(aw)
        dir_q = Signal()                # the previous edge went forward
        d_q = self.error                # d at the previous edge between adjacent sectors
        d_new = Signal(aw)
        if cpl:
            nd = Signal(aw)             # ~d
            m.d.comb += [nd.eq(bo1 + ~theta1), d_new.eq(~nd)]
            x_new = Mux(aligned1, d_new, d_q + nd + 1)
        else:
            m.d.comb += d_new.eq(theta1 - bo1)
            x_new = d_new - Mux(aligned1, 0, d_q)
        m.d.sync += [
            edge2.eq(edge1), fwd2.eq(fwd1), adjacent2.eq(adjacent1), aligned2.eq(aligned1),
            restart2.eq(restart1), jump2.eq(jump1),
            x2.eq(x_new),
        ]
        with m.If(edge1 & adjacent1):
            m.d.sync += d_q.eq(d_new)

        # Clock 3: the checks and the miss count, on the state of the previous edges.
        ref_ok = Signal()               # d_q is comparable with d now
        count = Signal(4)               # consecutive misses, saturating at 15
        # The two checks never apply together: one magnitude comparison serves both. For x
        # read as signed with sign s, |x| > tol ⇔ y > tol (s = 0) or y ≥ tol (s = 1) with
        # y = x ^ (s repeated): |x| = y + s. That is the carry out of y + ~tol + s: one carry
        # chain, no negation (never true for tol ≥ 2**(aw−1), where y < tol + s). Written as
        # the complement, tol ≥ y + s ⇔ the carry out of tol + ~y + ~s, so that ``tolerance``
        # (a register, mostly init-0 flip-flops) sits on the carry's non-inverted side and
        # the inversion folds into the LUTs that form y (iCE40: no inverter LUT per bit).
        # ``tolerance`` and ``misses`` are taken here, in this clock (not pipelined).
        x = x2
        sign = x[aw - 1]
        ny = x ^ ~sign.replicate(aw)    # ~y
        over = Signal()
        m.d.comb += over.eq(~(Cat(~sign, self.tolerance) + Cat(Const(1, 1), ny))[aw + 1])
        # count ≥ misses − 1 (0 acts as 1) ⇔ count + 1 ≥ misses: the counter's increment,
        # one compare in LUTs.
        inc = Signal(5)
        m.d.comb += inc.eq(count + 1)
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
        with m.Elif(jump2):
            m.d.sync += ref_ok.eq(0)
        with m.If(miss):
            m.d.sync += count.eq(Mux(count == 15, 15, inc))
        with m.Elif(passed):
            m.d.sync += count.eq(0)
        m.d.sync += [
            self.edge.eq(edge2),
            self.miss.eq(miss),
            self.fault.eq(miss & _ge(inc, Cat(self.misses, Const(0, 1)))),
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
    z_gate, lines_init, pole_pairs_init, z_offset_init
        See :class:`QuadratureDecoder`.
    fold_reload : bool
        See :class:`GlitchFilter`.
    plausibility_complement : bool
        See :class:`HallPlausibility` ``complement`` (default ``True``, the iCE40's form); with
        it the decoder's angle register ``theta_q`` is reset_less with init all ones (stored
        inverted on the iCE40; its value in the clock after a reset is never read: ``theta``
        shows the Hall angle then and no Hall edge is taken).

    Members
    -------
    a, b, z : In(1)
        Encoder pins (asynchronous).
    hall : In(unsigned(3))
        Hall pins (asynchronous), bit 0 = H_a, bit 1 = H_b, bit 2 = H_c.
    length : In(range(max_length + 1))
        Glitch filter length for all seven inputs, clocks (0, 1: no filtering).
    lines, pole_pairs, z_offset, lp_changed, z_changed, realign
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
        From the :class:`HallPlausibility` (``edge``, ``miss``, ``fault``, ``error``),
        :attr:`plausibility_latency` clocks after the pin changes of the Hall sector and encoder
        angle they compare (``hall_error`` one clock sooner).
    theta : Out(BinaryAngle(16))
        Electrical angle θ_e, a register or the Hall angle: the decoder's exact angle of the
        clock before (``theta_q``, :attr:`theta_latency`) when the decoder was ``aligned`` in
        the clock before, else the Hall angle (not delayed: :attr:`latency`). The register
        serves the plausibility check too (its own copy of the angle) and starts the paths
        behind θ at a flip-flop (ECP5 Fmax: the angle's sum and wrap test end there).
    ready : Out(1)
        The inputs have settled since reset.

    Attributes
    ----------
    latency : int
        Clocks from a pin change to the outputs with ``length`` ≤ 1 (4: two synchroniser flops,
        the filter register, the decoder); add ``length − 1`` for a longer filter.
    theta_latency : int
        The same for ``theta`` once aligned (5: the decoder's angle registered).
    plausibility_latency : int
        The same for ``hall_edge``, ``hall_miss`` and ``plausibility`` (7; ``hall_error`` 6).
    """

    latency = 4
    theta_latency = latency + 1
    plausibility_latency = latency + HallPlausibility.latency
    sync_stages = 2

    def __init__(self, *, max_length=255, z_gate=None, lines_init=5000, pole_pairs_init=4,
                 z_offset_init=0, fold_reload=True, plausibility_complement=True):
        self._max_length = check_param("EncoderFrontEnd", "max_length", max_length, 1, 65535)
        _check_z_gate("EncoderFrontEnd", z_gate)   # before any child exists (no unused child)
        cpl = check_bool("EncoderFrontEnd", "plausibility_complement", plausibility_complement)
        init = _check_config_init("EncoderFrontEnd", lines_init, pole_pairs_init, z_offset_init)
        self._decoder = QuadratureDecoder(z_gate=z_gate, lines_init=init[0],
                                          pole_pairs_init=init[1], z_offset_init=init[2])
        self._filter = GlitchFilter(width=6, max_length=max_length, fold_reload=fold_reload)
        self._hall = HallSensor()
        self._plausibility = HallPlausibility(theta_registered=True, complement=cpl)
        super().__init__({
            "a": In(1), "b": In(1), "z": In(1), "hall": In(3),
            "length": In(range(max_length + 1)),
            "lines": In(LINES_WIDTH, init=init[0]),
            "pole_pairs": In(POLE_PAIRS_WIDTH, init=init[1]),
            "z_offset": In(CPR_WIDTH, init=init[2]),
            "hall_offset": In(ANGLE.shape),
            "hall_tolerance": In(ANGLE.width, init=ANGLE.turn // 8),
            "hall_misses": In(4, init=1),
            "lp_changed": In(1), "z_changed": In(1),
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
    fold_reload = property(lambda self: self._filter.fold_reload)
    plausibility_complement = property(lambda self: self._plausibility.complement)
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

        # Clocks since reset minus 3: ready once it reaches length (one comparison in LUTs,
        # no length + 4 adder).
        settle = Signal(range(-3, self._max_length + 1), init=-3)
        lw = len(self.length)
        with m.If(~self.ready):
            m.d.sync += settle.eq(settle + 1)
            with m.If(~settle[-1] & _ge(settle[:lw], self.length)):
                m.d.sync += self.ready.eq(1)

        m.d.comb += [
            dec.a.eq(flt.o[0]), dec.b.eq(flt.o[1]), dec.z.eq(flt.o[2]), dec.hold.eq(~self.ready),
            dec.lines.eq(self.lines), dec.pole_pairs.eq(self.pole_pairs),
            dec.z_offset.eq(self.z_offset), dec.realign.eq(self.realign),
            dec.lp_changed.eq(self.lp_changed), dec.z_changed.eq(self.z_changed),
            hall.h.eq(flt.o[3:6]), hall.offset.eq(self.hall_offset), hall.hold.eq(~self.ready),
        ]
        # The decoder's angle (a sum and a wrap test) and its alignment, registered: θ's source
        # when aligned, and the plausibility check's clock-1 copy of the angle.
        theta_q = (Signal(ANGLE.shape, init=ANGLE.turn - 1, reset_less=True)
                   if self._plausibility.complement else Signal(ANGLE.shape))
        aligned_q = Signal()
        m.d.sync += [theta_q.eq(dec.theta), aligned_q.eq(dec.aligned)]
        for name in ("count", "e", "step", "up", "a_rise", "illegal", "index", "aligned", "busy",
                     "config_error"):
            m.d.comb += getattr(self, name).eq(getattr(dec, name))
        m.d.comb += [
            self.hall_sector.eq(hall.sector),
            self.hall_valid.eq(hall.valid),
            self.hall_fault.eq(hall.fault),
            self.theta.eq(Mux(aligned_q, theta_q, hall.theta)),
        ]
        m.d.comb += [
            plaus.theta.eq(theta_q), plaus.aligned.eq(dec.aligned),
            plaus.restart.eq(dec.busy | dec.config_error),
            plaus.sector.eq(hall.sector), plaus.valid.eq(hall.valid), plaus.hold.eq(~self.ready),
            plaus.offset.eq(self.hall_offset), plaus.tolerance.eq(self.hall_tolerance),
            plaus.misses.eq(self.hall_misses),
            self.hall_edge.eq(plaus.edge), self.hall_miss.eq(plaus.miss),
            self.plausibility.eq(plaus.fault), self.hall_error.eq(plaus.error),
        ]
        return m
