# amaranth: UnusedElaboratable=no
# Ref: docs/PROTOCOL.md §Physical layer (UART 8N1, LSB first)
import random

import pytest
from amaranth.back import verilog
from amaranth.hdl import Module

from foc_servo.hdl.uart import PHASE_BITS, UartRx, UartTx
from foc_servo.sim.harness import simulate


def test_uart_parameter_validation():
    with pytest.raises(TypeError, match=r"^UartTx clk_hz must be a positive number, not '50e6'$"):
        UartTx(clk_hz="50e6")
    with pytest.raises(TypeError, match=r"^UartRx baud must be a positive number, not 0$"):
        UartRx(baud=0)
    with pytest.raises(TypeError, match=r"^UartRx baud must be a positive number, not True$"):
        UartRx(baud=True)
    with pytest.raises(ValueError, match=r"^UartTx baud must be at most clk_hz / 8 = 6.25e\+06, "
                                         r"not 7000000.0$"):
        UartTx(clk_hz=50e6, baud=7e6)
    with pytest.raises(TypeError, match=r"^UartTx compact must be a bool, not 1$"):
        UartTx(compact=1)
    with pytest.raises(TypeError, match=r"^UartRx compact must be a bool, not 1$"):
        UartRx(compact=1)


def test_uart_fractional_increment():
    tx = UartTx(clk_hz=50e6, baud=3e6)
    assert tx.increment == round(3e6 * 2**PHASE_BITS / 50e6)
    assert abs(tx.increment * 50e6 / 2**PHASE_BITS / 3e6 - 1) < 1e-6


def _loopback(clk_hz, baud_rx, baud_tx, data, *, compact=False):
    """Send `data` back to back from a UartTx at baud_tx into a UartRx at baud_rx."""
    m = Module()
    m.submodules.tx = tx = UartTx(clk_hz=clk_hz, baud=baud_tx, compact=compact)
    m.submodules.rx = rx = UartRx(clk_hz=clk_hz, baud=baud_rx, compact=compact)
    m.d.comb += [rx.rx.eq(tx.tx), rx.o.ready.eq(1)]
    got, errors = [], []
    limit = int((len(data) + 2) * 10 * clk_hz / min(baud_rx, baud_tx))

    async def sender(ctx):
        for b in data:
            ctx.set(tx.i.payload, b)
            ctx.set(tx.i.valid, 1)
            await ctx.tick().until(tx.i.ready)
        ctx.set(tx.i.valid, 0)

    async def receiver(ctx):
        for _ in range(limit):
            _, _, valid, payload, err = await ctx.tick().sample(rx.o.valid, rx.o.payload,
                                                                 rx.error)
            if valid:
                got.append(payload)
            if err:
                errors.append(len(got))
            if len(got) == len(data):
                break

    simulate(m, [sender, receiver], clock_hz=clk_hz, name="uart_loopback")
    return got, errors


@pytest.mark.parametrize("compact", [False, True])
@pytest.mark.parametrize("clk_hz, baud, nbytes, error", [
    (50e6, 115200, 2, -0.03), (50e6, 115200, 2, 0.03),
    *[(clk, baud, 24, e) for clk, baud in ((50e6, 3e6), (33.333e6, 3e6), (50e6, 50e6 / 8))
      for e in (-0.03, 0.0, 0.03)],
])
def test_uart_loopback_with_baud_error(clk_hz, baud, nbytes, error, compact):
    """The sender's rate is off by `error` relative to the receiver's."""
    rng = random.Random(int(baud) ^ int(error * 100))
    data = [0x00, 0xFF, 0x55, 0xAA, 0x80, 0x01][:nbytes]
    data += [rng.randrange(256) for _ in range(nbytes - len(data))]
    baud_tx, baud_rx = baud * (1 + error), baud
    if baud_tx * 8 > clk_hz:                    # the sender may not exceed clk/8: slow the receiver
        baud_tx, baud_rx = baud, baud / (1 + error)
    got, errors = _loopback(clk_hz, baud_rx, baud_tx, data, compact=compact)
    assert got == data
    assert errors == []


@pytest.mark.parametrize("compact", [False, True])
def test_uart_tx_bit_timing_and_latency(compact):
    clk_hz, baud = 50e6, 3e6
    m = Module()
    m.submodules.tx = tx = UartTx(clk_hz=clk_hz, baud=baud, compact=compact)
    trace = []
    accepted = []

    async def bench(ctx):
        ctx.set(tx.i.payload, 0b01010011)
        ctx.set(tx.i.valid, 1)
        for t in range(400):
            _, _, line, ready = await ctx.tick().sample(tx.tx, tx.i.ready)
            trace.append(line)
            if ready and ctx.get(tx.i.valid) and not accepted:
                accepted.append(t)
                ctx.set(tx.i.valid, 0)

    simulate(m, [bench], clock_hz=clk_hz, name="uart_tx_timing")
    t0 = accepted[0]
    assert trace[t0] == 1 and trace[t0 + tx.latency] == 0      # start bit from t + latency
    edges = [t for t in range(t0, len(trace) - 1) if trace[t] != trace[t + 1]]
    bits = [0, 1, 1, 0, 0, 1, 0, 1, 0, 1]                      # start, data LSB first, stop
    changes = [k for k in range(1, 10) if bits[k] != bits[k - 1]]
    per_bit = clk_hz / baud
    assert len(edges) == len(changes) + 1                      # + the start edge
    for k, e in zip(changes, edges[1:]):
        assert abs((e - edges[0]) - k * per_bit) < 1.0
    # the line stays high after the stop bit
    assert all(trace[int(edges[0] + 10 * per_bit) + 2:])


@pytest.mark.parametrize("clk_hz, baud", [(33e6, 115200), (50e6, 3e6), (33.333e6, 33.333e6 / 8)])
def test_uart_tx_compact_lockstep(clk_hz, baud):
    """``UartTx(compact=True)`` against the counter form, every clock: the same ``tx``,
    ``busy`` and ``i.ready`` for random bytes offered with random gaps (none, a clock, a few
    clocks, longer than a byte), i.e. back-to-back bytes, bytes from idle and offers that
    wait."""
    m = Module()
    m.submodules.old = old = UartTx(clk_hz=clk_hz, baud=baud)
    m.submodules.new = new = UartTx(clk_hz=clk_hz, baud=baud, compact=True)
    per_byte = int(10 * clk_hz / baud) + 2
    rng = random.Random(int(baud))
    plan = [(rng.randrange(256), rng.choice([0, 0, 1, 3, rng.randrange(per_byte + 40)]))
            for _ in range(24)]
    mismatches, sent = [], []

    async def bench(ctx):
        t = 0
        for byte, gap in plan:
            for _ in range(gap):
                ctx.set(old.i.valid, 0)
                ctx.set(new.i.valid, 0)
                await ctx.tick()
                t += 1
            for dut in (old, new):
                ctx.set(dut.i.payload, byte)
                ctx.set(dut.i.valid, 1)
            while True:
                got = [(ctx.get(d.tx), ctx.get(d.busy), ctx.get(d.i.ready)) for d in (old, new)]
                if got[0] != got[1]:
                    mismatches.append((t, got))
                await ctx.tick()
                t += 1
                if got[0][2]:
                    sent.append(byte)
                    break
        ctx.set(old.i.valid, 0)
        ctx.set(new.i.valid, 0)
        for _ in range(per_byte + 4):
            got = [(ctx.get(d.tx), ctx.get(d.busy), ctx.get(d.i.ready)) for d in (old, new)]
            if got[0] != got[1]:
                mismatches.append((t, got))
            await ctx.tick()
            t += 1

    simulate(m, [bench], clock_hz=clk_hz, name="uart_tx_compact")
    assert sent == [b for b, _ in plan]
    assert mismatches == []


def _rx_bench(bits_per_event, *, per_bit=16, ready=True):
    """Drive UartRx's pin with (level, clocks) events; collect bytes, errors, overruns."""
    clk_hz = 50e6
    rx = UartRx(clk_hz=clk_hz, baud=clk_hz / per_bit)
    got, errors, overruns = [], [], []
    total = sum(n for _, n in bits_per_event) + 4 * per_bit

    async def driver(ctx):
        for level, n in bits_per_event:
            ctx.set(rx.rx, level)
            await ctx.tick().repeat(n)

    async def monitor(ctx):
        ctx.set(rx.o.ready, int(ready))
        for t in range(total):
            _, _, v, p, e, o = await ctx.tick().sample(rx.o.valid, rx.o.payload, rx.error,
                                                       rx.overrun)
            if v and ready:
                got.append(p)
            if e:
                errors.append(t)
            if o:
                overruns.append(t)
        got.append(("held", ctx.get(rx.o.valid), ctx.get(rx.o.payload)))

    simulate(rx, [driver, monitor], clock_hz=clk_hz, name="uart_rx")
    return got, errors, overruns


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_uart_rx_compact_lockstep(seed):
    """``UartRx(compact=True)`` (no BREAK state) against the other form, every clock: the
    same ``o.valid``, ``o.payload``, ``error`` and ``overrun`` for a random line of good
    bytes, bytes with a low stop bit, breaks (long lows), glitches and false starts, at
    slightly wrong rates, with ``o.ready`` random."""
    per_bit = 16
    rng = random.Random(seed)
    events = [(1, 30)]
    for _ in range(60):
        kind = rng.choice(["byte", "byte", "bad_stop", "break", "glitch", "false_start",
                           "short_high"])
        if kind in ("byte", "bad_stop"):
            n = per_bit + rng.choice([-1, 0, 0, 1])
            events += _byte_events(rng.randrange(256), per_bit=n,
                                   stop=int(kind == "byte"))
        elif kind == "break":
            events.append((0, rng.randrange(per_bit * 10, per_bit * 30)))
        elif kind == "glitch":
            events.append((0, rng.randrange(1, 3)))
        elif kind == "false_start":
            events.append((0, rng.randrange(3, per_bit // 2)))
        else:
            events.append((1, rng.randrange(1, 4)))
        events.append((1, rng.choice([0, 1, 2, per_bit, 3 * per_bit])))
    events = [(level, n) for level, n in events if n] + [(1, 40)]
    m = Module()
    m.submodules.old = old = UartRx(clk_hz=50e6, baud=50e6 / per_bit)
    m.submodules.new = new = UartRx(clk_hz=50e6, baud=50e6 / per_bit, compact=True)
    total = sum(n for _, n in events)
    mismatches, counts = [], [0, 0]

    async def driver(ctx):
        for level, n in events:
            ctx.set(old.rx, level)
            ctx.set(new.rx, level)
            await ctx.tick().repeat(n)

    async def monitor(ctx):
        for t in range(total):
            ready = rng.random() < 0.7
            ctx.set(old.o.ready, ready)
            ctx.set(new.o.ready, ready)
            got = [(ctx.get(d.o.valid), ctx.get(d.o.payload), ctx.get(d.error),
                    ctx.get(d.overrun)) for d in (old, new)]
            if got[0] != got[1]:
                mismatches.append((t, got))
            counts[0] += got[0][0] and ready
            counts[1] += got[0][2]
            await ctx.tick()

    simulate(m, [driver, monitor], clock_hz=50e6, name="uart_rx_compact")
    assert counts[0] >= 5 and counts[1] >= 3
    assert mismatches == []


def _byte_events(b, per_bit=16, stop=1):
    bits = [0] + [(b >> k) & 1 for k in range(8)] + [stop]
    return [(bit, per_bit) for bit in bits]


def test_uart_rx_framing_error_then_recovery():
    ev = [(1, 40)] + _byte_events(0x5A, stop=0) + [(1, 48)] + _byte_events(0xC3) + [(1, 32)]
    got, errors, _ = _rx_bench(ev)
    assert got[:-1] == [0xC3]
    assert len(errors) == 1


def test_uart_rx_break_gives_one_error_and_no_bytes():
    ev = [(1, 40), (0, 16 * 30), (1, 40)] + _byte_events(0x81) + [(1, 32)]
    got, errors, _ = _rx_bench(ev)
    assert got[:-1] == [0x81]
    assert len(errors) == 1


def test_uart_rx_glitch_and_false_start_rejected():
    ev = [(1, 40), (0, 1), (1, 40), (0, 4), (1, 60)] + _byte_events(0x42) + [(1, 32)]
    got, errors, _ = _rx_bench(ev)
    assert got[:-1] == [0x42]
    assert errors == []


def test_uart_rx_overrun_keeps_newest_byte():
    ev = [(1, 40)] + _byte_events(0x11) + _byte_events(0x22) + [(1, 32)]
    got, errors, overruns = _rx_bench(ev, ready=False)
    assert got == [("held", 1, 0x22)]
    assert len(overruns) == 1 and errors == []


def test_uart_converts_to_verilog():
    verilog.convert(UartRx(clk_hz=33.333e6, baud=3e6))
    verilog.convert(UartTx(clk_hz=33.333e6, baud=3e6))


def test_uart_rx_payload_stable_while_valid():
    """``o.payload`` is the shift register: a held byte is withdrawn (``o.valid`` low) in the
    middle of the next byte's start bit, never changed under ``o.valid``; that byte then pulses
    ``overrun`` with its ``o.valid``."""
    per_bit, clk_hz = 16, 50e6
    rx = UartRx(clk_hz=clk_hz, baud=clk_hz / per_bit)
    ev = [(1, 40)] + _byte_events(0x11) + _byte_events(0x22) + [(1, 32)]
    trace = []

    async def driver(ctx):
        for level, n in ev:
            ctx.set(rx.rx, level)
            await ctx.tick().repeat(n)

    async def monitor(ctx):
        ctx.set(rx.o.ready, 0)
        for _ in range(sum(n for _, n in ev)):
            _, _, v, p, o = await ctx.tick().sample(rx.o.valid, rx.o.payload, rx.overrun)
            trace.append((v, p, o))

    simulate(rx, [driver, monitor], clock_hz=clk_hz, name="uart_rx_hold")
    rises = [t for t in range(1, len(trace)) if trace[t][0] and not trace[t - 1][0]]
    falls = [t for t in range(1, len(trace)) if not trace[t][0] and trace[t - 1][0]]
    assert len(rises) == 2 and len(falls) == 1
    assert {trace[t][1] for t in range(rises[0], falls[0])} == {0x11}
    assert {trace[t][1] for t in range(rises[1], len(trace))} == {0x22}
    # delivered in the first stop bit's middle, withdrawn in the middle of the second byte's
    # start bit: one bit time later
    assert abs(falls[0] - rises[0] - per_bit) <= 2
    assert [t for t, r in enumerate(trace) if r[2]] == [rises[1]]
