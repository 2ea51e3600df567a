# Ref: docs/ENGINE.md "Speed loop as a program"; hdl/servo.py (SpeedLoop's equations)
"""The speed loop as a loop-engine program, on the interpreter, against :class:`SpeedLoopModel`
(the iCEBreaker top's speed loop: ``kx_format`` UQ(24, 20), the other parameters default)."""

import numpy as np
import pytest

from foc_servo.hdl.fixed import UQ, round_shift_np, saturate_np
from foc_servo.hdl.foc_engine import current_loop_program, speed_loop_program
from foc_servo.hdl.engine import Op
from foc_servo.sim.models.engine import EngineLoopModel, EngineSpeedModel
from foc_servo.sim.models.servo import SpeedLoopModel

from engine_trace import start_and_follow

from amaranth.hdl import signed

S32 = (-(1 << 31), -(1 << 31) + 1, -(1 << 31) + 2, -1, 0, 1, (1 << 31) - 2, (1 << 31) - 1)
SLEWS = (0, 1, 2, 3, (1 << 31) - 1, 1 << 31, (1 << 31) + 1, (1 << 32) - 2, (1 << 32) - 1)
S16 = (-(1 << 15), -(1 << 15) + 1, -1, 0, 1, (1 << 15) - 1)


def _stimulus(seed, n):
    """Per-run inputs with corners: 32-bit extremes, slews 0 / 1 / 2**31 ± 1 / max, the
    speed reference often held (the profile then converges), inverted limits, ref_delay
    0 … max, int_hold, clear pulses."""
    rng = np.random.default_rng(seed)
    pick = lambda xs: int(xs[rng.integers(len(xs))])                   # noqa: E731
    runs = []
    sref = 0
    for _ in range(n):
        if rng.random() < 0.4:
            sref = pick(S32) if rng.random() < 0.3 else int(rng.integers(-(1 << 31), 1 << 31))
        r = rng.random()
        slew = (pick(SLEWS) if r < 0.3 else int(rng.integers(0, 1 << 32)) if r < 0.5 else
                int(rng.integers(0, 1 << int(rng.integers(1, 30)))))
        speed = pick(S32) if rng.random() < 0.2 else int(rng.integers(-(1 << 31), 1 << 31))
        lo, hi = (pick(S16) if rng.random() < 0.3 else int(rng.integers(-(1 << 15), 1 << 15))
                  for _ in range(2))
        if rng.random() < 0.6 and lo > hi:
            lo, hi = hi, lo
        iq_ff = pick(S16) if rng.random() < 0.3 else int(rng.integers(-(1 << 15), 1 << 15))
        if rng.random() < 0.5:          # near the reference: the PI's linear region
            speed = int(np.clip(sref + int(rng.integers(-(1 << 12), 1 << 12)) *
                                int(rng.integers(1, 1 << 8)), -(1 << 31), (1 << 31) - 1))
        gain = lambda: (pick((0, 1, (1 << 24) - 1)) if rng.random() < 0.2 else  # noqa: E731
                        int(rng.integers(0, 1 << int(rng.integers(1, 25)))))
        runs.append(dict(speed=speed, speed_ref=sref, speed_slew=slew, iq_ff=iq_ff,
                         lim_lo=lo, lim_hi=hi, ref_delay=int(rng.integers(0, 32)),
                         int_hold=int(rng.random() < 0.5),
                         kp=gain(), kx=gain(),
                         clear=int(rng.integers(1, 4)) if rng.random() < 0.06 else 0))
    return runs


def _compare(runs):
    """Run both; return the number of runs compared. Asserts equality run by run."""
    model = SpeedLoopModel(kx_format=UQ(24, 20))
    eng = EngineSpeedModel()
    to_pi = lambda v: int(saturate_np(round_shift_np(v, 8), signed(24)))  # noqa: E731
    compared = 0
    for k, inp in enumerate(runs):
        port = dict(speed=inp["speed"], speed_ref=inp["speed_ref"], kp=inp["kp"],
                    kx=inp["kx"], lim_lo=inp["lim_lo"], lim_hi=inp["lim_hi"], rate_div=0,
                    speed_slew=inp["speed_slew"], iq_ff=inp["iq_ff"],
                    ref_delay=inp["ref_delay"], int_hold=inp["int_hold"])
        for _ in range(inp["clear"]):
            model.clock(valid=0, clear=1, **port)
            eng.clear(inp["speed_ref"] if inp["speed_slew"] == 0 else inp["speed"])
            assert eng.ref_int == model.ref_int
        runs_before = model.runs
        model.clock(valid=1, clear=0, **port)
        assert model.runs == runs_before + 1
        got = eng.run(**{name: inp[name] for name in (
            "speed", "speed_ref", "speed_slew", "iq_ff", "lim_lo", "lim_hi", "ref_delay",
            "int_hold", "kp", "kx")})
        want = {"plan": model.plan, "ff": model.ff, "hold": model.hold,
                "fb": to_pi(inp["speed"]), "e": model.pi.last["e"],
                "integrator": model.pi.integrator, "ep": model.pi.e_prev}
        for name, value in want.items():
            assert got[name] == value, (f"run {k}: {name} {got[name]} != {value} "
                                        f"(inputs {inp})")
        strobes = 0
        for _ in range(model.interval - 1):
            strobes += model.clock(valid=0, clear=0, **port)[0]
        assert strobes == 1
        assert eng.ref_int == model.ref_int == model.plan
        assert (got["iq"], got["sat"]) == (model.o_payload, model.sat), (
            f"run {k}: i_q, sat {got['iq']}, {got['sat']} != {model.o_payload}, {model.sat} "
            f"(inputs {inp}, PI {model.pi.last})")
        compared += 1
    return compared


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_speed_loop_program_matches_speed_loop_model(seed):
    """plan (ref_int), ff, hold, fb and E of every run, bit for bit, over 400 runs with
    corners (random runs; every 32-bit extreme of speed, speed_ref and the slew; clear)."""
    assert _compare(_stimulus(seed, 400)) == 400


def test_speed_loop_program_corners():
    """Every slew corner against every (speed_ref, R) extreme pair: R set by a clear with
    slew 0 (R = speed_ref), then one run towards the other extreme."""
    runs = []
    base = dict(speed=0, iq_ff=-(1 << 15), lim_lo=-(1 << 15), lim_hi=(1 << 15) - 1,
                ref_delay=9, int_hold=1, kp=1, kx=1)
    for r0 in S32:
        for sref in S32:
            for slew in SLEWS:
                runs.append(dict(base, speed_ref=r0, speed_slew=0, clear=1))
                runs.append(dict(base, speed_ref=sref, speed_slew=slew, clear=0))
    assert _compare(runs) == len(runs)


def test_speed_loop_program_integrator_clamp_corners():
    """I + dI just above / at / just below ``hi·2**16`` and ``lo·2**16`` (the clamp decided on
    the ceiling and the floor of ``(I + dI) / 2**16``), and the same in the second run from a
    clamped integrator: kx = 256, E = 2**20 + k (first run after clear: E[n−1] = 0, I = 0),
    so dI = 2**24 + 16·k against the limit 2**24 (lim_hi 1)."""
    runs = []
    base = dict(speed=0, speed_slew=0, iq_ff=0, ref_delay=0, int_hold=0, kp=0, kx=256)
    for k in (-5, -1, 0, 1, 3, 4095, 4096, 4097):
        for sign in (1, -1):
            e = sign * ((1 << 20) + k)
            lims = dict(lim_lo=-1, lim_hi=1)
            runs.append(dict(base, speed_ref=e << 8, clear=1, **lims))
            runs.append(dict(base, speed_ref=e << 8, clear=0, **lims))
    assert _compare(runs) == len(runs)


def test_speed_loop_program_exact_compare_is_needed():
    """The test can fail: a program deciding ``D > S`` on the halves alone (V ignored) differs
    from the model on some corner."""
    import foc_servo.hdl.foc_engine as fe
    orig = fe.Assembler.alu

    def broken(self, op, dst, a, b="k.0", **kw):
        if op == Op.SEL and isinstance(dst, str) and dst.endswith("_k") and kw.get(
                "cond") == "Z":
            return orig(self, op, dst, 1, 0, **kw)          # T = 0: key 0 instead of V
        return orig(self, op, dst, a, b, **kw)

    fe.Assembler.alu = broken
    try:
        program = speed_loop_program()
    finally:
        fe.Assembler.alu = orig
    eng = EngineSpeedModel(program=program)
    eng.clear(0)
    got = eng.run(speed=0, speed_ref=3, speed_slew=2, iq_ff=0, lim_lo=-5, lim_hi=5,
                  ref_delay=0, int_hold=0, kp=0, kx=0)
    assert got["plan"] != 2           # the model: 3 − 0 > 2, so R[n] = 0 + 2


def test_speed_loop_program_fits():
    """The words it needs beside the current loop's 256 (ROM 512: 8 BRAM)."""
    p = speed_loop_program()
    assert len(p.words) <= 256
    assert len(speed_loop_program(schedule=False).words) >= len(p.words)


def _run_args(inp, *models):
    """One stimulus run: its ``clear`` applied to every speed model (tracking the reference,
    or the speed when slewing), and its arguments for ``run``/``specials_of``."""
    if inp["clear"]:
        track = inp["speed_ref"] if inp["speed_slew"] == 0 else inp["speed"]
        for model in models:
            model.clear(track)
    return {name: inp[name] for name in ("speed", "speed_ref", "speed_slew", "iq_ff", "lim_lo",
                                         "lim_hi", "ref_delay", "int_hold", "kp", "kx")}


def test_combined_program_runs_both_loops_unchanged():
    """``current_loop_program(speed=True)``: the speed run at the ``speed`` label, its
    temporaries in the current loop's registers, on one register file: current-loop samples
    and speed runs interleaved give exactly what each program gives alone (the current loop's
    outputs and DC-bus gain sample by sample; the speed loop's i_q, sat, ref_int, integrator,
    E[n−1] run by run), so neither clobbers the other's state. 345 words (500 unfolded; ROM
    512), 124 RF words (of 128)."""
    from foc_servo.sim.verify import foc as verify_foc
    combined = current_loop_program(speed=True)
    assert len(combined.words) == 345 and combined.labels["speed"] == 184
    vec = verify_foc.stimulus(60, seed=5)
    vec = {k: np.asarray(v) for k, v in vec.items() if k != "theta_lead"} | {
        "lead_k": np.asarray(vec["theta_lead"]) % (1 << 16)}
    n = len(vec["ia"])
    loop_a, loop_b = EngineLoopModel(), EngineLoopModel(program=combined)
    spd_a = EngineSpeedModel()
    spd_b = EngineSpeedModel(program=combined, engine=loop_b.engine)
    runs = _stimulus(7, n)
    for k in range(n):
        one = {name: v[k:k + 1] for name, v in vec.items()}
        a, b = loop_a.run(**one), loop_b.run(**one)
        for name in a:
            assert np.array_equal(a[name], b[name]), (k, name)
        assert loop_a.dc_gain == loop_b.dc_gain
        args = _run_args(runs[k], spd_a, spd_b)
        ra, rb = spd_a.run(**args), spd_b.run(**args)
        for name in ("iq", "sat", "integrator", "ep"):
            assert ra[name] == rb[name], (k, name)
        assert spd_a.ref_int == spd_b.ref_int


# --- the combined program on the gateware engine, cycle by cycle ---------------------------------

def test_combined_program_on_the_engine_matches_the_interpreter_cycle_by_cycle():
    """``current_loop_program(speed=True)`` on :class:`Engine` (``start_pc`` 0: a current-loop
    sample; the ``speed`` label: a speed run, the five flags as 1-bit special operands)
    against :class:`EngineModel` on one register file, runs interleaved at random: every
    executed instruction's write back (pc, P, destination, value) in the same clock, the
    output registers after each END; the speed run's results also against
    :class:`EngineSpeedModel` on the speed program alone."""
    from amaranth.hdl import signed as s_

    from foc_servo.hdl.engine import Engine
    from foc_servo.hdl.foc_engine import OUTS, SPECIALS, SPEED_OUTS, SPEED_SHAPES
    from foc_servo.sim.harness import simulate
    from foc_servo.sim.models.engine import EngineModel, _complete
    from foc_servo.sim.verify import foc as verify_foc

    prog = current_loop_program(speed=True)
    outs = {**OUTS, **SPEED_OUTS}
    shapes = {**{n: s_(20) for n in SPECIALS}, **SPEED_SHAPES}
    dut = Engine(program=prog, special_shapes=shapes, out_widths=outs)
    model = EngineModel(prog, out_widths=outs)
    ref = EngineSpeedModel()                      # the speed program alone
    shadow = EngineSpeedModel(program=prog, engine=model)   # builds the specials only
    vec = verify_foc.stimulus(40, seed=3)
    vec = {k: np.asarray(v) for k, v in vec.items() if k != "theta_lead"} | {
        "lead_k": np.asarray(vec["theta_lead"]) % (1 << 16)}
    runs = _stimulus(11, 40)
    rng = np.random.default_rng(11)
    order = ["c"] * 40 + ["s"] * 40
    rng.shuffle(order)
    jobs, kc, ks = [], 0, 0
    for kind in order:
        if kind == "c":
            jobs.append(("c", EngineLoopModel.specials_of(vec, kc)))
            kc += 1
        else:
            jobs.append(("s", runs[ks]))
            ks += 1
    errors, count = [], [0, 0]

    async def testbench(ctx):
        for k, (kind, job) in enumerate(jobs):
            if kind == "c":
                spec, conds = _complete(prog, *job)
                start = 0
            else:
                args = _run_args(job, ref, shadow)
                spec, conds = shadow.specials_of(**args)
                start = shadow.start
                got_model = shadow.run(**args)
                want = ref.run(**args)
                for name in ("iq", "sat", "integrator", "ep"):
                    if got_model[name] != want[name]:
                        errors.append((k, "model", name))
                trace = shadow.trace
            if kind == "c":
                trace = model.run(spec, conds)
            for name in shapes:
                ctx.set(getattr(dut, f"s_{name}"), spec[name])
            for name, val in conds.items():
                ctx.set(getattr(dut, f"c_{name}"), int(val))
            ctx.set(dut.start_pc, start)
            error, _ = await start_and_follow(ctx, dut, trace)
            if error is not None:
                errors.append((k, kind, *error))
                return
            count[kind == "s"] += 1
            await ctx.tick()
            for name, ow in outs.items():
                if ctx.get(getattr(dut, f"o_{name}")) != model.outs[name] % (1 << ow):
                    errors.append((k, kind, name))

    simulate(dut, [testbench], name="engine_speed")
    assert errors == []
    assert count == [40, 40]


def test_combined_program_rom_is_64_bits_wide():
    """The combined ROM's word (instruction + special key) with the configuration RAM as the
    iCEBreaker top has it: 64 bits (500 × 64: 8 block RAMs; 56 of them used since session 18,
    345 × 56: 7); the speed flags as conditions or
    three 1-bit ``ref_delay`` flags would make 32 keys, 65 bits (9 BRAM)."""
    import gc
    import warnings

    from amaranth.hdl import UnusedElaboratable, signed as s_

    from foc_servo.hdl.engine import Engine
    from foc_servo.hdl.foc_engine import CONFIG, OUTS, SPECIALS, SPEED_OUTS, SPEED_SHAPES

    prog = current_loop_program(speed=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UnusedElaboratable)
        dut = Engine(program=prog, special_shapes={**{n: s_(20) for n in SPECIALS},
                                                   **SPEED_SHAPES},
                     out_widths={**OUTS, **SPEED_OUTS}, config=CONFIG)
        base = Engine(program=current_loop_program(), special_shapes={n: s_(20) for n in SPECIALS},
                      out_widths=OUTS, config=CONFIG)
        widths = dut.rom_width, base.rom_width
        words = dut.rom_words
        del dut, base
        gc.collect()                    # (built for their attributes only: no warning)
    assert widths == (64, 63)
    # Bits that are 0 in every word, which yosys drops: the 7 spare bits and asl (in the key):
    # 56 bits used, 7 block RAMs of 512 × 8 (session 18, AREA.md §7.81); with the registers'
    # reuse (AREA.md §7.87: 30 register words, below 32) also dst's two top bits: 54.
    used = 0
    for w in words:
        used |= w
    assert bin(used).count("1") == 54 and used >> 52 & 0x7F == 0
    assert max(v for k, v in prog.regs.items() if not k.startswith("k.")) < 32
    assert any(i.asl for i in prog.instrs)
