# Tests of hdl/engine.py (loop engine), hdl/foc_engine.py (the current loop as its program) and
# sim/models/engine.py (the interpreter): program vs CurrentLoopModel (bit-identical), gateware vs
# interpreter (cycle by cycle), EngineCurrentLoop vs CurrentLoopModel (through the CurrentLoop
# verification bench).
import dataclasses
import gc
import warnings

import numpy as np
import pytest
from amaranth.hdl import Elaboratable, Module, UnusedElaboratable, signed, unsigned

from foc_servo.hdl.engine import (HAZARD_P, HAZARD_RF, P_WORD, SAT_NONE, SAT_W, SAT_W1, WORD,
                                  Assembler, Engine, Op)
from foc_servo.hdl.foc import CurrentLoop
from foc_servo.hdl.foc_engine import (DUTY_CLOCKS, OUTS, SPECIALS, EngineCurrentLoop, _paths,
                                      current_loop_program, duty_lengths, path_lengths)
from foc_servo.sim.harness import simulate
from foc_servo.sim.models.engine import (EngineLoopModel, EngineModel, lead_angle,
                                         loop_model_inputs)
from foc_servo.sim.models.foc import OUTPUT_FIELDS, CurrentLoopModel
from foc_servo.sim.models.rotator import rotate_ideal
from foc_servo.sim.models.svpwm import dcbus_gain
from foc_servo.sim.verify import foc as verify_foc

from engine_trace import random_speed_args, start_and_follow


def _engine_vec(vec):
    """The engine's inputs for a CurrentLoop stimulus: its random 16-bit ``theta_lead`` column
    taken as the ``lead_k`` register (θ_lead then follows from the speed, as in the program)."""
    out = {k: v for k, v in vec.items() if k != "theta_lead"}
    out["lead_k"] = np.asarray(vec["theta_lead"]) % (1 << 16)
    return out


def _compare(vec, program=None, gain_limit=2.0):
    """``vec``: the engine's inputs (``lead_k``); the model runs on the equivalent θ_lead."""
    exp = CurrentLoopModel(gain_limit=gain_limit).run(**loop_model_inputs(vec))
    em = EngineLoopModel(program=program, gain_limit=gain_limit)
    got = em.run(**vec)
    bad = {k: int(np.sum(np.asarray(exp[k]) != np.asarray(got[k]))) for k in OUTPUT_FIELDS}
    return exp, got, {k: v for k, v in bad.items() if v}, em


# --- the program on the interpreter against the current loop's golden model ---------------------

def test_program_bit_identical_to_current_loop_model():
    vec = _engine_vec(verify_foc.stimulus(1500, seed=11))   # random segments + the corners
    exp, got, bad, em = _compare(vec)
    assert bad == {}
    # Coverage: every path of the program ran, every flag was seen both ways.
    assert {len(t) for t in em.traces} == set(path_lengths(em.program))
    for k in ("overmod", "sat_d", "sat_q", "dc_limited"):
        assert 0 < exp[k].sum() < len(exp[k]), k


def test_program_corners():
    """Saturating references, limits hit, inverted and zero-width limits, zero and negative U_dc,
    over-modulation, θ wrap, ff on/off, open loop, enable low (PI cleared)."""
    vec = _engine_vec(verify_foc.stimulus(0, seed=3))
    n = vec["ia"].size
    rng = np.random.default_rng(5)
    extra = {k: np.copy(v) for k, v in vec.items()}
    extra["theta"] = np.where(rng.random(n) < 0.5, 0xFFFF, 0)
    extra["speed"] = np.where(rng.random(n) < 0.5, (1 << 31) - 1, -(1 << 31))
    extra["lead_k"] = np.full(n, 2)                       # θ_lead = ±2: θ + θ_lead wraps
    assert set(lead_angle(extra["speed"], 2)) == {2, (1 << 16) - 2}
    extra["udc"] = np.where(rng.random(n) < 0.5, -1, 0)
    extra["ff_enable"] = 1 - vec["ff_enable"]
    for v in (vec, extra):
        _, _, bad, _ = _compare(v)
        assert bad == {}


def _gain_cases(rng, limit_raw):
    """(U_rated, U_dc) pairs: corners (U_dc 0, negative, tiny, > U_rated, full scale; U_rated 0
    and full scale), the exact limit boundary (gain L and L + 1), rounding ties, random."""
    cases = [(r, u) for r in (0, 1, 16000, 32767, 65535) for u in (-32768, -1, 0, 1, 2, 3)]
    cases += [(r, u) for r in (0, 1, 1000, 16000, 32767, 65535)
              for u in (r // 2, r - 1, r, r + 1, 2 * r, 32767) if 0 <= u < 32768]
    for r in (1000, 16000, 32767, 65535):
        for u in range(max(1, (r << 16) // (limit_raw + 1) - 2),
                       (r << 16) // max(limit_raw - 1, 1) + 3):
            if u < 32768:
                cases.append((r, u))                 # gain around L: limited or not
    exact = 0
    for u in range(1, 32768):                        # gain exactly L, not limited
        r = -(-(limit_raw * u - u // 2) >> 16)
        if r < 65536 and ((r << 16) + u // 2) // u == limit_raw:
            cases += [(r, u), (r, u + 1), (r + 1, u)]
            exact += 1
            if exact == 5:
                break
    for _ in range(200):                             # ties: R·2**17 + U = (2q + 1)·U ± …
        u = int(rng.integers(1, 32768))
        q = int(rng.integers(1 << 15, min(limit_raw, 65535 * 65536 // u) + 1))
        r = (q * u) >> 16
        cases += [(r, u), (min(r + 1, 65535), u)]
    cases += [(int(rng.integers(0, 1 << 16)), int(rng.integers(-100, 1 << 15)))
              for _ in range(300)]
    return cases


@pytest.mark.parametrize("gain_limit", [2.0, 1.0, 1.5, 3.99])
def test_program_dc_bus_gain_is_exact(gain_limit):
    """The gain the program computes after the duties (register ``dcg``) equals the DC-bus
    block's ``min(round(U_rated·2**16 / U_dc), L)`` (half up; U_dc ≤ 0: L) to the LSB, with
    the ``dc_limited`` flag, over the corners, the limit boundary and rounding ties; the next
    sample is compensated with it (every output bit-identical to CurrentLoopModel)."""
    rng = np.random.default_rng(17)
    limit_raw = round(gain_limit * (1 << 16))
    cases = _gain_cases(rng, limit_raw)
    vec = _engine_vec(verify_foc.stimulus(0, seed=1))
    k = np.arange(len(cases)) % vec["ia"].size
    vec = {name: np.asarray(col)[k] for name, col in vec.items()}
    vec["u_rated"] = np.array([r for r, _ in cases])
    vec["udc"] = np.array([u for _, u in cases])
    exp, got, bad, em = _compare(vec, gain_limit=gain_limit)
    assert bad == {}
    want, limited = dcbus_gain(vec["u_rated"], np.maximum(vec["udc"], 0),
                               gain_limit_raw=limit_raw)
    # The gain computed from sample n is applied to sample n + 1.
    np.testing.assert_array_equal(got["dc_gain"][1:], want[:-1])
    assert em.dc_gain == want[-1]
    np.testing.assert_array_equal(got["dc_limited"], limited)
    assert got["dc_gain"][0] == 1 << 16                  # 1.0 at power-up
    assert 0 < limited.sum() < len(cases)
    assert ((want == limit_raw) & (limited == 0)).sum() >= 5   # gain L exactly, not limited


def test_program_dc_bus_gain_off_by_one_is_caught():
    """The gain check can fail: the division's rounding term floor(U/2) taken as round(U/2)
    (the gain 1 LSB high for some odd U_dc) shows up in the gain comparison."""
    prog = current_loop_program()
    regs = prog.regs
    words = list(prog.words)
    k = next(i for i, ins in enumerate(prog.instrs)
             if ins.wen and ins.dst == regs["uh"] and ins.sh == 9)
    words[k] = dataclasses.replace(prog.instrs[k], rnd=1).encode()
    broken = dataclasses.replace(prog, words=words)
    rng = np.random.default_rng(17)
    cases = _gain_cases(rng, 2 << 16)
    want, _ = dcbus_gain([r for r, _ in cases], [max(u, 0) for _, u in cases],
                         gain_limit_raw=2 << 16)
    em = EngineLoopModel(program=broken)
    vec = _engine_vec(verify_foc.stimulus(0, seed=1))
    idx = np.arange(len(cases)) % vec["ia"].size
    vec = {name: np.asarray(col)[idx] for name, col in vec.items()}
    vec["u_rated"] = np.array([r for r, _ in cases])
    vec["udc"] = np.array([u for _, u in cases])
    got = em.run(**vec)
    diff = np.asarray(got["dc_gain"][1:]) - want[:-1]
    assert set(diff) == {0, 1}


def test_program_widest_values_fit_the_words():
    """The 32-bit register file (``WORD``) holds the widest value, the PI's ``kp·E``, at its
    extremes (kp = 65 535, E = ±full scale); the interpreter would raise OverflowError on a
    write that does not fit (and on P beyond ``P_WORD``), and the results match the model."""
    vec = _engine_vec(verify_foc.stimulus(0, seed=3))
    n = vec["ia"].size
    ext = {k: np.copy(v) for k, v in vec.items()}
    ext.update(kp_d=np.full(n, 65535), kp_q=np.full(n, 65535), enable=np.ones(n, np.int64),
               ol_enable=np.zeros(n, np.int64),
               id_ref=np.where(np.arange(n) % 2, 32767, -32768),
               iq_ref=np.where(np.arange(n) % 2, -32768, 32767))
    exp, got, bad, em = _compare(ext)
    assert bad == {}
    widest = max(max(abs(t["y"]) for t in tr if t["y"] is not None) for tr in em.traces)
    assert 1 << 30 < widest < 1 << (WORD - 1)


def test_program_breaks_when_changed():
    """The comparison can fail: one rounding flag flipped in the program shows up."""
    prog = current_loop_program()
    words = list(prog.words)
    k = next(i for i, ins in enumerate(prog.instrs) if ins.rnd and ins.sh == 15)   # Clarke a
    words[k] = dataclasses.replace(prog.instrs[k], rnd=0).encode()
    broken = dataclasses.replace(prog, words=words)
    _, _, bad, _ = _compare(_engine_vec(verify_foc.stimulus(100, seed=2)), program=broken)
    assert bad.get("a", 0) > 0


def test_fused_posts_change_nothing_but_length():
    """The assembler's peephole (a post fused into the next MUL) against the plain program."""
    plain = current_loop_program(fuse=False)
    fused = current_loop_program()
    assert len(fused.words) < len(plain.words)
    assert all(a < b for a, b in zip(path_lengths(fused), path_lengths(plain)))
    vec = _engine_vec(verify_foc.stimulus(200, seed=6))
    a = EngineLoopModel(program=plain).run(**vec)
    b = EngineLoopModel(program=fused).run(**vec)
    for k in OUTPUT_FIELDS:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


def test_scheduled_program_changes_nothing_but_length():
    """The assembler's list scheduling (straight-line code reordered to fill the hazard
    distances) against the program in written order: same outputs, fewer clocks."""
    plain = current_loop_program(schedule=False)
    sched = current_loop_program()
    assert all(a < b for a, b in zip(path_lengths(sched), path_lengths(plain)))
    vec = _engine_vec(verify_foc.stimulus(200, seed=8))
    a = EngineLoopModel(program=plain).run(**vec)
    b = EngineLoopModel(program=sched).run(**vec)
    for k in OUTPUT_FIELDS:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


def test_program_park_against_float_rotation():
    """Independent check: i_d, i_q against the float Park of the engine's own α, β."""
    vec = _engine_vec(verify_foc.stimulus(300, seed=4))
    _, got, _, _ = _compare(vec)
    xf, yf = rotate_ideal(got["i_alpha"], got["i_beta"], (-vec["theta"]) % (1 << 16),
                          width=16, angle_width=16)
    sat = (np.abs(xf) > 32767) | (np.abs(yf) > 32767)
    assert np.max(np.abs(got["i_d"] - xf)[~sat]) < 1.2
    assert np.max(np.abs(got["i_q"] - yf)[~sat]) < 1.2


# --- ISA details on small programs ------------------------------------------------------------

def _small(build, fold=True):
    A = Assembler(specials=("x", "y"), bspecials=("y",), conds=(), outs=("ang", "r"))
    A.guard = 8
    build(A)
    A.end()
    prog = A.assemble(fold=fold)
    return prog, EngineModel(prog, out_widths={"ang": 16, "r": WORD})


def test_div_step_is_floor_division():
    rng = np.random.default_rng(1)
    for _ in range(200):
        d = int(rng.integers(1, 1 << 26))
        num = int(rng.integers(0, d << 16))             # quotient < 2**16

        def build(A):
            for _ in range(16):
                A.emit(Op.DIV, b=f"k.{d}")
            A.alu(Op.ADD, None, "s.PQ", 0, out="r")

        def build_rep(A):                               # the same 16 steps in one word
            A.div(f"k.{d}", 16)
            A.alu(Op.ADD, None, "s.PQ", 0, out="r")
        for b in (build, build_rep):
            prog, em = _small(b)
            em.p = num                                  # P is architectural state
            trace = em.run({"x": 0, "y": 0}, {})
            assert em.outs["r"] == num // d
            assert em.p >> 16 == num % d
            assert len(trace) == 16 + 1 + 1 + 1         # 16 steps, a NOP (HAZARD_P), ADD, END
        assert len(prog.words) == 4 and prog.instrs[0].sh == 15


def test_repeated_div_errors_and_program_size():
    """``Assembler.div``: 1 … 32 steps, not in a delay slot; the current-loop program fits the
    256-word ROM (4 block RAMs on the iCE40) with its DIVs repeated."""
    A = Assembler(specials=("x",), conds=(), outs=("ang",))
    with pytest.raises(ValueError, match=r"^Assembler: DIV steps must be from 1 to 32, not 33$"):
        A.div("r.d", 33)
    with pytest.raises(ValueError, match=r"^Assembler: DIV takes no operand A \(it is the "
                                         r"constant 1\), not 'r.x'$"):
        A.emit(Op.DIV, a="r.x", b="r.d")
    A.br("!F", "l")
    A.div("r.d", 2)
    A.nop()
    A.label("l")
    A.end()
    with pytest.raises(ValueError, match=r"^Assembler: a repeated DIV in a branch delay slot "
                                         r"at 1$"):
        A.assemble()
    prog = current_loop_program()
    assert len(prog.words) <= 256
    assert sorted(i.sh + 1 for i in prog.instrs if i.op == Op.DIV) == [16, 18]


def test_rounding_saturation_and_overflow_check():
    def build(A):
        A.alu(Op.ADD, None, "s.x", 0, sh=4, rnd=True, sat=SAT_W, out="r")
    _, em = _small(build)
    for x in (-24, -8, 8, 24, -(1 << 30), 1 << 30):
        em.run({"x": x, "y": 0}, {})
        r = em.outs["r"]
        r = r - (1 << WORD) if r >> (WORD - 1) else r
        want = int(np.sign(x)) * ((abs(x) + 8) >> 4)           # half away from zero
        assert r == max(-32768, min(32767, want))

    def build2(A):
        A.mul("s.x", "b.y")
    _, em = _small(build2)
    with pytest.raises(OverflowError, match="multiplier A"):
        em.run({"x": 1 << 18, "y": 1}, {})


def test_assembler_errors():
    A = Assembler(specials=("x",), conds=(), outs=("ang",))
    with pytest.raises(ValueError, match=r"^Assembler: special operand s.x only on A"):
        A.alu(Op.ADD, "r.t", 0, "s.x")
    with pytest.raises(ValueError, match=r"^Assembler: destination must be a register"):
        A.alu(Op.ADD, "s.x", 0, 0)
    with pytest.raises(ValueError, match=r"^Assembler: asl takes a special operand A only"):
        A.alu(Op.ADD, "r.t", "r.u", 0, asl=True)
    with pytest.raises(ValueError, match=r"^Assembler: rnd only with ADD, SUB, RSUB and the "
                                         r"posts, not with MIN, MAX or SEL$"):
        A.alu(Op.MIN, "r.t", "r.u", 0, sh=2, rnd=True)
    A.alu(Op.ADD, "r.t", 1 << 50, 0)
    with pytest.raises(ValueError, match=rf"^Assembler: constant \d+ does not fit {WORD} bits"):
        A.assemble()


def test_assembler_inserts_nops_and_rejects_slot_hazards():
    def build(A):
        A.alu(Op.ADD, "r.x", "s.x", 0)
        A.alu(Op.ADD, None, "r.x", 1, out="r")                # reads x at once: a NOP between
    prog, em = _small(build, fold=False)        # (folded: the ADD carries the NOPs as bubbles)
    assert HAZARD_RF == 4
    assert [Op(i.op) for i in prog.instrs] == [Op.ADD] + [Op.NOP] * 3 + [Op.ADD, Op.END]
    em.run({"x": 5, "y": 0}, {})
    assert em.outs["r"] == 6
    # Four-stage execute: a result is read from the fourth instruction after its writer on.
    def build2(A):
        A.alu(Op.ADD, "r.x", "s.x", 0)
        A.alu(Op.ADD, "r.y", "s.y", 0)
        A.alu(Op.ADD, "r.z", "r.x", "r.y", out="r")           # x: two NOPs, y: three
    prog, em = _small(build2, fold=False)
    assert [Op(i.op) for i in prog.instrs] == [Op.ADD, Op.ADD] + [Op.NOP] * 3 + [Op.ADD, Op.END]
    em.run({"x": 5, "y": 7}, {})
    assert em.outs["r"] == 12
    # P (written in X3) is read by a post in X2: one NOP between a MUL and a post of its
    # product; none between a MUL and a MAC (read in X3).
    def build_p(A):
        A.mul("s.x", "b.y")
        A.mac("s.x", 1)
        A.post(None, 0, rnd=False, out="r")
    prog, em = _small(build_p, fold=False)
    assert HAZARD_P == 2
    assert [Op(i.op) for i in prog.instrs] == [Op.MUL, Op.MUL, Op.NOP, Op.ADD, Op.END]
    em.run({"x": 5, "y": 7}, {})
    assert em.outs["r"] == 40
    # A delay slot that would need NOPs: they go in front of the branch.
    def build_slot(A):
        A.alu(Op.ADD, "r.x", "s.x", 0)
        A.br("!F", "l")
        A.alu(Op.ADD, None, "r.x", 1, out="r")                # delay slot: reads x
        A.nop()
        A.label("l")
    prog, em = _small(build_slot, fold=False)
    assert [Op(i.op) for i in prog.instrs][:5] == [Op.ADD, Op.NOP, Op.NOP, Op.BR, Op.ADD]
    em.run({"x": 5, "y": 7}, {})
    assert em.outs["r"] == 6

    # A hazard only on the branch path (the target reads a delay slot's result): the NOP goes
    # in front of the target, which both paths then execute.
    def build3(A):
        A.br("!F", "l")
        A.alu(Op.ADD, "r.x", "s.x", 0)
        A.alu(Op.ADD, "r.y", "s.y", 0)
        A.alu(Op.ADD, "r.x", "r.x", 1)                        # not taken: x written again
        A.alu(Op.ADD, "r.w", "s.y", 0)
        A.alu(Op.ADD, "r.w", "s.y", 1)
        A.label("l")
        A.alu(Op.ADD, None, "r.x", 0, out="r")
    prog, em = _small(build3, fold=False)
    target = prog.labels["l"]
    assert Op(prog.instrs[target].op) == Op.NOP
    em.run({"x": 5, "y": 7}, {})
    assert em.outs["r"] == 5
    A = Assembler(specials=("x",), conds=(), outs=("ang",))
    A.br("!F", "l")
    A.alu(Op.ADD, "r.x", "s.x", 0)
    A.alu(Op.ADD, "r.y", "r.x", 0)                            # in the second delay slot
    A.label("l")
    A.end()
    with pytest.raises(ValueError, match=r"^Assembler: hazard in a branch delay slot at 2"):
        A.assemble()


# --- NOP folding ---------------------------------------------------------------------------------

def _clock_trails(program, start=0):
    """Every path through ``program`` clock by clock (:func:`_paths`, each word expanded to
    its clocks): the instruction issued (``nb`` and ``tgt`` cleared: the addresses differ
    between the folded and the unfolded form) or ``None`` (a NOP or a bubble)."""
    trails, instrs = [], program.instrs
    for path in _paths(program, start):
        seq = []
        for pc in path:
            ins = instrs[pc]
            issued = None if ins.op == Op.NOP else dataclasses.replace(ins, nb=0, tgt=0)
            seq += [issued] * (ins.sh + 1 if ins.op == Op.DIV else 1) + [None] * ins.nb
        trails.append(seq)
    return trails


def _same_trace(folded, t_folded, unfolded, t_unfolded):
    """The interpreter's traces of one run of the folded and the unfolded form of a program:
    the same entry (write enable, destination, value, P) in every clock, a bubble or a NOP
    where the unfolded form executes a NOP, the same instruction elsewhere."""
    fi_, ui_ = folded.instrs, unfolded.instrs
    assert len(t_folded) == len(t_unfolded)
    for k, (f, u) in enumerate(zip(t_folded, t_unfolded)):
        fi, ui = fi_[f["pc"]], ui_[u["pc"]]
        if ui.op == Op.NOP:
            assert f["bubble"] or fi.op == Op.NOP, k
        else:
            assert not f["bubble"] and not u["bubble"], k
            assert dataclasses.replace(fi, nb=0, tgt=0) == dataclasses.replace(ui, tgt=0), k
        assert {n: f[n] for n in ("wen", "dst", "y", "p")} == \
            {n: u[n] for n in ("wen", "dst", "y", "p")}, k


def _mt(branches, fold):
    """:func:`~foc_servo.hdl.engine_mt.mt_program`, folded or not."""
    from foc_servo.hdl.engine_mt import MT_OUTS, MT_SPECIALS, mt_arith
    A = Assembler(specials=MT_SPECIALS, conds=(), outs=tuple(MT_OUTS))
    mt_arith(A, branches=branches)
    A.end()
    return A.assemble(fold=fold)


def test_folded_programs_take_the_same_clocks():
    """NOP folding (``Assembler.assemble(fold=True)``, the default) on the current-loop, speed,
    combined and M/T programs: every path issues the same instructions in the same clocks as
    the unfolded form (a bubble where it has a NOP), so every timing figure is the same; the
    words before and after (docs/ENGINE.md, AREA.md §7.81)."""
    from foc_servo.hdl.engine_mt import mt_run_timing
    from foc_servo.hdl.foc_engine import (REF_STATUS, STATUS, phase_latency, sample_read,
                                          speed_loop_program, speed_run_timing, status_quiet)
    progs = {
        "current": lambda fold: current_loop_program(fold=fold),
        "speed": lambda fold: speed_loop_program(fold=fold),
        "combined": lambda fold: current_loop_program(speed=True, fold=fold),
        "refs": lambda fold: current_loop_program(speed=True, refs=True, fold=fold),
        "mt": lambda fold: _mt(False, fold), "mt_branches": lambda fold: _mt(True, fold)}
    words = {}
    for name, make in progs.items():
        new, old = make(True), make(False)
        words[name] = (len(old.words), len(new.words), sum(i.op == Op.NOP for i in new.instrs))
        assert sum(i.op == Op.NOP for i in old.instrs) == \
            sum(i.nb for i in new.instrs) + sum(i.op == Op.NOP for i in new.instrs)
        assert all(i.nb == 0 for i in old.instrs)
        for label in ("", *old.labels):
            start = old.labels.get(label, 0)
            assert _clock_trails(new, new.labels.get(label, 0)) == \
                _clock_trails(old, start), (name, label)
        assert path_lengths(new) == path_lengths(old)
        if name in ("current", "combined", "refs"):
            assert duty_lengths(new) == duty_lengths(old)
            assert phase_latency(new) == phase_latency(old)
            assert sample_read(new) == sample_read(old)
            names = STATUS + REF_STATUS if name == "refs" else STATUS
            assert status_quiet(new, names) == status_quiet(old, names)
        if name in ("speed", "combined", "refs"):
            assert speed_run_timing(new) == speed_run_timing(old)
        if name.startswith("mt"):
            assert mt_run_timing(new) == mt_run_timing(old)
    assert words == {"current": (256, 184, 0), "speed": (244, 161, 0),
                     "combined": (500, 345, 0), "refs": (500, 350, 0),
                     "mt": (59, 38, 1), "mt_branches": (58, 36, 2)}


def test_folded_current_loop_runs_the_same_trace():
    """The current-loop and combined programs, folded and unfolded, on the interpreter: the
    same trace clock by clock (current-loop samples over every path; speed runs)."""
    vec = _engine_vec(verify_foc.stimulus(40, seed=12))
    for speed in (False, True):
        new = EngineLoopModel(program=current_loop_program(speed=speed))
        old = EngineLoopModel(program=current_loop_program(speed=speed, fold=False))
        a, b = new.run(**vec), old.run(**vec)
        for k in OUTPUT_FIELDS:
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)
        for tn, to in zip(new.traces, old.traces):
            _same_trace(new.program, tn, old.program, to)
        assert {len(t) for t in new.traces} <= set(path_lengths(new.program))
    from foc_servo.sim.models.engine import EngineSpeedModel
    new = EngineSpeedModel(program=new.program, engine=new.engine)
    old = EngineSpeedModel(program=old.program, engine=old.engine)
    rng = np.random.default_rng(12)
    for _ in range(20):
        args = random_speed_args(rng)
        assert new.run(**args) == old.run(**args)
        _same_trace(new.program, new.trace, old.program, old.trace)


def _fold_program(fold):
    """A small program with NOP runs of 1 … 5 after ALU, MUL, MAC and post words, around two
    branches (NOPs in both delay slots; a real first slot and a NOP in the second; NOPs after
    the second slot, on the fall-through path only; NOPs at a branch target) and after a DIV
    (neither folded)."""
    A = Assembler(specials=("x", "y"), bspecials=("y",), conds=("c1", "c2"),
                  outs=("ang", "r", "s", "t"))
    A.alu(Op.ADD, "r.a", "s.x", 0)
    A.nop()                                                   # ALU + 1
    A.alu(Op.ADD, "r.b", "s.y", 3)
    A.nop(), A.nop()                                          # ALU + 2
    A.mul("s.x", "b.y")
    A.nop(), A.nop(), A.nop()                                 # MUL + 3
    A.mac("s.x", 5, neg=True)
    A.nop()                                                   # MAC + 1
    A.post("r.c", 2)
    A.nop(), A.nop()                                          # post + 2
    A.alu(Op.ADD, "r.d", "r.a", "r.b", out="r")
    for _ in range(5):
        A.nop()                                               # ALU + 3, NOP + 1
    A.br("c1", "l1")
    A.nop(), A.nop()                                          # both slots: the BR + 2
    A.nop()                                                   # fall-through only
    A.alu(Op.ADD, "r.a", "r.a", 1)
    A.label("l1")
    A.nop()                                                   # a branch target
    A.nop()                                                   # + 1
    A.br("!c2", "l2")
    A.alu(Op.SUB, "r.e", "r.c", "r.d", setf=True)             # first slot + 1
    A.nop()
    A.nop(), A.nop()                                          # fall-through only
    A.alu(Op.ADD, "r.b", "r.b", 7, out="t")
    A.label("l2")
    A.alu(Op.SEL, "r.f", "r.a", "r.b", cond="N", out="s")
    A.nop(), A.nop(), A.nop()
    A.mul("r.f", 3)
    A.div("k.3", 2)
    A.nop(), A.nop()                                          # after a DIV: NOP + 1
    A.post("r.g", 1, rnd=True, out="r")
    A.nop()
    A.end()
    return A.assemble(schedule=False, fold=fold)


def test_fold_rules_and_the_engine_cycle_by_cycle():
    """NOP folding where it is exact and only there (:func:`_fold_program`): the hosts and
    their bubbles, the NOPs kept; the same clocks on every path as the unfolded form; the
    gateware ``Engine`` against the interpreter cycle by cycle (a bubble: ``trace_valid``
    low in its clock) for both forms over every branch combination."""
    new, old = _fold_program(True), _fold_program(False)
    assert _clock_trails(new) == _clock_trails(old)
    hosts = [(Op(i.op).name, i.nb) for i in new.instrs if i.nb]
    assert hosts == [("ADD", 1), ("ADD", 2), ("MUL", 3), ("MUL", 1), ("ADD", 2), ("ADD", 3),
                     ("NOP", 1), ("BR", 2), ("NOP", 1), ("SUB", 1), ("NOP", 1), ("ADD", 3),
                     ("SEL", 3), ("NOP", 1), ("ADD", 1)], hosts
    # Kept: the fourth NOP of a run of five (a host), the NOPs after the second delay slots
    # (one a host), the branch target's (a host), the NOP after the DIV (a host).
    assert [k for k, i in enumerate(new.instrs) if i.op == Op.NOP] == [6, 8, 10, 13, 18]
    assert len(new.words) == 21 and len(old.words) == 47
    assert Op(new.instrs[new.labels["l1"]].op) == Op.NOP
    widths = {"ang": 16, "r": WORD, "s": WORD, "t": WORD}
    shapes = {"x": signed(10), "y": signed(10)}
    rng = np.random.default_rng(18)
    runs = [({"x": int(rng.integers(-512, 512)), "y": int(rng.integers(-512, 512))},
             {"c1": c1, "c2": c2}) for c1 in (0, 1) for c2 in (0, 1) for _ in range(3)]
    for prog in (new, old):
        dut = Engine(program=prog, special_shapes=shapes, out_widths=widths)
        model = EngineModel(prog, out_widths=widths)
        errors = []

        async def testbench(ctx):
            for k, (spec, conds) in enumerate(runs):
                for name, val in spec.items():
                    ctx.set(getattr(dut, f"s_{name}"), val)
                for name, val in conds.items():
                    ctx.set(getattr(dut, f"c_{name}"), val)
                trace = model.run(spec, conds)
                error, _ = await start_and_follow(ctx, dut, trace)
                if error is not None:
                    errors.append((k, *error))
                    return
                await ctx.tick()
                for name in widths:
                    if ctx.get(getattr(dut, f"o_{name}")) != model.outs[name] % (1 << widths[name]):
                        errors.append((k, name))

        simulate(dut, [testbench], name="engine_fold")
        assert errors == []
    a, b = EngineModel(new, out_widths=widths), EngineModel(old, out_widths=widths)
    for spec, conds in runs:
        _same_trace(new, a.run(spec, conds), old, b.run(spec, conds))
        assert a.outs == b.outs and a.rf == b.rf and a.p == b.p


# --- gateware against the interpreter, cycle by cycle ------------------------------------------

def test_engine_hdl_matches_interpreter_cycle_by_cycle():
    prog = current_loop_program()
    dut = Engine(program=prog, special_shapes={n: signed(20) for n in SPECIALS},
                 out_widths=OUTS)
    model = EngineModel(prog, out_widths=OUTS)
    vec = _engine_vec(verify_foc.stimulus(60, seed=9))
    rng = np.random.default_rng(9)
    idx = np.concatenate([np.arange(60), rng.choice(np.arange(60, vec["ia"].size), 40,
                                                    replace=False)])
    samples = [EngineLoopModel.specials_of(vec, int(k)) for k in idx]
    errors, clocks = [], [0]

    async def testbench(ctx):
        for k, (spec, conds) in enumerate(samples):
            for name, val in spec.items():
                ctx.set(getattr(dut, f"s_{name}"), val)
            for name, val in conds.items():
                ctx.set(getattr(dut, f"c_{name}"), int(val))
            trace = model.run(spec, conds)
            error, cyc = await start_and_follow(ctx, dut, trace)
            if error is not None:
                errors.append((k, *error))
                return
            clocks[0] += cyc
            await ctx.tick()
            for name in OUTS:
                if ctx.get(getattr(dut, f"o_{name}")) != model.outs[name]:
                    errors.append((k, name))

    simulate(dut, [testbench], name="engine")
    assert errors == []
    assert clocks[0] > 100 * 90


def test_flag_outputs_need_an_unshifted_alu_result():
    """A 1-bit output is X ≠ 0 of an ALU operation with sh = 0 whose A is not P (the gateware
    tests the unshifted value in X4): other writes are refused by the gateware and the
    interpreter alike, with the output and the pc named."""
    def prog(build):
        A = Assembler(specials=("x",), bspecials=(), conds=(), outs=("ang", "f"))
        build(A)
        A.end()
        return A.assemble()
    widths = {"ang": 16, "f": 1}

    def check():
        ok = prog(lambda A: A.alu(Op.SUB, None, "s.x", 3, out="f"))
        Engine(program=ok, special_shapes={"x": signed(16)}, out_widths=widths)
        EngineModel(ok, out_widths=widths)
        for build, what in (
                (lambda A: A.alu(Op.ADD, None, "s.x", 0, sh=1, out="f"), "ADD with sh = 1"),
                (lambda A: A.post(None, 0, rnd=False, out="f"), "ADD with sh = 0 and A = P"),
                (lambda A: (A.mul("s.x", 1), A.mul("s.x", 1, out="f")), "MUL with sh = 0")):
            bad = prog(build)
            for make in (lambda: Engine(program=bad, special_shapes={"x": signed(16)},
                                        out_widths=widths),
                         lambda: EngineModel(bad, out_widths=widths)):
                with pytest.raises(ValueError, match=r"1-bit output 'f' at pc \d+ must be "
                                                     r"written by an ALU operation .*not " + what):
                    make()
    _built_for_signatures(check)


def _post_path_values(rng, n):
    """``n`` values of P (signed ``P_WORD`` bits) for the post-path test: around every power
    of two (the saturation thresholds ``2**(sh + sw − 1)`` and the split at ``2**(sh + WORD)``
    of the gateware's saturation test) with small offsets and rounding ties, and log-uniform."""
    lim = 1 << (P_WORD - 1)
    out = []
    for _ in range(n):
        k = int(rng.integers(0, P_WORD - 1))
        kind = rng.random()
        if kind < 0.5:
            v = (1 << k) + int(rng.integers(-3, 4))
        elif kind < 0.7 and k:
            v = (1 << k) + (1 << (k - 1)) * int(rng.integers(-1, 2)) + int(rng.integers(-1, 2))
        else:
            v = int(rng.integers(0, 1 << k)) if k else 0
        v = -v - int(rng.integers(0, 2)) if rng.random() < 0.5 else v
        out.append(max(-lim, min(lim - 1, v)))
    return out


def test_engine_hdl_post_path_matches_interpreter_cycle_by_cycle():
    """The post path (rounding add, barrel shift, saturation) of the gateware against the
    interpreter, every write back cycle by cycle: P near every power of two up to P_WORD bits
    (set exactly by a MUL and a MAC) through posts of every shift 0 … 31, floor and rounding,
    both saturation widths (and no saturation where the result fits WORD), and the ALU's
    33-bit sum with shifts 0 … 3 saturated, and PQ rounded by 1 … 17. The programs use only
    some of these shifts and saturation thresholds: this covers the rest of the shifter and of
    the saturation test."""
    A = Assembler(specials=("y1", "y2", "a", "b"), bspecials=("y1", "y2", "b"), conds=(),
                  outs=("ang",))
    A.mul(1 << 17, "b.y1")                          # P = 2**17 · (t >> 17) + (t mod 2**17)
    A.mac(1, "b.y2")
    i = 0
    for sat in (SAT_W, SAT_W1, SAT_NONE):
        for rnd in (False, True):
            for sh in range(32) if sat != SAT_NONE else range(P_WORD - WORD, 32):
                A.post(f"r.o{i % 8}", sh, rnd=rnd, sat=sat)
                i += 1
    for op in (Op.ADD, Op.SUB):
        for sat in (SAT_W, SAT_W1):
            for rnd in (False, True):
                for sh in range(4):
                    A.alu(op, f"r.o{i % 8}", "s.a", "b.b", sh=sh, rnd=rnd, sat=sat)
                    i += 1
    # PQ (P's low div_bits bits, never negative) rounded: its ties (P near powers of two)
    # need the rounding carry (AREA.md §7.74: the carry's PQ term dropped passes the rest).
    for sh in range(1, 18):
        A.alu(Op.ADD, f"r.o{i % 8}", "s.PQ", 0, sh=sh, rnd=True)
        i += 1
    A.end()
    prog = A.assemble()
    shapes = {"y1": signed(28), "y2": signed(28), "a": signed(32), "b": signed(32)}
    dut = Engine(program=prog, special_shapes=shapes, out_widths={"ang": 16})
    model = EngineModel(prog, out_widths={"ang": 16})
    rng = np.random.default_rng(16)
    ps = _post_path_values(rng, 60)
    words = [int(rng.choice([-1, 1])) * ((1 << int(rng.integers(0, 32))) + int(rng.integers(-2, 3)))
             for _ in range(2 * len(ps))]
    words = [max(-(1 << 31), min((1 << 31) - 1, v)) for v in words]
    errors = []

    async def testbench(ctx):
        for k, t in enumerate(ps):
            spec = {"y1": t >> 17, "y2": t & ((1 << 17) - 1), "a": words[2 * k],
                    "b": words[2 * k + 1]}
            for name, val in spec.items():
                ctx.set(getattr(dut, f"s_{name}"), val)
            trace = model.run(spec, {})
            error, _ = await start_and_follow(ctx, dut, trace)
            if error is not None:
                errors.append((k, t, *error))
                return
            await ctx.tick()

    simulate(dut, [testbench], name="engine_post")
    assert errors == []


# --- EngineCurrentLoop ---------------------------------------------------------------------------

def _random_sample(rng, *, config_ports):
    """One random ADC sample and per-sample inputs of :class:`EngineCurrentLoop` (with
    ``config_ports`` also ``lead_k`` and ``u_rated``, ports unless they are configuration
    words): ``(sample, values)``."""
    sample = {"ia": int(rng.integers(-32768, 32768)), "ib": int(rng.integers(-32768, 32768)),
              "udc": int(rng.integers(0, 32768)), "aux": 0}
    values = {"theta": int(rng.integers(1 << 16))}
    if config_ports:
        values["lead_k"] = int(rng.integers(1 << 16))
    values.update({"id_ref": int(rng.integers(-32768, 32768)),
                   "iq_ref": int(rng.integers(-32768, 32768)),
                   "ol_ud": int(rng.integers(-32768, 32768)),
                   "ol_uq": int(rng.integers(-32768, 32768)),
                   "enable": int(rng.random() < 0.8), "ol_enable": int(rng.random() < 0.2),
                   "ff_enable": int(rng.random() < 0.6),
                   "speed": int(rng.integers(-(1 << 31), 1 << 31))})
    if config_ports:
        values["u_rated"] = int(rng.integers(1 << 16))
    values["scale"] = int(rng.integers(1 << 16))
    return sample, values


def _built_for_signatures(check):
    """Run ``check``, whose components are built only for their signatures (no
    ``UnusedElaboratable`` warnings from them)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UnusedElaboratable)
        check()
        gc.collect()


def test_engine_current_loop_signature_and_parameters():
    _built_for_signatures(_check_signature_and_parameters)


def _check_signature_and_parameters():
    dut = EngineCurrentLoop()
    # CurrentLoop's ports, but the theta_lead register (lead_k) in place of θ_lead.
    mine = dict(dut.signature.members)
    theirs = dict(CurrentLoop().signature.members)
    assert mine.pop("lead_k").shape == theirs.pop("theta_lead").shape == unsigned(16)
    assert mine == theirs
    assert dut.latencies == [n + DUTY_CLOCKS for n in duty_lengths(dut.program)]
    assert dut.latency == max(dut.latencies) <= 240
    assert dut.interval == max(path_lengths(dut.program)) + 3 > dut.latency
    assert dut.gain_limit_raw == 2 << 16
    with pytest.raises(ValueError, match=r"^EngineCurrentLoop gain_limit must be at least 1.0 "
                                         r"and below 4.0, not 4.0$"):
        EngineCurrentLoop(gain_limit=4.0)
    with pytest.raises(TypeError, match=r"^EngineCurrentLoop gain_limit must be a number, "
                                        r"not 'x'$"):
        EngineCurrentLoop(gain_limit="x")
    with pytest.raises(ValueError, match=r"^EngineCurrentLoop width must be 16 \(the program is "
                                         r"written for it\), not 12$"):
        EngineCurrentLoop(width=12)
    with pytest.raises(ValueError, match=r"^EngineCurrentLoop int_guard must be 8 "):
        EngineCurrentLoop(int_guard=True)
    with pytest.raises(ValueError, match=r"^EngineCurrentLoop rotator must be one of table, "):
        EngineCurrentLoop(rotator="lut")


def test_engine_current_loop_against_model():
    """The CurrentLoop verification bench (sample ROM → dut → every output compared with
    CurrentLoopModel one clock after each transfer), with EngineCurrentLoop as the dut."""
    from amaranth.lib import data
    dut = EngineCurrentLoop()
    vec = _engine_vec(verify_foc.stimulus(40, seed=21))
    n = vec["ia"].size
    exp = CurrentLoopModel().run(**loop_model_inputs(vec))
    in_layout = data.StructLayout(verify_foc._input_shapes(dut))
    out_layout = data.StructLayout(verify_foc._output_shapes(dut))
    bench = verify_foc._CurrentLoopBench(dut, in_layout, verify_foc._pack(in_layout, vec, n),
                                         out_layout, verify_foc._pack(out_layout, exp, n))
    result = {}

    async def testbench(ctx):
        clocks = 0
        while ctx.get(bench.received) < n and clocks < n * (dut.latency + 2):
            await ctx.tick()
            clocks += 1
        for name in ("received", "mismatches", "first_mismatch"):
            result[name] = ctx.get(getattr(bench, name))
        result["overruns"] = ctx.get(dut.overruns)
        result["count"] = ctx.get(dut.count)

    simulate(bench, [testbench], name="engine_loop")
    assert result["received"] == n and result["count"] == n
    assert result["mismatches"] == 0, result
    assert result["overruns"] == 0


async def _clocks_until(ctx, valid, clocks, limit=300):
    """Tick until ``valid`` is high; returns ``clocks`` plus the ticks taken (at most ``limit``)."""
    while not ctx.get(valid):
        await ctx.tick()
        clocks += 1
        assert clocks < limit
    return clocks


def test_engine_current_loop_overrun_and_stalled_duties():
    dut = EngineCurrentLoop()
    seen = {}

    async def testbench(ctx):
        for name, value in {"gain_a": 1 << 15, "gain_b": 1 << 15, "kp_d": 256, "kp_q": 256,
                            "lim_lo_d": -1000, "lim_hi_d": 1000, "lim_lo_q": -1000,
                            "lim_hi_q": 1000, "u_rated": 20000, "scale": 2500,
                            "enable": 1, "iq_ref": 3000}.items():
            ctx.set(getattr(dut, name), value)
        ctx.set(dut.i.payload, {"ia": 100, "ib": -50, "udc": 20000, "aux": 0})
        ctx.set(dut.i.valid, 1)
        await ctx.tick()
        assert ctx.get(dut.busy)
        for _ in range(10):
            await ctx.tick()
        seen["overrun"] = ctx.get(dut.overrun)          # a sample while busy: dropped
        await ctx.tick()
        ctx.set(dut.i.valid, 0)
        seen["latency"] = await _clocks_until(ctx, dut.o.valid, 12)
        duties = ctx.get(dut.o.payload)
        for _ in range(20):                             # o.ready low: duties held, still busy
            await ctx.tick()
            assert ctx.get(dut.o.valid) and ctx.get(dut.busy)
            assert ctx.get(dut.o.payload) == duties
        ctx.set(dut.o.ready, 1)
        assert ctx.get(dut.done)
        await ctx.tick()
        ctx.set(dut.o.ready, 0)
        seen.update(count=ctx.get(dut.count), busy=ctx.get(dut.busy),
                    overruns=ctx.get(dut.overruns), valid=ctx.get(dut.o.valid))

    simulate(dut, [testbench], name="engine_overrun")
    assert seen == {"overrun": 1, "latency": seen["latency"], "count": 1, "busy": 0,
                    "overruns": 11, "valid": 0}     # i.valid held 11 clocks while busy
    assert seen["latency"] in dut.latencies


@pytest.mark.parametrize("loop", ["pipelined", "engine"])
def test_phase_latency_attribute(loop):
    """``phase_latency`` of both loops (the top's dead-time compensation relies on it) against
    the clocks from the accepted sample to ``phase.valid`` in simulation."""
    dut = CurrentLoop() if loop == "pipelined" else EngineCurrentLoop()
    seen = {}

    async def testbench(ctx):
        ctx.set(dut.gain_a, 1 << 15)
        ctx.set(dut.gain_b, 1 << 15)
        ctx.set(dut.i.payload, {"ia": 100, "ib": -50, "udc": 20000, "aux": 0})
        ctx.set(dut.i.valid, 1)
        await ctx.tick()
        ctx.set(dut.i.valid, 0)
        seen["clocks"] = await _clocks_until(ctx, dut.phase.valid, 1)
        seen["phase"] = ctx.get(dut.phase.payload)

    simulate(dut, [testbench], name=f"phase_latency_{loop}")
    assert seen["clocks"] == dut.phase_latency
    assert seen["phase"] == {"a": 100, "b": -50, "c": -50}
    if loop == "pipelined":
        assert dut.phase_latency == dut.stage_latency["clarke"]
    else:
        assert dut.phase_latency + 20 < min(dut.latencies)


def _sample_run(dut, codes, *, speed_first=0):
    """One sample into ``dut`` (gains 1.0, enabled): ``i.valid`` in clock ``4 + speed_first``
    (after a speed run requested in clock 4 when ``speed_first``), the payload ``codes[k]``
    (ia, ib) from clock ``4 + speed_first + k`` on; the phase currents and the duties."""
    seen = {}
    t0 = 4 + speed_first

    async def testbench(ctx):
        for name, value in {"enable": 1, "iq_ref": 3000, "scale": 2500}.items():
            ctx.set(getattr(dut, name), value)
        if not dut.speed_mode:
            for name, value in {"gain_a": 1 << 15, "gain_b": 1 << 15, "kp_d": 256, "kp_q": 256,
                                "lim_lo_d": -1000, "lim_hi_d": 1000, "lim_lo_q": -1000,
                                "lim_hi_q": 1000, "u_rated": 20000}.items():
                ctx.set(getattr(dut, name), value)
        for t in range(t0 + 400):
            ctx.set(dut.speed_valid if dut.speed_mode else dut.enable,
                    int(t == 4) if dut.speed_mode else 1)
            ctx.set(dut.i.valid, int(t == t0))
            k = t - t0
            if 0 <= k < len(codes):
                ctx.set(dut.i.payload, {"ia": codes[k][0], "ib": codes[k][1], "udc": 20000,
                                        "aux": 0})
            if ctx.get(dut.phase.valid):
                seen["phase"] = ctx.get(dut.phase.payload)
            if ctx.get(dut.o.valid) and "duties" not in seen:
                seen["duties"] = ctx.get(dut.o.payload)
            await ctx.tick()

    simulate(dut, [testbench], name="engine_sample_read")
    return seen


def test_engine_current_loop_reads_the_adc_codes_at_sample_read():
    """The program reads ``i.payload.ia``, ``ib`` from the port itself (no latch at the
    sample), the last in the clock ``sample_read`` after its start (the accepting clock, the
    engine idle): a change of the codes in that clock is the sample's, one in the next is not.
    Behind a speed run (the engine busy when the sample comes) the codes are read later but
    within ``sample_hold``: a change in the clock after the sample is the sample's, one
    ``sample_hold + 1`` clocks after it is not."""
    x, y = (1200, -700), (-300, 900)
    dut = EngineCurrentLoop()
    r = dut.sample_read
    assert r == 3 and dut.sample_hold > r
    ports = [EngineCurrentLoop() for _ in range(5)]
    base, other, mixed = (_sample_run(ports.pop(), [c]) for c in (x, y, (x[0], y[1])))
    assert len({str(v) for v in (base, other, mixed)}) == 3
    assert mixed["phase"]["a"] == x[0] and mixed["phase"]["b"] == y[1]
    # ia is read in the clock r − 1, ib in r.
    assert _sample_run(ports.pop(), [x] * (r - 1) + [y]) == other
    assert _sample_run(ports.pop(), [x] * r + [y]) == mixed
    assert _sample_run(dut, [x] * (r + 1) + [y]) == base

    speed = [EngineCurrentLoop(config="ram", status="ram", speed=True,
                               config_init=[1 << 15, 1 << 15] + [0] * 18) for _ in range(4)]
    hold = speed[0].sample_hold
    assert hold > dut.sample_hold
    base, other = (_sample_run(speed.pop(), [c], speed_first=1) for c in (x, y))
    assert base["phase"] != other["phase"]
    assert _sample_run(speed.pop(), [x, y], speed_first=1) == other
    assert _sample_run(speed.pop(), [x] * (hold + 1) + [y], speed_first=1) == base


# --- EngineCurrentLoop(config="ram") ------------------------------------------------------------

class _PortsAndRam(Elaboratable):
    """Both configurations of EngineCurrentLoop side by side (simulation only)."""

    def __init__(self, ports, config_init):
        self.ports = ports
        self.ram = EngineCurrentLoop(config="ram", config_init=config_init)

    def elaborate(self, platform):
        m = Module()
        m.submodules.ports = self.ports
        m.submodules.ram = self.ram
        return m


def _config_word(shape, value):
    """A configuration value as the register file's export port carries it (its read format:
    sign-extended to 32 bits for a signed shape)."""
    return value & 0xFFFF_FFFF


def _random_config(rng, shape):
    if shape.signed:
        return int(rng.integers(-(1 << (shape.width - 1)), 1 << (shape.width - 1)))
    return int(rng.integers(0, 1 << shape.width))


@pytest.mark.parametrize("seed", [1, 2])
def test_engine_current_loop_config_ram_equals_ports_cycle_by_cycle(seed):
    """config="ram" against config="ports" on the same samples: every RAM word is written (in
    random clocks, also while the program runs and in the clock before it reads the word: the
    bypass) one clock before the same value reaches the ports loop's input, as the register
    file's export port writes it one clock before its flip-flop would change. Every output is
    compared in every clock."""
    from foc_servo.hdl.foc_engine import CONFIG, CONFIG_PORTS
    rng = np.random.default_rng(seed)
    ports = EngineCurrentLoop()
    shapes = [getattr(ports, CONFIG_PORTS[n]).shape() for n in CONFIG]
    init = [_random_config(rng, s) for s in shapes]
    bench = _PortsAndRam(ports, [_config_word(s, v) for s, v in zip(shapes, init)])
    a, b = bench.ports, bench.ram
    outs = ["busy", "done", "overmod", "dc_limited", "overrun", "overruns", "count", "sat_d",
            "sat_q", "i_alpha", "i_beta", "i_d", "i_q", "u_d", "u_q", "u_alpha", "u_beta"]
    fig = {"clocks": 0, "writes": 0, "runs": 0, "mismatch": None}

    async def testbench(ctx):
        for name, v in zip(CONFIG, init):
            ctx.set(getattr(a, CONFIG_PORTS[name]), v)
        later = None                                # (port, value) for the next clock
        for clock in range(6000):
            if later is not None:
                ctx.set(getattr(a, later[0]), later[1])
                later = None
            ctx.set(b.config.valid, 0)
            if rng.random() < 0.4:
                j = int(rng.integers(len(CONFIG)))
                v = _random_config(rng, shapes[j]) if rng.random() < 0.8 else init[j]
                ctx.set(b.config.valid, 1)
                ctx.set(b.config.index, j)
                ctx.set(b.config.data, _config_word(shapes[j], v))
                later = (CONFIG_PORTS[CONFIG[j]], v)
                fig["writes"] += 1
            start = not ctx.get(a.busy) and rng.random() < 0.2
            for dut in (a, b):
                ctx.set(dut.i.valid, int(start))
                ctx.set(dut.o.ready, 1)
            if start:
                fig["runs"] += 1
                # (lead_k, u_rated: configuration, randomised by the writes above.)
                sample, values = _random_sample(rng, config_ports=False)
                for dut in (a, b):
                    ctx.set(dut.i.payload, sample)
                    for name, v in values.items():
                        ctx.set(getattr(dut, name), v)
            got_a = [ctx.get(getattr(a, n)) for n in outs] + [
                ctx.get(a.o.valid), ctx.get(a.o.payload.as_value()), ctx.get(a.phase.valid),
                ctx.get(a.phase.payload.as_value())]
            got_b = [ctx.get(getattr(b, n)) for n in outs] + [
                ctx.get(b.o.valid), ctx.get(b.o.payload.as_value()), ctx.get(b.phase.valid),
                ctx.get(b.phase.payload.as_value())]
            if got_a != got_b and fig["mismatch"] is None:
                fig["mismatch"] = (clock, [(n, x, y) for n, x, y in
                                           zip(outs + ["o.valid", "o", "phase.valid", "phase"],
                                               got_a, got_b) if x != y])
            fig["clocks"] += 1
            await ctx.tick()

    simulate(bench, [testbench], name="engine_config_ram")
    assert fig["mismatch"] is None, fig["mismatch"]
    assert fig["runs"] > 15 and fig["writes"] > 2000


def test_engine_current_loop_config_ram_ports_and_errors():
    _built_for_signatures(_check_config_ram_ports_and_errors)


def _check_config_ram_ports_and_errors():
    from foc_servo.hdl.bus import WordWriteSignature
    from foc_servo.hdl.foc_engine import CONFIG, CONFIG_PORTS
    ram = EngineCurrentLoop(config="ram")
    ports = EngineCurrentLoop()
    members = set(ram.signature.members)
    assert members == (set(ports.signature.members) - set(CONFIG_PORTS.values())) | {"config"}
    sig = ram.signature.members["config"].signature
    assert isinstance(sig, WordWriteSignature) and sig.depth == len(CONFIG) == 16
    assert {"lead_k", "u_rated"} <= set(ports.signature.members) - members
    assert ram.config_mode == "ram" and ports.config_mode == "ports"
    with pytest.raises(ValueError, match=r"^EngineCurrentLoop config must be one of 'ports', "
                                         r"'ram', not 'regs'$"):
        EngineCurrentLoop(config="regs")
    with pytest.raises(ValueError, match=r"^EngineCurrentLoop config_init applies only to "
                                         r"config='ram', not config='ports'$"):
        EngineCurrentLoop(config_init=[0] * 16)
    with pytest.raises(ValueError, match=r"^EngineCurrentLoop config_init must be a list of 16 "
                                         r"integers, not \[0\]$"):
        EngineCurrentLoop(config="ram", config_init=[0])


# --- EngineCurrentLoop(status="ram") ------------------------------------------------------------

class _PortsAndStatusRam(Elaboratable):
    """status="ports" and status="ram" side by side (simulation only)."""

    def __init__(self):
        self.ports = EngineCurrentLoop()
        self.ram = EngineCurrentLoop(status="ram")

    def elaborate(self, platform):
        m = Module()
        m.submodules.ports = self.ports
        m.submodules.ram = self.ram
        return m


@pytest.mark.parametrize("seed", [1, 2])
def test_engine_current_loop_status_ram_reads_what_the_ports_hold(seed):
    """status="ram" against status="ports" on the same random samples (also accepted in the
    ``done`` clock, back to back), both read ports given a random word in every clock:
    ``status_rd.data`` in clock t + 1 is the ports loop's status output of t + 1 (a
    transparent read), ``status_probe.data`` in c + 1 its output of c (the old word), and the
    RAM holds the outputs in every clock. No status output changes in the ``status_quiet``
    clocks from ``done`` on (its writes land in the RAM at the end of a clock; the scope's
    reads there never meet one); every other output is equal in every clock."""
    from foc_servo.hdl.foc_engine import STATUS
    rng = np.random.default_rng(seed)
    bench = _PortsAndStatusRam()
    a, b = bench.ports, bench.ram
    assert b.status_quiet == a.status_quiet == 12
    outs = ["busy", "done", "overmod", "dc_limited", "overrun", "overruns", "count", "sat_d",
            "sat_q"]
    fig = {"runs": 0, "back_to_back": 0, "changes": 0, "bad": None, "quiet_bad": None}

    def bad(clock, what):
        if fig["bad"] is None:
            fig["bad"] = (clock, what)

    async def testbench(ctx):
        prev_status, prev_addr, dones = None, None, []
        for clock in range(5000):
            done = bool(ctx.get(a.done))
            start = (not ctx.get(a.busy) or done) and rng.random() < (0.5 if done else 0.05)
            for dut in (a, b):
                ctx.set(dut.i.valid, int(start))
                ctx.set(dut.o.ready, 1)
            if start:
                fig["runs"] += 1
                fig["back_to_back"] += done
                sample, values = _random_sample(rng, config_ports=True)
                for dut in (a, b):
                    ctx.set(dut.i.payload, sample)
                    for name, v in values.items():
                        ctx.set(getattr(dut, name), v)
            status = [ctx.get(getattr(a, n)) for n in STATUS]
            if [ctx.get(b.status_memory.data[j]) for j in range(len(STATUS))] != status:
                bad(clock, "RAM words")
            if prev_addr is not None:
                if ctx.get(b.status_rd.data) != status[prev_addr[0]]:
                    bad(clock, ("status_rd", prev_addr[0]))
                if ctx.get(b.status_probe.data) != prev_status[prev_addr[1]]:
                    bad(clock, ("status_probe", prev_addr[1]))
            if prev_status is not None and status != prev_status:
                fig["changes"] += 1
                # Written at the end of the clock before: not one of the quiet clocks.
                if any(d <= clock - 1 < d + a.status_quiet for d in dones):
                    fig["quiet_bad"] = fig["quiet_bad"] or clock
            if done:
                dones = dones[-3:] + [clock]
            if [ctx.get(getattr(a, n)) for n in outs] != [ctx.get(getattr(b, n)) for n in outs]:
                bad(clock, "outputs")
            if (ctx.get(a.o.payload.as_value()), ctx.get(a.phase.payload.as_value())) != \
                    (ctx.get(b.o.payload.as_value()), ctx.get(b.phase.payload.as_value())):
                bad(clock, "o, phase")
            addr = (int(rng.integers(len(STATUS))), int(rng.integers(len(STATUS))))
            ctx.set(b.status_rd.addr, addr[0])
            ctx.set(b.status_probe.addr, addr[1])
            prev_status, prev_addr = status, addr
            await ctx.tick()

    simulate(bench, [testbench], name="engine_status_ram")
    assert fig["bad"] is None, fig["bad"]
    assert fig["quiet_bad"] is None, fig["quiet_bad"]
    assert fig["runs"] > 15 and fig["back_to_back"] > 3 and fig["changes"] > 20


def test_engine_current_loop_status_ram_ports_and_errors():
    _built_for_signatures(_check_status_ram_ports_and_errors)


def _check_status_ram_ports_and_errors():
    from foc_servo.hdl.foc_engine import STATUS, status_quiet
    ram = EngineCurrentLoop(status="ram")
    ports = EngineCurrentLoop()
    assert set(ram.signature.members) == (set(ports.signature.members) - set(STATUS)) | {
        "status_rd", "status_probe"}
    assert ram.status_mode == "ram" and ports.status_mode == "ports"
    assert ports.status_memory is None and ram.status_memory is None    # not elaborated
    assert status_quiet(ram.program) == ram.status_quiet
    with pytest.raises(ValueError, match=r"^EngineCurrentLoop status must be one of "
                                         r"'ports', 'ram', not 'regs'$"):
        EngineCurrentLoop(status="regs")
    with pytest.raises(ValueError, match=r"^Engine strobe_outs must be a tuple of distinct "
                                         r"outputs of out_widths, wider than 1 bit, not "
                                         r"ang, not \('ang',\)$"):
        Engine(program=ram.program, special_shapes={n: signed(16) for n in SPECIALS},
               out_widths=OUTS, strobe_outs=("ang",))


def test_round_shift_plain_equals_round_shift():
    """The speed latch's rounding (:func:`~foc_servo.hdl.fixed.round_shift_plain`, one
    carry chain) equals :func:`round_shift` bit for bit: ties both ways, the extremes, random."""
    from amaranth.hdl import Signal
    from amaranth.sim import Simulator
    from foc_servo.hdl.fixed import round_shift_np
    from foc_servo.hdl.fixed import round_shift_plain
    k = 16
    rng = np.random.default_rng(13)
    vals = [-(1 << 31), (1 << 31) - 1, 0, 1, -1]
    vals += [a * (1 << k) + b for a in (-32768, -2, -1, 0, 1, 32767)
             for b in (-(1 << (k - 1)) - 1, -(1 << (k - 1)), -(1 << (k - 1)) + 1, -1, 0, 1,
                       (1 << (k - 1)) - 1, 1 << (k - 1), (1 << (k - 1)) + 1)]
    vals += [int(v) for v in rng.integers(-(1 << 31), 1 << 31, 300)]
    vals = [v for v in vals if -(1 << 31) <= v < (1 << 31)]
    v = Signal(signed(32))
    y = Signal(signed(18))
    m = Module()
    m.d.comb += y.eq(round_shift_plain(v, k))
    got = []

    async def bench(ctx):
        for x in vals:
            ctx.set(v, x)
            got.append(ctx.get(y))

    sim = Simulator(m)
    sim.add_testbench(bench)
    sim.run()
    assert got == [round_shift_np(x, k) for x in vals]
    with pytest.raises(ValueError, match="shift >= 1"):
        round_shift_plain(v, 0)
