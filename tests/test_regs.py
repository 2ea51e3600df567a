# amaranth: UnusedElaboratable=no
# Ref: issue 5 item 1 (register file, shadowing); hdl/bus.py (register bus)
import re

import pytest
from amaranth.back import verilog
from amaranth.hdl import signed, unsigned

from foc_servo.hdl.bus import Status
from foc_servo.hdl.regmap import FAULT_FIELDS, REGMAP, Access, Mode, Scales, build_regmap
from foc_servo.hdl.regs import RegisterFile
from foc_servo.sim.harness import simulate
from foc_servo.sim.models.regs import RegisterFileModel
from foc_servo.sim.verify import regs as verify_regs
from foc_servo.sim.verify.regs import run, window_word


async def access(ctx, dut, addr, *, we=0, data=0, lock=0):
    """One bus access as the master does it; checks ``ack`` comes exactly ``dut.latency`` (2)
    clocks after ``stb`` and returns ``(r_data, status)``."""
    ctx.set(dut.bus.addr, addr)
    ctx.set(dut.bus.we, we)
    ctx.set(dut.bus.w_data, data & 0xFFFFFFFF)
    ctx.set(dut.bus.lock, lock)
    ctx.set(dut.bus.stb, 1)
    assert ctx.get(dut.bus.ack) == 0
    for _ in range(dut.latency - 1):
        await ctx.tick()
        assert ctx.get(dut.bus.ack) == 0              # stb held: not a new access
    await ctx.tick()
    assert ctx.get(dut.bus.ack) == 1                  # latency 2
    r_data, status = ctx.get(dut.bus.r_data), ctx.get(dut.bus.status)
    await ctx.tick()
    ctx.set(dut.bus.stb, 0)
    assert ctx.get(dut.bus.ack) == 0                  # stb held in the ack clock: no new access
    return r_data, Status(status)


def bits(port):
    return port.as_value() if hasattr(port, "as_value") else port


def run_tb(dut, tb, name):
    simulate(dut, [tb], name=name)


def test_register_file_rejects_a_non_regmap():
    with pytest.raises(TypeError, match=r"^RegisterFile regmap must be a RegMap, not \[\]$"):
        RegisterFile([])


def test_register_file_ports_follow_the_declaration():
    dut = RegisterFile()
    members = dut.signature.members
    for r in REGMAP:
        if r.access is Access.RW:
            assert members[r.name].flow.name == "Out"
            assert r.bits(bits(getattr(dut, r.name)).init) == r.bits(r.reset), r.name
        elif r.access is Access.RO:
            assert members[r.name].flow.name == "In"
        elif r.access is Access.STROBE:
            assert members[r.name].flow.name == "Out" and members[r.name].shape == 1
        else:
            assert r.name not in members
    assert members["mode"].shape is Mode
    assert list(members["prot_mask"].shape.members) == list(FAULT_FIELDS)
    assert members["pi_d_lim_lo"].shape == signed(16) and members["mt_k"].shape == unsigned(48)
    assert members["scope_rd_addr"].shape == 12
    assert members["scope_rd_data"].shape == 32
    assert dut.latency == 2 and dut.commit_latency == 1


def test_every_register_reset_value_reads_back():
    dut = RegisterFile()

    async def tb(ctx):
        for addr, r, k in REGMAP.words():
            r_data, status = await access(ctx, dut, addr)
            assert status is Status.OK, r.name
            expect = 0 if r.access in (Access.STROBE,) else r.read_word(r.bits(r.reset), k)
            assert r_data == expect, (r.name, k, hex(r_data), hex(expect))
    run_tb(dut, tb, "regs_reset")


def test_constants_follow_the_build_scales():
    scales = Scales(clk_hz=33_333_333, pwm_hz=9997.999, i_fs_a=15.5, u_fs_v=3.0e-3,
                    n_fs_rpm=6000)
    regmap = build_regmap(scales)
    dut = RegisterFile(regmap)

    async def tb(ctx):
        got = {}
        for name in ("id_clk_hz", "id_pwm_mhz", "id_i_fs_ma", "id_u_fs_uv", "id_n_fs_rpm"):
            got[name], status = await access(ctx, dut, regmap[name].addr)
            assert status is Status.OK
        assert Scales.from_id_raw(got) == Scales(clk_hz=33_333_333, pwm_hz=9997.999,
                                                 i_fs_a=15.5, u_fs_v=3.0e-3, n_fs_rpm=6000)
        lo, _ = await access(ctx, dut, regmap["dead_time"].addr)
        assert lo == 33                               # 1 µs at 33.333 MHz
    run_tb(dut, tb, "regs_consts")


def test_signed_register_reads_sign_extended_and_writes_take_low_bits():
    dut = RegisterFile()
    a = REGMAP["i_q_ref"].addr

    async def tb(ctx):
        r_data, status = await access(ctx, dut, a, we=1, data=0xABCD8001)
        assert status is Status.OK
        r_data, _ = await access(ctx, dut, a)
        assert r_data == 0xFFFF8001                   # -32767, sign-extended
    run_tb(dut, tb, "regs_signed")


def test_wide_register_spans_two_words_low_first():
    dut = RegisterFile()
    k = REGMAP["mt_k"]

    async def tb(ctx):
        await access(ctx, dut, k.addr, we=1, data=0x89ABCDEF, lock=1)
        await access(ctx, dut, k.addr + 1, we=1, data=0xFFFF1234, lock=1)
        assert [(await access(ctx, dut, k.addr + i))[0] for i in range(2)] == [0x89ABCDEF, 0x1234]
        ctx.set(dut.commit, 1)
        await ctx.tick()
        ctx.set(dut.commit, 0)
        assert ctx.get(dut.mt_k) == 0x123489ABCDEF
    run_tb(dut, tb, "regs_wide")


def test_burst_across_commit_with_lock_high_applies_only_after_lock_falls():
    dut = RegisterFile()
    kp, kx = REGMAP["pi_q_kp"], REGMAP["pi_q_kx"]

    async def tb(ctx):
        await access(ctx, dut, kp.addr, we=1, data=0x0123, lock=1)
        # A loop boundary in the middle of the frame: nothing may be applied yet.
        ctx.set(dut.commit, 1)
        await ctx.tick()
        ctx.set(dut.commit, 0)
        assert (ctx.get(dut.pi_q_kp), ctx.get(dut.pi_q_kx)) == (0, 0)
        ctx.set(dut.commit, 1)                     # commit during the second access, lock high
        await access(ctx, dut, kx.addr, we=1, data=0x4567, lock=1)
        ctx.set(dut.commit, 0)
        assert (ctx.get(dut.pi_q_kp), ctx.get(dut.pi_q_kx)) == (0, 0)
        # The reads already return the staged values.
        assert (await access(ctx, dut, kp.addr, lock=1))[0] == 0x0123
        ctx.set(dut.bus.lock, 0)                   # frame over
        for _ in range(3):
            await ctx.tick()
        assert (ctx.get(dut.pi_q_kp), ctx.get(dut.pi_q_kx)) == (0, 0)   # no commit yet
        ctx.set(dut.commit, 1)
        assert ctx.get(dut.pi_q_kp) == 0
        await ctx.tick()                           # applied at the end of the commit clock
        ctx.set(dut.commit, 0)
        assert (ctx.get(dut.pi_q_kp), ctx.get(dut.pi_q_kx)) == (0x0123, 0x4567)
    run_tb(dut, tb, "regs_burst_lock")


def test_immediate_register_and_strobe_act_the_clock_after_stb():
    dut = RegisterFile()
    oc, clear = REGMAP["prot_oc_limit"], REGMAP["clear_faults"]

    async def tb(ctx):
        ctx.set(dut.bus.addr, oc.addr)
        ctx.set(dut.bus.we, 1)
        ctx.set(dut.bus.w_data, 1234)
        ctx.set(dut.bus.lock, 1)                   # immediate registers ignore lock
        ctx.set(dut.bus.stb, 1)
        await ctx.tick()
        assert ctx.get(dut.bus.ack) == 0 and ctx.get(dut.prot_oc_limit) == 1234
        await ctx.tick()
        assert ctx.get(dut.bus.ack) == 1
        await ctx.tick()
        ctx.set(dut.bus.stb, 0)
        pulses = []
        ctx.set(dut.bus.addr, clear.addr)
        ctx.set(dut.bus.w_data, 0xFFFFFFF1)
        ctx.set(dut.bus.stb, 1)
        for _ in range(4):
            pulses.append(ctx.get(dut.clear_faults))
            await ctx.tick()
            ctx.set(dut.bus.stb, int(len(pulses) < 3))
        assert pulses == [0, 1, 0, 0]              # one pulse, the clock after stb
        r_data, status = await access(ctx, dut, clear.addr, we=1, data=0x2)
        assert status is Status.OK and ctx.get(dut.clear_faults) == 0   # bit 0 clear: no pulse
        assert (await access(ctx, dut, clear.addr))[0] == 0             # strobes read 0
    run_tb(dut, tb, "regs_immediate")


def test_bad_address_and_read_only_writes_change_nothing():
    dut = RegisterFile()
    model = RegisterFileModel()
    used = {a for a, _, _ in REGMAP.words()}
    bad = [a for a in (0x0008, 0x000F, 0x0108, 0x0205, 0x0FFF, 0x2000, 0xFFFF) if a not in used]
    ro = [REGMAP[n] for n in ("id_magic", "id_clk_hz", "st_speed", "scope_status")]

    async def tb(ctx):
        ctx.set(dut.st_speed, -5)
        for a in bad:
            assert await access(ctx, dut, a, we=1, data=0xFFFFFFFF) == (0, Status.BAD_ADDRESS)
            assert await access(ctx, dut, a) == (0, Status.BAD_ADDRESS)
        for r in ro:
            assert (await access(ctx, dut, r.addr, we=1, data=0x1234))[1] is Status.READ_ONLY
        assert (await access(ctx, dut, 0x1000, we=1, data=7))[1] is Status.READ_ONLY
        assert await access(ctx, dut, REGMAP["st_speed"].addr) == (0xFFFFFFFB, Status.OK)
        for addr, r, k in REGMAP.words():       # every rw register kept its reset value
            if r.access is Access.RW:
                assert (await access(ctx, dut, addr))[0] == r.read_word(model.staged[r.name], k)
                assert r.bits(ctx.get(bits(getattr(dut, r.name)))) == r.bits(r.reset), r.name
    run_tb(dut, tb, "regs_bad")


def test_scope_window_reads_the_memory_one_clock_later():
    bench = verify_regs.Bench()
    dut = bench.dut
    fields = bench.stim_fields

    async def tb(ctx):
        for off in (0, 1, 0x3FF, 0x400, 0xFFF):
            ctx.set(bench.stim, bench.pack(fields, dict(addr=0x1000 + off, stb=1)))
            assert ctx.get(dut.scope_rd_addr) == off
            await ctx.tick()
            assert ctx.get(dut.bus.ack) == 0                  # the address held: read in t + 1
            await ctx.tick()
            assert ctx.get(dut.bus.ack) == 1 and Status(ctx.get(dut.bus.status)) is Status.OK
            assert ctx.get(dut.bus.r_data) == window_word(off)
            ctx.set(bench.stim, 0)
            await ctx.tick()
    simulate(bench, [tb], name="regs_window")


def test_random_bus_traffic_matches_the_model():
    fig = run(2500, seed=3)
    assert fig["mismatches"] == 0, fig["first_mismatch"]
    assert fig["vectors"] == 2500 + len(REGMAP.words())
    for key in ("reads", "writes", "bad_address", "read_only", "window_reads",
                "commits_applied", "commits_locked", "strobe_pulses"):
        assert fig[key] > 0, key


def test_random_comparison_detects_a_model_that_ignores_lock(monkeypatch):
    step = RegisterFileModel.step

    def no_lock(self, **kw):
        return step(self, **{**kw, "lock": 0})
    monkeypatch.setattr(RegisterFileModel, "step", no_lock)
    fig = run(400, seed=1)
    assert fig["mismatches"] > 0
    assert re.match(r"^clock \d+: \(got, expected\) \{", fig["first_mismatch"])


def test_register_file_converts_to_verilog():
    text = verilog.convert(RegisterFile(), name="regs")
    assert "module regs" in text


@pytest.mark.slow
def test_register_file_100k_random_accesses():
    fig = run(100_000, seed=0)
    assert fig["mismatches"] == 0, fig["first_mismatch"]
