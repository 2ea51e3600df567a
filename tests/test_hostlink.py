# amaranth: UnusedElaboratable=no
# Ref: docs/PROTOCOL.md (framing, commands, status codes, resynchronisation); hdl/bus.py
import random

import pytest
from amaranth.back import verilog
from amaranth.hdl import Module, Signal
from amaranth.lib import wiring

from foc_servo.hdl.hostlink import (HostLink, LinkCore, _below, address_decode, crc16_byte,
                                    normalize_address_map)
from foc_servo.hdl.regmap import REGMAP
from foc_servo.hdl.top import regmap_address_map
from foc_servo.hdl.uart import UartRx
from foc_servo.host.protocol import (Command, ReplyStatus, cobs_decode, cobs_encode, crc16,
                                     decode_reply, encode_request, frame)
from foc_servo.sim.harness import simulate
from foc_servo.sim.link import LinkSim, StandInModel, StandInRegisters
from foc_servo.sim.models.hostlink import LinkModel
from foc_servo.sim.verify import link as verify

MAP = StandInRegisters.address_map


def test_hostlink_parameter_validation():
    with pytest.raises(TypeError, match=r"^Host link max_words must be an integer from 1 to 255, "
                                        r"not 256$"):
        LinkCore(max_words=256)
    with pytest.raises(TypeError, match=r"^Host link max_words must be an integer from 1 to 255, "
                                        r"not True$"):
        HostLink(max_words=True)
    with pytest.raises(TypeError, match=r"^Host link counter_width must be an integer from 1 to "
                                        r"32, not 0$"):
        LinkCore(counter_width=0)
    with pytest.raises(TypeError, match=r"^Address map region must be a \(start, stop, writable\) "
                                        r"tuple of two integers and a bool, not \(0, 4, 1\)$"):
        LinkCore(address_map=[(0, 4, 1)])
    with pytest.raises(ValueError, match=r"^Address map region must satisfy 0 <= start < stop <= "
                                         r"0x10000, not \(4, 4, True\)$"):
        LinkCore(address_map=[(4, 4, True)])
    with pytest.raises(ValueError, match=r"^Address map regions \(0, 8, True\) and \(4, 12, "
                                         r"False\) overlap$"):
        LinkCore(address_map=[(4, 12, False), (0, 8, True)])
    with pytest.raises(ValueError, match=r"^HostLink baud must be at most clk_hz / 8 = "
                                         r"4.16662e\+06, not 5000000.0$"):
        HostLink(clk_hz=33.333e6, baud=5e6)
    with pytest.raises(TypeError, match=r"^LinkCore read_hold must be a bool, not 1$"):
        LinkCore(read_hold=1)
    with pytest.raises(TypeError, match=r"^HostLink read_hold must be a bool, not None$"):
        HostLink(read_hold=None)
    assert HostLink(read_hold=True).core.read_hold and not LinkCore().read_hold
    with pytest.raises(ValueError, match=r"^LinkCore read_hold and compact are exclusive \(the "
                                         r"compact form's buffer reads at j's next value\), not "
                                         r"both True$"):
        HostLink(read_hold=True, compact=True)


def test_address_map_normalisation():
    assert normalize_address_map(None) == ((0, 0x10000, True),)
    assert normalize_address_map([(8, 16, True), (0, 8, True), (16, 20, False)]) == \
        ((0, 16, True), (16, 20, False))


def _decode_mismatches(address_map, addresses):
    """Addresses whose gateware decode (exists, writable) differs from the map's regions."""
    amap = normalize_address_map(address_map)
    a, e, w = Signal(17), Signal(), Signal()
    m = Module()
    exists, writable = address_decode(a, amap)
    m.d.comb += [e.eq(exists), w.eq(writable)]

    def ref(x):
        return next(((1, int(wb)) for s0, s1, wb in amap if s0 <= x < s1), (0, 0))

    bad = []

    async def testbench(ctx):
        for x in addresses:
            ctx.set(a, x)
            if (ctx.get(e), ctx.get(w)) != ref(x):
                bad.append(x)

    simulate(m, [testbench], name="address_decode")
    return bad


def test_address_decode_of_the_register_map_exhaustive():
    """The top's map, every address 0 … 0x1FFFF (the top bit: a burst past 0xFFFF)."""
    assert _decode_mismatches(regmap_address_map(REGMAP), range(1 << 17)) == []


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_address_decode_random_maps(seed):
    """Random maps of small and large regions: every region edge ± 2 and random addresses."""
    rng = random.Random(seed)
    edges = sorted(rng.sample(range(1, 0x10000), 40))
    if seed == 3:
        edges = [0] + edges[:-1] + [0x10000]            # regions touching both ends
    amap = [(edges[k], edges[k + 1], rng.random() < 0.5) for k in range(0, len(edges) - 1, 2)]
    probe = {x + d for x in edges for d in range(-2, 3)} | {rng.randrange(1 << 17)
                                                            for _ in range(3000)}
    assert _decode_mismatches(amap, sorted(x for x in probe if 0 <= x < 1 << 17)) == []
    assert _decode_mismatches(None, [0, 0xFFFF, 0x10000, 0x1FFFF]) == []


def test_below_is_the_magnitude_comparison():
    """``_below(v, k)`` (the link's constant compares without carry chains) is ``v < k`` for
    every value of 1- to 7-bit ``v`` and every ``k`` from −1 to 2**width + 1."""
    bad = []
    for width in range(1, 8):
        v = Signal(width)
        limits = range(-1, (1 << width) + 2)
        outs = [Signal(name=f"lt{k + 1}") for k in limits]
        m = Module()
        m.d.comb += [o.eq(_below(v, k)) for o, k in zip(outs, limits)]

        async def bench(ctx, v=v, outs=outs, limits=limits, width=width):
            for x in range(1 << width):
                ctx.set(v, x)
                bad.extend((width, x, k) for o, k in zip(outs, limits)
                           if ctx.get(o) != (x < k))

        simulate(m, [bench], name="below")
    assert bad == []


def test_crc16_byte_gateware_matches_reference():
    crc, byte, out = Signal(16), Signal(8), Signal(16)
    m = Module()
    m.d.comb += out.eq(crc16_byte(crc, byte))
    rng = random.Random(3)
    vectors = [(0xFFFF, 0x31), (0, 0), (0xFFFF, 0xFF)]
    vectors += [(rng.getrandbits(16), rng.getrandbits(8)) for _ in range(200)]
    bad = []

    async def bench(ctx):
        for c, b in vectors:
            ctx.set(crc, c)
            ctx.set(byte, b)
            if ctx.get(out) != crc16(bytes([b]), c):
                bad.append((c, b))

    simulate(m, [bench], name="crc16_byte")
    assert bad == []


class _Pair:
    """Gateware (byte-level engine in LinkSim) and model, fed the same bytes."""

    def __init__(self, max_words=8):
        self.sim = LinkSim(uart=False, max_words=max_words, chunk_clocks=8)
        self.regs = StandInModel()
        self.model = LinkModel(self.regs.read, self.regs.write, max_words=max_words,
                               address_map=MAP)

    def feed(self, data):
        self.sim.send(data)
        got = self.sim.run_until_idle(max_clocks=50_000)
        want = self.model.feed(data)
        assert got == want
        assert self.sim.bus_writes == self.regs.writes
        return got


def _replies(wire):
    out = []
    for raw in wire.split(b"\x00")[:-1]:
        p = cobs_decode(raw)
        assert crc16(p) == 0
        out.append(decode_reply(p[:-2]))
    return out


def test_link_ping_empty_frames_and_exact_reply_bytes():
    pair = _Pair()
    assert pair.feed(b"\x00\x00\x00") == b""                    # empty frames: no reply
    wire = pair.feed(frame(encode_request(Command.PING, 0x5A)))
    payload = bytes([0, 0x5A, 0, 8])
    assert wire == cobs_encode(payload + crc16(payload).to_bytes(2, "big")) + b"\x00"


def test_link_max_burst_and_cobs_0xff_blocks():
    pair = _Pair(max_words=64)
    words = [0x01010101] * 64                                   # a 262-byte reply, no zeros
    (r,) = _replies(pair.feed(frame(encode_request(Command.WRITE, 1, 0x100, 64, words))))
    assert (r.status, r.info) == (ReplyStatus.OK, 0)
    (r,) = _replies(pair.feed(frame(encode_request(Command.READ, 2, 0x100, 64))))
    assert (r.status, r.info, list(r.data)) == (ReplyStatus.OK, 64, words)
    mixed = [0x00FF0001 * (k % 3) for k in range(64)]
    pair.feed(frame(encode_request(Command.WRITE, 3, 0x100, 64, mixed)))
    (r,) = _replies(pair.feed(frame(encode_request(Command.READ, 4, 0x100, 64))))
    assert list(r.data) == mixed
    (r,) = _replies(pair.feed(frame(encode_request(Command.WRITE, 5, 0x100, 65, [1] * 65))))
    assert r.status == ReplyStatus.BAD_LENGTH


def test_link_burst_across_read_only_writes_nothing():
    pair = _Pair()
    pair.feed(frame(encode_request(Command.WRITE, 1, 0x0C, 4, [1, 2, 3, 4])))
    (r,) = _replies(pair.feed(frame(encode_request(Command.WRITE, 2, 0x0E, 4, [9, 9, 9, 9]))))
    assert (r.status, r.info) == (ReplyStatus.READ_ONLY, 2)
    (r,) = _replies(pair.feed(frame(encode_request(Command.READ, 3, 0x0C, 4))))
    assert list(r.data) == [1, 2, 3, 4]
    (r,) = _replies(pair.feed(frame(encode_request(Command.READ, 4, 0x0016, 4))))
    assert (r.status, r.info, r.data) == (ReplyStatus.BAD_ADDRESS, 2, ())
    (r,) = _replies(pair.feed(frame(encode_request(Command.WRITE, 5, 0xFFFE, 3, [0, 0, 0]))))
    assert (r.status, r.info) == (ReplyStatus.BAD_ADDRESS, 0)
    assert pair.regs.writes == 4


@pytest.mark.parametrize("kind", verify.KINDS)
def test_link_malformed_frames_match_model_and_resync(kind):
    pair = _Pair()
    rng = random.Random(kind)
    for k in range(12):
        wire = pair.feed(verify.malformed_frame(rng, kind, 8)
                         + frame(encode_request(Command.PING, k + 1)))
        last = _replies(wire[wire.rfind(b"\x00", 0, len(wire) - 1) + 1:])[-1]
        assert (last.cmd, last.seq, last.status) == (Command.PING, k + 1, ReplyStatus.OK)
    assert pair.regs.writes == 0
    assert pair.sim.counters["frames_ok"] == pair.model.counters["frames_ok"] == 12
    for name in ("crc_errors", "framing_errors", "rejected"):
        assert pair.sim.counters[name] == pair.model.counters[name]


def test_link_bus_lock_and_access_latency_cycle_by_cycle():
    core = LinkCore(max_words=8, address_map=MAP)
    slave = StandInRegisters()
    m = Module()
    m.submodules.core, m.submodules.slave = core, slave
    wiring.connect(m, core=core.bus, slave=slave.bus)
    words = [11, 22, 33]
    wire = frame(encode_request(Command.WRITE, 1, 0x0100, 3, words))
    trace = []
    end = []

    async def feeder(ctx):
        ctx.set(core.o.ready, 1)
        for t, b in enumerate(wire):
            ctx.set(core.i.payload, b)
            ctx.set(core.i.valid, 1)
            await ctx.tick()
        end.append(len(wire) - 1)                               # clock of the closing 0x00
        ctx.set(core.i.valid, 0)

    async def monitor(ctx):
        for t in range(len(wire) + 60):
            _, _, lock, stb, ack, we, addr, w = await ctx.tick().sample(
                core.bus.lock, core.bus.stb, core.bus.ack, core.bus.we, core.bus.addr,
                core.bus.w_data)
            trace.append((lock, stb, ack, we, addr, w))

    simulate(m, [feeder, monitor], name="hostlink_lock")
    stbs = [t for t, x in enumerate(trace) if x[1]]
    acks = [t for t, x in enumerate(trace) if x[1] and x[2]]
    assert stbs[0] == end[0] + core.access_latency(3)
    assert [trace[t][4:] for t in acks] == [(0x100 + k, w) for k, w in enumerate(words)]
    assert all(trace[t][3] for t in acks)
    assert all(trace[t][0] for t in range(stbs[0], acks[-1] + 1))     # lock over the frame
    assert not any(x[0] for x in trace[:stbs[0] - 1]) and not trace[acks[-1] + 1][0]
    assert all(not trace[t + 1][1] for t in acks)                       # stb drops after ack


@pytest.mark.parametrize("read_hold", [False, True])
def test_link_reply_bytes_with_output_stalls_match_model(read_hold):
    """Replies with ``o.ready`` low in random clocks (the UART's back-pressure, here at the core):
    the reply's buffer read keeps the word of the byte waiting in DATA and after a 254-byte block
    (``read_hold``: the read address is not chosen by ``o.ready``, docs/AREA.md §7.62). Reads of words with
    zero bytes (short COBS blocks) and without (254-byte blocks, one ending inside the data),
    compared byte for byte with the model."""
    core = LinkCore(max_words=64, address_map=MAP, read_hold=read_hold)
    m = Module()
    m.submodules.core = core
    m.submodules.slave = slave = StandInRegisters()
    wiring.connect(m, link=core.bus, slave=slave.bus)
    regs = StandInModel()
    model = LinkModel(regs.read, regs.write, max_words=64, address_map=MAP)
    rng = random.Random(7)
    mixed = [0x00FF0001 * (k % 3) + (k << 24) for k in range(64)]
    requests = [encode_request(Command.WRITE, 1, 0x100, 64, [0x01010101] * 64),
                encode_request(Command.READ, 2, 0x100, 64),
                encode_request(Command.WRITE, 3, 0x100, 64, mixed),
                encode_request(Command.READ, 4, 0x100, 64),
                encode_request(Command.READ, 5, 0x0C, 12),
                encode_request(Command.PING, 6),
                # A zero at byte 4, then a 254-byte block ending at byte 259, the last of a
                # word: the next block starts in that word (NEXT keeps it, not word 64).
                encode_request(Command.WRITE, 7, 0x100, 64,
                               [0x01010100] + [0x01010101] * 62 + [0x02010101]),
                encode_request(Command.READ, 8, 0x100, 64),
                encode_request(Command.READ, 9, 0x0016, 4)]            # BAD_ADDRESS
    wires = [frame(r) for r in requests]
    wires += [verify.malformed_frame(random.Random(kind), kind, 64) for kind in verify.KINDS]
    want = b"".join(model.feed(w) for w in wires)
    got = bytearray()

    async def bench(ctx):
        pending = list(b"".join(wires))
        for _ in range(200_000):                # (ends when every reply's 0x00 is out)
            ready = rng.random() < 0.4
            ctx.set(core.o.ready, ready)
            if ready and ctx.get(core.o.valid):
                got.append(ctx.get(core.o.payload))
            if pending and ctx.get(core.i.ready):
                ctx.set(core.i.payload, pending.pop(0))
                ctx.set(core.i.valid, 1)
            else:
                ctx.set(core.i.valid, 0)
            await ctx.tick()
            if got.count(0) == want.count(0):     # (0x00: only the delimiters)
                break

    simulate(m, [bench], name="hostlink_stalls")
    assert bytes(got) == want
    assert len(_replies(bytes(got))) >= len(requests)


def _bitbang(byte, per_bit, stop=1):
    return [0] + [(byte >> k) & 1 for k in range(8)] + [stop]


def test_hostlink_uart_framing_error_and_bytes_while_busy():
    clk_hz, per_bit = 50e6, 8
    baud = clk_hz / per_bit
    link = HostLink(clk_hz=clk_hz, baud=baud, max_words=8, address_map=MAP)
    host_rx = UartRx(clk_hz=clk_hz, baud=baud)
    m = Module()
    m.submodules.link, m.submodules.slave, m.submodules.host_rx = link, StandInRegisters(), host_rx
    wiring.connect(m, link=link.bus, slave=m.submodules.slave.bus)
    m.d.comb += [host_rx.rx.eq(link.tx), host_rx.o.ready.eq(1)]

    ping1 = frame(encode_request(Command.PING, 1))
    bits = []
    for k, b in enumerate(ping1):                                 # byte 3 has a bad stop bit
        bits += _bitbang(b, per_bit, stop=0 if k == 3 else 1) + ([1] if k == 3 else [])
    bits += [1] * 150                                             # the BAD_CRC reply goes out
    ping2 = frame(encode_request(Command.PING, 2))
    for b in ping2 + b"\x11\x22\x00":                             # garbage while busy
        bits += _bitbang(b, per_bit)
    bits += [1] * 400
    ping3 = frame(encode_request(Command.PING, 3))
    for b in ping3:
        bits += _bitbang(b, per_bit)
    got = bytearray()

    async def driver(ctx):
        for level in bits:
            ctx.set(link.rx, level)
            await ctx.tick().repeat(per_bit)

    async def monitor(ctx):
        for _ in range(len(bits) * per_bit + 3000):
            _, _, v, p = await ctx.tick().sample(host_rx.o.valid, host_rx.o.payload)
            if v:
                got.append(p)
        counters.update({n: ctx.get(getattr(link, n)) for n in
                         ("frames_ok", "crc_errors", "framing_errors", "rejected", "dropped")})

    counters = {}
    simulate(m, [driver, monitor], clock_hz=clk_hz, name="hostlink_uart_errors")
    replies = [(r.cmd, r.seq, r.status) for r in _replies(bytes(got))]
    assert replies == [(0, 0, ReplyStatus.BAD_CRC), (Command.PING, 2, ReplyStatus.OK),
                       (Command.PING, 3, ReplyStatus.OK)]
    assert counters == {"frames_ok": 2, "crc_errors": 0, "framing_errors": 1, "rejected": 0,
                        "dropped": 1}
    # The model agrees on the damaged frame when told which byte had the framing error.
    regs = StandInModel()
    model = LinkModel(regs.read, regs.write, max_words=8, address_map=MAP)
    assert model.feed(ping1, errors=[3]) == bytes(got[:got.index(0) + 1])


def test_link_random_run_through_pty_and_uart():
    r = verify.run(rw=20, malformed=60, uart_pairs=1)
    assert r["rw"] == r["rw_engine"] == 20
    assert r["rw_mismatches"] == 0 and r["rw_engine_mismatches"] == 0
    assert r["rw_uart_mismatches"] == 0
    assert r["malformed_writes"] == 0 and r["malformed_mismatches"] == 0 and r["hangs"] == 0
    assert r["mismatches"] == 0 and r["malformed_frames"] == 60


@pytest.mark.slow
def test_link_full_run_1000_rw_10000_malformed():
    r = verify.run(rw=1000, malformed=10_000, uart_pairs=10)
    assert r["rw_mismatches"] == 0 and r["rw_engine_mismatches"] == 0
    assert r["rw_uart_mismatches"] == 0
    assert r["malformed_writes"] == 0 and r["malformed_mismatches"] == 0 and r["hangs"] == 0


def test_hostlink_converts_to_verilog():
    verilog.convert(HostLink(clk_hz=33.333e6, baud=3e6, max_words=64, address_map=MAP))


def _lockstep_traffic(rng, max_words):
    """Wire bytes for the compact-form test: requests of every kind (reads of words with and
    without zero bytes, 254-byte COBS blocks where ``max_words`` allows, bursts into read-only
    words and holes) and the malformed kinds."""
    wires = []
    n_max = max_words
    if max_words >= 62:                 # 254-byte COBS blocks (one ending inside the data)
        n = min(max_words, 64)
        wires += [frame(encode_request(Command.WRITE, 250, 0x100, n, [0x01010101] * n)),
                  frame(encode_request(Command.READ, 251, 0x100, n)),
                  frame(encode_request(Command.WRITE, 252, 0x100, n, [0x01010100]
                                       + [0x01010101] * (n - 2) + [0x02010101])),
                  frame(encode_request(Command.READ, 253, 0x100, n))]
    for seq in range(40):
        kind = rng.randrange(8)
        if kind < 6:
            n = rng.randint(1, n_max)
            lo, hi = rng.choice((StandInRegisters.RW_LOW, StandInRegisters.RW_HIGH,
                                 (0x0C, 0x18), (0xF0, 0x140), (0xFFF0, 0x10000)))
            addr = rng.randrange(lo, hi)
            if kind < 3:
                style = rng.randrange(3)
                words = [(0x01010101 if style == 0 else rng.getrandbits(32) if style == 1
                          else rng.choice((0, 0xFF, 0x100, 0x01000000, rng.getrandbits(32))))
                         for _ in range(n)]
                wires.append(frame(encode_request(Command.WRITE, seq, addr, n, words)))
            else:
                wires.append(frame(encode_request(Command.READ, seq, addr, n)))
        elif kind == 6:
            wires.append(frame(encode_request(Command.PING, seq)))
        else:
            wires.append(verify.malformed_frame(rng, rng.choice(verify.KINDS), max_words))
    # Frames too short for a header but with a valid CRC (2 … 6 decoded bytes: BAD_LENGTH),
    # each after a request whose header bytes they leave behind: the reply's cmd is 0 below 3
    # bytes, its seq 0 below 4, else the short frame's own bytes.
    for n in range(5):
        wires.append(frame(encode_request(Command.READ, 200 + n, 0x10, 1)))
        wires.append(frame(bytes(rng.randrange(1, 256) for _ in range(n))))
    return b"".join(wires)


@pytest.mark.parametrize("max_words, address_map, strobed", [
    (64, MAP, ()), (16, MAP, ("frames_ok", "crc_errors", "framing_errors", "rejected", "dropped")),
    (16, None, ()), (61, MAP, ("rejected",)), (62, None, ())])
def test_link_compact_form_matches_clock_by_clock(max_words, address_map, strobed):
    """``compact=True`` (the iCE40's form) and the default form, fed the same bytes, output
    ready, lost-byte and UART-error strobes (at random): every output of the two cores is equal
    in every clock (``bus.addr`` under ``stb``, ``bus.w_data`` under ``stb & we``, where the bus
    gives them meaning). An ``address_map`` of ``None`` lets accesses hit the slave's holes and
    read-only words (the bus status path)."""
    cores = [LinkCore(max_words=max_words, address_map=address_map, strobed=strobed,
                      compact=compact) for compact in (False, True)]
    m = Module()
    for k, core in enumerate(cores):
        m.submodules[f"core{k}"] = core
        m.submodules[f"slave{k}"] = slave = StandInRegisters()
        wiring.connect(m, link=core.bus, slave=slave.bus)
    rng = random.Random(max_words * 7 + len(strobed))
    wire = _lockstep_traffic(rng, max_words)
    names = ["i.ready", "o.valid", "bus.stb", "bus.lock", "bus.we"] + [
        f"{n}_strobe" if n in strobed else n for n in
        ("frames_ok", "crc_errors", "framing_errors", "rejected", "dropped")]

    def get(ctx, core, name):
        obj = core
        for part in name.split("."):
            obj = getattr(obj, part)
        return ctx.get(obj)

    mismatches = []
    seen = {"o": 0, "stb": 0, "lost": 0}

    async def bench(ctx):
        pending = list(wire)
        idle = 0
        for t in range(400_000):
            ready = rng.random() < 0.5
            lost = rng.random() < 0.002
            error = rng.random() < 0.001
            send = bool(pending) and rng.random() < 0.7
            ref_ready = ctx.get(cores[0].i.ready)
            for core in cores:
                ctx.set(core.o.ready, ready)
                ctx.set(core.rx_lost, lost & ~ref_ready)
                ctx.set(core.rx_error, error)
                ctx.set(core.i.valid, send and ref_ready)
                if send:
                    ctx.set(core.i.payload, pending[0])
            if send and ref_ready:
                pending.pop(0)
            await ctx.delay(1e-9)               # (comb outputs after the inputs)
            vals = [[get(ctx, c, n) for n in names] for c in cores]
            if ctx.get(cores[0].o.valid):
                seen["o"] += 1
                vals = [v + [ctx.get(c.o.payload)] for v, c in zip(vals, cores)]
            if ctx.get(cores[0].bus.stb):
                seen["stb"] += 1
                vals = [v + [ctx.get(c.bus.addr)] for v, c in zip(vals, cores)]
                if ctx.get(cores[0].bus.we):
                    vals = [v + [ctx.get(c.bus.w_data)] for v, c in zip(vals, cores)]
            seen["lost"] += lost & ~ref_ready
            if vals[0] != vals[1] and len(mismatches) < 5:
                mismatches.append((t, dict(zip(names, zip(*vals)))))
            await ctx.tick()
            idle = 0 if (pending or not ref_ready or ctx.get(cores[0].o.valid)) else idle + 1
            if idle > 2000:
                break

    simulate(m, [bench], name="hostlink_compact")
    assert mismatches == []
    assert seen["o"] > 500 and seen["stb"] > 100 and seen["lost"] > 0
