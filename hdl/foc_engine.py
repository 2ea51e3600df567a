# Ref: paper eq. (1), (4)–(9), Fig. 7; SPEC.md §2, §2.5; AREA.md §4 stage 2; docs/ENGINE.md
"""The current loop as a program of the loop engine (:mod:`.engine`): a drop-in alternative to
:class:`~.foc.CurrentLoop` with its ports (but the ``theta_lead`` register, ``lead_k``, in place
of θ_lead) and bit-identical results (:class:`~foc_servo.sim.models.foc.CurrentLoopModel`, with
θ_lead as :class:`~.top.LeadAngle` makes it), one multiplier instead of ≈ 20, and a longer
latency (:attr:`EngineCurrentLoop.latency`; docs/ENGINE.md).

The program (:func:`current_loop_program`) follows ``hdl/foc.py`` step by step; the rotator's
integer sine and cosine are computed from the same table and ``kd`` ROM as
:class:`~.rotator.Rotator` (``RotatorParams``), the interpolation rewritten as one
multiply-accumulate per term with floor shifts (the same integers as the model's
``trig``). The inverse Park's advance θ_lead = ``round_shift(n·k, 15)`` (``n`` the sample's
speed as the feed-forward's, ``k`` = ``lead_k``) is one product (as :class:`~.top.LeadAngle`'s
shift-and-add). The DC-bus gain ``min(round(U_rated·2**16 / U_dc), L)`` (as
:class:`~.svpwm.DCBusCompensation`'s divider) is computed by the program from the sample's
``U_dc`` after its duties (18 ``DIV`` steps; the limit test, ``dc_limited``, before them) into
a register that the next sample's inverse Park uses: each sample is compensated with the
previous sample's bus voltage, as in :class:`~.foc.CurrentLoop` (1.0 at power-up).
"""

import math

from amaranth.hdl import Cat, Const, Module, Mux, Signal, signed, unsigned
from amaranth.lib import data, stream, wiring
from amaranth.lib.memory import Memory, ReadPort
from amaranth.lib.wiring import In, Out

from .bus import WordWriteSignature
from .dsp import saturate_bits
from .engine import SAT_W, SAT_W1, WRITE_DELAY, Assembler, Engine, Fetch, Op
from .fixed import Q, UQ, check_bool, check_choice, round_shift_plain
from .foc import ADC_CHANNELS, FF_FORMAT, SPEED_WIDTH, sample_handshake
from .rotator import RotatorParams

__all__ = ["EngineCurrentLoop", "current_loop_program", "path_lengths", "duty_lengths",
           "phase_latency", "sample_read", "SPECIALS", "BSPECIALS", "CONDS", "OUTS", "CONFIG", "CONFIGS",
           "ENGINE_WIDTH", "PIPELINE_CLOCKS", "DUTY_CLOCKS", "START_CLOCKS", "DCBUS_GAIN_FRAC",
           "STATUS", "STATUS_OUTS", "STATUSES", "status_quiet", "speed_loop_program",
           "speed_run_timing", "SPEED_CONFIG_WORDS", "SPEED_SLICES", "SPEED_PARAMS",
           "REF_CONFIG_WORDS", "REFS", "REF_SPECIALS", "REF_OUTS", "REF_STATUS",
           "REF_STATUS_OUTS",
           "CURRENT_STATE", "SPEED_STATE",
           "SPEED_SPECIALS", "SPEED_SHAPES", "SPEED_FLAGS", "SPEED_CONDS", "SPEED_OUTS"]

#: The only configuration the program is written for (validated by EngineCurrentLoop).
ENGINE_WIDTH = 16
#: Fraction bits of the DC-bus gain (UQ2.16, as :class:`~.svpwm.DCBusCompensation`'s).
DCBUS_GAIN_FRAC = 16

#: User special operands: latched sample values (``ia``, ``ib``: the sample port itself,
#: :attr:`EngineCurrentLoop.sample_read`) and configuration ports.
SPECIALS = ("ia", "ib", "theta", "klead", "id_ref", "iq_ref", "ol_ud", "ol_uq", "nspd",
            "gain_a", "gain_b", "off_a", "off_b", "kp_d", "kx_d", "lo_d", "hi_d", "kp_q",
            "kx_q", "lo_q", "hi_q", "ff_l", "ff_psi", "scale", "udc", "urat")
#: Specials that may be operand B (not a configuration special: ``config="ram"`` reads those
#: as A operands only).
BSPECIALS = ("ia", "ib", "nspd", "scale")
#: The configuration specials read from the engine's configuration RAM with ``config="ram"``,
#: in its word order (the port each comes from with ``config="ports"``: :data:`CONFIG_PORTS`).
CONFIG = ("gain_a", "gain_b", "off_a", "off_b", "kp_d", "kx_d", "lo_d", "hi_d", "kp_q", "kx_q",
          "lo_q", "hi_q", "ff_l", "ff_psi", "klead", "urat")
#: ``config="ports"``: the EngineCurrentLoop port of each configuration special.
CONFIG_PORTS = {"gain_a": "gain_a", "gain_b": "gain_b", "off_a": "offset_a",
                "off_b": "offset_b", "kp_d": "kp_d", "kx_d": "kx_d", "lo_d": "lim_lo_d",
                "hi_d": "lim_hi_d", "kp_q": "kp_q", "kx_q": "kx_q", "lo_q": "lim_lo_q",
                "hi_q": "lim_hi_q", "ff_l": "ff_l", "ff_psi": "ff_psi", "klead": "lead_k",
                "urat": "u_rated"}
#: Values of ``EngineCurrentLoop(config=...)``.
CONFIGS = ("ports", "ram")
#: ``EngineCurrentLoop(refs="ram")``: the references read from the configuration RAM (words
#: after :data:`CONFIG`, before the speed loop's :data:`SPEED_CONFIG_WORDS`) in place of the
#: ports ``ol_ud``, ``ol_uq``, ``id_ref``, ``iq_ref``, ``iq_lim_lo``, ``iq_lim_hi`` and the
#: latches of the first four: the open-loop voltages (the program selects them by ``OL``), the
#: current set-points ``idset``, ``iqset`` and the i_q limits ``ilo``, ``ihi`` (the speed run's
#: specials, now words), from which the program forms the references as the Servo did
#: (``current_loop_program(refs=True)``). The register file's export port writes them at its
#: commit copy, while the loop is idle (hdl/top.py).
REF_CONFIG_WORDS = ("ol_ud", "ol_uq", "idset", "iqset", "ilo", "ihi")
#: ``current_loop_program(refs=True)``: the special operands of the references (the
#: configuration words ``idset``, ``iqset``, the speed run's i_q reference ``sliq``) and the
#: outputs that show the references the program used (the scope's ``i_d_ref``, ``i_q_ref``).
REF_SPECIALS = ("idset", "iqset", "sliq")
REF_OUTS = {"idr": 16, "iqr": 16}
#: ``refs="ram"``: the status RAM's words after :data:`STATUS` (the references the program
#: used, for the scope; no status registers) and the outputs that write them.
REF_STATUS = ("i_d_ref", "i_q_ref")
REF_STATUS_OUTS = {"i_d_ref": "idr", "i_q_ref": "iqr"}
#: Values of ``EngineCurrentLoop(refs=...)``.
REFS = ("ports", "ram")
#: Values of ``EngineCurrentLoop(status=...)``.
STATUSES = ("ports", "ram")
#: The status outputs (``status="ram"``: the status RAM's words, in this order).
STATUS = ("i_alpha", "i_beta", "i_d", "i_q", "u_d", "u_q", "u_alpha", "u_beta")
#: The engine output each status value is written by.
STATUS_OUTS = {"i_alpha": "pa", **{name: name for name in STATUS[1:]}}
#: User conditions.
CONDS = ("RUN", "OL", "FF")
#: Output registers and their widths (``ang`` is the engine's angle register).
OUTS = {"ang": 16, "pa": 16, "pb": 16, "pc": 16, "i_beta": 16, "i_d": 16, "i_q": 16,
        "u_d": 16, "u_q": 16, "u_alpha": 16, "u_beta": 16, "sat_d": 1, "sat_q": 1, "om": 1,
        "da": 16, "db": 16, "dc": 16, "lim": 1}

#: The current-loop program's registers that hold state from one sample to the next (the
#: PIs' integrators and previous errors, the DC-bus gain); its other registers are
#: temporaries, free after its END.
CURRENT_STATE = ("i_d", "ep_d", "i_q", "ep_q", "dcg")
#: The speed-loop program's registers that hold state from one run to the next.
SPEED_STATE = ("h0", "h1", "h2", "ih", "il", "ep")

#: The speed-loop program's special operands (:func:`speed_profile_program`; docs/ENGINE.md
#: "Speed loop as a program"): the speed sample ``spd`` (the ``speed`` port, held from the
#: run's request to its read: :attr:`EngineCurrentLoop.speed_read`),
#: ``speed_ref``, the profile's reference ``ref_int`` (the output register, which the gateware
#: forces to the tracked value while ``clear``), the slew as ``slh = S >> 1`` and ``sll = S & 1``
#: (S is UQ1.31: no signed 32-bit operand holds it), ``iq_ff``, the i_q limits and the
#: fraction of ``ref_delay``; the gains in pieces that fit the multiplier's A operand
#: (wiring only): ``kph = kp >> 16``, ``kpl = kp & 0xFFFF``, ``kxa = (kx >> 16)·2**10``,
#: ``kxb = (kx >> 4) & 0xFFF``, ``kxc = kx & 0xF``.
#: Last the 1-bit flags (:data:`SPEED_FLAGS`) and ``dint``, the integer part of ``ref_delay``
#: (0 … 3), tested by an ``ADD``/``SUB`` with ``setf`` (then ``Z``, ``N``), not as conditions:
#: a condition-mux input per flag lengthened the engine's critical path (AREA.md §7.45: 15
#: conditions, 33.58 → 32.28 MHz on the UP5K); one 2-bit ``dint`` instead of three bits keeps
#: the program ROM's special-operand key at 5 bits (31 keys; the ROM 64 bits wide, 8 BRAM).
SPEED_SPECIALS = ("spd", "sref", "rint", "slh", "sll", "iqff", "ilo", "ihi", "dfr", "kph",
                  "kpl", "kxa", "kxb", "kxc", "fresh", "ih", "dint")
#: Shapes of :data:`SPEED_SPECIALS` as the gateware feeds them (the engine sign- or
#: zero-extends each to its 32-bit word): the speeds and ``ref_int`` signed(32), the slew's
#: halves, the currents signed(16), the gains' pieces (``kp``, ``kx`` UQ(24, ·)) unsigned.
SPEED_SHAPES = {"spd": signed(32), "sref": signed(32), "rint": signed(32), "slh": unsigned(31),
                "sll": unsigned(1), "iqff": signed(16), "ilo": signed(16), "ihi": signed(16),
                "dfr": unsigned(3), "kph": unsigned(8), "kpl": unsigned(16),
                "kxa": unsigned(18), "kxb": unsigned(12), "kxc": unsigned(4),
                "fresh": unsigned(1), "ih": unsigned(1), "dint": unsigned(2)}
#: The 1-bit special operands: first run after ``clear`` (``fresh``), ``int_hold``.
SPEED_FLAGS = ("fresh", "ih")
#: Its conditions: none of its own (the flags are special operands).
SPEED_CONDS = ()
#: Its output registers (``ang`` only because every engine has one).
SPEED_OUTS = {"ang": 16, "ref_int": 32, "iq": 16, "sat": 1}
#: ``EngineCurrentLoop(speed=True)``: the configuration RAM's words after :data:`CONFIG`, the
#: speed loop's (:data:`~.servo.SPEED_CONFIG` order: ``kp``, ``kx``, ``speed_slew``,
#: ``iq_ff``; the register file's export words in that order). ``iqff`` is read as a word,
#: the others through :data:`SPEED_SLICES`.
SPEED_CONFIG_WORDS = ("kp", "kx", "slew", "iqff")
#: The speed specials that are slices of a configuration word (``Engine(config_slices=)``:
#: ``name: (word, lo, bits, shift)``), as :data:`SPEED_SPECIALS` defines them.
SPEED_SLICES = {"kph": ("kp", 16, 8, 0), "kpl": ("kp", 0, 16, 0), "kxa": ("kx", 16, 8, 10),
                "kxb": ("kx", 4, 12, 0), "kxc": ("kx", 0, 4, 0), "slh": ("slew", 1, 31, 0),
                "sll": ("slew", 0, 1, 0)}
#: The speed-loop parameters the program is written for (:class:`~.servo.SpeedLoop`'s, the
#: iCEBreaker top's): ``EngineCurrentLoop(speed=True)`` / ``Servo(speed_loop="engine")``.
SPEED_PARAMS = {"speed_width": 32, "width": 24, "kp_format": UQ(24, 12),
                "kx_format": UQ(24, 20), "int_guard": 16, "delay_width": 5}


def _trig(asm, rot, pending=None, filler=None):
    """Integer |cos| / |sin| of the angle register into ``r.c1``, ``r.s1`` (signs: conditions
    NEGC, NEGS). The assembler keeps the table reads ``HAZARD_TABLE`` after the ``ang`` write.
    ``pending`` emits a post of the caller's product (it fuses into the first MUL), ``filler``
    one independent instruction (else a NOP goes there)."""
    w, g = rot.width, rot.interp_guard
    A = asm
    A.alu(Op.ADD, "r.v", "s.TC", 1 << (w + 2))                      # C'' + 2**(w+2)
    A.alu(Op.ADD, "r.us", "s.TS", 1 << (w + 1))                     # S'' + 2**(w+1)
    A.alu(Op.ADD, "r.shi", "s.TS", 1 << (w + 1), sh=3)              # (S'' >> 3) + 2**(w−2)
    A.alu(Op.ADD, "r.chi", "r.v", 0, sh=4)                          # (C'' >> 4) + 2**(w−2)
    if pending is not None:
        pending()
    # c_t = c_o + 2**w = floor(((C'' + 2**(w+2))·2**g − (kd·S_hi >> shift_s)) / 2**(g+2))
    A.mul("s.KD", "r.shi")
    A.post("r.t", rot.shift_s, rnd=False)
    # s_t = s_o + 2**(w−1) = floor((kd·C_hi + (S'' + 2**(w+1))·2**(g+shift_c)) / 2**(shift_c+g+2))
    A.mul("s.KD", "r.chi")
    A.mac("r.us", 1 << (g + rot.shift_c))
    A.post("r.st", rot.shift_c + g + 2, rnd=False)
    A.mul(1 << g, "r.v")
    A.mac("r.t", -1)
    A.post("r.ct", g + 2, rnd=False)
    if filler is not None:
        filler()
    A.alu(Op.SEL, "r.c1", "r.ct", "r.st", cond="SWAP")
    A.alu(Op.SEL, "r.s1", "r.st", "r.ct", cond="SWAP")


def _rotate(asm, x, y, xo, yo, out_x, out_y, w):
    """(xo, yo) = rotation of (x, y) by the angle register (after :func:`_trig`)."""
    A = asm
    A.mul(x, "r.c1", cond="NEGC")
    A.mac(y, "r.s1", neg=True, cond="NEGS")
    A.post(xo, w, sat=SAT_W, out=out_x)
    A.mul(x, "r.s1", cond="NEGS")
    A.mac(y, "r.c1", cond="NEGC")
    A.post(yo, w, sat=SAT_W, out=out_y)


def _pi_head(asm, ax, fb, ref=None):
    asm.alu(Op.SUB, f"r.e_{ax}", ref or f"s.i{ax}_ref", fb, sat=SAT_W)


def _pis(asm, *, kx_shift, filler=None):
    """PI_d and PI_q (after :func:`_pi_head`), written interleaved (the assembler's scheduler
    reorders further to fill the write-back distance) with no flag test separated from its
    flag-setting instruction by another: ``r.o_d``, ``r.o_q``, ``sat_d``,
    ``sat_q``, then the commands ``u_d = sat(o_d − ff_d)``, ``u_q = sat(o_q + ff_q)``.

    Per axis (hdl/pi.py): ``sx = E + E[n−1]``; ``−dI = round_shift(−kx·sx)`` (rounding is odd);
    ``p = kp·E``; ``I + dI`` clamped to the limits·2**g by MIN then MAX (``clamp`` exactly);
    ``u_c``; hold = (u_c > hi and dI > 0) or (u_c < lo and dI < 0); ``u``; output clamp; sat.
    ``filler()`` emits one independent instruction (no flags, no register the PIs use); the
    assembler's scheduler reorders the whole anyway (:meth:`Assembler.assemble`)."""
    A = asm
    g = A.guard
    r = lambda name, ax: f"r.{name}_{ax}"
    A.alu(Op.ADD, "r.sx_d", "r.e_d", "r.ep_d")
    A.alu(Op.ADD, "r.sx_q", "r.e_q", "r.ep_q")
    A.alu(Op.ADD, "r.ep_d", "r.e_d", 0)                               # E[n−1] = E
    A.mul("s.kx_d", "r.sx_d", neg=True)
    A.post("r.ndi_d", kx_shift)     # (each post fuses into the MUL after it: it sees the old P)
    A.mul("s.kx_q", "r.sx_q", neg=True)
    A.post("r.ndi_q", kx_shift)
    A.mul("s.kp_d", "r.e_d")
    A.post("r.pp_d", 0)
    A.mul("s.kp_q", "r.e_q")
    A.post("r.pp_q", 0)
    for ax in "dq":
        A.alu(Op.SUB, r("isum", ax), f"r.i_{ax}", r("ndi", ax))       # I + dI
    A.alu(Op.MIN, "r.t_d", "s.hi_d", "r.isum_d", asl=True, setf=True)   # N: sum > hi·2**g
    A.alu(Op.ADD, "r.ep_q", "r.e_q", 0)
    A.alu(Op.MAX, "r.ic_d", "s.lo_d", "r.t_d", asl=True, cond="N")
    A.alu(Op.MIN, "r.t_q", "s.hi_q", "r.isum_q", asl=True, setf=True)
    A.alu(Op.ADD, "r.uc_d", "r.pp_d", "r.ic_d", sh=g, rnd=True)
    A.alu(Op.MAX, "r.ic_q", "s.lo_q", "r.t_q", asl=True, cond="N")
    A.alu(Op.SUB, None, "s.hi_d", "r.uc_d", setf=True)                # N: u_c > hi
    A.alu(Op.ADD, "r.uc_q", "r.pp_q", "r.ic_q", sh=g, rnd=True)
    for ax in "dq":
        A.alu(Op.SEL, r("h1", ax), 0, r("ndi", ax), cond="N")          # h1 < 0: hold (1)
        A.alu(Op.SUB, None, f"s.lo_{ax}", r("uc", ax), setf=True)     # !LE: u_c < lo
        A.alu(Op.SEL, r("h2", ax), 0, r("ndi", ax), cond="!LE")        # h2 > 0: hold (2)
        if ax == "d":
            A.alu(Op.SUB, None, "s.hi_q", "r.uc_q", setf=True)
    for ax in "dq":
        A.alu(Op.ADD, None, r("h1", ax), 0, setf=True)
        A.alu(Op.SEL, r("t", ax), r("ic", ax), f"r.i_{ax}", cond="N")
        A.alu(Op.SUB, None, 0, r("h2", ax), setf=True)
        A.alu(Op.SEL, f"r.i_{ax}", r("t", ax), f"r.i_{ax}", cond="N")  # I unless held
    for ax in "dq":
        A.alu(Op.ADD, r("u", ax), r("pp", ax), f"r.i_{ax}", sh=g, rnd=True)
    A.alu(Op.MIN, "r.t_d", "s.hi_d", "r.u_d", setf=True)              # N: u > hi
    if filler is not None:
        filler()
    A.alu(Op.MAX, "r.o_d", "s.lo_d", "r.t_d", cond="N", sat=SAT_W)    # clamp(u, lo, hi)
    A.alu(Op.MIN, "r.t_q", "s.hi_q", "r.u_q", setf=True)
    A.alu(Op.SUB, None, "r.o_d", "r.u_d", out="sat_d")                # sat = out ≠ u
    A.alu(Op.MAX, "r.o_q", "s.lo_q", "r.t_q", cond="N", sat=SAT_W)
    A.alu(Op.SUB, "r.ud", "r.o_d", "r.ffd", sat=SAT_W, out="u_d")
    A.alu(Op.SUB, None, "r.o_q", "r.u_q", out="sat_q")
    A.alu(Op.ADD, "r.uq", "r.o_q", "r.ffq", sat=SAT_W, out="u_q")


def _lead_lim(A, gain_limit_raw):
    """The products of θ_lead (``r.lead``) and of the DC-bus gain's limit test (``r.lt``)."""
    # θ_lead = round_shift(n·k, 15) mod 2**16 (hdl/top.py LeadAngle: n the sample's speed, Q1.15
    # of N_FS, as the feed-forward's; k the theta_lead register, UQ0.16 turns at N_FS).
    A.mul("s.klead", "b.nspd")
    A.post("r.lead", 15)
    # DC-bus gain limit test (the gain itself is computed after the duties, below):
    # gain = round(R·2**16 / U) half up = floor(M / U), M = R·2**16 + floor(U/2) (R = U_rated,
    # U = max(U_dc, 0)); limited (U = 0 or gain > L) iff M ≥ (L + 1)·U iff
    # R·2**17 − (2L + 1)·U_dc ≥ 0 (with U_dc < 0 too).
    A.mul("s.urat", 1 << 17)
    A.mac("s.udc", 2 * gain_limit_raw + 1, neg=True)
    A.post("r.lt", 31, rnd=False)                         # < 0: not limited (|P| < 2**35)


def current_loop_program(*, width=16, clarke_gain_frac=15, kp_frac=8, kx_frac=16, int_guard=8,
                         count_width=16, gain_limit_raw=2 << 16, rotator=None, fuse=True,
                         schedule=True, fold=True, speed=False, refs=False,
                         mt=False, realloc=True):
    """Assemble the current-loop program (the configuration of :class:`EngineCurrentLoop`);
    ``fuse`` lets the assembler fuse posts into the following MUL, ``schedule`` reorder the
    straight-line code, ``fold`` fold NOPs into the word before them as its bubbles
    (:meth:`Assembler.assemble`). ``speed``: the speed-loop run
    (:func:`speed_loop_program`) follows at the label ``speed`` (its entry), its temporaries in
    the current loop's registers (:data:`CURRENT_STATE` excepted), its specials, conditions
    and outputs after the current loop's (whose words are then the same but for the constants'
    addresses); the plan's step 2 (docs/ENGINE.md). ``refs`` (with ``speed``): the current
    references from the configuration words and the speed run's result
    (:data:`REF_SPECIALS`; ``EngineCurrentLoop(refs="ram")``). ``mt``: M/T speed's arithmetic
    (:func:`~.engine_mt.mt_arith`, ``k="words"``) as the run at the label ``mt``, after the
    others, its temporaries in the current loop's registers (:data:`CURRENT_STATE` excepted),
    its state ``mt_pm`` a register of its own, its specials
    (:data:`~.engine_mt.MT_RUN_SPECIALS`) and output ``mtspd`` after the others'
    (``EngineCurrentLoop(mt=True)``; docs/AREA.md §7.64, §7.82). ``realloc``: the temporaries
    share register-file words after scheduling (:meth:`Assembler._realloc`; docs/AREA.md §7.87;
    ``False``: a word per register name, for comparison).

    Returns
    -------
    Program
    """
    rot = rotator if rotator is not None else RotatorParams(width=width, angle_width=16,
                                                            tag_width=1)
    w = width
    if refs and not speed:
        raise ValueError("engine program: refs needs speed (the i_q limits and the speed run's "
                         "i_q reference)")
    from .engine_mt import MT_OUTS, MT_RUN_SPECIALS
    mt_outs = tuple(o for o in MT_OUTS if o not in OUTS) if mt else ()
    mt_specials = MT_RUN_SPECIALS if mt else ()
    if speed:
        outs = tuple(OUTS) + tuple(o for o in SPEED_OUTS if o not in OUTS)
        outs += tuple(REF_OUTS) if refs else ()
        A = Assembler(specials=(SPECIALS + SPEED_SPECIALS + (REF_SPECIALS if refs else ())
                                + mt_specials),
                      bspecials=BSPECIALS, conds=CONDS + SPEED_CONDS, outs=outs + mt_outs)
    else:
        A = Assembler(specials=SPECIALS + mt_specials, bspecials=BSPECIALS, conds=CONDS,
                      outs=tuple(OUTS) + mt_outs)
    A.guard = int_guard
    A.reg("dcg", init=1 << DCBUS_GAIN_FRAC)             # the DC-bus gain, UQ2.16: 1.0 at power-up
    # Clarke constants (sim/models/clarke.py) and SVPWM constants (svpwm.py, width w + 1).
    import math
    c_frac = w + 2
    k_beta = math.floor(2.0 ** c_frac / math.sqrt(3.0) + 0.5)
    sv_frac = (w - 1) + 8                    # F of SVPWM(width=w+1, frac=w−1)
    sv_kfrac = (w + 1) + 2
    sv_k = math.floor(2.0 ** (8 + sv_kfrac) / math.sqrt(3.0) + 0.5)

    # --- Park angle, Clarke ------------------------------------------------------------------------
    A.alu(Op.RSUB, None, "s.theta", 0, out="ang")                     # −θ
    A.alu(Op.RSUB, "r.ta", "s.off_a", "b.ia")                        # ia − off_a
    A.alu(Op.RSUB, "r.tb", "s.off_b", "b.ib")
    A.mul("s.gain_a", "r.ta")
    A.post("r.a", clarke_gain_frac, sat=SAT_W, out="pa")   # (posts fuse into the next MUL)
    A.mul("s.gain_b", "r.tb")
    A.post("r.b", clarke_gain_frac, sat=SAT_W, out="pb")
    A.alu(Op.RSUB, "r.mina", "r.a", 0)
    A.mul("r.b", 2 * k_beta)
    A.mac("r.a", k_beta)
    # --- Park ----------------------------------------------------------------------------------
    _trig(A, rot, pending=lambda: A.post("r.beta", c_frac, sat=SAT_W, out="i_beta"),
          filler=lambda: A.alu(Op.SUB, "r.c", "r.mina", "r.b", sat=SAT_W, out="pc"))
    # (Written here, between the trig's products and the rotation's, so that the scheduler puts
    # their products where the multiplier waits for the trig's results: no clock added.)
    _lead_lim(A, gain_limit_raw)
    _rotate(A, "r.a", "r.beta", "r.id", "r.iq", "i_d", "i_q", w)
    A.alu(Op.ADD, None, "s.theta", "r.lead", out="ang")               # θ + θ_lead
    # For the gain's division after the duties (which reads the register file only).
    A.alu(Op.MAX, "r.u8", "s.udc", 0, asl=True)                       # 2**8·U, U = max(U_dc, 0)
    A.alu(Op.ADD, "r.uh", "r.u8", 0, sh=9)                            # floor(U/2)
    if refs:
        # The references as the Servo forms them (hdl/servo.py): i_d = id_set; i_q =
        # clamp(iq_set, lim_lo, lim_hi) in CURRENT mode, the speed run's result in SPEED mode
        # (OL, which the wrapper raises in SPEED mode too: on the RUN path it tells the two
        # apart); both also to the status outputs the scope records (idr, iqr).
        A.alu(Op.ADD, "r.iqs", "s.iqset", 0)
        A.alu(Op.MIN, "r.iqt", "s.ihi", "r.iqs", setf=True)           # N: iq_set > hi
        A.alu(Op.MAX, "r.iqc", "s.ilo", "r.iqt", cond="N")            # clamp (the Servo's order)
        A.alu(Op.SEL, "r.iqr", "s.sliq", "r.iqc", cond="!OL", out="iqr")
        A.alu(Op.ADD, None, "s.idset", 0, out="idr")
    # --- Run or clear ------------------------------------------------------------------------------
    A.br("!RUN", "off")
    _pi_head(A, "d", "r.id", "s.idset" if refs else None)             # delay slots
    _pi_head(A, "q", "r.iq", "r.iqr" if refs else None)
    A.br("!FF", "noff")
    A.alu(Op.ADD, "r.ffd", 0, 0)                                      # delay slots: ff = 0
    A.alu(Op.ADD, "r.ffq", 0, 0)
    # Decoupling feed-forward (hdl/foc.py).
    A.mul("s.ff_psi", "b.nspd")
    A.post("r.emf", FF_FORMAT.frac)
    A.mul("s.ff_l", "b.nspd")
    A.post("r.wl", FF_FORMAT.frac)
    A.mul("r.wl", "r.iq")
    A.post("r.ffd", w - 1)                                            # subtracted below
    A.mul("r.wl", "r.id")
    A.post("r.t", w - 1)
    A.alu(Op.ADD, "r.ffq", "r.t", "r.emf")
    A.label("noff")
    if kp_frac != int_guard:
        raise ValueError("engine program: kp_format.frac must equal int_guard")
    _pis(A, kx_shift=kx_frac - int_guard)
    # The inverse Park's sine and cosine (ang = θ + θ_lead since before the branch) in the same
    # straight-line region as the PIs, so that the scheduler interleaves the two chains (the
    # path with the PIs cleared has its own copy, below).
    _trig(A, rot)
    # --- Inverse Park, DC-bus compensation -----------------------------------------------------------
    A.label("inv")
    A.alu(Op.ADD, None, "r.lt", 0, setf=True)
    A.alu(Op.SEL, None, 0, 1, cond="!N", out="lim")                   # dc_limited
    A.alu(Op.SEL, "r.rr", "s.urat", 0, cond="!N")                     # R, or 0 if limited
    _rotate(A, "r.ud", "r.uq", "r.ua", "r.ub", "u_alpha", "u_beta", w)
    A.mul("r.ua", "r.dcg")                    # (u_β's post fuses into it)
    A.post("r.ca", 16, sat=SAT_W1)
    A.mul("r.ub", "r.dcg")
    A.post("r.cb", 16, sat=SAT_W1)
    # --- SVPWM (width w + 1, frac w − 1: hdl/svpwm.py, min–max injection) --------------------------
    if int_guard != 8:
        raise ValueError("engine program: int_guard must be 8 (the SVPWM guard shift uses it)")
    A.mul("r.ca", 1 << 8)                                            # α·2**8
    A.post("r.qa", 0)
    A.mul("r.cb", sv_k)
    A.post("r.qs", sv_kfrac)                                         # round(β·k, k_frac)
    A.alu(Op.ADD, "r.ta2", "r.qa", "r.qa")
    A.alu(Op.RSUB, "r.qn", "r.qs", 0)
    A.alu(Op.MAX, "r.mx", "r.qa", "r.qs")
    A.alu(Op.MIN, "r.mn", "r.qa", "r.qs")
    A.alu(Op.MAX, "r.mx", "r.mx", "r.qn")
    A.alu(Op.MIN, "r.mn", "r.mn", "r.qn")
    A.alu(Op.ADD, "r.tb2", "r.qs", "r.qs")
    A.alu(Op.SUB, "r.sp", "r.mx", "r.mn")
    A.alu(Op.ADD, "r.smm", "r.mx", "r.mn")
    A.alu(Op.ADD, "r.tc2", "r.qn", "r.qn")
    A.alu(Op.MAX, "r.d", "r.sp", 1 << sv_frac, setf=True)            # !LE: over-modulation
    A.alu(Op.SEL, None, 0, 1, cond="!LE", out="om")
    A.alu(Op.SUB, "r.bs", "r.d", "r.smm")                            # D − max − min
    for ph in "abc":                                                  # n = D + 2q − max − min
        A.alu(Op.ADD, f"r.n{ph}", "r.bs", f"r.t{ph}2")
    # D = 2**F: (scale·n + 2**F) >> (F + 1) = round_shift (scale·n ≥ 0). The first product
    # before the branch (the over-modulation path starts a new one).
    A.mul("s.scale", "r.na")
    A.br("!LE", "om")                                                 # flags of D − 2**F
    A.alu(Op.ADD, "r.d2", "r.d", "r.d")     # delay slots (only the over-modulation path uses
    A.alu(Op.ADD, "r.t", "r.na", "r.nb")    # them): 2D, na + nb
    for ph in "abc":
        if ph != "a":
            A.mul("s.scale", f"r.n{ph}")
        A.emit(Op.ADD, a="s.P", b=0, sh=sv_frac + 1, rnd=True, out=f"d{ph}")
    # --- DC-bus gain for the next sample (after the duties: o.valid is the write of dc) ------
    # gain = min(floor(M / U), L) (DCBusCompensation's), M = R'·2**16 + floor(U/2), R' = R (0
    # when limited: the division then stays small). Not limited: gain ≤ L < 2**18, 18 quotient
    # bits from the 16-bit DIV: N = 2**6·M divided by B = 2**8·U in 18 steps. The first 16
    # give floor(N / B) = floor(M / (4U)) < 2**16 in P's low bits; in the last two the
    # quotient's top bits move into the remainder's field, whose value and B are multiples of
    # 2**6 (N's low bits are zero): the compares are unchanged (the quotient adds < 4) and
    # P = 2**22·k + floor(M / U) at the end, so the gain is P − 2**22·(P >> 22).
    A.label("gain")
    A.mul("r.rr", 1 << 22)
    A.mac("r.uh", 1 << 6)                                             # N = 2**6·M
    A.div("r.u8", count_width + 2)
    A.post("r.hi", 22, rnd=False)
    A.mac("r.hi", -(1 << 22))
    A.post("r.q", 0)                                                  # floor(M / U)
    A.alu(Op.ADD, None, "r.lt", 0, setf=True)
    A.alu(Op.SEL, "r.dcg", gain_limit_raw, "r.q", cond="N")           # N: not limited
    A.end()
    # Over-modulation: the largest phase has n = 2D (duty = scale), the smallest n = 0 (duty 0),
    # the middle one n = Σn − 2D: one division.
    A.label("om")
    A.mul("s.scale", "r.nc")                                          # scale·(Σn − 2D) + D
    A.mac(1, "r.d")                   # (in this order: 2D and na + nb from the delay slots)
    A.mac("s.scale", "r.d2", neg=True)
    A.mac("s.scale", "r.t")
    A.div("r.d2", count_width)
    A.alu(Op.ADD, "r.qm", "s.PQ", 0)
    for ph in "abc":
        A.alu(Op.SUB, None, f"r.n{ph}", "r.d2", setf=True)
        A.alu(Op.SEL, "r.t", "r.qm", "b.scale", cond="Z")
        A.alu(Op.ADD, None, f"r.n{ph}", 0, setf=True)
        if ph == "c":
            A.br("!F", "gain")                                        # the last duty in its slot
        A.alu(Op.SEL, None, "r.t", 0, cond="Z", out=f"d{ph}")
    A.nop()
    # --- PIs cleared (enable low or open loop) ---------------------------------------------------
    A.label("off")
    for ax in "dq":
        A.alu(Op.ADD, f"r.i_{ax}", 0, 0)
        A.alu(Op.ADD, None, 0, 0, out=f"sat_{ax}")
    A.alu(Op.SEL, "r.ud", "s.ol_ud", 0, cond="!OL", out="u_d")
    A.alu(Op.SEL, "r.uq", "s.ol_uq", 0, cond="!OL", out="u_q")
    _trig(A, rot)
    A.br("!F", "inv")
    A.alu(Op.ADD, "r.ep_d", 0, 0)                 # delay slots: nothing at inv reads these
    A.alu(Op.ADD, "r.ep_q", 0, 0)
    pool = [r for r in A._regs if r not in CURRENT_STATE]
    if speed:
        # (mt: the speed run reads M/T's speed from the register the M/T run writes it to,
        # ``mt_spd``, as it writes the output ``mtspd``: no special line for ``spd``)
        A.label("speed")
        _speed_loop(_Renamed(A, pool, subst={"s.spd": "r.mt_spd"} if mt else None))
        A.end()
    if mt:
        from .engine_mt import MT_STATE, mt_arith
        A.label("mt")
        mt_arith(_Renamed(A, pool, prefix="", state=MT_STATE + ("mt_spd",)), prefix="",
                 k="words", dst="r.mt_spd" if speed else None)
        A.end()
    return A.assemble(fuse=fuse, schedule=schedule, fold=fold, realloc=realloc)


def _paths(program, start=0):
    """Every path through ``program`` from ``start`` (it has no loops; each branch taken or
    not, delay slots counted): the executed addresses, in order, one list per path (a word
    once, however many clocks it takes: :func:`_clocks`). The fetch as the gateware's
    (:class:`~.engine.Fetch`: a branch's delay slots are the clocks after it, which a word
    with repeats or bubbles fills alone)."""
    instrs = program.instrs
    paths = []

    def walk(fetch, issue, trail):
        while True:
            pc, rep, _ = issue
            ins = instrs[pc]
            taken = None
            if not rep:
                trail.append(pc)
                if ins.op == Op.END:
                    paths.append(trail)
                    return
                if ins.op == Op.BR and not (ins.cond == 0 and not ins.inv):
                    taken = fetch.copy()
            issue = fetch.issue()
            if taken is not None:
                taken.step(ins.tgt)
                walk(taken, issue, list(trail))
                if ins.cond == 0 and ins.inv:       # always taken
                    return
            fetch.step()

    fetch = Fetch(instrs, start)
    issue = fetch.issue()
    fetch.step()
    walk(fetch, issue, [])
    return paths


def _clocks(ins):
    """Clocks (of the execute stage) of one instruction word: a repeated DIV ``sh + 1``, a word
    with bubbles (folded NOPs) ``nb + 1``, else 1 (:attr:`~.engine.Instr.clocks`)."""
    return ins.clocks


def path_lengths(program):
    """Executed instructions of every path through ``program`` (it has no loops), to its END:
    a sorted list of distinct counts (each branch taken or not; delay slots counted; a
    repeated DIV counted as often as it is issued)."""
    instrs = program.instrs
    return sorted({sum(_clocks(instrs[pc]) for pc in p) for p in _paths(program)})


def duty_lengths(program):
    """Executed instructions of every path through ``program`` up to and including its write of
    the last duty (output ``dc``; ``o.valid`` follows it): a sorted list of distinct counts."""
    dc = program.outs.index("dc")
    instrs = program.instrs
    counts = set()
    for path in _paths(program):
        writes = [k for k, pc in enumerate(path) if instrs[pc].out == dc]
        if not writes:
            raise ValueError("engine program: a path without a write of the duty dc")
        # (The writer's own issue, not its bubbles: a duty is never written by a DIV.)
        counts.add(sum(_clocks(instrs[pc]) for pc in path[:writes[-1]]) + 1)
    return sorted(counts)


#: Clocks from the accepted sample (``start``) to the first instruction in X1.
START_CLOCKS = 3
#: Clocks from the accepted sample to ``o.valid`` beyond the executed instructions: the start,
#: then END's X1 clock is the last instruction's; the write back of the instruction before
#: END (X4) lands ``WRITE_DELAY − 1`` clocks after it, ``o.valid`` is registered.
PIPELINE_CLOCKS = START_CLOCKS + WRITE_DELAY - 1
#: Clocks from the accepted sample to ``o.valid`` beyond the executed instructions up to and
#: including the write of the last duty (:func:`duty_lengths`): the start, that instruction's
#: X1 clock, its write back (X4) ``WRITE_DELAY`` later, ``o.valid`` registered.
DUTY_CLOCKS = START_CLOCKS + WRITE_DELAY


def phase_latency(program):
    """Clocks from the accepted sample to ``phase.valid`` of :class:`EngineCurrentLoop` running
    ``program``: the write of phase c (output ``pc``) must be on the straight-line start of
    the program (before its first branch), executed as instruction ``k`` in X1 ``START_CLOCKS
    + k`` clocks after the sample, written back ``WRITE_DELAY`` later, ``phase.valid``
    registered."""
    outs = ("",) + tuple(OUTS)
    k = 0
    for ins in program.instrs:
        if ins.op == Op.BR or ins.op == Op.END:
            break
        if ins.out and outs[ins.out] == "pc":
            return START_CLOCKS + k + WRITE_DELAY + 1
        k += _clocks(ins)
    raise ValueError("engine program: no write of phase c before the first branch")


def ge_ripple(a, b):
    """``a >= b`` for unsigned values of one width, as a ripple of per-bit terms from the low
    bit up (``a < b`` on bits ``0 … i``: ``a_i < b_i``, or ``a_i = b_i`` and ``a < b`` below),
    with no adder: on the iCE40 a compare's carry chain takes a cell per bit, and an inverter
    cell per bit of the operand on its inverted side when that is a flip-flop (whose polarity
    its reset value fixes); the ripple takes one LUT per bit (the speed run's decimation, a
    slow path: AREA.md §7.63)."""
    if len(a) != len(b):
        raise ValueError(f"ge_ripple operands must have one width, not {len(a)} and {len(b)}")
    lt = Const(0)
    for i in range(len(a)):
        lt = (~a[i] & b[i]) | (~(a[i] ^ b[i]) & lt)
    return ~lt


def sample_read(program):
    """Clocks from the start of ``program`` (the accepted sample's, :class:`EngineCurrentLoop`)
    to the clock in which it reads the last of the ADC codes ``ia``, ``ib`` (special operands
    sampled in R, ``START_CLOCKS − 1`` clocks after the start for the first instruction): both
    are read on the straight-line start of the program (before its first branch) and
    nowhere else (checked)."""
    names = [program.specials.index(n) for n in ("ia", "ib")]
    bnames = [program.bspecials.index(n) for n in ("ia", "ib") if n in program.bspecials]
    reads = {}
    k, straight = 0, True
    for pc, ins in enumerate(program.instrs):
        if (ins.asp and ins.a in names) or (ins.bsp and ins.b in bnames):
            if not straight:
                raise ValueError("engine program: ia or ib read after the first branch")
            reads[pc] = k
        if ins.op in (Op.BR, Op.END):
            straight = False
        k += _clocks(ins)
    if not reads:
        raise ValueError("engine program: ia and ib are not read")
    return START_CLOCKS - 1 + max(reads.values())


def status_quiet(program, names=STATUS):
    """Clocks from ``done`` of :class:`EngineCurrentLoop` running ``program`` (that clock
    included) in which no status output (:data:`STATUS`) is written: after its last duty
    (``o.valid``, before ``done``) the program writes no status output, and the next program
    starts at the earliest in the ``done`` clock (a sample accepted then), writing its first
    status output ``START_CLOCKS + k + WRITE_DELAY`` clocks after that (``k`` instruction
    clocks before it, on the straight-line start of the program)."""
    outs = program.outs
    status = {outs.index({**STATUS_OUTS, **REF_STATUS_OUTS}[name]) for name in names}
    dc = outs.index("dc")
    instrs = program.instrs
    for path in _paths(program):
        last = max(k for k, pc in enumerate(path) if instrs[pc].out == dc)
        if any(instrs[pc].out in status for pc in path[last + 1:]):
            raise ValueError("engine program: a status output written after the last duty")
    k = 0
    for ins in instrs:
        if ins.op in (Op.BR, Op.END):
            break
        if ins.out in status:
            return START_CLOCKS + k + WRITE_DELAY
        k += _clocks(ins)
    raise ValueError("engine program: no status output written before the first branch")


def speed_run_timing(program):
    """The speed run's timing (``current_loop_program(speed=True)`` from its ``speed`` label,
    or :func:`speed_loop_program`), per profile path (``"up"``, ``"dn"``: the profile moves
    by the slew; ``"none"``: it steps to ``speed_ref``): a dict of path → dict with
    ``ref_latency`` (clocks from the run's start to the new ``ref_int``, ``ref_int``'s write +
    :data:`DUTY_CLOCKS`, the output registered as ``o.valid`` is), ``latency`` (to the i_q
    reference and ``o.valid``, the write of ``iq`` likewise), ``length`` (executed
    instructions: the engine takes the next start ``START_CLOCKS + length`` clocks after
    this one's) and ``speed_read`` (clocks from the start to the clock in which the engine
    samples the special ``spd``: the R stage of the one instruction that reads it,
    ``START_CLOCKS − 1`` + the clocks executed before it). ``sat`` is written before ``iq``
    on every path, ``spd`` read once (checked)."""
    start = program.labels.get("speed", 0)
    prefix = "spd_" if "speed" in program.labels else ""
    up, dn = program.labels[prefix + "up"], program.labels[prefix + "dn"]
    outs = program.outs
    spd = program.specials.index("spd")
    # (current_loop_program(mt=True): the run reads the M/T run's register mt_spd instead)
    spd_reg = program.regs.get("mt_spd")
    timing = {}
    for path in _paths(program, start):
        kind = "up" if up in path else "dn" if dn in path else "none"
        k, at, reads = 0, {}, []
        for pc in path:
            ins = program.instrs[pc]
            if ins.out and outs[ins.out] in ("ref_int", "iq", "sat"):
                at[outs[ins.out]] = k
            if (ins.asp and ins.a == spd) or (not ins.asp and ins.a == spd_reg):
                reads.append(k)
            k += _clocks(ins)
        if not at.get("sat", k) < at.get("iq", -1) or "ref_int" not in at:
            raise ValueError("speed program: sat must be written before iq, and ref_int")
        if len(reads) != 1:
            raise ValueError(f"speed program: the special spd must be read once per run, not "
                             f"{len(reads)} times")
        t = {"ref_latency": at["ref_int"] + 1 + DUTY_CLOCKS,
             "latency": at["iq"] + 1 + DUTY_CLOCKS, "length": k,
             "speed_read": START_CLOCKS - 1 + reads[0]}
        if timing.setdefault(kind, t) != t:
            raise ValueError(f"speed program: two {kind} paths of different timing")
    return timing


class EngineCurrentLoop(wiring.Component):
    """The current loop of :class:`~.foc.CurrentLoop` as a program of the loop engine.

    Same parameters, the same signature (ports, streams, status outputs) but for ``lead_k`` in
    place of ``theta_lead``, and bit-identical results
    (:class:`~foc_servo.sim.models.foc.CurrentLoopModel` with ``theta_lead`` =
    :func:`~foc_servo.sim.models.engine.lead_angle` of the sample's ``speed`` and ``lead_k``);
    only the timing differs: the whole computation runs on one multiplier and one ALU in
    sequence (:attr:`latency`). The program is written for the default formats; other values
    raise :exc:`ValueError`.

    Status outputs update when the program writes them; ``o.valid`` follows the program's
    write of the last duty, ``done`` marks the transfer as in :class:`~.foc.CurrentLoop`.
    ``dc_limited`` (the DC-bus gain limit hit by this sample's ``U_dc``, as the DC-bus block's
    flag) is written before the duties. After the duties the program computes the next
    sample's DC-bus gain (from the register file only) before it ends: a sample accepted in
    that time (back to back, less than :attr:`interval` clocks after the previous one) is
    latched (but its ADC codes ``ia``, ``ib``: ``i`` below) and its program starts when the
    running one ends (its latency then grows by the rest of it). ``phase.valid`` strobes the clock after the program wrote phase c. The DC-bus
    gain lives in the engine's register file (block RAM), which a reset does not clear: it is
    1.0 at power-up and after a reset the last gain computed until the next sample's.

    Members
    -------
    lead_k : In(unsigned(16))
        The ``theta_lead`` register: the inverse Park's advance at full-scale speed, UQ0.16
        turns; read while the program runs (like the gains), θ_lead = ``round_shift(n·k, 15)``
        mod 2**16 from the speed ``n`` latched with the sample (:class:`~.top.LeadAngle`).
        With ``config="ram"`` the configuration RAM's word ``klead`` instead (as ``u_rated``'s:
        word ``urat``).
    i : In(stream.Signature(...))
        The ADC sample (:class:`~.foc.CurrentLoop`'s). ``udc`` is latched at the accepting
        clock (the ``udc`` output), ``ia`` and ``ib`` are read by the program from the port
        itself (no latch), :attr:`sample_read` clocks after its start: they must hold from the
        accepting clock until then, :attr:`sample_hold` clocks at most (the top's ADC shift
        registers hold its codes until the next conversion's first bit, a PWM period later).
    speed : In(signed(32))
        The speed (M/T's), latched with each sample for the feed-forward and θ_lead; with
        ``speed=True`` also the speed run's feedback, which the program reads from the port
        itself, :attr:`speed_read` clocks after the run's start: ``speed`` must hold from the
        ``speed_valid`` strobe that requests a run until then (the top's M/T output register
        changes only at its strobes, a PWM period apart, longer than :attr:`interval` +
        :attr:`speed_read`: a run waits at most for one current-loop sample's program).

    Parameters
    ----------
    config : str
        Where the 16 configuration values (:data:`CONFIG`: Clarke gains and offsets, the PIs'
        gains and limits, the decoupling ``ff_l``, ``ff_psi``, then ``lead_k`` and
        ``u_rated``) come from: ``"ports"`` (default) the input ports of
        :class:`~.foc.CurrentLoop` (``gain_a``, ``offset_a``, ``kp_d``, ``lim_lo_d``, …) and
        ``lead_k``, ``u_rated``; ``"ram"`` the engine's configuration RAM, written through
        the ``config`` port (:class:`~.bus.WordWriteSignature`, word ``j`` = ``CONFIG[j]`` in
        the register file's read format; e.g. the register file's ``export`` port), which has
        none of those input ports. Both give the same results in the same clocks when each
        RAM word is written in the clock before the port value would change.
    config_init : list of int
        ``config="ram"``: the RAM's initial words (default all 0; the top passes the
        registers' reset values, :attr:`~.regs.RegisterFile.export_init`).
    refs : str
        ``"ports"`` (default): the references are input ports (``id_ref``, ``iq_ref``,
        ``ol_ud``, ``ol_uq`` latched with the sample; with ``speed=True`` the speed run's
        ``iq_lim_lo``, ``iq_lim_hi``). ``"ram"`` (needs ``config="ram"`` and ``speed=True``):
        none of those ports; the configuration RAM's words :data:`REF_CONFIG_WORDS` (after
        :data:`CONFIG`, before the speed loop's words) hold the open-loop voltages, the
        current set-points and the i_q limits, and the program forms the references as the
        Servo does (``current_loop_program(refs=True)``: ``id_ref`` = the set-point; ``iq_ref`` =
        the set-point clamped to the limits, or in SPEED mode (``speed_clear`` low at the
        sample) the speed run's result ``speed_o``; the voltages under ``ol_enable``), reading
        the words while it runs: the same values as the latches whenever no word is written
        between the accepting clock and the read (the register file's commit copy, which the
        top keeps clear of the loop's run, hdl/top.py "References in the engine's RAM"); a
        SPEED sample that waits behind a speed run takes that run's result. With
        ``status="ram"`` the references it used are two more words of ``status_probe``'s RAM
        (:data:`REF_STATUS`, for the scope).
    status : str
        Where the status outputs (:data:`STATUS`) are held: ``"ports"`` (default) output
        registers, the ``Out`` members ``i_alpha`` … ``u_beta``; ``"ram"`` a status RAM
        written in the same clocks (word ``j`` = ``STATUS[j]``, 0 at power-up; a domain reset
        does not clear it, where it clears the registers), read through two synchronous
        read ports in place of those members (``status_rd``, ``status_probe``, below).
    mt : bool
        M/T speed's multiply and divide as the engine's run ``mt`` (needs ``config="ram"``;
        ``current_loop_program(mt=True)``, :func:`~.engine_mt.mt_arith` with ``k="words"``;
        docs/AREA.md §7.64, §7.82): the window's operands on ``mt_run`` (``MTSpeed(arith=
        "engine")``'s ``run``: ``valid`` requests the run, the payload the specials ``mtm``,
        ``mtd``, ``mts``, ``mtb``, read while it runs), ``k`` as the configuration RAM's last two
        words (:data:`~.engine_mt.MT_CONFIG_WORDS`: the register file's export words of
        ``mt_k``), the result on ``mt_res`` (the output register ``mtspd`` and its write
        strobe). Start arbitration: a current-loop sample first, then the M/T run, then (with
        ``speed``) a speed run; a request that finds the engine running waits for its END (an
        M/T request behind a current-loop program, at most :attr:`interval` clocks; a sample
        behind an M/T run, its ``length``, which :attr:`sample_hold` includes). With ``speed``
        the speed run reads M/T's speed from the register the M/T run writes it to
        (``mt_spd``), not from the ``speed`` port: the same value, since a speed run starts
        at M/T's strobe after the M/T run that wrote it.

    Status RAM (``status="ram"``): two block RAMs of ``len(STATUS)`` words of ``width``
    bits, one per read port, written together at the engine's output writes (the registers'
    load clocks). Each read port takes ``addr`` (a word of :data:`STATUS`) and shows the word
    one clock later on ``data``:

    * ``status_rd`` reads transparently: ``data`` in clock ``t + 1`` is the value the
      register ``STATUS[addr]`` holds in ``t + 1`` (``addr`` given in ``t``); for the register
      file (:attr:`~.regs.RegisterFile` ``status_ram``), whose read multiplexer samples its
      inputs in ``t + 1``. (On the iCE40 synthesis adds the bypass of a write in ``t``.)
    * ``status_probe`` reads the old word: ``data`` in ``c + 1`` is the value the register
      held in ``c`` (``addr`` given in ``c``), as a flip-flop sampling the register in ``c``
      would hold it in ``c + 1``; for the scope (:class:`~.scope.Scope` ``ram_sources``), which
      samples a probe in ``c`` and writes it in ``c + 1``. Valid only in the
      :attr:`status_quiet` clocks from ``done`` on (no status output is written then, so the
      RAM's read-during-write behaviour never matters; it is left undefined): the scope, strobed
      by ``done``, samples its channels in ``done`` … ``done + channels − 1``.

    Attributes
    ----------
    latency : int
        Clocks from the accepted sample to ``o.valid``, worst case (over-modulation with
        feed-forward).
    latencies : list of int
        Every possible latency (per program path), :func:`duty_lengths` + :data:`DUTY_CLOCKS`.
    interval : int
        Clocks from an accepted sample until the program has ended (the DC-bus gain computed)
        on its longest path: a sample accepted later starts at once.
    gain_limit_raw : int
        ``gain_limit`` in UQ2.16 (``L``).
    phase_latency : int
        Clocks from the accepted sample to the ``phase`` transfer (the program's write of
        phase c, :func:`phase_latency`).
    sample_read : int
        Clocks from a sample's program start to the clock in which it reads the last of
        ``i.payload.ia``, ``ib`` (:func:`sample_read`; the start is the accepting clock when
        the engine is idle).
    sample_hold : int
        Clocks from the accepting clock to that read, worst case (the engine busy with the
        previous sample's program or, ``speed=True``, a speed run): ``ia``, ``ib`` must hold
        that long (class docstring, ``i``).
    status_quiet : int
        :func:`status_quiet` of the program: from ``done`` (included), the clocks in which no
        status output is written.
    status_mode : str
        The ``status`` parameter.
    speed_read : int or None
        ``speed=True``: clocks from a speed run's start to the clock in which the program
        samples ``speed`` (worst case over the profile paths; :func:`speed_run_timing`).
    mt_mode : bool
        The ``mt`` parameter.
    mt_timing, mt_latency : list, int or None
        ``mt=True``: :func:`~.engine_mt.mt_run_timing` of the program and its worst latency.
    program : Program
    """

    def __init__(self, *, width=16, adc_width=16, angle_width=16, count_width=16,
                 rotator="table", iterations_per_stage=3, clarke_gain_format=Q(18, 15),
                 kp_format=UQ(16, 8), kx_format=UQ(16, 16), int_guard=8, gain_limit=2.0,
                 config="ports", config_init=None, status="ports", speed=False, refs="ports",
                 mt=False):
        defaults = (("width", width, 16), ("adc_width", adc_width, 16),
                    ("angle_width", angle_width, 16), ("count_width", count_width, 16),
                    ("clarke_gain_format", clarke_gain_format, Q(18, 15)),
                    ("kp_format", kp_format, UQ(16, 8)), ("kx_format", kx_format, UQ(16, 16)),
                    ("int_guard", int_guard, 8))
        for name, value, allowed in defaults:
            if type(value) is not type(allowed) or value != allowed:
                raise ValueError(f"EngineCurrentLoop {name} must be {allowed!r} (the program "
                                 f"is written for it), not {value!r}")
        if rotator not in ("table", "cordic"):
            raise ValueError(f"EngineCurrentLoop rotator must be one of table, cordic (both mean "
                             f"the engine's sine table), not {rotator!r}")
        if (not isinstance(gain_limit, (int, float)) or isinstance(gain_limit, bool)
                or not math.isfinite(gain_limit)):
            raise TypeError(f"EngineCurrentLoop gain_limit must be a number, not {gain_limit!r}")
        limit_raw = round(gain_limit * (1 << DCBUS_GAIN_FRAC))
        if not (1 << DCBUS_GAIN_FRAC) <= limit_raw < (4 << DCBUS_GAIN_FRAC):
            raise ValueError(f"EngineCurrentLoop gain_limit must be at least 1.0 and below 4.0, "
                             f"not {gain_limit!r}")
        self._gain_limit_raw = limit_raw
        check_choice("EngineCurrentLoop", "config", config, CONFIGS)
        check_bool("EngineCurrentLoop", "speed", speed)
        if speed and config != "ram":
            raise ValueError(f"EngineCurrentLoop speed=True needs config='ram' (the speed "
                             f"loop's gains and slew are slices of its words), not "
                             f"config={config!r}")
        self._speed = speed
        check_choice("EngineCurrentLoop", "refs", refs, REFS)
        if refs == "ram" and (config, speed) != ("ram", True):
            raise ValueError(f"EngineCurrentLoop refs='ram' needs config='ram' and speed=True "
                             f"(the references are words of its configuration RAM, the SPEED "
                             f"mode's i_q the speed run's), not config={config!r}, "
                             f"speed={speed!r}")
        self._refs = refs
        from .engine_mt import MT_CONFIG_WORDS, mt_run_timing
        check_bool("EngineCurrentLoop", "mt", mt)
        if mt and config != "ram":
            raise ValueError(f"EngineCurrentLoop mt=True needs config='ram' (M/T's k is two "
                             f"words of its configuration RAM), not config={config!r}")
        self._mt = mt
        n_config = (len(CONFIG) + (len(REF_CONFIG_WORDS) if refs == "ram" else 0)
                    + (len(SPEED_CONFIG_WORDS) if speed else 0)
                    + (len(MT_CONFIG_WORDS) if mt else 0))
        if config_init is not None and config != "ram":
            raise ValueError(f"EngineCurrentLoop config_init applies only to config='ram', "
                             f"not config={config!r}")
        if config_init is not None and (not isinstance(config_init, (list, tuple))
                                        or len(config_init) != n_config
                                        or not all(isinstance(v, int) for v in config_init)):
            raise ValueError(f"EngineCurrentLoop config_init must be a list of {n_config} "
                             f"integers, not {config_init!r}")
        check_choice("EngineCurrentLoop", "status", status, STATUSES)
        self._status = status
        self._status_mems = {}                  # status="ram": made by elaborate()
        self._engine = None                     # made by elaborate()
        self._config = config
        self._config_init = list(config_init) if config_init is not None else [0] * n_config
        self._rot = RotatorParams(width=width, angle_width=angle_width, tag_width=1)
        self._program = current_loop_program(rotator=self._rot, gain_limit_raw=limit_raw,
                                             speed=speed, refs=refs == "ram", mt=mt)
        #: The status RAM's words (``status="ram"``).
        self._status_words = STATUS + (REF_STATUS if refs == "ram" else ())
        self._speed_timing = speed_run_timing(self._program) if speed else None
        self._mt_timing = mt_run_timing(self._program) if mt else None
        self._latencies = [n + DUTY_CLOCKS for n in duty_lengths(self._program)]
        self._interval = max(path_lengths(self._program)) + START_CLOCKS
        self._phase_latency = phase_latency(self._program)
        self._sample_read = sample_read(self._program)
        # A sample accepted while the engine runs starts when that program ends: a current-loop
        # program (accepted back to back, at the earliest at its done, ``min(latencies)``
        # after its start) or a speed run (``START_CLOCKS + length`` after its start).
        wait = self._interval - min(self._latencies)
        if speed:
            wait = max([wait] + [START_CLOCKS + t["length"] for t in self._speed_timing.values()])
        if mt:      # ... or an M/T run (``length`` counts its START_CLOCKS)
            wait = max([wait] + [length for _, length in self._mt_timing])
        self._sample_hold = wait + self._sample_read
        self._status_quiet = status_quiet(self._program,
                                          self._status_words if status == "ram" else STATUS)
        w, aw, cw = width, angle_width, count_width
        sw = signed(w)
        ports = {
            "ff_l": In(FF_FORMAT.shape), "ff_psi": In(FF_FORMAT.shape),
            "gain_a": In(clarke_gain_format.shape), "gain_b": In(clarke_gain_format.shape),
            "offset_a": In(signed(adc_width + 1)), "offset_b": In(signed(adc_width + 1)),
            "kp_d": In(kp_format.shape), "kx_d": In(kx_format.shape),
            "lim_lo_d": In(sw), "lim_hi_d": In(sw),
            "kp_q": In(kp_format.shape), "kx_q": In(kx_format.shape),
            "lim_lo_q": In(sw), "lim_hi_q": In(sw),
        }
        lead_k, u_rated = In(unsigned(16)), In(unsigned(adc_width))
        #: The configuration specials' shapes (the ports' shapes in both modes).
        shapes = {**ports, "lead_k": lead_k, "u_rated": u_rated}
        self._config_shapes = {name: shapes[CONFIG_PORTS[name]].shape for name in CONFIG}
        # (The members in the order they had before lead_k and u_rated were configuration.)
        first, last = {"lead_k": lead_k}, {"u_rated": u_rated}
        if config == "ram":
            ports = {"config": In(WordWriteSignature(n_config))}
            first, last = {}, {}
        speed_ports = {}
        if speed:
            sp = SPEED_PARAMS
            speed_ports = {
                "speed_valid": In(1), "speed_ref": In(signed(sp["speed_width"])),
                **({} if refs == "ram" else {"iq_lim_lo": In(sw), "iq_lim_hi": In(sw)}),
                "speed_rate_div": In(unsigned(8)),
                "speed_ref_delay": In(unsigned(sp["delay_width"])), "speed_int_hold": In(1),
                "speed_clear": In(1),
                "speed_o": Out(stream.Signature(sw, always_ready=True)),
                "speed_sat": Out(1), "speed_ref_int": Out(signed(sp["speed_width"])),
            }
        if mt:
            from .mt_speed import RUN_LAYOUT
            from .engine_mt import MT_ENGINE_PARAMS
            speed_ports["mt_run"] = In(stream.Signature(
                RUN_LAYOUT(MT_ENGINE_PARAMS["tc_width"], MT_ENGINE_PARAMS["m_width"]),
                always_ready=True))
            speed_ports["mt_res"] = Out(stream.Signature(
                signed(MT_ENGINE_PARAMS["out_width"]), always_ready=True))
        if status == "ram":
            rd = ReadPort.Signature(addr_width=(len(STATUS) - 1).bit_length(), shape=sw)
            probe = ReadPort.Signature(addr_width=(len(self._status_words) - 1).bit_length(),
                                       shape=sw)
            status_ports = {"status_rd": Out(rd), "status_probe": Out(probe)}
        else:
            status_ports = {name: Out(sw) for name in STATUS}
        super().__init__({
            "i": In(stream.Signature(data.StructLayout(
                {name: signed(adc_width) for name in ADC_CHANNELS}), always_ready=True)),
            "theta": In(unsigned(aw)), **first,
            **({} if refs == "ram" else {"id_ref": In(sw), "iq_ref": In(sw)}),
            "enable": In(1), "ol_enable": In(1),
            **({} if refs == "ram" else {"ol_ud": In(sw), "ol_uq": In(sw)}),
            "ff_enable": In(1),
            "speed": In(signed(SPEED_WIDTH)),
            **ports,
            **last, "scale": In(unsigned(cw)),
            "o": Out(stream.Signature(data.StructLayout({p: unsigned(cw) for p in "abc"}))),
            "overmod": Out(1),
            "phase": Out(stream.Signature(data.StructLayout({p: sw for p in "abc"}),
                                          always_ready=True)),
            "udc": Out(stream.Signature(signed(adc_width), always_ready=True)),
            **status_ports,
            "sat_d": Out(1), "sat_q": Out(1), "dc_limited": Out(1), "busy": Out(1),
            "overrun": Out(1), "overruns": Out(16), "count": Out(32), "done": Out(1),
            **speed_ports,
        })

    program = property(lambda self: self._program)
    config_mode = property(lambda self: self._config)
    width = property(lambda self: ENGINE_WIDTH)
    adc_width = property(lambda self: 16)
    angle_width = property(lambda self: 16)
    count_width = property(lambda self: 16)
    latency = property(lambda self: max(self._latencies))
    latencies = property(lambda self: list(self._latencies))
    interval = property(lambda self: self._interval)
    gain_limit_raw = property(lambda self: self._gain_limit_raw)
    phase_latency = property(lambda self: self._phase_latency)
    sample_read = property(lambda self: self._sample_read)
    sample_hold = property(lambda self: self._sample_hold)
    status_quiet = property(lambda self: self._status_quiet)
    status_mode = property(lambda self: self._status)
    speed_mode = property(lambda self: self._speed)
    mt_mode = property(lambda self: self._mt)
    #: ``mt=True``: :func:`~.engine_mt.mt_run_timing` of the program (``(latency, length)``
    #: per path: clocks from the M/T run's start to ``mt_res.valid``'s result in place, and to
    #: the engine's next start); else None.
    mt_timing = property(lambda self: None if self._mt_timing is None
                         else list(self._mt_timing))
    #: ``mt=True``: clocks from an M/T run's start to its result in place (``mt_res.valid`` is
    #: high in the clock before: the write), worst case; else None.
    mt_latency = property(lambda self: None if self._mt_timing is None
                          else max(lat for lat, _ in self._mt_timing))
    refs_mode = property(lambda self: self._refs)
    #: The status RAM's words (``status="ram"``: :data:`STATUS`, with ``refs="ram"`` then
    #: :data:`REF_STATUS`).
    status_words = property(lambda self: self._status_words)
    #: ``status="ram"``, ``refs="ram"``: the address of ``status_probe``'s word that is never
    #: written (it reads 0: the top's mask of the references, hdl/top.py); else None.
    status_zero = property(lambda self: len(self._status_words)
                           if self._refs == "ram" and self._status == "ram" else None)
    #: ``speed=True``: :func:`speed_run_timing` of the program (per profile path); else None.
    speed_timing = property(lambda self: None if self._speed_timing is None
                            else {k: dict(v) for k, v in self._speed_timing.items()})
    #: ``speed=True``: clocks from a speed run's request to its i_q reference when the engine
    #: is idle, worst case (a current-loop run in flight delays it; class docstring).
    speed_latency = property(lambda self: None if self._speed_timing is None
                             else max(t["latency"] for t in self._speed_timing.values()))
    speed_read = property(lambda self: None if self._speed_timing is None
                          else max(t["speed_read"] for t in self._speed_timing.values()))
    #: The :class:`~.engine.Engine` of the last elaboration, for a testbench (its trace
    #: port); ``None`` before it.
    engine = property(lambda self: self._engine)
    #: ``status="ram"``: the status RAM of the last elaboration (word ``j``: ``STATUS[j]``),
    #: for a testbench; ``None`` before it and with ``"ports"``.
    status_memory = property(lambda self: self._status_mems.get("status_rd"))
    #: ``status="ram"``: the scope's status RAM (``status_probe``'s; word ``j``:
    #: :attr:`status_words` ``[j]``), for a testbench.
    probe_memory = property(lambda self: self._status_mems.get("status_probe"))

    def elaborate(self, platform):
        m = Module()
        w = ENGINE_WIDTH
        sw = signed(w)
        shapes = {
            "ia": signed(16), "ib": signed(16), "theta": unsigned(16), "klead": unsigned(16),
            "id_ref": sw, "iq_ref": sw, "ol_ud": sw, "ol_uq": sw, "nspd": sw,
            **self._config_shapes,
            "scale": self.scale.shape(), "udc": signed(16),
        }
        shapes = {name: shapes[name] for name in SPECIALS}
        ram = self._config == "ram"
        spd = self._speed
        outs = dict(OUTS)
        strobe_outs = (tuple(STATUS_OUTS[n] for n in STATUS if STATUS_OUTS[n] != "pa")
                       if self._status == "ram" else ())
        refs = REF_CONFIG_WORDS if self._refs == "ram" else ()
        config = CONFIG
        if spd:
            shapes.update(SPEED_SHAPES)
            outs.update({k: v for k, v in SPEED_OUTS.items() if k not in OUTS})
            strobe_outs += ("ref_int", "iq")
            config = CONFIG + refs + SPEED_CONFIG_WORDS
        if refs:
            shapes.update({name: sw for name in REF_SPECIALS})
            outs.update(REF_OUTS)
            strobe_outs += tuple(REF_OUTS)
        if self._mt:
            from .engine_mt import MT_CONFIG_WORDS, MT_OUTS, MT_RUN_SHAPES
            shapes.update(MT_RUN_SHAPES)
            outs.update({k: v for k, v in MT_OUTS.items() if k not in OUTS})
            config = config + MT_CONFIG_WORDS
        m.submodules.engine = eng = Engine(program=self._program, special_shapes=shapes,
                                           out_widths=outs, width=w, guard=8,
                                           div_bits=16, rotator=self._rot,
                                           config=config if ram else (),
                                           config_init=self._config_init if ram else None,
                                           config_slices=SPEED_SLICES if spd else None,
                                           strobe_outs=strobe_outs)
        self._engine = eng

        # --- Trigger, busy, overrun, loop counter (as CurrentLoop) ------------------------------
        # The duties are valid from the program's write of the last one (``dc``); the program
        # then computes the next sample's DC-bus gain (from the register file only) before its
        # END. A sample accepted before that END (back to back, ``interval``) is latched and
        # starts the program when it ends (``pending``).
        accept, done = sample_handshake(m, self)
        with m.If(done):
            m.d.sync += self.overmod.eq(eng.o_om)
        with m.If(eng.o_dc_we):
            m.d.sync += self.o.valid.eq(1)
        with m.Elif(done):
            m.d.sync += self.o.valid.eq(0)
        pending = Signal()
        with m.If(accept & eng.running):
            m.d.sync += pending.eq(1)
        with m.Elif(~eng.running):
            m.d.sync += pending.eq(0)

        # --- Per-sample inputs, latched with the sample ------------------------------------------
        # (``ia``, ``ib``: read from the port, which holds until the program has read them:
        # ``sample_hold``, the class docstring.)
        lat = {name: Signal(shapes[name], name=f"l_{name}")
               for name in ("theta", "id_ref", "iq_ref", "ol_ud", "ol_uq", "nspd")
               if name not in refs and not (refs and name in ("id_ref", "iq_ref"))}
        run, ol, ff = Signal(), Signal(), Signal()
        nspd_round = round_shift_plain(self.speed, SPEED_WIDTH - w)
        with m.If(accept):
            m.d.sync += [
                lat["theta"].eq(self.theta),
                *(lat[name].eq(getattr(self, name)) for name in ("id_ref", "iq_ref", "ol_ud",
                                                                 "ol_uq") if name in lat),
                lat["nspd"].eq(saturate_bits(nspd_round, sw)),
                run.eq(self.enable & ~self.ol_enable),
                # (refs="ram": OL in SPEED mode too, where the program, on its RUN path, takes
                # the speed run's i_q reference, not the clamped set-point)
                ol.eq(self.ol_enable | ~self.speed_clear if refs else self.ol_enable),
                ff.eq(self.ff_enable & self.enable & ~self.ol_enable),
                self.udc.payload.eq(self.i.payload.udc),
            ]
        m.d.sync += self.udc.valid.eq(accept)
        # The configuration: ports into the engine's specials, or the engine's RAM's writes.
        if ram:
            wiring.connect(m, wiring.flipped(self.config), eng.cfg)
            config = {}
        else:
            config = {name: getattr(self, CONFIG_PORTS[name]) for name in CONFIG}
        config.update({"scale": self.scale, "udc": self.udc.payload,
                       "ia": self.i.payload.ia, "ib": self.i.payload.ib})
        for name, sig in list(lat.items()) + list(config.items()):
            m.d.comb += getattr(eng, f"s_{name}").eq(sig)
        m.d.comb += [eng.c_RUN.eq(run), eng.c_OL.eq(ol), eng.c_FF.eq(ff),
                     self.dc_limited.eq(eng.o_lim)]
        cur_go = accept | pending
        mt_go = self._mt_run(m, eng, cur_go) if self._mt else None
        if spd:
            self._speed_run(m, eng, cur_go, mt_go)
        elif mt_go is not None:
            m.d.comb += [eng.start.eq(cur_go | mt_go),
                         eng.start_pc.eq(Mux(mt_go, self._program.labels["mt"], 0))]
        else:
            m.d.comb += eng.start.eq(cur_go)

        # --- Outputs --------------------------------------------------------------------------------
        m.d.comb += [
            self.o.payload.a.eq(eng.o_da), self.o.payload.b.eq(eng.o_db),
            self.o.payload.c.eq(eng.o_dc),
            self.phase.payload.a.eq(eng.o_pa), self.phase.payload.b.eq(eng.o_pb),
            self.phase.payload.c.eq(eng.o_pc),
            self.sat_d.eq(eng.o_sat_d), self.sat_q.eq(eng.o_sat_q),
        ]
        if self._status == "ports":
            m.d.comb += [getattr(self, name).eq(getattr(eng, f"o_{STATUS_OUTS[name]}"))
                         for name in STATUS]
        else:
            self._status_ram(m, eng)
        m.d.sync += self.phase.valid.eq(eng.o_pc_we)
        return m

    def _mt_run(self, m, eng, cur_go):
        """``mt=True``: M/T's run (class docstring, *M/T speed*): its request, held while the
        engine runs or a current-loop sample starts (the sample has priority, then the M/T
        run, then a speed run), its operands (``mt_run.payload``, held by M/T from the request
        on) and its result. Returns the run's start."""
        req = Signal()          # a run requested, waiting for the engine
        go = Signal()
        run = self.mt_run
        m.d.comb += go.eq((run.valid | req) & ~cur_go & ~eng.running)
        with m.If(go):
            m.d.sync += req.eq(0)
        with m.Elif(run.valid):
            m.d.sync += req.eq(1)
        m.d.comb += [eng.s_mtm.eq(run.payload.m), eng.s_mtd.eq(run.payload.d),
                     eng.s_mts.eq(run.payload.s), eng.s_mtb.eq(run.payload.b),
                     self.mt_res.payload.eq(eng.o_mtspd), self.mt_res.valid.eq(eng.o_mtspd_we)]
        return go

    def _speed_run(self, m, eng, cur_go, mt_go=None):
        """``speed=True``: the speed run beside the current loop's samples (class docstring,
        *Speed loop*): request, decimation, start arbitration, the state the program keeps
        outside the engine (``ref_int``, ``fresh``), the abort of a run in flight at
        ``clear``, and the outputs."""
        sp = SPEED_PARAMS
        clear = self.speed_clear
        # ``speed_slew ≠ 0`` (the tracking choice while ``clear``, read every clock) as a
        # flip-flop loaded with the slew's configuration word (as SpeedLoop(config="ram")).
        j_slew = (len(CONFIG) + (len(REF_CONFIG_WORDS) if self._refs == "ram" else 0)
                  + SPEED_CONFIG_WORDS.index("slew"))
        slew_nz = Signal(init=int(self._config_init[j_slew] != 0))
        with m.If(self.config.valid & (self.config.index == j_slew)):
            m.d.sync += slew_nz.eq(self.config.data != 0)
        # Decimation (as SpeedLoop): every rate_div + 1-th strobe requests a run; a strobe
        # that finds a run requested or in flight is dropped (SpeedLoop drops it while busy).
        count = Signal(unsigned(8))
        with m.If(clear):
            m.d.sync += count.eq(0)
        with m.Elif(self.speed_valid):
            m.d.sync += count.eq(Mux(ge_ripple(count, self.speed_rate_div), 0, count + 1))
        req = Signal()          # a run requested (waits while the engine is busy)
        fl = Signal()           # a run started, its iq not yet written, not aborted
        abort = Signal(2)       # aborted runs whose iq is still to come (their writes gated)
        new = Signal()
        go = Signal()
        m.d.comb += new.eq(self.speed_valid & (count == 0) & ~clear & ~req & ~fl)
        # The current loop's sample has priority (its duties are due at the period boundary),
        # then (mt=True) M/T's run.
        labels = self._program.labels
        if mt_go is None:
            m.d.comb += [go.eq((new | req) & ~cur_go & ~eng.running & ~clear),
                         eng.start.eq(cur_go | go),
                         eng.start_pc.eq(Mux(go, labels["speed"], 0))]
        else:
            m.d.comb += [go.eq((new | req) & ~cur_go & ~mt_go & ~eng.running & ~clear),
                         eng.start.eq(cur_go | mt_go | go),
                         eng.start_pc.eq(Mux(go, labels["speed"],
                                             Mux(mt_go, labels["mt"], 0)))]
        with m.If(clear | go):
            m.d.sync += req.eq(0)
        with m.Elif(new):
            m.d.sync += req.eq(1)
        # The speed: read by the program from the port itself, which holds from the request
        # to the run's read (the contract, class docstring: M/T's output register in the top,
        # a PWM period between its updates; no 32-bit latch). ``fresh`` (set by clear)
        # latched at the start.
        fresh = Signal(init=1)
        l_fresh = Signal()
        with m.If(clear):
            m.d.sync += fresh.eq(1)
        with m.Elif(go):
            m.d.sync += [fresh.eq(0), l_fresh.eq(fresh)]
        # In flight / aborted: the iq write is the last output write of every run.
        iq_we = eng.o_iq_we
        ok = Signal()
        m.d.comb += ok.eq((abort == 0) & ~clear)
        with m.If(clear & fl):
            m.d.sync += [fl.eq(0), abort.eq(abort + 1)]
        with m.Else():
            with m.If(go):
                m.d.sync += fl.eq(1)
            with m.Elif(iq_we & (abort == 0)):
                m.d.sync += fl.eq(0)
            with m.If(iq_we & (abort != 0)):
                m.d.sync += abort.eq(abort - 1)
        # ref_int: forced to the tracked value while clear, else the program's write.
        ref_int = self.speed_ref_int
        with m.If(clear):
            m.d.sync += ref_int.eq(Mux(slew_nz, self.speed, self.speed_ref))
        with m.Elif(eng.o_ref_int_we & ok):
            m.d.sync += ref_int.eq(eng.o_data[:sp["speed_width"]])
        # The i_q reference, sat (written just before iq by the program) and o.valid.
        m.d.sync += self.speed_o.valid.eq(iq_we & ok)
        with m.If(clear):
            m.d.sync += [self.speed_o.payload.eq(0), self.speed_sat.eq(0)]
        with m.Elif(iq_we & ok):
            m.d.sync += [self.speed_o.payload.eq(eng.o_data[:16]),
                         self.speed_sat.eq(eng.o_sat)]
        d = self.speed_ref_delay
        refs = self._refs == "ram"      # (the limits are configuration words then)
        m.d.comb += [eng.s_spd.eq(self.speed), eng.s_sref.eq(self.speed_ref), eng.s_rint.eq(ref_int),
                     *([] if refs else [eng.s_ilo.eq(self.iq_lim_lo),
                                        eng.s_ihi.eq(self.iq_lim_hi)]),
                     eng.s_dfr.eq(d[:3]), eng.s_dint.eq(d[3:]), eng.s_fresh.eq(l_fresh),
                     eng.s_ih.eq(self.speed_int_hold)]
        if refs:
            m.d.comb += eng.s_sliq.eq(self.speed_o.payload)     # SPEED mode's i_q reference

    def _status_ram(self, m, eng):
        """The status RAM (class docstring): written at the engine's writes of the status
        outputs, read through ``status_rd`` (transparent) and ``status_probe`` (old word)."""
        words = self._status_words
        strobes = [getattr(eng, f"o_{({**STATUS_OUTS, **REF_STATUS_OUTS})[name]}_we")
                   for name in words]
        addr = Signal(range(len(words)))
        for j, we in enumerate(strobes):        # one strobe at a time (one write per clock)
            with m.If(we):
                m.d.comb += addr.eq(j)
        # The register file's port reads the word written in its clock (transparent), the
        # scope's the word before it; the scope reads only while no status output is written
        # (``status_quiet``): a read of the word being written is left undefined there
        # (``no_rw_check``: no bypass logic).
        # (The scope's: an asynchronous read port with its data registered here, which yosys
        # merges into the block RAM's synchronous port; a synchronous port reading the old word
        # made it add 38 flip-flops.)
        # One RAM per read port (a block RAM has one), both written alike.
        # (refs="ram": the references' words, for the scope, in the scope's RAM only, and one
        # more word there that is never written: it reads 0, ``status_zero``.)
        n_words = {"status_rd": len(STATUS),
                   "status_probe": len(words) + (self._refs == "ram")}
        self._status_mems = {
            name: Memory(shape=signed(ENGINE_WIDTH), depth=n_words[name], init=[],
                         attrs={} if name == "status_rd" else {"no_rw_check": 1})
            for name in ("status_rd", "status_probe")}
        for name, transparent in (("status_rd", True), ("status_probe", False)):
            port = getattr(self, name)
            m.submodules[f"{name}_ram"] = mem = self._status_mems[name]
            wr = mem.write_port()
            m.d.comb += [wr.en.eq(Cat(*strobes[:n_words[name]]).any()),
                         wr.addr.eq(addr[:len(wr.addr)]),
                         wr.data.eq(eng.o_data[:ENGINE_WIDTH])]
            if transparent:
                rd = mem.read_port(transparent_for=(wr,))
                m.d.comb += [rd.addr.eq(port.addr), rd.en.eq(port.en), port.data.eq(rd.data)]
            else:
                rd = mem.read_port(domain="comb")
                data_q = Signal(signed(ENGINE_WIDTH), reset_less=True)
                m.d.comb += [rd.addr.eq(port.addr), port.data.eq(data_q)]
                m.d.sync += data_q.eq(rd.data)


# --- The speed loop as an engine program (docs/ENGINE.md "Speed loop as a program") --------------


def speed_loop_program(*, schedule=True, fold=True, realloc=True):
    """Assemble a speed-loop run (:class:`~.servo.SpeedLoop`'s equations with
    the iCEBreaker top's widths: ``speed_width`` 32, ``width`` 24, ``delay_width`` 5): the
    reference profile (``R[n]`` → the ``ref_int`` output), the feed-forward ``ff``, the
    ``ref_delay`` interpolation, the integrator hold, the PI's error ``E`` (these leave
    ``r.plan``, ``r.ff``, ``r.hold`` (0 / 1), ``r.ref``, ``r.fb``, ``r.e`` in the register
    file), the reference history (``r.h0 … r.h2``: ``to_pi`` of ``R`` one to three runs before
    the last), and the speed PI with the feed-forward (:func:`_speed_pi`) → the ``iq`` and
    ``sat`` outputs. Written for ``kp_format`` UQ(24, 12), ``kx_format`` UQ(24, 20) and
    ``int_guard`` 16 (the top's). ``schedule``, ``fold``, ``realloc``: as for
    :meth:`Assembler.assemble` (the registers left in the register file above and the PI's
    ``r.ih``, ``r.il``, ``r.ep`` kept in words of their own: a model reads them after a run).

    In the profile every value stays within the 32-bit ``WORD``: a difference of two 32-bit
    values (33 bits) is only compared (the ALU's flags are those of its 33-bit sum) or halved;
    ``D > S`` for ``D = speed_ref − R`` and the UQ1.31 slew ``S`` is decided on
    ``floor(D/2) − (S >> 1)`` (sign, zero) and the low bits ``D − 2·floor(D/2)``, ``S & 1``;
    ``R ± S`` is formed only on the path where it lies between ``R`` and ``speed_ref``.

    Returns
    -------
    Program
    """
    A = Assembler(specials=SPEED_SPECIALS, conds=SPEED_CONDS, outs=tuple(SPEED_OUTS))
    _speed_loop(A)
    A.end()
    return A.assemble(schedule=schedule, fold=fold, realloc=realloc,
                      keep=("plan", "ff", "hold", "ref", "fb", "e", "ih", "il", "ep"))


class _Renamed:
    """A run's emitter on another program's assembler: its temporaries take that program's
    registers ``pool`` (in order, then new ones), its state registers (``state``: the speed
    loop's :data:`SPEED_STATE`) and labels get the prefix ``prefix`` (``spd_``); ``subst``:
    operands read in place of others (e.g. a register for a special)."""

    def __init__(self, asm, pool, *, prefix="spd_", state=SPEED_STATE, subst=None):
        self._asm, self._pool, self._map = asm, list(pool), {}
        self._prefix, self._state, self._subst = prefix, tuple(state), dict(subst or {})

    def _r(self, x):
        if isinstance(x, str) and x in self._subst:
            return self._subst[x]
        if not isinstance(x, str) or not x.startswith("r."):
            return x
        name = x[2:]
        if name not in self._map:
            self._map[name] = (self._prefix + name if name in self._state or not self._pool
                               else self._pool.pop(0))
        return "r." + self._map[name]

    def alu(self, op, dst, a, b="k.0", **kw):
        return self._asm.alu(op, self._r(dst), self._r(a), self._r(b), **kw)

    def mul(self, a, b, **kw):
        return self._asm.mul(self._r(a), self._r(b), **kw)

    def mac(self, a, b, **kw):
        return self._asm.mac(self._r(a), self._r(b), **kw)

    def post(self, dst, sh=0, **kw):
        return self._asm.post(self._r(dst), sh, **kw)

    def div(self, b, steps=1):
        return self._asm.div(self._r(b), steps)

    def br(self, cond, label):
        return self._asm.br(cond, self._prefix + label)

    def label(self, name):
        return self._asm.label(self._prefix + name)

    def nop(self):
        return self._asm.nop()


def _speed_loop(A):
    """Emit a speed-loop run (:func:`speed_loop_program`) without its END."""
    top = (1 << 23) - 1                             # signed(24): the PI's width

    def to_pi(dst, src):
        """dst = saturate(round_shift(src, 8), signed(24)) (≥ −2**23 for any 32-bit src)."""
        A.alu(Op.ADD, dst + "_r", src, 0, sh=8, rnd=True)
        A.alu(Op.MIN, dst, top, dst + "_r")

    def exceeds(name, x, y):
        """r.name = 1 if x − y > S else 0 (x, y 32-bit registers; D = x − y has 33 bits)."""
        r = lambda s: f"r.{name}_{s}"                                     # noqa: E731
        A.alu(Op.SUB, r("f"), x, y, sh=1)                   # Df = floor(D/2)
        A.alu(Op.SUB, r("a"), x, r("f"))                    # ceil((x + y)/2)
        A.alu(Op.ADD, r("b"), y, r("f"))                    # floor((x + y)/2)
        A.alu(Op.SUB, r("l"), r("a"), r("b"))               # D − 2·Df ∈ {0, 1}
        A.alu(Op.SUB, r("v"), r("l"), "r.sl")               # V = (D − 2·Df) − (S & 1)
        # D − S = 2·T + V, T = Df − (S >> 1): > 0 iff T > 0, or T = 0 and V > 0.
        A.alu(Op.SUB, None, r("f"), "r.sh", setf=True)
        A.alu(Op.SEL, r("k"), 1, r("v"), cond="Z")
        A.alu(Op.SEL, r("k"), r("k"), -1, cond="N")
        A.alu(Op.ADD, None, r("k"), 0, setf=True)
        A.alu(Op.SEL, f"r.{name}", 1, 0, cond="LE")

    def flag(name):
        """Z ← the special ``name`` is 0 (a 1-bit flag set: ``!Z``)."""
        A.alu(Op.ADD, None, f"s.{name}", 0, setf=True)

    # R[n−1], to_pi(R[n−1]); after clear the history starts at it and the PI is cleared.
    A.alu(Op.ADD, "r.R", "s.rint", 0)
    to_pi("r.tp", "s.rint")
    flag("fresh")
    for h in ("h0", "h1", "h2"):
        A.alu(Op.SEL, f"r.{h}", f"r.{h}", "r.tp", cond="!Z")
    for reg in ("r.ih", "r.il", "r.ep"):
        A.alu(Op.SEL, reg, reg, 0, cond="!Z")
    A.alu(Op.ADD, "r.sref", "s.sref", 0)
    A.alu(Op.ADD, "r.sh", "s.slh", 0)
    A.alu(Op.ADD, "r.sl", "s.sll", 0)
    A.alu(Op.ADD, None, "r.sh", "r.sl", setf=True)                    # Z: S = 0 (no profile)
    A.alu(Op.SEL, "r.snz", 1, 0, cond="Z")
    # up: speed_ref − R > S; dn: R − speed_ref > S (S ≠ 0).
    exceeds("up", "r.sref", "r.R")
    exceeds("dn", "r.R", "r.sref")
    A.alu(Op.MIN, "r.up", "r.up", "r.snz")
    A.alu(Op.MIN, "r.dn", "r.dn", "r.snz")
    # ff = clamp(±iq_ff, lim_lo, lim_hi) while the profile moves, else 0.
    A.alu(Op.ADD, "r.f", "s.iqff", 0)
    A.alu(Op.SUB, "r.nf", 0, "r.f")
    A.alu(Op.ADD, None, "r.up", 0, setf=True)
    A.alu(Op.SEL, "r.fv", "r.f", "r.nf", cond="Z")                     # up ? F : −F
    A.alu(Op.MIN, "r.ft", "s.ihi", "r.fv", setf=True)                 # N: fv > hi
    A.alu(Op.MAX, "r.fc", "s.ilo", "r.ft", cond="N")                  # clamp(fv, lo, hi)
    A.alu(Op.MAX, "r.updn", "r.up", "r.dn")
    A.alu(Op.ADD, None, "r.updn", 0, setf=True)
    A.alu(Op.SEL, "r.ff", "r.fc", 0, cond="Z")
    # plan = R + S (up), R − S (dn), else speed_ref: R ± S lies between R and speed_ref there.
    A.alu(Op.ADD, None, "r.up", 0, setf=True)
    A.br("!Z", "up")
    A.nop()
    A.nop()
    A.alu(Op.ADD, None, "r.dn", 0, setf=True)
    A.br("!Z", "dn")
    A.nop()
    A.nop()
    A.alu(Op.ADD, "r.plan", "r.sref", 0)
    A.br("!F", "plan")
    A.nop()
    A.nop()
    A.label("up")
    A.alu(Op.ADD, "r.p1", "r.R", "r.sh")
    A.alu(Op.ADD, "r.p2", "r.p1", "r.sh")
    A.alu(Op.ADD, "r.plan", "r.p2", "r.sl")
    A.br("!F", "plan")
    A.nop()
    A.nop()
    A.label("dn")
    A.alu(Op.SUB, "r.p1", "r.R", "r.sh")
    A.alu(Op.SUB, "r.p2", "r.p1", "r.sh")
    A.alu(Op.SUB, "r.plan", "r.p2", "r.sl")
    A.label("plan")
    A.alu(Op.ADD, None, "r.plan", 0, out="ref_int")
    # The PI's reference: to_pi(plan) (d = 0), else a + round_shift(f·(b − a), 3) with
    # a = tap d − 1, b = tap d of (to_pi(R[n−1]), h0, h1, h2).
    to_pi("r.tpl", "r.plan")
    A.alu(Op.SUB, None, "s.dint", 2, setf=True)            # N: d < 2, Z: d = 2
    A.alu(Op.SEL, "r.ta1", "r.h1", "r.h0", cond="Z")
    A.alu(Op.SEL, "r.tb1", "r.h2", "r.h1", cond="Z")
    A.alu(Op.SEL, "r.ta", "r.ta1", "r.tp", cond="N")
    A.alu(Op.SEL, "r.tb", "r.tb1", "r.h0", cond="N")
    A.alu(Op.SUB, "r.cb", "r.tb", "r.ta")
    A.mul("s.dfr", "r.cb")
    A.post("r.fd", 3)
    A.alu(Op.ADD, "r.refi", "r.ta", "r.fd")
    flag("dint")                                            # Z: d = 0
    A.alu(Op.SEL, "r.ref", "r.refi", "r.tpl", cond="Z")
    # hold = int_hold and S ≠ 0 and (R[n−1] ≠ speed_ref or (d ≥ 1 and ref ≠ to_pi(R[n−1]))).
    A.alu(Op.SUB, None, "r.R", "r.sref", setf=True)
    A.alu(Op.SEL, "r.m1", 1, 0, cond="Z")
    A.alu(Op.SUB, None, "r.ref", "r.tp", setf=True)
    A.alu(Op.SEL, "r.m2", 1, 0, cond="Z")
    flag("dint")
    A.alu(Op.SEL, "r.m3", "r.m2", 0, cond="Z")
    A.alu(Op.MAX, "r.mv", "r.m1", "r.m3")
    A.alu(Op.MIN, "r.mv2", "r.mv", "r.snz")
    flag("ih")
    A.alu(Op.SEL, "r.hold", 0, "r.mv2", cond="!Z")
    # fb = to_pi(speed); E = saturate(ref − fb, signed(24)).
    to_pi("r.fb", "s.spd")
    A.alu(Op.SUB, "r.e0", "r.ref", "r.fb")
    A.alu(Op.MIN, "r.e1", top, "r.e0")
    A.alu(Op.MAX, "r.e", -(1 << 23), "r.e1")
    # The history moves on: h2 ← h1 ← h0 ← to_pi(R[n−1]).
    A.alu(Op.ADD, "r.h2", "r.h1", 0)
    A.alu(Op.ADD, "r.h1", "r.h0", 0)
    A.alu(Op.ADD, "r.h0", "r.tp", 0)
    _speed_pi(A)


def _speed_pi(A):
    """The speed PI (hdl/pi.py's equations, ``width`` 24, ``int_guard`` g = 16, ``kp``
    UQ(24, 12): ``p = 16·kp·E``, ``kx`` UQ(24, 20): ``dI = round_shift(kx·(E + E[n−1]), 4)``)
    with the limits ``sat((lim − ff)·2**8)`` and the output ``i_q = sat(round_shift(O +
    ff·2**8, 8), signed(16))``, on the 32-bit RF and the 45-bit P.

    Widths: the integrator I (40 bits) is kept as ``Ih = I >> 16`` and ``Il = I & 0xFFFF``;
    ``dI`` (< 2**44) is formed exactly in P from three pieces of ``kx = 2**16·a + 2**4·b + c``
    (``round_shift(kx·x, 4) = 2**12·a·x + b·x + round_shift(c·x, 4)``: ``c·x`` has the sum's
    sign; ``2**12·a·x = (2**10·a)·(4·x)`` fits the 19 × 28 multiplier) and enters
    ``I + dI`` saturated to about ±2**41 (exact below), ``p`` (up to 52 bits) as
    ``2**16·q' + kpl·16E`` with ``q = kph·16E`` saturated to about ±2**25 (exact below): beyond
    those ``I + dI`` lies outside the limits·2**16 and ``p + I`` beyond ``±2**41 − 2**39``
    whatever I (``|I| ≤ 2**39``), so every comparison, clamp and output is that of the exact
    values (as SpeedLoop's own saturation of P and dI, hdl/servo.py). A value is saturated in
    P by ``y = sat17(P >> k)``, ``r = sat17(P − 2**k·y)``: exact when ``y`` is, else beyond.
    ``I + dI`` (< 2**43) is split as ``floor / 2**16`` and the remainder: above ``hi·2**16`` iff
    its ceiling exceeds ``hi``, below ``lo·2**16`` iff its floor is below ``lo``."""
    top, bot = (1 << 23) - 1, -(1 << 23)
    # (First run after clear: the PI's state is cleared at the run's start, :func:`_speed_loop`.)
    # Limits lo_s, hi_s = sat((lim − ff)·2**8, signed(24)).
    for side in ("lo", "hi"):
        A.alu(Op.SUB, f"r.{side}d", f"s.i{side}", "r.ff")
        A.mul(f"r.{side}d", 256)
        A.post(f"r.{side}s0", 0)
        A.alu(Op.MIN, f"r.{side}s1", top, f"r.{side}s0")
        A.alu(Op.MAX, f"r.{side}s", bot, f"r.{side}s1")
    # x = E + E[n−1] (0 when held: kx = 0); E[n−1] ← E.
    A.alu(Op.ADD, "r.x0", "r.e", "r.ep")
    A.alu(Op.ADD, None, "r.hold", 0, setf=True)
    A.alu(Op.SEL, "r.x", "r.x0", 0, cond="!Z")
    A.alu(Op.ADD, "r.ep", "r.e", 0)
    A.mul(4, "r.x")
    A.post("r.x4", 0)
    # dI = 2**12·a·x + b·x + round_shift(c·x, 4), exact in P; its sign → r.ds.
    A.mul("s.kxc", "r.x")
    A.post("r.rc", 4)
    A.mul("s.kxa", "r.x4")
    A.mac("s.kxb", "r.x")
    A.mac(1, "r.rc")
    A.post("r.ds", 0, sat=SAT_W1)                   # sign and zero of dI
    A.post("r.dy", 25, rnd=False, sat=SAT_W1)       # dI saturated: 2**25·dy + 2**9·d9 + d0
    A.mac("r.dy", -(1 << 25))
    A.post("r.d9", 9, rnd=False, sat=SAT_W1)
    A.mac("r.d9", -(1 << 9))
    A.post("r.d0", 0, sat=SAT_W1)
    # I + dI → sh16 = floor(/2**16), sl = the remainder; sc = ceiling.
    A.mul("r.dy", 1 << 25)
    A.mac("r.d9", 1 << 9)
    A.mac("r.d0", 1)
    A.mac(1 << 16, "r.ih")
    A.mac("r.il", 1)
    A.post("r.sh16", 16, rnd=False)
    A.mac(-(1 << 16), "r.sh16")
    A.post("r.sl", 0)
    A.alu(Op.ADD, None, "r.sl", 0, setf=True)
    A.alu(Op.SEL, "r.slnz", 1, 0, cond="Z")
    A.alu(Op.ADD, "r.sc", "r.sh16", "r.slnz")
    # I_c = clamp(I + dI, lo_s·2**16, hi_s·2**16) as (ich, icl): above first (clamp's order).
    A.alu(Op.SUB, None, "r.sh16", "r.los", setf=True)              # N: below
    A.alu(Op.SEL, "r.ich1", "r.sh16", "r.los", cond="N")
    A.alu(Op.SEL, "r.icl1", "r.sl", 0, cond="N")
    A.alu(Op.SUB, None, "r.his", "r.sc", setf=True)                # N: above
    A.alu(Op.SEL, "r.ich", "r.ich1", "r.his", cond="N")
    A.alu(Op.SEL, "r.icl", "r.icl1", 0, cond="N")
    # p = 2**16·q' + kpl·16E, q = kph·16E saturated: 2**9·qy + qr.
    A.mul(16, "r.e")
    A.post("r.e16", 0)
    A.mul("s.kph", "r.e16")
    A.post("r.qy", 9, rnd=False, sat=SAT_W1)
    A.mac("r.qy", -(1 << 9))
    A.post("r.qr", 0, sat=SAT_W1)

    def u_of(dst, ih, il):
        A.mul("r.qy", 1 << 25)
        A.mac("r.qr", 1 << 16)
        A.mac("s.kpl", "r.e16")
        A.mac(1 << 16, ih)
        A.mac(il, 1)
        A.post(dst, 16)                             # round_shift(p + I, 16)

    u_of("r.uc", "r.ich", "r.icl")
    # hold = (u_c > hi_s and dI > 0) or (u_c < lo_s and dI < 0): I kept, else I_c.
    A.alu(Op.SUB, None, "r.his", "r.uc", setf=True)                # N: u_c > hi
    A.alu(Op.SEL, "r.g1", 0, "r.ds", cond="N")                     # > 0: hold
    A.alu(Op.SUB, None, "r.uc", "r.los", setf=True)                # N: u_c < lo
    A.alu(Op.SEL, "r.g2", 0, "r.ds", cond="N")                     # < 0: hold
    A.alu(Op.ADD, None, "r.g1", 0, setf=True)
    A.alu(Op.SEL, "r.nh1", "r.ich", "r.ih", cond="!LE")
    A.alu(Op.SEL, "r.nl1", "r.icl", "r.il", cond="!LE")
    A.alu(Op.ADD, None, "r.g2", 0, setf=True)
    A.alu(Op.SEL, "r.ih", "r.nh1", "r.ih", cond="N")
    A.alu(Op.SEL, "r.il", "r.nl1", "r.il", cond="N")
    u_of("r.u", "r.ih", "r.il")
    # O = clamp(u, lo_s, hi_s); sat; i_q = sat(round_shift(O + ff·2**8, 8), signed(16)).
    A.alu(Op.MIN, "r.ot", "r.his", "r.u", setf=True)               # N: u > hi
    A.alu(Op.MAX, "r.o", "r.los", "r.ot", cond="N")
    A.alu(Op.SUB, None, "r.o", "r.u", out="sat")                   # sat = O ≠ u
    A.mul("r.ff", 256)
    A.post("r.ff8", 0)
    A.alu(Op.ADD, "r.iq", "r.o", "r.ff8", sh=8, rnd=True, sat=SAT_W, out="iq")
