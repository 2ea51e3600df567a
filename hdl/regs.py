# Ref: paper §3 (on-line adjustable parameters); issue 5 item 1; hdl/bus.py (register bus)
"""The register file: the bus slave generated from the register map (:mod:`.regmap`).

Timing (``t`` = the clock ``bus.stb`` rises for an access)::

    t      stb, addr, we, w_data (held by the master until ack)
           write: staging / immediate register loaded at the end of t; the address decoded
           into a registered word select
    t + 1  a strobe register's pulse; the read multiplexer (word select → the word's value,
           status inputs sampled in this clock) into the registered read data
    t + 2  ack, status, r_data; the master may start the next access in t + 3 (stb is still
           high in t + 1 and t + 2 and is not taken as a new access)

The read is split over two clocks (:attr:`RegisterFile.latency` 2) so that neither the address
decode nor the word multiplexer sits behind the other in one clock (the whole top's 100 MHz on
the ECP5: the 16-bit compares and the ~130-way 32-bit multiplexer in series measured 10.2 ns
alone, 14.6 ns in the routed top, docs/AREA.md §7.7).

Shadowing: a write to a shadowed ``rw`` register loads its staging register; the staging
registers of all shadowed registers are copied to the active ones (the Out members) at the end of
every clock with ``commit`` high and ``bus.lock`` low, so the writes of one host frame (``lock``
held high over it) are applied together at the first commit after the frame. Immediate (unshadowed)
``rw`` registers have no staging: the write changes the Out member in ``t + 1``. Reads of ``rw``
registers return the staging value (what the host wrote), which equals the active value once
committed.
"""

from amaranth.hdl import Module, Mux, Signal, Value, unsigned
from amaranth.lib import wiring
from amaranth.lib.wiring import In, Out

from .bus import DATA_WIDTH, RegBusSignature, Status
from .regmap import REGMAP, Access, RegMap

__all__ = ["RegisterFile"]


def _bits(port):
    """The plain value of a port (a View / EnumView or a Signal)."""
    return port.as_value() if hasattr(port, "as_value") else Value.cast(port)


class RegisterFile(wiring.Component):
    """Bus slave holding every register of a :class:`~.regmap.RegMap`.

    Parameters
    ----------
    regmap : RegMap
        The declaration (default :data:`~.regmap.REGMAP`). ``const`` registers read their
        declared reset value: build the map for the drive's clock and scales with
        :func:`~.regmap.build_regmap`.

    Members
    -------
    bus : In(RegBusSignature())
        Register bus from the host link (see :mod:`.bus`); ``ack`` two clocks after ``stb``.
    commit : In(1)
        Loop-boundary strobe: staging → active for every shadowed register, while ``bus.lock``
        is low. Pulse it when no loop is computing (e.g. the PWM ``period_start``).
    <rw register> : Out(register.shape, init=reset)
        The active value the control path uses (enum, StructLayout of the fields, or the raw
        fixed-point shape ``register.fmt.shape``).
    <ro register> : In(register.shape)
        Status from the control path.
    <strobe register> : Out(1)
        One-clock pulse in ``t + 1`` after a write with bit 0 set.
    <window>_rd_addr : Out(window.addr_width)
        Word offset of the access into the window (``bus.addr``'s low bits, combinational).
    <window>_rd_data : In(32)
        The word at ``<window>_rd_addr`` one clock earlier (a memory read port); returned on
        ``bus.r_data`` in the ack clock of a window read (the address is held: read in t + 1).

    Attributes
    ----------
    latency : int
        Clocks from ``stb`` to ``ack``: 2.
    commit_latency : int
        Clocks from a ``commit`` (lock low) to the new active values: 1.

    Raises
    ------
    TypeError
        ``regmap`` is not a :class:`~.regmap.RegMap`.
    """

    latency = 2
    commit_latency = 1

    def __init__(self, regmap=REGMAP):
        if not isinstance(regmap, RegMap):
            raise TypeError(f"RegisterFile regmap must be a RegMap, not {regmap!r}")
        self._regmap = regmap
        members = {"bus": In(RegBusSignature()), "commit": In(1)}
        for r in regmap:
            if r.access is Access.RW:
                members[r.name] = Out(r.shape, init=r.init)
            elif r.access is Access.RO:
                members[r.name] = In(r.shape)
            elif r.access is Access.STROBE:
                members[r.name] = Out(1)
        for w in regmap.windows:
            members[f"{w.name}_rd_addr"] = Out(w.addr_width)
            members[f"{w.name}_rd_data"] = In(DATA_WIDTH)
        super().__init__(members)

    regmap = property(lambda self: self._regmap)

    def elaborate(self, platform):
        m = Module()
        bus = self.bus

        access = Signal()
        pending = Signal()                      # t + 1 of an access: the read multiplexer
        r_data = Signal(DATA_WIDTH)
        win_hit = {w.name: Signal(name=f"{w.name}_hit") for w in self._regmap.windows}
        win_pend = {w.name: Signal(name=f"{w.name}_pend") for w in self._regmap.windows}
        status_p = Signal(Status)
        words = self._regmap.words()
        # Word select: 1 + the index of the addressed register word (0: none, reads 0).
        sel = Signal(range(len(words) + 1))
        m.d.comb += access.eq(bus.stb & ~pending & ~bus.ack)
        m.d.sync += [pending.eq(access), bus.ack.eq(pending)]

        out = r_data
        for w in self._regmap.windows:
            m.d.comb += getattr(self, f"{w.name}_rd_addr").eq(bus.addr[:w.addr_width])
            out = Mux(win_hit[w.name], getattr(self, f"{w.name}_rd_data"), out)
        m.d.comb += bus.r_data.eq(out)

        # The value each register's reads return, and where writes go.
        held = {}
        for r in self._regmap:
            port = getattr(self, r.name, None)
            if r.access is Access.RW and r.shadow is not None:
                staged = Signal(unsigned(r.width), init=r.bits(r.reset), name=f"{r.name}_staged")
                held[r.name] = staged
                with m.If(self.commit & ~bus.lock):
                    m.d.sync += _bits(port).eq(staged)
            elif r.access is Access.RW:
                held[r.name] = _bits(port)
            elif r.access is Access.RO:
                held[r.name] = _bits(port)
            elif r.access is Access.CONST:
                held[r.name] = r.bits(r.reset)
            else:
                held[r.name] = 0
                m.d.sync += port.eq(0)

        # t: address decode → writes, status, word select (registered).
        with m.If(access):
            m.d.sync += [
                status_p.eq(Status.BAD_ADDRESS),
                sel.eq(0),
                *(hit.eq(0) for hit in win_pend.values()),
            ]
            with m.Switch(bus.addr):
                for i, (addr, r, k) in enumerate(words):
                    with m.Case(addr):
                        self._word(m, r, k, held[r.name], status_p)
                        with m.If(~bus.we):
                            m.d.sync += sel.eq(i + 1)
                for w in self._regmap.windows:
                    pattern = format(w.addr >> w.addr_width, f"0{16 - w.addr_width}b")
                    with m.Case(pattern + "-" * w.addr_width):
                        with m.If(bus.we):
                            m.d.sync += status_p.eq(Status.READ_ONLY)
                        with m.Else():
                            m.d.sync += [status_p.eq(Status.OK), win_pend[w.name].eq(1)]
        # t + 1: word select → read data; status and window hit passed on (all for t + 2).
        with m.If(pending):
            m.d.sync += [bus.status.eq(status_p),
                         *(win_hit[n].eq(win_pend[n]) for n in win_hit)]
            with m.Switch(sel):
                with m.Case(0):
                    m.d.sync += r_data.eq(0)
                for i, (addr, r, k) in enumerate(words):
                    with m.Case(i + 1):
                        m.d.sync += r_data.eq(self._read_word(r, k, held[r.name]))
        return m

    @staticmethod
    def _read_word(r, k, held):
        """The bus word ``k`` of register ``r`` holding ``held`` (a value or a constant)."""
        if isinstance(held, int):               # constants (and strobes: 0)
            return r.read_word(held, k)
        lo, hi = r.word_slice(k)
        word = held[lo:hi]
        if r.signed and k == r.words - 1:
            word = word.as_signed()             # sign-extended to the bus width
        return word

    def _word(self, m, r, k, held, status):
        """The write and status logic of word ``k`` of register ``r`` (inside its address
        ``Case``; ``status`` the register passed on to ``bus.status``)."""
        bus = self.bus
        lo, hi = r.word_slice(k)
        with m.If(bus.we):
            if r.access is Access.STROBE:
                m.d.sync += [status.eq(Status.OK), getattr(self, r.name).eq(bus.w_data[0])]
            elif r.access is Access.RW:
                m.d.sync += [status.eq(Status.OK), held[lo:hi].eq(bus.w_data[:hi - lo])]
            else:
                m.d.sync += status.eq(Status.READ_ONLY)
        with m.Else():
            m.d.sync += status.eq(Status.OK)
