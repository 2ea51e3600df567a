# Ref: paper §3 (on-line adjustable parameters); issue 5 item 1; hdl/bus.py (register bus)
"""The register file: the bus slave generated from the register map (:mod:`.regmap`).

Timing (``t`` = the clock ``bus.stb`` rises for an access)::

    t      stb, addr, we, w_data (held by the master until ack)
           write: staging / immediate register loaded at the end of t
    t + 1  ack, status, r_data; a strobe register's pulse; the master may start the next
           access in t + 2 (stb is still high in t + 1 and is not taken as a new access)

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
        Register bus from the host link (see :mod:`.bus`); ``ack`` one clock after ``stb``.
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
        ``bus.r_data`` in the ack clock of a window read.

    Attributes
    ----------
    latency : int
        Clocks from ``stb`` to ``ack``: 1.
    commit_latency : int
        Clocks from a ``commit`` (lock low) to the new active values: 1.

    Raises
    ------
    TypeError
        ``regmap`` is not a :class:`~.regmap.RegMap`.
    """

    latency = 1
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
        r_data = Signal(DATA_WIDTH)
        win_hit = {w.name: Signal(name=f"{w.name}_hit") for w in self._regmap.windows}
        m.d.comb += access.eq(bus.stb & ~bus.ack)
        m.d.sync += bus.ack.eq(access)

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

        with m.If(access):
            m.d.sync += [
                bus.status.eq(Status.BAD_ADDRESS),
                r_data.eq(0),
                *(hit.eq(0) for hit in win_hit.values()),
            ]
            with m.Switch(bus.addr):
                for addr, r, k in self._regmap.words():
                    with m.Case(addr):
                        self._word(m, r, k, held[r.name], r_data)
                for w in self._regmap.windows:
                    pattern = format(w.addr >> w.addr_width, f"0{16 - w.addr_width}b")
                    with m.Case(pattern + "-" * w.addr_width):
                        with m.If(bus.we):
                            m.d.sync += bus.status.eq(Status.READ_ONLY)
                        with m.Else():
                            m.d.sync += [bus.status.eq(Status.OK), win_hit[w.name].eq(1)]
        return m

    def _word(self, m, r, k, held, r_data):
        """The access logic of word ``k`` of register ``r`` (inside its address ``Case``)."""
        bus = self.bus
        lo, hi = r.word_slice(k)
        with m.If(bus.we):
            if r.access is Access.STROBE:
                m.d.sync += [bus.status.eq(Status.OK), getattr(self, r.name).eq(bus.w_data[0])]
            elif r.access is Access.RW:
                m.d.sync += [bus.status.eq(Status.OK), held[lo:hi].eq(bus.w_data[:hi - lo])]
            else:
                m.d.sync += bus.status.eq(Status.READ_ONLY)
        with m.Else():
            m.d.sync += bus.status.eq(Status.OK)
            if isinstance(held, int):           # constants (and strobes: 0)
                m.d.sync += r_data.eq(r.read_word(held, k))
            else:
                word = held[lo:hi]
                if r.signed and k == r.words - 1:
                    word = word.as_signed()     # sign-extended to the bus width
                m.d.sync += r_data.eq(word)
