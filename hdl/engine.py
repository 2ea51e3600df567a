# Ref: AREA.md §4 "Stage 2: one micro-sequenced datapath"; docs/ENGINE.md (ISA, pipeline); issue 7
"""The loop engine: a micro-sequenced, single-issue datapath with one multiplier, a 48-bit ALU,
a block-RAM register file, the rotator's sine table and a program ROM.

The instruction set, the encoding and a tiny assembler (:class:`Assembler`) are defined here and
shared by the gateware (:class:`Engine`) and the bit-true interpreter
(:class:`foc_servo.sim.models.engine.EngineModel`), so that the two cannot disagree on a field.
docs/ENGINE.md has the rationale; the semantics of one instruction (``A``, ``B`` its operands,
``c`` its condition, ``P`` the product register, ``Y`` the post-processed result)::

    A   = SPECIAL[a] if asp else RF[a];  A <<= guard if asl   (A = P or PQ: ADD with B = 0 only)
    B   = SPECIAL[BSPECIALS[b]] if bsp else RF[b]
    c   = COND[cond] ^ inv
    ADD  X = A + B        SUB  X = A − B        RSUB X = B − A        (flags N, Z of X)
    MIN  X = B if (c or A − B ≥ 0) else A      MAX  X = B if (c or A − B ≤ 0) else A
    SEL  X = B if c else A                     (flags of MIN, MAX, SEL: N, Z of A − B)
    Y    = sat(round_shift(X, sh) if rnd else X >> sh)   sat: none, signed(w) or signed(w + 1)
           → RF[dst] if wen; → output register ``out`` (1-bit outputs take X ≠ 0, from an
           ALU operation whose A is not P)
    MUL  P = (P if acc else 0) + (−1 if neg ^ c else 1) · A[:mul_a] · B[:mul_b]; and, fused,
         Y from X = P (the old P: the previous product, post-processed) → RF[dst] / out
    DIV  one restoring step: T = 2P; if T >> q ≥ B: T = T − B·2**q + 1; P = T   (q = div_bits)
    BR   if c: jump to tgt after the two delay-slot instructions
    END  o.valid, halt

Pipeline (one instruction per clock, no stalls): F (program ROM addressed by ``pc``), R (operand
RF read, transparent for the write port), X1 (operand select, ALU adder, flags, branch; MUL and
DIV operands registered), X2 (round/shift/saturate, write back to the RF and the output
registers; product and P update; P is read only here). Hence: an instruction does not see the
register written by the instruction just before it (the assembler inserts a NOP where a program
would, and checks every branch path); flags and P behave sequentially (an ALU operation on P or
PQ is an ADD with B = 0 and reads P in X2). A branch resolves in X1: the two instructions behind
it (the delay slots) always execute. The angle register ``ang`` (an output, written in X2)
addresses the sine table: the fold flags are valid from the second instruction after the one
writing ``ang``, ``KD`` from the third, the table words ``TS``, ``TC`` from the fourth (the
special operands are selected and registered in R).
"""

import dataclasses
import enum

from amaranth.hdl import Cat, Const, Module, Mux, Signal, signed, unsigned
from amaranth.lib import data, wiring
from amaranth.lib.memory import Memory
from amaranth.lib.wiring import In, Out

from .fixed import check_param
from .rotator import RotatorParams

__all__ = ["Op", "FIELDS", "Instr", "Assembler", "Program", "Engine", "WORD", "MUL_A", "MUL_B",
           "RF_DEPTH", "BUILTIN_SPECIALS", "BUILTIN_CONDS", "SAT_NONE", "SAT_W", "SAT_W1"]

#: Width of the register file words, the ALU and the product register ``P``.
WORD = 48
#: Signed widths of the multiplier operands (A, B).
MUL_A, MUL_B = 19, 28
#: Register-file words.
RF_DEPTH = 128
#: Saturation choices.
SAT_NONE, SAT_W, SAT_W1 = 0, 1, 2


class Op(enum.IntEnum):
    NOP = 0
    ADD = 1
    SUB = 2
    RSUB = 3
    MIN = 4
    MAX = 5
    SEL = 6
    MUL = 7
    DIV = 8
    BR = 9
    END = 10


#: ALU operations (they produce ``X`` and may write back).
ALU_OPS = (Op.ADD, Op.SUB, Op.RSUB, Op.MIN, Op.MAX, Op.SEL)

#: Instruction fields, in bit order (name, width).
FIELDS = (("op", 4), ("wen", 1), ("dst", 7), ("asp", 1), ("a", 7), ("bsp", 1), ("b", 7), ("sh", 5),
          ("rnd", 1), ("sat", 2), ("setf", 1), ("cond", 4), ("inv", 1), ("neg", 1), ("acc", 1),
          ("asl", 1), ("out", 5), ("tgt", 8))
INSTR_LAYOUT = data.StructLayout({name: unsigned(width) for name, width in FIELDS})
INSTR_WIDTH = sum(w for _, w in FIELDS)

#: Special operands every engine has (before the user's): the product register, its low
#: ``div_bits`` bits (the quotient after ``div_bits`` DIV steps), the table words and ``kd``.
BUILTIN_SPECIALS = ("P", "PQ", "TS", "TC", "KD")
#: Conditions every engine has (before the user's): never, N, Z, N or Z, the fold flags.
BUILTIN_CONDS = ("F", "N", "Z", "LE", "SWAP", "NEGC", "NEGS")


@dataclasses.dataclass(frozen=True)
class Instr:
    """One decoded instruction (field values as integers)."""
    op: int = Op.NOP
    wen: int = 0
    dst: int = 0
    asp: int = 0
    a: int = 0
    bsp: int = 0
    b: int = 0
    sh: int = 0
    rnd: int = 0
    sat: int = 0
    setf: int = 0
    cond: int = 0
    inv: int = 0
    neg: int = 0
    acc: int = 0
    asl: int = 0
    out: int = 0
    tgt: int = 0

    def encode(self):
        word, pos = 0, 0
        for name, width in FIELDS:
            v = int(getattr(self, name))
            if not 0 <= v < (1 << width):
                raise ValueError(f"Instruction field {name} must be from 0 to {(1 << width) - 1}, "
                                 f"not {v}")
            word |= v << pos
            pos += width
        return word

    @classmethod
    def decode(cls, word):
        values, pos = {}, 0
        for name, width in FIELDS:
            values[name] = (word >> pos) & ((1 << width) - 1)
            pos += width
        return cls(**values)


@dataclasses.dataclass
class Program:
    """An assembled program: ROM words, register-file initial contents and the symbol tables."""
    words: list
    rf_init: list
    regs: dict
    labels: dict
    specials: tuple
    bspecials: tuple
    conds: tuple
    outs: tuple

    @property
    def instrs(self):
        return [Instr.decode(w) for w in self.words]


class Assembler:
    """A tiny assembler: named registers (allocated on first use), constants (a pool of
    read-only register-file words with initial values), labels and branch targets.

    Operands are written as strings: ``"r.name"`` a register, ``"s.name"`` a special input,
    ``"k.value"`` or an ``int`` a constant.

    Parameters
    ----------
    specials : sequence of str
        Names of the special operands after :data:`BUILTIN_SPECIALS`.
    bspecials : sequence of str
        The specials that may also be operand B (``"b.name"``), at most 8.
    conds : sequence of str
        Names of the condition inputs after :data:`BUILTIN_CONDS`.
    outs : sequence of str
        Names of the output registers (out 1 …; out 0 is none).
    """

    def __init__(self, *, specials, bspecials=(), conds, outs):
        self.specials = BUILTIN_SPECIALS + tuple(specials)
        self.bspecials = tuple(bspecials)
        if not set(self.bspecials) <= set(self.specials) or len(self.bspecials) > 8:
            raise ValueError("Assembler bspecials must be at most 8 of the specials")
        self.conds = BUILTIN_CONDS + tuple(conds)
        self.outs = ("",) + tuple(outs)
        if len(self.specials) > 64 or len(self.conds) > 16 or len(self.outs) > 32:
            raise ValueError("Assembler: too many specials, conditions or outputs")
        self._instrs = []
        self._regs = {}
        self._consts = {}
        self._labels = {}
        self._fixups = []

    # --- operands ------------------------------------------------------------------------------
    def reg(self, name):
        if name not in self._regs:
            self._regs[name] = len(self._regs)
        return self._regs[name]

    def const(self, value):
        value = int(value)
        if value not in self._consts:
            self._consts[value] = None
        return ("k", value)

    def _operand(self, x, side):
        if isinstance(x, int):
            x = f"k.{x}"
        kind, _, name = x.partition(".")
        if kind == "r":
            self.reg(name)
            return 0, ("r", name)
        if kind == "k":
            self.const(int(name))
            return 0, ("k", int(name))
        if kind == "s":
            if side != "a":
                raise ValueError(f"Assembler: special operand {x} only on A (use b.{name})")
            return 1, ("s", self.specials.index(name))
        if kind == "b":
            if side != "b":
                raise ValueError(f"Assembler: B special operand {x} only on B")
            return 1, ("s", self.bspecials.index(name))
        raise ValueError(f"Assembler: bad operand {x!r}")

    def _cond(self, cond):
        if cond is None:
            return 0, 0
        inv = cond.startswith("!")
        return self.conds.index(cond.lstrip("!")), int(inv)

    def emit(self, op, *, dst=None, a="k.0", b="k.0", sh=0, rnd=False, sat=SAT_NONE,
             setf=False, cond=None, neg=False, acc=False, asl=False, out=None, tgt=None):
        asp, a_ref = self._operand(a, "a")
        bsp, b_ref = self._operand(b, "b")
        c, inv = self._cond(cond)
        if dst is not None:
            if not dst.startswith("r."):
                raise ValueError(f"Assembler: destination must be a register, not {dst!r}")
            self.reg(dst[2:])
        fields = dict(op=int(op), wen=int(dst is not None), asp=asp, bsp=bsp, sh=sh, rnd=int(rnd),
                      sat=sat, setf=int(setf), cond=c, inv=inv, neg=int(neg), acc=int(acc),
                      asl=int(asl), out=self.outs.index(out) if out else 0)
        if op in ALU_OPS and a_ref in (("s", 0), ("s", 1)) and (
                b_ref != ("k", 0) or bsp or setf or asl or op != Op.ADD):
            raise ValueError("Assembler: an ALU operation on P or PQ must be ADD with B = 0, "
                             "no flags and no asl (P is read after the ALU)")
        self._instrs.append((fields, a_ref, b_ref, ("r", dst[2:]) if dst else None, tgt))
        return len(self._instrs) - 1

    def label(self, name):
        self._labels[name] = len(self._instrs)

    # --- mnemonics -------------------------------------------------------------------------------
    def alu(self, op, dst, a, b="k.0", **kw):
        return self.emit(op, dst=dst, a=a, b=b, **kw)

    def mul(self, a, b, **kw):
        return self.emit(Op.MUL, a=a, b=b, **kw)

    def mac(self, a, b, **kw):
        return self.emit(Op.MUL, a=a, b=b, acc=True, **kw)

    def post(self, dst, sh=0, *, rnd=True, sat=SAT_NONE, out=None):
        """``dst = sat(round_shift(P, sh))`` (``rnd``) or ``sat(P >> sh)``."""
        return self.emit(Op.ADD, dst=dst, a="s.P", b="k.0", sh=sh, rnd=rnd, sat=sat, out=out)

    def br(self, cond, label):
        return self.emit(Op.BR, cond=cond, tgt=label)

    def nop(self):
        return self.emit(Op.NOP)

    def end(self):
        return self.emit(Op.END)

    # --- output ----------------------------------------------------------------------------------
    def _fuse(self):
        """Peephole: a post (``Y = post(P)`` into a register) followed by a MUL that does not
        read that register becomes one MUL with the post fused (it sees the old P). Never across
        a label or inside branch delay slots."""
        instrs = self._instrs
        targets = set(self._labels.values())
        slots = set()
        for i, (f, *_rest) in enumerate(instrs):
            if f["op"] == Op.BR:
                slots.update((i + 1, i + 2))
        out, index = [], {}
        i = 0
        while i < len(instrs):
            index[i] = len(out)
            f, a_ref, b_ref, dst, tgt = instrs[i]
            if i + 1 < len(instrs) and i + 1 not in targets and not {i, i + 1} & slots:
                g, ga, gb, gdst, gtgt = instrs[i + 1]
                is_post = (f["op"] == Op.ADD and a_ref == ("s", 0) and f["asp"] and
                           b_ref == ("k", 0) and not f["bsp"] and not f["setf"] and
                           not f["asl"] and (dst is not None or f["out"]))
                reads = {ga if not g["asp"] else None, gb if not g["bsp"] else None}
                if is_post and g["op"] == Op.MUL and not g["wen"] and not g["out"] and \
                        (dst is None or dst not in reads):
                    merged = dict(g, wen=f["wen"], sh=f["sh"], rnd=f["rnd"], sat=f["sat"],
                                  out=f["out"])
                    out.append((merged, ga, gb, dst, gtgt))
                    index[i + 1] = len(out) - 1
                    i += 2
                    continue
            out.append(instrs[i])
            i += 1
        index[len(instrs)] = len(out)
        self._instrs = out
        self._labels = {k: index[v] for k, v in self._labels.items()}

    # --- hazards of the two-stage execute (write back one instruction late) --------------------
    def _needs(self, prev1, prev2, cur, prev3=None):
        """NOPs needed between ``prev1`` (the previous instruction) and ``cur``."""
        def info(entry):
            f, a_ref, b_ref, dst, _ = entry
            op = f["op"]
            writer = op in ALU_OPS or op == Op.MUL
            return {
                "reads": {r for r, sp, use in ((a_ref, f["asp"], writer),
                                               (b_ref, f["bsp"], writer or op == Op.DIV))
                          if use and not sp and r[0] == "r"},
                "writes": dst if (writer and f["wen"]) else None,
                "ang": writer and f["out"] == self.outs.index("ang"),
                "kd": f["asp"] and a_ref == ("s", self.specials.index("KD")) and writer,
                "fold": f["cond"] in (self.conds.index(c) for c in ("SWAP", "NEGC", "NEGS")),
                "table": f["asp"] and writer and a_ref in (("s", self.specials.index("TS")),
                                                           ("s", self.specials.index("TC"))),
            }
        c = info(cur)
        n = 0
        if prev1 is not None:
            p1 = info(prev1)
            if p1["writes"] is not None and p1["writes"] in c["reads"]:
                n = 1
        # ang written k instructions before: fold flags need k ≥ 2, KD k ≥ 3, the table k ≥ 4.
        for k, prev in ((1, prev1), (2, prev2), (3, prev3)):
            if prev is not None and info(prev)["ang"]:
                n = max(n, 2 - k if c["fold"] else 0, 3 - k if c["kd"] else 0,
                        4 - k if c["table"] else 0)
        return n

    def _insert_nops(self):
        instrs = self._instrs
        slots = {i + k for i, (f, *_r) in enumerate(instrs) if f["op"] == Op.BR for k in (1, 2)}
        out, index = [], {}
        nop = (dict(op=int(Op.NOP), wen=0, asp=0, bsp=0, sh=0, rnd=0, sat=0, setf=0, cond=0,
                    inv=0, neg=0, acc=0, asl=0, out=0), ("k", 0), ("k", 0), None, None)
        self.const(0)
        for i, entry in enumerate(instrs):
            prev1 = out[-1] if out else None
            prev2 = out[-2] if len(out) > 1 else None
            prev3 = out[-3] if len(out) > 2 else None
            n = self._needs(prev1, prev2, entry, prev3)
            if n:
                if i in slots:
                    raise ValueError(f"Assembler: hazard in a branch delay slot at {i}: "
                                     f"reorder by hand")
                out.extend([nop] * n)
            index[i] = len(out)
            out.append(entry)
        index[len(instrs)] = len(out)
        self._instrs = out
        self._labels = {k: index[v] for k, v in self._labels.items()}
        # Check every execution path (branch targets follow the second delay slot).
        errors = []

        def walk(queue, hist):
            queue = list(queue)
            while True:
                pc = queue.pop(0)
                if pc >= len(out):
                    return
                entry = out[pc]
                if self._needs(hist[-1], hist[-2], entry, hist[-3]):
                    errors.append(pc)
                    return
                hist = [hist[-2], hist[-1], entry]
                f = entry[0]
                if f["op"] == Op.END:
                    return
                nxt = queue[-1] + 1
                if f["op"] == Op.BR and not (f["cond"] == 0 and not f["inv"]):
                    walk(queue + [self._labels[entry[4]]], hist)
                    if f["cond"] == 0 and f["inv"]:
                        return
                queue.append(nxt)

        walk([0, 1, 2], [None, None, None])
        if errors:
            raise ValueError(f"Assembler: hazards on a branch path at {sorted(set(errors))}")

    def assemble(self, *, fuse=True):
        if fuse:
            self._fuse()
        self._insert_nops()
        regs = {}
        for name in self._regs:
            regs[name] = len(regs)
        consts = sorted(self._consts)
        if len(regs) + len(consts) > RF_DEPTH:
            raise ValueError(f"Assembler: {len(regs)} registers and {len(consts)} constants "
                             f"exceed the {RF_DEPTH}-word register file")
        kaddr = {v: RF_DEPTH - 1 - i for i, v in enumerate(consts)}
        rf_init = [0] * RF_DEPTH
        for v, addr in kaddr.items():
            if not -(1 << (WORD - 1)) <= v < (1 << (WORD - 1)):
                raise ValueError(f"Assembler: constant {v} does not fit {WORD} bits")
            rf_init[addr] = v

        def resolve(ref):
            kind, x = ref
            if kind == "r":
                return regs[x]
            if kind == "k":
                return kaddr[x]
            return x

        words = []
        for fields, a_ref, b_ref, dst, tgt in self._instrs:
            f = dict(fields)
            f["a"] = resolve(a_ref)
            f["b"] = resolve(b_ref)
            f["dst"] = resolve(dst) if dst else 0
            f["tgt"] = self._labels[tgt] if tgt is not None else 0
            words.append(Instr(**f).encode())
        if len(words) > 256:
            raise ValueError(f"Assembler: {len(words)} instructions exceed 256")
        symbols = dict(regs)
        symbols.update({f"k.{v}": a for v, a in kaddr.items()})
        return Program(words=words, rf_init=rf_init, regs=symbols, labels=dict(self._labels),
                       specials=self.specials, bspecials=self.bspecials, conds=self.conds,
                       outs=self.outs)


class Engine(wiring.Component):
    """The loop engine's datapath and sequencer (see the module docstring).

    Parameters
    ----------
    program : Program
        From :meth:`Assembler.assemble`.
    special_shapes : dict of str to Shape
        Shapes of the user special operands, in :attr:`Program.specials` order after the
        built-ins (the values are sign- or zero-extended to :data:`WORD`).
    out_widths : dict of str to int
        Widths of the output registers, in :attr:`Program.outs` order (1 = a flag: Y ≠ 0).
    width : int
        ``w`` of the saturation choices ``signed(w)``, ``signed(w + 1)``.
    guard : int
        Left shift of A by ``asl``.
    div_bits : int
        Quotient bits ``q`` of a DIV step (the low ``q`` bits of P are the special ``PQ``).
    rotator : RotatorParams
        Sine table, ``kd`` and angle folding (``ANG`` is ``rotator.angle_width`` bits).

    Members
    -------
    start : In(1)
        Start the program at address 0 (ignored while running).
    running : Out(1)
        The program runs (from the clock after ``start`` to its END).
    end : Out(1)
        One-clock strobe: END executed.
    <special> : In(shape)
        One port per user special operand.
    <cond> : In(1)
        One port per user condition.
    <out> : Out(width), <out>_we : Out(1)
        Output registers (held) and their one-clock write strobes.
    trace_* : Out
        Per-clock view of the instruction in X2, for the tests: ``trace_valid``,
        ``trace_pc``, ``trace_wen``, ``trace_dst``, ``trace_y`` (the value written back),
        ``trace_p`` (P before this instruction's update).
    """

    def __init__(self, *, program, special_shapes, out_widths, width=16, guard=8, div_bits=16,
                 rotator=None):
        if not isinstance(program, Program):
            raise TypeError(f"Engine program must be a Program, not {program!r}")
        user_specials = program.specials[len(BUILTIN_SPECIALS):]
        if tuple(special_shapes) != user_specials:
            raise ValueError(f"Engine special_shapes must name {user_specials}, "
                             f"not {tuple(special_shapes)}")
        if out_widths.get("ang") != (rotator or RotatorParams()).angle_width:
            raise ValueError("Engine out_widths must have \"ang\", the angle register, of the "
                             "rotator's angle_width")
        if tuple(out_widths) != program.outs[1:]:
            raise ValueError(f"Engine out_widths must name {program.outs[1:]}, "
                             f"not {tuple(out_widths)}")
        for name, value, lo, hi in (("width", width, 4, 32), ("guard", guard, 0, 16),
                                    ("div_bits", div_bits, 1, 24)):
            check_param("Engine", name, value, lo, hi)
        if rotator is None:
            rotator = RotatorParams(width=16, angle_width=16)
        self._program = program
        self._special_shapes = dict(special_shapes)
        self._out_widths = dict(out_widths)
        self._width = width
        self._guard = guard
        self._div_bits = div_bits
        self._rot = rotator
        members = {
            "start": In(1),
            "running": Out(1),
            "end": Out(1),
            "trace_valid": Out(1),
            "trace_pc": Out(8),
            "trace_wen": Out(1),
            "trace_dst": Out(7),
            "trace_y": Out(signed(WORD)),
            "trace_p": Out(signed(WORD)),
        }
        for name, shape in self._special_shapes.items():
            members[f"s_{name}"] = In(shape)
        for name in program.conds[len(BUILTIN_CONDS):]:
            members[f"c_{name}"] = In(1)
        for name, w in self._out_widths.items():
            members[f"o_{name}"] = Out(w)
            members[f"o_{name}_we"] = Out(1)
        super().__init__(members)

    program = property(lambda self: self._program)
    rotator = property(lambda self: self._rot)

    def elaborate(self, platform):
        m = Module()
        prog, rot = self._program, self._rot
        w, q = self._width, self._div_bits

        # --- Fetch, register read, execute ---------------------------------------------------------
        m.submodules.rom = rom = Memory(shape=INSTR_WIDTH, depth=max(len(prog.words), 2),
                                        init=prog.words)
        m.submodules.rf = rf = Memory(shape=signed(WORD), depth=RF_DEPTH, init=prog.rf_init)
        rf_w = rf.write_port()
        rf_a = rf.read_port(transparent_for=(rf_w,))
        rf_b = rf.read_port(transparent_for=(rf_w,))
        rom_r = rom.read_port()

        pc = Signal(8)
        f_valid = Signal()          # an instruction is being fetched (pc)
        r_valid = Signal()          # rom_r.data is an instruction in R
        x_valid = Signal()
        ir = data.View(INSTR_LAYOUT, Signal(INSTR_WIDTH))   # the instruction in X1
        ir2 = data.View(INSTR_LAYOUT, Signal(INSTR_WIDTH))  # the instruction in X2
        x2_valid = Signal()
        ir1 = data.View(INSTR_LAYOUT, rom_r.data)
        m.d.comb += [rom_r.addr.eq(pc), rf_a.addr.eq(ir1.a), rf_b.addr.eq(ir1.b)]
        m.d.sync += [ir.as_value().eq(rom_r.data), r_valid.eq(f_valid), x_valid.eq(r_valid)]

        # --- Angle register, sine table, kd, fold flags ----------------------------------------------
        aw, mb, n, ft = rot.angle_width, rot.interp_bits, rot.table_bits, rot.table_frac
        ang = self.o_ang                    # the output register named "ang"
        m.submodules.table = table = Memory(shape=2 * ft, depth=1 << n, init=rot.table_words)
        tab_r = table.read_port()
        quad = ang[aw - 2:]
        mu = ang[aw - 3]
        m.d.comb += tab_r.addr.eq(ang[mb:aw - 3] ^ Mux(mu, (1 << n) - 1, 0))
        kd_rom = [Const(v, unsigned(max(1, max(rot.kd_rom).bit_length()))) for v in rot.kd_rom]
        kd = Signal(unsigned(max(1, max(rot.kd_rom).bit_length())))
        with m.Switch(Cat(ang[:mb], mu)):
            for i, v in enumerate(kd_rom):
                with m.Case(i):
                    m.d.comb += kd.eq(v)
        ts = tab_r.data[:ft].as_signed()
        tc = tab_r.data[ft:].as_signed()

        # --- Operands --------------------------------------------------------------------------------
        p = Signal(signed(WORD))
        # P and PQ are read in X2 (below), not through this mux.
        specials = [Const(0), Const(0), ts, tc, kd] + [getattr(self, f"s_{name}")
                                          for name in self._special_shapes]
        # The special operands are selected in R (registered with the RF read).
        spec = Signal(signed(WORD))
        with m.Switch(ir1.a):
            for i, v in enumerate(specials):
                with m.Case(i):
                    m.d.sync += spec.eq(v)
        a_raw = Mux(ir.asp, spec, rf_a.data)
        a = Signal(signed(WORD))
        m.d.comb += a.eq(Mux(ir.asl, a_raw << self._guard, a_raw))
        bspec = Signal(signed(WORD))
        with m.Switch(ir1.b):
            for i, name in enumerate(prog.bspecials):
                with m.Case(i):
                    m.d.sync += bspec.eq(getattr(self, f"s_{name}"))
        b = Signal(signed(WORD))
        m.d.comb += b.eq(Mux(ir.bsp, bspec, rf_b.data))

        flag_n = Signal()
        flag_z = Signal()
        conds = [Const(0), flag_n, flag_z, flag_n | flag_z, quad[0] ^ mu, quad[0] ^ quad[1],
                 quad[1]] + [getattr(self, f"c_{name}") for name in prog.conds[len(BUILTIN_CONDS):]]
        cond_raw = Signal()
        with m.Switch(ir.cond):
            for i, v in enumerate(conds):
                with m.Case(i):
                    m.d.comb += cond_raw.eq(v)
        c = cond_raw ^ ir.inv

        # --- ALU ---------------------------------------------------------------------------------
        is_add = ir.op == Op.ADD
        is_rsub = ir.op == Op.RSUB
        s = Signal(signed(WORD + 1))
        # One adder: A + B, A + ~B + 1 (A − B) or ~A + B + 1 (B − A).
        inv_b = ~is_add & ~is_rsub
        m.d.comb += s.eq(Mux(is_rsub, ~a, a) + Mux(inv_b, ~b, b) + ~is_add)
        ge = ~s[-1]
        le = s[-1] | (s == 0)
        x = Signal(signed(WORD + 1))
        with m.Switch(ir.op):
            with m.Case(Op.MIN):
                m.d.comb += x.eq(Mux(c | ge, b, a))
            with m.Case(Op.MAX):
                m.d.comb += x.eq(Mux(c | le, b, a))
            with m.Case(Op.SEL):
                m.d.comb += x.eq(Mux(c, b, a))
            with m.Default():
                m.d.comb += x.eq(s)
        # --- X2: post (shift, rounded half away from zero or floor; saturate), write back ------
        x2 = Signal(signed(WORD + 1))
        x2_nz = Signal()                        # 1-bit outputs take X ≠ 0, known in X1
        m.d.sync += [x2.eq(x), x2_nz.eq(x != 0), ir2.as_value().eq(ir.as_value())]
        # P is read in X2 only (MUL and DIV update it at the end of X2): by a MUL's fused post
        # and by an ALU operation whose A is P or PQ (B ignored).
        xp = Signal(signed(WORD + 1))
        with m.If(ir2.op == Op.MUL):
            m.d.comb += xp.eq(p)
        with m.Elif(ir2.asp & (ir2.a == 0)):
            m.d.comb += xp.eq(p)
        with m.Elif(ir2.asp & (ir2.a == 1)):
            m.d.comb += xp.eq(p[:q])
        with m.Else():
            m.d.comb += xp.eq(x2)
        # Rounding constant 2**(sh−1) (− 1 for negative X), prepared in X1: no carry chain
        # in front of the rounding adder.
        h_one = Signal(unsigned(WORD))
        h_mask = Signal(unsigned(WORD))
        rounding = ir.rnd & (ir.sh != 0)
        m.d.sync += [h_one.eq(Mux(rounding, (Const(1, unsigned(WORD)) << ir.sh)[1:], 0)),
                     h_mask.eq(Mux(rounding, (Const(1, unsigned(WORD)) << ir.sh)[1:] - 1, 0))]
        half = Signal(signed(WORD + 1))
        m.d.comb += half.eq(Mux(xp[-1], h_mask, h_one))
        shifted = Signal(signed(WORD + 2))
        m.d.comb += shifted.eq((xp + half) >> ir2.sh)
        y = Signal(signed(WORD))
        with m.Switch(ir2.sat):
            for code, sw in ((SAT_W, w), (SAT_W1, w + 1)):
                with m.Case(code):
                    lo, hi = -(1 << (sw - 1)), (1 << (sw - 1)) - 1
                    top = shifted[sw - 1:]          # fits signed(sw): these bits all equal
                    m.d.comb += y.eq(Mux(top.all() | ~top.any(), shifted,
                                         Mux(shifted[-1], lo, hi)))
            with m.Default():
                m.d.comb += y.eq(shifted)

        # --- Multiplier, divider step ----------------------------------------------------------
        # Operands registered at the end of X1; product and P update in X2.
        ma = Signal(signed(MUL_A))
        mb = Signal(signed(MUL_B))
        m_neg = Signal()
        m.d.sync += [ma.eq(a[:MUL_A]), mb.eq(b[:MUL_B]), m_neg.eq(ir.neg ^ c)]
        prod = Signal(signed(MUL_A + MUL_B))
        m.d.comb += prod.eq(ma * mb)
        t2 = Signal(signed(WORD + 1))
        m.d.comb += t2.eq(p << 1)
        div_diff = Signal(signed(WORD + 1))
        m.d.comb += div_diff.eq((t2 >> q) - mb)
        div_ge = ~div_diff[-1]

        is_alu = (ir.op == Op.ADD) | (ir.op == Op.SUB) | (ir.op == Op.RSUB) | \
            (ir.op == Op.MIN) | (ir.op == Op.MAX) | (ir.op == Op.SEL)
        execute = x_valid & self.running
        m.d.sync += x2_valid.eq(execute)
        writes2 = x2_valid & ((ir2.op == Op.ADD) | (ir2.op == Op.SUB) | (ir2.op == Op.RSUB) |
                              (ir2.op == Op.MIN) | (ir2.op == Op.MAX) | (ir2.op == Op.SEL) |
                              (ir2.op == Op.MUL))
        m.d.comb += [
            rf_w.addr.eq(ir2.dst),
            rf_w.data.eq(y),
            rf_w.en.eq(writes2 & ir2.wen),
            self.trace_valid.eq(x2_valid),
            self.trace_wen.eq(rf_w.en),
            self.trace_dst.eq(ir2.dst),
            self.trace_y.eq(y),
            self.trace_p.eq(p),
        ]
        x_pc = Signal(8)
        r_pc = Signal(8)
        x2_pc = Signal(8)
        m.d.sync += [r_pc.eq(pc), x_pc.eq(r_pc), x2_pc.eq(x_pc)]
        m.d.comb += self.trace_pc.eq(x2_pc)

        # Outputs (written in X2, like the register file).
        for i, (name, ow) in enumerate(self._out_widths.items(), start=1):
            reg = getattr(self, f"o_{name}")
            we = getattr(self, f"o_{name}_we")
            m.d.comb += we.eq(writes2 & (ir2.out == i))
            with m.If(we):
                m.d.sync += reg.eq(x2_nz if ow == 1 else y[:ow])

        with m.If(execute):
            with m.If(is_alu & ir.setf):
                m.d.sync += [flag_n.eq(s[-1]), flag_z.eq(s == 0)]
        with m.If(x2_valid & (ir2.op == Op.MUL)):
            # P ± prod: one adder, the carry-in negates.
            m.d.sync += p.eq(Mux(ir2.acc, p, 0) + Mux(m_neg, ~prod, prod) + m_neg)
        with m.If(x2_valid & (ir2.op == Op.DIV)):
            m.d.sync += p.eq(Mux(div_ge, Cat(Const(1, 1), t2[1:q], div_diff), t2))

        # --- Sequencer -------------------------------------------------------------------------
        m.d.comb += self.end.eq(execute & (ir.op == Op.END))
        with m.If(self.start & ~self.running):
            m.d.sync += [self.running.eq(1), pc.eq(0), f_valid.eq(1),
                         r_valid.eq(0), x_valid.eq(0)]
        with m.Elif(self.end):
            m.d.sync += [self.running.eq(0), f_valid.eq(0), r_valid.eq(0), x_valid.eq(0)]
        with m.Elif(self.running):
            with m.If(execute & (ir.op == Op.BR) & c):
                m.d.sync += pc.eq(ir.tgt)
            with m.Else():
                m.d.sync += pc.eq(pc + 1)
        return m
