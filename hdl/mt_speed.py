# Ref: SPEC.md §2.3 (paper Fig. 6): M/T speed, n = ΔM·60·f_TCLK/(P_n·ΔT), D_n = k·ΔM/ΔT
"""M/T speed measurement: edges counted over a window that starts and ends on an edge.

MC counts encoder edges (signed by direction), TC runs at f_TCLK, T latches TC at every counted
edge. At each speed-update strobe the window closes on the last counted edge: ``ΔM`` = edges
since the previous window's last edge, ``ΔT = T2 - T1`` between those two edges, and
``D_n = k·ΔM/ΔT`` is computed unsigned, ``k·|ΔM| / ΔT`` with ``min(out_width − 1, k_width +
m_width − 1)`` quotient bits (a larger quotient saturates), then the sign of ΔM applied to the
result: ``trunc(k·ΔM/ΔT)`` saturated to ±(2**(out_width−1) − 1), as a signed division would give.

One result per update period (thousands of clocks) needs no parallel hardware, so the block is
one sequential data path (iCE40 area, session 9): the product ``k·|ΔM|`` is formed 16 bits of
``k`` at a time on one multiplier and written straight into the register of a restoring
division, whose first step decides saturation and whose quotient bits enter with the result's
sign already applied (see :meth:`MTSpeed.elaborate`). TC and the T latches are not stored as
such: the gateware keeps the *age* of the last edge (TC − T mod 2**tc_width) and the *gap*
from the reference edge to the last one, which give ΔT (the gap), the elapsed time (their sum,
the reference's age) and the expiry (that sum at its largest value) directly.

Window rules (the golden model :mod:`foc_servo.sim.models.mt_speed` reproduces them clock for
clock):

* **No edge in an update period**: the window stays open (its reference edge is kept) and the
  output is the last measurement *bounded* by the one-edge limit ``k/elapsed`` (elapsed = TCLK
  ticks since the reference edge): the next edge has not come yet, so the speed cannot exceed one
  edge per elapsed time. A motor that stops thus reads a speed decaying as ``1/t`` to 0, never a
  stale value; at constant speed the bound never bites (beyond the ±1 tick quantisation of T).
* **No edge within the TC span** (``2**tc_width`` ticks since the reference edge): the reference
  expires, the output is 0 with ``stopped`` set until a new window (two edges, the first becoming
  the reference) has been measured.
* **Direction reversal inside a window**: edges count +1/−1 by direction, so ``ΔM`` is the net
  displacement and ``D_n`` the mean speed over the window (a net-zero window reads exactly 0).
  This is exact when the strobe marks the crossing of one fixed count position in either
  direction (×4: every quadrature state change; "a_rising": the A-rising position, i.e. A↑ moving
  forward and A↓ moving backward). A decoder that strobes A↑ in time in both directions counts a
  position half a line away after a reversal: ΔM is then off by one edge in the window of the
  reversal.
"""

import enum

from amaranth.hdl import Cat, Const, Module, Mux, Signal, signed, unsigned
from amaranth.lib import data, stream, wiring
from amaranth.lib import enum as lib_enum
from amaranth.lib.wiring import In, Out

from .fixed import check_bool, check_choice, check_param
from .regmap import MT_EDGES_PER_LINE

__all__ = ["MTSpeed", "EDGE_LAYOUT", "EdgeMode", "WindowMode", "output_layout", "ARITHS",
           "RUN_LAYOUT"]


#: One counted encoder edge: ``step`` is a 1-clock strobe, ``neg`` its direction (1 = count −1).
EDGE_LAYOUT = data.StructLayout({"step": 1, "neg": 1})


class EdgeMode(enum.Enum):
    """Which encoder edges the ``edge`` strobe carries (sets the edges counted per line)."""
    A_RISING = "a_rising"   # one edge per line: the A-rising position
    X4 = "x4"               # four edges per line: every quadrature state change

    @property
    def edges_per_line(self):
        return MT_EDGES_PER_LINE[self.value]


class WindowMode(lib_enum.Enum, shape=2):
    """What an update computes (see the module docstring)."""
    STOPPED = 0     # no valid reference or no measurement since the last expiry: 0, stopped
    BOUND = 1       # window open, no new edge: last measurement bounded by k/elapsed
    FRESH = 2       # window closed on a new edge: k·ΔM/ΔT


#: Values of ``MTSpeed(arith=...)``.
ARITHS = ("gateware", "engine")

#: ``arith="engine"``: the operands of one update's run on the loop engine (the specials
#: ``mtm``, ``mtd``, ``mts``, ``mtb`` of :func:`~.engine_mt.mt_arith`, docs/AREA.md §7.64):
#: the dividend's factor ``m`` (|ΔM| fresh, 1 bounded, 0 stopped), the divisor ``d`` (ΔT
#: fresh, the ticks since the reference bounded; bit 0 set when ``m`` is 0), the result's sign
#: ``s`` and ``b`` = bounded.
def RUN_LAYOUT(tc_width, m_width):
    """Payload layout of :attr:`MTSpeed.run` (``arith="engine"``)."""
    return data.StructLayout({"m": unsigned(m_width), "d": unsigned(tc_width), "s": 1, "b": 1})


def output_layout(out_width):
    """Payload layout of :attr:`MTSpeed.o`."""
    return data.StructLayout({
        "speed": signed(out_width),
        "stopped": 1,
        "fresh": 1,
    })


def _check_hz(name, value):
    if (not isinstance(value, (int, float)) or isinstance(value, bool)
            or not value > 0 or value == float("inf")):
        raise TypeError(f"MTSpeed {name} must be a positive finite number of hertz, not {value!r}")
    return float(value)


class MTSpeed(wiring.Component):
    """M/T speed measurement (paper Fig. 6) with the foundation divider.

    Parameters
    ----------
    clk_hz : float
        System clock frequency, Hz.
    tclk_hz : float or None
        Requested TC frequency f_TCLK, Hz, at most ``clk_hz``; ``None`` = ``clk_hz`` (best
        resolution). TC advances once every ``tclk_ratio = round(clk_hz / tclk_hz)`` clocks, so the
        **actual** f_TCLK is ``clk_hz / tclk_ratio`` (attribute :attr:`tclk_hz`): exact when
        ``tclk_hz`` divides ``clk_hz`` (50 MHz / 1 MHz), rounded otherwise (33.333 MHz / 1 MHz
        → ratio 33, 1.0101 MHz). Compute ``k`` from :attr:`tclk_hz`, not from the request.
    tc_width : int
        Width of TC and of the T latches (the paper: 16), 8 … 48. The TC span
        ``2**tc_width / f_TCLK`` is the longest measurable edge interval.
    out_width : int
        Width of the speed output, 8 … 48: Q1.(out_width−1) of the full-scale speed N_M set by
        ``k``, saturated symmetrically to ±(2**(out_width−1) − 1).
    edge_mode : str
        ``"a_rising"`` (one counted edge per line, the default) or ``"x4"`` (four); only changes
        :attr:`edges_per_line`, i.e. the ``k`` to program (the ``edge`` port is the same).
    k_width : int or None
        Width of the ``k`` register, 2 … 64; ``None`` = ``out_width + 16`` (full-scale edge
        period up to 2**17 TCLK ticks).
    m_width : int
        Width of the window edge count ΔM, 2 … 32 (saturating; far above any edge count per
        update period).
    chunk_multipliers : bool
        One multiplier per 16-bit chunk of ``k`` (:attr:`k_chunks` of them), each fed its
        chunk straight from ``k`` and sampling it in the same clock as the single multiplier
        would, instead of one multiplier behind a :attr:`k_chunks`-way select of the chunks
        (iCE40: two more SB_MAC16 for the default 48-bit ``k``, no select in front of them and
        the carry's select beside its flip-flops; docs/AREA.md §7.76). Same outputs in the
        same clocks.
    k_steady : bool
        ``k`` holds its value from the clock of an accepted update to its result (it changes
        only between computations, e.g. a register file's shadowed register committed before
        ``period_start``): the per-chunk multipliers (``chunk_multipliers`` required) take
        ``k`` as it is, without their sampling registers (the products registered as before),
        so that a register in front of ``k`` becomes the multipliers' own input register
        (iCE40: SB_MAC16 A registers with their hold; the Top's ``mt_k`` from the register
        file's export port, docs/AREA.md §7.76). Same outputs in the same clocks as the other
        forms for such a ``k``; a ``k`` that changes during a computation gives another
        product.
    arith : str
        Where the arithmetic after the snapshot runs (:data:`ARITHS`): ``"gateware"`` (default)
        the multiplier and the restoring division here; ``"engine"`` the loop engine's run
        ``mt`` (:func:`~.engine_mt.mt_arith`, ``EngineCurrentLoop(mt=True)``; docs/AREA.md
        §7.64, §7.82): this block keeps the window logic only, gives each accepted update's
        operands on :attr:`run` (``valid`` the clock after the update) and shows the engine's
        result on ``o``: ``o.payload.speed`` is the ``res`` input (the engine's output register
        ``mtspd``), ``o.valid`` the clock after ``res.valid`` (its write). No ``k`` port (``k``
        is the engine's); written for :data:`~.engine_mt.MT_ENGINE_PARAMS` (``out_width`` 32,
        ``k_width`` 48, ``m_width`` 16, ``tc_width`` at most 27: the engine's ``DIV`` divisor
        is its multiplier's signed 28-bit operand); no ``chunk_multipliers``, ``k_steady``.
        Same outputs as the other form for the same results, :attr:`latency` clocks after the
        update being the run's (``None`` here: the engine's, ``EngineCurrentLoop.mt_latency``,
        plus the wait for its start).

    Members
    -------
    edge : In(EDGE_LAYOUT)
        ``step``: 1-clock strobe per counted edge (at most one per clock); ``neg``: its direction,
        1 = backward (ΔM −1). T latches the TC value of the clock of the strobe.
    update : In(1)
        Speed-update strobe (the PWM ``period_start``). Accepted when no computation is in flight
        (updates at least :attr:`latency` clocks apart are all accepted; one arriving earlier is
        ignored: its window stays open and the next accepted update measures it).
    k : In(unsigned(k_width))
        Scale factor, an integer: ``D_n = k·ΔM/ΔT`` in Q1.(out_width−1) of N_M;
        ``k = 60·2**(out_width−1)·f_TCLK / (lines·edges_per_line·N_M)`` (see
        :func:`foc_servo.sim.models.mt_speed.k_for`). Sampled 16 bits at a time, least
        significant first, in the clock of the accepted update and the :attr:`k_chunks` − 1
        clocks after it (hold it steady; the register file changes it only at a commit).
    o : Out(stream.Signature(output_layout(out_width), always_ready=True))
        One 1-clock ``valid`` strobe :attr:`latency` clocks after each accepted update; payload
        held until the next. ``speed``: signed Q1.(out_width−1) of N_M, truncated toward zero,
        symmetric saturation (division by ΔT = 0, more edges than one per TC tick, saturates with
        the sign of ΔM, also when ``k = 0``). ``stopped``: no edge within the TC span (or no
        measurement yet since reset); ``speed`` is then 0. ``fresh``: the window closed on a new
        edge this update (``speed = k·ΔM/ΔT``); 0 = bounded previous measurement or stopped.

    run : Out(stream.Signature(RUN_LAYOUT(27, m_width), always_ready=True))
        ``arith="engine"``: the run's request (``valid``, one clock, the clock after an
        accepted update) and its operands (held until the next request).
    res : In(stream.Signature(signed(out_width), always_ready=True))
        ``arith="engine"``: the engine's output register ``mtspd`` (``payload``, held between
        its writes) and its write strobe (``valid``: the register holds the run's result from
        the next clock on).

    Attributes
    ----------
    latency : int or None
        Clocks from an accepted update strobe to ``o.valid`` (update high in clock ``u``,
        ``o.valid`` high in clock ``u + latency``): 1 (snapshot; the multiplier's first k
        chunk) + 1 (first partial product) + :attr:`k_chunks` (carry adds, the product's
        chunks written into the division register) + :attr:`divide_steps` + 1 (output
        register) = ``min(out_width − 1, k_width + m_width − 1) + k_chunks + 4`` (38 for the
        defaults, as with the separate divider before session 9).
    k_chunks : int
        ``ceil(k_width / 16)``: ``k·|ΔM|`` is computed as ``k_chunks`` products of 16 bits of
        ``k`` and ``|ΔM|``, one per clock, least significant first (one 16 × ``m_width``
        multiplier instead of ``k_chunks``; the result is the exact product). Each partial
        product is registered before its carry add (ECP5 Fmax: the multiplier and the adder
        chain in separate clocks).
    divide_steps : int
        ``min(out_width − 1, k_width + m_width − 1) + 1``: clocks of the restoring division
        (one quotient bit each; the first decides saturation).
    tclk_ratio : int
        System clocks per TC tick.
    tclk_hz : float
        Actual f_TCLK.
    tc_span_s : float
        ``2**tc_width / tclk_hz``: no edge within this time reads as stopped.
    edges_per_line : int
        1 (``"a_rising"``) or 4 (``"x4"``).

    Raises
    ------
    TypeError
        If a parameter has the wrong type or is out of its range.
    ValueError
        If ``tclk_hz`` exceeds ``clk_hz`` or ``edge_mode`` is not one of the two modes.
    """

    def __init__(self, *, clk_hz=50e6, tclk_hz=None, tc_width=32, out_width=32,
                 edge_mode="a_rising", k_width=None, m_width=16, chunk_multipliers=False,
                 k_steady=False, arith="gateware"):
        clk_hz = _check_hz("clk_hz", clk_hz)
        tclk_hz = clk_hz if tclk_hz is None else _check_hz("tclk_hz", tclk_hz)
        if tclk_hz > clk_hz:
            raise ValueError(f"MTSpeed tclk_hz must be at most clk_hz {clk_hz!r}, not {tclk_hz!r}")
        self._tc_width = check_param("MTSpeed", "tc_width", tc_width, 8, 48)
        self._out_width = check_param("MTSpeed", "out_width", out_width, 8, 48)
        if k_width is None:
            k_width = out_width + 16
        self._k_width = check_param("MTSpeed", "k_width", k_width, 2, 64)
        self._m_width = check_param("MTSpeed", "m_width", m_width, 2, 32)
        self._chunk_multipliers = check_bool("MTSpeed", "chunk_multipliers", chunk_multipliers)
        self._k_steady = check_bool("MTSpeed", "k_steady", k_steady)
        if k_steady and not chunk_multipliers:
            raise ValueError("MTSpeed k_steady needs chunk_multipliers=True")
        try:
            self._edge_mode = EdgeMode(edge_mode)
        except ValueError:
            raise ValueError(f"MTSpeed edge_mode must be 'a_rising' or 'x4', not {edge_mode!r}") \
                from None
        self._arith = check_choice("MTSpeed", "arith", arith, ARITHS)
        if arith == "engine":
            from .engine_mt import MT_ENGINE_PARAMS
            for name, value, want in (("out_width", out_width, MT_ENGINE_PARAMS["out_width"]),
                                      ("k_width", k_width, MT_ENGINE_PARAMS["k_width"]),
                                      ("m_width", m_width, MT_ENGINE_PARAMS["m_width"])):
                if value != want:
                    raise ValueError(f"MTSpeed arith='engine' needs {name} {want} (the "
                                     f"engine's program is written for it), not {value!r}")
            if tc_width > MT_ENGINE_PARAMS["tc_width"]:
                raise ValueError(f"MTSpeed arith='engine' needs tc_width at most "
                                 f"{MT_ENGINE_PARAMS['tc_width']} (the engine's DIV divisor "
                                 f"is its multiplier's signed 28-bit operand), not {tc_width}")
            if chunk_multipliers or k_steady:
                raise ValueError("MTSpeed arith='engine' has no multiplier: chunk_multipliers "
                                 "and k_steady must be False")
        self._clk_hz = clk_hz
        self._tclk_ratio = max(1, round(clk_hz / tclk_hz))
        members = {
            "edge": In(EDGE_LAYOUT),
            "update": In(1),
            "o": Out(stream.Signature(output_layout(self._out_width), always_ready=True)),
        }
        if arith == "engine":
            # (the divisor as the engine takes it: 27 bits, this TC's zero-extended)
            members["run"] = Out(stream.Signature(
                RUN_LAYOUT(MT_ENGINE_PARAMS["tc_width"], self._m_width), always_ready=True))
            members["res"] = In(stream.Signature(signed(self._out_width), always_ready=True))
        else:
            members["k"] = In(unsigned(self._k_width))
        super().__init__(members)

    clk_hz = property(lambda self: self._clk_hz)
    tc_width = property(lambda self: self._tc_width)
    out_width = property(lambda self: self._out_width)
    k_width = property(lambda self: self._k_width)
    m_width = property(lambda self: self._m_width)
    chunk_multipliers = property(lambda self: self._chunk_multipliers)
    k_steady = property(lambda self: self._k_steady)
    arith = property(lambda self: self._arith)
    edge_mode = property(lambda self: self._edge_mode.value)
    edges_per_line = property(lambda self: self._edge_mode.edges_per_line)
    tclk_ratio = property(lambda self: self._tclk_ratio)
    tclk_hz = property(lambda self: self._clk_hz / self._tclk_ratio)
    tc_span_s = property(lambda self: (1 << self._tc_width) / self.tclk_hz)

    @property
    def _quotient_width(self):
        # |k·ΔM| < 2**(k_width + m_width − 1); the output's magnitude needs out_width − 1 bits.
        return min(self._out_width - 1, self._k_width + self._m_width - 1)

    @property
    def divide_steps(self):
        return self._quotient_width + 1

    @property
    def k_chunks(self):
        return -(-self._k_width // 16)

    @property
    def latency(self):
        if self._arith == "engine":
            return None
        return 2 + self.k_chunks + self.divide_steps + 1

    def elaborate(self, platform):
        m = Module()
        w, ow, mw = self._tc_width, self._out_width, self._m_width
        r = self._tclk_ratio

        # --- Time: instead of a free-running TC and the latched T of the reference and last
        # edges, the *age* of the last counted edge, counting TCLK ticks modulo 2**w, and the
        # *gap* from the reference edge to the last one (T(last) − T(ref) mod 2**w, 0 when they
        # are the same edge): the reference's age is their sum (age = TC − T mod 2**w).
        # age_last restarts at each counted edge; the gap takes the reference's age at an edge
        # that does not close the window, and is cleared when the last edge becomes the
        # reference (a first edge, a close), so no register has to take another's value in
        # that clock: no select in front of the adders and no subtractor for ΔT (iCE40 area;
        # docs/AREA.md §7.67).
        tick = Signal()
        if r == 1:
            m.d.comb += tick.eq(1)
        else:
            pre = Signal(range(r))
            with m.If(pre == r - 1):
                m.d.sync += pre.eq(0)
                m.d.comb += tick.eq(1)
            with m.Else():
                m.d.sync += pre.eq(pre + 1)
        age_last = Signal(w, reset_less=True)
        gap = Signal(w, reset_less=True)
        # The reference's age, modulo 2**w (without a reference, have_ref low, nothing reads it).
        age_ref = Signal(w)
        m.d.comb += age_ref.eq(age_last + gap)
        # A whole span since the reference edge: TC + 1 == T(reference) with a tick this clock
        # (the age at 2**w − 1; a compare in LUTs, no carry chain).
        at_span = tick & (age_ref == (1 << w) - 1)

        # --- Window state. Invariant: pending == 0 implies ΔM == 0 and (with have_ref) gap == 0,
        # i.e. age_last == age_ref; have_ref == 0 implies pending == 0.
        # Net edges since the reference edge, saturating to signed(mw), kept as magnitude and
        # sign (ECP5 Fmax: the snapshot's |ΔM| is then one up/down step of a register, without a
        # negation behind the signed add and its saturation). m_neg is meaningless when
        # m_mag == 0.
        m_mag = Signal(mw)              # |ΔM| <= 2**(mw - 1)
        m_neg = Signal()                # ΔM < 0
        pending = Signal()              # edges counted since the reference
        have_ref = Signal()             # a reference edge younger than the TC span exists
        # A fresh measurement since reset / the last expiry: set when a fresh window is
        # snapshotted, cleared by an expiry (also one during the computation).
        prev_valid = Signal()
        busy = Signal()                 # a computation is in flight

        step, neg = self.edge.step, self.edge.neg
        mag_e = Signal(mw)              # the state including this clock's edge
        neg_e = Signal()
        pend_e = Signal()
        # A step away from zero (or from zero) adds 1 to the magnitude up to the limit of its
        # sign (2**(mw − 1) − 1 positive, 2**(mw − 1) negative: saturate to signed(mw)); a step
        # towards zero subtracts 1 (the sign is kept on reaching 0: a zero magnitude's sign is
        # never used, the next step sets it and a snapshot of 0 reads 0). One adder, its
        # operand +1 or −1 by the edge's direction; the compares are formed from the registers.
        zero = m_mag == 0
        away = zero | (neg == m_neg)
        at_lim = m_mag == Mux(m_neg, 1 << (mw - 1), (1 << (mw - 1)) - 1)
        mag_s = Signal(mw)              # m_mag ± 1: one adder
        m.d.comb += mag_s.eq(m_mag + Cat(Const(1, 1), (~away).replicate(mw - 1)))
        m.d.comb += [mag_e.eq(m_mag), neg_e.eq(m_neg), pend_e.eq(pending)]
        with m.If(step):
            m.d.comb += [
                mag_e.eq(Mux(away & at_lim, m_mag, mag_s)),
                neg_e.eq(Mux(zero, neg, m_neg)),
                pend_e.eq(1),
            ]
        expire = have_ref & at_span
        start = self.update & ~busy

        # The window's next state, written as flat enables:
        # * no reference: the first edge becomes the reference;
        # * update, or expiry (update period > span), with edges since the reference: close the
        #   window on its last edge, which becomes the new reference;
        # * expiry without edges: the reference is dropped; any expiry not at a closing update
        #   also invalidates the last measurement;
        # * otherwise the edge of this clock (if any) is counted.
        # ΔM and pending are 0 while there is no reference, and at an expiry without edges.
        first = ~have_ref & step
        close = have_ref & pend_e & (start | expire)
        # An edge in this clock: its age is 0 now, `tick` in the next clock.
        m.d.sync += [
            age_last.eq(Mux(step, tick, age_last + tick)),
        ]
        # The reference's next age is age_ref + tick unless the last edge becomes the
        # reference (first edge, close: gap 0); an edge that is counted into the open window
        # is the new last edge (age tick next clock): the gap is then age_ref.
        with m.If(first | close):
            m.d.sync += gap.eq(0)
        with m.Elif(step):
            m.d.sync += gap.eq(age_ref)
        with m.If(have_ref):
            m.d.sync += [m_mag.eq(Mux(close, 0, mag_e)), m_neg.eq(neg_e & ~close),
                         pending.eq(pend_e & ~close)]
        with m.If(have_ref & expire & ~(start & pend_e)):
            m.d.sync += prev_valid.eq(0)
        with m.If(first):
            m.d.sync += have_ref.eq(1)
        with m.Elif(expire & ~pend_e):
            m.d.sync += have_ref.eq(0)

        # --- Computation: snapshot, product, division, result, all on one data path.
        # Snapshot at the update (clock u): the dividend's factor `dm` = |ΔM| (fresh), 1 (bounded)
        # or 0 (stopped), the divisor `dv` = ΔT (fresh: age_ref − age_last, or age_ref when the
        # last edge is in this clock) or the ticks elapsed since the reference (bounded:
        # age_ref), and the sign `sgn` of the result (ΔM's, or the last output's when bounded).
        # A zero `dm` (stopped, or a net-zero fresh window) sets dv's bit 0 a clock later: the
        # quotient is then 0/dv = 0 (also for ΔT = 0), so the result needs no override.
        mode = Signal(WindowMode)
        dm = Signal(mw)                 # |ΔM| <= 2**(mw - 1)
        n_dv = Signal(w)                # ~divisor (inverted: the division subtracts it)
        sgn = Signal()
        p = self.o.payload
        dt = Signal(w)
        m.d.comb += dt.eq(Mux(pending & ~step, gap, age_ref))     # gap = age_ref − age_last
        with m.If(start):
            m.d.sync += [busy.eq(1), n_dv.eq(~dt)]
            with m.If(have_ref & pend_e):
                m.d.sync += [mode.eq(WindowMode.FRESH), dm.eq(mag_e), sgn.eq(neg_e),
                             prev_valid.eq(1)]
            with m.Elif(have_ref & prev_valid):
                m.d.sync += [mode.eq(WindowMode.BOUND), dm.eq(1), sgn.eq(p.speed[-1])]
            with m.Else():
                m.d.sync += [mode.eq(WindowMode.STOPPED), dm.eq(0), sgn.eq(0)]

        if self._arith == "engine":
            self._engine_result(m, start, busy, mode, dm, n_dv, sgn)
            return m

        # k·|ΔM| on 16-bit chunks of k, least significant first, in two stages (the multiplier
        # and the carry adder in separate clocks: ECP5 Fmax). Clock u + 1 + c (c = 0 … nk − 1):
        # `pp` = k_c·|ΔM|. Clock u + 2 + c: t = pp + carry; t's low 16 bits are bits 16c … 16c + 15
        # of the product, written straight into their place in the division register `acc`,
        # the rest is the next carry; the last t (clock u + nk + 1, `ready`) is the product's top.
        nk = self.k_chunks
        qs = self.divide_steps          # quotient bits computed, the top one only saturates
        aw = qs + w                     # acc = Cat(quo, rem)
        acc = Signal(aw)
        quo = acc[:qs]                  # rem = acc[qs:]
        # The quotient saturates: product bits at or above aw (only when k_width + m_width − 1
        # > aw), or the first division step's quotient bit.
        sat = Signal()
        carry = Signal(mw)                              # (pp + carry) >> 16 < 2**mw
        # The registered partial product k_c·|ΔM|: no reset (it is rewritten every clock and
        # only read while `adding`), so that iCE40 synthesis takes it into the SB_MAC16's own
        # pipeline register and keeps the carry add in the SB_MAC16's adder.
        left = Signal(range(nk + 1))                    # chunks still to multiply
        adding = Signal()                               # pp holds a partial product
        ready = Signal()                                # t is the product's last chunk
        k_pad = Cat(self.k, Const(0, 16 * nk - self._k_width))
        chunks = [k_pad[16 * c:16 * c + 16] for c in range(nk)]
        if self._chunk_multipliers:
            # One multiplier per chunk: its k operand register `k_c<c>` takes chunk c in every
            # clock (no reset, no select), so in clock u + c it samples k's chunk c as the
            # single multiplier's k_c does, and its product `pp<c>` is read in clock u + 2 + c
            # only; `t<c>` = pp<c> + carry is chunk c's sum.
            # With k_steady the product is formed from k's chunk as it is (no k_c<c>): dm is
            # the snapshot from clock u + 1 on, k the same from u on, so in clock u + 2 + c it
            # equals the product of the samples. (The products stay registered: three
            # multipliers read in exclusive clocks would otherwise be shared into one behind a
            # select by yosys.)
            ts = []
            for c in range(nk):
                t_c = Signal(16 + mw, name=f"t{c}")
                pp_c = Signal(16 + mw, reset_less=True, name=f"pp{c}")
                if self._k_steady:
                    m.d.sync += pp_c.eq(chunks[c] * dm)
                else:
                    k_cc = Signal(16, reset_less=True, name=f"k_c{c}")
                    m.d.sync += [k_cc.eq(chunks[c]), pp_c.eq(k_cc * dm)]
                m.d.comb += t_c.eq(pp_c + carry)
                ts.append(t_c)
        else:
            pp = Signal(16 + mw, reset_less=True)
            t = Signal(16 + mw)                         # pp + carry < 2**(16 + mw)
            # The multiplier's k operand from a register, `k_c` (ECP5 Fmax: no word
            # multiplexer in front of the MULT18X18D), loaded a clock before `pp` is formed
            # with it: k is sampled in clocks u … u + nk − 1. No reset: read only while
            # `adding`, i.e. after a start.
            k_c = Signal(16, reset_less=True)
            m.d.comb += t.eq(pp + carry)
            # Chunk c is loaded in clock u + c: chunk 0 at the start, chunk c >= 1 while left
            # == nk + 1 − c. Other clocks load don't-care values (k_c is read only while
            # `adding`).
            k_sel = chunks[-1]
            for c in reversed(range(1, nk - 1)):
                k_sel = Mux(left == nk + 1 - c, chunks[c], k_sel)
            if nk > 1:
                k_sel = Mux(start, chunks[0], k_sel)
            m.d.sync += [k_c.eq(k_sel), pp.eq(k_c * dm)]
            ts = [t] * nk
        m.d.sync += [
            adding.eq(left != 0),
            ready.eq(left == 1),
        ]
        with m.If(start):
            m.d.sync += [carry.eq(0), left.eq(nk), sat.eq(0)]
        with m.Else():
            with m.If(left != 0):
                m.d.sync += left.eq(left - 1)
            if self._chunk_multipliers:
                for c in range(nk - 1):
                    with m.If(adding & (left == nk - 1 - c)):
                        m.d.sync += carry.eq(ts[c][16:])
            else:
                with m.If(adding & ~ready):
                    m.d.sync += carry.eq(t[16:])
        with m.If(left == nk):                          # clock u + 1: dm is the snapshot
            with m.If(dm == 0):
                m.d.sync += n_dv[0].eq(0)

        # Restoring division of acc = the product by dv, one quotient bit per clock, MSB first:
        # trial = 2·rem + next dividend bit, subtract dv when it fits. The first of the qs steps
        # sees trial = product >> (qs − 1) (w + 1 bits: the product is below 2**aw unless `sat`
        # is already set) and fits iff product >= dv·2**(qs − 1), i.e. iff the quotient needs
        # more than qs − 1 bits (or dv = 0): then `sat` is set and the result saturates,
        # whatever the later (meaningless) remainders. Otherwise the partial remainder is below
        # dv from then on, as in a divider whose dividend has qs − 1 bits above the divisor's,
        # and the qs − 1 later steps give the truncated quotient q. No separate compare of the
        # dividend's top against the divisor, no division-by-zero flag.
        # The divisor is kept inverted: trial − dv = trial + ~dv + 1, the +1 through a low bit
        # (iCE40: no inverters in front of the carry chain).
        count = Signal(range(qs + 1))                   # division steps still to run
        fin = Signal()                                  # acc holds the result
        trial = acc[qs - 1:]                            # w + 1 bits
        diff_c = Signal(w + 3)
        m.d.comb += diff_c.eq(Cat(Const(1, 1), trial)
                              + Cat(Const(1, 1), n_dv, Const(0b11, 2)))
        diff = diff_c[1:]                               # trial − dv: top bit set iff trial < dv
        fits = ~diff[-1]
        m.d.sync += fin.eq(count == 1)
        with m.If(count != 0):
            m.d.sync += [
                # Quotient bits enter as ~(q ^ sgn), all ones for q once saturated: quo[:qs − 1]
                # ends as ~(q ^ −sgn).
                acc.eq(Cat((fits | sat) ^ ~sgn, quo[:-1], Mux(fits, diff, trial)[:w])),
                count.eq(count - 1),
            ]
            with m.If((count == qs) & fits):
                m.d.sync += sat.eq(1)
        for c in range(nk):
            lo, t = 16 * c, ts[c]
            if lo >= aw:
                part, top = Const(0, 1), (t if c == nk - 1 else t[:16])
            elif c == nk - 1:
                part, top = t[:aw - lo], t[aw - lo:]
            else:
                part, top = t[:min(16, aw - lo)], t[min(16, aw - lo):16]
            with m.If(adding & (left == nk - 1 - c)):
                if lo < aw:                             # the last one zero-extended
                    m.d.sync += acc[lo:lo + 16 if c < nk - 1 else aw].eq(part)
                if len(top):
                    with m.If(top != 0):
                        m.d.sync += sat.eq(1)
        with m.If(ready):
            m.d.sync += count.eq(qs)

        # The result from the final acc: `nqx` = ~(qx), qx = q ^ −sgn in ow bits (q < 2**(qs − 1)
        # <= 2**(ow − 1), or q = s_max saturated), so that the result ±q = qx + sgn =
        # ~(nqx − sgn): a decrement, its operands straight from registers.
        nqx = Signal(ow)
        m.d.comb += nqx.eq(Cat(quo[:qs - 1], (sat ^ ~sgn).replicate(ow - qs), ~sgn))
        # A bounded result never exceeds the last fresh measurement: as the bound k/elapsed only
        # falls while the window stays open, the last output o.speed is min(bound, last fresh)
        # already, with the sign `sgn`; a bound q at or above |o.speed| leaves it as it is.
        # In a bounded update sgn is o.speed's sign, so q < |o.speed| is qx[:ow − 1] <
        # o.speed[:ow − 1] (sgn = 0) or >= (sgn = 1: −q > o.speed, i.e. ~q >= o.speed, both
        # negative): one compare of ow − 1 bits, the carry out of o.speed + ~qx.
        lt_c = Signal(ow)
        m.d.comb += lt_c.eq(p.speed[:ow - 1] + nqx[:ow - 1])
        lt = lt_c[-1] ^ sgn
        keep = (mode == WindowMode.BOUND) & ~lt
        m.d.sync += self.o.valid.eq(fin)
        with m.If(fin):
            m.d.sync += [
                busy.eq(0),
                p.stopped.eq(mode == WindowMode.STOPPED),
                p.fresh.eq(mode == WindowMode.FRESH),
            ]
            with m.If(~keep):
                m.d.sync += p.speed.eq(~(nqx - sgn))
        return m

    def _engine_result(self, m, start, busy, mode, dm, n_dv, sgn):
        """``arith="engine"``: the snapshot's operands to the engine's run and its result to
        ``o`` (class docstring, ``arith``). The snapshot registers are the ones the other form
        computes from (``n_dv`` the divisor inverted, bit 0 cleared a clock after the update
        when ``dm`` is 0: 0 / D reads 0 for D = 0 too), the request the clock after the
        update, in which ``dm`` is the snapshot."""
        run, p = self.run, self.o.payload
        m.d.sync += run.valid.eq(start)
        with m.If(run.valid & (dm == 0)):
            m.d.sync += n_dv[0].eq(0)
        m.d.comb += [run.payload.m.eq(dm), run.payload.d.eq(~n_dv), run.payload.s.eq(sgn),
                     run.payload.b.eq(mode == WindowMode.BOUND),
                     p.speed.eq(self.res.payload)]
        m.d.sync += self.o.valid.eq(self.res.valid & busy)
        with m.If(self.res.valid & busy):
            m.d.sync += [
                busy.eq(0),
                p.stopped.eq(mode == WindowMode.STOPPED),
                p.fresh.eq(mode == WindowMode.FRESH),
            ]
