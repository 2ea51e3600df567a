# Ref: docs/PROTOCOL.md; issue 5 item 7 (the host library against the simulated gateware)
"""The host link gateware in Amaranth's simulator, behind a byte transport.

:class:`LinkSim` simulates a :class:`~foc_servo.hdl.hostlink.HostLink` (UART pins, a host-side
UART model made of the same gateware) or, for bulk tests, the bare
:class:`~foc_servo.hdl.hostlink.LinkCore` fed one byte per clock, plus a bus slave (the
:class:`StandInRegisters` bank, or the real register file through ``bus_slave_factory``). The
host's bytes pass through a simulation-only ring buffer (a memory) and the link's replies
through a shift register, which a Python testbench fills and drains once per ``chunk_clocks``:
Python stays out of the per-clock loop, and the simulator only runs while bytes are in flight
(nothing is simulated while the link is idle). Cost: ~7–10 k clocks/s in pysim; the engine
takes a wire byte per clock and ~3 clocks per reply byte, the UART 10·clk/baud = 80 clocks per
byte at clk/8.

Two ways in:

* :meth:`LinkSim.transport` — an in-process :class:`~foc_servo.host.protocol.Transport`;
* :meth:`LinkSim.open_pty` — a pseudo-terminal whose slave path any serial client opens
  (``serial.Serial(path)``); a thread bridges the pty's master side to the simulation.
"""

import os
import select
import threading
import time
import tty

from amaranth.hdl import Cat, Module, Mux, Signal
from amaranth.lib import wiring
from amaranth.lib.memory import Memory
from amaranth.lib.wiring import In, Out
from amaranth.sim import Simulator

from ..hdl.bus import RegBusSignature, Status
from ..hdl.hostlink import HostLink, LinkCore
from ..hdl.uart import UartRx, UartTx
from ..host.protocol import Transport

__all__ = ["StandInRegisters", "StandInModel", "ByteSim", "LinkSim"]

_RING = 4096
_OUT = 40           # output bytes held between two testbench visits


class StandInRegisters(wiring.Component):
    """A small register bank standing in for the register file in link tests.

    * ``0x0000 … 0x000F``: 16 read-write words (reset 0);
    * ``0x0010 … 0x0017``: 8 read-only words, ``0xC0DE0000 | address``;
    * ``0x0018 … 0x00FF``: no registers (BAD_ADDRESS);
    * ``0x0100 … 0x013F``: 64 read-write words (reset 0), for the longest bursts;
    * everything above: no registers.

    ``ack`` comes one clock after ``stb`` (and drops the clock after); ``status`` per
    :class:`~foc_servo.hdl.bus.Status`.

    Members
    -------
    bus : In(RegBusSignature())

    Attributes
    ----------
    address_map : tuple of (start, stop, writable)
        For :class:`~foc_servo.hdl.hostlink.HostLink`'s address checks.
    """

    bus: In(RegBusSignature())

    RW_LOW = (0x0000, 0x0010)
    RO = (0x0010, 0x0018)
    RW_HIGH = (0x0100, 0x0140)
    address_map = ((0x0000, 0x0010, True), (0x0010, 0x0018, False), (0x0100, 0x0140, True))

    def elaborate(self, platform):
        m = Module()
        bus = self.bus
        lo, hi = self.RW_LOW, self.RW_HIGH
        m.submodules.mem = mem = Memory(shape=32, depth=128, init=[])
        rd = mem.read_port()
        wr = mem.write_port()
        a = bus.addr
        in_lo = a < lo[1]
        in_ro = (a >= self.RO[0]) & (a < self.RO[1])
        in_hi = (a >= hi[0]) & (a < hi[1])
        index = Mux(in_lo, a[:7], (a - hi[0] + 64)[:7])
        ro_sel = Signal()
        m.d.comb += [rd.addr.eq(index), wr.addr.eq(index), wr.data.eq(bus.w_data)]
        m.d.sync += [bus.ack.eq(bus.stb & ~bus.ack), ro_sel.eq(in_ro)]
        with m.If(bus.stb & ~bus.ack & bus.we & (in_lo | in_hi)):
            m.d.comb += wr.en.eq(1)
        m.d.comb += bus.r_data.eq(Mux(ro_sel, 0xC0DE0000 | bus.addr, Mux(bus.status == Status.OK,
                                                                          rd.data, 0)))
        with m.If(in_lo | in_hi | (in_ro & ~bus.we)):
            m.d.comb += bus.status.eq(Status.OK)
        with m.Elif(in_ro):
            m.d.comb += bus.status.eq(Status.READ_ONLY)
        with m.Else():
            m.d.comb += bus.status.eq(Status.BAD_ADDRESS)
        return m


class StandInModel:
    """Python twin of :class:`StandInRegisters`: ``read``/``write`` callables for
    :class:`~foc_servo.sim.models.hostlink.LinkModel`, and ``writes`` (bus writes seen)."""

    def __init__(self):
        self.regs = {}
        self.writes = 0

    @staticmethod
    def kind(addr):
        for start, stop, writable in StandInRegisters.address_map:
            if start <= addr < stop:
                return "rw" if writable else "ro"
        return None

    def read(self, addr):
        kind = self.kind(addr)
        if kind == "rw":
            return self.regs.get(addr, 0), 0
        if kind == "ro":
            return 0xC0DE0000 | addr, 0
        return 0, 1

    def write(self, addr, word):
        self.writes += 1
        kind = self.kind(addr)
        if kind == "rw":
            self.regs[addr] = word
            return 0
        return 2 if kind == "ro" else 1


class _Bench(wiring.Component):
    """Simulation top: input ring → (host UART →) link (→ host UART) → output ring; bus slave;
    bus write counter; an ``idle`` flag (nothing in flight for a while)."""

    in_wp: In(range(_RING))
    in_rp: Out(range(_RING))
    out_n: Out(range(_OUT + 1))
    out_buf: Out(8 * _OUT)
    idle: Out(1)
    bus_writes: Out(32)

    def __init__(self, slave, *, uart, clk_hz, baud, max_words, address_map):
        self.slave = slave
        self.uart = uart
        if uart:
            self.link = HostLink(clk_hz=clk_hz, baud=baud, max_words=max_words,
                                 address_map=address_map)
            self.quiet_clocks = int(2 * clk_hz / baud) + 16
        else:
            self.link = LinkCore(max_words=max_words, address_map=address_map)
            self.quiet_clocks = 4
        self.clk_hz, self.baud = clk_hz, baud
        self.in_mem = Memory(shape=8, depth=_RING, init=[])
        super().__init__()

    def elaborate(self, platform):
        m = Module()
        m.submodules.slave = slave = self.slave
        m.submodules.link = link = self.link
        m.submodules.in_mem = self.in_mem
        wiring.connect(m, link=link.bus, slave=slave.bus)
        bus = link.bus
        with m.If(bus.stb & bus.ack & bus.we):
            m.d.sync += self.bus_writes.eq(self.bus_writes + 1)

        in_rd = self.in_mem.read_port(domain="comb")
        in_rp = self.in_rp
        m.d.comb += in_rd.addr.eq(in_rp)
        pending = in_rp != self.in_wp
        src_valid, src_payload = Signal(), Signal(8)
        core = link.core if self.uart else link

        if self.uart:
            m.submodules.host_tx = host_tx = UartTx(clk_hz=self.clk_hz, baud=self.baud)
            m.submodules.host_rx = host_rx = UartRx(clk_hz=self.clk_hz, baud=self.baud)
            m.d.comb += [link.rx.eq(host_tx.tx), host_rx.rx.eq(link.tx), host_rx.o.ready.eq(1)]
            source, sink = host_tx.i, host_rx.o
            activity = (pending | src_valid | host_tx.busy | ~core.i.ready | ~link.tx
                        | ~link.rx)
        else:
            source, sink = link.i, link.o
            m.d.comb += sink.ready.eq(1)
            activity = pending | src_valid | ~core.i.ready | sink.valid

        # A register stage between the ring and the link: the link's inputs then change at the
        # clock edge with its own registers (no extra pysim delta cycle).
        with m.If(~src_valid | source.ready):
            m.d.sync += [src_valid.eq(pending), src_payload.eq(in_rd.data)]
            with m.If(pending):
                m.d.sync += in_rp.eq(in_rp + 1)
        m.d.comb += [source.payload.eq(src_payload), source.valid.eq(src_valid)]
        # Output bytes shift in from the top; the testbench takes the newest `out_n` and clears
        # `out_n` on each visit (a memory write port would wake pysim every clock).
        with m.If(sink.valid):
            m.d.sync += [self.out_buf.eq(Cat(self.out_buf[8:], sink.payload)),
                         self.out_n.eq(self.out_n + 1)]

        quiet = Signal(range(self.quiet_clocks + 1))
        with m.If(activity):
            m.d.sync += quiet.eq(0)
        with m.Elif(quiet != self.quiet_clocks):
            m.d.sync += quiet.eq(quiet + 1)
        m.d.comb += self.idle.eq(~activity & (quiet == self.quiet_clocks))
        return m


class _InProcess(Transport):
    """In-process :class:`~foc_servo.host.protocol.Transport` over a :class:`ByteSim`: a read
    runs the simulation until the bytes are there or the link has gone idle (then it returns
    what there is at once: nothing more can come)."""

    def __init__(self, link_sim):
        self._sim = link_sim

    def write(self, data):
        self._sim.send(data)

    def read(self, size, timeout_s):
        return self._sim.receive(size)

    @property
    def drained(self):
        return self._sim.idle and not self._sim.has_output

    def reset_input(self):
        self._sim.take_output()


class ByteSim:
    """A simulated byte link: the byte interface, the in-process transport and the pty bridge
    shared by :class:`LinkSim` and the closed-loop co-simulation
    (:class:`~foc_servo.sim.closed_loop.CoSim`).

    A subclass provides :meth:`step` (simulate a little further, collecting reply bytes with
    :meth:`_received`), :attr:`idle` (nothing in flight) and :meth:`_queue` (take host bytes).
    """

    _thread = None
    #: The pty bridge keeps simulating while no bytes are in flight (a drive whose motor moves
    #: while the host is quiet), instead of pausing.
    free_run = False

    def _init_bytes(self):
        self._out = bytearray()
        self.bytes_in = self.bytes_out = 0

    def step(self):
        raise NotImplementedError

    @property
    def idle(self):
        raise NotImplementedError

    def _queue(self, data):
        raise NotImplementedError

    def _received(self, data):
        self._out += data
        self.bytes_out += len(data)

    # --- byte interface ---------------------------------------------------------------------

    def send(self, data):
        """Queue bytes for the link."""
        data = bytes(data)
        self._queue(data)
        self.bytes_in += len(data)

    def receive(self, size):
        """Simulate until some bytes have come back or the link is idle; return up to ``size``
        of them."""
        while not self._out and not self.idle:
            self.step()
        out = bytes(self._out[:size])
        del self._out[:size]
        return out

    @property
    def has_output(self):
        """Bytes have come back that nobody has taken yet."""
        return bool(self._out)

    def take_output(self):
        """All bytes received so far (without simulating further)."""
        out = bytes(self._out)
        self._out.clear()
        return out

    def run_until_idle(self, max_clocks=10_000_000):
        """Simulate until nothing is in flight; return the bytes that came back."""
        start = self.clocks
        while not self.idle:
            if self.clocks - start > max_clocks:
                raise TimeoutError(f"link still busy after {max_clocks} clocks")
            self.step()
        return self.take_output()

    def transport(self):
        """An in-process :class:`~foc_servo.host.protocol.Transport` (not while a pty is open)."""
        if self._thread is not None:
            raise RuntimeError(f"{type(self).__name__} is bridged to a pty; use the pty path")
        return _InProcess(self)

    # --- pseudo-terminal ----------------------------------------------------------------------

    def open_pty(self):
        """Bridge the simulation to a new pseudo-terminal; return its slave path, for
        ``serial.Serial(path)``. From now on only the bridge thread touches the simulation."""
        if self._thread is not None:
            raise RuntimeError(f"{type(self).__name__} pty is already open")
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._bridge, name=f"{type(self).__name__}-pty",
                                        daemon=True)
        self._thread.start()
        return os.ttyname(self._slave)

    def _bridge(self):
        master = self._master
        while not self._stop.is_set():
            busy = not self.idle
            ready, _, _ = select.select([master], [], [], 0 if busy else 0.005)
            if ready:
                try:
                    data = os.read(master, 4096)
                except OSError:
                    data = b""
                if data:
                    self.send(data)
                    busy = True
            if busy or self.free_run:
                self.step()
            out = self.take_output()
            while out:
                n = os.write(master, out)
                out = out[n:]
                time.sleep(0)               # let the client's thread take the GIL now

    def close(self):
        """Stop the pty bridge (if any) and close its file descriptors."""
        if self._thread is not None:
            self._stop.set()
            self._thread.join()
            os.close(self._master)
            os.close(self._slave)
            self._thread = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class LinkSim(ByteSim):
    """The host link gateware and a bus slave, simulated behind a byte transport.

    Parameters
    ----------
    bus_slave_factory : callable() -> Component with ``bus: In(RegBusSignature())``
        Builds the bus slave (default :class:`StandInRegisters`). If the slave has an
        ``address_map`` attribute and ``address_map`` is not given, the link uses it.
    clk_hz : float
        Simulated clock frequency, Hz.
    baud : float or None
        UART bit rate; ``None``: ``clk_hz / 8`` (80 clocks per byte; the UART is verified at
        real rates in ``tests/test_uart.py``).
    uart : bool
        ``True``: the whole :class:`~foc_servo.hdl.hostlink.HostLink` with UART pins and a
        host-side UART. ``False``: the bare :class:`~foc_servo.hdl.hostlink.LinkCore`, one wire
        byte per clock (for bulk protocol tests; no UART timing).
    max_words : int
        The link's maximum burst.
    address_map : tuple or None
        See :class:`~foc_servo.hdl.hostlink.LinkCore`.
    chunk_clocks : int or None
        Clocks simulated between two visits of the Python testbench (buffers, flags); ``None``:
        16 (engine) or 256 (UART).

    Attributes
    ----------
    bytes_in, bytes_out : int
        Bytes sent to and received from the link so far.
    clocks : int
        Clocks simulated so far.
    sim_s : float
        Wall-clock seconds spent simulating.
    bus_writes : int
        Bus write accesses so far (counted on the bus, whatever the slave).
    counters : dict
        The link's status counters as of the last visit.
    """

    def __init__(self, bus_slave_factory=StandInRegisters, *, clk_hz=50e6, baud=None, uart=True,
                 max_words=64, address_map=None, chunk_clocks=None):
        if baud is None:
            baud = clk_hz / 8
        slave = bus_slave_factory()
        if address_map is None:
            address_map = getattr(slave, "address_map", None)
        self.bench = _Bench(slave, uart=uart, clk_hz=clk_hz, baud=baud, max_words=max_words,
                            address_map=address_map)
        self.link = self.bench.link
        self.uart = uart
        if chunk_clocks is None:
            chunk_clocks = 256 if uart else 16
        # At most one byte per clock (engine) or per 10 bit times (UART) between two visits.
        limit = _OUT - 2 if not uart else int((_OUT - 2) * 10 * clk_hz / baud)
        if not isinstance(chunk_clocks, int) or not 1 <= chunk_clocks <= limit:
            raise ValueError(f"LinkSim chunk_clocks must be an integer from 1 to {limit}, "
                             f"not {chunk_clocks!r}")
        self._period_fs = round(1e15 / clk_hz)
        self._chunk_fs = chunk_clocks * self._period_fs
        self._init_bytes()
        self._pending = bytearray()
        self._in_wp = 0
        self._idle = True
        self._now_fs = 0
        self.sim_s = 0.0
        self.bus_writes = 0
        self.counters = {}
        self._sim = Simulator(self.bench)
        self._sim.add_clock(self._period_fs / 1e15)
        self._sim.add_testbench(self._service)
        self.step()                         # reset, first visit

    @property
    def clocks(self):
        return self._now_fs // self._period_fs

    async def _service(self, ctx):
        b = self.bench
        await ctx.tick()
        await ctx.delay(self._period_fs / 4e15)         # visit between clock edges
        names = ("frames_ok", "crc_errors", "framing_errors", "rejected", "dropped")
        while True:
            if self._pending:
                free = _RING - 1 - (self._in_wp - ctx.get(b.in_rp)) % _RING
                chunk = self._pending[:free]
                for byte in chunk:
                    ctx.set(b.in_mem.data[self._in_wp], byte)
                    self._in_wp = (self._in_wp + 1) % _RING
                del self._pending[:len(chunk)]
                ctx.set(b.in_wp, self._in_wp)
            n = ctx.get(b.out_n)
            if n:
                assert n < _OUT, "LinkSim output buffer overflow: lower chunk_clocks"
                self._received(ctx.get(b.out_buf).to_bytes(_OUT, "little")[_OUT - n:])
                ctx.set(b.out_n, 0)
            self._idle = bool(ctx.get(b.idle)) and not self._pending
            self.bus_writes = ctx.get(b.bus_writes)
            if self._idle:
                self.counters = {n: ctx.get(getattr(self.link, n)) for n in names}
            await ctx.delay(self._chunk_fs / 1e15)

    def step(self):
        """Simulate ``chunk_clocks`` more clocks."""
        start = time.perf_counter()
        self._now_fs += self._chunk_fs
        self._sim.run_until(self._now_fs / 1e15)
        self.sim_s += time.perf_counter() - start

    @property
    def idle(self):
        """Nothing in flight: no queued input, the link waiting for a frame, lines quiet."""
        return self._idle and not self._pending

    def _queue(self, data):
        self._pending += data
