# Ref: docs/PROTOCOL.md (framing, commands, status codes, resynchronisation); hdl/bus.py
"""The host link: UART bytes → COBS frames with CRC-16 → register bus accesses → reply frames.

:class:`LinkCore` speaks the protocol on byte streams (wire bytes, COBS encoded, 0x00 delimited);
:class:`HostLink` puts :class:`~foc_servo.hdl.uart.UartRx` / :class:`~foc_servo.hdl.uart.UartTx`
in front of it. The protocol constants come from :mod:`foc_servo.host.protocol`, the pure-Python
golden model of the framing, so gateware and host cannot disagree on them.

A request is buffered whole (header in registers, which keep the previous frame's bytes until
overwritten, or with ``compact`` its first four bytes in a word of the buffer; data words in a
``max_words``-deep :class:`~amaranth.lib.memory.Memory`) while its CRC runs; only after the
frame's closing 0x00 are the CRC, the length, the command and every address of the burst
checked against ``address_map``, and only then does the first bus access start, with
``bus.lock`` high until the last. A malformed frame therefore never writes anything, and a burst
writes all its words or none.
"""

from amaranth.hdl import Assert, Cat, Const, Module, Mux, Shape, Signal, Value
from amaranth.lib import stream, wiring
from amaranth.lib.memory import Memory
from amaranth.lib.wiring import In, Out

from ..host.protocol import CRC_BYTES, REPLY_HEADER, REQUEST_HEADER, Command, ReplyStatus
from .bus import ADDR_WIDTH, RegBusSignature, Status
from .fixed import check_bool
from .uart import UartRx, UartTx, uart_params

__all__ = ["normalize_address_map", "address_decode", "hostlink_params", "crc16_byte", "LinkCore",
           "HostLink"]

_ADDR_SPACE = 1 << ADDR_WIDTH


def normalize_address_map(address_map):
    """Validate an address map and merge adjacent regions of the same access.

    Parameters
    ----------
    address_map : iterable of (int, int, bool) or None
        ``(start, stop, writable)`` word-address regions, ``0 <= start < stop <= 0x10000``, not
        overlapping. ``None`` means the whole address space, writable.

    Returns
    -------
    tuple of (int, int, bool)
        Sorted, adjacent regions of equal access merged.

    Raises
    ------
    TypeError
        If a region is not a ``(start, stop, writable)`` tuple of two ints and a bool.
    ValueError
        If a region is empty, outside 0 … 0x10000 or overlaps another.
    """
    if address_map is None:
        return ((0, _ADDR_SPACE, True),)
    regions = []
    for region in address_map:
        if (not isinstance(region, tuple) or len(region) != 3
                or not all(isinstance(v, int) and not isinstance(v, bool) for v in region[:2])
                or not isinstance(region[2], bool)):
            raise TypeError(f"Address map region must be a (start, stop, writable) tuple of two "
                            f"integers and a bool, not {region!r}")
        start, stop, _ = region
        if not 0 <= start < stop <= _ADDR_SPACE:
            raise ValueError(f"Address map region must satisfy 0 <= start < stop <= 0x10000, "
                             f"not {region!r}")
        regions.append(region)
    regions.sort()
    merged = []
    for start, stop, writable in regions:
        if merged and start < merged[-1][1]:
            raise ValueError(f"Address map regions {merged[-1]!r} and {(start, stop, writable)!r} "
                             f"overlap")
        if merged and start == merged[-1][1] and writable == merged[-1][2]:
            merged[-1] = (merged[-1][0], stop, writable)
        else:
            merged.append((start, stop, writable))
    return tuple(merged)


def _aligned_blocks(start, stop):
    """``[start, stop)`` as the fewest aligned power-of-two blocks ``(base, log2 size)``."""
    blocks = []
    while start < stop:
        k = (start & -start).bit_length() - 1 if start else ADDR_WIDTH
        while start + (1 << k) > stop:
            k -= 1
        blocks.append((start, k))
        start += 1 << k
    return blocks


def address_decode(addr, address_map):
    """Whether the word address ``addr`` exists in ``address_map`` and whether it is writable,
    decoded from its bits: no magnitude comparisons (on the iCE40 each is a carry chain).

    Each region is split into aligned power-of-two blocks. A block of 16 words or more is one
    prefix match of the address's upper bits; smaller blocks are collected per aligned group
    of 16 words into two 16-bit maps (exists, writable) indexed by the address's 4 low bits, a
    constant function of 4 bits (one LUT4), enabled by the group's prefix match.

    Parameters
    ----------
    addr : Value
        ``ADDR_WIDTH + 1`` bits: the word address and an overflow bit (set: no such word).
    address_map : tuple
        A normalised address map (:func:`normalize_address_map`).

    Returns
    -------
    exists, writable : Value
        1-bit values.
    """
    addr = Value.cast(addr)
    exists, writable = [], []
    groups = {}                             # group of 16 words → [exists map, writable map]
    for start, stop, is_writable in address_map:
        for base, k in _aligned_blocks(start, stop):
            if k >= 4:
                hit = addr[k:] == base >> k
                exists.append(hit)
                if is_writable:
                    writable.append(hit)
            else:
                maps = groups.setdefault(base >> 4, [0, 0])
                bits = ((1 << (1 << k)) - 1) << (base & 15)
                maps[0] |= bits
                if is_writable:
                    maps[1] |= bits
    for group, (e_map, w_map) in sorted(groups.items()):
        hit = addr[4:] == group
        exists.append(hit & Const(e_map, 16).bit_select(addr[:4], 1))
        if w_map:
            writable.append(hit & Const(w_map, 16).bit_select(addr[:4], 1))
    return Cat(*exists).any(), Cat(*writable).any()


def _below(value, limit):
    """``value < limit`` for a constant ``limit``, decoded from the bits of ``value``: one
    prefix match per one bit of ``limit`` (``value`` agrees with ``limit`` above it and has a 0
    there), so LUTs only. yosys maps a magnitude comparison, even with a constant, to a carry
    chain (iCE40: a logic cell per bit, each a carry alone, and a feed-out cell)."""
    value = Value.cast(value)
    width = len(value)
    if limit <= 0:
        return Const(0, 1)
    if limit >= 1 << width:
        return Const(1, 1)
    terms = []
    for b in range(width):
        if limit >> b & 1:
            term = ~value[b]
            if b + 1 < width:
                term = term & (value[b + 1:] == limit >> (b + 1))
            terms.append(term)
    return Cat(*terms).any()


def hostlink_params(*, max_words=64, address_map=None, counter_width=16):
    """Validate the parameters shared by :class:`LinkCore`, :class:`HostLink` and the model.

    Raises
    ------
    TypeError
        If ``max_words`` is not an integer from 1 to 255 or ``counter_width`` not one from 1
        to 32; see also :func:`normalize_address_map`.
    """
    if not isinstance(max_words, int) or isinstance(max_words, bool) or not 1 <= max_words <= 255:
        raise TypeError(f"Host link max_words must be an integer from 1 to 255, not {max_words!r}")
    if (not isinstance(counter_width, int) or isinstance(counter_width, bool)
            or not 1 <= counter_width <= 32):
        raise TypeError(f"Host link counter_width must be an integer from 1 to 32, "
                        f"not {counter_width!r}")
    return {"max_words": max_words, "address_map": normalize_address_map(address_map),
            "counter_width": counter_width}


def _crc_matrix():
    """For each bit of the CRC-16/CCITT-FALSE state after one byte: the set of input bits whose
    XOR it is (0 … 15: state, 16 … 23: data byte)."""
    c = [{i} for i in range(16)]
    for k in range(8):                      # data bits MSB first
        fb = c[15] ^ {16 + 7 - k}
        c = [set()] + c[:15]
        for tap in (0, 5, 12):              # 0x1021
            c[tap] = c[tap] ^ fb
    return c


_CRC_MATRIX = _crc_matrix()


def crc16_byte(crc, byte):
    """CRC-16/CCITT-FALSE state after one more byte, as a 16-bit Amaranth value (a parallel XOR
    network, no loop)."""
    inputs = Cat(crc, byte)
    bits = []
    for terms in _CRC_MATRIX:
        acc = Const(0, 1)
        for t in sorted(terms):
            acc = acc ^ inputs[t]
        bits.append(acc)
    return Cat(*bits)


#: Status counters of the link, in port order.
COUNTERS = ("frames_ok", "crc_errors", "framing_errors", "rejected", "dropped")


#: The counters that count once per reply (in the REPLY state, after the frame's accesses).
REPLY_COUNTERS = ("frames_ok", "crc_errors", "framing_errors", "rejected")


def _check_strobed(owner, strobed):
    if (not isinstance(strobed, tuple) or len(set(strobed)) != len(strobed)
            or not all(name in COUNTERS for name in strobed)):
        raise ValueError(f"{owner} strobed must be a tuple of distinct names from "
                         f"{COUNTERS!r}, not {strobed!r}")
    return strobed


def _counter_members(width, strobed=()):
    """The link's status counters (wrapping, ``width`` bits), shared by LinkCore and HostLink;
    a ``<name>_strobe`` for those in ``strobed``."""
    return {(f"{name}_strobe" if name in strobed else name): Out(1 if name in strobed else width)
            for name in COUNTERS}

class LinkCore(wiring.Component):
    """Protocol engine of the host link on wire-byte streams (no UART).

    Receives COBS frames delimited by 0x00, checks them, runs the bus accesses and sends one
    reply frame (COBS, then 0x00) per nonempty frame received in the ``RECV`` state; see
    ``docs/PROTOCOL.md`` for the reply each kind of frame gets. Bytes that arrive while the
    link is busy (checking, accessing or replying) cannot be taken: the UART wrapper reports them
    on ``rx_lost`` and the link then ignores everything up to the next 0x00.

    Parameters
    ----------
    max_words : int
        Longest burst, 1 … 255 words; also the depth of the frame buffer (32-bit words).
    address_map : iterable of (start, stop, writable) or None
        Word-address regions that exist (see :func:`normalize_address_map`). Every address of
        a request is checked against it before the first access: outside all regions →
        BAD_ADDRESS; a write to a region with ``writable=False`` → READ_ONLY. ``None``: all of
        0 … 0xFFFF exists and is writable (the bus status still reports holes, but then a burst
        may be cut short after some writes: give the map).
    counter_width : int
        Width of the status counters (they wrap).
    strobed : tuple of str
        Counters (of :data:`COUNTERS`) not counted here: each has a ``<name>_strobe`` instead,
        for a counter elsewhere (the Top's: in the register file's staging RAM,
        ``RegisterFile(counters=...)``). A reply counter's strobe is high for one clock, the
        clock in which the counter would first hold its new value (the one after the REPLY
        state's, a register); ``dropped``'s is combinational, high in the clock in which the
        counter would count (the loss). Default ``()``.
    read_hold : bool
        The frame buffer's read address from two flags registered with the state, and its read
        register held where the reply needs the same word again (the ECP5 board's choice, for
        its Fmax: no state decode or ``o.ready`` in front of the distributed-RAM read); default
        ``False``: the address chosen from the state in every clock (fewer iCE40 cells). The
        same replies, accesses and timing either way; ``bus.w_data`` outside accesses (no
        meaning, the bus protocol) may differ.
    compact : bool
        The iCE40's forms (fewer logic cells, longer paths; the ECP5's 100 MHz paths run through
        the link, docs/AREA.md §7.62, §7.75): the reply's zero test on the selected byte; the
        COBS code byte counted in place, up and down by one adder; the reply byte index held
        as j − 4, the CRC bytes in the header's first two byte slots; the CRC and SCAN passes'
        end tests on j itself (not registered); the buffer read at j's next value; the bus's
        ``stb``, ``we`` and ``lock`` decoded from the state; the request header's cmd, seq and
        addr bytes in a word of the frame buffer (its header word, above the data words: the
        buffer is then ``2**ceil_log2(max_words + 1)`` words deep), read back as the reply's
        first two bytes and by the checks, cmd and seq cleared there in CHECK (docs/AREA.md
        §7.85). Default ``False``; not with ``read_hold``. The same replies and accesses in the
        same clocks either way (``bus.w_data`` outside accesses aside, as above).

    Members
    -------
    i : In(stream.Signature(8))
        Wire bytes from the host. ``i.ready`` is high in the ``RECV`` state (taking a byte per
        clock), low while the link is busy with a frame.
    rx_lost : In(1)
        Strobe: a byte arrived while ``i.ready`` was low and was lost. The link skips the rest of
        that frame (up to the next 0x00) without a reply and counts it in ``dropped``.
    rx_error : In(1)
        Strobe: a damaged byte (UART framing error). The frame being received gets a BAD_CRC
        reply and counts in ``framing_errors``; while the link is busy it counts as ``rx_lost``.
    o : Out(stream.Signature(8))
        Wire bytes to the host.
    bus : Out(RegBusSignature())
        Register bus master; ``lock`` is high from the first to the last access of a frame.
        ``w_data`` is the frame buffer's output: meaningful with ``stb & we`` only (the bus
        protocol), other values outside writes.
    frames_ok, crc_errors, framing_errors, rejected, dropped : Out(counter_width)
        Frames answered OK; BAD_CRC for a CRC mismatch; BAD_CRC for a damaged frame (COBS
        error, UART framing error); frames answered with BAD_LENGTH, BAD_COMMAND, BAD_ADDRESS or
        READ_ONLY; frames skipped because bytes were lost. Wrap modulo ``2**counter_width``.
        (Not those named in ``strobed``.)
    <name>_strobe : Out(1)
        Only for the counters named in ``strobed``: its count strobe.

    Attributes
    ----------
    max_frame : int
        Longest decoded request, ``5 + 4·max_words + 2`` bytes; longer ones get BAD_LENGTH.
    address_map : tuple
        The normalised address map.

    Timing: a wire byte per clock in; :meth:`access_latency` to the first access; each access
    takes ``2 + (ack delay)`` clocks (4 with :class:`~.regs.RegisterFile`, which acks two clocks
    after ``stb``); a
    reply of ``n`` decoded bytes (``4 + 4·words + 2``) takes about ``3n + 4`` clocks when the
    output never stalls (CRC pass, COBS scan, emission, one byte per clock each).
    """

    def __init__(self, *, max_words=64, address_map=None, counter_width=16, strobed=(),
                 read_hold=False, compact=False):
        p = hostlink_params(max_words=max_words, address_map=address_map,
                            counter_width=counter_width)
        self._strobed = _check_strobed("LinkCore", strobed)
        self._read_hold = check_bool("LinkCore", "read_hold", read_hold)
        self._compact = check_bool("LinkCore", "compact", compact)
        if read_hold and compact:
            raise ValueError("LinkCore read_hold and compact are exclusive (the compact form's "
                             "buffer reads at j's next value), not both True")
        self._max_words = p["max_words"]
        self._address_map = p["address_map"]
        self._counter_width = p["counter_width"]
        cw = self._counter_width
        super().__init__({
            "i": In(stream.Signature(8)),
            "rx_lost": In(1),
            "rx_error": In(1),
            "o": Out(stream.Signature(8)),
            "bus": Out(RegBusSignature()),
            **_counter_members(cw, self._strobed),
        })

    strobed = property(lambda self: self._strobed)
    read_hold = property(lambda self: self._read_hold)
    compact = property(lambda self: self._compact)
    max_words = property(lambda self: self._max_words)
    address_map = property(lambda self: self._address_map)
    counter_width = property(lambda self: self._counter_width)

    @property
    def max_frame(self):
        return REQUEST_HEADER + 4 * self._max_words + CRC_BYTES

    @staticmethod
    def access_latency(count):
        """Clocks from the acceptance of a request's closing 0x00 to ``bus.stb`` of its first
        access: ``count + 3`` (a check clock, one address check per word, a buffer read)."""
        return count + 3

    def elaborate(self, platform):
        m = Module()
        mw = self._max_words
        lmax = self.max_frame
        bus = self.bus

        # The read port is asynchronous with a reset-less register behind it (``rd_data``, with
        # an enable: see the reply's read below), which yosys merges into the block RAM's
        # synchronous port (its read enable); ``no_rw_check`` leaves a read of
        # the word being written undefined, so yosys does not emulate Amaranth's read-old-data
        # behaviour in the fabric (32 flip-flops and their multiplexers on the iCE40). No read
        # is used in a clock that writes its word: RECV writes word ``idx`` and reads it, a read
        # access's ack writes word ``idx`` and reads it, and the next clock (RECV, CHECK, SETUP,
        # REPLY) uses ``rd_data`` nowhere (``bus.w_data`` matters only under ``stb``); the
        # compact form's header word (below) is written in RECV while RECV reads it, and in
        # CHECK on the way to REPLY: neither next clock uses ``rd_data`` either (CHECK's comes
        # from the closing 0x00's clock, which writes nothing). In simulation the register
        # samples the old word, as the synchronous port did.
        # The compact form keeps the request header's first four bytes (cmd, seq, addr) in
        # the buffer too, in the word ``hdr_addr`` (all ones of the index's bits, above every
        # data word): the reply reads cmd and seq from there as the header's first two bytes
        # (the word of reply byte j < 4 is j's bits 2 and up, all ones), the checks read cmd
        # and addr from the read register. No flip-flops for them (iCE40: a lone flip-flop
        # each, loaded from one shared LUT per bit). The buffer is ``2**ab`` words deep then
        # (``ab`` = the bits of ``idx``: the same block RAMs for max_words ≤ 255).
        hdr_ram = self._compact
        ab = Shape.cast(range(mw + 1)).width
        hdr_addr = (1 << ab) - 1
        m.submodules.mem = mem = Memory(shape=32, depth=(1 << ab) if hdr_ram else mw, init=[],
                                        attrs={"no_rw_check": 1})
        wr = mem.write_port(granularity=8)      # request bytes land in their lane directly
        rd = mem.read_port(domain="comb")
        if hdr_ram:
            # The header word as the proof sees it (boards/prove.py, HostLinkSpec's aux
            # invariants): a read port whose data nothing in the block uses (yosys removes it).
            probe = mem.read_port(domain="comb")
            hdr_word = Signal(32)
            m.d.comb += [probe.addr.eq(hdr_addr), hdr_word.eq(probe.data)]
        rd_data = Signal(32, reset_less=True)   # the buffer's read data (the RAM's register)
        hold = self._read_hold
        if not hold:
            m.d.sync += rd_data.eq(rd.data)

        # --- receive state -----------------------------------------------------------------
        length = Signal(range(lmax + 2))        # decoded bytes, saturating at lmax + 1
        # Data bytes left in the current COBS block, plus one (1: a code byte is next): loaded
        # with the code byte itself, no subtractor in front (iCE40: a carry chain fewer).
        # ``cobs_left``, the count itself, is for the hostlink proof only (unused in a build).
        cobs_run = Signal(8, init=1)
        cobs_left = Signal(8)
        m.d.comb += cobs_left.eq(cobs_run - 1)
        cobs_ff = Signal()                      # the current block's code was 0xFF
        started = Signal()                      # a code byte has been seen in this frame
        bad = Signal()                          # damaged frame (COBS error, UART error)
        skip = Signal()                         # bytes were lost: ignore up to the next 0x00
        crc = Signal(16, init=0xFFFF)
        hdr = [Signal(8, name=f"hdr{k}") for k in range(REQUEST_HEADER)]
        cmd_in, seq_in, count_in = hdr[0], hdr[1], hdr[4]
        addr_in = Cat(hdr[2], hdr[3])
        if hdr_ram:                             # (the read register holds the header word)
            cmd_in, seq_in, addr_in = rd_data[:8], None, rd_data[16:32]
        bpos = Signal(2)                        # byte lane of the next data byte (little endian)
        if self._compact:
            # The lane as length − 5 mod 4 (the data bytes are bytes 5, 6, … of the frame; only
            # used while length counts, below lmax + 1: writes stop at idx = max_words, byte
            # 5 + 4·max_words, and CHECK reads it only for a length ≤ lmax): no register.
            assert REQUEST_HEADER % 4 == 1          # (length − 5 mod 4 = length − 1 mod 4)
            bpos = Cat(~length[0], ~(length[1] ^ length[0]))

        # --- execution and reply state -----------------------------------------------------
        # Word index: of the request's data words while receiving (saturating at max_words),
        # then of the burst (< count ≤ max_words): one buffer address for both, no multiplexer.
        idx = Signal(range(mw + 1))
        is_write = Signal()
        # The reply's cmd and seq are the request's header registers (cleared in REPLY where
        # the reply carries 0).
        # info ≤ max_words (count ≤ max_words, an index < count, or max_words itself): no
        # register bits above it; the reply byte is it zero-extended.
        r_cmd, r_seq, r_info = cmd_in, seq_in, Signal(range(mw + 1))
        info8 = Signal(8)
        m.d.comb += info8.eq(r_info)
        r_status = Signal(8)
        framing = Signal()                      # the BAD_CRC is for a damaged frame
        nwords = Signal(range(mw + 1))          # data words in the reply
        # Reply byte index. The compact form holds j − 4 (modulo 2**jw; the header's bytes are
        # the top four values, above every data and CRC byte's): the buffer word of byte j is
        # then its bits 2 and up, no subtractor in front of the buffer's read address. Every
        # comparison of j below is with a value of the same form, byte selections use j mod 4
        # (the same), and the comments speak of j itself.
        jw = Shape.cast(range(REPLY_HEADER + 4 * mw + CRC_BYTES + 1)).width
        j_off = REPLY_HEADER if self._compact else 0
        j_0 = -j_off % (1 << jw)                # the register's value for j = 0
        j = Signal(jw, init=j_0)
        p = Signal.like(j)                      # COBS block start
        # nwords + 1, set with it (j − 4's form: nwords − 1, jw − 2 bits, modulo)
        if self._compact:
            nwords1, nw_step = Signal(jw - 2, name="nwords1"), -1
        else:
            nwords1, nw_step = Signal(range(mw + 2), name="nwords1"), 1
        nwords_d = nwords1 if self._compact else nwords     # the bits above dend's
        nwords_r = nwords if self._compact else nwords1     # the bits above rlen's
        # A reply of at most 253 bytes (max_words ≤ 61) has no 254-byte COBS block: then the
        # block length needs fewer bits, and the tests for such a block are constant false.
        rlen_max = REPLY_HEADER + 4 * mw + CRC_BYTES
        long_blocks = rlen_max >= 254
        # COBS block length (non-zero bytes), plus ``b1``: 1 in the compact form, where blk
        # holds the block's code byte itself (no incrementer in front of the reply byte).
        b1 = int(self._compact)
        blk = Signal(range(min(255, rlen_max + 1) + b1))
        blk_zero = Signal()                     # the block ended at a zero byte
        j_next = Signal.like(j)                 # j in the next clock

        # Comb values used by other comb logic are expressions, not signals: pysim evaluates a
        # fragment's comb statements from committed values, so each signal-to-signal link costs
        # another delta cycle every clock.
        # Index of the first CRC byte, and the reply length, as bit fields of the registers
        # ``nwords`` and ``nwords + 1`` (4 + 4·n = 4·(n + 1)): no adder in front of the reply's
        # byte selection and buffer address (100 MHz).
        # dend = 4 + 4·nwords = Cat(0b00, nwords1) itself is not needed: only its neighbours are.
        dend_m1 = Cat(Const(3, 2), nwords_d)    # dend − 1 (the CRC pass's last byte)
        dend_m2 = Cat(Const(2, 2), nwords_d)    # dend − 2 (≥ 2)
        rlen = Cat(Const(2, 2), nwords_r)       # dend + 2
        rlen_m1 = Cat(Const(1, 2), nwords_r)    # rlen − 1
        # NEXT's test for another block after a 254-byte one (blk = 254, p + blk ≠ rlen),
        # registered in SCAN's last clock (j = p + blk then). DATA counts blk down to its last
        # byte, so NEXT finds the block's end p + blk in j: no adder on p, no end register.
        more254 = Signal() if long_blocks else Const(0, 1)
        # The CRC and SCAN passes' end tests on j, registered with j (set where j_next is: to
        # the test on j's next value, j + 1 = x as j = x − 1), so no comparison of j sits in
        # front of j's own next-state multiplexer (100 MHz). crc_last: j = dend − 1, in CRC;
        # scan_end: j = rlen or j = p + 254, in SCAN. Both 0 outside those states. CRC starts
        # at j = 0 (dend − 1 ≥ 3), SCAN at j = 0 (rlen ≥ 6, p + 254 = 254), at p + blk + 1
        # after a zero (p + 254 is then farther), or at p + blk ≠ rlen after a 254-byte block.
        # In SCAN, blk counts the bytes scanned (blk = j − p): j = p + 253 is blk = 253.
        # The compact form tests j itself (no flip-flops, no state in their inputs).
        if self._compact:
            crc_last = (j + 1)[:jw] == Cat(Const(0, 2), nwords)     # j + 1 = dend (nwords1 unused)
            scan_end = (j == rlen) | (blk == 254 + b1) if long_blocks else j == rlen
        else:
            crc_last = Signal()
            scan_end = Signal()
            m.d.sync += [crc_last.eq(0), scan_end.eq(0)]

        def set_end(flag, value):
            """The registered end test ``flag`` := ``value`` (not in the compact form)."""
            if not self._compact:
                m.d.sync += flag.eq(value)

        # The reply's byte j. The buffer is read one clock ahead (below: ``rd_data`` holds the
        # word of byte j in every clock where ``jb`` is used). Which part of the reply j is in (header, data,
        # first CRC byte, second) is registered with j, from the candidate values of j_next
        # (dend is valid from CRC on, and j = 0, set in REPLY, is in the header whatever dend
        # is), so no comparison of j sits in front of the byte selection (100 MHz); the flags
        # are meaningful from CRC to DATA.
        m.d.sync += j.eq(j_next)
        j_hdr, j_dat, j_dend = Signal(init=1), Signal(), Signal()   # j < 4, j < dend, j = dend
        flags = Cat(j_hdr, j_dat, j_dend)
        flags_next = Signal.like(flags)
        m.d.sync += flags.eq(flags_next)
        if self._compact:
            # The CRC bytes (j = dend, dend + 1: j mod 4 = 0, 1) in the header's first two
            # byte slots: one selection by j mod 4 for both, no j_dend.
            # cmd and seq (j = 0, 1) are the buffer's header word's first two bytes.
            jb = Mux(j_dat & ~(j_hdr & j[1]), rd_data.word_select(j[:2], 8),
                     Cat(crc[8:], crc[:8], r_status, info8).word_select(j[:2], 8))
        else:
            jb = Mux(j_hdr, Cat(r_cmd, r_seq, r_status, info8).word_select(j[:2], 8),
                     Mux(j_dat, rd_data.word_select(j[:2], 8),       # (j − 4) mod 4 = j mod 4
                         Mux(j_dend, crc[8:], crc[:8])))
        # jb == 0 as the same selection of per-byte zero tests: the buffer word's four tests
        # run in parallel from its read register, the selection after them (SCAN's end test,
        # the whole top's 100 MHz). The compact form tests the selected byte itself.
        if self._compact:
            jb_zero = jb == 0
        else:
            hdr_zero = Cat(b == 0 for b in (r_cmd, r_seq, r_status, r_info))
            dat_zero = Cat(rd_data.word_select(k, 8) == 0 for k in range(4))
            jb_zero = Mux(j_hdr, hdr_zero.bit_select(j[:2], 1),
                          Mux(j_dat, dat_zero.bit_select(j[:2], 1),
                              Mux(j_dend, crc[8:] == 0, crc[:8] == 0)))

        def word(value):
            """Buffer address of reply byte ``value``."""
            if self._compact:
                return Value.cast(value)[2:jw]
            return (Value.cast(value) - REPLY_HEADER)[2:jw]

        # The part flags of j = 0 (a header byte; dend ≥ 4), of j + 1 from j (j < 3;
        # j + 1 < dend as j's own data flag and j ≠ dend − 1, since the flags follow j from
        # REPLY on; j = dend − 1: no adder or magnitude comparison in front), and registers
        # holding those of p (set with p): no comparison of p with dend.
        parts_0 = Const(0b011, 3)
        if self._compact:                   # j < 3: j − 4 is one of the top four but the last
            below3 = (j[2:] == (1 << (jw - 2)) - 1) & (j[:2] != 3)
        else:
            below3 = _below(j, REPLY_HEADER - 1)
        # (compact: j = dend − 1 as crc_last's j + 1 = dend, so nwords1 has no reader and
        # synthesis drops it and its decrementer)
        if self._compact:
            parts_j1 = Cat(below3, j_dat & ~crc_last, crc_last)
        else:
            parts_j1 = Cat(below3, j_dat & (j != dend_m1), j == dend_m1)
        p_flags = Signal(3)

        def set_j(value, value_parts):
            """j := ``value``, with its part flags ``value_parts``."""
            m.d.comb += [j_next.eq(value), flags_next.eq(value_parts)]

        # The buffer's read. Without ``read_hold`` the FSM gives the address of the byte j is set
        # to (``next_j``: word(j_next), or ``read``), in DATA with o.ready high byte j + 1,
        # selected last, after the state decode (o.ready comes from the transmitter's state).
        # With ``read_hold`` (the ECP5's form) no state decode or ``o.ready`` sits in front of
        # the address (the whole top's 100 MHz on the ECP5: the state → address multiplexer →
        # distributed-RAM read → ``rd_data`` path, docs/AREA.md §7.62). The address is one of
        # three, chosen by two flags registered with the state: word(j + 1) in CRC, SCAN, DATA
        # and NEXT (``rd_rep``), word(p) in CODE (``rd_at_p`` too), else ``idx`` (the accesses;
        # and whatever the RECV, CHECK, REPLY and END clocks read is unused). Where the reply
        # needs the word of j itself, the register keeps it (``rd_hold``): DATA waiting for
        # ``o.ready`` (j stays; the word of j came from CODE's word(p) or the last word(j + 1)
        # with j := j + 1) and NEXT without a zero byte (j is the block's end, so the word of j
        # again: a 254-byte block's next SCAN starts there, or END, which reads nothing).
        # ``rd_data`` is the same word as a read of word(j) in every clock that uses it;
        # ``bus.w_data`` outside accesses (meaningless, the bus protocol) may differ.
        rd_rep = Signal()
        rd_at_p = Signal()
        rd_hold = Signal()
        if hold:
            with m.If(~rd_hold):
                m.d.sync += rd_data.eq(rd.data)
            m.d.comb += rd.addr.eq(Mux(rd_rep, Mux(rd_at_p, word(p), word(j + 1)), idx))

        def next_j(value, value_parts, *, read=None):
            """:func:`set_j`; without ``read_hold`` the buffer reads reply byte ``read``
            (default ``value``)."""
            set_j(value, value_parts)
            if not hold:
                m.d.comb += rd_addr.eq(word(value if read is None else read))

        def read_flag(flag, value):
            """With ``read_hold``: the read address's ``flag`` := ``value`` (with the state)."""
            if hold:
                m.d.sync += flag.eq(value)

        # The receive state's reset for the next frame: one enable, applied after the FSM (it
        # overrides every other assignment of these registers in its clock).
        new_frame = Signal()

        def reset_frame():
            m.d.comb += new_frame.eq(1)

        # Address checks of word `idx`, decoded from the address bits. a_full = addr_in + idx
        # (ADDR_WIDTH + 1 bits: no wrap) as a register set with idx (idx = 0 with addr_in, idx
        # + 1 with a_full + 1; the header does not change from CHECK to the reply): no adder in
        # front of the decode (the whole top's 100 MHz).
        a_full = Signal(ADDR_WIDTH + 1)
        a_exists, a_writable = address_decode(a_full, self._address_map)

        def a_to(value):
            """a_full := ``value`` (a statement list)."""
            return [a_full.eq(value)]

        # The bus outputs, registered (the values the FSM's SETUP / ACCESS states imply, set
        # one clock ahead): no state decode or adder in front of the register file's address
        # decode and write enables (the whole top's 100 MHz). idx does not change in SETUP,
        # the clock before every ACCESS, and `addr` is a_full, which holds word idx's address
        # from SETUP to the access's ack. Outside ACCESS stb and we are 0 (addr is then
        # meaningless, as the bus allows); lock is high in SETUP and ACCESS.
        # The compact form decodes them from the state instead (ACCESS; SETUP or ACCESS).
        bus_stb = Signal()
        bus_lock = Signal()
        bus_we = Signal()

        def bus_to(*stmts):
            """The bus registers' ``stmts`` (none in the compact form)."""
            return [] if self._compact else list(stmts)

        m.d.comb += [bus.stb.eq(bus_stb), bus.lock.eq(bus_lock), bus.we.eq(bus_we),
                     bus.addr.eq(a_full[:ADDR_WIDTH]), bus.w_data.eq(rd_data)]

        # One CRC network for both directions: the decoded request byte while receiving, the
        # reply byte `jb` in the reply's CRC pass.
        emit = Signal()
        dbyte = Signal(8)
        crc_reply = Signal()
        crc_next = crc16_byte(crc, Mux(crc_reply, jb, dbyte))

        def counter(sig):
            m.d.sync += sig.eq(sig + 1)

        for name in self._strobed:              # (high only in the clock after REPLY's)
            if name in REPLY_COUNTERS:
                m.d.sync += getattr(self, f"{name}_strobe").eq(0)

        with m.If((self.rx_lost | self.rx_error) & ~self.i.ready & ~skip):
            m.d.sync += skip.eq(1)
            if "dropped" in self._strobed:      # (combinational: the clock it would count)
                m.d.comb += self.dropped_strobe.eq(1)
            else:
                counter(self.dropped)

        if hold:
            m.d.comb += [j_next.eq(j), flags_next.eq(flags), wr.addr.eq(idx)]
        else:
            rd_addr = Signal.like(rd.addr)
            m.d.comb += [j_next.eq(j), flags_next.eq(flags), rd_addr.eq(idx)]
            if not hdr_ram:
                m.d.comb += wr.addr.eq(idx)

        with m.FSM(name="link") as fsm:
            # blk's count (SCAN: up, DATA: down): the compact form has one adder for both.
            if self._compact:
                blk_up = blk_down = (blk + Mux(fsm.ongoing("DATA"), (1 << len(blk)) - 1, 1)
                                     )[:len(blk)]
            else:
                blk_up, blk_down = blk + 1, blk - 1
            with m.State("RECV"):
                m.d.comb += self.i.ready.eq(1)
                with m.If(self.rx_error):
                    m.d.sync += bad.eq(1)
                byte = self.i.payload
                with m.If(self.i.valid):
                    with m.If(skip):
                        with m.If(byte == 0):
                            m.d.sync += skip.eq(0)
                            reset_frame()
                    with m.Elif(byte == 0):
                        with m.If(~started & ~bad & ~self.rx_error):
                            reset_frame()                       # empty frame: ignored
                        with m.Else():
                            with m.If(cobs_run != 1):
                                m.d.sync += bad.eq(1)           # truncated COBS block
                            m.next = "CHECK"
                    with m.Elif(cobs_run == 1):                 # a code byte
                        m.d.sync += [cobs_run.eq(byte), cobs_ff.eq(byte == 0xFF),
                                     started.eq(1)]
                        m.d.comb += [emit.eq(started & ~cobs_ff), dbyte.eq(0)]
                    with m.Else():
                        m.d.sync += cobs_run.eq(cobs_run - 1)
                        m.d.comb += [emit.eq(1), dbyte.eq(byte)]
                with m.If(emit):
                    m.d.sync += crc.eq(crc_next)
                    with m.If(_below(length, lmax + 1)):
                        m.d.sync += length.eq(length + 1)
                    with m.Switch(length):
                        for k in range(REQUEST_HEADER):
                            with m.Case(k):
                                if hdr_ram and k < 4:   # (into the header word's lane k)
                                    m.d.comb += [wr.data.eq(dbyte.replicate(4)),
                                                 wr.en.eq(1 << k)]
                                else:
                                    m.d.sync += hdr[k].eq(dbyte)
                        with m.Default():
                            if not self._compact:
                                m.d.sync += bpos.eq(bpos + 1)
                            with m.If(_below(idx, mw)):
                                m.d.comb += [wr.data.eq(dbyte.replicate(4)),
                                             wr.en.eq(1 << bpos)]
                                with m.If(bpos == 3):
                                    m.d.sync += idx.eq(idx + 1)

            with m.State("CHECK"):
                count_ok = (count_in != 0) & _below(count_in, mw + 1)
                if hdr_ram:
                    # The reply's cmd and seq cleared here (REPLY clears the registers of the
                    # other form): a BAD_CRC reply, decided in this clock (bad, the CRC, fewer
                    # than 2 bytes), or a request too short to hold them. Zeros written into the
                    # header word (the clock after, REPLY, does not use the read register; the
                    # CRC pass reads the word from REPLY on).
                    bad_crc = bad | (crc != 0) | _below(length, 2)
                    m.d.comb += wr.en.eq(Cat(bad_crc | _below(length, 3),
                                             bad_crc | _below(length, 4)))
                m.d.sync += [
                    r_info.eq(0), nwords.eq(0), nwords1.eq(nw_step), idx.eq(0), *a_to(addr_in),
                    framing.eq(0),
                    is_write.eq(cmd_in == Command.WRITE),
                ]
                m.next = "REPLY"

                def status(s):
                    m.d.sync += r_status.eq(s)
                with m.If(bad):
                    status(ReplyStatus.BAD_CRC)
                    m.d.sync += framing.eq(1)
                # (The proof's --broken mutant edits this line's text.)
                with m.Elif((crc != 0) | _below(length, 2)):
                    status(ReplyStatus.BAD_CRC)
                with m.Elif(_below(length, REQUEST_HEADER + CRC_BYTES)):
                    status(ReplyStatus.BAD_LENGTH)
                with m.Elif((cmd_in != Command.PING) & (cmd_in != Command.READ)
                            & (cmd_in != Command.WRITE)):
                    status(ReplyStatus.BAD_COMMAND)
                with m.Elif(~_below(length, lmax + 1)):
                    status(ReplyStatus.BAD_LENGTH)
                with m.Elif(cmd_in == Command.PING):
                    with m.If(length == REQUEST_HEADER + CRC_BYTES):
                        status(ReplyStatus.OK)
                        m.d.sync += r_info.eq(mw)
                    with m.Else():
                        status(ReplyStatus.BAD_LENGTH)
                with m.Elif(cmd_in == Command.READ):
                    with m.If(count_ok & (length == REQUEST_HEADER + CRC_BYTES)):
                        status(ReplyStatus.OK)
                        m.next = "ACHECK"
                    with m.Else():
                        status(ReplyStatus.BAD_LENGTH)
                with m.Else():
                    # length = 5 + 4·count + 2 (≤ lmax, checked above): `count` whole words
                    # after the header and the two CRC bytes, no adder or wide compare.
                    with m.If(count_ok & (idx == count_in) & (bpos == CRC_BYTES)):
                        status(ReplyStatus.OK)
                        m.next = "ACHECK"
                    with m.Else():
                        status(ReplyStatus.BAD_LENGTH)

            with m.State("ACHECK"):
                with m.If(a_full[-1] | ~a_exists):
                    m.d.sync += [r_status.eq(ReplyStatus.BAD_ADDRESS), r_info.eq(idx)]
                    m.next = "REPLY"
                with m.Elif(is_write & ~a_writable):
                    m.d.sync += [r_status.eq(ReplyStatus.READ_ONLY), r_info.eq(idx)]
                    m.next = "REPLY"
                with m.Elif(idx + 1 == count_in):
                    m.d.sync += [idx.eq(0), *a_to(addr_in), *bus_to(bus_lock.eq(1))]
                    m.next = "SETUP"
                with m.Else():
                    m.d.sync += [idx.eq(idx + 1), *a_to(a_full + 1)]

            with m.State("SETUP"):                  # the buffer read of word idx settles
                m.d.sync += bus_to(bus_stb.eq(1), bus_we.eq(is_write))
                m.next = "ACCESS"

            with m.State("ACCESS"):                 # stb, lock, we, addr high (registers)
                with m.If(bus.ack):
                    m.d.sync += bus_to(bus_stb.eq(0), bus_we.eq(0))
                    with m.If(bus.status != Status.OK):     # the map and the slave disagree
                        m.d.sync += [
                            r_status.eq(Mux(bus.status == Status.READ_ONLY,
                                            ReplyStatus.READ_ONLY, ReplyStatus.BAD_ADDRESS)),
                            r_info.eq(idx),
                            *bus_to(bus_lock.eq(0)),
                        ]
                        m.next = "REPLY"
                    with m.Else():
                        with m.If(~is_write):
                            m.d.comb += [wr.data.eq(bus.r_data),
                                         wr.en.eq(0b1111)]
                        with m.If(idx + 1 == count_in):
                            with m.If(~is_write):
                                m.d.sync += [nwords.eq(count_in), nwords1.eq(count_in + nw_step),
                                             r_info.eq(count_in)]
                            m.d.sync += bus_to(bus_lock.eq(0))
                            m.next = "REPLY"
                        with m.Else():
                            m.d.sync += [idx.eq(idx + 1), *a_to(a_full + 1)]
                            m.next = "SETUP"

            with m.State("REPLY"):
                # The reply's cmd and seq: 0 for BAD_CRC, and where the request was too short
                # to hold them (hdr0 / hdr1 then hold CRC bytes, or nothing). Cleared here, from
                # registers, before the CRC pass reads them.
                if not hdr_ram:                 # (the header word's were cleared in CHECK)
                    with m.If((r_status == ReplyStatus.BAD_CRC) | _below(length, 3)):
                        m.d.sync += r_cmd.eq(0)
                    with m.If((r_status == ReplyStatus.BAD_CRC) | _below(length, 4)):
                        m.d.sync += r_seq.eq(0)
                # One of the four reply counters counts per reply. Each has its own
                # incrementer: on the iCE40 a counter bit is one logic cell (LUT, carry and
                # flip-flop together), less than a shared incrementer's select in front.
                is_ok, is_crc = r_status == ReplyStatus.OK, r_status == ReplyStatus.BAD_CRC
                which = Cat(is_ok, is_crc & framing, is_crc & ~framing, ~is_ok & ~is_crc)
                counted = ("frames_ok", "framing_errors", "crc_errors", "rejected")
                for w, name in zip(which, counted):
                    with m.If(w):
                        if name in self._strobed:
                            m.d.sync += getattr(self, f"{name}_strobe").eq(1)
                        else:
                            counter(getattr(self, name))
                m.d.sync += [crc.eq(0xFFFF), p.eq(j_0), p_flags.eq(parts_0), blk.eq(b1)]
                next_j(j_0, parts_0)
                read_flag(rd_rep, 1)
                m.next = "CRC"

            # One reply byte per clock in every pass: the buffer is addressed with j_next, so
            # `jb` is the byte at j in every clock where it is used. CRC and SCAN read byte
            # j + 1 whatever they decide (no comparison in front of the buffer address, the
            # link's 100 MHz): when CRC ends, SCAN starts at j = 0, a header byte; when SCAN
            # ends, CODE sends `blk + 1` and reads byte p for DATA. The byte read in those
            # last clocks is never used. SCAN steps j to j + 1 whatever it decides too, and
            # CODE sets j back to p: the zero test of `jb` (after the buffer's read register
            # and the byte selection) drives the state and blk's enable only, not j's
            # next-state multiplexer (the whole top's 100 MHz; the clocks are the same).
            with m.State("CRC"):                    # CRC over the reply payload
                m.d.comb += crc_reply.eq(1)
                m.d.sync += crc.eq(crc_next)
                with m.If(crc_last):                 # j = dend − 1
                    next_j(j_0, parts_0, read=j + 1)
                    m.next = "SCAN"
                with m.Else():
                    set_end(crc_last, j == dend_m2)
                    next_j(j + 1, parts_j1)

            with m.State("SCAN"):                   # length of the COBS block starting at p
                # The block ends at the reply's end (j = rlen), after 254 bytes (j = p + 254,
                # so j − p = 254 too) or at a zero byte.
                next_j(j + 1, parts_j1)             # also when the block ends: CODE sets p
                with m.If(scan_end | jb_zero):
                    read_flag(rd_at_p, 1)
                    m.d.sync += blk_zero.eq(~scan_end)
                    if long_blocks:
                        m.d.sync += more254.eq((blk == 254 + b1) & (j != rlen))
                    m.next = "CODE"
                with m.Else():
                    set_end(scan_end, (j == rlen_m1) | (blk == 253 + b1) if long_blocks
                            else j == rlen_m1)
                    m.d.sync += blk.eq(blk_up)

            with m.State("CODE"):                   # j = the scan's end + 1 (unused), then p
                next_j(p, p_flags)
                m.d.comb += [self.o.valid.eq(1), self.o.payload.eq(blk if b1 else blk + 1)]
                with m.If(self.o.ready):
                    read_flag(rd_at_p, 0)
                    with m.If(blk == b1):
                        m.next = "NEXT"
                    with m.Else():
                        m.next = "DATA"

            with m.State("DATA"):
                m.d.comb += [self.o.valid.eq(1), self.o.payload.eq(jb)]
                if hold:
                    m.d.comb += rd_hold.eq(~self.o.ready)
                else:
                    next_j(j, flags)
                with m.If(self.o.ready):
                    set_j(j + 1, parts_j1)          # and the buffer reads byte j + 1 (below)
                    m.d.sync += blk.eq(blk_down)    # bytes of the block still to send
                    with m.If(blk == 1 + b1):       # j + 1 = p + blk
                        m.next = "NEXT"

            with m.State("NEXT"):                   # j = p + blk, the block's end
                if hold:
                    m.d.comb += rd_hold.eq(~blk_zero)
                with m.If(blk_zero):                # the next block starts after the zero
                    m.d.sync += [p.eq(j + 1), p_flags.eq(parts_j1), blk.eq(b1)]
                    set_end(scan_end, j == rlen_m1)
                    next_j(j + 1, parts_j1)
                    m.next = "SCAN"
                with m.Elif(more254):              # blk = 254, p + blk ≠ rlen
                    m.d.sync += [p.eq(j), p_flags.eq(flags), blk.eq(b1)]
                    next_j(j, flags)
                    m.next = "SCAN"
                with m.Else():
                    read_flag(rd_rep, 0)
                    if hdr_ram:
                        # j back to 0 (a header byte) until the next reply: the buffer reads
                        # the header word in RECV, CHECK and ACHECK (the read register holds
                        # it in CHECK and ACHECK; no other byte of it is written in the
                        # closing 0x00's clock, nor in CHECK on the way to ACHECK).
                        next_j(j_0, parts_0)
                    m.next = "END"

            with m.State("END"):
                m.d.comb += [self.o.valid.eq(1), self.o.payload.eq(0)]
                with m.If(self.o.ready):
                    reset_frame()
                    m.next = "RECV"
        with m.If(new_frame):
            m.d.sync += [length.eq(0), cobs_run.eq(1), cobs_ff.eq(0), started.eq(0),
                         bad.eq(0), crc.eq(0xFFFF), idx.eq(0),
                         *([] if self._compact else [bpos.eq(0)])]
        if self._compact:
            access = fsm.ongoing("ACCESS")
            m.d.comb += [bus_stb.eq(access), bus_we.eq(access & is_write),
                         bus_lock.eq(access | fsm.ongoing("SETUP"))]
        if hold:
            # (The read address's flags follow the state: checked in every simulation.)
            in_rep = Cat(fsm.ongoing(s) for s in ("CRC", "SCAN", "CODE", "DATA", "NEXT")).any()
            m.d.sync += Assert((rd_rep == in_rep) & (rd_at_p == fsm.ongoing("CODE")),
                               "LinkCore: the buffer's read flags and the state disagree")
        elif self._compact:
            # The word of the byte j is set to, in every state but the accesses' (SETUP reads
            # word idx for the write, ACCESS keeps it): j's own next-state multiplexer, no
            # second one for the address. The reads this changes are unused: REPLY's, CRC's
            # last (word(0) now, word(j + 1) before: SCAN's first byte is a header byte) and
            # those outside the reply's passes (idx before).
            m.d.comb += rd.addr.eq(Mux(fsm.ongoing("SETUP") | fsm.ongoing("ACCESS"), idx,
                                       word(j_next)))
            # The header word's writes (the first four bytes received, the clears in CHECK):
            # idx is 0 while the header arrives, and any value ORed with all ones in CHECK.
            hdr_at = _below(length, 4) | fsm.ongoing("CHECK")
            m.d.comb += wr.addr.eq(idx | hdr_at.replicate(ab))
        else:
            m.d.comb += rd.addr.eq(Mux(fsm.ongoing("DATA") & self.o.ready, word(j + 1),
                                       rd_addr))
        return m


class HostLink(wiring.Component):
    """The host link on UART pins: :class:`UartRx` → :class:`LinkCore` → :class:`UartTx`.

    Parameters
    ----------
    clk_hz : float
        Clock frequency, Hz.
    baud : float
        UART bit rate, bit/s; at most ``clk_hz / 8``.
    max_words, address_map, counter_width, strobed, read_hold
        See :class:`LinkCore`.
    compact : bool
        See :class:`LinkCore`; also :class:`UartTx`'s and :class:`UartRx`'s ``compact`` (the
        iCE40's transmitter without its bit count, receiver without its BREAK state,
        docs/AREA.md §7.86).

    Members
    -------
    rx : In(1, init=1)
        UART receive pin (asynchronous; synchronised inside).
    tx : Out(1, init=1)
        UART transmit pin.
    bus : Out(RegBusSignature())
        Register bus master.
    frames_ok, crc_errors, framing_errors, rejected, dropped : Out(counter_width)
        See :class:`LinkCore`; UART framing errors count in ``framing_errors`` (through the
        frame's BAD_CRC reply), bytes lost while the link is busy in ``dropped``.
    <name>_strobe : Out(1)
        Only for the counters named in ``strobed``: see :class:`LinkCore`.

    Attributes
    ----------
    core : LinkCore
    max_frame : int
        See :class:`LinkCore`.
    """

    def __init__(self, *, clk_hz=50e6, baud=115200, max_words=64, address_map=None,
                 counter_width=16, strobed=(), read_hold=False, compact=False):
        uart_params("HostLink", clk_hz, baud)
        hostlink_params(max_words=max_words, address_map=address_map, counter_width=counter_width)
        _check_strobed("HostLink", strobed)
        check_bool("HostLink", "read_hold", read_hold)
        check_bool("HostLink", "compact", compact)
        self._core = LinkCore(max_words=max_words, address_map=address_map,
                              counter_width=counter_width, strobed=strobed, read_hold=read_hold,
                              compact=compact)
        self._clk_hz, self._baud = clk_hz, baud
        cw = self._core.counter_width
        super().__init__({
            "rx": In(1, init=1),
            "tx": Out(1, init=1),
            "bus": Out(RegBusSignature()),
            **_counter_members(cw, strobed),
        })

    strobed = property(lambda self: self._core.strobed)
    read_hold = property(lambda self: self._core.read_hold)
    compact = property(lambda self: self._core.compact)
    clk_hz = property(lambda self: self._clk_hz)
    baud = property(lambda self: self._baud)
    core = property(lambda self: self._core)
    max_words = property(lambda self: self._core.max_words)
    address_map = property(lambda self: self._core.address_map)
    max_frame = property(lambda self: self._core.max_frame)

    def elaborate(self, platform):
        m = Module()
        m.submodules.uart_rx = urx = UartRx(clk_hz=self._clk_hz, baud=self._baud,
                                            compact=self.compact)
        m.submodules.uart_tx = utx = UartTx(clk_hz=self._clk_hz, baud=self._baud,
                                            compact=self.compact)
        m.submodules.core = core = self._core
        m.d.comb += [
            urx.rx.eq(self.rx),
            self.tx.eq(utx.tx),
            core.i.payload.eq(urx.o.payload),
            core.i.valid.eq(urx.o.valid),
            urx.o.ready.eq(1),
            core.rx_lost.eq(urx.o.valid & ~core.i.ready),
            core.rx_error.eq(urx.error),
        ]
        wiring.connect(m, core=core.o, uart_tx=utx.i)
        wiring.connect(m, core=core.bus, link=wiring.flipped(self.bus))
        for name in COUNTERS:
            name = f"{name}_strobe" if name in self._core.strobed else name
            m.d.comb += getattr(self, name).eq(getattr(core, name))
        return m
