# Ref: docs/ENGINE.md "Speed loop as a program" (the wrapper); hdl/servo.py (SpeedLoop's equations)
"""The speed loop on the loop engine beside the current loop (``EngineCurrentLoop(speed=True)``),
clock by clock against :class:`SpeedLoopModel` with the engine's timing: the run requested at
M/T's strobe (decimated), waiting while a current-loop sample runs (and the sample waiting
behind a speed run), ``ref_int`` forced while ``clear``, runs aborted by ``clear``, the
configuration words (gains, slew, feed-forward) written into the engine's configuration RAM."""

import numpy as np
from foc_servo.hdl.fixed import UQ
from foc_servo.hdl.foc_engine import (CONFIG, OUTS, SPEED_CONFIG_WORDS, SPEED_OUTS,
                                      DUTY_CLOCKS, START_CLOCKS, EngineCurrentLoop)
from foc_servo.sim.harness import simulate
from foc_servo.sim.models.engine import EngineModel, _complete
from foc_servo.sim.models.servo import SpeedLoopModel

S32 = (-(1 << 31), -(1 << 31) + 1, -1, 0, 1, (1 << 31) - 1)
SLEWS = (0, 1, (1 << 31) - 1, 1 << 31, (1 << 32) - 1)
S16 = (-(1 << 15), -1, 0, 1, (1 << 15) - 1)


def _plan(seed, clocks):
    """Per-clock events: ``cur`` (a current-loop sample), ``spd`` (M/T's strobe, with a new
    speed), ``clear`` (1 … 3 clocks, some inside runs), ``cfg`` (a parameter change: the
    four configuration words written in four clocks, the port inputs changed at once)."""
    rng = np.random.default_rng(seed)
    pick = lambda xs: int(xs[rng.integers(len(xs))])                   # noqa: E731
    ev = [dict() for _ in range(clocks)]
    t = int(rng.integers(20, 60))
    while t < clocks:                               # current-loop samples
        ev[t]["cur"] = 1
        t += int(rng.integers(280, 700))
    t = int(rng.integers(5, 40))
    while t < clocks:                               # M/T strobes
        ev[t]["spd"] = pick(S32) if rng.random() < 0.15 else int(rng.integers(-(1 << 31),
                                                                              1 << 31))
        t += int(rng.integers(60, 420)) if rng.random() < 0.9 else int(rng.integers(1, 8))
    t = int(rng.integers(200, 900))
    while t < clocks:                               # clear pulses
        for k in range(int(rng.integers(1, 4))):
            if t + k < clocks:
                ev[t + k]["clear"] = 1
        t += int(rng.integers(300, 2500))
    t = 2
    while t < clocks:                               # parameter changes (when idle)
        gain = lambda: (pick((0, 1, (1 << 24) - 1)) if rng.random() < 0.2 else  # noqa: E731
                        int(rng.integers(0, 1 << int(rng.integers(1, 25)))))
        r = rng.random()
        slew = (pick(SLEWS) if r < 0.3 else int(rng.integers(0, 1 << 32)) if r < 0.5 else
                int(rng.integers(0, 1 << int(rng.integers(1, 30)))))
        lo, hi = (pick(S16) if rng.random() < 0.3 else int(rng.integers(-(1 << 15), 1 << 15))
                  for _ in range(2))
        if rng.random() < 0.7 and lo > hi:
            lo, hi = hi, lo
        ev[t]["cfg"] = dict(
            kp=gain(), kx=gain(), speed_slew=slew,
            iq_ff=pick(S16) if rng.random() < 0.3 else int(rng.integers(-(1 << 15), 1 << 15)),
            speed_ref=pick(S32) if rng.random() < 0.3 else int(rng.integers(-(1 << 31), 1 << 31)),
            lim_lo=lo, lim_hi=hi, ref_delay=int(rng.integers(0, 32)),
            int_hold=int(rng.random() < 0.5), rate_div=pick((0, 0, 0, 1, 2)))
        t += int(rng.integers(150, 1500))
    return ev


def _disabled_timing(program):
    """A current-loop sample with the loop disabled (the test's samples: one path): executed
    instructions, and clocks from its start to ``o.valid`` (its write of ``dc``)."""
    model = EngineModel(program, out_widths={**OUTS, **SPEED_OUTS})
    trace = model.run(*_complete(program, {}, {}))
    dc = program.outs.index("dc")
    k = max(i for i, e in enumerate(trace) if program.instrs[e["pc"]].out == dc)
    return len(trace), k + 1 + DUTY_CLOCKS


def _run(seed, clocks):
    """Simulate; returns (errors, stats)."""
    dut = EngineCurrentLoop(config="ram", status="ram", speed=True,
                            config_init=[0] * (len(CONFIG) + len(SPEED_CONFIG_WORDS)))
    timing = dut.speed_timing
    n_cur, lat_cur = _disabled_timing(dut.program)
    model = SpeedLoopModel(kx_format=UQ(24, 20), engine_timing=timing)
    ev = _plan(seed, clocks)
    errors, stats = [], {"runs": 0, "starts": 0, "waited": 0, "cur_waited": 0, "aborted": 0,
                         "valid": 0, "cur_dropped": 0}
    j_cfg = len(CONFIG)

    async def testbench(ctx):
        ports = dict(speed=0, speed_ref=0, kp=0, kx=0, lim_lo=0, lim_hi=0, rate_div=0,
                     speed_slew=0, iq_ff=0, ref_delay=0, int_hold=0)
        cfg_queue = []              # (word index, value, model key) written one per clock
        free = 0                    # first clock the engine takes a start
        cur_pend = False
        cur_done = 0                # the clock the current loop's duties are valid (done)
        cur_valid = []              # the clocks its o.valid is due
        ctx.set(dut.o.ready, 1)
        for t in range(clocks):
            e = ev[t]
            clear = e.get("clear", 0)
            idle = not model.busy and not cfg_queue
            # Port inputs (the model sees a configuration word from the clock after its write).
            if "cfg" in e and idle and not clear:
                c = e["cfg"]
                for name in ("speed_ref", "lim_lo", "lim_hi", "ref_delay", "int_hold",
                             "rate_div"):
                    ports[name] = c[name]
                cfg_queue = [(j_cfg + k, c[key], key) for k, key in
                             enumerate(("kp", "kx", "speed_slew", "iq_ff"))]
            strobe = "spd" in e and not cfg_queue
            # (M/T's register changes with each strobe; the engine reads the port itself, so
            # it holds from a run's request to the engine's read: EngineCurrentLoop's
            # contract, kept by the top's PWM period. A strobe in that window, only here,
            # keeps it and still exercises the drop.)
            if strobe and not model.speed_held:
                ports["speed"] = e["spd"]
            ctx.set(dut.speed_valid, int(strobe))
            ctx.set(dut.speed, ports["speed"])
            ctx.set(dut.speed_ref, ports["speed_ref"])
            ctx.set(dut.iq_lim_lo, ports["lim_lo"])
            ctx.set(dut.iq_lim_hi, ports["lim_hi"])
            ctx.set(dut.speed_rate_div, ports["rate_div"])
            ctx.set(dut.speed_ref_delay, ports["ref_delay"])
            ctx.set(dut.speed_int_hold, ports["int_hold"])
            ctx.set(dut.speed_clear, clear)
            write = None
            if cfg_queue:
                write = cfg_queue.pop(0)
                ctx.set(dut.config.valid, 1)
                ctx.set(dut.config.index, write[0])
                ctx.set(dut.config.data, write[1] % (1 << 32))
            else:
                ctx.set(dut.config.valid, 0)
            cur = e.get("cur", 0)
            ctx.set(dut.i.valid, cur)
            # The current loop's handshake: a sample is accepted from its predecessor's done.
            cur = cur and t >= cur_done and not cur_pend
            stats["cur_dropped"] += int(e.get("cur", 0) and not cur)
            # The engine's arbitration: a current-loop sample first, then a waiting speed run.
            cur_go = bool(cur) or cur_pend
            can = t >= free
            if cur_go and can:
                free, cur_pend = t + n_cur + START_CLOCKS, False
                cur_done = t + lat_cur
                cur_valid.append(cur_done)
            elif cur_go:
                cur_pend = True
                cur_done = clocks + 1
            if ctx.get(dut.o.valid) != int(t in cur_valid):
                errors.append((t, "current-loop o.valid"))
            inflight = model.pending is not None or model.waiting is not None
            got = (ctx.get(dut.speed_o.valid), ctx.get(dut.speed_o.payload),
                   ctx.get(dut.speed_sat), ctx.get(dut.speed_ref_int))
            runs = model.runs
            want = model.clock(int(strobe), ports["speed"], ports["speed_ref"], ports["kp"],
                               ports["kx"], ports["lim_lo"], ports["lim_hi"],
                               ports["rate_div"], clear, ports["speed_slew"], ports["iq_ff"],
                               ports["ref_delay"], ports["int_hold"],
                               start=int(can and not cur_go))
            if model.runs != runs:
                stats["runs"] += 1
            if model.started is not None:
                stats["starts"] += 1
                stats["waited"] += model.started[1] > 0
                free = t + timing[model.started[0]]["length"] + START_CLOCKS
            stats["aborted"] += int(bool(clear) and inflight)
            if cur_pend and model.started is not None:      # pragma: no cover
                errors.append((t, "arbitration"))
            stats["cur_waited"] += int(bool(cur) and cur_pend)
            stats["valid"] += want[0]
            if write is not None:
                ports[write[2]] = write[1]
            if got != tuple(want):
                errors.append((t, got, tuple(want)))
                if len(errors) > 5:
                    return
            await ctx.tick()

    simulate(dut, [testbench], name="engine_servo")
    return errors, stats


def test_engine_speed_loop_matches_speed_loop_model_cycle_by_cycle():
    """Every clock's i_q reference, o.valid, sat and ref_int of ``EngineCurrentLoop(speed=True)``
    equal :class:`SpeedLoopModel`'s with the engine's timing (runs started by the engine's
    arbitration), over random runs, 32-bit corners, parameter changes, decimation, clear
    pulses (some aborting runs in flight or waiting) and current-loop samples that delay
    speed runs and wait behind them."""
    errors, stats = _run(5, 24000)
    assert errors == []
    assert stats["starts"] >= 40 and stats["waited"] >= 3 and stats["cur_waited"] >= 2
    assert stats["aborted"] >= 5 and stats["valid"] >= 30


def _read_run(path, speeds):
    """One speed run on an idle engine (kp 1.0, no integral, the profile path ``path``): the
    strobe in clock 4 with ``speeds[0]``, the ``speed`` port then ``speeds[k]`` from clock
    ``4 + k`` on; the run's i_q reference."""
    init = [0] * len(CONFIG) + [1 << 12, 0, 0 if path == "none" else 1, 0]
    dut = EngineCurrentLoop(config="ram", status="ram", speed=True, config_init=init)
    ref = {"none": 0, "up": 1 << 24, "dn": -(1 << 24)}[path]
    got = []

    async def testbench(ctx):
        ctx.set(dut.iq_lim_lo, -(1 << 15))
        ctx.set(dut.iq_lim_hi, (1 << 15) - 1)
        ctx.set(dut.speed_ref, ref)
        for t in range(400):
            k = t - 4
            ctx.set(dut.speed_valid, int(k == 0))
            if 0 <= k < len(speeds):
                ctx.set(dut.speed, speeds[k])
            if ctx.get(dut.speed_o.valid):
                got.append(ctx.get(dut.speed_o.payload))
            await ctx.tick()

    simulate(dut, [testbench], name=f"engine_speed_read_{path}")
    assert len(got) == 1
    return got[0], dut.speed_timing[path]["speed_read"], dut.speed_read


def test_engine_speed_run_reads_the_speed_port_at_speed_read():
    """The speed run reads the ``speed`` port itself (no latch at the request), in the clock
    ``speed_timing[path]["speed_read"]`` after its start (here the strobe's clock, the engine
    idle), on each profile path: a change of the port in that clock is the run's speed, one in
    the next is not; ``speed_read`` is the worst case (the contract the top's M/T register
    keeps, EngineCurrentLoop's docstring)."""
    x, y = 1 << 22, -(1 << 22)
    reads = []
    for path in ("none", "up", "dn"):
        iq_x, read, worst = _read_run(path, [x])
        iq_y = _read_run(path, [y])[0]
        assert iq_x != iq_y
        assert _read_run(path, [x] * read + [y])[0] == iq_y, path
        assert _read_run(path, [x] * (read + 1) + [y])[0] == iq_x, path
        reads.append(read)
    assert worst == max(reads) and len(set(reads)) == 3


def test_ge_ripple_is_unsigned_greater_or_equal():
    """``ge_ripple`` (the decimation's compare, no adder) against ``>=``: every pair of 5-bit
    values, the 8-bit corners and random 8-bit pairs; operands of two widths refused."""
    import pytest
    from amaranth.hdl import Module, Signal

    from foc_servo.hdl.foc_engine import ge_ripple
    rng = np.random.default_rng(3)
    cases = {5: [(a, b) for a in range(32) for b in range(32)],
             8: ([(a, b) for a in (0, 1, 127, 128, 254, 255) for b in (0, 1, 127, 128, 254, 255)]
                 + [tuple(int(v) for v in rng.integers(0, 256, 2)) for _ in range(400)])}
    for width, pairs in cases.items():
        m = Module()
        ab, ge = Signal(2 * width), Signal()           # the operands side by side
        m.d.comb += ge.eq(ge_ripple(ab[:width], ab[width:]))
        got = []

        async def testbench(ctx):
            for x, y in pairs:
                ctx.set(ab, x | y << width)
                got.append(ctx.get(ge))

        simulate(m, [testbench], name=f"ge_ripple_{width}")
        assert got == [int(x >= y) for x, y in pairs]
    with pytest.raises(ValueError, match=r"^ge_ripple operands must have one width, not 3 and 4$"):
        ge_ripple(Signal(3), Signal(4))


def test_engine_speed_parameters_are_checked():
    """Clear errors: ``speed`` not a bool, ``speed=True`` without the configuration RAM, a
    ``config_init`` not of the 20 words; an ``Engine`` slice of a word not in ``config`` or
    wider than its special."""
    import gc
    import warnings

    import pytest
    from amaranth.hdl import UnusedElaboratable, signed

    from foc_servo.hdl.engine import Engine
    from foc_servo.hdl.foc_engine import (SPECIALS, SPEED_SHAPES, SPEED_SLICES,
                                          current_loop_program)

    with pytest.raises(TypeError, match=r"^EngineCurrentLoop speed must be a bool, not 1$"):
        EngineCurrentLoop(config="ram", speed=1)
    with pytest.raises(ValueError, match=r"^EngineCurrentLoop speed=True needs config='ram' "):
        EngineCurrentLoop(speed=True)
    with pytest.raises(ValueError, match=r"^EngineCurrentLoop config_init must be a list of 20 "
                                         r"integers, not \[0, 0\]$"):
        EngineCurrentLoop(config="ram", speed=True, config_init=[0, 0])
    prog = current_loop_program(speed=True)
    shapes = {**{n: signed(20) for n in SPECIALS}, **SPEED_SHAPES}
    outs = {**OUTS, **SPEED_OUTS}
    words = CONFIG + SPEED_CONFIG_WORDS
    with pytest.raises(ValueError, match=r"^Engine config_slices\['kph'\] must be \(word of "
                                         r"config, lo, bits >= 1, shift\) "):
        Engine(program=prog, special_shapes=shapes, out_widths=outs, config=CONFIG,
               config_slices=SPEED_SLICES)
    with pytest.raises(ValueError, match=r"^Engine config_slices\['kxc'\] must be "):
        Engine(program=prog, special_shapes=shapes, out_widths=outs, config=words,
               config_slices={**SPEED_SLICES, "kxc": ("kx", 0, 5, 0)})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UnusedElaboratable)
        eng = Engine(program=prog, special_shapes=shapes, out_widths=outs, config=words,
                     config_init=[0] * len(words), config_slices=SPEED_SLICES)
        assert eng.config_width == 32 and eng.rom_width == 64
        assert not any(hasattr(eng, f"s_{n}") for n in SPEED_SLICES)
        del eng
        gc.collect()                    # (built for its attributes only: no warning)
