# Ref: SPEC.md §2.3 (paper Fig. 6): D_n = k·ΔM/ΔT; docs/AREA.md §7.64; docs/ENGINE.md (ISA)
"""M/T speed's arithmetic as a loop-engine program piece (design and interpreter prototype,
docs/AREA.md §7.64): what :class:`~.mt_speed.MTSpeed` computes after its snapshot, the
result ``speed`` of one update from the window's operands, on the engine's 32-bit register
file, 45-bit ``P``, 19 × 28 multiplier and 16-bit ``DIV`` steps.

The gateware part that stays (TC's ages, the edge count ΔM, the window/stopped/fresh logic)
gives, at each accepted update, the operands of :func:`mt_operands`: ``mtm`` the dividend's
factor (``|ΔM|`` fresh, 1 bounded, 0 stopped), ``mtd`` the divisor (ΔT fresh, the ticks since
the reference bounded; bit 0 set when ``mtm`` is 0, as ``MTSpeed`` sets its divisor's, so that
0/0 reads 0), ``mts`` the result's sign (ΔM's, or the last output's when bounded) and ``mtb``
(1 = bounded: the result is the last output bounded by ``k/elapsed``). ``k`` (48 bits) comes in
two 24-bit slices ``mkl = k[0:24]``, ``mkh = k[24:48]`` (wiring, as the speed loop's gains).

The piece (:func:`mt_arith`) computes, with ``N = k·mtm`` (< 2**63) and ``D = mtd``::

    G = floor(N / 2**24) = mkh·mtm + floor(mkl·mtm / 2**24)        (MUL, post, MUL, MAC)
    saturated  iff  N >= 2**31·D  iff  G >= 2**7·D                 (MAC, post, flag; then
        the division below runs on 0 / 1 and 2**31 − 1 is added, or ``branches``: a BR)
    A = floor(N / 2**16) = (mkh·mtm)·2**8 + floor(mkl·mtm / 2**16)  (MUL, 8 DIV steps by D,
        whose trials stay below D/2 (A < 2**15·D): a left shift, no new constant; MAC), so
    q1 = floor(A / D) < 2**15, R1 = A mod D                         (16 DIV steps)
    q2 = floor((R1·2**16 + N mod 2**16) / D) < 2**16                (MACs, 16 DIV steps)
    q  = q1·2**16 + q2 = floor(N / D), or 2**31 − 1 saturated      (MUL, MAC, post)
    |speed| = min(|last|, q) if bounded else q;  speed = −|speed| if mts else |speed|

which is :func:`~foc_servo.sim.models.mt_speed.fresh_speed` (and ``simulate``'s bounded and
stopped outputs) bit for bit for ``out_width`` 32, ``k_width`` 48, ``m_width`` 16 and a divisor
below 2**27: the ``DIV`` step's divisor is the multiplier's 28-bit signed B operand, so the
TC span must be 27 bits (:data:`MT_ENGINE_PARAMS`; the iCEBreaker top has 28 today:
:data:`~.top.MT_TC_WIDTH`). ``|last|`` is the register ``mt_pm`` (:data:`MT_STATE`), the
magnitude of the last output.
"""

from amaranth.hdl import signed, unsigned

from .engine import MUL_B, Assembler, Op
from .foc_engine import DUTY_CLOCKS, START_CLOCKS, _clocks, _paths

__all__ = ["MT_SPECIALS", "MT_SHAPES", "MT_OUTS", "MT_STATE", "MT_ENGINE_PARAMS", "MT_SAT",
           "MT_RUN_SPECIALS", "MT_RUN_SHAPES", "MT_CONFIG_WORDS", "MT_K_FORMS",
           "mt_arith", "mt_program", "mt_operands", "mt_k_slices", "mt_k_words",
           "mt_run_timing"]

#: The MTSpeed parameters the piece is written for (the iCEBreaker top's, but the TC span:
#: 27 bits, the ``DIV`` divisor's limit).
MT_ENGINE_PARAMS = {"out_width": 32, "k_width": 48, "m_width": 16, "tc_width": 27}
#: The saturated magnitude, ``2**(out_width − 1) − 1``.
MT_SAT = (1 << (MT_ENGINE_PARAMS["out_width"] - 1)) - 1
#: The piece's special operands (A side): the window's operands and ``k``'s slices.
MT_SPECIALS = ("mtm", "mtd", "mts", "mtb", "mkl", "mkh")
#: Their shapes as the gateware would feed them (zero-extended to the 32-bit word).
MT_SHAPES = {"mtm": unsigned(MT_ENGINE_PARAMS["m_width"]),
             "mtd": unsigned(MT_ENGINE_PARAMS["tc_width"]), "mts": unsigned(1),
             "mtb": unsigned(1), "mkl": unsigned(24), "mkh": unsigned(24)}
#: ``k`` as the piece takes it (:func:`mt_arith` ``k``): ``"slices"`` the specials ``mkl``,
#: ``mkh`` (24 bits each, wiring); ``"words"`` the register file's two export words of the
#: 48-bit ``mt_k`` as configuration words of the engine's RAM (:data:`MT_CONFIG_WORDS`), which
#: the piece splits itself.
MT_K_FORMS = ("slices", "words")
#: ``k="words"``: the configuration words (the register file's export words of ``mt_k``,
#: :func:`mt_k_words`): ``mtk0`` = k[0:32] (read sign-extended from 32 bits, as the
#: engine's 32-bit configuration RAM gives it), ``mtk1`` = k[32:48].
MT_CONFIG_WORDS = ("mtk0", "mtk1")
#: The specials of the run on the loop engine (``EngineCurrentLoop(mt=True)``): the window's
#: four operands (ports: one key each, 4 of the ROM's 31; ``mts`` and ``mtb`` are 1-bit lines
#: of the special select) and ``k``'s two configuration words (the configuration key).
MT_RUN_SPECIALS = ("mtm", "mtd", "mts", "mtb") + MT_CONFIG_WORDS
#: Their shapes.
MT_RUN_SHAPES = {**{n: MT_SHAPES[n] for n in MT_RUN_SPECIALS[:4]}, "mtk0": signed(32),
                 "mtk1": unsigned(16)}
#: Its output register: the signed speed, Q1.31 of N_M.
MT_OUTS = {"ang": 16, "mtspd": 32}
#: The register that holds state from one update to the next: ``|last output|``.
MT_STATE = ("mt_pm",)

#: ``DIV``'s divisor is the multiplier's signed B operand (28 bits).
_DIV_MAX = (1 << (MUL_B - 1)) - 1


def mt_k_slices(k):
    """``k`` (unsigned, 48 bits) as the specials ``mkl``, ``mkh``."""
    if not isinstance(k, int) or isinstance(k, bool) or not 0 <= k < 1 << 48:
        raise ValueError(f"M/T k must be an integer from 0 to 2**48 − 1, not {k!r}")
    return {"mkl": k & ((1 << 24) - 1), "mkh": k >> 24}


def mt_k_words(k):
    """``k`` (unsigned, 48 bits) as the configuration words ``mtk0`` (k[0:32] as the engine
    reads it: sign-extended from 32 bits) and ``mtk1`` (k[32:48])."""
    mt_k_slices(k)                                      # (checks k)
    lo = k & 0xFFFFFFFF
    return {"mtk0": lo - (1 << 32) if lo >> 31 else lo, "mtk1": k >> 32}


def mt_operands(mode, dm, dt, last):
    """The specials the gateware gives the piece for one update (besides ``k``'s).

    Parameters
    ----------
    mode : int
        :data:`~foc_servo.sim.models.mt_speed.STOPPED`, ``BOUND`` or ``FRESH``.
    dm, dt : int
        The operands ``simulate`` reports (fresh: ΔM, ΔT; bounded: 1 and the ticks since the
        reference; stopped: ignored).
    last : int
        The last output (signed): its sign is a bounded result's.

    Raises
    ------
    ValueError
        If ``dm`` or ``dt`` is out of the piece's range (``|ΔM| <= 2**15``,
        ``0 <= ΔT < 2**27``).
    """
    from ..sim.models.mt_speed import BOUND, FRESH, STOPPED
    if mode == STOPPED:
        m, d, s = 0, 1, 0
    elif mode == BOUND:
        m, d, s = 1, int(dt), int(last < 0)
    elif mode == FRESH:
        m, d, s = abs(int(dm)), int(dt), int(dm < 0)
    else:
        raise ValueError(f"M/T mode must be STOPPED, BOUND or FRESH, not {mode!r}")
    if not m <= 1 << (MT_ENGINE_PARAMS["m_width"] - 1):
        raise ValueError(f"M/T |ΔM| must be at most 2**15, not {m}")
    if not 0 <= d <= _DIV_MAX:
        raise ValueError(f"M/T ΔT must be from 0 to 2**27 − 1, not {d}")
    if m == 0:
        d |= 1              # 0 / D reads 0 for D = 0 too (MTSpeed sets its divisor's bit 0)
    return {"mtm": m, "mtd": d, "mts": s, "mtb": int(mode == BOUND)}


def mt_arith(A, *, out="mtspd", dst=None, prefix="mt_", branches=False, k="slices"):
    """Emit the M/T piece (module docstring) without an END into the assembler ``A`` (its
    specials :data:`MT_SPECIALS`, its output ``out``): temporaries and labels carry
    ``prefix``; the state register is ``r.mt_pm``; ``dst``: a register that takes the
    speed too (for a program that goes on with it). ``branches``: the saturated case takes a
    branch around the division (shorter there, but the piece is then three straight-line
    regions); else it runs the division on 0 / 1 and selects the saturated value after it
    (one region, which the assembler can interleave with other straight-line code).
    ``k``: :data:`MT_K_FORMS` — ``"words"`` reads ``k`` as the configuration words
    :data:`MT_CONFIG_WORDS` and forms the slices in the register file (5 instructions more,
    no new constant: the engine's guard shift ``asl`` must be 8)::

        t = floor(L / 2**24)  (L = mtk0, signed: −128 … 127; N: L < 0)
        mkl = L − t·2**24 = k mod 2**24     (the product t·2**25 posted >> 1)
        mkh = mtk1·2**8 + t + (256 if L < 0)"""
    if k not in MT_K_FORMS:
        raise ValueError(f"M/T piece k must be one of {MT_K_FORMS}, not {k!r}")
    # Five temporaries, each value in the first one free (by the written order; the
    # scheduler keeps every read before the next write of a register).
    slot = dict(kl="a", c24="a", sg="a", sv="a", kh="b", khs="b", q1="b", mm="b", c16="c",
                c16s="c", q2="c", nm="c", d="d", ds="d", q="d", lo="e", los="e", qd="e",
                t8="f", c8="g", u="h", x="c")
    r = lambda name: f"r.{prefix}{slot[name]}"                            # noqa: E731
    sat, done = prefix + "sat", prefix + "out"
    if k == "slices":
        A.alu(Op.ADD, r("kl"), "s.mkl", 0)
        A.alu(Op.ADD, r("kh"), "s.mkh", 0)
    else:
        A.alu(Op.ADD, r("t8"), "s.mtk0", 0, sh=24, setf=True)    # N: L < 0 (k bit 31)
        A.alu(Op.SEL, r("c8"), 0, 256, cond="N")
        A.mul(r("t8"), 1 << 25)
        A.post(r("u"), 1, rnd=False)                            # t·2**24
        A.alu(Op.SUB, r("kl"), "s.mtk0", r("u"))
        A.alu(Op.ADD, r("x"), "s.mtk1", r("t8"), asl=True)
        A.alu(Op.ADD, r("kh"), r("x"), r("c8"))
    A.alu(Op.ADD, r("d"), "s.mtd", 0)
    A.mul("s.mtm", r("kl"))                         # P1 = mkl·m < 2**39
    A.post(r("c24"), 24, rnd=False)
    A.post(r("c16"), 16, rnd=False)
    A.alu(Op.ADD, r("lo"), "s.PQ", 0)               # N mod 2**16 = P1 mod 2**16
    A.mul("s.mtm", r("kh"))
    A.mac(1, r("c24"))                              # G = floor(N / 2**24)
    if k == "slices":
        A.mac(1 << 7, r("d"), neg=True)             # G − 2**7·D
    else:                                           # (the same, without the constant 128)
        A.mac(1 << 6, r("d"), neg=True)
        A.mac(1 << 6, r("d"), neg=True)
    A.post(r("sg"), 31, rnd=False)                  # < 0 iff not saturated
    A.alu(Op.ADD, None, r("sg"), 0, setf=True)     # N: not saturated
    if branches:
        A.br("!N", sat)
        A.nop()
        A.nop()
        kh, c16, lo, d = r("kh"), r("c16"), r("lo"), r("d")
    else:
        # Saturated: the division runs on 0 / 1 (no overflow) and gives 0, to which
        # sv = 2**31 − 1 is added (the flag is read here only: the piece interleaves with
        # code that uses the flags).
        kh, c16, lo, d = r("khs"), r("c16s"), r("los"), r("ds")
        for x, v in ((kh, "kh"), (c16, "c16"), (lo, "lo")):
            A.alu(Op.SEL, x, 0, r(v), cond="N")
        A.alu(Op.SEL, d, 1, r("d"), cond="N")
        A.alu(Op.SEL, r("sv"), MT_SAT, 0, cond="N")
    A.mul("s.mtm", kh)                              # < 2**34 when not saturated
    A.div(d, 8)                                     # ·2**8: every trial is below D / 2
    A.mac(1, c16)                                   # A = floor(N / 2**16) < 2**15·D
    A.div(d, 16)                                    # P = R1·2**16 + q1
    A.alu(Op.ADD, r("q1"), "s.PQ", 0)
    A.mac(1, r("q1"), neg=True)
    A.mac(1, lo)                                    # P = R1·2**16 + N mod 2**16
    A.div(d, 16)                                    # P = R2·2**16 + q2
    A.alu(Op.ADD, r("q2"), "s.PQ", 0)
    A.mul(r("q1"), 1 << 16)
    A.mac(r("q2"), 1)
    if branches:
        A.post(r("q"), 0)                           # floor(N / D) < 2**31
        A.br("!F", done)
        A.nop()
        A.nop()
        A.label(sat)
        A.alu(Op.ADD, r("q"), MT_SAT, 0)
        A.label(done)
    else:
        A.post(r("qd"), 0)
        A.alu(Op.ADD, r("q"), r("qd"), r("sv"))
    # Bounded: min(|last|, q) (MIN: B if c or A − B ≥ 0, else A; c = Z = not bounded: q).
    A.alu(Op.ADD, None, "s.mtb", 0, setf=True)
    A.alu(Op.MIN, r("mm"), "r.mt_pm", r("q"), cond="Z")
    A.alu(Op.RSUB, None, "s.mts", 0, setf=True)     # N: negative
    A.alu(Op.ADD, "r.mt_pm", r("mm"), 0)
    A.alu(Op.RSUB, r("nm"), r("mm"), 0)
    A.alu(Op.SEL, dst, r("mm"), r("nm"), cond="N", out=out)


def mt_program(*, fuse=True, schedule=True, branches=False, k="slices"):
    """The M/T piece alone as a program (:func:`mt_arith`, then END): the prototype the
    interpreter runs (:class:`~foc_servo.sim.models.engine_mt.EngineMTModel`); ``k="words"``
    with the specials :data:`MT_RUN_SPECIALS` (the run's in ``EngineCurrentLoop(mt=True)``)."""
    A = Assembler(specials=MT_SPECIALS if k == "slices" else MT_RUN_SPECIALS, conds=(),
                  outs=tuple(MT_OUTS))
    mt_arith(A, branches=branches, k=k)
    A.end()
    return A.assemble(fuse=fuse, schedule=schedule)


def mt_run_timing(program, *, out="mtspd"):
    """Per path through ``program`` from its ``mt`` label (or 0): ``latency``, the clocks from
    the run's start to the output ``out`` in place (its write + :data:`DUTY_CLOCKS`, a
    strobe registered as the speed run's ``o.valid`` is), and ``length``, the clocks until
    the engine takes its next start (executed instructions + :data:`START_CLOCKS`). A sorted
    list of ``(latency, length)``, one per distinct path timing."""
    start = program.labels.get("mt", 0)
    index = program.outs.index(out)
    timing = set()
    for path in _paths(program, start):
        k, at = 0, None
        for pc in path:
            ins = program.instrs[pc]
            if ins.out == index:
                at = k
            k += _clocks(ins)
        if at is None:
            raise ValueError(f"M/T program: a path without a write of {out}")
        timing.add((at + 1 + DUTY_CLOCKS, k + START_CLOCKS))
    return sorted(timing)
