"""EngineCurrentLoop(refs="ram"): the references as words of the loop engine's configuration
RAM and the program's own forming of them (docs/AREA.md §7.69), against the ports and latches
of ``refs="ports"`` fed as the Servo feeds them."""

import numpy as np
import pytest
from amaranth.hdl import Elaboratable, Module

from foc_servo.hdl.foc_engine import (CONFIG, REF_CONFIG_WORDS, REF_STATUS, SPEED_CONFIG_WORDS,
                                      START_CLOCKS, STATUS, EngineCurrentLoop, _clocks, _paths,
                                      current_loop_program, duty_lengths, path_lengths,
                                      speed_run_timing, status_quiet)
from foc_servo.sim.harness import simulate

from test_engine import _built_for_signatures

N_CFG = len(CONFIG)
WORD = {name: N_CFG + j for j, name in enumerate(REF_CONFIG_WORDS)}


class _Pair(Elaboratable):
    """``refs="ports"`` and ``refs="ram"`` side by side (simulation only), both with the speed
    run and the configuration RAM (the iCEBreaker's engine)."""

    def __init__(self, init, refs_init):
        self.ports = EngineCurrentLoop(config="ram", speed=True, config_init=init)
        self.ram = EngineCurrentLoop(config="ram", speed=True, refs="ram",
                                     config_init=init[:N_CFG] + refs_init + init[N_CFG:])

    def elaborate(self, platform):
        m = Module()
        m.submodules.ports = self.ports
        m.submodules.ram = self.ram
        return m


OUTS = ["busy", "done", "overmod", "dc_limited", "overrun", "overruns", "count", "sat_d",
        "sat_q", "i_alpha", "i_beta", "i_d", "i_q", "u_d", "u_q", "u_alpha", "u_beta",
        "speed_sat", "speed_ref_int"]


def _outputs(ctx, dut):
    return [ctx.get(getattr(dut, n)) for n in OUTS] + [
        ctx.get(dut.o.valid), ctx.get(dut.o.payload.as_value()), ctx.get(dut.phase.valid),
        ctx.get(dut.phase.payload.as_value()), ctx.get(dut.udc.payload),
        ctx.get(dut.speed_o.valid), ctx.get(dut.speed_o.payload)]


def _clamp(x, lo, hi):
    """The Servo's ``clamp(iq_set)`` (hdl/servo.py): above ``hi`` first."""
    return hi if x > hi else lo if x < lo else x


def _s16(rng):
    return int(rng.integers(-32768, 32768))


@pytest.mark.parametrize("seed", [1, 2])
def test_engine_refs_ram_equals_ports_cycle_by_cycle(seed):
    """Random samples in every mode (DISABLED, OPEN_LOOP, CURRENT, SPEED: ``enable``,
    ``ol_enable``, ``speed_clear`` as the Servo drives them) and speed runs between them,
    every output in every clock: the ports loop gets ``id_ref``, ``iq_ref`` as the Servo forms
    them (``id_set`` when running, ``clamp(iq_set, lo, hi)`` in CURRENT mode, its own speed
    run's i_q reference in SPEED mode, else 0), ``ol_ud``, ``ol_uq`` and the limits as ports;
    the RAM loop has the six words written into its configuration RAM before the sample (as
    the register file's commit copy writes them before the period, in the top) and rewritten
    with the same values while it runs; inverted and narrow limits included."""
    rng = np.random.default_rng(seed)
    # A working loop (the PIs' outputs follow their references): modest gains, limits ±20000.
    cfg = {"gain_a": 1 << 15, "gain_b": 1 << 15, "kp_d": int(rng.integers(1 << 7, 1 << 9)),
           "kp_q": int(rng.integers(1 << 7, 1 << 9)), "kx_d": int(rng.integers(1 << 12)),
           "kx_q": int(rng.integers(1 << 12)), "ff_l": int(rng.integers(1 << 10)),
           "ff_psi": int(rng.integers(1 << 10)), "klead": int(rng.integers(1 << 16)),
           "urat": int(rng.integers(1 << 14, 1 << 15)),
           **{f"{side}_{ax}": (20000 if side == "hi" else -20000 & 0xFFFF_FFFF)
              for side in ("lo", "hi") for ax in "dq"}}
    init = [cfg.get(name, 0) for name in CONFIG] + [
        int(rng.integers(1 << 10, 1 << 14)), int(rng.integers(0, 1 << 16)), 0, 300]
    bench = _Pair(init, [0] * len(REF_CONFIG_WORDS))
    a, b = bench.ports, bench.ram
    assert not any(hasattr(b, n) for n in ("ol_ud", "ol_uq", "id_ref", "iq_ref", "iq_lim_lo",
                                           "iq_lim_hi"))
    fig = {"modes": [0, 0, 0, 0], "speed_runs": 0, "rewrites": 0, "clamped": 0,
           "mismatch": None}

    async def tick(ctx, clock):
        got_a, got_b = _outputs(ctx, a), _outputs(ctx, b)
        if got_a != got_b and fig["mismatch"] is None:
            fig["mismatch"] = (clock, [(k, x, y) for k, (x, y) in enumerate(zip(got_a, got_b))
                                       if x != y])
        await ctx.tick()
        for dut in (a, b):
            ctx.set(dut.config.valid, 0)
            ctx.set(dut.i.valid, 0)
            ctx.set(dut.speed_valid, 0)

    async def testbench(ctx):
        words = dict.fromkeys(REF_CONFIG_WORDS, 0)
        ref = int(rng.integers(-(1 << 31), 1 << 31))
        for dut in (a, b):
            ctx.set(dut.o.ready, 1)
            ctx.set(dut.speed_rate_div, 0)
            ctx.set(dut.speed_clear, 1)
            ctx.set(dut.speed_ref, ref)
        ctx.set(a.iq_lim_lo, 0)
        ctx.set(a.iq_lim_hi, 0)
        clock = 0
        for mode in rng.permutation([0, 1, 2, 3] * 6):  # DISABLED, OPEN_LOOP, CURRENT, SPEED
            mode = int(mode)
            fig["modes"][mode] += 1
            # The mode and the speed run's inputs, between runs (the Servo's loop strobe).
            hold, delay = int(rng.random() < 0.2), int(rng.integers(32))
            for dut in (a, b):
                ctx.set(dut.speed_clear, int(mode != 3))
                ctx.set(dut.speed_int_hold, hold)
                ctx.set(dut.speed_ref_delay, delay)
            # The references: one word a clock into the RAM (the export port's copy), the
            # limits also to the ports loop's ports (read by its speed runs too).
            lo, hi = sorted((_s16(rng), _s16(rng)))
            iqset = _s16(rng)
            if mode == 2:               # CURRENT: the clamp's cases in turn
                case = fig["modes"][2] % 6
                lo, hi = sorted((int(rng.integers(-20000, 0)), int(rng.integers(0, 20000))))
                iqset = (int(rng.integers(lo, hi)), hi + 100, lo - 100)[case % 3]
                if case >= 3:
                    lo, hi = hi, lo                                 # inverted limits
            words = {"ol_ud": _s16(rng), "ol_uq": _s16(rng), "idset": _s16(rng),
                     "iqset": iqset, "ilo": lo, "ihi": hi}
            for name, v in words.items():
                ctx.set(b.config.valid, 1)
                ctx.set(b.config.index, WORD[name])
                ctx.set(b.config.data, v & 0xFFFF_FFFF)
                await tick(ctx, clock)
                clock += 1
            ctx.set(a.iq_lim_lo, lo)
            ctx.set(a.iq_lim_hi, hi)
            # A speed run (SPEED mode, or cleared), then the sample after it.
            speed = int(rng.integers(-(1 << 30), 1 << 30))
            for dut in (a, b):
                ctx.set(dut.speed, speed)
                ctx.set(dut.speed_valid, 1)
            fig["speed_runs"] += 1
            for _ in range(int(rng.integers(240, 300))):
                await tick(ctx, clock)
                clock += 1
            sample = {"ia": int(rng.integers(-9000, 9000)), "ib": int(rng.integers(-9000, 9000)),
                      "udc": int(rng.integers(9000, 32768)), "aux": 0}
            enable, ol = int(mode != 0), int(mode == 1)
            run = mode in (2, 3)
            iq = (_clamp(words["iqset"], lo, hi) if mode == 2 else
                  ctx.get(b.speed_o.payload) if mode == 3 else 0)
            fig["clamped"] += mode == 2 and iq != words["iqset"]
            values = {"theta": int(rng.integers(1 << 16)), "enable": enable, "ol_enable": ol,
                      "ff_enable": int(rng.random() < 0.6),
                      "speed": int(rng.integers(-(1 << 31), 1 << 31)),
                      "scale": int(rng.integers(1 << 16))}
            for dut in (a, b):
                ctx.set(dut.i.payload, sample)
                ctx.set(dut.i.valid, 1)
                for name, v in values.items():
                    ctx.set(getattr(dut, name), v)
            ctx.set(a.id_ref, words["idset"] if run else 0)
            ctx.set(a.iq_ref, iq)
            ctx.set(a.ol_ud, words["ol_ud"] if ol else 0)
            ctx.set(a.ol_uq, words["ol_uq"] if ol else 0)
            for k in range(int(rng.integers(280, 330))):
                if 0 < k and rng.random() < 0.2:                   # the same word again
                    name = REF_CONFIG_WORDS[int(rng.integers(len(REF_CONFIG_WORDS)))]
                    ctx.set(b.config.valid, 1)
                    ctx.set(b.config.index, WORD[name])
                    ctx.set(b.config.data, words[name] & 0xFFFF_FFFF)
                    fig["rewrites"] += 1
                await tick(ctx, clock)
                clock += 1

    simulate(bench, [testbench], name="engine_refs_ram")
    assert fig["mismatch"] is None, fig["mismatch"]
    assert fig["modes"] == [6] * 4 and fig["clamped"] >= 4 and fig["rewrites"] > 800


def _read_clocks(program, name, start=0):
    """Clocks from a program's start (an idle engine: the accepting clock) to the R clocks of
    the instructions that read the special ``name`` (on the straight-line start or the
    open-loop path: every path through one has the same clocks before it), in order."""
    j = program.specials.index(name)
    at = {sum(_clocks(program.instrs[p]) for p in path[:k])
          for path in _paths(program, start) for k, pc in enumerate(path)
          if program.instrs[pc].asp and program.instrs[pc].a == j}
    return [START_CLOCKS - 1 + k for k in sorted(at)]


def test_engine_refs_ram_word_read_when_the_program_reads_it():
    """The documented difference from the ports' latches: a word written after the accepting
    clock is the run's if it is written before the program reads it (the write in the clock
    before the reading instruction's R clock, bypassed), not if it comes in that clock or
    later; a latch would take neither. Open loop (``ol_ud``) and CURRENT mode (``idset``), one
    run each."""
    init = [0] * (N_CFG + len(REF_CONFIG_WORDS) + 4)
    # PI_d: kp 1.0, limits ±full scale (its output follows the reference).
    for name, v in {"kp_d": 1 << 8, "lo_d": -32768 & 0xFFFF_FFFF, "hi_d": 32767}.items():
        init[CONFIG.index(name)] = v
    dut = EngineCurrentLoop(config="ram", speed=True, refs="ram", config_init=init)
    cases = {"ol_ud": (1, "u_d", 3000, -5000), "idset": (0, "u_d", 3000, -5000)}
    # (idset: read for the scope's word at 33, by PI_d at 43; iqset, ihi, ilo, the speed
    # run's i_q: at 5, 9, 19, 27)
    assert _read_clocks(dut.program, "idset") == [33, 43]
    assert [_read_clocks(dut.program, n) for n in ("iqset", "ihi", "ilo", "sliq")] == [
        [5], [9], [19], [27]]
    reads = {name: _read_clocks(dut.program, name)[-1] for name in cases}
    assert reads["ol_ud"] == 58
    runs = {}

    async def testbench(ctx):
        sample = {"ia": 0, "ib": 0, "udc": 9000, "aux": 0}
        ctx.set(dut.o.ready, 1)
        ctx.set(dut.speed_clear, 1)
        for name, (ol, out, old, new) in cases.items():
            read = reads[name]
            for delay in ("warm-up", None, read - 1, read):
                ctx.set(dut.config.valid, 1)            # the word's old value, idle
                ctx.set(dut.config.index, WORD[name])
                ctx.set(dut.config.data, old)
                await ctx.tick()
                ctx.set(dut.config.valid, 0)
                ctx.set(dut.i.payload, sample)
                for port, v in {"theta": 0, "enable": 1, "ol_enable": ol, "ff_enable": 0,
                                "scale": 1000}.items():
                    ctx.set(getattr(dut, port), v)
                ctx.set(dut.i.valid, 1)
                for clock in range(400):
                    if clock == delay:
                        ctx.set(dut.config.valid, 1)    # the new value, mid-run
                        ctx.set(dut.config.data, new & 0xFFFF_FFFF)
                    await ctx.tick()
                    ctx.set(dut.i.valid, 0)
                    ctx.set(dut.config.valid, 0)
                    if ctx.get(dut.o.valid):
                        runs[name, delay] = ctx.get(dut.u_d)
                while ctx.get(dut.busy):
                    await ctx.tick()

    simulate(dut, [testbench], name="engine_refs_read")
    # Open loop: u_d is the word; CURRENT: the PI's output moves with the reference.
    assert runs["ol_ud", None] == runs["ol_ud", reads["ol_ud"]] == 3000
    assert runs["ol_ud", reads["ol_ud"] - 1] == -5000
    assert runs["idset", None] == runs["idset", reads["idset"]]
    assert runs["idset", reads["idset"] - 1] != runs["idset", None]


def test_engine_refs_program_timing_unchanged():
    """``current_loop_program(speed=True, refs=True)``: its five instructions fill NOP slots of
    the straight-line start, so every output the outside sees is written in the same clock of
    every path as without ``refs`` (the duties, the status values, ``o.valid`` and ``done``:
    the top's ports, the scope's samples), the speed run too, in the same 500 words unfolded
    (folded: the five words where five bubbles were, 345 → 350); the two
    new status words are written before the last duty and leave the scope's quiet clocks."""
    def writes(program, start=0):
        seen = []
        for path in _paths(program, start):
            k, w = 0, []
            for pc in path:
                ins = program.instrs[pc]
                if ins.out and program.outs[ins.out] not in ("idr", "iqr"):
                    w.append((k, program.outs[ins.out]))
                k += _clocks(ins)
            seen.append((w, k))
        return seen
    old = current_loop_program(speed=True)
    new = current_loop_program(speed=True, refs=True)
    assert len(current_loop_program(speed=True, refs=True, fold=False).words) == \
        len(current_loop_program(speed=True, fold=False).words) == 500
    assert (len(old.words), len(new.words)) == (345, 350)
    assert writes(new) == writes(old)
    assert writes(new, new.labels["speed"]) == writes(old, old.labels["speed"])
    assert duty_lengths(new) == duty_lengths(old) and path_lengths(new) == path_lengths(old)
    assert speed_run_timing(new) == speed_run_timing(old)
    assert status_quiet(new, STATUS + REF_STATUS) == status_quiet(old) == 12
    with pytest.raises(ValueError, match=r"^engine program: refs needs speed"):
        current_loop_program(refs=True)


def test_engine_refs_parameters():
    _built_for_signatures(_check_parameters)


def _check_parameters():
    from foc_servo.hdl.bus import WordWriteSignature
    n = N_CFG + len(SPEED_CONFIG_WORDS)
    ports = EngineCurrentLoop(config="ram", speed=True, status="ram")
    ram = EngineCurrentLoop(config="ram", speed=True, status="ram", refs="ram")
    assert set(ports.signature.members) - set(ram.signature.members) == {
        "ol_ud", "ol_uq", "id_ref", "iq_ref", "iq_lim_lo", "iq_lim_hi"}
    sig = ram.signature.members["config"].signature
    assert isinstance(sig, WordWriteSignature) and sig.depth == n + 6 == 26
    assert ram.status_words == STATUS + REF_STATUS and ports.status_words == STATUS
    assert ram.signature.members["status_probe"].signature.addr_width == 4
    assert ram.signature.members["status_rd"].signature.addr_width == 3
    assert ports.refs_mode == "ports" and ram.refs_mode == "ram"
    with pytest.raises(ValueError, match=r"^EngineCurrentLoop refs must be one of 'ports', "
                                         r"'ram', not 'regs'$"):
        EngineCurrentLoop(config="ram", speed=True, refs="regs")
    for kw in ({}, {"config": "ram"}):
        with pytest.raises(ValueError, match=r"^EngineCurrentLoop refs='ram' needs config='ram' "
                                             r"and speed=True \(the references are words of "
                                             r"its configuration RAM, the SPEED mode's i_q the "
                                             r"speed run's\), not config="):
            EngineCurrentLoop(refs="ram", **kw)
    with pytest.raises(ValueError, match=r"^EngineCurrentLoop config_init must be a list of 26 "
                                         r"integers, not \[0\]$"):
        EngineCurrentLoop(config="ram", speed=True, refs="ram", config_init=[0])


def test_engine_refs_sample_behind_a_speed_run_takes_its_result():
    """The other documented difference (hdl/top.py "References in the engine's RAM"): a SPEED
    mode sample accepted while a speed run is in flight waits for it (``pending``) and, reading
    the run's i_q reference when it runs, takes that run's result, where the ports' latch took
    the reference of the accepting clock (the previous run's: here 0, the first after
    ``clear``). PI_q with kp 1, no integral, full-scale limits, zero currents: u_q is the
    reference it used."""
    init = [0] * (N_CFG + len(REF_CONFIG_WORDS) + 4)
    for name, v in {"kp_q": 1 << 8, "lo_q": -32768 & 0xFFFF_FFFF, "hi_q": 32767}.items():
        init[CONFIG.index(name)] = v
    init[WORD["ilo"]], init[WORD["ihi"]] = -5000 & 0xFFFF_FFFF, 5000
    init[N_CFG + len(REF_CONFIG_WORDS)] = 1 << 12                     # speed kp 1.0
    dut = EngineCurrentLoop(config="ram", speed=True, refs="ram", config_init=init)
    seen = {}

    async def testbench(ctx):
        ctx.set(dut.o.ready, 1)
        for port, v in {"speed_clear": 0, "speed_ref": 1 << 28, "speed": 0, "theta": 0,
                        "enable": 1, "ol_enable": 0, "ff_enable": 0, "scale": 1000}.items():
            ctx.set(getattr(dut, port), v)
        ctx.set(dut.i.payload, {"ia": 0, "ib": 0, "udc": 9000, "aux": 0})
        ctx.set(dut.speed_valid, 1)                 # a speed run starts (the engine is idle)
        await ctx.tick()
        ctx.set(dut.speed_valid, 0)
        await ctx.tick().repeat(20)
        seen["before"] = ctx.get(dut.speed_o.payload)
        ctx.set(dut.i.valid, 1)                     # a sample during the run: it waits
        await ctx.tick()
        ctx.set(dut.i.valid, 0)
        for _ in range(600):
            if ctx.get(dut.speed_o.valid):
                seen["iq"] = ctx.get(dut.speed_o.payload)
                seen["iq_valid_before_o"] = "o" not in seen
            if ctx.get(dut.o.valid) and "o" not in seen:
                seen["o"] = ctx.get(dut.u_q)
            await ctx.tick()

    simulate(dut, [testbench], name="engine_refs_behind_speed")
    assert seen["before"] == 0 and seen["iq"] == 4096 and seen["iq_valid_before_o"]
    assert seen["o"] == 4096
