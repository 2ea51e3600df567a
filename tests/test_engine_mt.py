# Ref: docs/AREA.md §7.64; hdl/engine_mt.py; sim/models/mt_speed.py
"""M/T speed's arithmetic as a loop-engine program piece, on the interpreter, against
:class:`MTSpeedModel`'s arithmetic (``fresh_speed``) and its window outputs (``simulate``:
fresh, bounded and stopped updates), bit for bit, for ``out_width`` 32, ``k_width`` 48,
``m_width`` 16 and a 27-bit TC span."""

import numpy as np
import pytest

from foc_servo.hdl.engine import MUL_B, Assembler, Op
from foc_servo.hdl.engine_mt import (MT_ENGINE_PARAMS, MT_SAT, MT_SPECIALS, mt_k_slices,
                                     mt_k_words, mt_operands, mt_program, mt_run_timing)
from foc_servo.hdl.foc_engine import _clocks, _paths
from foc_servo.sim.models.engine import EngineModel
from foc_servo.sim.models.engine_mt import EngineMTModel
from foc_servo.sim.models.mt_speed import (BOUND, FRESH, STOPPED, MTParams, fresh_speed,
                                           simulate)

K_MAX = (1 << 48) - 1
M_MAX = 1 << 15
D_MAX = (1 << 27) - 1
PROGRAMS = {"straight": mt_program(), "branches": mt_program(branches=True)}


def _corners():
    """(k, ΔM, ΔT) at the edges of the arithmetic: ΔT = 0, ΔM = 0, k = 0 / 1 / max, |ΔM| =
    2**15, ΔT = 2**27 − 1, products at the saturation threshold ``k·|ΔM| = 2**31·ΔT`` ± 1,
    quotients at the 16-bit digit boundaries with remainders 0 and ΔT − 1."""
    rng = np.random.default_rng(7)
    cases = []
    for k in (0, 1, 2, K_MAX, K_MAX - 1, 1 << 47, (1 << 24) - 1, 1 << 24):
        for dm in (0, 1, -1, M_MAX - 1, -(M_MAX - 1), -M_MAX, 2, -2):
            for dt in (0, 1, 2, 3, D_MAX, D_MAX - 1, 1 << 26, 12345):
                cases.append((k, dm, dt))
    for _ in range(400):
        # k·m = 2**31·D + e at the saturation threshold (e = −1, 0, 1).
        m = int(rng.integers(1, M_MAX + 1))
        d = int(rng.integers(1, min(D_MAX, (K_MAX * m) >> 31) + 1))
        for e in (-1, 0, 1):
            n = (d << 31) + e
            if n % m == 0 and 0 <= n // m <= K_MAX:
                cases.append((n // m, m * int(rng.choice((1, -1))), d))
            k = n // m                                  # k·m just below / at the threshold
            if 0 <= k <= K_MAX:
                cases.append((k, m, d))
                cases.append((k + 1, -m, d) if k + 1 <= K_MAX else (k, -m, d))
    for _ in range(400):
        # N = q·D + r with q at digit boundaries (q1 = 0, 2**15 − 1; q2 = 0, 2**16 − 1).
        d = int(rng.integers(1, D_MAX + 1))
        q = int(rng.choice((0, 1, (1 << 16) - 1, 1 << 16, (1 << 31) - 1, (1 << 31) - 2,
                            (((1 << 15) - 1) << 16), ((1 << 15) - 1) << 16 | 0xFFFF)))
        r = int(rng.choice((0, d - 1)))
        n = q * d + r
        for m in (1, 2, 3, 1 << 15):
            if n % m == 0 and n // m <= K_MAX:
                cases.append((n // m, m, d))
                cases.append((n // m, -m, d))
    return cases


def _random(seed, n):
    rng = np.random.default_rng(seed)
    cases = []
    for _ in range(n):
        k = int(rng.integers(0, 1 << int(rng.integers(1, 49)), dtype=np.uint64))
        dm = int(rng.integers(-M_MAX, M_MAX + 1)) if rng.random() < 0.5 else \
            int(rng.integers(-8, 9))
        dt = int(rng.integers(0, 1 << int(rng.integers(1, 28))))
        cases.append((k, dm, dt))
    return cases


@pytest.mark.parametrize("variant", sorted(PROGRAMS))
def test_engine_mt_fresh_matches_the_model(variant):
    """Every fresh window's speed = ``fresh_speed`` (the gateware's arithmetic), bit for bit,
    over the corners and random operands; the interpreter checks every value's width (the
    32-bit register file, the 45-bit P, the multiplier's operands, the DIV divisor)."""
    model = EngineMTModel(program=PROGRAMS[variant])
    cases = _corners() + _random(1, 1500)
    sat = zero = 0
    for k, dm, dt in cases:
        want = fresh_speed(k, dm, dt, out_width=32)
        got = model.update(k, FRESH, dm, dt)
        assert got == want, (k, dm, dt)
        sat += abs(want) == MT_SAT
        zero += want == 0
    # The stimulus reaches both ends (saturated and zero results, not only mid-range ones).
    assert sat > 300 and zero > 300 and len(cases) - sat - zero > 1000


def _window_stimulus(seed):
    """Edge strobes and update strobes with bursts (fresh windows, reversals), gaps between
    updates (bounded outputs), gaps beyond the 27-bit span (expiry: stopped) and back-to-back
    edges (ΔT = 1)."""
    rng = np.random.default_rng(seed)
    edges, negs, ups = [], [], []
    c, u = 10, 5
    neg = False
    for _ in range(300):
        r = rng.random()
        if r < 0.05:
            c += int(rng.integers(1 << 26, 1 << 28))        # a stop (or near one)
        elif r < 0.3:
            c += int(rng.integers(1, 4))                    # back to back
        else:
            c += int(rng.integers(1, 1 << int(rng.integers(1, 24))))
        if rng.random() < 0.08:
            neg = not neg
        edges.append(c)
        negs.append(neg)
    end = c + (1 << 28)
    while u < end:
        ups.append(u)
        u += int(rng.integers(100, 1 << int(rng.integers(8, 26))))
    return np.array(edges), np.array(negs), np.array(ups)


@pytest.mark.parametrize("seed", range(4))
def test_engine_mt_windows_match_the_model(seed):
    """``simulate`` (the window logic that stays in gateware, with the 27-bit TC) gives each
    update's mode and operands; the piece, run once per update with its last output kept in
    the engine, gives ``simulate``'s speed for every update: fresh, bounded (the last output
    bounded by ``k/elapsed``) and stopped."""
    params = MTParams(tclk_ratio=1, **MT_ENGINE_PARAMS)
    edges, negs, ups = _window_stimulus(seed)
    rng = np.random.default_rng(100 + seed)
    for k in (int(rng.integers(1 << 30, 1 << 40)), K_MAX, 1):
        out = simulate(edges, negs, ups, k=k, params=params)
        modes = set(zip(out["stopped"].tolist(), out["fresh"].tolist()))
        assert modes == {(1, 0), (0, 1), (0, 0)}, modes       # stopped, fresh, bounded
        got = EngineMTModel().replay(out, k)
        bad = np.flatnonzero(got != out["speed"])
        assert bad.size == 0, (k, bad[:5], got[bad[:5]], out["speed"][bad[:5]])


def test_engine_mt_bounded_and_stopped_updates():
    """Directly: a bounded update keeps the last output when ``k/elapsed`` is not below its
    magnitude, else gives ``±k/elapsed`` with the last output's sign; a stopped one reads 0
    (and a later bounded one is bounded by that 0)."""
    m = EngineMTModel()
    k = 1 << 40
    assert m.update(k, FRESH, -3, 1 << 20) == -((3 << 40) >> 20)
    assert m.update(k, BOUND, 1, 1 << 18) == -((3 << 40) >> 20)      # bound 2**22 ≥ 3·2**20
    assert m.update(k, BOUND, 1, 1 << 22) == -(1 << 18)               # bound 2**18 < 3·2**20
    assert m.update(k, BOUND, 1, 0) == -(1 << 18)                     # bound saturated
    assert m.update(k, FRESH, 5, 0) == MT_SAT
    assert m.update(k, BOUND, 1, 1) == MT_SAT
    assert m.update(k, STOPPED, 0, 0) == 0
    assert m.update(k, BOUND, 1, 1) == 0


def test_engine_mt_operands_and_k_slices():
    assert mt_operands(FRESH, -7, 99, 5) == {"mtm": 7, "mtd": 99, "mts": 1, "mtb": 0}
    assert mt_operands(FRESH, 0, 0, 5) == {"mtm": 0, "mtd": 1, "mts": 0, "mtb": 0}
    assert mt_operands(BOUND, 1, 40, -5) == {"mtm": 1, "mtd": 40, "mts": 1, "mtb": 1}
    assert mt_operands(STOPPED, 3, 40, -5) == {"mtm": 0, "mtd": 1, "mts": 0, "mtb": 0}
    assert mt_k_slices(K_MAX) == {"mkl": (1 << 24) - 1, "mkh": (1 << 24) - 1}
    for args, msg in (((FRESH, (1 << 15) + 1, 3, 0), "at most 2\\*\\*15"),
                      ((FRESH, 1, 1 << 27, 0), "from 0 to 2\\*\\*27"),
                      ((FRESH, 1, -1, 0), "from 0 to 2\\*\\*27"),
                      ((7, 1, 1, 0), "STOPPED, BOUND or FRESH")):
        with pytest.raises(ValueError, match=msg):
            mt_operands(*args)
    for k in (-1, 1 << 48, 1.5, True):
        with pytest.raises(ValueError, match="k must be an integer"):
            mt_k_slices(k)


def test_engine_div_divisor_is_the_multipliers_b_operand():
    """The interpreter refuses a DIV divisor beyond the multiplier's signed 28-bit B operand
    (the gateware divides by ``prod[:MUL_B]``, the product 1·B): the reason for the 27-bit
    TC span."""
    A = Assembler(specials=(), conds=(), outs=("ang",))
    A.div("r.d", 1)
    A.end()
    prog = A.assemble()
    eng = EngineModel(prog, out_widths={"ang": 16})
    eng.rf[prog.regs["d"]] = (1 << (MUL_B - 1)) - 1
    eng.run({}, {})
    eng.rf[prog.regs["d"]] = 1 << (MUL_B - 1)
    with pytest.raises(OverflowError, match="DIV divisor"):
        eng.run({}, {})


def test_engine_mt_program_size():
    """The figures of docs/AREA.md §7.64: words, NOPs, clocks per run (every path), and the
    run's timing: the speed in place 101 clocks after the start (MTSpeed: 38), the engine free
    99 clocks after it."""
    sizes = {}
    for name, prog in PROGRAMS.items():
        ins = prog.instrs
        sizes[name] = (len(ins), sum(i.op == Op.NOP for i in ins),
                       sorted(sum(_clocks(ins[pc]) for pc in p) for p in _paths(prog)))
    # (Unfolded, §7.64: 59 words with 22 NOPs, 58 with 24; NOP folding, §7.81, the clocks
    # unchanged.)
    assert sizes == {"straight": (38, 1, [96]), "branches": (36, 2, [35, 94])}
    assert set(PROGRAMS["straight"].specials) >= set(MT_SPECIALS)
    assert mt_run_timing(PROGRAMS["straight"]) == [(101, 99)]
    assert mt_run_timing(PROGRAMS["branches"]) == [(40, 38), (99, 97)]


def test_engine_mt_on_the_gateware_engine_cycle_by_cycle():
    """The piece on the gateware :class:`Engine` (its specials as ports, shaped as
    :data:`MT_SHAPES`) against :class:`EngineMTModel`: every executed instruction's write back
    (pc, P, destination, value) in the same clock, and the output ``mtspd`` after each END,
    over updates in sequence (the state register kept in the register file): saturated and
    not, ΔT up to 2**27 − 1 (the DIV divisor's limit in the gateware too), bounded and
    stopped ones."""
    from foc_servo.hdl.engine import Engine
    from foc_servo.hdl.engine_mt import MT_OUTS, MT_SHAPES
    from foc_servo.sim.harness import simulate as hdl_simulate
    from foc_servo.sim.models.engine import _complete

    from engine_trace import start_and_follow

    prog = PROGRAMS["straight"]
    dut = Engine(program=prog, special_shapes=MT_SHAPES, out_widths=MT_OUTS)
    model = EngineMTModel(program=prog)
    jobs = [(K_MAX, FRESH, -M_MAX, 1), (K_MAX, FRESH, 3, D_MAX), (1, FRESH, 1, D_MAX),
            (0, FRESH, 5, 0), (1 << 40, FRESH, -3, 1 << 20), (1 << 40, BOUND, 1, 1 << 18),
            (1 << 40, BOUND, 1, 1 << 22), (1 << 40, STOPPED, 0, 0), (1 << 40, BOUND, 1, 7)]
    jobs += [(k, FRESH, dm, dt) for k, dm, dt in _random(9, 30)]
    jobs += [(k, FRESH, dm, dt) for k, dm, dt in _corners()[::180]]
    errors, done = [], [0]

    async def testbench(ctx):
        for n, (k, mode, dm, dt) in enumerate(jobs):
            want = model.update(k, mode, dm, dt)
            spec = {**mt_k_slices(k), **mt_operands(mode, dm, dt, last[0])}
            last[0] = want
            spec, _ = _complete(prog, spec, {})
            for name in MT_SHAPES:
                ctx.set(getattr(dut, f"s_{name}"), spec[name])
            error, _ = await start_and_follow(ctx, dut, model.trace)
            if error is not None:
                errors.append((n, *error))
                return
            await ctx.tick()
            if ctx.get(dut.o_mtspd) != want % (1 << 32):
                errors.append((n, "mtspd", ctx.get(dut.o_mtspd), want))
            done[0] += 1

    last = [0]
    hdl_simulate(dut, [testbench], name="engine_mt")
    assert errors == []
    assert done[0] == len(jobs)


def test_engine_mt_run_in_the_current_loop_engine_cycle_by_cycle():
    """The run ``mt`` of ``EngineCurrentLoop(mt=True)`` (the current loop's program with the
    M/T piece at the label ``mt``, ``k`` as the two configuration words ``mtk0``, ``mtk1``
    written through the ``config`` port as the register file's export port writes ``mt_k``)
    against :class:`EngineMTModel` on the same program: every executed instruction's write
    back (pc, P, destination, value) in the same clock, ``mt_res`` (the output ``mtspd``
    and its write strobe) after each run; updates in sequence (``mt_pm`` kept), ``k`` with bit
    31 set (``mtk0`` negative as the engine reads it), saturated, bounded and stopped."""
    from foc_servo.hdl.engine_mt import MT_CONFIG_WORDS
    from foc_servo.hdl.foc_engine import CONFIG, OUTS, EngineCurrentLoop
    from foc_servo.sim.harness import simulate as hdl_simulate

    from engine_trace import follow_trace

    cl = EngineCurrentLoop(config="ram", mt=True)
    prog = cl.program
    assert prog.labels["mt"] > 0 and cl.mt_timing == mt_run_timing(prog)
    model = EngineMTModel(program=prog, out_widths={**OUTS, "mtspd": 32})
    jobs = [(K_MAX, FRESH, -M_MAX, 1), (K_MAX, FRESH, 3, D_MAX), ((1 << 31) | 5, FRESH, 7, 999),
            (1, FRESH, 1, D_MAX), (0, FRESH, 5, 0), (1 << 40, FRESH, -3, 1 << 20),
            (1 << 40, BOUND, 1, 1 << 18), (1 << 40, BOUND, 1, 1 << 22), (1 << 40, STOPPED, 0, 0),
            (1 << 40, BOUND, 1, 7), ((1 << 48) - (1 << 31), FRESH, 2, 3)]
    jobs += [(k, FRESH, dm, dt) for k, dm, dt in _random(11, 20)]
    errors, done, last = [], [0], [0]
    cfg = {name: len(CONFIG) + j for j, name in enumerate(MT_CONFIG_WORDS)}

    async def testbench(ctx):
        eng = cl.engine
        for n, (k, mode, dm, dt) in enumerate(jobs):
            for name, v in mt_k_words(k).items():
                ctx.set(cl.config.valid, 1)
                ctx.set(cl.config.index, cfg[name])
                ctx.set(cl.config.data, v % (1 << 32))
                await ctx.tick()
            ctx.set(cl.config.valid, 0)
            want = model.update(k, mode, dm, dt)
            op = mt_operands(mode, dm, dt, last[0])
            last[0] = want
            ctx.set(cl.mt_run.payload, {"m": op["mtm"], "d": op["mtd"], "s": op["mts"],
                                        "b": op["mtb"]})
            ctx.set(cl.mt_run.valid, 1)
            await ctx.tick()
            ctx.set(cl.mt_run.valid, 0)
            error, _ = await follow_trace(ctx, eng, model.trace)
            if error is not None:
                errors.append((n, *error))
                return
            for _ in range(8):
                await ctx.tick()
            if (strobes[0], ctx.get(cl.mt_res.payload)) != (n + 1, want):
                errors.append((n, "mt_res", strobes[0], ctx.get(cl.mt_res.payload), want))
            done[0] += 1

    strobes = [0]

    async def count(ctx):
        async for *_, valid in ctx.tick().sample(cl.mt_res.valid):
            strobes[0] += valid

    hdl_simulate(cl, [testbench], [count], name="engine_mt_run")
    assert errors == []
    assert done[0] == len(jobs)


def test_engine_mt_run_start_arbitration():
    """``EngineCurrentLoop(mt=True)``: a current-loop sample and an M/T request in the same
    clock (the sample's program first, the M/T run at its END), an M/T request while the
    current loop runs (it waits for the END), a sample while the M/T run runs (latched, its
    program at the M/T run's END). The duties equal those of the same loop without the M/T run
    fed the same samples (alone, undelayed), every M/T result the interpreter's."""
    from amaranth.hdl import Module

    from foc_servo.hdl.foc_engine import CONFIG, OUTS, EngineCurrentLoop
    from foc_servo.sim.harness import simulate as hdl_simulate

    rng = np.random.default_rng(5)
    init = [int(rng.integers(0, 1 << 14)) for _ in CONFIG]
    k = (1 << 40) + 12345
    kw = mt_k_words(k)
    cl = EngineCurrentLoop(config="ram", mt=True,
                           config_init=init + [kw["mtk0"] % (1 << 32), kw["mtk1"]])
    ref = EngineCurrentLoop(config="ram", config_init=init)
    m = Module()
    m.submodules.cl, m.submodules.ref = cl, ref
    model = EngineMTModel(program=cl.program, out_widths={**OUTS, "mtspd": 32})
    mt_at = cl.program.labels["mt"]
    # (clock offsets: sample, M/T request) per scenario
    plan = [(0, 0), (0, 50), (30, 0)]
    starts, ends, duties, ref_duties, results, want = [], [], [], [], [], []

    async def record(ctx):
        eng = cl.engine
        clock, after = 0, 0
        async for _, _, go, run, pc, v, p, rv, rp, mv, mp, end in ctx.tick().sample(
                eng.start, eng.running, eng.start_pc, cl.o.valid, cl.o.payload, ref.o.valid,
                ref.o.payload, cl.mt_res.valid, cl.mt_res.payload, eng.end):
            if end:
                ends.append(clock)
            if go and not run:
                starts.append((clock, pc))
            if v:
                duties.append(p.as_value().value)
            if rv:
                ref_duties.append(rp.as_value().value)
            if after:                   # (the register holds the result the clock after
                results.append(mp)      # its write strobe)
            after = mv
            clock += 1

    async def testbench(ctx):
        for dut in (cl, ref):
            ctx.set(dut.o.ready, 1)
        last = 0
        for n, (t_sample, t_mt) in enumerate(plan):
            sample, values = _sample(rng)
            op = mt_operands(FRESH, 3 + n, 1000 + n, last)
            last = model.update(k, FRESH, 3 + n, 1000 + n)
            want.append(last)
            for c in range(max(t_sample, t_mt) + 1):
                if c == t_sample:
                    for dut in (cl, ref):
                        ctx.set(dut.i.payload, sample)
                        for name, v in values.items():
                            ctx.set(getattr(dut, name), v)
                        ctx.set(dut.i.valid, 1)
                if c == t_mt:
                    ctx.set(cl.mt_run.payload, {"m": op["mtm"], "d": op["mtd"],
                                                "s": op["mts"], "b": op["mtb"]})
                    ctx.set(cl.mt_run.valid, 1)
                await ctx.tick()
                for dut in (cl, ref):
                    ctx.set(dut.i.valid, 0)
                ctx.set(cl.mt_run.valid, 0)
            for _ in range(800):
                await ctx.tick()

    hdl_simulate(m, [testbench], [record], name="engine_mt_arbitration")
    assert results == want and len(want) == 3
    assert duties == ref_duties and len(duties) == 3
    pcs = [pc for _, pc in starts]
    assert pcs == [0, mt_at, 0, mt_at, mt_at, 0], starts
    # The waits: each second start in its scenario comes right after the first run's END
    # (the engine takes the next start a clock before its end strobe, as back to back samples
    # do), the M/T run's at its length.
    for i in (0, 2, 4):
        end = min(e for e in ends if e > starts[i][0])
        assert starts[i + 1][0] == end - 1, (i, starts, ends)
    assert starts[5][0] - starts[4][0] == max(length for _, length in cl.mt_timing)


def _sample(rng):
    sample = {"ia": int(rng.integers(-2000, 2000)), "ib": int(rng.integers(-2000, 2000)),
              "udc": int(rng.integers(10000, 30000)), "aux": 0}
    values = {"theta": int(rng.integers(1 << 16)), "enable": 1, "ol_enable": 0,
              "ff_enable": 1, "speed": int(rng.integers(-(1 << 30), 1 << 30)),
              "id_ref": 100, "iq_ref": -300, "scale": 1000}
    return sample, values
