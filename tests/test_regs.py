# amaranth: UnusedElaboratable=no
# Ref: issue 5 item 1 (register file, shadowing); hdl/bus.py (register bus)
import gc
import re
import warnings

import pytest
from amaranth.back import verilog
from amaranth.hdl import (Elaboratable, Module, Mux, Signal, UnusedElaboratable, signed,
                          unsigned)
from amaranth.lib.memory import Memory

from foc_servo.hdl.bus import Status
from foc_servo.hdl.regmap import (FAULT_FIELDS, REGMAP, Access, Mode, RegMap, Register, Scales,
                                  build_regmap)
from foc_servo.hdl.bus import WordWriteSignature
from foc_servo.hdl.regs import (Derived, RegisterFile, export_init, export_words, staging_slots,
                                word_index)
from foc_servo.sim.harness import simulate
from foc_servo.sim.models.regs import RegisterFileModel
from foc_servo.sim.verify import regs as verify_regs
from foc_servo.sim.verify.regs import run, run_export, window_word


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


async def access_waiting(ctx, dut, addr, *, we=0, data=0, lock=0):
    """One bus access, ``stb`` held until ``ack`` (a copy or the reset walk may hold it off);
    returns ``(r_data, status, clocks from stb to ack)``."""
    ctx.set(dut.bus.addr, addr)
    ctx.set(dut.bus.we, we)
    ctx.set(dut.bus.w_data, data & 0xFFFFFFFF)
    ctx.set(dut.bus.lock, lock)
    ctx.set(dut.bus.stb, 1)
    clocks = 0
    while not ctx.get(dut.bus.ack):
        await ctx.tick()
        clocks += 1
    r_data, status = ctx.get(dut.bus.r_data), ctx.get(dut.bus.status)
    await ctx.tick()
    ctx.set(dut.bus.stb, 0)
    return r_data, Status(status), clocks


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


def test_word_index_tells_every_word_apart_with_the_fewest_address_bits():
    block_bits, picked = word_index(REGMAP)
    assert (block_bits, picked) == (6, (1, 2, 3, 4))      # addr[0:6], addr[7:11]
    bits = list(range(block_bits)) + [block_bits + p for p in picked]
    words = [a for a, _, _ in REGMAP.words()]
    index = {sum(((a >> b) & 1) << j for j, b in enumerate(bits)) for a in words}
    assert len(index) == len(words)
    blocks = {a >> block_bits for a in words}
    assert len({tuple((blk >> p) & 1 for p in picked) for blk in blocks}) == len(blocks)
    # (word_index tries blocks of 1 … 256 words: none gives this map an index under 10 bits.)
    small = build_regmap(Scales(clk_hz=50e6, pwm_hz=20e3, i_fs_a=10, u_fs_v=24, n_fs_rpm=6000))
    assert word_index(small) == (block_bits, picked)      # constants do not move addresses


def test_register_file_converts_to_verilog():
    text = verilog.convert(RegisterFile(), name="regs")
    assert "module regs" in text


# --- staging="bram" ------------------------------------------------------------------------

BRAM = dict(staging="bram", copy_last=("pwm_symmetric",))


@pytest.mark.parametrize("kwargs, exc, msg", [
    ({"staging": 1}, TypeError, r"^RegisterFile staging must be a string, one of 'ff', 'bram', "
                                r"not 1$"),
    ({"staging": "sram"}, ValueError, r"^RegisterFile staging must be one of 'ff', 'bram', "
                                      r"not 'sram'$"),
    ({"staging": "bram", "copy_last": ["mode"]}, TypeError,
     r"^RegisterFile copy_last must be a tuple of register names, not \['mode'\]$"),
    ({"staging": "bram", "copy_last": ("prot_oc_limit",)}, ValueError,
     r"^RegisterFile copy_last must name shadowed rw registers, not 'prot_oc_limit'$"),
    ({"staging": "bram", "copy_last": ("nope",)}, ValueError,
     r"^RegisterFile copy_last must name shadowed rw registers, not 'nope'$"),
    ({"staging": "bram", "copy_last": ("mode", "mode")}, ValueError,
     r"^RegisterFile copy_last must not repeat a name, not \('mode', 'mode'\)$"),
    ({"copy_last": ("mode",)}, ValueError,
     r"^RegisterFile copy_last applies only to staging='bram', not staging='ff'$"),
    ({"staging": "bram", "export": "pi_d_kp"}, TypeError,
     r"^RegisterFile export must be a tuple of register names, not 'pi_d_kp'$"),
    ({"staging": "bram", "export": ("u_rated", "prot_oc_limit")}, ValueError,
     r"^RegisterFile export must name shadowed rw registers, not 'prot_oc_limit'$"),
    ({"staging": "bram", "export": ("st_mode",)}, ValueError,
     r"^RegisterFile export must name shadowed rw registers, not 'st_mode'$"),
    ({"staging": "bram", "export": ("pi_d_kp", "pi_d_kp")}, ValueError,
     r"^RegisterFile export must not repeat a name, not \('pi_d_kp', 'pi_d_kp'\)$"),
    ({"export": ("pi_d_kp",)}, ValueError,
     r"^RegisterFile export applies only to staging='bram', not staging='ff'$"),
    ({"staging": "bram", "mirror": ("prot_oc_limit", "pi_d_kp")}, ValueError,
     r"^RegisterFile mirror must name immediate rw registers, not 'pi_d_kp'$"),
    ({"staging": "bram", "mirror": ("st_mode",)}, ValueError,
     r"^RegisterFile mirror must name immediate rw registers, not 'st_mode'$"),
    ({"mirror": ("prot_oc_limit",)}, ValueError,
     r"^RegisterFile mirror applies only to staging='bram', not staging='ff'$"),
])
def test_register_file_staging_validation(kwargs, exc, msg):
    with pytest.raises(exc, match=msg):
        RegisterFile(**kwargs)


def test_model_staging_validation():
    with pytest.raises(ValueError, match=r"^RegisterFileModel staging must be one of 'ff', "
                                         r"'bram', not 'x'$"):
        RegisterFileModel(staging="x")


def test_bram_staging_slots_and_timing_attributes():
    slots = staging_slots(REGMAP, ("pwm_symmetric",))
    shadowed = [(a, r.name) for a, r, _ in REGMAP.words()
                if r.access is Access.RW and r.shadow is not None]
    assert [(a, r.name) for a, r, _ in slots] == (
        [w for w in shadowed if w[1] != "pwm_symmetric"]
        + [w for w in shadowed if w[1] == "pwm_symmetric"])
    assert [a for a, _, _ in staging_slots(REGMAP)] == [a for a, _ in shadowed]
    immediate = [a for a, r, _ in REGMAP.words() if r.access is Access.RW and r.shadow is None]
    dut = RegisterFile(**BRAM)
    # The RAM's slots: the 48 copied words, then the 15 immediate ones (read back, walked).
    assert len(slots) == 48 and len(immediate) == 15
    assert dut.staging == "bram" and dut.slots == len(slots) + len(immediate) == 63
    assert dut.latency == 2 and dut.commit_clocks == dut.commit_latency == 49
    assert dut.reset_clocks == 63
    ff = RegisterFile()
    assert (ff.staging, ff.slots, ff.commit_clocks, ff.reset_clocks) == ("ff", 0, 1, 0)
    assert set(dut.signature.members) == set(ff.signature.members)


def test_bram_reads_after_reset_return_reset_values_after_the_walk():
    dut = RegisterFile(**BRAM)

    async def tb(ctx):
        first = True
        for addr, r, k in REGMAP.words():
            if r.access is not Access.RW:
                continue
            r_data, status, clocks = await access_waiting(ctx, dut, addr)
            # The first access waits for the reset walk (reset_clocks) before it is taken.
            assert clocks == (dut.reset_clocks + dut.latency if first else dut.latency), r.name
            first = False
            assert status is Status.OK and r_data == r.read_word(r.bits(r.reset), k), r.name
    run_tb(dut, tb, "regs_bram_reset")


def test_bram_commit_copies_one_word_per_clock_and_holds_accesses_off():
    """A commit with ``lock`` low in clock s: slot i's active register changes at the end of
    clock s + 1 + i (all new in s + commit_clocks); an access arriving in the copy's first
    clock or in its last reading clock is taken after the copy (s + slots)."""
    dut = RegisterFile(**BRAM)
    slots = staging_slots(REGMAP, BRAM["copy_last"])
    n = len(slots)
    new = {}

    async def tb(ctx):
        await ctx.tick().repeat(dut.reset_clocks)
        # Write every staged word (one frame) with a value unlike its reset.
        for i, (addr, r, k) in enumerate(slots):
            lo, hi = r.word_slice(k)
            word = (r.read_word(r.bits(r.reset), k) ^ (1 + 2 * i)) & ((1 << (hi - lo)) - 1)
            new[addr] = word
            assert (await access(ctx, dut, addr, we=1, data=word, lock=1))[1] is Status.OK
        ctx.set(dut.bus.lock, 0)
        for late in (0, n - 1):               # access in the copy's first / last reading clock
            changed = {}
            before = {r.name: r.bits(ctx.get(bits(getattr(dut, r.name)))) for _, r, _ in slots}
            ctx.set(dut.commit, 1)
            for c in range(n + 3):
                if c == late:
                    ctx.set(dut.bus.addr, slots[0][0])
                    ctx.set(dut.bus.we, 0)
                    ctx.set(dut.bus.stb, 1)
                    stb_at = c
                if c == 1:
                    ctx.set(dut.commit, 0)
                await ctx.tick()
                for _, r, _ in slots:
                    v = r.bits(ctx.get(bits(getattr(dut, r.name))))
                    if v != before[r.name]:
                        changed.setdefault(r.name, []).append(c + 1)
                        before[r.name] = v
                if ctx.get(dut.bus.ack):
                    ack_at = c + 1
                    r_data = ctx.get(dut.bus.r_data)
                    await ctx.tick()
                    ctx.set(dut.bus.stb, 0)
                    break
            assert ack_at == n + dut.latency, (late, stb_at, ack_at)    # taken in clock s + n
            assert r_data == new[slots[0][0]]
            if late == 0:
                # Register of slot i: in place from clock s + 2 + i (one change per word).
                for i, (addr, r, k) in enumerate(slots):
                    assert 2 + i in changed[r.name], (r.name, i, changed.get(r.name))
                assert max(c for v in changed.values() for c in v) == dut.commit_clocks
                for addr, r, k in slots:
                    lo, hi = r.word_slice(k)
                    got = r.bits(ctx.get(bits(getattr(dut, r.name))))
                    assert (got >> lo) & ((1 << (hi - lo)) - 1) == new[addr], r.name
            else:
                assert changed == {}          # the second copy copies the same values
    run_tb(dut, tb, "regs_bram_copy")


def test_bram_commit_is_ignored_under_lock_during_an_access_and_during_a_copy():
    dut = RegisterFile(**BRAM)
    kp = REGMAP["pi_q_kp"]

    async def tb(ctx):
        await ctx.tick().repeat(dut.reset_clocks)
        await access(ctx, dut, kp.addr, we=1, data=0x0123, lock=1)
        # Under lock: nothing starts (the next access is taken at once).
        ctx.set(dut.commit, 1)
        await ctx.tick()
        ctx.set(dut.commit, 0)
        assert (await access(ctx, dut, kp.addr, lock=1))[0] == 0x0123
        await ctx.tick().repeat(dut.commit_clocks)
        assert ctx.get(dut.pi_q_kp) == 0
        # In an unlocked access's second clock (t + 1): ignored, the access is not delayed.
        ctx.set(dut.bus.lock, 0)
        ctx.set(dut.bus.addr, kp.addr)
        ctx.set(dut.bus.stb, 1)
        await ctx.tick()
        ctx.set(dut.commit, 1)
        await ctx.tick()
        ctx.set(dut.commit, 0)
        assert ctx.get(dut.bus.ack) == 1
        await ctx.tick()
        ctx.set(dut.bus.stb, 0)
        await ctx.tick().repeat(dut.commit_clocks)
        assert ctx.get(dut.pi_q_kp) == 0
        # Taken in the ack clock; a second commit during the copy does not restart it.
        ctx.set(dut.commit, 1)
        await ctx.tick()
        await ctx.tick().repeat(dut.commit_clocks - 2)
        ctx.set(dut.commit, 0)
        assert ctx.get(dut.pi_q_kp) == 0x0123
        r_data, _, clocks = await access_waiting(ctx, dut, kp.addr)
        assert (r_data, clocks) == (0x0123, dut.latency)
    run_tb(dut, tb, "regs_bram_ignored")


def test_bram_reset_during_a_copy_restores_every_reset_value():
    bench = verify_regs.Bench(**BRAM)
    dut = bench.dut
    f = bench.stim_fields
    kp = REGMAP["pi_q_kp"]

    async def tb(ctx):
        await ctx.tick().repeat(dut.reset_clocks)
        for data in (0x0123, 0x0456):
            ctx.set(bench.stim, bench.pack(f, dict(addr=kp.addr, we=1, w_data=data, stb=1)))
            await ctx.tick().repeat(3)
            ctx.set(bench.stim, bench.pack(f, dict(commit=1)))
            await ctx.tick()
            ctx.set(bench.stim, 0)
            await ctx.tick().repeat(dut.commit_clocks)
            assert ctx.get(dut.pi_q_kp) == data
        ctx.set(bench.stim, bench.pack(f, dict(addr=kp.addr, we=1, w_data=0x789, stb=1)))
        await ctx.tick().repeat(3)
        ctx.set(bench.stim, bench.pack(f, dict(commit=1)))
        await ctx.tick().repeat(10)                    # in the middle of the copy
        ctx.set(bench.stim, bench.pack(f, dict(rst=1)))
        await ctx.tick()
        ctx.set(bench.stim, 0)
        assert ctx.get(dut.pi_q_kp) == kp.reset
        ctx.set(bench.stim, bench.pack(f, dict(addr=kp.addr, stb=1)))
        clocks = 0
        while not ctx.get(dut.bus.ack):
            await ctx.tick()
            clocks += 1
        assert clocks == dut.reset_clocks + dut.latency
        assert ctx.get(dut.bus.r_data) == kp.reset     # the walk rewrote the staging RAM
        assert ctx.get(dut.pi_q_kp) == kp.reset
    simulate(bench, [tb], name="regs_bram_reset_copy")


@pytest.mark.parametrize("staging", ["ff", "bram"])
def test_random_bus_traffic_with_resets_matches_the_model(staging):
    kw = BRAM if staging == "bram" else {}
    fig = run(2500, seed=7, rst_p=0.002, **kw)
    assert fig["mismatches"] == 0 and fig["stuck"] == 0, fig["first_mismatch"]
    for key in ("reads", "writes", "bad_address", "read_only", "window_reads",
                "commits_applied", "commits_locked", "strobe_pulses", "resets"):
        assert fig[key] > 0, key
    if staging == "bram":
        assert fig["copies"] > 10 and fig["held"] > 100


@pytest.mark.parametrize("kinds", [("slot", "ro"), ("slot", "ro", "imm16"),
                                   ("slot", "imm8", "ro", "const")])
def test_random_bram_traffic_on_small_maps_matches_the_model(kinds):
    """Block-RAM staging on maps of one or two slots (the word select's code and the format
    table at their smallest: one slot, one format), with a read-only word (the bench needs
    one) and a const word."""
    from foc_servo.hdl.fixed import Q, UQ
    make = {"slot": lambda: Register("a", 0x10, UQ(8, 0), Access.RW, 3, "a", shadow="g"),
            "ro": lambda: Register("b", 0x400, Q(16, 0), Access.RO, 0, "b"),
            "imm16": lambda: Register("c", 0x11, Q(16, 0), Access.RW, -3, "c"),
            "imm8": lambda: Register("c", 0x11, UQ(8, 0), Access.RW, 5, "c"),
            "const": lambda: Register("d", 0x12, UQ(12, 0), Access.CONST, 0x5A5, "d")}
    fig = run(600, seed=5, regmap=RegMap([make[k]() for k in kinds]), staging="bram",
              rst_p=0.002)
    assert fig["mismatches"] == 0 and fig["stuck"] == 0, fig["first_mismatch"]
    assert fig["writes"] > 100 and fig["bad_address"] > 50


def test_random_bram_comparison_detects_a_wrong_copy_order_or_a_copy_under_lock(monkeypatch):
    from foc_servo.sim.models import regs as model_regs
    slots = model_regs.staging_slots
    monkeypatch.setattr(model_regs, "staging_slots",
                        lambda regmap, copy_last=(): list(reversed(slots(regmap, copy_last))))
    fig = run(400, seed=1, **BRAM)
    assert fig["mismatches"] > 0 and fig["stuck"] == 0
    monkeypatch.undo()
    step = RegisterFileModel.step
    monkeypatch.setattr(RegisterFileModel, "step",
                        lambda self, **kw: step(self, **{**kw, "lock": 0}))   # copies under lock
    fig = run(400, seed=1, **BRAM)
    assert fig["mismatches"] > 0


# --- staging="bram" with export ------------------------------------------------------------

#: The loop engine's configuration registers (hdl/top.py exports them on the iCEBreaker) and a
#: two-word register (``mt_k``) for the word index.
EXPORT = ("pi_d_kp", "pi_d_kx", "pi_d_lim_lo", "pi_d_lim_hi", "pi_q_kp", "pi_q_kx",
          "pi_q_lim_lo", "pi_q_lim_hi", "clarke_gain_a", "clarke_offset_a", "clarke_gain_b",
          "clarke_offset_b", "decouple_l", "decouple_psi", "mt_k")


def test_export_ports_words_and_init():
    dut = RegisterFile(**BRAM, export=EXPORT)
    words = export_words(REGMAP, EXPORT)
    assert [(r.name, k) for _, r, k in words] == [(n, 0) for n in EXPORT] + [("mt_k", 1)]
    assert dut.exported == EXPORT and dut.export_words == words
    assert dut.export_init == export_init(REGMAP, EXPORT) == [
        r.read_word(r.bits(r.reset), k) for _, r, k in words]
    assert dut.export_init[EXPORT.index("pi_d_lim_lo")] == (-28378) & 0xFFFFFFFF   # sign-ext.
    members = set(dut.signature.members)
    assert members == (set(RegisterFile(**BRAM).signature.members) - set(EXPORT)) | {
        "export", "export_walk"}
    sig = dut.signature.members["export"].signature
    assert isinstance(sig, WordWriteSignature) and (sig.depth, sig.width) == (len(EXPORT) + 1, 32)
    # Same slots, timing attributes and host reads as without export.
    plain = RegisterFile(**BRAM)
    assert (dut.slots, dut.commit_clocks, dut.reset_clocks) == (
        plain.slots, plain.commit_clocks, plain.reset_clocks)


def test_export_port_writes_each_word_in_its_copy_clock():
    """Commit in clock s: exported slot i is on the port (valid, its export index, the new
    word sign-extended) in clock s + 1 + i and in no other clock; after a reset the walk puts
    the reset values on the port in clocks 2 + i; ``export_walk`` is high up to the walk's last
    word."""
    export = ("pi_q_lim_lo", "clarke_gain_a")       # order unlike the slots'
    dut = RegisterFile(**BRAM, export=export)
    slots = staging_slots(REGMAP, BRAM["copy_last"])
    slot = {r.name: i for i, (_, r, _) in enumerate(slots)}
    value = {"pi_q_lim_lo": -1234, "clarke_gain_a": 0x1_2345}

    async def tb(ctx):
        seen, walk = [], []
        for c in range(dut.reset_clocks + 3):       # the power-up walk
            if ctx.get(dut.export.valid):
                seen.append((c, ctx.get(dut.export.index), ctx.get(dut.export.data)))
            walk.append(ctx.get(dut.export_walk))
            await ctx.tick()
        # the walk's last word (slot reset_clocks − 1) is loaded in clock reset_clocks
        assert walk == [1] * (dut.reset_clocks + 1) + [0, 0]
        # (power-up: the walk starts in clock 0 rather than 1 after a reset clock)
        assert seen == [(1 + slot[n], j, export_init(REGMAP, export)[j])
                        for j, n in sorted(enumerate(export), key=lambda x: slot[x[1]])]
        for name, v in value.items():
            await access(ctx, dut, REGMAP[name].addr, we=1, data=v, lock=1)
        ctx.set(dut.bus.lock, 0)
        ctx.set(dut.commit, 1)                      # clock s = 0
        seen = []
        for c in range(dut.commit_clocks + 2):
            if ctx.get(dut.export.valid):
                seen.append((c, ctx.get(dut.export.index), ctx.get(dut.export.data)))
            await ctx.tick()
            ctx.set(dut.commit, 0)
        want = [(1 + slot[n], j, value[n] & 0xFFFFFFFF) for j, n in enumerate(export)]
        assert seen == sorted(want)
    run_tb(dut, tb, "regs_bram_export")


def test_random_traffic_with_export_matches_the_model():
    fig = run(2500, seed=7, rst_p=0.002, **BRAM, export=EXPORT)
    assert fig["mismatches"] == 0 and fig["stuck"] == 0, fig["first_mismatch"]
    assert fig["export_writes"] > 100 and fig["resets"] > 0 and fig["copies"] > 10


def test_export_ram_holds_what_the_flip_flops_hold():
    """A RAM written from the port equals, clock by clock, the flip-flops of the same register
    file built without export (random frames, commits, resets); a consumer one clock late
    differs."""
    fig = run_export(2000, seed=5, export=EXPORT, copy_last=BRAM["copy_last"])
    assert fig["mismatches"] == 0, fig["first_mismatch"]
    assert fig["changes"] > 10 and fig["commits"] > 20 and fig["resets"] > 3
    late = run_export(800, seed=5, export=EXPORT, copy_last=BRAM["copy_last"], late=True)
    assert late["mismatches"] > 0


MIRROR = ("prot_oc_limit", "prot_ov_limit", "prot_uv_limit", "prot_os_limit")


def test_mirror_ports_words_and_init():
    """``mirror``: no Out member for the mirrored registers, a ``mirror`` port of their words
    (and their reset values as a RAM's init); the slots and timing as without it."""
    dut = RegisterFile(**BRAM, mirror=MIRROR)
    assert dut.mirrored == MIRROR
    assert [(r.name, k) for _, r, k in dut.mirror_words] == [(n, 0) for n in MIRROR]
    assert dut.mirror_init == export_init(REGMAP, MIRROR)
    assert dut.mirror_init[1:3] == [0x7FFF, 0xFFFF8000]             # sign-extended
    members = set(dut.signature.members)
    assert members == (set(RegisterFile(**BRAM).signature.members) - set(MIRROR)) | {"mirror"}
    sig = dut.signature.members["mirror"].signature
    assert isinstance(sig, WordWriteSignature) and (sig.depth, sig.width) == (len(MIRROR), 32)
    plain = RegisterFile(**BRAM)
    assert (dut.slots, dut.commit_clocks, dut.reset_clocks) == (
        plain.slots, plain.commit_clocks, plain.reset_clocks)
    with pytest.raises(ValueError, match=r"^RegisterFile derived must not name a mirrored "
                                         r"register, not 'prot_oc_limit'$"):
        RegisterFile(**BRAM, mirror=MIRROR,
                     derived={"prot_oc_limit": Derived(16, lambda v: v, lambda b: b)})


def test_mirror_port_writes_each_word_a_clock_after_its_write():
    """A host write to a mirrored register (taken in t) is on the ``mirror`` port in t + 1
    (valid, its index, the word sign-extended) and in no other clock; reads return it."""
    dut = RegisterFile(**BRAM, mirror=MIRROR)

    async def tb(ctx):
        for _ in range(dut.reset_clocks + 2):       # the power-up walk
            await ctx.tick()
        seen = []
        ctx.set(dut.bus.addr, REGMAP["prot_uv_limit"].addr)
        ctx.set(dut.bus.we, 1)
        ctx.set(dut.bus.w_data, (-1234) & 0xFFFFFFFF)
        ctx.set(dut.bus.stb, 1)                     # taken in clock 0
        for c in range(5):
            if ctx.get(dut.mirror.valid):
                seen.append((c, ctx.get(dut.mirror.index), ctx.get(dut.mirror.data)))
            await ctx.tick()
            if c == 2:
                ctx.set(dut.bus.stb, 0)
        assert seen == [(1, MIRROR.index("prot_uv_limit"), (-1234) & 0xFFFFFFFF)]
        r_data, status = await access(ctx, dut, REGMAP["prot_uv_limit"].addr)
        assert (r_data, status) == ((-1234) & 0xFFFFFFFF, Status.OK)
    run_tb(dut, tb, "regs_bram_mirror")


def test_mirror_ram_holds_what_the_flip_flops_held_a_clock_before():
    """A RAM written from the ``mirror`` port equals, clock by clock, the flip-flops of the
    same register file built without it one clock before (random frames, commits, resets;
    after a reset until the walk rewrote the word: excused); a consumer a clock later still
    differs."""
    fig = run_export(2000, seed=5, export=MIRROR, copy_last=BRAM["copy_last"], mirror=True)
    assert fig["mismatches"] == 0, fig["first_mismatch"]
    assert fig["changes"] > 10 and fig["resets"] > 3
    late = run_export(800, seed=5, export=MIRROR, copy_last=BRAM["copy_last"], mirror=True,
                      late=True)
    assert late["mismatches"] > 0


@pytest.mark.slow
def test_register_file_bram_100k_random_accesses():
    fig = run(100_000, seed=0, rst_p=0.0005, **BRAM)
    assert fig["mismatches"] == 0, fig["first_mismatch"]


@pytest.mark.slow
def test_register_file_100k_random_accesses():
    fig = run(100_000, seed=0)
    assert fig["mismatches"] == 0, fig["first_mismatch"]


# --- staging="bram" with derived active values ---------------------------------------------

def _minus_one():
    return Derived(unsigned(8), lambda v: Mux(v == 0, 0, v - 1), lambda x: max(x, 1) - 1)


#: A shadowed register (speed_div, copied), immediate ones (scope_decim, its operand 16 bits;
#: scope_chan0, narrowed to 4 bits; prot_ov_limit), and a signed shadowed one (i_d_ref, an
#: arithmetic shift: the value sees the raw value signed, the const its bits).
DERIVED = {
    "speed_div": _minus_one(),
    "scope_decim": Derived(unsigned(16), lambda v: Mux(v == 0, 0, v - 1),
                           lambda x: max(x, 1) - 1),
    "scope_chan0": Derived(unsigned(4), lambda v: Mux(v >= 14, 14, v[:4]),
                           lambda x: min(x, 14)),
    "prot_ov_limit": Derived(unsigned(3), lambda v: v[13:], lambda x: x >> 13),
    "i_d_ref": Derived(signed(14), lambda v: v >> 2,
                       lambda x: ((x - (1 << 16) if x >> 15 else x) >> 2) & 0x3FFF),
}


def test_random_traffic_with_derived_matches_the_model():
    """Derived active values (shadowed, immediate, signed, beside export) load in the clocks
    of the raw ones, with the function applied; reads return the raw values. A model whose
    function differs from the gateware's is caught."""
    fig = run(2500, seed=11, rst_p=0.002, **BRAM, export=EXPORT, derived=DERIVED)
    assert fig["mismatches"] == 0 and fig["stuck"] == 0, fig["first_mismatch"]
    assert fig["copies"] > 10 and fig["writes"] > 500 and fig["resets"] > 0
    fig = run(1500, seed=11, **BRAM, derived={**DERIVED, "speed_div": Derived(
        unsigned(8), lambda v: Mux(v == 0, 0, v - 1), lambda x: max(x, 2) - 1)})
    assert fig["mismatches"] > 0


def test_derived_members_and_errors():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UnusedElaboratable)
        dut = RegisterFile(REGMAP, **BRAM, derived=DERIVED)
        members = dut.signature.members
        assert members["scope_chan0"].shape == unsigned(4)
        assert members["speed_div"].init == REGMAP["speed_div"].reset - 1
        assert members["i_d_ref"].shape == signed(14)
        assert set(dut.derived) == set(DERIVED)
        for kw, exc, msg in (
                (dict(derived={"speed_div": 1}), TypeError,
                 r"^RegisterFile derived must be a mapping of register names to Derived, "
                 r"not \{'speed_div': 1\}$"),
                (dict(derived=[("speed_div", _minus_one())]), TypeError,
                 r"^RegisterFile derived must be a mapping of register names to Derived, "),
                (dict(derived={"mode": _minus_one()}), ValueError,
                 r"^RegisterFile derived must name one-word rw registers without enum or "
                 r"fields, not exported or in changed, not 'mode'$"),
                (dict(derived={"mt_k": _minus_one()}), ValueError,
                 r"^RegisterFile derived must name .* not 'mt_k'$"),
                (dict(derived={"st_udc": _minus_one()}), ValueError,
                 r"^RegisterFile derived must name .* not 'st_udc'$"),
                (dict(derived={"nope": _minus_one()}), ValueError,
                 r"^RegisterFile derived must name .* not 'nope'$"),
                (dict(export=("u_rated",), derived={"u_rated": _minus_one()}), ValueError,
                 r"^RegisterFile derived must name .* not 'u_rated'$"),
                (dict(changed=("enc_lines",), derived={"enc_lines": _minus_one()}), ValueError,
                 r"^RegisterFile derived must name .* not 'enc_lines'$")):
            with pytest.raises(exc, match=msg):
                RegisterFile(REGMAP, **BRAM, **kw)
        with pytest.raises(ValueError, match=r"^RegisterFile derived applies only to "
                                             r"staging='bram', not staging='ff'$"):
            RegisterFile(REGMAP, derived={"speed_div": _minus_one()})
        with pytest.raises(TypeError, match=r"^Derived value and const must be callables, "):
            Derived(unsigned(8), 1, lambda x: x)
        del dut
        gc.collect()


# --- status read from a RAM (status_ram) ---------------------------------------------------------

STATUS_RAM = ("st_i_alpha", "st_i_beta", "st_i_d", "st_i_q", "st_u_d", "st_u_q", "st_u_alpha",
              "st_u_beta")


class _StatusRamBench(Elaboratable):
    """A register file reading ``STATUS_RAM`` from a RAM (a transparent read port) beside one
    reading the same values from flip-flops loaded in the same clocks (simulation only)."""

    def __init__(self, staging):
        self.ref = RegisterFile(REGMAP, staging=staging)
        self.dut = RegisterFile(REGMAP, staging=staging, status_ram=STATUS_RAM)
        self.st_we = Signal()
        self.st_addr = Signal(range(len(STATUS_RAM)))
        self.st_data = Signal(signed(16))

    def elaborate(self, platform):
        m = Module()
        m.submodules.ref = self.ref
        m.submodules.dut = self.dut
        m.submodules.mem = mem = Memory(shape=signed(16), depth=len(STATUS_RAM), init=[])
        wr = mem.write_port()
        rd = mem.read_port(transparent_for=(wr,))
        m.d.comb += [wr.en.eq(self.st_we), wr.addr.eq(self.st_addr), wr.data.eq(self.st_data),
                     rd.addr.eq(self.dut.status_rd.addr), rd.en.eq(self.dut.status_rd.en),
                     self.dut.status_rd.data.eq(rd.data)]
        for j, name in enumerate(STATUS_RAM):
            held = Signal(signed(16), name=f"held_{name}")
            with m.If(self.st_we & (self.st_addr == j)):
                m.d.sync += held.eq(self.st_data)
            m.d.comb += getattr(self.ref, name).eq(held)
        return m


@pytest.mark.parametrize("staging", ["ff", "bram"])
def test_status_ram_reads_equal_status_inputs_clock_by_clock(staging):
    """``status_ram``: random status writes in random clocks (also in an access's clock and the
    one after), random reads of every word: the bus (ack, status, r_data sign-extended) is the
    same in every clock as a register file's whose status inputs are flip-flops loaded in those
    clocks; also for writes (READ_ONLY, r_data 0) and for addresses outside the map whose word
    index is a status word's (BAD_ADDRESS, r_data 0)."""
    import numpy as np
    rng = np.random.default_rng(11)
    bench = _StatusRamBench(staging)
    ref, dut = bench.ref, bench.dut
    st_addrs = [REGMAP[n].addr for n in STATUS_RAM]
    others = [a for a, r, k in REGMAP.words() if r.name not in STATUS_RAM]
    fig = {"reads": 0, "status_reads": 0, "negative": 0, "status_writes": 0, "aliases": 0,
           "bad": None}
    block_bits, picked = word_index(REGMAP)
    used = {a >> block_bits for a, _, _ in REGMAP.words()} | {REGMAP.windows[0].addr >> block_bits}
    # Addresses outside the map's blocks with a status word's index (same offset and picked
    # block bits, another block).
    aliases = [a ^ (1 << b) for a in st_addrs for b in range(block_bits, 16)
               if all(b != block_bits + p for p in picked) and (a ^ (1 << b)) >> block_bits
               not in used]

    async def tb(ctx):
        stb, addr, we = 0, 0, 0
        for clock in range(3000):
            ctx.set(bench.st_we, int(rng.random() < 0.5))
            ctx.set(bench.st_addr, int(rng.integers(len(STATUS_RAM))))
            ctx.set(bench.st_data, int(rng.integers(-32768, 32768)))
            if not stb and rng.random() < 0.5:
                stb = 1
                kind = rng.random()
                addr = (int(rng.choice(st_addrs)) if kind < 0.6 else
                        int(rng.choice(aliases)) if kind < 0.7 else int(rng.choice(others)))
                we = int(rng.random() < 0.2)
                fig["status_writes"] += we and addr in st_addrs
                fig["aliases"] += addr in aliases
                w_data = int(rng.integers(1 << 32))
                for rf in (ref, dut):
                    ctx.set(rf.bus.addr, addr)
                    ctx.set(rf.bus.we, we)
                    ctx.set(rf.bus.w_data, w_data)
            for rf in (ref, dut):
                ctx.set(rf.bus.stb, stb)
            got = [(ctx.get(rf.bus.ack), ctx.get(rf.bus.status), ctx.get(rf.bus.r_data))
                   for rf in (ref, dut)]
            if got[0] != got[1] and fig["bad"] is None:
                fig["bad"] = (clock, hex(addr), got)
            if got[0][0]:
                fig["reads"] += 1
                if addr in st_addrs and not we:
                    fig["status_reads"] += 1
                    fig["negative"] += got[0][2] >> 31
                stb = 0
            await ctx.tick()

    simulate(bench, [tb], name=f"regs_status_ram_{staging}")
    assert fig["bad"] is None, fig["bad"]
    assert fig["status_reads"] > 300 and fig["reads"] > fig["status_reads"] + 100
    assert fig["negative"] > 50
    assert fig["status_writes"] > 50 and fig["aliases"] > 50


def test_status_ram_members_and_errors():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UnusedElaboratable)
        dut = RegisterFile(REGMAP, status_ram=STATUS_RAM)
        members = dut.signature.members
        assert "status_rd" in members and not set(STATUS_RAM) & set(members)
        assert dut.status_ram == STATUS_RAM
        sig = members["status_rd"].signature
        assert sig.addr_width == 3 and sig.shape == signed(16)
        for bad, exc, msg in (
                (["st_i_d"], TypeError, r"^RegisterFile status_ram must be a tuple of register "
                                        r"names, not \['st_i_d'\]$"),
                (("pi_d_kp",), ValueError, r"^RegisterFile status_ram must name one-word ro "
                                           r"registers, not 'pi_d_kp'$"),
                (("scope_arm",), ValueError, r"^RegisterFile status_ram must name one-word "
                                             r"ro registers, not 'scope_arm'$"),
                (("st_i_d", "st_i_d"), ValueError, r"^RegisterFile status_ram must not repeat "),
                (("st_i_d", "st_mode"), ValueError, r"^RegisterFile status_ram must name "
                                                    r"registers of one shape, ")):
            with pytest.raises(exc, match=msg):
                RegisterFile(REGMAP, status_ram=bad)
        del dut
        gc.collect()


# --- change strobes (changed) ------------------------------------------------------------------

CHANGED = ("enc_lines", "enc_pole_pairs", "enc_z_offset")


@pytest.mark.parametrize("kwargs, msg", [
    ({"changed": ("prot_oc_limit",)}, r"^RegisterFile changed must name unexported one-word "
                                      r"shadowed rw registers, not 'prot_oc_limit'$"),
    ({"changed": ("st_mode",)}, r"^RegisterFile changed must name unexported one-word "
                                r"shadowed rw registers, not 'st_mode'$"),
    ({**BRAM, "export": ("pi_d_kp",), "changed": ("pi_d_kp",)},
     r"^RegisterFile changed must name unexported one-word shadowed rw registers, "
     r"not 'pi_d_kp'$"),
    ({"changed": ("enc_lines", "enc_lines")},
     r"^RegisterFile changed must not repeat a name, not \('enc_lines', 'enc_lines'\)$"),
])
def test_changed_validation(kwargs, msg):
    with pytest.raises(ValueError, match=msg):
        RegisterFile(**kwargs)
    with pytest.raises(TypeError, match=r"^RegisterFile changed must be a tuple of register "
                                        r"names, not 'enc_lines'$"):
        RegisterFile(changed="enc_lines")


@pytest.mark.parametrize("staging", ["ff", "bram"])
def test_changed_strobe_marks_every_change_of_the_active_value(staging):
    """``<name>_changed`` is high exactly in the clocks whose active value differs from the
    previous clock's (random frames of the named registers and a neighbour, half of them
    rewriting the active value, with and without lock; commits every 60 clocks)."""
    import random
    kw = BRAM if staging == "bram" else {}
    dut = RegisterFile(**kw, changed=CHANGED)
    assert set(dut.signature.members) == set(RegisterFile(**kw).signature.members) | {
        f"{n}_changed" for n in CHANGED}
    names = CHANGED + ("enc_hall_offset",)
    rng = random.Random(12)
    seen = {"strobes": 0, "rewrites": 0, "bad": []}
    done = []

    async def driver(ctx):
        await ctx.tick().repeat(dut.reset_clocks + 1)
        for frame in range(40):
            # (values read back as the active ones: a frame starts long after a copy)
            for name in rng.sample(names, rng.randint(1, len(names))):
                r = REGMAP[name]
                cur = r.bits(ctx.get(bits(getattr(dut, name))))
                value = cur if rng.random() < 0.5 else rng.randrange(1 << r.width)
                seen["rewrites"] += value == cur
                await access(ctx, dut, r.addr, we=1, data=value, lock=frame % 4 != 0)
            ctx.set(dut.bus.lock, 0)
            await ctx.tick().repeat(rng.randint(1, 5))
            ctx.set(dut.commit, 1)
            await ctx.tick()
            ctx.set(dut.commit, 0)
            await ctx.tick().repeat(60)
        done.append(1)

    async def checker(ctx):
        prev = {n: ctx.get(bits(getattr(dut, n))) for n in CHANGED}
        while not done:
            await ctx.tick()
            for n in CHANGED:
                v = ctx.get(bits(getattr(dut, n)))
                strobe = ctx.get(getattr(dut, f"{n}_changed"))
                seen["strobes"] += strobe
                if strobe != (v != prev[n]):
                    seen["bad"].append((n, prev[n], v, strobe))
                prev[n] = v

    simulate(dut, [driver, checker], name=f"regs_changed_{staging}")
    assert not seen["bad"], seen["bad"][:3]
    assert seen["strobes"] > 20 and seen["rewrites"] > 10
