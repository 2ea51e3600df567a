# Ref: issue 5 item 3 (trace buffer for the paper's Fig. 8/9 from real hardware)
"""Trace buffer ("scope"): chosen signals captured at loop rate into block RAM.

``channels`` channels, each selecting one of the named ``sources`` by its ``sel`` register,
record one sample per ``decim + 1`` strobes of ``strobe`` (the loop rate) into a circular buffer
of ``depth`` samples per channel: one single-port RAM of ``channels · depth`` words of ``width``
bits (4 × 1024 × 16 bit = 64 Kbit by default, the paper's RAM), word ``channel · depth + ring
slot``. ``ram`` chooses it: ``"bram"`` (default) an :class:`~amaranth.lib.memory.Memory` (block
RAM; 16 ``SB_RAM40_4K`` on the iCE40), ``"ice40_spram"`` one iCE40 UP5K ``SB_SPRAM256KA``
(16 K × 16, an :class:`~amaranth.hdl.Instance`: synthesis only, the simulators cannot run it).
Both behave the same clock for clock (below), except that the SPRAM's contents are undefined
until written, where the Memory starts at 0.

**Sample word.** Each source is MSB-aligned to ``width`` bits: a wider source keeps its top
``width`` bits (truncated, i.e. floored: the Q format's scale is kept, its LSBs dropped), a
narrower one is padded with zeros below. A Q1.31 speed thus reads as Q1.15 of N_FS, a Q1.15
current as itself, a BinaryAngle(16) as itself. The bits are stored raw; the reader knows from
the source whether they are signed.

**One source multiplexer, time-shared.** A sample is taken over ``channels`` consecutive clocks:
channel ``c`` records its source ``c`` clocks after the taken strobe (the strobe's clock for
channel 0), through one source multiplexer, into its own lane of the RAM word (a write-enable per
lane). Sources that hold their value for ``channels`` clocks after the strobe (all the current
loop's outputs, the references, the M/T speed and the ADC code in the top) read as if sampled
together; a source changing every clock (the measured θ) is read ``c`` clocks late in channel
``c``. While a sample's channels are being taken (the ``channels − 1`` clocks after a taken
strobe) further strobes are ignored entirely (neither taken nor counted by the decimation).
(Four independent multiplexers cost ≈ 180 LUT4 each on the iCE40; see docs/AREA.md.) So strobes
must come at least ``strobe_interval`` = ``channels`` clocks apart to be all seen; the top
strobes once per current-loop computation (one per PWM period, ≥ 5 000 clocks).

**Write register.** The multiplexer's output is registered together with the write enable and
the channel, and written into the RAM one clock after it was taken (channel ``c`` in clock
``c + 1`` after the strobe's): the RAM's data input comes from a flip-flop, not from sources
spread over the whole design. The word's ring slot is the write pointer itself, which steps in
the clock that writes a sample's last channel (or the last one before an ``arm``), not at the
taken strobe: the reads it translates in between all fall in write clocks and read 0 (below). ``done`` waits until the last channel of the last sample is in the
RAM (``write_clocks`` = ``channels + 1`` clocks from the strobe). ``arm`` abandons the channels
not yet taken; one taken in the clock before ``arm`` still reaches the RAM in ``arm``'s clock.

**Sources read from a RAM** (``ram_sources``; docs/AREA.md, "Session 11: engine status").
Sources held in another block's RAM rather than in flip-flops (the loop engine's status,
``EngineCurrentLoop(status="ram")``) are not members of ``src``: the channel that samples one
in clock ``c`` puts its position in ``ram_sources`` on ``ram_rd.addr`` in ``c``, and the RAM's
synchronous read gives the value the source had in ``c`` on ``ram_rd.data`` in ``c + 1``,
where it takes the place of the write register's data. The sample word and every timing above
are unchanged: such a source reads exactly as if it were a member of ``src``.

**Capture** (``state``: :class:`ScopeState`)::

    arm ─► PRE: samples go into the ring; once `pretrigger` of them are in (pre_full), a trigger
           event (force, or trigger with trig_src = EXTERNAL) is accepted; earlier ones are ignored
        ─► POST: the first sample taken at or after the trigger clock is the trigger sample; with
           it, depth − pretrigger samples are taken
        ─► IDLE, done = 1: the ring holds exactly `pretrigger` samples before the trigger sample,
           the trigger sample and the samples after it (depth in all).

``arm`` (a strobe) restarts a capture at any time; the clock of ``arm`` takes no sample; it
latches ``sel``, ``decim``, ``pretrigger`` and ``trig_src`` for the whole capture and restarts the
decimation (the first strobe after ``arm`` is sampled). ``force`` (host strobe) triggers whatever
``trig_src`` says.

**Read-back** (the register file maps it as a window): ``rd_addr = channel · depth + index``,
``index`` 0 being the oldest sample of the capture (index ``pretrigger`` is the trigger sample);
``rd_data`` holds the sample one clock later (1-clock latency, as a synchronous block-RAM read).
The index is translated by the write pointer (``(index + wr_ptr) mod depth``), so the capture
reads back in time order without the host knowing where the ring starts. A channel number
≥ ``channels`` reads 0. Reading while a capture runs returns the ring as it stands, except that
the RAM has one port: a read in a clock in which a channel is written (the ``channels`` clocks
from the one after a taken strobe) reads 0 (the SPRAM's output is undefined after a write
cycle); a read in the taken strobe's own clock is undisturbed. After ``done`` nothing is
written, so a read-back of a complete capture is never affected.
"""

from collections.abc import Mapping

from amaranth.hdl import (C, Cat, ClockSignal, Instance, Module, Mux, Shape, Signal, Value,
                          signed, unsigned)
from amaranth.lib import data, wiring
from amaranth.lib.memory import Memory, ReadPort
from amaranth.lib.wiring import In, Out
from amaranth.utils import ceil_log2

from .fixed import check_bool, check_choice, is_int
from .regmap import ScopeState, TriggerSource

__all__ = ["Scope", "ScopeState", "TriggerSource", "DEFAULT_SOURCES", "RAMS"]

#: ``Scope(ram=…)`` choices: a generic :class:`~amaranth.lib.memory.Memory` (block RAM), or
#: the iCE40 UP5K's single-port 16 K × 16 ``SB_SPRAM256KA``.
RAMS = ("bram", "ice40_spram")

#: Words and bits of one ``SB_SPRAM256KA``.
SPRAM_DEPTH, SPRAM_WIDTH = 16384, 16

#: Default source list (select code = position): the top drives these members of ``src``.
DEFAULT_SOURCES = {
    "speed": signed(32),        # Q1.31 of N_FS (M/T)
    "speed_ref": signed(32),    # Q1.31 of N_FS
    "i_d": signed(16),          # Q1.15 of I_FS
    "i_q": signed(16),
    "i_d_ref": signed(16),
    "i_q_ref": signed(16),
    "i_alpha": signed(16),
    "i_beta": signed(16),
    "u_d": signed(16),          # Q1.15 of (2/3)·U_dc
    "u_q": signed(16),
    "u_alpha": signed(16),
    "u_beta": signed(16),
    "theta": unsigned(16),      # BinaryAngle(16)
    "u_dc": signed(16),         # ADC code
}


def check_scope(sources, channels, depth, width, decim_width, ram="bram"):
    """Validate the :class:`Scope` parameters; returns the sources as a dict of shapes."""
    ok = isinstance(sources, Mapping) and len(sources) > 0
    shapes = {}
    if ok:
        for name, shape in sources.items():
            try:
                shape = Shape.cast(shape)
            except TypeError:
                ok = False
                break
            if not (isinstance(name, str) and name.isidentifier()) or not 1 <= shape.width <= 64:
                ok = False
                break
            shapes[name] = shape
    if not ok:
        raise TypeError(f"Scope sources must be a non-empty dict of names to shapes of 1 to 64 "
                        f"bits, not {sources!r}")
    if not is_int(channels) or not 1 <= channels <= 16:
        raise TypeError(f"Scope channels must be an integer from 1 to 16, not {channels!r}")
    if (not is_int(depth) or not 16 <= depth <= 65536) or depth & (depth - 1):
        raise TypeError(f"Scope depth must be a power of two from 16 to 65536, not {depth!r}")
    if not is_int(width) or not 1 <= width <= 32:
        raise TypeError(f"Scope width must be an integer from 1 to 32, not {width!r}")
    if not is_int(decim_width) or not 1 <= decim_width <= 32:
        raise TypeError(f"Scope decim_width must be an integer from 1 to 32, "
                        f"not {decim_width!r}")
    check_choice("Scope", "ram", ram, RAMS)
    if ram == "ice40_spram" and (width > SPRAM_WIDTH or channels * depth > SPRAM_DEPTH):
        raise ValueError(f"Scope ram 'ice40_spram' holds at most {SPRAM_DEPTH} words of "
                         f"{SPRAM_WIDTH} bits, not channels · depth = {channels * depth} words "
                         f"of width {width} bits")
    return shapes


class Scope(wiring.Component):
    """Trace buffer with pre-trigger, decimation and a read-back window (module docstring).

    Parameters
    ----------
    sources : dict of str → shape
        The signals a channel can select, in select-code order (:data:`DEFAULT_SOURCES`).
    channels : int
        Number of channels, 1 … 16.
    depth : int
        Samples per channel, a power of two, 16 … 65536.
    width : int
        Bits per sample, 1 … 32.
    decim_width : int
        Width of ``decim``, 1 … 32.
    ram : str
        ``"bram"`` (an :class:`~amaranth.lib.memory.Memory`) or ``"ice40_spram"`` (one
        ``SB_SPRAM256KA``: ``width`` ≤ 16 and ``channels · depth`` ≤ 16 384; synthesis only).
    ram_sources : tuple of str
        Sources of one shape read through ``ram_rd`` (module docstring) rather than ``src``,
        in their RAM's word order. Default ``()``.
    down_counts : bool
        The pre-trigger fill and the samples after the trigger counted down to zero (no compare
        of a fill count with the pre-trigger count, no ``~pre + 1`` adder: the iCE40's form,
        docs/AREA.md §7.70); ``False`` (default): a fill count compared with it and a post
        count loaded from ``~pre`` or ``~pre + 1`` (fewer LUT6 where carry chains are cheap,
        Spartan-7). The same behaviour clock for clock.

    Members
    -------
    src : In(StructLayout(sources))
        The source signals, one field per name (not those of ``ram_sources``).
    ram_rd : In(ReadPort.Signature(addr_width=max(1, ceil_log2(len(ram_sources))), shape))
        Only with ``ram_sources``: ``addr`` (out) the position in ``ram_sources`` of the
        source sampled in this clock; ``data`` (in) that source's value of the clock before
        (a synchronous read port of the RAM, the word before a write in the same clock).
    sel : In(ArrayLayout(unsigned(sel_width), channels))
        Source code of each channel (latched at ``arm``); a code ≥ ``len(sources)`` records 0.
    strobe : In(1)
        Loop-rate sample strobe; strobes within ``channels − 1`` clocks after a taken one are
        ignored (module docstring).
    decim : In(unsigned(decim_width))
        One sample per ``decim + 1`` strobes (latched at ``arm``).
    pretrigger : In(unsigned(log2(depth)))
        Samples kept before the trigger sample, 0 … depth − 1 (latched at ``arm``).
    trig_src : In(TriggerSource)
        Latched at ``arm``.
    arm, force, trigger : In(1)
        Strobes: start a capture; host trigger; external trigger event (e.g.
        :attr:`Servo.ref_step`).
    state : Out(ScopeState)
    done : Out(1)
        A capture is complete, its last sample's channels all written (cleared by ``arm``).
    pre_full : Out(1)
        In PRE with the pre-trigger part full: a trigger now is accepted.
    rd_addr : In(unsigned(addr_width))
        ``channel · depth + index`` (``addr_width = ceil_log2(channels) + log2(depth)``).
    rd_data : Out(unsigned(width))
        The sample at ``rd_addr`` of the previous clock; 0 if a channel was written in that clock.

    Attributes
    ----------
    read_latency : int
        1: ``rd_data`` shows the sample addressed in the previous clock.
    write_clocks : int
        ``channels + 1``: clocks from a taken strobe to its last channel in the RAM (channel
        ``c`` sampled in clock ``c`` after the strobe's, written into the RAM in clock
        ``c + 1``).
    strobe_interval : int
        ``channels``: the smallest strobe spacing, in clocks, at which no strobe is ignored.
    ram : str
        The ``ram`` parameter.
    source_names : tuple of str
        Names in select-code order.
    sel_width, addr_width, memory_bits : int
    """

    def __init__(self, *, sources=DEFAULT_SOURCES, channels=4, depth=1024, width=16,
                 decim_width=16, ram="bram", ram_sources=(), down_counts=False):
        shapes = check_scope(sources, channels, depth, width, decim_width, ram)
        self._down_counts = check_bool("Scope", "down_counts", down_counts)
        if (not isinstance(ram_sources, tuple) or len(set(ram_sources)) != len(ram_sources)
                or not all(n in shapes for n in ram_sources)
                or len({shapes[n] for n in ram_sources}) > 1):
            raise ValueError(f"Scope ram_sources must be a tuple of distinct sources of one "
                             f"shape, not {ram_sources!r}")
        self._ram_sources = ram_sources
        self._ram = ram
        self._sources = shapes
        self._channels = channels
        self._depth = depth
        self._width = width
        self._decim_width = decim_width
        self._abits = depth.bit_length() - 1
        self._sel_width = max(ceil_log2(len(shapes)), 1)
        self._cbits = ceil_log2(channels)
        extra = {}
        if ram_sources:
            extra["ram_rd"] = In(ReadPort.Signature(
                addr_width=max(1, ceil_log2(len(ram_sources))), shape=shapes[ram_sources[0]]))
        super().__init__({
            **extra,
            "src": In(data.StructLayout({n: shape for n, shape in shapes.items()
                                         if n not in ram_sources})),
            "sel": In(data.ArrayLayout(unsigned(self._sel_width), channels)),
            "strobe": In(1),
            "decim": In(unsigned(decim_width)),
            "pretrigger": In(unsigned(self._abits)),
            "trig_src": In(TriggerSource),
            "arm": In(1),
            "force": In(1),
            "trigger": In(1),
            "state": Out(ScopeState),
            "done": Out(1),
            "pre_full": Out(1),
            "rd_addr": In(unsigned(self._cbits + self._abits)),
            "rd_data": Out(unsigned(width)),
        })

    sources = property(lambda self: dict(self._sources))
    source_names = property(lambda self: tuple(self._sources))
    channels = property(lambda self: self._channels)
    depth = property(lambda self: self._depth)
    width = property(lambda self: self._width)
    decim_width = property(lambda self: self._decim_width)
    sel_width = property(lambda self: self._sel_width)
    addr_width = property(lambda self: self._cbits + self._abits)
    memory_bits = property(lambda self: self._channels * self._depth * self._width)
    read_latency = property(lambda self: 1)
    write_clocks = property(lambda self: self._channels + 1)
    strobe_interval = property(lambda self: self._channels)
    ram = property(lambda self: self._ram)
    ram_sources = property(lambda self: self._ram_sources)
    down_counts = property(lambda self: self._down_counts)

    def _aligned(self, name):
        """Source ``name`` MSB-aligned to ``width`` bits (raw, unsigned)."""
        return self._align(self.src[name])

    def _align(self, value):
        """``value`` MSB-aligned to ``width`` bits (raw, unsigned)."""
        value = Value.cast(value).as_unsigned()
        sw, w = len(value), self._width
        return value[sw - w:] if sw >= w else value << (w - sw)

    def _spram(self, ports):
        """The ``SB_SPRAM256KA`` cell with ``ports`` (``Instance`` keyword arguments, yosys
        ``ice40/cells_sim.v`` names). A test replaces it with a simulation stand-in."""
        return Instance("SB_SPRAM256KA", **ports)

    def elaborate(self, platform):
        m = Module()
        n, depth, ab = self._channels, self._depth, self._abits
        width = self._width

        # The channels' source codes, latched at arm and rotated by one channel with each step
        # of `phase`: sel[0] is always the code of the channel sampled in this clock (no
        # `sel[phase]` multiplexer in front of the source multiplexer).
        sel = Signal.like(self.sel)
        # Latched at arm and read only while capturing: no reset needed (its power-up value,
        # all ones, is from the decimation's former carry-chain compare, AREA.md §7.50; the
        # equality that replaced it takes either polarity).
        decim = Signal.like(self.decim, init=(1 << len(self.decim)) - 1, reset_less=True)
        pre = Signal.like(self.pretrigger)
        trig_src = Signal(TriggerSource)
        state = Signal(ScopeState)
        done = Signal()
        # The ring slot of the sample being taken and written: it steps when the RAM writes a
        # sample's last channel (or arm cuts a sample short), not at the take, so it stays
        # the sample's slot while its channels are written (no copy of it, no multiplexer in
        # front of the write address). Only reads see it between the take and that write,
        # and those read 0 (wr_en is high in all of those clocks).
        wr_ptr = Signal(unsigned(ab))
        down = self._down_counts
        if down:
            # PRE: pre-trigger samples still wanted, `pre − taken` down to 0 (full: 0; no
            # compare of a fill count with `pre`). POST: samples left = post_left + post_extra
            # (post_extra: the trigger clock took no sample, one more; no `~pre + 1` adder);
            # post_left holds ~pre from arm on (pre itself is then not kept).
            need = Signal(unsigned(ab))
            post_left = Signal(unsigned(ab))
            post_extra = Signal()
        else:
            # PRE: samples taken, saturating at depth − 1 (full: filled ≥ pre). POST: left.
            filled = Signal(unsigned(ab))
            post_left = Signal(unsigned(ab + 1))
        dcount = Signal.like(self.decim)
        dzero = Signal(init=1)          # dcount == 0, registered (off the RAM-address path)
        # Channel being sampled: 0 while idle (channel 0 goes with the taken strobe), 1 … n − 1
        # in the clocks after it. The RAM writes each channel a clock later (wr_en, wr_chan,
        # wr_data) in ring slot wr_ptr.
        phase = Signal(range(n))
        busy = phase != 0
        wr_en = Signal()                # the RAM writes (a channel of the clock before's sample)

        capturing = state != ScopeState.IDLE
        strobe = Signal()
        take = Signal()
        full = Signal()
        event = Signal()
        write = Signal()
        m.d.comb += [
            strobe.eq(self.strobe & ~busy),
            take.eq(strobe & capturing & dzero & ~self.arm),
            write.eq((take | busy) & ~self.arm),
            full.eq(need == 0 if down else filled >= pre),
            event.eq(self.force | (self.trigger & (trig_src == TriggerSource.EXTERNAL))),
            self.state.eq(state),
            self.done.eq(done & ~busy & ~wr_en),
            self.pre_full.eq((state == ScopeState.PRE) & full),
        ]

        # Sample word: one multiplexer, the source code of the channel sampled in this clock.
        names = self.source_names
        sample = Signal(unsigned(width))
        ram_src = Signal()              # the source sampled in this clock is in a RAM
        with m.Switch(sel[0]):
            for code, name in enumerate(names):
                with m.Case(code):
                    if name in self._ram_sources:
                        m.d.comb += [ram_src.eq(1),
                                     self.ram_rd.addr.eq(self._ram_sources.index(name))]
                    else:
                        m.d.comb += sample.eq(self._aligned(name))
        if n > 1:
            with m.If(self.arm):
                m.d.sync += phase.eq(0)
            # `phase` steps n times per sample (0 → 1 → … → n − 1 → 0): so does the rotation, and
            # sel is back in channel order when the sample is complete.
            rotated = Cat(*(sel[(c + 1) % n] for c in range(n)))
            with m.Elif(take):
                m.d.sync += [phase.eq(1), sel.eq(rotated)]
            with m.Elif(busy):
                m.d.sync += [phase.eq(Mux(phase == n - 1, 0, phase + 1)), sel.eq(rotated)]

        # The write of channel `phase` (word `channel · depth + ring slot`), registered: the
        # RAM's data, write enable and channel come from flip-flops, one clock after the
        # multiplexer (the sources reach the multiplexer from all over the design; the RAM's
        # data input is a long route), the slot from wr_ptr, which holds until that write.
        words = n * depth
        wr_chan = Signal.like(phase)
        wr_data = Signal(unsigned(width))
        m.d.sync += [
            wr_en.eq(write),
            wr_chan.eq(phase),
            wr_data.eq(sample),
        ]
        wr_addr = Cat(wr_ptr, wr_chan)
        if self._ram_sources:
            # A source in a RAM: its read data (the value of the clock before) in place of the
            # write register's (0 for it).
            ram_q = Signal()
            m.d.sync += ram_q.eq(ram_src)
            wr_word = Signal(unsigned(width))
            m.d.comb += wr_word.eq(wr_data | Mux(ram_q, self._align(self.ram_rd.data), 0))
            wr_data = wr_word
        # One RAM port: the registered write, or else the read-back window, its index translated
        # by the write pointer.
        addr = Signal(range(words))
        r_addr = Cat((self.rd_addr[:ab] + wr_ptr)[:ab], self.rd_addr[ab:])
        m.d.comb += addr.eq(Mux(wr_en, wr_addr, r_addr))
        if self._ram == "bram":
            m.submodules.mem = mem = Memory(shape=unsigned(width), depth=words, init=[])
            wr = mem.write_port()
            rd = mem.read_port()
            m.d.comb += [
                wr.addr.eq(addr), wr.data.eq(wr_data), wr.en.eq(wr_en),
                rd.addr.eq(addr),
            ]
            word = rd.data
        else:
            # Single port, always selected and powered, all four nibbles written; DATAOUT is
            # registered: the word at ADDRESS one clock later, undefined after a write cycle.
            address = Signal(ceil_log2(SPRAM_DEPTH))
            datain = Signal(SPRAM_WIDTH)
            word = Signal(SPRAM_WIDTH)
            m.d.comb += [address.eq(addr), datain.eq(wr_data)]
            m.submodules.spram = self._spram(dict(
                i_ADDRESS=address, i_DATAIN=datain, i_MASKWREN=C(0b1111, 4), i_WREN=wr_en,
                i_CHIPSELECT=C(1, 1), i_CLOCK=ClockSignal(), i_STANDBY=C(0, 1),
                i_SLEEP=C(0, 1), i_POWEROFF=C(1, 1), o_DATAOUT=word))
        # Read-back: 0 for a channel ≥ channels and in the clock after a write.
        valid_q = Signal()
        m.d.sync += valid_q.eq(~wr_en & (self.rd_addr[ab:] < n))
        m.d.comb += self.rd_data.eq(Mux(valid_q, word[:width], 0))

        # The slot steps with the RAM's write of a sample's last channel (channel n − 1, then
        # phase is back at 0), or of the last one before an arm abandoned the rest.
        with m.If(wr_en & (~busy | self.arm)):
            m.d.sync += wr_ptr.eq(wr_ptr + 1)
        with m.If(self.arm):
            m.d.sync += [
                state.eq(ScopeState.PRE),
                done.eq(0),
                *([] if down else [filled.eq(0)]),  # (down_counts: need, post_left below)
                dcount.eq(0),
                dzero.eq(1),
                sel.eq(self.sel),
                decim.eq(self.decim),
                *([] if down else [pre.eq(self.pretrigger)]),
                trig_src.eq(self.trig_src),
            ]
        with m.Else():
            with m.If(strobe & capturing):
                # dcount runs 0 … decim (decim holds from arm on), so `dcount >= decim` is
                # `dcount == decim`: an equality in LUTs, no carry chain.
                wrap = dcount == decim
                m.d.sync += [dcount.eq(Mux(wrap, 0, dcount + 1)), dzero.eq(wrap)]
            with m.If(state == ScopeState.PRE):
                # depth − pre − take samples are left. No subtractor behind `take` (a late
                # signal: strobe, phase, decimation): with pre < depth, depth − pre − 1 = ~pre,
                # so the count is ~pre or ~pre + 1 (down_counts: ~pre and post_extra), and it is
                # zero only if `take` and pre = depth − 1 (all ones).
                with m.If(event & full):
                    with m.If(take & ((post_left == 0) if down else pre.all())):
                        m.d.sync += [state.eq(ScopeState.IDLE), done.eq(1)]
                    with m.Else():
                        m.d.sync += state.eq(ScopeState.POST)
                        if down:
                            m.d.sync += post_extra.eq(~take)
                        else:
                            m.d.sync += post_left.eq(Mux(take, ~pre, ~pre + 1))
                if not down:
                    with m.Elif(take & (filled != depth - 1)):
                        m.d.sync += filled.eq(filled + 1)
            with m.Elif(state == ScopeState.POST):
                with m.If(take):
                    if down:
                        with m.If(post_extra):
                            m.d.sync += post_extra.eq(0)
                        last = (post_left[1:] == 0) & (post_left[0] ^ post_extra)
                    else:
                        m.d.sync += post_left.eq(post_left - 1)
                        last = post_left == 1
                    with m.If(last):
                        m.d.sync += [state.eq(ScopeState.IDLE), done.eq(1)]
        if down:
            # The two down-counters: loaded at arm (need with the pre-trigger count,
            # post_left with ~pretrigger: nothing else writes it before POST, so no copy of
            # pre is kept), need − 1 for each take in PRE while not full, post_left − 1 for
            # each take in POST but the extra one. Each as one LUT a bit on its carry: the
            # count's step `dec` (0 in the arm clock: `take` excludes it) is both the adder's
            # operand on every bit (−1 or 0) and the select of the load, so the LUT has four
            # inputs (the load bit, the count bit, dec, the carry) and packs with its carry
            # and flip-flop (iCE40: one logic cell a bit, not two; docs/AREA.md §7.79). The
            # steps are kept wires: one net for both uses.
            keep = {"keep": 1}
            dec = Signal(attrs=keep)
            post_dec = Signal(attrs=keep)
            m.d.comb += [
                dec.eq((state == ScopeState.PRE) & take & ~full),
                post_dec.eq((state == ScopeState.POST) & take & ~post_extra),
            ]
            with m.If(self.arm | dec):
                m.d.sync += need.eq(Mux(dec, need + dec.replicate(ab), self.pretrigger))
            with m.If(self.arm | post_dec):
                m.d.sync += post_left.eq(Mux(post_dec, post_left + post_dec.replicate(ab),
                                             ~self.pretrigger))
        return m
