# Ref: AREA.md §4 "Stage 2: one micro-sequenced datapath"; docs/ENGINE.md (ISA, pipeline); issue 7
"""The loop engine: a micro-sequenced, single-issue datapath with one multiplier, a 32-bit ALU
(:data:`WORD`; the product register ``P`` and the post path :data:`P_WORD` = 45 bits), a
block-RAM register file, the rotator's sine table and a program ROM.

The instruction set, the encoding and a tiny assembler (:class:`Assembler`) are defined here and
shared by the gateware (:class:`Engine`) and the bit-true interpreter
(:class:`foc_servo.sim.models.engine.EngineModel`), so that the two cannot disagree on a field.
docs/ENGINE.md has the rationale; the semantics of one instruction (``A``, ``B`` its operands,
``c`` its condition, ``P`` the product register, ``Y`` the post-processed result)::

    A   = SPECIAL[a] if asp else RF[a];  A <<= guard if asl   (asl: special A only;
                                                              A = P or PQ: ADD with B = 0 only)
    B   = SPECIAL[BSPECIALS[b]] if bsp else RF[b]
    c   = COND[cond] ^ inv
    ADD  X = A + B        SUB  X = A − B        RSUB X = B − A        (flags N, Z of X)
    MIN  X = B if (c or A − B ≥ 0) else A      MAX  X = B if (c or A − B ≤ 0) else A
    SEL  X = B if c else A                     (flags of MIN, MAX, SEL: N, Z of A − B)
    Y    = sat(round_shift(X, sh) if rnd else X >> sh)   sat: none, signed(w) or signed(w + 1)
           (rnd: not with MIN, MAX, SEL: the assembler refuses it, the gateware ignores it)
           → RF[dst] if wen; → output register ``out`` (1-bit outputs take X ≠ 0, from an
           ALU operation with sh = 0 whose A is not P: :func:`check_flag_outputs`)
    MUL  P = (P if acc else 0) + (−1 if neg ^ c else 1) · A[:mul_a] · B[:mul_b]; and, fused,
         Y from X = P (the old P: the previous product, post-processed) → RF[dst] / out
    DIV  one restoring step: T = 2P; if T >> q ≥ B: T = T − B·2**q + 1; P = T   (q = div_bits;
         A is the constant 1: B reaches X3 as the product 1·B),
         sh + 1 times (one step per clock: the word is held in R, the fetch stalls)
    BR   if c: jump to tgt after the two delay-slot instructions
    END  o.valid, halt
    nb   (every op but DIV) nb = 0 … 3 bubbles after the instruction: clocks in which nothing is
         issued (the fetch holds the word in R, as a DIV's repeats): folded NOPs
         (:meth:`Assembler._fold`; the delay slots of a branch are the two clocks after it)

Pipeline (one instruction per clock, no stalls): F (program ROM addressed by ``pc``; beside each
instruction the key of its special operand), R (operand RF read; the special operand selected,
shifted by ``asl``, or the value written back in this clock to the register read, registered;
adder mode, condition and result select decoded and registered), X1 (operand select,
carry-select ALU adder, flags, branch; MUL and DIV operands, the rounding constant, the sum,
A and B registered as they are), X2 (SEL/MIN/MAX choice beside the rounding adder, P read,
rounding add; the product registered), X3 (barrel shift and the saturation test's high part
registered; P update: ± product, DIV step), X4 (the saturation test's low part and select,
write back to the RF and the output registers). Hence: a register written by instruction i is
seen from instruction
i + 4 on (``HAZARD_RF`` = ``WRITE_DELAY`` + 1; the assembler schedules straight-line code to
fill the gap, inserts NOPs where it cannot, and checks every branch path); flags behave
sequentially; P is written in X3, read there by MAC and DIV (sequentially) but read in X2 by
a post (an ALU operation on P or PQ, an ADD with B = 0, or a MUL's fused post): a post sees
the P of instruction i from i + 2 on (``HAZARD_P``). A branch resolves in X1: the two
instructions behind it (the delay slots) always execute. The angle register ``ang`` (an
output, written in X4) addresses the sine table: after instruction i writes ``ang``, the fold
flags are valid from i + 4, ``KD`` from i + 5, the table words ``TS``, ``TC`` from i + 6 (the
special operands are selected and registered in R).
"""

import dataclasses
import enum

from amaranth.hdl import Cat, Const, Module, Mux, Shape, Signal, Value, signed, unsigned
from amaranth.lib import data, wiring
from amaranth.lib.memory import Memory
from amaranth.lib.wiring import In, Out

from .bus import WordWriteSignature
from .fixed import check_param
from .rotator import RotatorParams

__all__ = ["Op", "FIELDS", "Instr", "Fetch", "Assembler", "Program", "Engine", "WORD", "P_WORD",
           "MUL_A", "MUL_B", "MAX_BUBBLES", "TGT_LO",
           "RF_DEPTH", "PC_WIDTH", "HAZARD_P", "HAZARD_RF", "HAZARD_FOLD", "HAZARD_KD",
           "HAZARD_TABLE", "WRITE_DELAY",
           "BUILTIN_SPECIALS", "BUILTIN_CONDS", "SAT_NONE", "SAT_W", "SAT_W1",
           "check_flag_outputs"]

#: Width of the register-file words and of the X1 ALU's operands (its sum has ``WORD + 1``
#: bits). The current-loop program's widest register value is the PI's ``kp·E`` (``kp`` UQ(16, 8),
#: ``E`` signed(16): ``|kp·E| < 2**31``), every other ≤ 28 bits; the interpreter raises on a
#: write that does not fit.
WORD = 32
#: Width of the product register ``P`` and of the X2 post path (rounding add, shift,
#: saturation, on ``P_WORD + 1`` bits): the over-modulation division's partial remainder
#: ``2·P < 2**28 · 2**16`` needs 45 bits.
P_WORD = 45
#: Signed widths of the multiplier operands (A, B).
MUL_A, MUL_B = 19, 28
#: Register-file words.
RF_DEPTH = 128
#: Execute stages after X1 (X2, X3, X4): an instruction writes back this many clocks after its
#: X1. The hazard distances follow from it: the register file is read (transparently) in R, the
#: fold flags in X1, ``KD`` is selected in R from the angle register, the table words one
#: clock later (the table's read port is registered).
WRITE_DELAY = 3
HAZARD_RF = WRITE_DELAY + 1
HAZARD_FOLD = WRITE_DELAY + 1
HAZARD_KD = WRITE_DELAY + 2
HAZARD_TABLE = WRITE_DELAY + 3
#: P is written (MUL, DIV) at the end of X3 and read there by MAC and DIV (sequentially), but
#: read in X2 by a post (an ALU operation on P or PQ, or a MUL's fused post): a post sees the
#: P of instruction i from i + HAZARD_P on.
HAZARD_P = 2
#: (Hazard distances, in instructions from the writer: a register written by instruction i is
#: read correctly from i + HAZARD_RF on; after a write of the angle register ``ang``, the fold
#: flags are valid from i + HAZARD_FOLD, ``KD`` from i + HAZARD_KD, the table words ``TS``,
#: ``TC`` from i + HAZARD_TABLE.)
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

#: Width of the program counter and of branch targets (programs of up to 2**PC_WIDTH words).
PC_WIDTH = 9

#: Instruction fields, in bit order (name, width). ``nb``: the bubbles after the instruction
#: (NOP folding: clocks in which nothing is issued, ``pc`` and the ROM held; every op but DIV,
#: whose ``sh`` counts its repeats), then 7 spare bits (0). A BR's target (``tgt``,
#: ``PC_WIDTH`` bits) is not a field of its own: it lies in the bits of ``sh``, ``rnd``, ``sat``
#: and ``setf`` (:data:`TGT_LO`), which a BR does not use, so that ``nb`` is in the same bits
#: for every op (one LUT level for the fetch's hold).
FIELDS = (("op", 4), ("wen", 1), ("dst", 7), ("asp", 1), ("a", 7), ("bsp", 1), ("b", 7), ("sh", 5),
          ("rnd", 1), ("sat", 2), ("setf", 1), ("cond", 4), ("inv", 1), ("neg", 1), ("acc", 1),
          ("asl", 1), ("out", 5), ("nb", 2), ("spare", PC_WIDTH - 2))
INSTR_LAYOUT = data.StructLayout({name: unsigned(width) for name, width in FIELDS})
INSTR_WIDTH = sum(w for _, w in FIELDS)
#: First bit of a BR's target (the bits of ``sh``, ``rnd``, ``sat``, ``setf``).
TGT_LO = sum(w for name, w in FIELDS[:[n for n, _ in FIELDS].index("sh")])
#: The fields a BR's target overlays.
TGT_FIELDS = ("sh", "rnd", "sat", "setf")
assert sum(dict(FIELDS)[n] for n in TGT_FIELDS) == PC_WIDTH
#: Most bubbles one word carries (``nb``: 2 bits).
MAX_BUBBLES = (1 << dict(FIELDS)["nb"]) - 1

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
    nb: int = 0
    tgt: int = 0

    @property
    def extra(self):
        """Clocks the fetch holds this word in R after its first issue: a DIV's repeats
        (``sh``, each issued), else its bubbles (``nb``, nothing issued)."""
        return self.sh if self.op == Op.DIV else self.nb

    @property
    def clocks(self):
        """Clocks of the execute stage this word takes: 1 + :attr:`extra`."""
        return 1 + self.extra

    def encode(self):
        word, pos = 0, 0
        for name, width in FIELDS:
            v = 0 if name == "spare" else int(getattr(self, name))
            if not 0 <= v < (1 << width):
                raise ValueError(f"Instruction field {name} must be from 0 to {(1 << width) - 1}, "
                                 f"not {v}")
            word |= v << pos
            pos += width
        if self.op == Op.BR:
            if any(getattr(self, name) for name in TGT_FIELDS):
                raise ValueError(f"Instruction: a BR's {', '.join(TGT_FIELDS)} must be 0 (its "
                                 f"target lies in their bits)")
            if not 0 <= int(self.tgt) < (1 << PC_WIDTH):
                raise ValueError(f"Instruction field tgt must be from 0 to "
                                 f"{(1 << PC_WIDTH) - 1}, not {self.tgt}")
            word |= int(self.tgt) << TGT_LO
        elif self.tgt:
            raise ValueError(f"Instruction: tgt only with BR, not with {Op(self.op).name}")
        return word

    @classmethod
    def decode(cls, word):
        values, pos = {}, 0
        for name, width in FIELDS:
            values[name] = (word >> pos) & ((1 << width) - 1)
            pos += width
        del values["spare"]
        if values["op"] == Op.BR:
            values["tgt"] = (word >> TGT_LO) & ((1 << PC_WIDTH) - 1)
            values.update({name: 0 for name in TGT_FIELDS})
        return cls(**values)


class Fetch:
    """The engine's F and R stages as the gateware sequences them, clock by clock: what R
    issues into X1 and how ``pc`` and R's word move on, for the interpreter
    (:class:`~foc_servo.sim.models.engine.EngineModel`) and the timing helpers
    (``hdl.foc_engine._paths``). R holds a word for :attr:`Instr.extra` clocks after its
    first issue (``pc`` and the ROM held): a DIV is issued again in each, any other word
    leaves a bubble (nothing issued). A branch taken in X1 loads ``pc`` with its target, so
    its delay slots are the clocks R fills meanwhile: the word behind it (with its repeats or
    bubbles) and, if that word is not held, the next one.

    Parameters
    ----------
    instrs : list of Instr
    start : int
        The first word (in R in the clock before its first X1).
    """

    def __init__(self, instrs, start):
        self.instrs = instrs
        self.r, self.rep, self.pc = start, 0, start + 1

    def copy(self):
        f = Fetch.__new__(Fetch)
        f.instrs, f.r, f.rep, f.pc = self.instrs, self.r, self.rep, self.pc
        return f

    def issue(self):
        """What R issues into X1 in the next clock: ``(address, rep, bubble)`` (``rep``: the
        clocks R has held the word before; ``bubble``: nothing is issued)."""
        return self.r, self.rep, bool(self.rep) and self.instrs[self.r].op != Op.DIV

    def step(self, target=None):
        """One clock; ``target``: the target of a branch taken in X1 in this clock."""
        hold = self.rep != self.instrs[self.r].extra
        pc = target if target is not None else (self.pc if hold else self.pc + 1)
        self.r, self.rep = (self.r, self.rep + 1) if hold else (self.pc, 0)
        self.pc = pc


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
        self._reg_init = {}
        self._consts = {}
        self._labels = {}
        self._fixups = []

    # --- operands ------------------------------------------------------------------------------
    def reg(self, name, *, init=None):
        """The register ``name`` (allocated on first use); ``init``: its value at power-up (the
        register file's initial contents; 0 otherwise). A register file in block RAM is not
        reset: the value holds after a reset only until the program writes the register."""
        if name not in self._regs:
            self._regs[name] = len(self._regs)
        if init is not None:
            init = int(init)
            if not -(1 << (WORD - 1)) <= init < (1 << (WORD - 1)):
                raise ValueError(f"Assembler: initial value {init} of r.{name} does not fit "
                                 f"{WORD} bits")
            self._reg_init[name] = init
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
        if op == Op.DIV:
            # The divisor reaches X3 as the product 1·B (no register of its own).
            if a not in ("k.0", "k.1", 1):
                raise ValueError(f"Assembler: DIV takes no operand A (it is the constant 1), "
                                 f"not {a!r}")
            a = 1
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
        if rnd and sh and op in (Op.MIN, Op.MAX, Op.SEL):
            raise ValueError("Assembler: rnd only with ADD, SUB, RSUB and the posts, not with "
                             "MIN, MAX or SEL")
        if asl and not asp:
            raise ValueError("Assembler: asl takes a special operand A only (it is shifted in "
                             "the R stage)")
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

    def div(self, b, steps=1):
        """``steps`` restoring DIV steps (1 … 32) with divisor ``b``, in one word (its ``sh``
        field holds ``steps − 1``: the engine repeats it, one step per clock). Not in a branch
        delay slot."""
        if not isinstance(steps, int) or not 1 <= steps <= 32:
            raise ValueError(f"Assembler: DIV steps must be from 1 to 32, not {steps!r}")
        return self.emit(Op.DIV, b=b, sh=steps - 1)

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

    # --- list scheduling of straight-line code ----------------------------------------------------
    def _effects(self, entry):
        """What one instruction reads and writes, for :meth:`_schedule`: sets of resources
        (``("r", name)`` registers, ``"flags"``, ``"P"``, ``"ang"``, ``("out", n)``)."""
        f, a_ref, b_ref, dst, _ = entry
        op = f["op"]
        writer = op in ALU_OPS or op == Op.MUL
        reads, writes = set(), set()
        for ref, sp, use in ((a_ref, f["asp"], writer), (b_ref, f["bsp"], writer or op == Op.DIV)):
            if use and not sp and ref[0] == "r":
                reads.add(ref)
        if writer and f["asp"] and a_ref in (("s", 0), ("s", 1)):
            reads.add("P")                                      # a post of P or PQ
        if writer and f["asp"] and a_ref in (("s", self.specials.index(n))
                                             for n in ("TS", "TC", "KD")):
            reads.add("ang")
        cond = self.conds[f["cond"]] if f["cond"] < len(self.conds) else None
        if cond in ("N", "Z", "LE"):
            reads.add("flags")
        if cond in ("SWAP", "NEGC", "NEGS"):
            reads.add("ang")
        if op == Op.MUL:
            writes.add("P")
            if f["acc"] or f["wen"] or f["out"]:
                reads.add("P")                                  # MAC, or a fused post
        if op == Op.DIV:
            reads.add("P")
            writes.add("P")
        if op in ALU_OPS and f["setf"]:
            writes.add("flags")
        if writer and f["wen"]:
            writes.add(dst)
        if writer and f["out"]:
            writes.add(("out", f["out"]))
            if f["out"] == self.outs.index("ang"):
                writes.add("ang")
        return reads, writes

    def _schedule(self):
        """Reorder each straight-line region (between labels, branches with their two delay
        slots and ENDs, which stay in place) by list scheduling: every dependence (a register,
        the flags, P, the angle register; read after write, write after read, write after write)
        keeps its order; writes of the output registers keep theirs (the outside sees them in
        program order); among the instructions free to go, the one needing the fewest NOPs
        (:meth:`_needs`, given what was placed before it) goes first, then the one heading the
        longest dependence chain, then program order."""
        instrs = self._instrs
        fixed = set(self._labels.values())      # region starts
        pinned = set()
        for i, (f, *_r) in enumerate(instrs):
            if f["op"] in (Op.BR, Op.END):
                pinned.update((i, i + 1, i + 2) if f["op"] == Op.BR else (i,))
        out = []
        i = 0
        while i < len(instrs):
            if i in pinned:
                out.append(instrs[i])
                i += 1
                continue
            j = i + 1
            while j < len(instrs) and j not in pinned and j not in fixed:
                j += 1
            out.extend(self._schedule_region(instrs[i:j], out))
            i = j
        self._instrs = out

    def _schedule_region(self, region, before):
        n = len(region)
        eff = [self._effects(e) for e in region]
        preds = [set() for _ in range(n)]
        for i in range(n):
            ri, wi = eff[i]
            for j in range(i):
                rj, wj = eff[j]
                if (ri & wj) or (wi & rj) or (wi & wj):
                    preds[i].add(j)
        # Longest chain of dependences from each instruction (weighted by the RF distance
        # where a register is passed on).
        height = [0] * n
        for i in reversed(range(n)):
            for k in range(i + 1, n):
                if i in preds[k]:
                    regs = {r for r in eff[i][1] & eff[k][0] if isinstance(r, tuple) and
                            r[0] == "r"}
                    gap = HAZARD_RF if regs else (HAZARD_P if "P" in eff[i][1] & eff[k][0]
                                                  else 1)
                    height[i] = max(height[i], height[k] + gap)
        seq = list(before[-HAZARD_TABLE:])
        done, order = set(), []
        while len(order) < n:
            best = None
            for i in range(n):
                if i in done or not preds[i] <= done:
                    continue
                key = (self._needs(seq, region[i]), -height[i], i)
                if best is None or key < best:
                    best = key
            nops, _, i = best
            seq.extend([None] * nops)
            seq.append(region[i])
            done.add(i)
            order.append(region[i])
        return order

    # --- hazards of the four-stage execute (write back three instructions late) ------------------
    def _needs(self, hist, cur):
        """NOPs needed in front of ``cur``; ``hist`` holds the instructions before it, the
        latest last (``None`` for none)."""
        def info(entry):
            f, a_ref, b_ref, dst, _ = entry
            op = f["op"]
            writer = op in ALU_OPS or op == Op.MUL
            return {
                "reads": {r for r, sp, use in ((a_ref, f["asp"], writer),
                                               (b_ref, f["bsp"], writer or op == Op.DIV))
                          if use and not sp and r[0] == "r"},
                "writes": dst if (writer and f["wen"]) else None,
                "pw": op in (Op.MUL, Op.DIV),
                "pr": (op in ALU_OPS and f["asp"] and a_ref in (("s", 0), ("s", 1))) or
                      (op == Op.MUL and bool(f["wen"] or f["out"])),
                "ang": writer and f["out"] == self.outs.index("ang"),
                "kd": f["asp"] and a_ref == ("s", self.specials.index("KD")) and writer,
                "fold": f["cond"] in (self.conds.index(c) for c in ("SWAP", "NEGC", "NEGS")),
                "table": f["asp"] and writer and a_ref in (("s", self.specials.index("TS")),
                                                           ("s", self.specials.index("TC"))),
            }
        c = info(cur)
        n = 0
        for k in range(1, HAZARD_TABLE):
            if k > len(hist):
                break
            if hist[-k] is None:                                # a NOP
                continue
            p = info(hist[-k])
            # A register written k instructions before is read from k ≥ HAZARD_RF on; after
            # a write of ang: fold flags k ≥ HAZARD_FOLD, KD k ≥ HAZARD_KD, the table
            # k ≥ HAZARD_TABLE.
            if p["writes"] is not None and p["writes"] in c["reads"]:
                n = max(n, HAZARD_RF - k)
            if p["pw"] and c["pr"]:
                n = max(n, HAZARD_P - k)
            if p["ang"]:
                n = max(n, HAZARD_FOLD - k if c["fold"] else 0,
                        HAZARD_KD - k if c["kd"] else 0, HAZARD_TABLE - k if c["table"] else 0)
        return n

    def _insert_nops(self):
        instrs = self._instrs
        slots = {i + k for i, (f, *_r) in enumerate(instrs) if f["op"] == Op.BR for k in (1, 2)}
        out, index = [], {}
        nop = (dict(op=int(Op.NOP), wen=0, asp=0, bsp=0, sh=0, rnd=0, sat=0, setf=0, cond=0,
                    inv=0, neg=0, acc=0, asl=0, out=0), ("k", 0), ("k", 0), None, None)
        self.const(0)
        for i, entry in enumerate(instrs):
            if i in slots and entry[0]["op"] == Op.DIV and entry[0]["sh"]:
                raise ValueError(f"Assembler: a repeated DIV in a branch delay slot at {i}")
            n = self._needs(out, entry)
            if entry[0]["op"] == Op.BR and i + 2 < len(instrs):
                # Where a delay slot would need NOPs, they go in front of the branch.
                hist = out + [None] * n + [entry]
                n += max(self._needs(hist, instrs[i + 1]),
                         self._needs(hist + [instrs[i + 1]], instrs[i + 2]))
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
        # Every execution path (a branch target follows the second delay slot): where a path
        # still has a hazard (at a branch target), a NOP goes in front of it (the label then
        # points to the NOP, so both paths execute it); repeated until no path has one.
        for _ in range(HAZARD_TABLE * len(out) + 1):
            errors = self._path_hazards()
            if not errors:
                return
            pc = min(errors)
            out = self._instrs
            slots = {i + k for i, (f, *_r) in enumerate(out) if f["op"] == Op.BR
                     for k in (1, 2)}
            if pc in slots:
                raise ValueError(f"Assembler: hazard in a branch delay slot at {pc} on a branch "
                                 f"path: reorder by hand")
            out.insert(pc, nop)
            self._labels = {k: v + 1 if v > pc else v for k, v in self._labels.items()}
        raise ValueError("Assembler: hazards on a branch path do not converge")  # pragma: no cover

    def _path_hazards(self):
        """Addresses where an execution path meets a hazard (the first on each path)."""
        out = self._instrs
        errors = []

        def walk(queue, hist):
            queue = list(queue)
            while True:
                pc = queue.pop(0)
                if pc >= len(out):
                    return
                entry = out[pc]
                if self._needs(hist, entry):
                    errors.append(pc)
                    return
                hist = hist[1:] + [entry]
                f = entry[0]
                if f["op"] == Op.END:
                    return
                nxt = queue[-1] + 1
                if f["op"] == Op.BR and not (f["cond"] == 0 and not f["inv"]):
                    walk(queue + [self._labels[entry[4]]], hist)
                    if f["cond"] == 0 and f["inv"]:
                        return
                queue.append(nxt)

        walk([0, 1, 2], [None] * (HAZARD_TABLE - 1))
        return sorted(set(errors))

    def _fold(self):
        """NOP folding: a NOP that every path executing the word before it executes right
        after that word becomes a bubble of it (``nb``, at most :data:`MAX_BUBBLES`; the fetch
        holds the word in R that many clocks, issuing nothing), so the program takes the same
        clocks on every path in fewer words. A NOP is folded into the word before it (or into
        that word's host, when that word is a folded NOP) unless it is a label (a branch target
        or an entry: a path may reach it without the word before), the word before it is a
        branch's second delay slot (the NOP is then on the fall-through path only: a bubble
        there would be on the branch path too) or an END (after which nothing executes), or
        the host is a DIV (its ``sh`` counts repeats) or an END, or the host has
        :data:`MAX_BUBBLES` already (the NOP then stays, a host itself). A branch may be a host
        (its delay-slot NOPs become its bubbles: the fetch model, :class:`Fetch`)."""
        instrs = self._instrs
        labels = set(self._labels.values())
        slot2 = {i + 2 for i, (f, *_r) in enumerate(instrs) if f["op"] == Op.BR}
        out, index = [], {}
        for i, entry in enumerate(instrs):
            if (entry[0]["op"] == Op.NOP and out and i not in labels and i - 1 not in slot2
                    and instrs[i - 1][0]["op"] != Op.END):
                hf, *rest = out[-1]
                if hf["op"] not in (Op.DIV, Op.END) and hf.get("nb", 0) < MAX_BUBBLES:
                    out[-1] = (dict(hf, nb=hf.get("nb", 0) + 1), *rest)
                    continue
            index[i] = len(out)
            out.append(entry)
        index[len(instrs)] = len(out)
        self._instrs = out
        self._labels = {k: index[v] for k, v in self._labels.items()}

    # --- register reuse on the final instruction order --------------------------------------------
    def _entries(self):
        """Addresses a run may start at: 0 and every label no branch targets."""
        targets = {self._labels[e[4]] for e in self._instrs if e[0]["op"] == Op.BR}
        return sorted({0} | {v for v in self._labels.values() if v not in targets})

    def _issue_paths(self, start):
        """Every path from ``start`` to its END (or the last word) on the final instruction
        order, as the fetch (:class:`Fetch`) sequences it: one list per path of ``(clock,
        address)`` for each clock in which R issues an instruction into X1 (a DIV once per
        repeat; bubbles issue nothing but take their clock). Each branch taken or not (no
        loops)."""
        instrs = [Instr(**dict(f, a=0, b=0, dst=0, nb=f.get("nb", 0),
                               tgt=self._labels[tgt] if tgt is not None else 0))
                  for f, _a, _b, _d, tgt in self._instrs]
        paths = []
        stack = [(Fetch(instrs, start), 0, [])]
        while stack:
            fetch, t, trail = stack.pop()
            while True:
                pc, rep, bubble = fetch.issue()
                ins = instrs[pc]
                if not bubble:
                    trail.append((t, pc))
                if not rep and ins.op == Op.END:
                    paths.append(trail)
                    break
                if not rep and ins.op == Op.BR and not (ins.cond == 0 and not ins.inv):
                    taken = fetch.copy()
                    taken.step(ins.tgt)
                    stack.append((taken, t + 1, list(trail)))
                    if ins.cond == 0 and ins.inv:           # always taken
                        break
                fetch.step()
                t += 1
                if fetch.r >= len(instrs):              # no END: the path ends there
                    paths.append(trail)
                    break
        return paths

    def _realloc(self, keep=()):
        """Register reuse after scheduling, NOP insertion and folding (the order is final: no
        instruction moves). Over every path from every entry (:meth:`_entries`,
        :meth:`_issue_paths`), with the pipeline's clocks: an instruction issued into X1 in
        clock t reads its register operands in R, clock t − 1 (the value written back in that
        clock bypassed), and writes back in X4, clock t + :data:`WRITE_DELAY`. A read sees the
        latest write back at or before its clock on the path; a register read on some path
        before any write on it (the state kept between runs), one with an initial value and
        one in ``keep`` keeps a word of its own; every other one (a temporary) is live, after
        each write back W, in the clocks (W, R] up to the last read R that sees it. Two
        temporaries interfere if one is written back in a clock where the other is live, on
        some path; they are coloured greedily (first use first, lowest word first) after the
        kept words. Returns name → word."""
        paths = [p for e in self._entries() for p in self._issue_paths(e)]
        instrs = self._instrs
        acc = []
        for f, a_ref, b_ref, dst, _ in instrs:
            op = f["op"]
            writer = op in ALU_OPS or op == Op.MUL
            reads = {r[1] for r, sp, use in ((a_ref, f["asp"], writer),
                                             (b_ref, f["bsp"], writer or op == Op.DIV))
                     if use and not sp and r[0] == "r"}
            acc.append((reads, dst[1] if (writer and f["wen"] and dst) else None))
        pinned = set(self._reg_init) | set(keep)
        unknown = set(keep) - set(self._regs)
        if unknown:
            raise ValueError(f"Assembler: keep names no register: {sorted(unknown)}")
        edges = {name: set() for name in self._regs}
        for path in paths:
            events = []
            for t, pc in path:
                reads, w = acc[pc]
                if w is not None:
                    events.append((t + WRITE_DELAY, 0, w))
                for r in reads:
                    events.append((t - 1, 1, r))
            events.sort()
            live = {}                   # name → [W, last R] of its latest write back
            spans = []
            writes = []
            for clock, kind, name in events:
                if kind == 0:
                    if name in live:
                        spans.append((name, *live[name]))
                    live[name] = [clock, clock]
                    writes.append((clock, name))
                elif name in live:
                    live[name][1] = clock
                else:
                    pinned.add(name)            # read before written: state
            spans.extend((name, w, r) for name, (w, r) in live.items())
            for clock, y in writes:
                for x, w, r in spans:
                    if w < clock <= r and x != y:
                        edges[x].add(y)
                        edges[y].add(x)
        regs = {}
        for name in self._regs:
            if name in pinned:
                regs[name] = len(regs)
        base = len(regs)
        colour = {}
        for name in self._regs:
            if name not in pinned:
                taken = {colour[n] for n in edges[name] if n in colour}
                c = 0
                while c in taken:
                    c += 1
                colour[name] = c
                regs[name] = base + c
        return regs

    def assemble(self, *, fuse=True, schedule=True, fold=True, realloc=False, keep=()):
        """The program: posts fused into the next MUL (``fuse``), straight-line code reordered
        to fill the hazard distances (``schedule``, :meth:`_schedule`; then fused again), NOPs
        inserted where a hazard remains, every branch path checked, then NOPs folded into the
        word before them as its bubbles where every path is unchanged (``fold``,
        :meth:`_fold`: the same instructions in the same clocks, fewer words), then, with
        ``realloc``, the temporaries given register-file words by interference colouring on
        the final instruction order (:meth:`_realloc`: no instruction moves, every path keeps
        its clocks; the state, the registers with an initial value and those named in ``keep``
        (read from outside the program, e.g. by a model after a run) keep words of their own);
        without it, every register has a word of its own (allocated on first use).

        Returns
        -------
        Program
        """
        if fuse:
            self._fuse()
        if schedule:
            self._schedule()
            if fuse:
                self._fuse()
        self._insert_nops()
        if fold:
            self._fold()
        if realloc:
            regs = self._realloc(keep)
        else:
            regs = {}
            for name in self._regs:
                regs[name] = len(regs)
        consts = sorted(self._consts)
        used = len(set(regs.values()))
        if used + len(consts) > RF_DEPTH:
            raise ValueError(f"Assembler: {used} register words and {len(consts)} constants "
                             f"exceed the {RF_DEPTH}-word register file")
        kaddr = {v: RF_DEPTH - 1 - i for i, v in enumerate(consts)}
        rf_init = [0] * RF_DEPTH
        for v, addr in kaddr.items():
            if not -(1 << (WORD - 1)) <= v < (1 << (WORD - 1)):
                raise ValueError(f"Assembler: constant {v} does not fit {WORD} bits")
            rf_init[addr] = v
        for name, v in self._reg_init.items():
            rf_init[regs[name]] = v

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
        if len(words) > 1 << PC_WIDTH:
            raise ValueError(f"Assembler: {len(words)} instructions exceed {1 << PC_WIDTH}")
        symbols = dict(regs)
        symbols.update({f"k.{v}": a for v, a in kaddr.items()})
        return Program(words=words, rf_init=rf_init, regs=symbols, labels=dict(self._labels),
                       specials=self.specials, bspecials=self.bspecials, conds=self.conds,
                       outs=self.outs)


def check_flag_outputs(who, program, out_widths):
    """Raise ``ValueError`` unless every write of a 1-bit output (a flag: ``X ≠ 0``) in
    ``program`` is an ALU operation (ADD … SEL) with ``sh`` = 0 whose A is not P or PQ: the
    gateware tests the unshifted result, its ``WORD`` bits and sign, in X4."""
    for pc, ins in enumerate(program.instrs):
        if not ins.out or out_widths.get(program.outs[ins.out]) != 1:
            continue
        if ins.op not in ALU_OPS or ins.sh or (ins.asp and ins.a in (0, 1)):
            raise ValueError(f"{who}: the 1-bit output {program.outs[ins.out]!r} at pc {pc} "
                             f"must be written by an ALU operation (ADD ... SEL) with sh = 0 "
                             f"whose A is not P or PQ, not {Op(ins.op).name} with sh = "
                             f"{ins.sh}{' and A = P/PQ' if ins.asp and ins.a in (0, 1) else ''}")


def _delay_line(m, name, n, behind, fields):
    """``fields`` (name → value) ``behind + 1`` clocks later, through a 4-word RAM ``name``
    (written every clock at ``n``, a 2-bit count of the clocks, read at ``n − behind`` through
    an asynchronous port with its data registered: the register file's pattern, which yosys
    merges into a block RAM without collision logic; the addresses always differ). The data
    register (``{name}_q``) is not reset; returns a view of it."""
    layout = data.StructLayout({k: len(Value.cast(v)) for k, v in fields.items()})
    m.submodules[name] = mem = Memory(shape=layout, depth=4, init=[],
                                      attrs={"ram_style": "block", "no_rw_check": 1})
    wr, rd = mem.write_port(), mem.read_port(domain="comb")
    q = Signal(layout.size, reset_less=True, name=f"{name}_q")
    m.d.sync += q.eq(rd.data)
    m.d.comb += [wr.addr.eq(n), wr.en.eq(1), wr.data.eq(Cat(*fields.values())),
                 rd.addr.eq(n - behind)]
    return data.View(layout, q)


def _shift_right(v, sh, width):
    """``v >> sh`` (``v`` signed, ``sh`` unsigned): its low ``width`` bits and the sign above
    them (``width + 1`` bits), as a logarithmic shifter whose largest stage comes first, so
    that each stage is only as wide as the bits the later ones still need (``width`` plus
    their largest shift): 5 × 2:1 multiplexers of ``P_WORD + 2``, ``WORD + 15``, … bits in
    place of five full-width stages."""
    sign = v[-1]
    bits = [v[j] for j in range(len(v))]
    for i in reversed(range(len(sh))):
        step = 1 << i
        need = width + step - 1                 # the later stages shift by at most step − 1
        bits = [Mux(sh[i], bits[j + step] if j + step < len(bits) else sign, bits[j])
                if j < len(bits) else sign for j in range(need)]
    return Cat(*bits[:width], sign)


def _special_and_or(m, sel, lines):
    """The AND-OR of R's special operand, ``WORD`` bits: ``OR_k (sel[k] ? value_k : 0)`` for
    ``lines[k] = ((base, lo, width, signed, shift), asl)``, value_k = ``base[lo:lo + width]``
    (sign- or zero-extended) shifted left by ``shift + asl``, built bit by bit: per result
    bit, the lines that read the same source bit share one AND (their selects ORed: e.g. the
    configuration word and its low slices), and the terms that appear in the same set of
    result bits (the sign bits of the 16-bit specials in bits 16 … 31) are ORed once for all
    of them. The same function as the plain AND-OR of the lines (a rewrite of the sum of
    products; ``sel`` one-hot or not)."""
    bit_terms = [dict() for _ in range(WORD)]       # per result bit: source bit -> line set
    sources = {}
    for k, ((base, lo, width, sgn, shift), asl) in enumerate(lines):
        for j in range(WORD):
            src = j - shift - asl
            if src < 0 or (src >= width and not sgn):
                continue
            idx = lo + min(src, width - 1)
            sources[(id(base), idx)] = (base, idx)
            bit_terms[j].setdefault((id(base), idx), set()).add(k)
    sel_or = {}

    def select(ks):
        ks = frozenset(ks)
        if ks not in sel_or:
            s = Signal(name=f"spec_sel_{len(sel_or)}")
            m.d.comb += s.eq(Cat(*(sel[k] for k in sorted(ks))).any())
            sel_or[ks] = s if len(ks) > 1 else sel[next(iter(ks))]
        return sel_or[ks]

    # Terms (source bit, line set) and the result bits each appears in.
    where = {}
    for j, terms in enumerate(bit_terms):
        for src, ks in terms.items():
            where.setdefault((src, frozenset(ks)), set()).add(j)
    groups = {}
    for term, bits in where.items():
        groups.setdefault(frozenset(bits), []).append(term)
    per_bit = [[] for _ in range(WORD)]
    for bits, terms in sorted(groups.items(), key=lambda g: (min(g[0]), len(g[0]))):
        ands = [sources[src][0][sources[src][1]] & select(ks) for src, ks in terms]
        if len(bits) > 1 and len(ands) > 1:
            shared = Signal(name=f"spec_or_{min(bits)}_{max(bits)}")
            m.d.comb += shared.eq(Cat(*ands).any())
            ands = [shared]
        for j in bits:
            per_bit[j] += ands
    return Cat(*(Cat(*t).any() if t else Const(0, 1) for t in per_bit))


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
    config : tuple of str
        User specials read from the configuration RAM instead of a port (A operand only; at
        most one per instruction by the encoding), in the RAM's word order. Default ``()``.
        The RAM holds ``config_width`` bits of each word (sign-extended when read: a value of
        an unsigned shape needs one bit more than its width) and is written through ``cfg``;
        it behaves exactly like a flip-flop register per word loaded at the end of each clock
        with ``cfg.valid`` (the value an instruction reads is the word in its R clock, as for
        a port), see "Configuration RAM" below.
    config_init : list of int
        The configuration RAM's initial words (default all 0), as ``cfg.data`` carries them
        (e.g. :attr:`~.regs.RegisterFile.export_init`: the registers' reset values).
    config_slices : dict of str to tuple
        User specials that are slices of a configuration RAM word: ``name: (word, lo, bits,
        shift)`` reads ``(word[lo:lo + bits]) << shift`` (zero-extended) from the word named
        ``word`` of ``config`` (a word read only through slices need not be a special; it is
        then ``lo + bits`` bits wide at most). Each slice is one more line of R's special
        AND-OR (its own key), fed by the same RAM read: e.g. the speed loop's gain pieces
        ``kph = kp >> 16`` … of the ``kp``, ``kx`` words. Default none.
    strobe_outs : tuple of str
        Outputs (of ``out_widths``, not ``ang``, not 1-bit) with no register: only their write
        strobe ``o_<name>_we`` and the write data ``o_data``, for a consumer that keeps them
        elsewhere (e.g. a RAM). Default ``()``.

    Configuration RAM (``config``): block RAM of ``len(config)`` words of ``config_width``
    bits. The word of an instruction's config operand is looked up, in the clock before F,
    from the next ``pc`` in a second ROM beside the program ROM (``cfg_rom``: per
    instruction its config word), so the RAM is read in F and its data is one more input of
    R's special AND-OR (one line, and one for ``asl``), in place of one line per config
    special. ``cfg_rom`` also holds whether the instruction reads ``TC``: with ``config`` the
    sine table's halves are words of their own (``TS`` at ``i``, ``TC`` at ``i + 2**n``), so
    that ``TS`` and ``TC`` are one line (one key) too. The RAM is read one clock before the
    port values were: a write in the F clock
    of the word read (``cfg.valid`` and ``cfg.index`` equal to it) is taken from ``cfg.data``
    registered (the bypass), so each read returns the word as of the R clock.

    Members
    -------
    start : In(1)
        Start the program at ``start_pc`` (ignored while running).
    start_pc : In(PC_WIDTH)
        The address ``start`` starts at: 0, or an entry label's (:attr:`Program.labels`, e.g.
        the ``speed`` run of ``current_loop_program(speed=True)``); 0 when not driven.
    running : Out(1)
        The program runs (from the clock after ``start`` to its END).
    end : Out(1)
        One-clock strobe: END in X3 (the instruction before it writes back in this clock;
        from the next clock on every result is in place).
    <special> : In(shape)
        One port per user special operand (not those of ``config``).
    cfg : In(WordWriteSignature(len(config)))
        With ``config``: writes of the configuration RAM (``data``'s low ``config_width``
        bits; written at the end of the ``valid`` clock).
    <cond> : In(1)
        One port per user condition.
    <out> : Out(width), <out>_we : Out(1)
        Output registers (held) and their one-clock write strobes (``strobe_outs``: the
        strobe only).
    o_data : Out(signed(WORD))
        The value written back in this clock (X4): what an output written in this clock
        (its ``_we`` high) takes, its low ``width`` bits.
    trace_* : Out
        Per-clock view of the instruction in X4 (write back), for the tests:
        ``trace_valid`` (low in a bubble), ``trace_pc``, ``trace_wen``, ``trace_dst``,
        ``trace_y`` (the value written back), ``trace_p`` (P as this instruction read it in X2,
        before its update).
    """

    def __init__(self, *, program, special_shapes, out_widths, width=16, guard=8, div_bits=16,
                 rotator=None, config=(), config_init=None, config_slices=None,
                 strobe_outs=()):
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
        check_flag_outputs("Engine", program, out_widths)
        for name, value, lo, hi in (("width", width, 4, 32), ("guard", guard, 0, 16),
                                    ("div_bits", div_bits, 1, 24)):
            check_param("Engine", name, value, lo, hi)
        if rotator is None:
            rotator = RotatorParams(width=16, angle_width=16)
        config_slices = dict(config_slices or {})
        for name, spec in config_slices.items():
            if (name not in user_specials or name in config or not isinstance(spec, tuple)
                    or len(spec) != 4 or spec[0] not in config
                    or not all(isinstance(v, int) and not isinstance(v, bool) and v >= 0
                               for v in spec[1:]) or spec[2] < 1
                    or Shape.cast(special_shapes[name]).signed
                    or Shape.cast(special_shapes[name]).width < spec[2] + spec[3]):
                raise ValueError(f"Engine config_slices[{name!r}] must be (word of config, lo, "
                                 f"bits >= 1, shift) for an unsigned user special not in "
                                 f"config that holds bits + shift bits, not {spec!r}")
        sliced = {spec[0] for spec in config_slices.values()}
        if (not isinstance(config, tuple) or len(set(config)) != len(config)
                or not all(n in user_specials or n in sliced for n in config)):
            raise ValueError(f"Engine config must be a tuple of distinct user specials "
                             f"{user_specials} (or words read through config_slices), "
                             f"not {config!r}")
        for name in config:
            if name in program.bspecials:
                raise ValueError(f"Engine config special {name!r} is a B special: config "
                                 f"specials are A operands only")
        if config_init is None:
            config_init = [0] * len(config)
        if (not isinstance(config_init, (list, tuple)) or len(config_init) != len(config)
                or not all(isinstance(v, int) for v in config_init)):
            raise ValueError(f"Engine config_init must be a list of {len(config)} integers, "
                             f"not {config_init!r}")
        if (not isinstance(strobe_outs, tuple) or len(set(strobe_outs)) != len(strobe_outs)
                or not all(n in out_widths and n != "ang" and out_widths[n] > 1
                           for n in strobe_outs)):
            raise ValueError(f"Engine strobe_outs must be a tuple of distinct outputs of "
                             f"out_widths, wider than 1 bit, not ang, not {strobe_outs!r}")
        self._strobe_outs = strobe_outs
        self._config = config
        self._config_slices = config_slices
        self._config_width = max([Shape.cast(special_shapes[n]).width
                                  + (0 if Shape.cast(special_shapes[n]).signed else 1)
                                  for n in config if n in user_specials]
                                 + [lo + bits for _, lo, bits, _ in config_slices.values()],
                                 default=0)
        self._config_init = [int(v) for v in config_init]
        self._program = program
        # The (special, asl) pairs the ROM's key field names, computed once (rom_width and the
        # ROM's words use them): the configuration specials share one key.
        self._cfg_specials = {program.specials.index(name) for name in config
                              if name in user_specials}
        self._slice_specials = {program.specials.index(name): j
                                for j, name in enumerate(config_slices)}
        self._keys = sorted({self._key_of(ins) for ins in program.instrs
                             if ins.asp and ins.a >= 2})
        self._special_shapes = dict(special_shapes)
        self._out_widths = dict(out_widths)
        self._width = width
        self._guard = guard
        self._div_bits = div_bits
        self._rot = rotator
        members = {
            "start": In(1),
            "start_pc": In(PC_WIDTH),
            "running": Out(1),
            "end": Out(1),
            "trace_valid": Out(1),
            "trace_pc": Out(PC_WIDTH),
            "trace_wen": Out(1),
            "trace_dst": Out(7),
            "trace_y": Out(signed(WORD)),
            "trace_p": Out(signed(P_WORD)),
            "o_data": Out(signed(WORD)),
        }
        for name, shape in self._special_shapes.items():
            if name not in config and name not in config_slices:
                members[f"s_{name}"] = In(shape)
        if config:
            members["cfg"] = In(WordWriteSignature(len(config)))
        for name in program.conds[len(BUILTIN_CONDS):]:
            members[f"c_{name}"] = In(1)
        for name, w in self._out_widths.items():
            if name not in strobe_outs:
                members[f"o_{name}"] = Out(w)
            members[f"o_{name}_we"] = Out(1)
        super().__init__(members)

    def _key_of(self, ins):
        """The (special, asl) pair of an instruction's special A (config specials: one;
        a config slice: one per slice)."""
        n = len(self._program.specials)
        if ins.a in self._cfg_specials:
            return (n, ins.asl)
        if ins.a in self._slice_specials:
            return (n + 1 + self._slice_specials[ins.a], ins.asl)
        if self._config and ins.a == 3:         # TC: the table line (TS's key), other half
            return (2, ins.asl)
        return (ins.a, ins.asl)

    @property
    def rom_width(self):
        """Bits of a program ROM word: the instruction and its special operand's key (0 for
        none, ``k + 1`` for the k-th (special, asl) pair)."""
        return INSTR_WIDTH + max(1, len(self._keys).bit_length())

    @property
    def rom_words(self):
        """The program ROM's words: the instruction and, above it, its special key. ``asl`` is
        part of the key (its (special, asl) pair) and read nowhere else: its lane is written 0,
        so that yosys drops it with the spare bits (const-0 lanes): 56 bits, a 512-word ROM in 7
        block RAMs of 512 × 8 on the iCE40 instead of 8 (AREA.md §7.81)."""
        prog, keys = self._program, self._keys
        asl_lo = sum(w for _, w in FIELDS[:[n for n, _ in FIELDS].index("asl")])
        return [(word & ~(1 << asl_lo))
                | ((keys.index(self._key_of(ins)) + 1 if ins.asp and ins.a >= 2 else 0)
                   << INSTR_WIDTH) for word, ins in zip(prog.words, prog.instrs)]

    program = property(lambda self: self._program)
    rotator = property(lambda self: self._rot)
    config = property(lambda self: self._config)
    config_width = property(lambda self: self._config_width)
    config_slices = property(lambda self: dict(self._config_slices))
    strobe_outs = property(lambda self: self._strobe_outs)

    def elaborate(self, platform):
        m = Module()
        prog, rot = self._program, self._rot
        w, q = self._width, self._div_bits

        # --- Fetch, register read, execute ---------------------------------------------------------
        # The program ROM holds, beside each instruction, the key of its special operand A
        # (``k + 1`` for the k-th (special, asl) pair the program uses, 0 for none; in the
        # spare bits of the ROM's block RAM), decoded in R to the special's one-hot select.
        # With ``config``, the config specials share one key (two with asl): CFG stands for
        # the configuration RAM's read data.
        cfg_of = {prog.specials.index(name): j for j, name in enumerate(self._config)
                  if name in prog.specials}
        cfg_of.update({prog.specials.index(name): self._config.index(spec[0])
                       for name, spec in self._config_slices.items()})
        keys = self._keys
        key_w = self.rom_width - INSTR_WIDTH
        rom_words = self.rom_words
        m.submodules.rom = rom = Memory(shape=INSTR_WIDTH + key_w,
                                        depth=max(len(prog.words), 2), init=rom_words)
        # The register file's read ports: asynchronous ports with their data registered here
        # (the same clock as a synchronous port), so that yosys merges the registers into the
        # block RAM and, with ``no_rw_check``, leaves out its read-during-write emulation (a
        # register of the write data and an address compare, two LUT levels in front of the
        # X1 adder on the iCE40): a collision's read data is never used, the engine bypasses
        # it itself (``use_a``, ``use_b`` below).
        m.submodules.rf = rf = Memory(shape=signed(WORD), depth=RF_DEPTH, init=prog.rf_init,
                                      attrs={"no_rw_check": 1})
        rf_w = rf.write_port()
        rf_a = rf.read_port(domain="comb")
        rf_b = rf.read_port(domain="comb")
        rf_a_data = Signal(signed(WORD), reset_less=True)
        rf_b_data = Signal(signed(WORD), reset_less=True)
        m.d.sync += [rf_a_data.eq(rf_a.data), rf_b_data.eq(rf_b.data)]
        rom_r = rom.read_port()

        pc = Signal(PC_WIDTH)
        pc_next = Signal(PC_WIDTH)  # pc in the next clock
        m.d.sync += pc.eq(pc_next)
        r_valid = Signal()          # rom_r.data is an instruction in R (the fetch: ``running``)
        x_valid = Signal()
        ir = data.View(INSTR_LAYOUT, Signal(INSTR_WIDTH))   # the instruction in X1
        ir2 = data.View(INSTR_LAYOUT, Signal(INSTR_WIDTH))  # the instruction in X2
        x2_valid = Signal()
        x3_valid = Signal()
        ir1 = data.View(INSTR_LAYOUT, rom_r.data[:INSTR_WIDTH])
        m.d.comb += [rom_r.addr.eq(pc), rf_a.addr.eq(ir1.a), rf_b.addr.eq(ir1.b)]
        m.d.sync += ir.as_value().eq(rom_r.data[:INSTR_WIDTH])
        # The fields X3 uses (``sh``, ``acc``, whether the op is MUL, DIV or END), three
        # clocks after R, and those X4 uses (below), four after: delay lines in small RAMs,
        # written every clock with R's instruction (the ROM's read data, which X1's register
        # ``ir`` takes in the next clock: no enable from R to X4) and read through an
        # asynchronous port two (X3) or three (X4) words behind, its data registered here,
        # in place of flip-flop stages (on the iCE40 a flip-flop loaded from a flip-flop or
        # a block RAM is a lone cell; docs/AREA.md §7.63). Their data are not reset
        # (x3_valid and x4_valid, which are, gate every use); ``ram_style`` asks yosys for a
        # block RAM for the 4 words, ``no_rw_check`` for no collision logic (the read and
        # write addresses always differ).
        dl_n = Signal(2)
        m.d.sync += dl_n.eq(dl_n + 1)
        # R's DIV decode and repeat tests as kept wires (yosys ``keep``), one and two LUT levels
        # behind the ROM: without them abc mapped the decode as a chain of four LUTs shared
        # with the delay line's fields, in front of ``hold`` and ``pc`` (``foc_engine_speed``
        # seed 3: ROM → pc 33.8 ns, 29.6 MHz; AREA.md §7.74). ``r_nb``: the bubbles of a word
        # not yet all made (``rep_k`` < ``nb`` ≤ 3: two bits), one LUT level.
        r_div = Signal(attrs={"keep": 1})
        r_rep = Signal(attrs={"keep": 1})
        r_nb = Signal(attrs={"keep": 1})
        rep_k = Signal(5)
        m.d.comb += [r_div.eq(ir1.op == Op.DIV), r_rep.eq(rep_k != ir1.sh),
                     r_nb.eq(rep_k[:len(ir1.nb)] != ir1.nb)]
        ir3 = _delay_line(m, "x3_delay", dl_n, 2,          # the fields of the instruction in X3
                          {"sh": ir1.sh, "acc": ir1.acc, "mul": ir1.op == Op.MUL,
                           "div": r_div, "end": ir1.op == Op.END})
        # A repeated DIV (``sh`` = repeats, :meth:`Assembler.div`): held in R (the ROM's read
        # enable low, ``pc`` held) until it has been issued ``sh + 1`` times, one per clock.
        # Any other word with bubbles (``nb``, NOP folding: :meth:`Assembler._fold`) is held
        # in R ``nb`` clocks after its issue likewise, issuing nothing (``r_bub``: R's word is
        # a bubble; X1 invalid: no flag, branch, END, write back, P update or output).
        hold = Signal()
        r_bub = Signal()
        m.d.comb += [hold.eq(r_valid & Mux(r_div, r_rep, r_nb)),
                     rom_r.en.eq(~hold)]
        m.d.sync += [rep_k.eq(Mux(hold, rep_k + 1, 0)), r_bub.eq(hold & ~r_div)]

        # --- Angle register, sine table, kd, fold flags ----------------------------------------------
        aw, mb, n, ft = rot.angle_width, rot.interp_bits, rot.table_bits, rot.table_frac
        ang = self.o_ang                    # the output register named "ang"
        # With ``config`` the table holds TS and TC as words of their own (TS at ``i``, TC at
        # ``i + 2**n``), one special line for both: the half is the address's top bit, looked
        # up beside the configuration word in ``cfg_rom`` (F: the clock the table is
        # addressed in), so that R's AND-OR has one ``ft``-bit line in place of two.
        tab_half = bool(self._config)
        ft_mask = (1 << ft) - 1
        m.submodules.table = table = Memory(
            shape=ft if tab_half else 2 * ft, depth=(2 if tab_half else 1) << n,
            init=([v & ft_mask for v in rot.table_words] + [v >> ft for v in rot.table_words]
                  if tab_half else rot.table_words))
        tab_r = table.read_port()
        quad = ang[aw - 2:]
        mu = ang[aw - 3]
        tab_idx = ang[mb:aw - 3] ^ Mux(mu, (1 << n) - 1, 0)
        if not tab_half:
            m.d.comb += tab_r.addr.eq(tab_idx)
        kd_rom = [Const(v, unsigned(max(1, max(rot.kd_rom).bit_length()))) for v in rot.kd_rom]
        kd = Signal(unsigned(max(1, max(rot.kd_rom).bit_length())))
        with m.Switch(Cat(ang[:mb], mu)):
            for i, v in enumerate(kd_rom):
                with m.Case(i):
                    m.d.comb += kd.eq(v)

        # --- Operands --------------------------------------------------------------------------------
        p = Signal(signed(P_WORD))
        # P and PQ are read in X2 (below), not through this mux.
        # The special operands as bit fields (base value, first bit, width, signed, left shift):
        # the AND-OR below is built bit by bit from them (``_special_and_or``).
        kd_w = len(kd)
        fields = [None, None, (tab_r.data, 0, ft, True, 0),
                  None if tab_half else (tab_r.data, ft, ft, True, 0), (kd, 0, kd_w, False, 0)]
        for name, shape in self._special_shapes.items():
            if name in self._config or name in self._config_slices:
                fields.append(None)
            else:
                shape = Shape.cast(shape)
                fields.append((getattr(self, f"s_{name}"), 0, shape.width, shape.signed, 0))
        if self._config:
            cfg_value, tc_half = self._config_ram(m, prog, cfg_of, pc_next)
            m.d.comb += tab_r.addr.eq(Cat(tab_idx, tc_half))
            fields.append((cfg_value, 0, len(cfg_value), True, 0))
            # The slices: wirings of the same read (zero-extended).
            fields += [(cfg_value, lo, bits, False, shift)
                       for _, lo, bits, shift in self._config_slices.values()]
        # The special operands are selected in R (registered with the RF read) by an AND-OR
        # over a one-hot select: one line per (special, asl) pair the program uses (asl: the
        # value shifted by the guard; a special A only), decoded from the key the ROM holds
        # beside the instruction (no decode of the a field, no mux tree behind the ROM).
        key = rom_r.data[INSTR_WIDTH:]
        sel = Signal(max(1, len(keys)))
        m.d.comb += sel.eq(Cat(*(key == k + 1 for k in range(len(keys)))))
        spec = Signal(signed(WORD))
        m.d.comb += spec.eq(_special_and_or(
            m, sel, [(fields[i], self._guard if asl else 0) for i, asl in keys]))
        bspec = Signal(signed(WORD))
        with m.Switch(ir1.b):
            for i, name in enumerate(prog.bspecials):
                with m.Case(i):
                    m.d.comb += bspec.eq(getattr(self, f"s_{name}"))
        # Operands A, B in X1: the register file's read data, or an alternative registered in
        # R (``alt_a``, ``alt_b``, assigned below): the special operand, or the value written
        # back (X4) in R's clock to the register read (the read-during-write bypass, in place
        # of the memory's transparency): one select in front of the adder.
        alt_a = Signal(signed(WORD), reset_less=True)
        alt_b = Signal(signed(WORD), reset_less=True)
        use_a = Signal()
        use_b = Signal()
        a = Signal(signed(WORD))
        b = Signal(signed(WORD))
        m.d.comb += [a.eq(Mux(use_a, alt_a, rf_a_data)), b.eq(Mux(use_b, alt_b, rf_b_data))]

        # Flags: the sum's sign (``flag_s``) and its zero test, computed from the adder's
        # operands beside the carry chain (below) and registered in groups (``flag_zg``: a
        # group is set where the sum is not zero), are registered; Z is their NOR and N of a
        # MAX (which adds B − A) is derived where read.
        flag_s = Signal()
        flag_max = Signal()
        flag_zg = Signal(-(-(-(-(WORD + 1) // 4)) // 4))    # one per 16 bits of the sum
        flag_z = Signal()
        flag_n = Signal()
        m.d.comb += [flag_z.eq(~flag_zg.any()),
                     flag_n.eq(Mux(flag_max, ~flag_s & ~flag_z, flag_s))]
        conds = [Const(0), flag_n, flag_z, flag_n | flag_z, quad[0] ^ mu, quad[0] ^ quad[1],
                 quad[1]] + [getattr(self, f"c_{name}") for name in prog.conds[len(BUILTIN_CONDS):]]
        # The condition by an AND-OR over a one-hot select decoded in R.
        cond_sel = Signal(len(conds))
        m.d.sync += cond_sel.eq(1 << ir1.cond)
        c = Signal()
        m.d.comb += c.eq(Cat(*(cond_sel[i] & v for i, v in enumerate(conds))).any() ^ ir.inv)

        # --- ALU ---------------------------------------------------------------------------------
        # The adder's mode and the result select are decoded in R (registered with the operands).
        d_inv_a = Signal()          # ~A + B + 1 = B − A (RSUB, MAX)
        d_inv_b = Signal()          # A + ~B + 1 = A − B (SUB, MIN, SEL)
        d_mm = Signal()             # MIN or MAX: X = B if (c or sign of the sum clear) else A
        d_sel = Signal()            # SEL: X = B if c else A
        d_max = Signal()
        m.d.sync += [
            d_inv_a.eq((ir1.op == Op.RSUB) | (ir1.op == Op.MAX)),
            d_inv_b.eq((ir1.op == Op.SUB) | (ir1.op == Op.MIN) | (ir1.op == Op.SEL)),
            d_mm.eq((ir1.op == Op.MIN) | (ir1.op == Op.MAX)),
            d_sel.eq(ir1.op == Op.SEL),
            d_max.eq(ir1.op == Op.MAX),
        ]
        s = Signal(signed(WORD + 1))
        # One adder: A + B, A − B or B − A. MAX computes B − A, so that both MIN (A − B ≥ 0) and
        # MAX (A − B ≤ 0, i.e. B − A ≥ 0) select on the sum's sign alone.
        # A carry-select adder: the low half's carry picks one of two high halves (two short
        # carry chains in parallel instead of one of WORD + 1 bits).
        ea = Signal(signed(WORD + 1))
        eb = Signal(signed(WORD + 1))
        cin = d_inv_a | d_inv_b
        m.d.comb += [ea.eq(Mux(d_inv_a, ~a, a)), eb.eq(Mux(d_inv_b, ~b, b))]
        k = WORD // 2
        lo = Signal(k + 2)
        hi0 = Signal(WORD + 1 - k + 1)
        hi1 = Signal(WORD + 1 - k + 1)
        m.d.comb += [lo.eq(ea[:k] + eb[:k] + cin), hi0.eq(ea[k:] + eb[k:]),
                     hi1.eq(ea[k:] + eb[k:] + 1),
                     s.eq(Cat(lo[:k], Mux(lo[k], hi1[:WORD + 1 - k], hi0[:WORD + 1 - k])))]
        # The sum is zero iff every bit's operand bits agree with the carry a zero sum would
        # bring into it (cin into bit 0, ea | eb of the bit below): no carry chain in front.
        carries = Cat(cin, (ea | eb)[:WORD])
        s_nz = (ea ^ eb ^ carries)[:WORD + 1]
        # Two levels of OR4; the first level's outputs kept (yosys ``keep``): without them abc
        # mapped the zero test as a chain of 7 LUTs from the register file's read data to
        # ``flag_zg`` (the iCEBreaker engine's critical path on seed 1, AREA.md §7.74).
        s_z4 = []
        for j in range(0, WORD + 1, 4):
            z = Signal(name=f"s_z4_{j // 4}", attrs={"keep": 1})
            m.d.comb += z.eq(s_nz[j:j + 4].any())
            s_z4.append(z)
        s_zg = Cat(*(Cat(*s_z4[j:j + 4]).any() for j in range(0, len(s_z4), 4)))
        # The result: the sum, A, or B (SEL: on c; MIN, MAX: on c or the sum's sign). The sum
        # is registered as it leaves the adder (``s2``), A and B beside it (``a2``, ``b2``); the
        # choice is made in X2 (``x2_b``: SEL, MIN or MAX take B), keeping every select off the
        # carry chain's end and the condition's fan-out small.
        # --- X2: rounding add (P read here); X3: shift, saturation test; X4: write back ------
        s2 = Signal(signed(WORD + 1), reset_less=True)
        a2 = Signal(signed(WORD), reset_less=True)
        b2 = Signal(signed(WORD), reset_less=True)
        mm2 = Signal()
        sel2 = Signal()
        c2 = Signal()
        m.d.sync += [s2.eq(s), a2.eq(a), b2.eq(b), mm2.eq(d_mm), sel2.eq(d_sel), c2.eq(c),
                     ir2.as_value().eq(ir.as_value())]
        x2_b = Signal()
        m.d.comb += x2_b.eq((mm2 & (c2 | ~s2[-1])) | (sel2 & c2))
        # P is read in X2 (MUL and DIV update it at the end of X3): by a MUL's fused post and by
        # an ALU operation whose A is P or PQ (B ignored). The rounding adder's operand ``xp``
        # is an AND-OR of P (its low ``q`` bits for PQ) and the sum under selects registered
        # in X1: one LUT level. SEL, MIN and MAX are never rounded: their choice of A or B
        # (``x2m``, on the sum's sign) bypasses the adder (whose operands are then all 0) and
        # is ORed into its result.
        d_plo = Signal()
        d_phi = Signal()
        k_s = Signal()
        k_t = Signal()
        p_read = (ir.op == Op.MUL) | (ir.asp & (ir.a == 0))
        pq_read = (ir.op != Op.MUL) & ir.asp & (ir.a == 1)
        m.d.sync += [d_plo.eq(p_read | pq_read), d_phi.eq(p_read),
                     k_s.eq(~p_read & ~pq_read & ~d_mm & ~d_sel),
                     k_t.eq(~p_read & ~pq_read & (d_mm | d_sel))]
        x2m = Signal(signed(P_WORD + 2))          # SEL, MIN, MAX: X; else 0
        m.d.comb += x2m.eq(Mux(k_t, Mux(x2_b, b2, a2), 0))
        xp = Signal(signed(P_WORD + 1))
        m.d.comb += xp.eq(Cat(Mux(d_plo, p[:q], 0), Mux(d_phi, p[q:], 0)).as_signed() |
                          Mux(k_s, s2, 0))
        # Rounding: X + 2**(sh−1) − (X < 0) = X + (2**(sh−1) − 1) + (X ≥ 0): the constant
        # 2**(sh−1) − 1 prepared in X1, the sign as the carry-in (no select in front of the
        # rounding adder's operands).
        h_mask = Signal(unsigned(P_WORD), reset_less=True)
        # The carry-in (X ≥ 0) in two terms: ``rc_s`` of the sum (its sign at the end of X1's
        # adder, registered) or PQ (never negative), ``rc_p`` of P (its sign in X2); they
        # enter the rounding adder as the carry out of a bit below its operands (1 + rc_s +
        # rc_p carries rc_s | rc_p): no OR and no feed-in cell in front of the carry chain
        # (rc_s straight from its flip-flop, rc_p one LUT behind P). AREA.md §7.74.
        rc_s = Signal()
        rnd_p = Signal()
        rounding = ir.rnd & (ir.sh != 0)
        m.d.sync += [h_mask.eq(Mux(rounding & ~d_mm & ~d_sel,
                                   ~(Const((1 << (P_WORD + 1)) - 1, P_WORD + 1) << ir.sh)[1:P_WORD + 1], 0)),
                     rnd_p.eq(rounding & p_read),
                     rc_s.eq((rounding & pq_read) |
                             (rounding & ~p_read & ~pq_read & ~d_mm & ~d_sel & ~s[-1]))]
        rc_p = Signal()
        m.d.comb += rc_p.eq(rnd_p & ~p[-1])
        # X3: the rounded sum registered; shift by sh (floor) and the saturation test,
        # registered. X4: the saturation select, write back.
        r3 = Signal(signed(P_WORD + 2))
        # A ripple adder (a carry-select one, two half-length chains, cost 34 LUT4 and 22
        # carries more on the iCE40 with the engine's Fmax unchanged: AREA.md §7.66).
        rx = Signal(P_WORD + 2)
        rh = Signal(P_WORD + 2)
        m.d.comb += [rx.eq(xp), rh.eq(h_mask)]
        # (Rounding applies to P, PQ (never negative) and the sum only: not to SEL, MIN, MAX.)
        m.d.sync += r3.eq((Cat(rc_s, rx) + Cat(rc_p, rh) + 1)[1:P_WORD + 3] | x2m)
        shifted = Signal(signed(WORD + 1))     # r3 >> sh: its low WORD bits and the sign
        m.d.sync += shifted.eq(_shift_right(r3, ir3.sh, WORD))
        # Saturation: the shifted value fits signed(sw) iff its bits from sw − 1 up all equal
        # its sign, i.e. ``shifted``'s bits sw − 1 … WORD − 1 (fixed positions: tested in X4,
        # in front of the select) and r3's bits from sh + WORD up (the shifted value's bits
        # beyond ``shifted``): tested in X3 beside the barrel shift under a mask made in X2
        # (``hi_mask``: r3's bit WORD + i when i ≥ sh, for a saturating instruction only),
        # P_WORD + 2 − WORD bits in place of a mask over all of r3.
        hw = P_WORD + 2 - WORD
        hi_mask = Signal(hw)
        sat2 = (ir2.sat == SAT_W) | (ir2.sat == SAT_W1)
        m.d.sync += hi_mask.eq(Mux(sat2, (Const((1 << hw) - 1, hw) << ir2.sh)[:hw], 0))
        ovf_hi4 = Signal()
        m.d.sync += ovf_hi4.eq((hi_mask & (r3[WORD:] ^ r3[-1].replicate(hw))).any())
        # The fields X4 uses (and whether the op writes back): the delay line of X3's (above),
        # read three words behind.
        ir4 = _delay_line(m, "x4_delay", dl_n, 3,
                          {"dst": ir1.dst, "out": ir1.out, "wen": ir1.wen, "sat": ir1.sat,
                           "writes": (ir1.op == Op.ADD) | (ir1.op == Op.SUB) |
                           (ir1.op == Op.RSUB) | (ir1.op == Op.MIN) | (ir1.op == Op.MAX) |
                           (ir1.op == Op.SEL) | (ir1.op == Op.MUL)})
        w4_sat, w4_dst, w4_out, w4_wen = ir4.sat, ir4.dst, ir4.out, ir4.wen
        y = Signal(signed(WORD))
        lim = Signal(signed(WORD))
        m.d.comb += lim.eq(Mux(w4_sat == SAT_W1,
                               Mux(shifted[-1], -(1 << w), (1 << w) - 1),
                               Mux(shifted[-1], -(1 << (w - 1)), (1 << (w - 1)) - 1)))
        sgn4 = shifted[-1]
        ovf4 = Signal()
        m.d.comb += ovf4.eq(ovf_hi4 |
                            (((w4_sat == SAT_W) | (w4_sat == SAT_W1)) &
                             (shifted[w:WORD] ^ sgn4.replicate(max(WORD - w, 0))).any()) |
                            ((w4_sat == SAT_W) & (shifted[w - 1] ^ sgn4)))
        m.d.comb += y.eq(Mux(ovf4, lim, shifted))

        # --- Multiplier, divider step ----------------------------------------------------------
        # Operands registered at the end of X1; the product registered at the end of X2 (the
        # multiplier and its partial-product adders alone in X2); P updated in X3 (± product,
        # DIV step), read in X2 by the posts (``HAZARD_P``) and in X3 by MAC and DIV.
        # The operands are X1's A and B as registered for X2 (``a2``, ``b2``): no registers of
        # their own (they were a copy of the same bits: 47 flip-flops without a LUT in front on
        # the iCE40).
        ma = Signal(signed(MUL_A))
        mb = Signal(signed(MUL_B))
        m_neg = Signal()
        m.d.comb += [ma.eq(a2[:MUL_A]), mb.eq(b2[:MUL_B])]
        m.d.sync += m_neg.eq(ir.neg ^ c)
        # ``init`` ones on the multiplier's 28 bits: an iCE40 flip-flop stores ``value XOR
        # init``, so they hold ``~prod`` and DIV's ``− prod`` gets its carry operand without an
        # inverter LUT; the inversion at D folds into the sum LUT of the adder that joins the
        # SB_MAC16s' partial products (bits 16–27) or packs with the flip-flop (bits 0–15, fed
        # by an SB_MAC16 output: alone in their cells before), and X3's ``± prod`` XOR LUT
        # takes the other polarity. Loaded every clock and read only in X3: the power-up value
        # is never used (docs/AREA.md §7.55, §7.63).
        prod = Signal(signed(MUL_A + MUL_B), reset_less=True,
                      init=(1 << MUL_B) - 1)
        m_neg3 = Signal(reset_less=True)
        m.d.sync += [prod.eq(ma * mb), m_neg3.eq(m_neg)]
        t2 = Signal(signed(P_WORD + 1))
        m.d.comb += t2.eq(p << 1)
        div_diff = Signal(signed(P_WORD + 1))
        # DIV's divisor: the product of its A, the constant 1 (the assembler's), and B.
        m.d.comb += div_diff.eq((t2 >> q) - prod[:MUL_B].as_signed())
        div_ge = ~div_diff[-1]

        is_alu = (ir.op == Op.ADD) | (ir.op == Op.SUB) | (ir.op == Op.RSUB) | \
            (ir.op == Op.MIN) | (ir.op == Op.MAX) | (ir.op == Op.SEL)
        execute = x_valid                   # (x_valid only while running)
        x4_valid = Signal()
        m.d.sync += [x2_valid.eq(execute), x3_valid.eq(x2_valid), x4_valid.eq(x3_valid)]
        writes4 = x4_valid & ir4.writes
        p3 = Signal(signed(P_WORD))           # P as the instruction in X3 read it in X2 (trace)
        p4 = Signal(signed(P_WORD))           # the same, in X4
        m.d.sync += [p3.eq(p), p4.eq(p3)]
        m.d.comb += [
            rf_w.addr.eq(w4_dst),
            rf_w.data.eq(y),
            rf_w.en.eq(writes4 & w4_wen),
        ]
        m.d.sync += [
            alt_a.eq(Mux(ir1.asp, spec, y)),
            use_a.eq(ir1.asp | (rf_w.en & (rf_w.addr == ir1.a))),
            alt_b.eq(Mux(ir1.bsp, bspec, y)),
            use_b.eq(ir1.bsp | (rf_w.en & (rf_w.addr == ir1.b))),
        ]
        m.d.comb += [
            self.trace_valid.eq(x4_valid),
            self.trace_wen.eq(rf_w.en),
            self.trace_dst.eq(w4_dst),
            self.trace_y.eq(y),
            self.trace_p.eq(p4),
        ]
        x_pc = Signal(PC_WIDTH)
        r_pc = Signal(PC_WIDTH)
        x2_pc = Signal(PC_WIDTH)
        x3_pc = Signal(PC_WIDTH)
        x4_pc = Signal(PC_WIDTH)
        with m.If(~hold):
            m.d.sync += r_pc.eq(pc)
        m.d.sync += [x_pc.eq(r_pc), x2_pc.eq(x_pc), x3_pc.eq(x2_pc), x4_pc.eq(x3_pc)]
        m.d.comb += self.trace_pc.eq(x4_pc)

        # Outputs (written in X4, like the register file).
        m.d.comb += self.o_data.eq(y)
        for i, (name, ow) in enumerate(self._out_widths.items(), start=1):
            we = getattr(self, f"o_{name}_we")
            m.d.comb += we.eq(writes4 & (w4_out == i))
            if name in self._strobe_outs:
                continue                        # no register: o_data with the strobe
            reg = getattr(self, f"o_{name}")
            with m.If(we):
                # A 1-bit output takes X ≠ 0: the shifted value's (its WORD bits and sign:
                # X's 33 bits), as a 1-bit output is written with sh = 0 only
                # (:func:`check_flag_outputs`).
                m.d.sync += reg.eq((shifted != 0) if ow == 1 else y[:ow])

        # The P update of a MUL, P_WORD bits (mod 2**P_WORD: the interpreter checks that P
        # fits): a ripple adder, the carry-in negating (a carry-select one, two half-length
        # chains, cost 29 logic cells more on the iCEBreaker: AREA.md §7.66).
        pa = Signal(P_WORD)
        pb = Signal(P_WORD)
        m.d.comb += [pa.eq(Mux(ir3.acc, p, 0)), pb.eq(Mux(m_neg3, ~prod, prod))]
        p_sum = Signal(P_WORD)
        m.d.comb += p_sum.eq(pa + pb + m_neg3)
        with m.If(execute):
            with m.If(is_alu & ir.setf):
                # Of the sum (MAX: B − A); N, Z of A − B are derived from them where read.
                m.d.sync += [flag_s.eq(s[-1]), flag_zg.eq(s_zg), flag_max.eq(d_max)]
        with m.If(x3_valid & ir3.mul):
            # P ± prod: one adder, the carry-in negates (``p_sum``, above).
            m.d.sync += p.eq(p_sum)
        with m.If(x3_valid & ir3.div):
            m.d.sync += p.eq(Mux(div_ge, Cat(Const(1, 1), t2[1:q], div_diff), t2))

        # --- Sequencer -------------------------------------------------------------------------
        # END stops the fetch in X1; ``end`` strobes with END in X3, when the instruction before
        # it writes back (X4): from the next clock on every result is in place.
        # ``start`` (late: the wrapper's arbitration) enters each next state in its last LUT
        # only: ``running`` = running ? ¬halt : start, ``pc_next`` = the start address or the
        # running program's next pc. R and X1 are valid only while running (``r_valid`` =
        # running and not halted a clock before, ``x_valid`` behind it, low for a bubble,
        # ``r_bub``): no start term (a start finds both clear) and no ``running`` term in
        # ``execute`` and ``hold``.
        halt = execute & (ir.op == Op.END)
        m.d.comb += self.end.eq(x3_valid & ir3.end)
        m.d.sync += [self.running.eq(Mux(self.running, ~halt, self.start)),
                     r_valid.eq(self.running & ~halt), x_valid.eq(r_valid & ~halt & ~r_bub)]
        pc_run = Signal(PC_WIDTH)
        m.d.comb += pc_run.eq(pc)
        with m.If(self.running & ~halt):
            with m.If(execute & (ir.op == Op.BR) & c):
                m.d.comb += pc_run.eq(ir.as_value()[TGT_LO:TGT_LO + PC_WIDTH])
            with m.Elif(~hold):
                m.d.comb += pc_run.eq(pc + 1)
        m.d.comb += pc_next.eq(Mux(self.start & ~self.running, self.start_pc, pc_run))
        return m

    def _config_ram(self, m, prog, cfg_of, pc_next):
        """The configuration RAM (class docstring): its write port, the word look-up from the
        next ``pc`` (``cfg_rom``), the read in F and the bypass of a write in the F clock.
        Returns the configuration operand as of the R clock (sign-extended) and the F
        clock's sine-table half (1: TC)."""
        cw, n = self._config_width, len(self._config)
        # Per instruction the config word its A operand reads (0 for none: read, not used)
        # and, above it, whether it reads TC (the sine table's half: its address's top bit).
        ww = Shape.cast(range(max(n, 2))).width
        words = [(cfg_of[ins.a] if ins.asp and ins.a in cfg_of else 0)
                 | (int(bool(ins.asp and ins.a == 3)) << ww) for ins in prog.instrs]
        # (In a block RAM: as a LUT ROM on ``pc_next`` it lengthened the branch condition's
        # path to 32.8 ns, 30.5 MHz on the UP5K; the block RAM's address takes pc_next as is.)
        m.submodules.cfg_rom = cfg_rom = Memory(shape=ww + 1,
                                                depth=max(len(words), 2), init=words,
                                                attrs={"rom_style": "block"})
        look_r = cfg_rom.read_port()            # the word of the instruction at pc (F)
        m.d.comb += look_r.addr.eq(pc_next)
        look = data.View(data.StructLayout({"data": ww, "tc": 1}), look_r.data)
        init = [(v & ((1 << cw) - 1)) - ((v >> (cw - 1) & 1) << cw) for v in self._config_init]
        # The read port as the register file's: asynchronous, its data registered here (one
        # synchronous block RAM port); a read of the word being written is undefined
        # (``no_rw_check``): the bypass below replaces it.
        m.submodules.cfg_ram = ram = Memory(shape=signed(cw), depth=n, init=init,
                                            attrs={"no_rw_check": 1})
        wr = ram.write_port()
        rd = ram.read_port(domain="comb")
        m.d.comb += [wr.en.eq(self.cfg.valid), wr.addr.eq(self.cfg.index),
                     wr.data.eq(self.cfg.data[:cw]), rd.addr.eq(look.data)]
        rd_data = Signal(signed(cw), reset_less=True)
        byp = Signal()
        byp_data = Signal(signed(cw), reset_less=True)
        m.d.sync += [rd_data.eq(rd.data),
                     byp.eq(self.cfg.valid & (self.cfg.index == look.data))]
        with m.If(self.cfg.valid):
            m.d.sync += byp_data.eq(self.cfg.data[:cw])
        value = Signal(signed(cw))
        m.d.comb += value.eq(Mux(byp, byp_data, rd_data))
        return value, look.tc
