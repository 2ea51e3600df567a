# Ref: docs/ENGINE.md; hdl/engine.py (ISA); AREA.md §4 stage 2
"""Bit-true interpreter of :class:`foc_servo.hdl.engine.Engine`: runs the same ROM words clock by
clock (one instruction per clock, two branch delay slots; a DIV word ``sh + 1`` times, a word
with bubbles (``nb``, folded NOPs) followed by ``nb`` clocks in which nothing is issued; the
fetch as the gateware's, :class:`~foc_servo.hdl.engine.Fetch`) with the gateware's timing where a
program can see it: register and output writes land ``WRITE_DELAY`` (3) instructions late (the
X4 stage), the fold flags follow the angle register at once, ``KD`` a clock later, the table
words two (the special operands are registered in the R stage); flags are sequential; P is
sequential for MAC and DIV (X3) but a post reads it in X2, before the update of the
instruction just before it (``HAZARD_P``). It records, per executed instruction, what the
gateware shows on its ``trace_*`` ports in that instruction's X4 clock.

Every value is checked against the widths the gateware gives it (multiplier operands
``signed(MUL_A)`` × ``signed(MUL_B)``, register file ``signed(WORD)``, ``P`` ``signed(P_WORD)``): a program that
would overflow raises :exc:`OverflowError` here instead of wrapping there.
"""

import collections

from ...hdl.engine import (BUILTIN_CONDS, BUILTIN_SPECIALS, MUL_A, MUL_B, SAT_W, SAT_W1, WORD,
                           P_WORD, WRITE_DELAY, Fetch, Instr, Op, check_flag_outputs)
from ...hdl.rotator import RotatorParams

__all__ = ["EngineModel", "EngineLoopModel", "EngineSpeedModel", "engine_fields",
           "lead_angle", "loop_model_inputs"]

ALU = (Op.ADD, Op.SUB, Op.RSUB, Op.MIN, Op.MAX, Op.SEL)
#: What X1 executes in a bubble (a folded NOP): nothing.
_BUBBLE = Instr()


def _fits(value, bits, what):
    lo, hi = -(1 << (bits - 1)), (1 << (bits - 1)) - 1
    if not lo <= value <= hi:
        raise OverflowError(f"engine {what} {value} does not fit signed({bits})")
    return value


class EngineModel:
    """The engine's architectural state and an interpreter of its program.

    Parameters
    ----------
    program : foc_servo.hdl.engine.Program
    out_widths : dict of str to int
        As for :class:`~foc_servo.hdl.engine.Engine`.
    width, guard, div_bits, rotator
        As for :class:`~foc_servo.hdl.engine.Engine`.

    Attributes
    ----------
    rf : list of int
        Register file.
    p : int
        Product register.
    outs : dict of str to int
        Output registers.
    """

    def __init__(self, program, *, out_widths, width=16, guard=8, div_bits=16, rotator=None):
        self.program = program
        self.instrs = program.instrs
        self.out_widths = dict(out_widths)
        check_flag_outputs("EngineModel", program, self.out_widths)
        self.width = width
        self.guard = guard
        self.div_bits = div_bits
        self.rot = rotator if rotator is not None else RotatorParams(width=16, angle_width=16)
        self.rf = list(program.rf_init)
        self.p = 0
        self.n = self.z = 0
        self.outs = {name: 0 for name in self.out_widths}
        self.tbl = self._table_word(0)
        self.sreg = self.tbl + (self._fold(0)[1],)

    # --- angle unit ------------------------------------------------------------------------------
    def _fold(self, ang):
        r = self.rot
        aw, mb, n = r.angle_width, r.interp_bits, r.table_bits
        quad = ang >> (aw - 2)
        mu = (ang >> (aw - 3)) & 1
        k = (ang >> mb) & ((1 << n) - 1)
        if mu:
            k ^= (1 << n) - 1
        low = ang & ((1 << mb) - 1)
        kd = r.kd_rom[(mu << mb) | low]
        return k, kd, (quad & 1) ^ mu, (quad & 1) ^ (quad >> 1), quad >> 1

    def _table_word(self, ang):
        r = self.rot
        return r.table_s[self._fold(ang)[0]], r.table_c[self._fold(ang)[0]]

    def _write(self, writes):
        for kind, where, y in writes:
            if kind == "rf":
                self.rf[where] = y
            else:
                self.outs[where] = y & ((1 << self.out_widths[where]) - 1)

    # --- one program run -------------------------------------------------------------------------
    def run(self, specials, conds, start=0):
        """Run the program from address ``start`` (0, or an entry label's) to its END.

        Parameters
        ----------
        specials : dict of str to int
            Values of the user special operands.
        conds : dict of str to bool
            Values of the user conditions.

        Returns
        -------
        list of dict
            One entry per executed instruction (= per clock of the execute stage): ``pc``,
            ``wen``, ``dst``, ``y`` (the post-processed result), ``p`` (P as the instruction's
            post reads it in X2), ``bubble`` (1: a clock in which nothing was issued, a
            folded NOP: ``pc`` is the word whose bubble it is, the gateware's ``trace_valid``
            is low; the trace of a program equals that of its unfolded form but for this and
            the addresses); ``outs`` holds the output registers afterwards.
        """
        prog = self.program
        q = self.div_bits
        trace = []
        fetch = Fetch(self.instrs, start)   # F and R as the gateware sequences them
        issue = fetch.issue()               # into X1 in the first clock
        fetch.step()
        pending = collections.deque()     # writes in flight (X2, X3), the oldest first
        p_lag = self.p      # P as the next instruction's post reads it (X2: HAZARD_P)
        ang = self.outs["ang"]                      # steady state after the idle clocks
        self.tbl = self._table_word(ang)
        self.sreg = self.tbl + (self._fold(ang)[1],)
        while True:
            pc, _, bubble = issue
            ins = _BUBBLE if bubble else self.instrs[pc]
            ang = self.outs["ang"]
            _, kd_now, swap, negc, negs = self._fold(ang)
            ts, tc, kd = self.sreg                  # selected and registered in R
            # A post reads P in X2, before the update (X3) of the instruction before it.
            p_x2, p_lag = p_lag, self.p
            spec = [p_x2, p_x2 & ((1 << q) - 1), ts, tc, kd] + [
                int(specials[name]) for name in prog.specials[len(BUILTIN_SPECIALS):]]
            cvals = [0, self.n, self.z, self.n | self.z, swap, negc, negs] + [
                int(bool(conds[name])) for name in prog.conds[len(BUILTIN_CONDS):]]
            a = spec[ins.a] if ins.asp else self.rf[ins.a]
            if ins.asl:
                a <<= self.guard
            b = int(specials[prog.bspecials[ins.b]]) if ins.bsp else self.rf[ins.b]
            c = cvals[ins.cond] ^ ins.inv
            op = Op(ins.op)
            s = a + b if op == Op.ADD else (b - a if op == Op.RSUB else a - b)
            if op == Op.MIN:
                x = b if (c or s >= 0) else a
            elif op == Op.MAX:
                x = b if (c or s <= 0) else a
            elif op == Op.SEL:
                x = b if c else a
            elif ins.asp and ins.a in (0, 1):
                x = a                   # P or PQ (read in X2: p_x2; B is 0)
            else:
                x = s
            sh = ins.sh
            if ins.rnd and sh:
                y = (x + (1 << (sh - 1)) - (x < 0)) >> sh
            else:
                y = x >> sh
            if ins.sat in (SAT_W, SAT_W1):
                sw = self.width + (ins.sat == SAT_W1)
                y = min(max(y, -(1 << (sw - 1))), (1 << (sw - 1)) - 1)
            entry = {"pc": pc, "wen": 0, "dst": ins.dst, "y": None, "p": p_x2,
                     "bubble": int(bubble)}
            writes = []                 # applied WRITE_DELAY instructions later (X4)
            taken = False
            if op in ALU:
                entry["y"] = y
                if ins.wen:
                    writes.append(("rf", ins.dst, _fits(y, WORD, f"result at pc {pc}")))
                    entry["wen"] = 1
                if ins.setf:
                    self.n, self.z = int(s < 0), int(s == 0)
                if ins.out:
                    writes.append(("out", prog.outs[ins.out], int(x != 0)
                                   if self.out_widths[prog.outs[ins.out]] == 1 else y))
            elif op == Op.MUL:
                if ins.wen or ins.out:                  # fused post of the old P
                    x = p_x2
                    y = (x + (1 << (sh - 1)) - (x < 0)) >> sh if (ins.rnd and sh) else x >> sh
                    if ins.sat in (SAT_W, SAT_W1):
                        sw = self.width + (ins.sat == SAT_W1)
                        y = min(max(y, -(1 << (sw - 1))), (1 << (sw - 1)) - 1)
                    entry["y"] = y
                    if ins.wen:
                        writes.append(("rf", ins.dst, _fits(y, WORD, f"result at pc {pc}")))
                        entry["wen"] = 1
                    if ins.out:
                        if self.out_widths[prog.outs[ins.out]] == 1:
                            raise ValueError(f"engine: 1-bit output from a MUL at pc {pc}")
                        writes.append(("out", prog.outs[ins.out], y))
                _fits(a, MUL_A, f"multiplier A at pc {pc}")
                _fits(b, MUL_B, f"multiplier B at pc {pc}")
                prod = -(a * b) if (ins.neg ^ c) else a * b
                self.p = _fits((self.p if ins.acc else 0) + prod, P_WORD, f"P at pc {pc}")
            elif op == Op.DIV:
                # The divisor reaches X3 as the product 1·B: the multiplier's B operand.
                _fits(b, MUL_B, f"DIV divisor at pc {pc}")
                t2 = self.p << 1
                if (t2 >> q) >= b:
                    t2 = t2 - (b << q) + 1
                self.p = _fits(t2, P_WORD, f"P (DIV) at pc {pc}")
            elif op == Op.BR:
                taken = bool(c)
            trace.append(entry)
            # The table read port follows the angle register one clock behind; then the write
            # back (X4) of the instruction WRITE_DELAY before this one lands.
            self.sreg = self.tbl + (kd_now,)
            self.tbl = self._table_word(ang)
            pending.append(writes)
            if len(pending) > WRITE_DELAY:
                self._write(pending.popleft())
            if op == Op.END:
                while pending:
                    self._write(pending.popleft())
                break
            # R issues into X1 in the next clock; a branch taken here loads pc.
            issue = fetch.issue()
            fetch.step(ins.tgt if taken else None)
        return trace


def _complete(program, specials, conds):
    """The special operands and conditions of ``program`` not given (those of the other program
    in a combined ROM, ``current_loop_program(speed=True)``) as 0."""
    from ...hdl.engine import BUILTIN_CONDS, BUILTIN_SPECIALS
    specials = {**{n: 0 for n in program.specials[len(BUILTIN_SPECIALS):]}, **specials}
    conds = {**{n: False for n in program.conds[len(BUILTIN_CONDS):]}, **conds}
    return specials, conds


def _signed(v, bits):
    v &= (1 << bits) - 1
    return v - (1 << bits) if v >> (bits - 1) else v


def engine_fields():
    """Per-sample inputs of :class:`EngineLoopModel` (and of the gateware
    :class:`~foc_servo.hdl.foc_engine.EngineCurrentLoop`): ``CurrentLoopModel``'s, with the
    inverse Park's advance ``theta_lead`` replaced by the ``lead_k`` register (θ_lead is
    computed from the sample's speed, :func:`lead_angle`)."""
    from .foc import SAMPLE_FIELDS
    return tuple("lead_k" if f == "theta_lead" else f for f in SAMPLE_FIELDS)


def lead_angle(speed, k):
    """θ_lead of :class:`~foc_servo.hdl.top.LeadAngle` (and of the engine's program):
    ``round_shift(n·k, 15) mod 2**16``, ``n = sat(round_shift(speed, 16), signed(16))`` (speed
    Q1.31 of N_FS, ``k`` UQ0.16 turns at N_FS; rounding half away from zero)."""
    import numpy as np
    from amaranth.hdl import signed
    from ...hdl.fixed import round_shift_np, saturate_np
    n = np.asarray(saturate_np(round_shift_np(np.asarray(speed, dtype=np.int64), 16),
                               signed(16)), dtype=np.int64)
    return np.asarray(round_shift_np(n * np.asarray(k, dtype=np.int64), 15),
                      dtype=np.int64) & 0xFFFF


def loop_model_inputs(inputs):
    """The inputs of :class:`~foc_servo.sim.models.foc.CurrentLoopModel` equivalent to the
    engine's ``inputs`` (dict of arrays): ``theta_lead`` from ``speed`` and ``lead_k``."""
    out = {k: v for k, v in inputs.items() if k != "lead_k"}
    out["theta_lead"] = lead_angle(inputs["speed"], inputs["lead_k"])
    return out


class EngineLoopModel:
    """The current-loop program (:func:`foc_servo.hdl.foc_engine.current_loop_program`) on
    :class:`EngineModel`, with the ports of :class:`~foc_servo.sim.models.foc.CurrentLoopModel`
    but ``lead_k`` in place of ``theta_lead`` (:func:`engine_fields`, :func:`loop_model_inputs`):
    :meth:`run` returns the same dictionary, so the two can be compared directly.

    The DC-bus gain is the program's own (its register ``dcg``, 1.0 at power-up, written after
    each sample's duties for the next sample).

    Attributes
    ----------
    engine : EngineModel
    traces : list
        The instruction trace of every sample of the last :meth:`run`.
    """

    def __init__(self, *, gain_limit=2.0, program=None):
        from ...hdl.foc_engine import OUTS, SPEED_OUTS, current_loop_program
        limit_raw = round(gain_limit * (1 << 16))
        self.program = (program if program is not None
                        else current_loop_program(gain_limit_raw=limit_raw))
        self.engine = EngineModel(self.program, out_widths={
            **OUTS, **{k: v for k, v in SPEED_OUTS.items() if k in self.program.outs}})
        self.traces = []

    @property
    def dc_gain(self):
        """DC-bus gain (UQ2.16) the next sample will be compensated with."""
        return self.engine.rf[self.program.regs["dcg"]]

    @staticmethod
    def specials_of(v, k):
        """Special operands and conditions of sample ``k`` of the input arrays ``v``."""
        from ...hdl.fixed import round_shift_np, saturate_np
        from amaranth.hdl import signed
        g = lambda name: int(v[name][k])
        nspd = int(saturate_np(round_shift_np(g("speed"), 32 - 16), signed(16)))
        spec = {"ia": g("ia"), "ib": g("ib"), "theta": g("theta") % (1 << 16),
                "klead": g("lead_k"), "id_ref": g("id_ref"),
                "iq_ref": g("iq_ref"), "ol_ud": g("ol_ud"), "ol_uq": g("ol_uq"), "nspd": nspd,
                "gain_a": g("gain_a"), "gain_b": g("gain_b"), "off_a": g("offset_a"),
                "off_b": g("offset_b"), "kp_d": g("kp_d"), "kx_d": g("kx_d"),
                "lo_d": g("lim_lo_d"), "hi_d": g("lim_hi_d"), "kp_q": g("kp_q"),
                "kx_q": g("kx_q"), "lo_q": g("lim_lo_q"), "hi_q": g("lim_hi_q"),
                "ff_l": g("ff_l"), "ff_psi": g("ff_psi"), "scale": g("scale"),
                "udc": g("udc"), "urat": g("u_rated")}
        en, ol, ff = g("enable") != 0, g("ol_enable") != 0, g("ff_enable") != 0
        conds = {"RUN": en and not ol, "OL": ol, "FF": ff and en and not ol}
        return spec, conds

    def run(self, **inputs):
        import numpy as np
        from .foc import CONFIG_FIELDS, OUTPUT_FIELDS
        fields = engine_fields() + CONFIG_FIELDS
        arrays = np.broadcast_arrays(*(np.asarray(inputs[k], dtype=np.int64) for k in fields))
        v = dict(zip(fields, (np.atleast_1d(a) for a in arrays)))
        n = v["ia"].size
        out = {k: np.zeros(n, dtype=np.int64) for k in OUTPUT_FIELDS}
        self.traces = []
        for k in range(n):
            spec, conds = _complete(self.program, *self.specials_of(v, k))
            applied = self.dc_gain
            self.traces.append(self.engine.run(spec, conds))
            o = self.engine.outs
            res = {"a": _signed(o["pa"], 16), "b": _signed(o["pb"], 16),
                   "c": _signed(o["pc"], 16), "i_alpha": _signed(o["pa"], 16),
                   "i_beta": _signed(o["i_beta"], 16), "i_d": _signed(o["i_d"], 16),
                   "i_q": _signed(o["i_q"], 16), "u_d": _signed(o["u_d"], 16),
                   "u_q": _signed(o["u_q"], 16), "u_alpha": _signed(o["u_alpha"], 16),
                   "u_beta": _signed(o["u_beta"], 16), "duty_a": o["da"], "duty_b": o["db"],
                   "duty_c": o["dc"], "overmod": o["om"], "sat_d": o["sat_d"],
                   "sat_q": o["sat_q"], "dc_gain": applied, "dc_limited": o["lim"],
                   "udc": int(v["udc"][k])}
            for name, val in res.items():
                out[name][k] = val
        return out


class EngineSpeedModel:
    """A speed-loop run (:func:`foc_servo.hdl.foc_engine.speed_loop_program`) on
    :class:`EngineModel`, one :meth:`run` per accepted run, with the state the gateware keeps
    outside the program: the ``ref_int`` output register (forced to the tracked value by
    :meth:`clear`) and the ``fresh`` flag (a 1-bit special; set by :meth:`clear`, cleared by a run). The
    outputs ``iq`` and ``sat`` hold until the next run (the gateware clears them with
    ``clear``).

    ``program`` may be the combined ROM (``current_loop_program(speed=True)``): the run then
    starts at its ``speed`` label, and ``engine`` may be an :class:`EngineLoopModel`'s, so that
    the two programs share the register file as they would in the gateware (only
    ``ih``, ``il``, ``ep`` of :data:`RESULTS` are returned then: the others are temporaries
    in the current loop's registers).

    Attributes
    ----------
    engine : EngineModel
    ref_int : int
        The profile's reference ``R`` (signed 32 bits), as ``SpeedLoopModel.ref_int`` after a
        run or a ``clear``.
    trace : list of dict
        :meth:`EngineModel.run`'s trace of the last run.
    """

    #: Register-file values :meth:`run` returns.
    RESULTS = ("plan", "ff", "hold", "ref", "fb", "e", "ih", "il", "ep")

    def __init__(self, *, program=None, engine=None):
        from ...hdl.foc_engine import OUTS, SPEED_OUTS, speed_loop_program
        self.program = program if program is not None else speed_loop_program()
        self.engine = engine if engine is not None else EngineModel(
            self.program, out_widths={**OUTS, **SPEED_OUTS})
        self.start = self.program.labels.get("speed", 0)
        self.prefix = "spd_" if "speed" in self.program.labels else ""
        self.fresh = False
        self.ref_int = 0
        self.trace = []

    def clear(self, track):
        """A clock of ``clear``: ``R`` tracks ``track`` (the speed if the slew is not 0, else
        ``speed_ref``); the next run starts the history and the PI afresh."""
        self.fresh = True
        self.ref_int = int(track)

    def run(self, *, speed, speed_ref, speed_slew, iq_ff, lim_lo, lim_hi, ref_delay, int_hold,
            kp, kx):
        """One accepted run (raw integers as :meth:`SpeedLoopModel.clock` takes them) → dict
        of :data:`RESULTS` (register-file values) and the outputs ``iq`` (signed), ``sat``."""
        spec, conds = self.specials_of(
            speed=speed, speed_ref=speed_ref, speed_slew=speed_slew, iq_ff=iq_ff,
            lim_lo=lim_lo, lim_hi=lim_hi, ref_delay=ref_delay, int_hold=int_hold, kp=kp, kx=kx)
        self.trace = self.engine.run(spec, conds, start=self.start)
        self.fresh = False
        self.ref_int = _signed(self.engine.outs["ref_int"], 32)
        regs = self.program.regs
        if self.prefix:     # the combined program: only the state registers keep their names
            out = {k: self.engine.rf[regs[self.prefix + k]] for k in ("ih", "il", "ep")}
        else:
            out = {k: self.engine.rf[regs[k]] for k in self.RESULTS}
        out["iq"] = _signed(self.engine.outs["iq"], 16)
        out["sat"] = self.engine.outs["sat"]
        out["integrator"] = (out["ih"] << 16) + out["il"]
        return out

    def specials_of(self, *, speed, speed_ref, speed_slew, iq_ff, lim_lo, lim_hi, ref_delay,
                    int_hold, kp, kx):
        """The engine's special operands and conditions (every one of the program's) for a run
        with these inputs and the state (``ref_int``, ``fresh``) as it is: ``(specials,
        conds)``, the values the gateware feeds its ports."""
        from ...hdl.servo import DELAY_FRAC
        d = int(ref_delay) >> DELAY_FRAC
        spec = {"spd": speed, "sref": speed_ref, "rint": self.ref_int, "slh": speed_slew >> 1,
                "sll": speed_slew & 1, "iqff": iq_ff, "ilo": lim_lo, "ihi": lim_hi,
                "dfr": ref_delay & ((1 << DELAY_FRAC) - 1), "kph": kp >> 16,
                "kpl": kp & 0xFFFF, "kxa": (kx >> 16) << 10, "kxb": (kx >> 4) & 0xFFF,
                "kxc": kx & 0xF, "fresh": int(self.fresh), "ih": int(bool(int_hold)),
                "dint": d}
        return _complete(self.program, {k: int(v) for k, v in spec.items()}, {})
