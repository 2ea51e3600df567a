# Ref: docs/PROTOCOL.md; issue 5 targets (host link: 1 000 writes + read-backs, 10 000 malformed)
"""The host link gateware against the protocol model, end to end.

0. ``drive``: the host library's :class:`~foc_servo.host.servo.Servo`, through pyserial on a
   pseudo-terminal, against the **whole controller** (:class:`~foc_servo.hdl.top.Top` with its
   UART at 3.125 Mbaud, the register file, the motor plant) in the closed-loop co-simulation
   (:class:`~foc_servo.sim.closed_loop.CoSim`, compiled engine): random values, in physical units,
   written to random read-write registers and read back raw (the register's width);

then three parts, each on a fresh :class:`~foc_servo.sim.link.LinkSim` with the
:class:`~foc_servo.sim.link.StandInRegisters` bank:

1. ``rw``: random register writes, each read back, by :class:`~foc_servo.host.protocol.Client`
   through pyserial on the simulator's pseudo-terminal, on the bare protocol engine
   (:class:`~foc_servo.hdl.hostlink.LinkCore`, one wire byte per clock);
2. ``uart_pairs``: the same through the whole :class:`~foc_servo.hdl.hostlink.HostLink` (UART
   pins at clk/8, a host-side UART), fewer of them: 80 clocks per byte are expensive in pysim;
3. ``malformed``: malformed frames (random bytes, truncated, wrong CRC, bad address / read-only /
   burst across a hole, over-long and bad length, bad command), each followed by a ping, on the
   bare engine through the in-process transport. Every reply byte is compared with
   :class:`~foc_servo.sim.models.hostlink.LinkModel`; bus writes are counted on the bus.
"""

import concurrent.futures
import multiprocessing
import os
import random
import time

import serial

from ...host.protocol import (Client, Command, SerialTransport, cobs_encode, crc16, encode_request,
                              frame)
from ..harness import Progress
from ..link import LinkSim, StandInModel, StandInRegisters
from ..models.hostlink import LinkModel

__all__ = ["run", "summary", "malformed_frame", "KINDS"]

#: Kinds of malformed frames, in the order they are drawn.
KINDS = ("random", "truncated", "bad_crc", "bad_address", "bad_length", "bad_command")

_RW = [(a, b) for a, b, w in StandInRegisters.address_map if w]
_RO = [(a, b) for a, b, w in StandInRegisters.address_map if not w]


def _rw_addr(rng):
    lo, hi = rng.choice(_RW)
    return rng.randrange(lo, hi)


def _valid_request(rng, max_words):
    """A random well-formed request payload (CRC not yet added)."""
    cmd = rng.choice((Command.PING, Command.READ, Command.WRITE))
    seq = rng.randrange(256)
    if cmd == Command.PING:
        return encode_request(cmd, seq, 0, 0)
    lo, hi = rng.choice(_RW)
    n = rng.randint(1, min(max_words, hi - lo))
    addr = rng.randrange(lo, hi - n + 1)
    if cmd == Command.READ:
        return encode_request(cmd, seq, addr, n)
    return encode_request(cmd, seq, addr, n, [rng.getrandbits(32) for _ in range(n)])


def _wire(payload, crc=None):
    if crc is None:
        crc = crc16(payload)
    return b"\x00" + cobs_encode(payload + crc.to_bytes(2, "big")) + b"\x00"


def malformed_frame(rng, kind, max_words):
    """Wire bytes of one malformed frame of ``kind`` (see :data:`KINDS`)."""
    if kind == "random":
        return bytes(rng.getrandbits(8) for _ in range(rng.randint(1, 24)))
    if kind == "truncated":
        wire = _wire(_valid_request(rng, min(max_words, 4)))
        return wire[:rng.randint(2, len(wire) - 2)]      # leading 0x00 kept, end cut off
    if kind == "bad_crc":
        payload = _valid_request(rng, min(max_words, 4))
        if rng.random() < 0.5:
            return _wire(payload, crc16(payload) ^ (1 << rng.randrange(16)))
        bad = bytearray(payload)
        bad[rng.randrange(len(bad))] ^= 1 << rng.randrange(8)
        return _wire(bytes(bad), crc16(payload))
    if kind == "bad_address":
        seq = rng.randrange(256)
        choice = rng.randrange(5)
        if choice == 0:                                 # write into the read-only block
            lo, hi = rng.choice(_RO)
            addr, n = rng.randrange(lo, hi), 1
        elif choice == 1:                               # burst from rw into ro or a hole
            lo, hi = rng.choice(_RW)
            n = rng.randint(2, max_words)
            addr = rng.randrange(max(lo, hi - n + 1), hi)
        elif choice == 2:                               # burst running past 0xFFFF
            n = rng.randint(2, max_words)
            addr = rng.randrange(0x10000 - n + 1, 0x10000)
        else:                                           # a hole (reads and writes)
            addr, n = rng.choice((rng.randrange(0x18, 0x100), rng.randrange(0x140, 0x10000))), 1
            if choice == 4:
                return _wire(encode_request(Command.READ, seq, addr, n))
        words = [rng.getrandbits(32) for _ in range(n)]
        return _wire(encode_request(Command.WRITE, seq, addr, n, words))
    if kind == "bad_length":
        seq = rng.randrange(256)
        addr = _rw_addr(rng)
        choice = rng.randrange(5)
        if choice == 0:                                 # over-long: more words than max_words
            n = max_words + rng.randint(1, 3)
            words = [rng.getrandbits(32) for _ in range(n)]
            return _wire(encode_request(Command.WRITE, seq, addr, n & 0xFF, words))
        if choice == 1:                                 # count 0
            cmd = rng.choice((Command.READ, Command.WRITE))
            return _wire(encode_request(cmd, seq, addr, 0))
        if choice == 2:                                 # count and data disagree
            n = rng.randint(1, max_words)
            k = rng.choice([x for x in range(0, max_words + 1) if x != n])
            words = [rng.getrandbits(32) for _ in range(k)]
            return _wire(encode_request(Command.WRITE, seq, addr, n, words))
        if choice == 3:                                 # short header
            return _wire(bytes(rng.getrandbits(8) for _ in range(rng.randint(0, 4))))
        payload = encode_request(rng.choice(list(Command)), seq, addr, 1)    # trailing junk
        return _wire(payload + bytes(rng.getrandbits(8) for _ in range(rng.randint(1, 3))))
    if kind == "bad_command":
        cmd = rng.randrange(3, 256)
        return _wire(encode_request(cmd, rng.randrange(256), _rw_addr(rng), rng.randint(1, 4)))
    raise ValueError(f"Malformed frame kind must be one of {KINDS}, not {kind!r}")


def _model(max_words, regs):
    return LinkModel(regs.read, regs.write, max_words=max_words,
                     address_map=StandInRegisters.address_map)


def _rw_pass(count, *, rng, uart, max_words, clk_hz, progress, label):
    """Random writes with read-backs through pyserial on the pty; returns figures."""
    sim = LinkSim(uart=uart, max_words=max_words, clk_hz=clk_hz)
    path = sim.open_pty()
    mismatches = 0
    bar = Progress(label, count, enabled=progress)
    try:
        with serial.Serial(path, timeout=1) as port:
            client = Client(SerialTransport(port), timeout_s=600, max_words=max_words)
            for k in range(count):
                addr, word = _rw_addr(rng), rng.getrandbits(32)
                try:
                    client.write(addr, [word])
                    if client.read(addr, 1) != [word]:
                        mismatches += 1
                except Exception:                       # a failed transaction is a mismatch
                    mismatches += 1
                bar.update(k + 1)
    finally:
        sim.close()
        bar.close()
    return {"mismatches": mismatches, "bytes": sim.bytes_in + sim.bytes_out,
            "clocks": sim.clocks, "sim_s": sim.sim_s}


def _drive_pass(count, *, rng, engine, progress):
    """Random register writes in physical units + raw read-backs, Servo ⇄ pty ⇄ whole top."""
    from ...host.registers import REGISTERS
    from ...host.servo import Servo
    from ..closed_loop import CoSim
    cosim = CoSim(engine=engine, progress=progress)
    path = cosim.open_pty()
    names = [n for n, r in REGISTERS.items() if r.access == "rw"]
    mismatches = 0
    failures = []
    bar = Progress("link rw (pty, Servo, whole top)", count, enabled=progress)
    start = time.perf_counter()
    try:
        with Servo.open(path, baud=round(cosim.baud), timeout_s=600) as servo:
            for k in range(count):
                reg = REGISTERS[rng.choice(names)]
                if reg.kind == "enum":      # the library rejects codes outside the enum
                    raw = rng.choice([m.value for m in reg.enum])
                else:
                    raw = rng.randint(reg.fmt.min_raw, reg.fmt.max_raw)
                try:
                    value = servo._decode(reg, raw)
                    servo.set(reg.name, value)
                    got = reg.from_words(servo.client.read(reg.addr, reg.words))
                    if got != raw:
                        mismatches += 1
                        failures.append(f"{reg.name}: wrote raw {raw} ({value!r}), read {got}")
                except Exception as e:                  # a failed transaction is a mismatch
                    mismatches += 1
                    failures.append(f"{reg.name}: raw {raw}: {type(e).__name__}: {e}")
                bar.update(k + 1)
    finally:
        cosim.close()
        bar.close()
    return {"mismatches": mismatches, "bytes": cosim.bytes_in + cosim.bytes_out,
            "clocks": cosim.now, "sim_s": time.perf_counter() - start, "failures": failures}


def _malformed_items(count, rng, max_words):
    """``count`` (kind, wire bytes) items: a malformed frame that the model confirms writes
    nothing, then a ping with its own sequence number."""
    items = []
    for k in range(count):
        kind = KINDS[k % len(KINDS)]
        ping = frame(encode_request(Command.PING, k % 255 + 1))
        while True:
            bad = malformed_frame(rng, kind, max_words)
            trial = StandInModel()
            _model(max_words, trial).feed(bad + ping)
            if trial.writes == 0:
                break
        items.append((kind, bad + ping))
    return items


def _frames(wire):
    return [f + b"\x00" for f in wire.split(b"\x00")[:-1]]


def _malformed_pass(items, max_words, clk_hz, batch, progress=False):
    """Feed the items to the engine ``batch`` at a time; compare every reply with the model."""
    sim = LinkSim(uart=False, max_words=max_words, clk_hz=clk_hz, chunk_clocks=16)
    model = _model(max_words, StandInModel())
    writes = mism = hangs = 0
    bar = Progress("link malformed", len(items), enabled=progress)
    for start in range(0, len(items), batch):
        group = items[start:start + batch]
        expected = [_frames(model.feed(data)) for _, data in group]
        before = sim.bus_writes
        sim.send(b"".join(data for _, data in group))
        try:
            got = _frames(sim.run_until_idle(max_clocks=100_000 * len(group)))
        except TimeoutError:                            # the link hangs: every ping is lost
            hangs += len(items) - start
            mism += len(items) - start
            break
        writes += sim.bus_writes - before
        pos = 0
        for want in expected:                           # each item ends with its ping's reply
            try:
                end = got.index(want[-1], pos) + 1
            except ValueError:
                hangs += 1
                mism += 1
                continue
            mism += got[pos:end] != want
            pos = end
        mism += pos != len(got)                         # replies nobody asked for
        bar.update(min(start + batch, len(items)))
    bar.close()
    return {"writes": writes, "mismatches": mism, "hangs": hangs,
            "bytes": sim.bytes_in + sim.bytes_out, "clocks": sim.clocks, "sim_s": sim.sim_s}


def run(rw=1000, malformed=10_000, *, drive=None, engine="compiled", seed=0, progress=False,
        uart_pairs=10, max_words=16, clk_hz=50e6, batch=16, jobs=None):
    """Run the parts; return the figures.

    Parameters
    ----------
    rw : int
        Writes + read-backs through pyserial on the bare engine.
    drive : int or None
        Writes (physical units, by :class:`~foc_servo.host.servo.Servo`) + read-backs through
        pyserial on the whole controller in the co-simulation; ``None``: as many as ``rw``.
    engine : str
        The co-simulation's engine for ``drive``.
    malformed : int
        Malformed frames, each followed by a ping.
    uart_pairs : int
        Writes + read-backs through pyserial on the whole UART link (clk/8 baud).
    max_words : int
        The link's maximum burst (small keeps over-long frames short: 5 + 4·max_words + 2
        bytes is the longest well-formed request).
    batch : int
        Malformed frames (each with its ping) queued at once; the engine's flow control loses
        no byte, so the replies are those of the frames one by one.
    jobs : int or None
        Processes for the malformed part (the frames are independent); ``None``: up to 2, as
        many as there are CPUs.

    Returns
    -------
    dict
        ``rw_mismatches``, ``rw_uart_mismatches``, ``malformed_frames``, ``malformed_writes``
        (bus writes during the malformed frames), ``malformed_mismatches`` (frames whose
        replies differ from the model's), ``hangs`` (pings not answered correctly), per-kind
        counts ``kinds``, ``mismatches`` (all of these mismatches), ``vectors``, ``bytes``,
        ``clocks``, ``sim_s`` (seconds spent simulating, summed over the processes),
        ``uart_clocks`` (of the UART part), ``wall_s``.
    """
    start = time.perf_counter()
    rng = random.Random(seed)
    d = _drive_pass(rw if drive is None else drive, rng=rng, engine=engine, progress=progress)
    a = _rw_pass(rw, rng=rng, uart=False, max_words=max_words, clk_hz=clk_hz,
                 progress=progress, label="link rw (pty, engine)")
    b = _rw_pass(uart_pairs, rng=rng, uart=True, max_words=max_words, clk_hz=clk_hz,
                 progress=progress, label="link rw (pty, UART)")

    if jobs is None:
        jobs = min(2, os.cpu_count() or 1)
    items = _malformed_items(malformed, rng, max_words)
    kinds = dict.fromkeys(KINDS, 0)
    for kind, _ in items:
        kinds[kind] += 1
    if jobs > 1 and malformed >= 2 * batch:
        step = -(-len(items) // jobs)
        parts = [items[k:k + step] for k in range(0, len(items), step)]
        ctx = multiprocessing.get_context("fork")
        with concurrent.futures.ProcessPoolExecutor(len(parts), mp_context=ctx) as pool:
            results = list(pool.map(_malformed_pass, parts, [max_words] * len(parts),
                                    [clk_hz] * len(parts), [batch] * len(parts)))
    else:
        results = [_malformed_pass(items, max_words, clk_hz, batch, progress=progress)]
    c = {key: sum(r[key] for r in results) for key in results[0]}
    n_drive = rw if drive is None else drive
    return {
        "rw_mismatches": d["mismatches"],
        "rw_engine_mismatches": a["mismatches"],
        "rw_uart_mismatches": b["mismatches"],
        "rw": n_drive,
        "rw_engine": rw,
        "drive_clocks": d["clocks"],
        "drive_failures": d["failures"][:20],
        "drive_s": d["sim_s"],
        "uart_pairs": uart_pairs,
        "malformed_frames": malformed,
        "malformed_writes": c["writes"],
        "malformed_mismatches": c["mismatches"],
        "hangs": c["hangs"],
        "kinds": kinds,
        "mismatches": d["mismatches"] + a["mismatches"] + b["mismatches"] + c["mismatches"],
        "vectors": n_drive + rw + uart_pairs + malformed,
        "bytes": d["bytes"] + a["bytes"] + b["bytes"] + c["bytes"],
        "clocks": a["clocks"] + b["clocks"] + c["clocks"],
        "sim_s": a["sim_s"] + b["sim_s"] + c["sim_s"],
        "uart_clocks": b["clocks"],
        "wall_s": time.perf_counter() - start,
    }


def summary(figures):
    """Human-readable lines of :func:`run`'s figures (for ``foc-servo bench link``)."""
    f = figures
    return "\n".join([
        f"rw (pty, Servo, whole top, UART 3.125 Mbaud) {f['rw']:6d} writes + read-backs, "
        f"{f['rw_mismatches']} mismatches ({f['drive_clocks']} clocks in {f['drive_s']:.1f} s)",
        f"rw (pty, engine)      {f['rw_engine']:6d} writes + read-backs, "
        f"{f['rw_engine_mismatches']} mismatches",
        f"rw (pty, UART clk/8)  {f['uart_pairs']:6d} writes + read-backs, "
        f"{f['rw_uart_mismatches']} mismatches",
        f"malformed frames      {f['malformed_frames']:6d} "
        f"({', '.join(f'{k} {v}' for k, v in f['kinds'].items())})",
        f"  bus writes caused   {f['malformed_writes']:6d}",
        f"  replies != model    {f['malformed_mismatches']:6d}",
        f"  hangs (ping lost)   {f['hangs']:6d}",
        f"simulated             {f['clocks']} clocks, {f['bytes']} bytes, {f['sim_s']:.1f} s "
        f"({f['clocks'] / max(f['sim_s'], 1e-9):.0f} clocks/s); wall {f['wall_s']:.1f} s",
    ])
