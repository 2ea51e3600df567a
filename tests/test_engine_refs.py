"""EngineCurrentLoop(refs="ram"): the per-sample references as words of the loop engine's
configuration RAM (docs/AREA.md §7.69), against the ports and latches of ``refs="ports"``."""

import numpy as np
import pytest
from amaranth.hdl import Elaboratable, Module

from foc_servo.hdl.foc_engine import (CONFIG, REF_CONFIG_WORDS, START_CLOCKS, EngineCurrentLoop,
                                      _clocks, _paths)
from foc_servo.sim.harness import simulate

from test_engine import _built_for_signatures, _random_sample


class _Pair(Elaboratable):
    """``refs="ports"`` and ``refs="ram"`` side by side (simulation only)."""

    def __init__(self, config_init):
        self.ports = EngineCurrentLoop(config="ram", config_init=config_init)
        self.ram = EngineCurrentLoop(config="ram", refs="ram",
                                     config_init=config_init + [0] * len(REF_CONFIG_WORDS))

    def elaborate(self, platform):
        m = Module()
        m.submodules.ports = self.ports
        m.submodules.ram = self.ram
        return m


OUTS = ["busy", "done", "overmod", "dc_limited", "overrun", "overruns", "count", "sat_d",
        "sat_q"]


def _outputs(ctx, dut):
    return [ctx.get(getattr(dut, n)) for n in OUTS] + [
        ctx.get(dut.o.valid), ctx.get(dut.o.payload.as_value()), ctx.get(dut.phase.valid),
        ctx.get(dut.phase.payload.as_value()), ctx.get(dut.udc.payload)]


def _ref_read(program, name):
    """Clocks from a sample's start (an idle engine: the accepting clock) to the R clock of the
    one instruction that reads the special ``name`` (on the straight-line start and the
    open-loop path: every path through it has the same clocks before it)."""
    j = program.specials.index(name)
    at = {sum(_clocks(program.instrs[p]) for p in path[:k])
          for path in _paths(program) for k, pc in enumerate(path)
          if program.instrs[pc].asp and program.instrs[pc].a == j}
    assert len(at) == 1, at
    return START_CLOCKS - 1 + at.pop()


@pytest.mark.parametrize("seed", [1, 2])
def test_engine_refs_ram_equals_ports_cycle_by_cycle(seed):
    """Random samples (open loop in about a third), every output in every clock: the ports
    loop latches ``ol_ud``, ``ol_uq`` at the accepting clock, the RAM loop has them written
    into its configuration RAM in that clock (as the register file's commit copy writes them
    before the sample, in the top) and, in random clocks while it runs, the same values again
    (a rewrite changes nothing); the other configuration words are written alike into both
    RAMs in random clocks."""
    rng = np.random.default_rng(seed)
    init = [int(rng.integers(0, 1 << 16)) for _ in CONFIG]
    bench = _Pair(init)
    a, b = bench.ports, bench.ram
    assert not hasattr(b, "ol_ud") and not hasattr(b, "ol_uq") and b.refs_mode == "ram"
    n = len(CONFIG)
    fig = {"runs": 0, "ol_runs": 0, "rewrites": 0, "mismatch": None}

    async def testbench(ctx):
        held = {"ol_ud": 0, "ol_uq": 0}
        for clock in range(5000):
            for dut in (a, b):
                ctx.set(dut.config.valid, 0)
                ctx.set(dut.o.ready, 1)
            start = not ctx.get(a.busy) and rng.random() < 0.2
            for dut in (a, b):
                ctx.set(dut.i.valid, int(start))
            if start:
                fig["runs"] += 1
                sample, values = _random_sample(rng, config_ports=False)
                if rng.random() < 0.35:
                    values.update(enable=1, ol_enable=1)
                    fig["ol_runs"] += 1
                for dut in (a, b):
                    ctx.set(dut.i.payload, sample)
                    for name, v in values.items():
                        if hasattr(dut, name):
                            ctx.set(getattr(dut, name), v)
                j = int(rng.integers(len(REF_CONFIG_WORDS)))
                held = {name: values[name] for name in REF_CONFIG_WORDS}
                name = REF_CONFIG_WORDS[j]
                # One word in the accepting clock (the write port takes one a clock), the
                # other in the next.
                ctx.set(b.config.valid, 1)
                ctx.set(b.config.index, n + j)
                ctx.set(b.config.data, held[name] & 0xFFFF_FFFF)
                if _outputs(ctx, a) != _outputs(ctx, b) and fig["mismatch"] is None:
                    fig["mismatch"] = (clock, "accept")
                await ctx.tick()
                other = REF_CONFIG_WORDS[1 - j]
                for dut in (a, b):
                    ctx.set(dut.i.valid, 0)
                ctx.set(b.config.valid, 1)
                ctx.set(b.config.index, n + 1 - j)
                ctx.set(b.config.data, held[other] & 0xFFFF_FFFF)
            elif rng.random() < 0.3:
                if rng.random() < 0.5:
                    j = int(rng.integers(len(REF_CONFIG_WORDS)))
                    ctx.set(b.config.valid, 1)
                    ctx.set(b.config.index, n + j)
                    ctx.set(b.config.data, held[REF_CONFIG_WORDS[j]] & 0xFFFF_FFFF)
                    fig["rewrites"] += 1
                else:
                    j = int(rng.integers(n))
                    v = int(rng.integers(0, 1 << 16))
                    for dut in (a, b):
                        ctx.set(dut.config.valid, 1)
                        ctx.set(dut.config.index, j)
                        ctx.set(dut.config.data, v)
            got_a, got_b = _outputs(ctx, a), _outputs(ctx, b)
            if got_a != got_b and fig["mismatch"] is None:
                fig["mismatch"] = (clock, got_a, got_b)
            await ctx.tick()

    simulate(bench, [testbench], name="engine_refs_ram")
    assert fig["mismatch"] is None, fig["mismatch"]
    assert fig["runs"] > 15 and fig["ol_runs"] > 5 and fig["rewrites"] > 100


def test_engine_refs_ram_word_read_when_the_program_reads_it():
    """The documented difference from the ports' latch: a word written after the accepting
    clock is the run's if its write comes before the program reads it (``_ref_read``: the
    write in the clock before the reading instruction's R clock, bypassed), not if it comes in
    that clock or later; with the latch neither is. Open loop, ``ol_ud``, one run each."""
    dut = EngineCurrentLoop(config="ram", refs="ram",
                            config_init=[0] * (len(CONFIG) + len(REF_CONFIG_WORDS)))
    read = _ref_read(dut.program, "ol_ud")
    assert read > 40                        # well after the accepting clock (the latch's)
    j = len(CONFIG) + REF_CONFIG_WORDS.index("ol_ud")
    runs = {}

    async def testbench(ctx):
        sample = {"ia": 0, "ib": 0, "udc": 9000, "aux": 0}
        for delay in ("warm-up", None, read - 1, read):   # (the DC-bus gain: the previous run's)
            ctx.set(dut.o.ready, 1)
            ctx.set(dut.config.valid, 1)            # ol_ud = 3000, idle
            ctx.set(dut.config.index, j)
            ctx.set(dut.config.data, 3000)
            await ctx.tick()
            ctx.set(dut.config.valid, 0)
            ctx.set(dut.i.payload, sample)
            for name, v in {"theta": 0, "enable": 1, "ol_enable": 1, "ff_enable": 0,
                            "scale": 1000}.items():
                ctx.set(getattr(dut, name), v)
            ctx.set(dut.i.valid, 1)
            for clock in range(400):
                if clock == delay:
                    ctx.set(dut.config.valid, 1)    # ol_ud = −5000, mid-run
                    ctx.set(dut.config.data, -5000 & 0xFFFF_FFFF)
                await ctx.tick()
                ctx.set(dut.i.valid, 0)
                ctx.set(dut.config.valid, 0)
                if ctx.get(dut.o.valid):
                    runs[delay] = (ctx.get(dut.u_d), ctx.get(dut.o.payload.as_value()))
            while ctx.get(dut.busy):
                await ctx.tick()

    simulate(dut, [testbench], name="engine_refs_read")
    assert runs[None] == runs[read] != runs[read - 1]
    assert runs[None][0] == 3000 and runs[read - 1][0] == -5000


def test_engine_refs_parameters():
    _built_for_signatures(_check_parameters)


def _check_parameters():
    from foc_servo.hdl.bus import WordWriteSignature
    ports = EngineCurrentLoop(config="ram")
    ram = EngineCurrentLoop(config="ram", refs="ram")
    assert set(ports.signature.members) - set(ram.signature.members) == set(REF_CONFIG_WORDS)
    sig = ram.signature.members["config"].signature
    assert isinstance(sig, WordWriteSignature) and sig.depth == len(CONFIG) + 2 == 18
    assert ports.refs_mode == "ports" and ram.program.words == ports.program.words
    with pytest.raises(ValueError, match=r"^EngineCurrentLoop refs must be one of 'ports', "
                                         r"'ram', not 'regs'$"):
        EngineCurrentLoop(config="ram", refs="regs")
    with pytest.raises(ValueError, match=r"^EngineCurrentLoop refs='ram' needs config='ram' "
                                         r"\(the references are words of its configuration "
                                         r"RAM\), not config='ports'$"):
        EngineCurrentLoop(refs="ram")
    with pytest.raises(ValueError, match=r"^EngineCurrentLoop config_init must be a list of 18 "
                                         r"integers, not \[0\]$"):
        EngineCurrentLoop(config="ram", refs="ram", config_init=[0])
