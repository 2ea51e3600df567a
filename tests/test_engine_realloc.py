# Ref: docs/ENGINE.md (Memory); docs/AREA.md §7.87; issue 7
"""Register reuse after scheduling (:meth:`Assembler._realloc`, ``assemble(realloc=True)``):
the register-file words the programs use with and without it, the same instructions in the same
clocks (only register numbers change), the interpreter's traces of both allocations equal write
back by write back, and the pipeline's boundaries (a write landing in the clock of the last read,
the state read before written) on small programs."""

import contextlib
import dataclasses
import functools

import numpy as np

from foc_servo.hdl.engine import BUILTIN_CONDS, BUILTIN_SPECIALS, Assembler, Op
from foc_servo.hdl.engine_mt import mt_program
from foc_servo.hdl.foc_engine import current_loop_program, speed_loop_program
from foc_servo.sim.models.engine import EngineLoopModel, EngineModel, EngineSpeedModel
from foc_servo.sim.models.foc import OUTPUT_FIELDS
from foc_servo.sim.verify import foc as verify_foc
from engine_trace import random_speed_args


@contextlib.contextmanager
def _realloc(keep=()):
    """Every program assembled inside uses ``assemble(realloc=True, keep=keep)``."""
    orig = Assembler.assemble
    Assembler.assemble = functools.partialmethod(orig, realloc=True, keep=keep)
    try:
        yield
    finally:
        Assembler.assemble = orig


def _words(program):
    """Register-file words a program uses: (registers, constants)."""
    regs = {v for k, v in program.regs.items() if not k.startswith("k.")}
    return len(regs), sum(k.startswith("k.") for k in program.regs)


def _same_code(old, new):
    """The same instructions, word by word, but for the register numbers (the constants'
    addresses unchanged); every register name of the old allocation maps to one new word."""
    assert len(old.words) == len(new.words)
    for o, n in zip(old.instrs, new.instrs):
        assert dataclasses.replace(o, a=0, b=0, dst=0) == dataclasses.replace(n, a=0, b=0, dst=0)
    kold = {k: v for k, v in old.regs.items() if k.startswith("k.")}
    assert kold == {k: v for k, v in new.regs.items() if k.startswith("k.")}
    assert old.regs.keys() == new.regs.keys()
    back = {v: k for k, v in old.regs.items()}
    for o, n in zip(old.instrs, new.instrs):
        for f, sp in (("a", o.asp), ("b", o.bsp), ("dst", not o.wen)):
            if not sp:
                assert new.regs[back[getattr(o, f)]] == getattr(n, f)


def _same_trace(t_old, t_new):
    """Every clock's entry equal but for the destination register's number."""
    assert len(t_old) == len(t_new)
    for k, (a, b) in enumerate(zip(t_old, t_new)):
        assert {n: v for n, v in a.items() if n != "dst"} == \
            {n: v for n, v in b.items() if n != "dst"}, k


def _mt(realloc):
    if not realloc:
        return mt_program()
    with _realloc():
        return mt_program()


# Figures (docs/AREA.md §7.87): register words (registers, constants) without → with realloc.
PROGRAMS = {
    "current": (lambda r: current_loop_program(realloc=r), (81, 16), (20, 16)),
    "speed": (lambda r: speed_loop_program(realloc=r), (94, 15), (23, 15)),
    "combined": (lambda r: current_loop_program(speed=True, refs=True, mt=True, realloc=r),
                 (101, 27), (31, 27)),
    "mt": (_mt, (6, 5), (6, 5)),                    # (every register is state)
}


def test_realloc_words_and_code():
    """Fewer register-file words, the same ROM (words and instructions but for a, b, dst);
    the engine programs reallocate by default."""
    for name, (build, before, after) in PROGRAMS.items():
        old, new = build(False), build(True)
        _same_code(old, new)
        w_old, w_new = _words(old), _words(new)
        assert w_new[0] <= w_old[0] and w_new[1] == w_old[1], name
        assert (w_old, w_new) == (before, after), name
    # The iCEBreaker's combined program: 58 of 128 words (128 before).
    assert sum(PROGRAMS["combined"][2]) == 58 and sum(PROGRAMS["combined"][1]) == 128
    assert current_loop_program(speed=True).regs == current_loop_program(speed=True,
                                                                        realloc=True).regs
    assert speed_loop_program().regs == speed_loop_program(realloc=True).regs


def test_realloc_current_loop_same_trace():
    """The current-loop and combined programs with both allocations on the interpreter: the same
    outputs and the same write backs (value, clock, P) in every sample over every path, the
    state carried from sample to sample; then speed runs on the combined program."""
    vec = verify_foc.stimulus(40, seed=12)
    vec = {k: v for k, v in vec.items() if k != "theta_lead"} | {
        "lead_k": np.asarray(vec["theta_lead"]) % (1 << 16)}
    for kw in (dict(), dict(speed=True)):
        old = EngineLoopModel(program=current_loop_program(**kw, realloc=False))
        new = EngineLoopModel(program=current_loop_program(**kw))
        a, b = old.run(**vec), new.run(**vec)
        for k in OUTPUT_FIELDS:
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)
        for to, tn in zip(old.traces, new.traces):
            _same_trace(to, tn)
    old = EngineSpeedModel(program=old.program, engine=old.engine)
    new = EngineSpeedModel(program=new.program, engine=new.engine)
    rng = np.random.default_rng(12)
    for _ in range(30):
        args = random_speed_args(rng)
        assert old.run(**args) == new.run(**args)
        _same_trace(old.trace, new.trace)


def test_realloc_speed_program_same_trace():
    """The speed-loop program alone (the model reads its RESULTS registers after each run:
    ``keep``) with both allocations: the same results and traces over random runs."""
    old = EngineSpeedModel(program=speed_loop_program(realloc=False))
    new = EngineSpeedModel(program=speed_loop_program())
    rng = np.random.default_rng(5)
    for _ in range(60):
        args = random_speed_args(rng)
        assert old.run(**args) == new.run(**args)
        _same_trace(old.trace, new.trace)


def _boundary(gap, realloc=True):
    """``x`` written back in clock 3 (issued in 0), ``y`` issued in 4 (written back in 7), ``x``
    last read by the word issued in ``8 − gap`` (its R stage in ``7 − gap``): with ``gap = 0``
    ``y`` lands in the clock of that read (which would see ``y`` bypassed), with ``gap = 1`` a
    clock after it. The order as written (no scheduling, no folding)."""
    A = Assembler(specials=("s",), conds=(), outs=("ang", "o"))
    A.alu(Op.ADD, "r.x", "s.s", 1)
    A.nop(), A.nop(), A.nop()
    A.alu(Op.ADD, "r.y", "s.s", 2)
    for _ in range(3 - gap):
        A.nop()
    A.alu(Op.ADD, "r.z", "r.x", 0, out="o")
    A.nop(), A.nop(), A.nop()
    A.alu(Op.ADD, "r.w", "r.y", "r.z", out="o")
    A.end()
    return A.assemble(schedule=False, fold=False, realloc=realloc)


def test_realloc_pipeline_boundaries():
    """A write back in the clock of the last read of another register's value (the read sees
    the bypassed new value) interferes; one a clock later does not: ``x`` and ``y`` share a
    word only then. State (read before written: ``acc``) and registers with an initial value
    keep their own words, and the runs' results are those of the old allocation."""
    p0, p1 = _boundary(0), _boundary(1)
    assert p0.regs["x"] != p0.regs["y"]
    assert p1.regs["x"] == p1.regs["y"]
    for gap, p in ((0, p0), (1, p1)):
        for s in (5, -7):
            outs = []
            for prog in (p, _boundary(gap, realloc=False)):
                eng = EngineModel(prog, out_widths={"ang": 16, "o": 16})
                trace = eng.run({"s": s}, {})
                outs.append(([e["y"] for e in trace], eng.outs["o"]))
            assert outs[0] == outs[1]
    # State: acc is read (by its own update) before any write on the run's path.
    A = Assembler(specials=("s",), conds=(), outs=("ang", "o"))
    A.reg("g", init=3)
    A.alu(Op.ADD, "r.t", "s.s", "r.g")
    A.nop(), A.nop(), A.nop()
    A.alu(Op.ADD, "r.acc", "r.acc", "r.t", out="o")
    A.alu(Op.ADD, "r.u", "s.s", 1)
    A.nop(), A.nop(), A.nop()
    A.alu(Op.ADD, "r.v", "r.u", 1, out="o")
    A.end()
    p = A.assemble(schedule=False, fold=False, realloc=True)
    assert len({p.regs[n] for n in ("g", "acc")}) == 2
    assert p.regs["t"] not in (p.regs["g"], p.regs["acc"])
    assert p.regs["u"] not in (p.regs["g"], p.regs["acc"])
    eng = EngineModel(p, out_widths={"ang": 16, "o": 16})
    acc = []
    for s in (1, 2, 3):
        eng.run({"s": s}, {})
        acc.append(eng.rf[p.regs["acc"]])
    assert acc == [4, 9, 15]



def _div_repeats(realloc):
    """A DIV's divisor ``d`` is read in each of its repeats (R holds the word): ``e``, issued
    in the clock before the DIV's first issue (4), lands (7) in the R clock of its last repeat
    (issued in 8), so ``d`` and ``e`` must not share a word."""
    A = Assembler(specials=("s",), conds=(), outs=("ang", "o", "q"))
    A.alu(Op.ADD, "r.d", "s.s", 5)                  # issued in 0, written back in 3
    A.nop(), A.nop(), A.nop()
    A.alu(Op.ADD, "r.e", "s.s", 7)                  # issued in 4, written back in 7
    A.div("r.d", 4)                                 # issued in 5, 6, 7, 8 (reads in 4 … 7)
    A.nop(), A.nop(), A.nop()
    A.post(None, 0, rnd=False, out="q")
    A.alu(Op.ADD, None, "r.e", 0, out="o")
    A.end()
    return A.assemble(schedule=False, fold=False, realloc=realloc)


def test_realloc_div_repeats_read_the_divisor():
    """The divisor's live range runs to the last repeat of its DIV (a shorter one lets ``e``
    share ``d``'s word and the last steps divide by 7 + s)."""
    p = _div_repeats(True)
    assert p.regs["d"] != p.regs["e"]
    for s in (3, 100):
        res = []
        for prog in (p, _div_repeats(False)):
            eng = EngineModel(prog, out_widths={"ang": 16, "o": 16, "q": 16})
            eng.p = 1000 << 8
            trace = eng.run({"s": s}, {})
            res.append(([(e["y"], e["p"]) for e in trace], dict(eng.outs)))
        assert res[0] == res[1]


def test_realloc_combined_program_random_runs_same_trace():
    """The iCEBreaker's combined program (speed, refs, M/T) with both allocations on the
    interpreter: 300 runs from its three entries (0, ``speed``, ``mt``) in a random order with
    random specials (16-bit; ``udc``, ``ia``, ``ib`` and M/T's in plausible ranges) and random
    conditions, the state carried from run to run: every run's trace (but for ``dst``) and
    outputs equal, or both runs raise the same error (a value that does not fit its word: the
    over-modulation's DIV on random references; both engines then start afresh)."""
    from foc_servo.hdl.engine_mt import MT_OUTS, MT_RUN_SPECIALS
    from foc_servo.hdl.foc_engine import OUTS, REF_OUTS, SPEED_OUTS
    progs = [current_loop_program(speed=True, refs=True, mt=True, realloc=r)
             for r in (False, True)]
    widths = {**OUTS, **SPEED_OUTS, **REF_OUTS, **MT_OUTS}
    engs = [EngineModel(p, out_widths={n: widths[n] for n in p.outs[1:]}) for p in progs]
    prog = progs[0]
    user = prog.specials[len(BUILTIN_SPECIALS):]
    conds = prog.conds[len(BUILTIN_CONDS):]
    entries = [0, prog.labels["speed"], prog.labels["mt"]]
    assert entries == [0, progs[1].labels["speed"], progs[1].labels["mt"]]
    rng = np.random.default_rng(87)
    errors = 0
    for _ in range(300):
        start = int(rng.choice(entries))
        spec = {n: int(rng.integers(1, 1 << 11)) if n in MT_RUN_SPECIALS
                else int(rng.integers(10000, 30000)) if n == "udc"
                else int(rng.integers(-2000, 2000)) if n in ("ia", "ib")
                else int(rng.integers(-(1 << 15), 1 << 15)) for n in user}
        cond = {n: bool(rng.random() < 0.5) for n in conds}
        res = []
        for eng in engs:
            try:
                res.append((eng.run(spec, cond, start=start), dict(eng.outs)))
            except (ValueError, OverflowError) as e:
                res.append((str(e), None))
        if res[0][1] is None:
            errors += 1
            assert res[1][1] is None and res[0][0] == res[1][0]
            for eng, p in zip(engs, progs):         # start afresh after an error
                eng.__init__(p, out_widths=eng.out_widths)
            continue
        _same_trace(res[0][0], res[1][0])
        assert res[0][1] == res[1][1]
    assert errors < 100                     # (44 of 300: the DIV of the over-modulation)
