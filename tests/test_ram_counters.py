# amaranth: UnusedElaboratable=no
# Ref: docs/AREA.md §7.59 (the host link's reply counters in the register file's staging RAM)
"""``RegisterFile(counters=...)`` (counters in the staging RAM, counted from strobes) and
``LinkCore(strobed=...)`` (the link's count strobes): reads against flip-flop counters, and the
link with its register file clock for clock against the flip-flop counters' pair."""
import random

import pytest
from amaranth.hdl import Elaboratable, Module, ResetInserter, Signal
from amaranth.lib import wiring

from foc_servo.hdl.bus import Status
from foc_servo.hdl.hostlink import COUNTERS, REPLY_COUNTERS, HostLink, LinkCore
from foc_servo.hdl.regmap import REGMAP
from foc_servo.hdl.regs import RegisterFile
from foc_servo.hdl.top import regmap_address_map
from foc_servo.host.protocol import Command, ReplyStatus, encode_request, frame
from foc_servo.sim.harness import simulate
from foc_servo.sim.verify import link as verify

NAMES = tuple(f"st_link_{n}" for n in REPLY_COUNTERS)
#: The counters' strobes and the commits in the random test come at least this many clocks
#: apart (the documented bound: a count strobed while the same counter is pending is lost).
GAP = RegisterFile(REGMAP, staging="bram", counters=NAMES).count_interval


class _CounterBench(Elaboratable):
    def __init__(self):
        self.rst = Signal()
        self.dut = RegisterFile(REGMAP, staging="bram", counters=NAMES)

    def elaborate(self, platform):
        m = Module()
        m.submodules.dut = ResetInserter(self.rst)(self.dut)
        return m


def test_ram_counters_read_every_strobe_up_to_the_access_clock():
    """Random count strobes (each counter at least GAP clocks apart, often in an access's
    clocks), random reads of the counters and of other words, writes to the counters (read
    only), commits (copies, at least GAP clocks apart) and domain resets: every read of a counter returns the strobes of
    the clocks from the last reset (exclusive) up to its access clock ``ack − 2`` (inclusive),
    modulo 2**16, as a flip-flop counter sampled in ``t + 1`` does; other reads and the
    statuses are unchanged; an access is held off only while a count is pending."""
    rng = random.Random(59)
    bench = _CounterBench()
    dut = bench.dut
    addrs = [REGMAP[n].addr for n in NAMES]
    others = [a for a, r, k in REGMAP.words() if r.name not in NAMES]
    fig = {"reads": 0, "while_offered": 0, "next_clock": 0, "held": 0, "resets": 0, "bad": []}

    async def tb(ctx):
        strobes = []                        # per clock: the tuple of strobes
        last = [-GAP] * len(NAMES)
        last_commit = -GAP
        start = 0                           # first clock after the last reset
        stb, taken, addr, we = 0, None, 0, 0
        await ctx.tick().repeat(dut.reset_clocks)
        strobes += [(0,) * len(NAMES)] * dut.reset_clocks
        for clock in range(dut.reset_clocks, 40_000):
            s = tuple(int(clock - last[j] >= GAP and rng.random() < 0.08)
                      for j in range(len(NAMES)))
            for j, v in enumerate(s):
                ctx.set(getattr(dut, f"{NAMES[j]}_inc"), v)
                if v:
                    last[j] = clock
            strobes.append(s)
            commit = int(clock - last_commit >= GAP and rng.random() < 0.05)
            ctx.set(dut.commit, commit)
            if commit:
                last_commit = clock
            rst = int(rng.random() < 0.0015)
            ctx.set(bench.rst, rst)
            if not stb and not rst and rng.random() < 0.5:
                stb = 1
                addr = rng.choice(addrs) if rng.random() < 0.7 else rng.choice(others)
                we = int(rng.random() < 0.15)
                ctx.set(dut.bus.addr, addr)
                ctx.set(dut.bus.we, we)
                ctx.set(dut.bus.w_data, rng.getrandbits(32))
                taken = clock
            ctx.set(dut.bus.stb, stb)
            if stb and ctx.get(dut.bus.ack):
                t = clock - 2
                fig["held"] += t > taken
                if addr in addrs and not we:
                    j = addrs.index(addr)
                    want = sum(x[j] for x in strobes[start:t + 1]) % (1 << 16)
                    got = ctx.get(dut.bus.r_data)
                    fig["reads"] += 1
                    # boundary cases: a strobe of the counter while the read was offered (it
                    # is held off), one in t + 1 (not counted by this read)
                    fig["while_offered"] += any(x[j] for x in strobes[taken:t + 1])
                    fig["next_clock"] += strobes[t + 1][j]
                    if (got, ctx.get(dut.bus.status)) != (want, Status.OK):
                        fig["bad"].append((clock, hex(addr), got, want))
                elif addr in addrs and ctx.get(dut.bus.status) != Status.READ_ONLY:
                    fig["bad"].append((clock, hex(addr), "write not read-only"))
                stb = 0
                ctx.set(dut.bus.stb, 0)
            if rst:
                fig["resets"] += 1
                stb = 0
                ctx.set(dut.bus.stb, 0)
                start = clock + 1
            await ctx.tick()
        ctx.set(bench.rst, 0)

    simulate(bench, [tb], name="regs_ram_counters")
    assert fig["bad"] == [], fig["bad"][:5]
    assert fig["reads"] > 3000 and fig["held"] > 300
    assert fig["while_offered"] > 20 and fig["next_clock"] > 20
    assert fig["resets"] >= 20


def test_ram_counter_wraps_modulo_its_width():
    """One counter strobed every third clock (it alone: never pending twice), read after
    2**16 − 1, 2**16 and 2**16 + 3 strobes: 65535, 0, 3."""
    dut = RegisterFile(REGMAP, staging="bram", counters=NAMES)
    got = []

    async def tb(ctx):
        await ctx.tick().repeat(dut.reset_clocks)
        inc = getattr(dut, f"{NAMES[1]}_inc")
        for strobes in ((1 << 16) - 1, 1, 3):
            for _ in range(strobes):
                ctx.set(inc, 1)
                await ctx.tick()
                ctx.set(inc, 0)
                await ctx.tick().repeat(2)
            ctx.set(dut.bus.addr, REGMAP[NAMES[1]].addr)
            ctx.set(dut.bus.stb, 1)
            while not ctx.get(dut.bus.ack):
                await ctx.tick()
            got.append(ctx.get(dut.bus.r_data))
            await ctx.tick()
            ctx.set(dut.bus.stb, 0)

    simulate(dut, [tb], name="regs_ram_counter_wrap")
    assert got == [(1 << 16) - 1, 0, 3]


@pytest.mark.parametrize("kwargs, msg", [
    (dict(staging="ff", counters=NAMES), r"counters applies only to staging='bram'"),
    (dict(staging="bram", counters=("st_speed",)), r"counters must name one-word unsigned ro"),
    (dict(staging="bram", counters=("i_q_ref",)), r"counters must name one-word unsigned ro"),
    (dict(staging="bram", counters=NAMES[:1] * 2), r"counters must not repeat a name"),
    (dict(staging="bram", counters=("st_link_frames_ok", "st_position")),
     r"counters must name registers of one width"),
])
def test_ram_counters_validation(kwargs, msg):
    with pytest.raises(ValueError, match=msg):
        RegisterFile(REGMAP, **kwargs)


def test_ram_counters_members_and_ram_size():
    dut = RegisterFile(REGMAP, staging="bram", counters=NAMES)
    ref = RegisterFile(REGMAP, staging="bram")
    names = set(dut.signature.members)
    assert all(f"{n}_inc" in names and n not in names for n in NAMES)
    assert dut.reset_clocks == ref.reset_clocks + len(NAMES)
    assert dut.commit_clocks == ref.commit_clocks and dut.slots == ref.slots
    for bad in (("lost",), ("frames_ok", "frames_ok"), ["frames_ok"]):
        with pytest.raises(ValueError, match=r"strobed must be a tuple of distinct names"):
            LinkCore(strobed=bad)
    for link in (LinkCore(strobed=REPLY_COUNTERS), HostLink(strobed=REPLY_COUNTERS)):
        members = set(link.signature.members)
        assert {f"{n}_strobe" for n in REPLY_COUNTERS} <= members and "dropped" in members
        assert not members & set(REPLY_COUNTERS)
    members = set(HostLink(strobed=REPLY_COUNTERS[:1]).signature.members)
    assert "frames_ok_strobe" in members and "crc_errors" in members


#: The pair test's output takes a byte every this many clocks (8 wire bytes ≥ GAP clocks).
OUT_EVERY = -(-GAP // 8)


class _LinkPair(Elaboratable):
    """The link and the register file twice: ``a`` with the link's flip-flop counters on the
    register file's status inputs, ``b`` with the counters ``strobed`` in the staging RAM."""

    def __init__(self, strobed):
        amap = regmap_address_map(REGMAP)
        self.strobed = strobed
        self.a_link = LinkCore(max_words=16, address_map=amap)
        self.a_regs = RegisterFile(REGMAP, staging="bram")
        self.b_link = LinkCore(max_words=16, address_map=amap, strobed=strobed)
        self.b_regs = RegisterFile(REGMAP, staging="bram",
                                   counters=tuple(f"st_link_{n}" for n in strobed))
        self.commit = Signal()

    def elaborate(self, platform):
        m = Module()
        m.submodules.a_link, m.submodules.a_regs = self.a_link, self.a_regs
        m.submodules.b_link, m.submodules.b_regs = self.b_link, self.b_regs
        wiring.connect(m, self.a_link.bus, self.a_regs.bus)
        wiring.connect(m, self.b_link.bus, self.b_regs.bus)
        m.d.comb += [self.a_regs.commit.eq(self.commit), self.b_regs.commit.eq(self.commit)]
        for name in COUNTERS:
            m.d.comb += getattr(self.a_regs, f"st_link_{name}").eq(getattr(self.a_link, name))
            if name in self.strobed:
                m.d.comb += getattr(self.b_regs, f"st_link_{name}_inc").eq(
                    getattr(self.b_link, f"{name}_strobe"))
            else:
                m.d.comb += getattr(self.b_regs, f"st_link_{name}").eq(
                    getattr(self.b_link, name))
        return m


@pytest.mark.parametrize("strobed", [REPLY_COUNTERS, COUNTERS])
def test_link_with_ram_counters_is_clock_for_clock_the_flip_flop_pair(strobed):
    """Random frames (reads of the link's counters among other words, writes, malformed frames
    of every kind, pings), bytes one per clock or with gaps, bytes arriving while the link is
    busy (lost: ``dropped``), commits: both links' wire output, ``i.ready`` and bus are equal in
    every clock, and the counters read back are not all 0. As in the Top, the output takes a
    byte at most every ``OUT_EVERY`` clocks (the UART: ≥ 80 clocks a byte) and commits come at
    least ``count_interval`` clocks apart (the Top: one per PWM period), so a reply's counts
    are in the RAM before the next frame's first access (a reply is at least 8 wire bytes).
    With ``dropped`` in the RAM too (``COUNTERS``), a byte lost while the link is busy with
    its accesses holds the next access off for two clocks or so: then the wire bytes, the bus
    accesses and every read's data are the same in the same order, only later (bytes are
    offered only while both links are ready, lost ones while both are busy)."""
    rng = random.Random(7)
    pair = _LinkPair(strobed)
    exact = "dropped" not in strobed
    seq = ([], [])                          # per side: wire bytes out, (addr, r_data) at acks
    links = (pair.a_link, pair.b_link)
    counter_addr = REGMAP["st_link_frames_ok"].addr
    fig = {"clocks": 0, "out": 0, "lost": 0, "bad": None, "nonzero": 0}
    wire = bytearray()
    for k in range(120):
        x = rng.random()
        if x < 0.35:
            wire += frame(encode_request(Command.READ, k & 0xFF, counter_addr, 5))
        elif x < 0.5:
            wire += frame(encode_request(Command.WRITE, k & 0xFF, REGMAP["i_q_ref"].addr, 1,
                                         [rng.getrandbits(16)]))
        elif x < 0.6:
            wire += frame(encode_request(Command.WRITE, k & 0xFF, counter_addr, 1, [5]))
        elif x < 0.85:
            wire += verify.malformed_frame(rng, rng.choice(verify.KINDS), 16)
        else:
            wire += frame(encode_request(Command.PING, k & 0xFF))

    async def tb(ctx):
        await ctx.tick().repeat(pair.a_regs.reset_clocks + 8)
        pos, clock, last_commit = 0, 0, -GAP
        while pos < len(wire) or fig["clocks"] < 400:
            clock += 1
            for link in links:
                ctx.set(link.o.ready, clock % OUT_EVERY == 0)
            # mostly only while the link is ready; now and then a byte while it is busy
            ready = ctx.get(pair.a_link.i.ready)
            if not exact and ready != ctx.get(pair.b_link.i.ready):
                send = False
            else:
                send = pos < len(wire) and rng.random() < (0.8 if ready else 0.003)
            for link in links:
                ctx.set(link.i.valid, send)
                ctx.set(link.i.payload, wire[pos] if send else 0)
                # (a byte offered while busy is lost, as HostLink's rx_lost says)
                ctx.set(link.rx_lost, send and not ready)
            fig["lost"] += send and not ready
            commit = clock - last_commit >= GAP and rng.random() < 0.02
            ctx.set(pair.commit, commit)
            if commit:
                last_commit = clock
            if send:
                pos += 1
            else:
                fig["clocks"] += pos >= len(wire)
            got = [(ctx.get(link.i.ready), ctx.get(link.o.valid), ctx.get(link.o.payload),
                    ctx.get(link.bus.stb), ctx.get(link.bus.addr), ctx.get(link.bus.ack),
                    ctx.get(link.bus.r_data) if ctx.get(link.bus.ack) else 0)
                   for link in links]
            for side, g in zip(seq, got):
                if g[1] and clock % OUT_EVERY == 0:
                    side.append(("out", g[2]))
                if g[5]:
                    side.append(("ack", g[4], g[6]))
            fig["delayed"] = fig.get("delayed", 0) + (got[0][5] != got[1][5])
            if exact and got[0] != got[1] and fig["bad"] is None:
                fig["bad"] = (pos, got)
            if got[0][5] and got[0][4] in range(counter_addr, counter_addr + 5):
                fig["nonzero"] += got[0][6] != 0
            fig["out"] += got[0][1] and clock % OUT_EVERY == 0
            await ctx.tick()

    simulate(pair, [tb], name="link_ram_counters_pair")
    assert fig["bad"] is None, fig["bad"]
    assert seq[0] == seq[1]
    assert (fig["delayed"] == 0) == exact
    assert fig["out"] > 800 and fig["nonzero"] > 100 and fig["lost"] > 10


def test_top_uses_ram_counters_with_bram_staging_and_checks_their_interval():
    from foc_servo.hdl.top import Top
    top = Top(pwm_hz=100e3, baud=50e6 / 8, regs_staging="bram")
    assert top._regs.counters == (tuple(f"st_link_{n}" for n in COUNTERS)
                                  + ("st_speed_loops", "st_overruns", "st_adc_overruns",
                                     "st_current_loops"))
    assert top._link.strobed == COUNTERS
    assert Top(pwm_hz=100e3, baud=50e6 / 8)._link.strobed == ()
    with pytest.raises(ValueError, match=r"^Top: the counters in the register file's RAM "
                                         r"need the PWM period and 2 UART bytes to last at "
                                         r"least 139 clocks, not 100$"):
        Top(pwm_hz=500e3, baud=50e6 / 8, regs_staging="bram")


def test_top_bram_link_counters_read_over_the_uart():
    """The Top with ``regs_staging="bram"`` (the four reply counters in the staging RAM, wired
    from the link's strobes): a bad-CRC frame, a damaged (framing) frame, a bad-address read,
    a PING, then a read of the five ``st_link_*`` words over the UART: one count each where
    it belongs (frames_ok 1, crc_errors 1, framing_errors 1, rejected 1, dropped 0); a second
    read after it counts the first read's OK reply."""
    from foc_servo.hdl.top import Top
    from foc_servo.host.protocol import cobs_encode, crc16
    from test_top import BAUD, CLK, _Bench, _uart_host
    per_bit = round(CLK / BAUD)
    top = Top(pwm_hz=100e3, baud=BAUD, regs_staging="bram")
    bench = _Bench(top, BAUD)
    addr = REGMAP["st_link_frames_ok"].addr
    wire = bytearray()
    seen = []

    async def monitor(ctx):
        while True:
            *_, byte = await ctx.posedge(bench.host_rx.o.valid).sample(bench.host_rx.o.payload)
            wire.append(byte)

    replies, send, reply = _uart_host(bench, wire, per_bit)

    async def testbench(ctx):
        await ctx.tick().repeat(200)
        payload = encode_request(Command.READ, 1, addr, 1)
        bad_crc = (crc16(payload) ^ 0x0100).to_bytes(2, "big")
        await send(ctx, b"\x00" + cobs_encode(payload + bad_crc) + b"\x00")
        await reply(ctx, 1)
        await send(ctx, frame(encode_request(Command.PING, 2)), bad_stop=3)
        await reply(ctx, 2)
        await send(ctx, frame(encode_request(Command.READ, 3, 0x0FFF, 1)))
        await reply(ctx, 3)
        await send(ctx, frame(encode_request(Command.PING, 4)))
        await reply(ctx, 4)
        for n in (5, 6):
            await send(ctx, frame(encode_request(Command.READ, n, addr, 5)))
            seen.append(await reply(ctx, n))

    simulate(bench, [testbench], [monitor], name="top_bram_link_counters")
    assert [r.status for r in seen] == [ReplyStatus.OK] * 2
    assert list(seen[0].data) == [1, 1, 1, 1, 0]        # frames_ok, crc, framing, rejected, dropped
    assert list(seen[1].data) == [2, 1, 1, 1, 0]


def test_top_bram_own_counters_read_the_events_over_the_uart():
    """The Top with ``regs_staging="bram"`` in speed mode: ``st_current_loops``,
    ``st_speed_loops``, ``st_overruns``, ``st_adc_overruns`` (0x0418 …, counted in the staging
    RAM from the loop's ``done``, ``servo.speed_valid``, the loop's ``overrun``, the ADC's
    ``overrun``) read over the UART lie between the events counted at those signals before the
    request and at the reply; the speed loop has run."""
    from foc_servo.hdl.regmap import Mode
    from foc_servo.hdl.top import Top
    from foc_servo.host.protocol import cobs_decode, decode_reply
    from test_top import BAUD, CLK, HALL_OK, _Bench, _bitbang, _encoder_process
    per_bit = round(CLK / BAUD)
    top = Top(pwm_hz=100e3, baud=BAUD, regs_staging="bram",
              resets={"mode": Mode.SPEED.value, "prot_mask": 0})
    bench = _Bench(top, BAUD)
    events = {"done": 0, "speed": 0, "overrun": 0, "adc": 0}
    wire = bytearray()
    seen = []

    async def monitor(ctx):
        while True:
            *_, byte = await ctx.posedge(bench.host_rx.o.valid).sample(bench.host_rx.o.payload)
            wire.append(byte)

    async def count(ctx):
        async for _, _, d, s, o, a in ctx.tick().sample(top._loop.done, top._servo.speed_valid,
                                                       top._loop.overrun, top._adc.overrun):
            events["done"] += d
            events["speed"] += s
            events["overrun"] += o
            events["adc"] += a

    async def testbench(ctx):
        ctx.set(top.hall, HALL_OK)
        await ctx.tick().repeat(8000)
        for n in (1, 2):
            before = dict(events)
            for byte in frame(encode_request(Command.READ, n, 0x0418, 4)):
                for level in _bitbang(byte):
                    ctx.set(bench.inject, level)
                    await ctx.tick().repeat(per_bit)
            while len(wire.split(b"\x00")) <= n:
                await ctx.tick().repeat(20)
            r = decode_reply(cobs_decode(bytes(wire.split(b"\x00")[n - 1]))[:-2])
            seen.append((before, list(r.data), dict(events)))
            await ctx.tick().repeat(3000)

    simulate(bench, [testbench], [monitor, count, _encoder_process(top, 25)],
             name="top_bram_own_counters")
    for before, data, after in seen:
        for value, name in zip(data, ("done", "speed", "overrun", "adc")):
            assert before[name] <= value <= after[name], (name, before, data, after)
    assert seen[-1][1][1] >= 10 and seen[-1][1][1] > seen[0][1][1]
    assert seen[-1][1][0] >= 10 and seen[-1][1][0] > seen[0][1][0]
