# Ref: paper §3 (on-line adjustable parameters); issue 5 item 1; hdl/bus.py (register bus)
"""The register file: the bus slave generated from the register map (:mod:`.regmap`).

Timing (``t`` = the clock ``bus.stb`` rises for an access)::

    t      stb, addr, we, w_data (held by the master until ack)
           write: staging / immediate register loaded at the end of t (address compared in
           full: its block and its offset in the block, each decoded once); the word select
           and a one-hot select of the read multiplexer's words looked up from the word index
           (:func:`word_index`: a choice of address bits, no compare) and whether the
           address's block is the map's, all registered
    t + 1  a strobe register's pulse; the read multiplexer (one-hot select → the word's
           value, an AND-OR; status inputs sampled in this clock) into the registered read
           data; the status looked up from the word select
    t + 2  ack, status, r_data; the master may start the next access in t + 3 (stb is still
           high in t + 1 and t + 2 and is not taken as a new access)

The read is split over two clocks (:attr:`RegisterFile.latency` 2) so that neither the address
decode nor the word multiplexer sits behind the other in one clock (the whole top's 100 MHz on
the ECP5: the 16-bit compares and the ~130-way 32-bit multiplexer in series measured 10.2 ns
alone, 14.6 ns in the routed top, docs/AREA.md §7.7). Session 8 took the status and the word
select's encoder off the address compares (docs/AREA.md, "Session 8: register file"): the
clock t logic behind ``bus.addr`` is the write enables and look-ups of ten address bits.
Session 9 replaced the decode of ``sel`` in front of the multiplexer by the one-hot select.

Shadowing: a write to a shadowed ``rw`` register loads its staging register; the staging
registers of all shadowed registers are copied to the active ones (the Out members) at the end of
every clock with ``commit`` high and ``bus.lock`` low, so the writes of one host frame (``lock``
held high over it) are applied together at the first commit after the frame. Immediate (unshadowed)
``rw`` registers have no staging: the write changes the Out member in ``t + 1``. Reads of ``rw``
registers return the staging value (what the host wrote), which equals the active value once
committed.

Staging in block RAM (``staging="bram"``; docs/AREA.md §7.11, "Session 9: register file"). The
staging registers are one RAM of :attr:`~RegisterFile.slots` 32-bit words: one per shadowed
register word (the *copied* slots: index in :func:`staging_slots`, address order, ``copy_last``
registers at the end), then one per immediate register word (a copy of the Out member, which
reads return; written with it, never copied), each held in its read format (the top word of a
signed register sign-extended). A second part of the same RAM holds the slots' reset values and
after them the ``const`` words (initial contents, never written; reads of a const word return
it). The read multiplexer is left with the read-only status words. The bus timing is the same,
``ack`` two clocks after the access is taken::

    t      word select registered, as with "ff"; an immediate register or strobe written
    t + 1  the RAM word is the word select's code (with ``"bram"`` the code of a RAM word is
           its RAM address), its format a table of the code; write: the RAM's word written
           (w_data still held, formatted); read: the RAM read
    t + 2  ack; a read's r_data is the RAM's read data

``commit`` is a copy, one word per clock: it starts in clock ``s`` with ``commit`` high only if
``bus.lock`` is low, no access is in its ``t + 1`` and no copy or walk runs (else it is ignored,
never deferred); the RAM reads copied slot ``i`` in clock ``s + i`` and the active register word
of slot ``i`` changes at the end of clock ``s + 1 + i`` (enabled by bit ``i`` of a one-hot shift
register started by the copy, not by a compare of the slot counter; with ``export`` restarted by
a compare after each run of exported slots, which the reset walk's reads of the reset values pass
too: its loads write reset values into active words that hold them), so every active value is the
new one from clock ``s + commit_clocks`` (copied slots + 1). While the RAM is read for the copy
(clocks ``s`` … ``s + commit_clocks − 2``) no access is taken: an access whose ``stb`` rises then
(or in ``s``) is taken in ``s + commit_clocks − 1`` and acked two clocks later (the bus allows any
``ack`` delay; the host link waits). A frame therefore never lands between two copied words.
After a domain reset (block RAM keeps its contents) the same sequencer walks the reset values
into every slot (:attr:`~RegisterFile.reset_clocks` = ``slots`` clocks, accesses held off,
commits ignored), so reads after a reset return the reset values, as with ``"ff"``. No read of
the RAM is used in a clock that writes the same word (a write's own ``t + 1``; the walk reads
the reset part while it writes a slot), so the RAM's read-during-write result is left undefined
(``no_rw_check``). Strobes, the immediate registers' Out members, status and the windows are as
with ``"ff"``.

Exported registers (``staging="bram"``, ``export``; docs/AREA.md §4 stage 3, "active values
where they are read"). The active words of the shadowed registers named in ``export`` are not
flip-flops of the register file: the ``export`` port (:class:`~.bus.WordWriteSignature`) carries
each of them instead, as a write to a consumer's RAM, in exactly the clock its flip-flops would
have been loaded::

    s + 1 + i   copied slot i is an exported word: export.valid, export.index (the word's
                position among the exported words, :func:`export_words`), export.data (the
                word in its read format, as the staging RAM holds it: the top word of a signed
                register sign-extended to 32 bits)

A RAM written from the port (written at the end of the ``valid`` clock) therefore holds, in
every clock, what the flip-flops would have held, with one exception: a domain reset loads the
flip-flops with their reset values at once, while the RAM (block RAM keeps its contents) gets
them from the reset walk, which puts each exported word on the port (its reset value, read from
the RAM's reset half) in clock ``2 + i`` after the reset clock (slot ``i``; the RAM holds it
from clock ``3 + i``); from clock ``2 + reset_clocks`` after the reset on every exported word
is its reset value again. At power-up the walk runs too; a consumer RAM initialised with
:func:`export_init` (the reset values) matches from the first clock. ``export_walk`` is high
while the walk's words are on the port (from the reset clock to the last one, inclusive), for a
consumer that must not start a computation the walk's writes would land in (the speed loop,
:class:`~.top.Top`).

Mirrored registers (``staging="bram"``, ``mirror``; docs/AREA.md §7.77). The immediate
(unshadowed) ``rw`` registers named in ``mirror`` have no flip-flops here either: the staging
RAM's writes of their words (a host write's ``t + 1``, the reset walk's load) are on the
``mirror`` port (:class:`~.bus.WordWriteSignature`: ``valid``, ``index`` the word's position
among the mirrored words, ``data`` the word in its read format), so a consumer RAM written from
it holds each value **one clock later** than the flip-flops would have (from ``t + 2``; the
flip-flops: from ``t + 1``), and after a domain reset gets the reset values from the walk (as
with ``export``). A write access is never taken in a copy's or the walk's load clocks, so the
port shows only these writes.

Derived active values (``staging="bram"``, ``derived``; docs/AREA.md, "Session 12: register
file"). With the staging RAM holding what the host wrote (reads return it), the active flip-flops
of a register need only hold what its consumer uses: :class:`Derived` gives that as a function of
the raw value (e.g. the scope's ``decim`` = ``scope_decim`` − 1, 0 for 0; a channel code clamped
to the scope's 4-bit select), applied where the flip-flops load (the write in ``t`` of an
immediate register, the copy's load clock of a shadowed one), so they change in the same clocks
and the consumer sees the same value as with the function behind the raw flip-flops.

Counters in the staging RAM (``staging="bram"``, ``counters``; docs/AREA.md §7.59). The
read-only registers named in ``counters`` (e.g. the host link's reply counters) are words of
the staging RAM after the slots, wrapping modulo ``2**width``, reset to 0 by the reset walk
(which therefore takes ``len(counters)`` clocks more), counted from a ``<name>_inc`` strobe
each: a strobe marks its counter pending; the lowest pending counter is read in a clock where
the RAM's read port is free (no access in its ``t + 1``, no copy or walk reading, no walk load
writing; a commit that starts a copy goes first) and written back plus one in the next. While
a counter is pending or strobed no access is taken (held off like a copy's), so a read taken in
``t`` returns every strobe of the clocks up to ``t``, as a counter flip-flop (status input)
sampled in ``t + 1`` would; only ``ack`` may come later. A strobe of a counter that is still
pending is lost: strobes of one counter, and commits, must come at least
:attr:`~RegisterFile.count_interval` clocks apart (a walk, a copy and every counter's
read-modify-write); the Top's counters count at most once per PWM period or host-link frame,
its commits once per PWM period (checked in ``Top``). Reads return the word as stored
(zero-extended).

Status read from a RAM (``status_ram``; docs/AREA.md, "Session 11: engine status"). The
read-only registers named in ``status_ram`` have no ``In`` member: their values live in a
consumer's RAM (e.g. the loop engine's status RAM), read through the ``status_rd`` port, a
synchronous read port whose ``data`` in clock ``t + 1`` is the register's value in ``t + 1``
for ``addr`` given in ``t`` (a transparent read)::

    t      status_rd.addr: the addressed register's position in ``status_ram``, looked up
           combinationally from the word index (ten address bits, no compare)
    t + 1  status_rd.data: one more term of the read multiplexer (its own one-hot bit, the
           sign bit for the sign extension), sampled in this clock like every status input

so such a read returns exactly what a status input sampled in ``t + 1`` would, in the same
clocks (``ack`` in ``t + 2``). ``addr`` is driven in every clock (a read in a clock without an
access is harmless).
"""

import dataclasses
import itertools
from collections.abc import Mapping

from amaranth.hdl import Cat, Const, Module, Mux, Shape, Signal, Value, unsigned
from amaranth.lib import wiring
from amaranth.lib.memory import Memory, ReadPort
from amaranth.lib.wiring import In, Out
from amaranth.utils import ceil_log2

from .bus import DATA_WIDTH, RegBusSignature, Status, WordWriteSignature
from .fixed import at_least, check_choice
from .regmap import REGMAP, Access, RegMap

__all__ = ["Derived", "RegisterFile", "STAGINGS", "export_init", "export_words", "ram_slots",
           "staging_slots", "word_index"]

#: Values of ``RegisterFile(staging=...)``.
STAGINGS = ("ff", "bram")


@dataclasses.dataclass(frozen=True)
class Derived:
    """What the active value of a register holds instead of the register's raw value
    (``RegisterFile(derived=...)``): a function of it that its consumer wants, computed where
    the value is loaded (the write of an immediate register, the copy of a shadowed one), so the
    flip-flops hold the consumer's operand (often fewer bits) and the consumer's logic behind
    them is gone. Reads still return the raw value (from the staging RAM).

    Parameters
    ----------
    shape : shape-castable
        Shape of the Out member.
    value : callable
        ``value(raw)``: the Out member's value from the register's raw value ``raw`` (a
        ``Value`` of the register's ``fmt.shape``), an Amaranth expression.
    const : callable
        ``const(bits)``: the same as a Python function of the raw bits (an ``int``, unsigned),
        for the Out member's reset value (``init``) and the golden model; a test checks that
        the two agree.
    """
    shape: object
    value: object
    const: object

    def __post_init__(self):
        Shape.cast(self.shape)
        if not callable(self.value) or not callable(self.const):
            raise TypeError(f"Derived value and const must be callables, not {self.value!r} "
                            f"and {self.const!r}")


def staging_slots(regmap, copy_last=()):
    """The staging RAM's slots of ``regmap`` (``staging="bram"``): ``[(addr, register, k), ...]``,
    one per word of a shadowed ``rw`` register, in address order except that the registers named
    in ``copy_last`` come last (in that order). Slot ``i`` is copied to the active register in
    the copy's clock ``i + 1``."""
    words = [(a, r, k) for a, r, k in regmap.words()
             if r.access is Access.RW and r.shadow is not None]
    last = [w for name in copy_last for w in words if w[1].name == name]
    return [w for w in words if w[1].name not in copy_last] + last


def ram_slots(regmap, copy_last=()):
    """Every staging RAM slot of ``regmap`` (``staging="bram"``): the copied slots
    (:func:`staging_slots`), then one per word of an immediate (unshadowed) ``rw`` register in
    address order (read back from the RAM, never copied)."""
    return staging_slots(regmap, copy_last) + [
        (a, r, k) for a, r, k in regmap.words() if r.access is Access.RW and r.shadow is None]


def export_words(regmap, export):
    """The exported words of ``regmap`` (``RegisterFile(export=...)``): ``[(addr, register,
    k), ...]``, the words of the registers named in ``export`` in that order (low word first);
    the position in this list is the ``export.index`` of the word."""
    return [(a, r, k) for name in export for a, r, k in regmap.words() if r.name == name]


def export_init(regmap, export):
    """The reset values of the exported words (:func:`export_words`) in their read format (the
    32-bit words the ``export`` port carries, unsigned): a consumer RAM's initial contents."""
    return [r.read_word(r.bits(r.reset), k) for _, r, k in export_words(regmap, export)]


def word_index(regmap):
    """The register file's word index of ``regmap``: ``(block_bits, picked)``.

    The word addresses fall into blocks of ``2 ** block_bits`` words (``addr >> block_bits``);
    ``picked`` are the fewest bit positions of the block number that tell the blocks apart. An
    address's *index* is ``Cat(addr[:block_bits], addr[block_bits + p] for p in picked)``: the
    index of every word of the map is distinct, and it is a mere choice of address wires, no
    logic. The access clock registers the index and whether ``addr``'s block is one of the
    map's; the read multiplexer and the status look-up of the next clock work on the index alone.
    ``block_bits`` is chosen (0 … 8) for the shortest index, then the largest ``block_bits``."""
    addrs = [a for a, _, _ in regmap.words()]
    best = None
    for b in range(9):
        blocks = sorted({a >> b for a in addrs})
        for n in range(17 - b):
            if (1 << n) < len(blocks):
                continue
            picked = next((sub for sub in itertools.combinations(range(16 - b), n)
                           if len({tuple((blk >> p) & 1 for p in sub) for blk in blocks})
                           == len(blocks)), None)
            if picked is not None:
                break
        key = (b + len(picked), -b)
        if best is None or key < best[0]:
            best = (key, b, picked)
    return best[1], best[2]


def _index_of(addr, block_bits, picked):
    """The index (:func:`word_index`) of address ``addr`` as an integer."""
    idx = addr & ((1 << block_bits) - 1)
    for j, p in enumerate(picked):
        idx |= ((addr >> (block_bits + p)) & 1) << (block_bits + j)
    return idx


def _or_tree(values):
    """The OR of ``values`` as a balanced tree."""
    while len(values) > 1:
        values = [values[i] | values[i + 1] if i + 1 < len(values) else values[i]
                  for i in range(0, len(values), 2)]
    return values[0] if values else Const(0, 1)


def _table_bit(index, table):
    """The bit ``table[index]`` (``None``: either value) as a tree of 2:1 multiplexers on the
    bits of ``index`` from the top, each subtree a constant where its entries allow one, equal
    subtrees shared."""
    memo = {}

    def node(level, entries):
        known = {e for e in entries if e is not None}
        if len(known) <= 1:
            return Const(known.pop() if known else 0, 1)
        key = (level, tuple(entries))
        if key not in memo:
            half = len(entries) // 2
            lo, hi = entries[:half], entries[half:]
            if all(e is None for e in hi):
                memo[key] = node(level - 1, lo)
            elif all(e is None for e in lo):
                memo[key] = node(level - 1, hi)
            else:
                memo[key] = Mux(index[level - 1], node(level - 1, hi), node(level - 1, lo))
        return memo[key]

    return node(len(index), list(table))


def _member_bits(m, index, block_bits, codes, name):
    """A register of one bit per block of ``index`` (its bits from ``block_bits`` up) holding
    ``codes``: bit ``j`` is ``index`` in the ``j``-th such block and its offset one of that
    block's codes, loaded in every clock; ``index in codes`` is their OR in the next clock."""
    blocks = {}
    for c in codes:
        blocks.setdefault(c >> block_bits, 0)
        blocks[c >> block_bits] |= 1 << (c & ((1 << block_bits) - 1))
    bits = Signal(max(1, len(blocks)), name=name)
    terms = [(index[block_bits:] == blk) & Const(mask, 1 << block_bits).bit_select(
                 index[:block_bits], 1) for blk, mask in sorted(blocks.items())]
    m.d.sync += bits.eq(Cat(terms) if terms else 0)
    return bits


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
    staging : str
        Where the staging copies of the shadowed ``rw`` registers live: ``"ff"`` (default) one
        flip-flop register per shadowed register, ``commit`` copies them all in one clock;
        ``"bram"`` one word per shadowed register word in a RAM (module docstring), ``commit``
        starts a copy of :attr:`commit_clocks` clocks, one word per clock.
    copy_last : tuple of str
        ``staging="bram"`` only: shadowed registers copied last, in this order (the last one in
        the copy's last clock; see :func:`staging_slots`). Default ``()``.
    export : tuple of str
        ``staging="bram"`` only: shadowed registers whose active value is not held here but
        written to a consumer's RAM through the ``export`` port (module docstring); they have
        no Out member. Default ``()``.
    status_ram : tuple of str
        Read-only registers of one word each, all of one shape, whose values are read from a
        consumer's RAM through the ``status_rd`` port (module docstring), in this order (the
        read address of a register is its position); they have no In member. Default ``()``.
    counters : tuple of str
        ``staging="bram"`` only: one-word unsigned ``ro`` registers of one width (not in
        ``status_ram``) that are counters in the staging RAM, counted from a ``<name>_inc``
        strobe each (module docstring, "Counters"); they have no In member. Default ``()``.
    changed : tuple of str
        One-word shadowed ``rw`` registers (not exported) that get a ``<name>_changed`` strobe:
        high for one clock, the first clock in which the Out member holds a new value that
        differs from the old one (the clock after the commit, ``"ff"``; after the register's
        copy clock, ``"bram"``): a consumer need not keep a copy of the register to see it
        change. A domain reset (the reset values loaded at once) gives no strobe. Default
        ``()``.
    mirror : tuple of str
        ``staging="bram"`` only: immediate (unshadowed) ``rw`` registers whose active value is
        not held here: the staging RAM's writes of their words go out on the ``mirror`` port
        (module docstring, "Mirrored registers"); they have no Out member. Default ``()``.
    derived : mapping of str to Derived
        ``staging="bram"`` only: one-word ``rw`` registers (no enum or fields, not exported)
        whose Out member holds :class:`Derived` ``value(raw)`` (its ``shape``, ``init``
        ``const(reset)``) instead of the raw value, loaded in the same clocks (the write's
        ``t`` of an immediate register, the copy's load clock of a shadowed one). Reads return
        the raw value, as for every register (the staging RAM holds it). Default none.

    Members
    -------
    bus : In(RegBusSignature())
        Register bus from the host link (see :mod:`.bus`); ``ack`` two clocks after ``stb``
        (``"bram"``: later while a copy or the reset walk holds the access off).
    commit : In(1)
        Loop-boundary strobe: staging → active for every shadowed register, while ``bus.lock``
        is low. ``"ff"``: in this clock; pulse it when no loop is computing (e.g. the PWM
        ``period_start``). ``"bram"``: starts the copy (only with ``lock`` low, no access in its
        second clock and no copy or reset walk running; otherwise ignored); pulse it
        :attr:`commit_clocks` clocks before the new values are wanted.
    <rw register> : Out(register.shape, init=reset)
        The active value the control path uses (enum, StructLayout of the fields, or the raw
        fixed-point shape ``register.fmt.shape``); not for the exported registers; for a
        ``derived`` one ``Out(derived.shape, init=derived.const(reset))``, its ``value``.
    export : Out(WordWriteSignature(len(export_words)))
        Only with ``export``: the exported active words as RAM writes (``valid``, ``index``,
        ``data``), in the clocks the module docstring gives.
    mirror : Out(WordWriteSignature(len(mirror_words)))
        Only with ``mirror``: the staging RAM's writes of the mirrored words (``index``: the
        position in :attr:`mirror_words`).
    export_walk : Out(1, init=1)
        Only with ``export``: high from a reset (and power-up) up to and including the clock
        the reset walk puts its last word on the port: the exported words are being rewritten;
        a consumer that must not see them change under a computation waits.
    <ro register> : In(register.shape)
        Status from the control path (not those of ``status_ram`` or ``counters``).
    <counter>_inc : In(1)
        Only for the registers named in ``counters``: the count strobe (one count per clock
        high; module docstring, "Counters").
    status_rd : In(ReadPort.Signature(addr_width=ceil_log2(len(status_ram)), shape=...))
        Only with ``status_ram``: ``addr`` (out; the position in ``status_ram``) in clock
        ``t``, the register's value in ``t + 1`` on ``data`` (in) in ``t + 1`` (a transparent
        synchronous read port of the consumer's RAM; ``en`` is always 1).
    <strobe register> : Out(1)
        One-clock pulse in ``t + 1`` after a write with bit 0 set.
    <register>_changed : Out(1)
        Only for the registers named in ``changed``: the change strobe (``changed`` above).
    <window>_rd_addr : Out(window.addr_width)
        Word offset of the access into the window (``bus.addr``'s low bits, combinational).
    <window>_rd_data : In(32)
        The word at ``<window>_rd_addr`` one clock earlier (a memory read port); returned on
        ``bus.r_data`` in the ack clock of a window read (the address is held: read in t + 1).

    Attributes
    ----------
    latency : int
        Clocks from the access clock (``stb`` taken) to ``ack``: 2.
    staging : str
        The parameter.
    slots : int
        Staging slots in the RAM (``"bram"``: one per word of a shadowed or immediate ``rw``
        register; 0 for ``"ff"``).
    commit_clocks : int
        Clocks from a ``commit`` that is taken (clock ``s``) to the clock from which every active
        value is the new one (``s + commit_clocks``): 1 (``"ff"``), ``len(staging_slots()) + 1``
        (``"bram"``: copied slot ``i`` changes at the end of clock ``s + 1 + i``).
    commit_latency : int
        The same as :attr:`commit_clocks` (kept for the existing callers).
    reset_clocks : int
        ``"bram"``: clocks after a reset during which accesses are held off while the reset
        values are written back into every staging slot and counter (``slots`` +
        ``len(counters)``); ``"ff"``: 0.
    count_interval : int
        See the property.
    exported : tuple of str
        The ``export`` parameter (``export`` is the port).
    export_words : list
        :func:`export_words`: ``(addr, register, k)`` per ``export.index``.
    export_init : list of int
        :func:`export_init`: the exported words' reset values (a consumer RAM's init).
    mirrored : tuple of str
        The ``mirror`` parameter.
    mirror_words : list
        ``(addr, register, k)`` per ``mirror.index`` (:func:`export_words` of ``mirror``).
    mirror_init : list of int
        The mirrored words' reset values (a consumer RAM's init, as :attr:`export_init`).

    Raises
    ------
    TypeError
        ``regmap`` is not a :class:`~.regmap.RegMap`; ``staging`` is not a string;
        ``copy_last``, ``export``, ``status_ram`` or ``changed`` is not a tuple of strings;
        ``derived`` is not a mapping of strings to :class:`Derived`.
    ValueError
        ``staging`` is not one of :data:`STAGINGS`; ``copy_last`` or ``export`` names a
        register that is not a shadowed ``rw`` register of ``regmap``, repeats a name, or is
        given with ``staging="ff"``; ``status_ram`` names a register that is not a one-word
        ``ro`` register, repeats a name, or names registers of different shapes; ``changed``
        names a register that is not a one-word shadowed ``rw`` register or is exported, or
        repeats a name; ``derived`` names a register that is not a one-word ``rw`` register
        without enum or fields, or an exported one, or one named in ``changed``, or is given
        with ``staging="ff"``.
    """

    latency = 2

    def __init__(self, regmap=REGMAP, *, staging="ff", copy_last=(), export=(),
                 status_ram=(), changed=(), derived=None, counters=(), mirror=()):
        if not isinstance(regmap, RegMap):
            raise TypeError(f"RegisterFile regmap must be a RegMap, not {regmap!r}")
        check_choice("RegisterFile", "staging", staging, STAGINGS)
        # Per parameter: which registers it may name (and what they must be), and whether it
        # needs block-RAM staging.
        rules = {"copy_last": (copy_last, "shadowed rw", True,
                               lambda r: r.access is Access.RW and r.shadow is not None),
                 "export": (export, "shadowed rw", True,
                            lambda r: r.access is Access.RW and r.shadow is not None),
                 "mirror": (mirror, "immediate rw", True,
                            lambda r: r.access is Access.RW and r.shadow is None),
                 "status_ram": (status_ram, "one-word ro", False,
                                lambda r: r.access is Access.RO and r.words == 1),
                 "changed": (changed, "unexported one-word shadowed rw", False,
                             lambda r: (r.access is Access.RW and r.shadow is not None
                                        and r.words == 1 and r.name not in export)),
                 "counters": (counters, "one-word unsigned ro (not in status_ram)", True,
                              lambda r: (r.access is Access.RO and r.words == 1
                                         and not r.signed and r.enum is None
                                         and r.fields is None and r.name not in status_ram))}
        for param, (names, kind, bram_only, allowed) in rules.items():
            if (not isinstance(names, tuple)
                    or not all(isinstance(n, str) for n in names)):
                raise TypeError(f"RegisterFile {param} must be a tuple of register names, "
                                f"not {names!r}")
            for name in names:
                if name not in regmap or not allowed(regmap[name]):
                    raise ValueError(f"RegisterFile {param} must name {kind} registers, "
                                     f"not {name!r}")
            if bram_only and names and staging != "bram":
                raise ValueError(f"RegisterFile {param} applies only to staging='bram', "
                                 f"not staging={staging!r}")
            if len(set(names)) != len(names):
                raise ValueError(f"RegisterFile {param} must not repeat a name, not {names!r}")
        derived = {} if derived is None else derived
        if (not isinstance(derived, Mapping)
                or not all(isinstance(n, str) and isinstance(d, Derived)
                           for n, d in derived.items())):
            raise TypeError(f"RegisterFile derived must be a mapping of register names to "
                            f"Derived, not {derived!r}")
        for name in derived:
            r = regmap[name] if name in regmap else None
            if (r is None or r.access is not Access.RW or r.words != 1 or r.enum is not None
                    or r.fields is not None or name in export or name in changed):
                raise ValueError(f"RegisterFile derived must name one-word rw registers without "
                                 f"enum or fields, not exported or in changed, not {name!r}")
            if name in mirror:
                raise ValueError(f"RegisterFile derived must not name a mirrored register, "
                                 f"not {name!r}")
        if derived and staging != "bram":
            raise ValueError(f"RegisterFile derived applies only to staging='bram', "
                             f"not staging={staging!r}")
        if len({(regmap[n].width, regmap[n].signed) for n in status_ram}) > 1:
            raise ValueError(f"RegisterFile status_ram must name registers of one shape, "
                             f"not {status_ram!r}")
        if len({regmap[n].width for n in counters}) > 1:
            raise ValueError(f"RegisterFile counters must name registers of one width, "
                             f"not {counters!r}")
        self._status_ram = status_ram
        self._counters = counters
        self._changed = changed
        self._derived = dict(derived)
        self._regmap = regmap
        self._staging = staging
        self._copy_last = copy_last
        self._export = export
        self._export_words = export_words(regmap, export)
        self._mirror = mirror
        self._mirror_words = export_words(regmap, mirror)
        self._slots = staging_slots(regmap, copy_last) if staging == "bram" else []
        self._copied = len(self._slots)
        if staging == "bram" and not self._slots:
            raise ValueError("RegisterFile staging='bram' needs a shadowed rw register in the "
                             "regmap, not none")
        # "bram": the immediate rw words after the copied slots (read back from the RAM, never
        # copied), the const words in the RAM's reset half after the reset values (read only).
        self._consts = []
        if staging == "bram":
            self._slots = ram_slots(regmap, copy_last)
            self._consts = [(a, r, k) for a, r, k in regmap.words() if r.access is Access.CONST]
        self._slot_of = {a: i for i, (a, _, _) in enumerate(self._slots)}
        # "bram" with counters: one RAM word per counter after the slots (reset to 0 by the
        # walk like a slot, never copied, written only by its count).
        self._counter_words = [(regmap[n].addr, regmap[n], 0) for n in counters]
        walked = len(self._slots) + len(self._counter_words)
        base = 1 << ceil_log2(walked) if self._slots else 0
        self._ram_addr = {**self._slot_of,
                          **{a: len(self._slots) + j
                             for j, (a, _, _) in enumerate(self._counter_words)},
                          **{a: base + walked + j for j, (a, _, _) in enumerate(self._consts)}}
        # "bram": the word select's codes (_sel_code): a RAM word's address, below a flag bit
        # that marks the words outside the RAM (its low bits: 0 none, 1 read-only, 2 strobe).
        ram_bits = ceil_log2(base + walked + len(self._consts)) if self._slots else 0
        self._sel_width = max(ram_bits, 2) + 1
        self._sel_none = 1 << (self._sel_width - 1)
        members = {"bus": In(RegBusSignature()), "commit": In(1)}
        if export:
            members["export"] = Out(WordWriteSignature(len(self._export_words)))
            members["export_walk"] = Out(1, init=1)
        if mirror:
            members["mirror"] = Out(WordWriteSignature(len(self._mirror_words)))
        if status_ram:
            r0 = regmap[status_ram[0]]
            members["status_rd"] = In(ReadPort.Signature(
                addr_width=ceil_log2(len(status_ram)), shape=r0.fmt.shape))
        for r in regmap:
            if r.access is Access.RW:
                if r.name in self._derived:     # (the consumer's operand, Derived)
                    d = self._derived[r.name]
                    members[r.name] = Out(d.shape, init=d.const(r.bits(r.reset)))
                elif r.name not in export and r.name not in mirror:
                    # (exported, mirrored: the consumer's RAM holds it)
                    members[r.name] = Out(r.shape, init=r.init)
            elif r.access is Access.RO and r.name in counters:
                members[f"{r.name}_inc"] = In(1)
            elif r.access is Access.RO and r.name not in status_ram:
                members[r.name] = In(r.shape)
            elif r.access is Access.STROBE:
                members[r.name] = Out(1)
        for name in changed:
            members[f"{name}_changed"] = Out(1)
        for w in regmap.windows:
            members[f"{w.name}_rd_addr"] = Out(w.addr_width)
            members[f"{w.name}_rd_data"] = In(DATA_WIDTH)
        super().__init__(members)

    regmap = property(lambda self: self._regmap)
    staging = property(lambda self: self._staging)
    copy_last = property(lambda self: self._copy_last)
    exported = property(lambda self: self._export)
    status_ram = property(lambda self: self._status_ram)
    counters = property(lambda self: self._counters)
    changed = property(lambda self: self._changed)
    derived = property(lambda self: dict(self._derived))
    export_words = property(lambda self: list(self._export_words))
    export_init = property(lambda self: export_init(self._regmap, self._export))
    mirrored = property(lambda self: self._mirror)
    mirror_words = property(lambda self: list(self._mirror_words))
    mirror_init = property(lambda self: export_init(self._regmap, self._mirror))
    slots = property(lambda self: len(self._slots))
    commit_clocks = property(lambda self: self._copied + 1)
    commit_latency = commit_clocks
    reset_clocks = property(lambda self: len(self._slots) + len(self._counter_words))

    @property
    def count_interval(self):
        """``counters``: the fewest clocks between two strobes of one counter, and between two
        commits, for which no count is lost (module docstring): a walk, a copy and every
        counter's read-modify-write (``reset_clocks + commit_clocks + 2·len(counters)``); 0
        without counters."""
        if not self._counter_words:
            return 0
        return self.reset_clocks + self.commit_clocks + 2 * len(self._counter_words)

    def elaborate(self, platform):
        m = Module()
        bus = self.bus
        bram = self._staging == "bram"
        words = self._regmap.words()
        block_bits, picked = word_index(self._regmap)
        blocks = sorted({a >> block_bits for a, _, _ in words})

        access = Signal()
        pending = Signal()                      # t + 1 of an access: the read multiplexer
        r_data = Signal(DATA_WIDTH)
        win_hit = {w.name: Signal(name=f"{w.name}_hit") for w in self._regmap.windows}
        win_pend = {w.name: Signal(name=f"{w.name}_pend") for w in self._regmap.windows}
        # The access's address, registered in t for t + 1: its word index (word_index(), a
        # choice of address bits), whether its block is one of the map's, and we.
        index = Cat(bus.addr[:block_bits], *(bus.addr[block_bits + p] for p in picked))
        # Word select, looked up from the word index (valid with blk_ok). Flip-flop staging:
        # not used (``known`` and ``read_only`` are registered from the index, below). Block-RAM
        # staging: the word's code (:meth:`_sel_code`), whose fields are what t + 1 needs: the
        # RAM address itself, or a flag and the kind of a word outside the RAM.
        sel = Signal(self._sel_width)
        blk_ok = Signal()
        we = Signal(name="we_p")
        win_wr = Signal()                       # a write to a window (read only)
        if bram:
            stage = self._stage(m, pending, sel, blk_ok, we)
            m.d.comb += access.eq(bus.stb & ~pending & ~bus.ack & ~stage["hold"])
        else:
            stage = None
            m.d.comb += access.eq(bus.stb & ~pending & ~bus.ack)
        m.d.sync += [pending.eq(access), bus.ack.eq(pending)]

        out = r_data
        if bram:
            out = Mux(stage["hit"], stage["rd_data"], out)
        for w in self._regmap.windows:
            m.d.comb += getattr(self, f"{w.name}_rd_addr").eq(bus.addr[:w.addr_width])
            out = Mux(win_hit[w.name], getattr(self, f"{w.name}_rd_data"), out)
        m.d.comb += bus.r_data.eq(out)

        # The value each register's reads return, and where writes go.
        held = {}
        for r in self._regmap:
            port = getattr(self, r.name, None)
            if r.access is Access.RW and (r.shadow is not None or r.name in self._mirror) and bram:
                held[r.name] = None             # in the staging RAM (mirrored: and the port)
            elif r.access is Access.RW and r.shadow is not None:
                staged = Signal(unsigned(r.width), init=r.bits(r.reset), name=f"{r.name}_staged")
                held[r.name] = staged
                with m.If(self.commit & ~bus.lock):
                    m.d.sync += _bits(port).eq(staged)
                if r.name in self._changed:
                    m.d.sync += getattr(self, f"{r.name}_changed").eq(
                        self.commit & ~bus.lock & (staged != _bits(port)))
            elif r.access is Access.RW:
                held[r.name] = _bits(port)
            elif r.access is Access.RO and r.name in self._status_ram:
                held[r.name] = None             # in the consumer's RAM (status_rd)
            elif r.access is Access.RO and r.name in self._counters:
                held[r.name] = None             # in the staging RAM (counted there)
            elif r.access is Access.RO:
                held[r.name] = _bits(port)
            elif r.access is Access.CONST:
                held[r.name] = r.bits(r.reset)
            else:
                held[r.name] = 0
                m.d.sync += port.eq(0)

        # t: the writes (address compared in full); the index, block and window hits registered.
        # The word select ``sel`` is loaded with the access, and only with block-RAM staging:
        # flip-flop staging reads the select only as ``known`` and ``read_only``, registered
        # from the index directly (below).
        def load_sel():
            # The code of every word's index, the no-word code for the other indexes of the
            # map's blocks, and any code for the indexes of other blocks (blk_ok low: the code
            # is not used), as a multiplexer tree per bit (_table_bit; a Switch of the words'
            # cases measured 35 logic cells more, docs/AREA.md §7.68).
            table = [None] * (1 << len(index))
            for blk in blocks:
                lo = _index_of(blk << block_bits, block_bits, picked)
                table[lo:lo + (1 << block_bits)] = [self._sel_none] * (1 << block_bits)
            for addr, r, k in words:
                table[_index_of(addr, block_bits, picked)] = self._sel_code(addr, r)
            m.d.sync += sel.eq(Cat(_table_bit(index, [None if c is None else c >> b & 1
                                                      for c in table])
                                   for b in range(len(sel))))
        if not bram:
            # Flip-flop staging reads the word select only as ``known`` and ``read_only``
            # (below): those two are registered from the index directly, each as one bit per
            # block of the index (its upper bits: one compare, and its lower ``block_bits`` a
            # constant function), ORed in t + 1 (ECP5 Fmax: the ~110-way OR of compares in one
            # clock was the critical path, docs/AREA.md §7.62).
            ro_codes = [_index_of(addr, block_bits, picked) for addr, r, k in words
                        if r.access in (Access.RO, Access.CONST)]
            codes = [_index_of(addr, block_bits, picked) for addr, r, k in words]
            assert len(set(codes)) == len(codes)        # (word_index: one index per word)
            known_q = _member_bits(m, index, block_bits, codes, "known")
            ro_q = _member_bits(m, index, block_bits, ro_codes, "read_only")
        with m.If(access):
            m.d.sync += [we.eq(bus.we), blk_ok.eq(0), win_wr.eq(0),
                         *(hit.eq(0) for hit in win_pend.values())]
            with m.Switch(bus.addr[block_bits:]):
                for blk in blocks:
                    with m.Case(blk):
                        m.d.sync += blk_ok.eq(1)
            if bram:
                load_sel()
            # The write enables: the address's block (one 16 − block_bits bit compare per block
            # with writable words) and its offset in the block (one compare per offset), each
            # decoded once and shared by the words, then ANDed per word.
            wr_blk, wr_off = {}, {}
            for addr, r, k in words:
                if held[r.name] is not None and r.access in (Access.RW, Access.STROBE):
                    blk, off = addr >> block_bits, addr & ((1 << block_bits) - 1)
                    if blk not in wr_blk:
                        wr_blk[blk] = Signal(name=f"wr_blk{blk:x}")
                        m.d.comb += wr_blk[blk].eq(bus.we & (bus.addr[block_bits:] == blk))
                    if off not in wr_off:
                        wr_off[off] = Signal(name=f"wr_off{off:x}")
                        m.d.comb += wr_off[off].eq(bus.addr[:block_bits] == off)
                    with m.If(wr_blk[blk] & wr_off[off]):
                        self._write(m, r, k, held[r.name])
            for w in self._regmap.windows:
                with m.If(bus.addr[w.addr_width:] == w.addr >> w.addr_width):
                    m.d.sync += [win_pend[w.name].eq(~bus.we), win_wr.eq(bus.we)]
        # t + 1: word select → read data and status; window hits passed on (all for t + 2).
        # The selected word's value (the words of the multiplexer), its bits zero-extended; the
        # sign extension of a signed word of width w is one sign bit per w (``sign[w]``, an
        # AND-OR over those words only) ORed into bits w … 31 after the multiplexer, rather
        # than the sign bit in every upper bit of the multiplexer. The multiplexer is an AND-OR
        # on a one-hot word select registered in t (``hot``, one bit per word of the
        # multiplexer, looked up from the index like ``sel``), not on a decode of ``sel``. The
        # hot bits are read only in t + 1 (``pending``) and the master holds ``addr`` from t to
        # the ack, so they are loaded in every clock, not under ``access`` (ECP5 Fmax: the bus
        # handshake was on the critical path into ``hot``'s enable, docs/AREA.md §7.58).
        muxed = [(i, r, k, held[r.name]) for i, (addr, r, k) in enumerate(words)
                 if held[r.name] is not None and addr not in self._ram_addr
                 and (not isinstance(held[r.name], int) or r.read_word(held[r.name], k))]
        word = Signal(DATA_WIDTH)
        sign = {}
        if bram:
            # sel is a word (blk_ok: the address is); a read-only one (ro, const): outside the
            # RAM its kind; in the RAM every word after the slots (counters, consts).
            flag = sel[-1]
            known = ~flag | (sel != self._sel_none)
            read_only = Mux(flag, sel == self._sel_none + 1, ~stage["staged"])
        else:
            known, read_only = known_q.any(), ro_q.any()

        def part(r, k, held_r):
            """The word's value (zero-extended) and its sign bit if it is sign-extended, else
            ``None``."""
            lo, hi = r.word_slice(k)
            if (isinstance(held_r, int) or not r.signed or k != r.words - 1
                    or hi - lo == DATA_WIDTH):
                return self._read_word(r, k, held_r), None
            if hi - lo not in sign:
                sign[hi - lo] = Signal(name=f"sign{hi - lo}")
            return held_r[lo:hi], held_r[hi - 1]

        terms, sign_terms = [], {}
        blk_now = Cat(bus.addr[block_bits:] == blk for blk in blocks).any()     # (blk_ok's D)
        if muxed:
            hot = Signal(len(muxed), name="hot")
            codes = [_index_of(words[i][0], block_bits, picked) for (i, r, k, _) in muxed]
            assert len(set(codes)) == len(codes)        # (one hot bit per index)
            # One compare per bit (no shared multiplexer tree, no reset term).
            if bram:                            # (the read's block hit and ~we in them)
                m.d.sync += hot.eq(Cat((index == c) & blk_now & ~bus.we for c in codes))
            else:
                m.d.sync += hot.eq(Cat(index == c for c in codes))
            for j, (i, r, k, held_r) in enumerate(muxed):
                value, sx = part(r, k, held_r)
                value = Value.cast(value)
                terms.append(value & hot[j].replicate(len(value)))
                if sx is not None:
                    sign_terms.setdefault(len(value), []).append(sx & hot[j])
        if self._status_ram:
            # The status words in the consumer's RAM: its address looked up from the index in
            # t, its data one more term in t + 1 under a hot bit of its own.
            st_hot = Signal(name="status_hot")
            rd = self.status_rd
            r0 = self._regmap[self._status_ram[0]]
            with m.Switch(index):
                for j, name in enumerate(self._status_ram):
                    with m.Case(_index_of(self._regmap[name].addr, block_bits, picked)):
                        m.d.comb += rd.addr.eq(j)
            m.d.sync += st_hot.eq(0)
            with m.Switch(index):
                for name in self._status_ram:
                    with m.Case(_index_of(self._regmap[name].addr, block_bits, picked)):
                        m.d.sync += st_hot.eq(blk_now & ~bus.we if bram else 1)
            value, sx = part(r0, 0, Value.cast(rd.data))
            value = Value.cast(value)
            terms.append(value & st_hot.replicate(len(value)))
            if sx is not None:
                sign_terms.setdefault(len(value), []).append(sx & st_hot)
        if terms:
            m.d.comb += word.eq(_or_tree(terms))
            for w, bits in sign_terms.items():
                m.d.comb += sign[w].eq(_or_tree(bits))
        value = word
        for w, bit in sign.items():
            value = value | Cat(Const(0, w), bit.replicate(DATA_WIDTH - w))
        with m.If(pending):
            # (With "bram" the hot bits are loaded with the block hit and ~we of their clock t
            # (blk_ok, we), so no word is selected outside a read of the map: no AND here.)
            m.d.sync += [r_data.eq(value if bram else Mux(blk_ok & ~we, value, 0)),
                         *(win_hit[n].eq(win_pend[n]) for n in win_hit)]
            if bram:
                m.d.sync += stage["hit"].eq(stage["pend"])
            with m.If(blk_ok & known):
                m.d.sync += bus.status.eq(Mux(we & read_only, Status.READ_ONLY, Status.OK))
            with m.Else():
                m.d.sync += bus.status.eq(Status.BAD_ADDRESS)
            with m.If(win_wr):
                m.d.sync += bus.status.eq(Status.READ_ONLY)
            for hit in win_pend.values():
                with m.If(hit):
                    m.d.sync += bus.status.eq(Status.OK)
        return m

    def _stage(self, m, pending, sel, blk_ok, we):
        """The staging RAM, its copy / reset-walk sequencer, the active registers' loads and the
        access's staging slot in t + 1 (``staging="bram"``; ``sel``, ``blk_ok``, ``we``: the
        access's registered word select, block hit and direction). Returns the signals the bus
        logic uses."""
        bus = self.bus
        slots = self._slots
        n = len(slots)                          # staging slots: copied, then immediate
        nc = self._copied
        ncnt = len(self._counter_words)         # the counters' words after the slots
        nw = n + ncnt                           # the words the reset walk rewrites
        base = 1 << ceil_log2(nw)               # the reset values' half: word i at base + i
        # One word per slot in its read format (``Register.read_word``: the top word of a
        # signed register sign-extended), so that a read returns the RAM's data as it is; the
        # counters (0 after a reset); the const words after the reset values.
        resets = [r.read_word(r.bits(r.reset), k) for _, r, k in slots] + [0] * ncnt
        consts = [r.read_word(r.bits(r.reset), k) for _, r, k in self._consts]
        # The read port is asynchronous with a register behind it, which yosys merges into a
        # synchronous block RAM port; ``no_rw_check`` lets it leave a read of the word being
        # written undefined (no read-first emulation: no read's data is used in a clock that
        # writes its word, see below), which an Amaranth synchronous read port cannot say.
        m.submodules.staging = mem = Memory(shape=DATA_WIDTH, depth=base + nw + len(consts),
                                            init=resets + [0] * (base - nw) + resets + consts,
                                            attrs={"no_rw_check": 1})
        rd = mem.read_port(domain="comb")
        rd_data = Signal(DATA_WIDTH, reset_less=True)     # the RAM's read data
        m.d.sync += rd_data.eq(rd.data)
        wr = mem.write_port()

        hold = Signal()                         # the RAM read port busy: no access taken
        start = Signal()                        # a copy starts (reads slot 0 in this clock)
        run = Signal(init=1)                    # a copy or the walk reads slot cnt next
        walk = Signal(init=1)                   # the reading is the reset walk
        cnt = Signal(range(nw))
        last = Signal()                         # cnt is the copy's / the walk's last slot
        load = Signal()                         # rd.data holds slot dst: load it
        load_walk = Signal()                    # a load of the walk: into the RAM's slot dst
        dst = Signal(range(nw))
        ram_addr = Signal(range(len(mem.init))) # the access's RAM word (in t + 1)
        formats = self._formats()
        fmt = Signal(range(max(1, len(formats))))       # its word format (index in formats)
        staged = Signal()                       # sel is a staged word (written in the RAM)
        in_ram = Signal()                       # sel is read from the RAM (staged or const)
        wr_pend = Signal()                      # t + 1 of a write to a staged word
        pend = Signal(name="stage_pend")        # t + 1 of a read of a RAM word
        hit = Signal(name="stage_hit")          # t + 2 of it: bus.r_data from the RAM

        # The counters: a count strobe marks its counter pending; the lowest pending one is
        # read (inc_rd) in a clock where the read port is free (no access in t + 1, no copy or
        # walk reading, no walk load writing) and written back + 1 in the next (inc_wr). While
        # one is pending or strobed no access is taken (hold), so a read taken in t returns
        # every count strobed up to t, as a counter flip-flop sampled in t + 1 would.
        inc_hold = Const(0, 1)
        inc_wr = Const(0, 1)                    # (a counter written back: none without counters)
        walk_data = rd_data                     # the RAM's write data of a walk's load / inc_wr
        if ncnt:
            cw = self._counter_words[0][1].width
            incs = Cat(*(getattr(self, f"{r.name}_inc") for _, r, _ in self._counter_words))
            inc_pend = Signal(ncnt)
            inc_rd = Signal()
            inc_wr = Signal()
            walk_data = Cat((rd_data[:cw] + inc_wr)[:cw], rd_data[cw:])
            inc_sel = Signal(range(ncnt))       # the lowest pending counter
            for j in reversed(range(ncnt)):
                with m.If(inc_pend[j]):
                    m.d.comb += inc_sel.eq(j)
            m.d.comb += inc_rd.eq(inc_pend.any() & ~start & ~run & ~pending & ~inc_wr
                                  & ~load_walk)
            m.d.sync += [inc_pend.eq((inc_pend & ~Mux(inc_rd, 1 << inc_sel, 0)) | incs),
                         inc_wr.eq(inc_rd)]
            inc_hold = inc_pend.any() | incs.any()
        m.d.comb += [
            start.eq(self.commit & ~bus.lock & ~run & ~pending),
            hold.eq(start | run | inc_hold),
        ]
        # The copy / walk: read slot cnt (base + cnt in the walk) in one clock, load it in the
        # next. The copy reads the copied slots (0 … nc − 1), the walk every slot. The bus read
        # of a RAM word uses the read port in t + 1 (pending), which never coincides with a
        # reading clock (start needs pending low; accesses are held off while reading).
        if nc == nw:
            m.d.comb += last.eq(cnt == nw - 1)
        else:
            m.d.comb += last.eq(Mux(walk, cnt == nw - 1, cnt == nc - 1))
        with m.If(start | run):
            m.d.sync += [load.eq(1), load_walk.eq(walk), dst.eq(cnt)]
            with m.If(last):
                m.d.sync += [cnt.eq(0), run.eq(0), walk.eq(0)]
            with m.Else():
                m.d.sync += [cnt.eq(cnt + 1), run.eq(1)]
        with m.Else():
            m.d.sync += [load.eq(0), load_walk.eq(0)]
        if ncnt:                                # (the counter written in inc_wr: in dst too)
            with m.If(inc_rd):
                m.d.sync += dst.eq(n + inc_sel)
        walk_addr = Cat(cnt, walk)              # cnt: log2(base) bits
        if ncnt:
            walk_addr = Mux(inc_rd, n + inc_sel, walk_addr)
        m.d.comb += rd.addr.eq(Mux(pending, ram_addr, walk_addr))

        # Active registers: copied slot i's word from the RAM in the copy's load clock
        # s + 1 + i, told by bit i of a one-hot shift register (no compare of dst per slot).
        # With export it has bits only for the slots with flip-flops (not exported): along a
        # run of them it shifts; the first after exported slots is ``cnt == i`` registered (two
        # LUT4 with its flip-flop, where a stage per exported slot is a lone flip-flop each).
        # That compare is also true in the reset walk's reading clock of slot i: the walk's
        # loads then write the active words from slot i on with their reset values (the walk
        # reads the RAM's reset half), which they hold already (the walk runs only after a
        # reset; commits and accesses wait for it). Without export: one chain, copies only.
        ld = Signal(nc, name="copy_ld")
        for i, (_, r, _) in enumerate(slots[:nc]):
            if r.name in self._export:
                continue                        # (stays 0)
            if i == 0:
                m.d.sync += ld[i].eq(start)
            elif slots[i - 1][1].name not in self._export:
                m.d.sync += ld[i].eq(ld[i - 1])
            else:
                m.d.sync += ld[i].eq(cnt == i)
        for i, (_, r, k) in enumerate(slots[:nc]):
            if r.name in self._export:
                continue                        # on the export port instead (below)
            lo, hi = r.word_slice(k)
            with m.If(ld[i]):
                if r.name in self._derived:     # (one word: lo, hi = 0, width)
                    m.d.sync += getattr(self, r.name).eq(self._derive(r, rd_data))
                else:
                    m.d.sync += _bits(getattr(self, r.name))[lo:hi].eq(rd_data[:hi - lo])
            if r.name in self._changed:             # (one word: lo, hi = 0, width; not derived)
                m.d.sync += getattr(self, f"{r.name}_changed").eq(
                    ld[i] & (rd_data[:hi - lo] != _bits(getattr(self, r.name))))
        # The export port: the exported slot's word in its load clock, copy or walk (``load``
        # with ``dst``), its export index and whether it is one looked up from ``cnt`` in the
        # reading clock and registered beside ``dst`` (no decode of ``dst`` behind a register).
        if self._export:
            index_of = {self._slot_of[a]: j for j, (a, _, _) in enumerate(self._export_words)}
            exp_on = Signal(name="export_on")
            exp_index = Signal(range(len(self._export_words)), name="export_index")
            exp_on_c = Signal()
            exp_index_c = Signal.like(exp_index)
            with m.Switch(cnt):
                for i, j in sorted(index_of.items()):
                    with m.Case(i):
                        m.d.comb += [exp_on_c.eq(1), exp_index_c.eq(j)]
            with m.If(start | run):
                m.d.sync += [exp_on.eq(exp_on_c), exp_index.eq(exp_index_c)]
            m.d.comb += [self.export.valid.eq(load & exp_on), self.export.index.eq(exp_index),
                         self.export.data.eq(rd_data),
                         self.export_walk.eq(walk | load_walk)]

        # t + 1: the access's RAM word (the word select's code itself), whether it is a slot
        # (code below n) and the slot's word format (a table of the code's low bits).
        flag = sel[-1]
        m.d.comb += [in_ram.eq(~flag), ram_addr.eq(sel[:-1]),
                     staged.eq(~flag & ~at_least(sel[:-1], n))]
        fbits = ceil_log2(n)
        fw = len(fmt)
        table = [formats.index(self._word_format(r, k)) for _, r, k in slots]
        table += [0] * ((1 << fbits) - n)
        if fw and fbits:                        # (else one format, or one slot: constant)
            m.d.comb += fmt.eq(Const(sum(f << (fw * i) for i, f in enumerate(table)),
                                     fw << fbits).word_select(sel[:fbits], fw))
        else:
            m.d.comb += fmt.eq(table[0])
        m.d.comb += [wr_pend.eq(pending & blk_ok & staged & we),
                     pend.eq(pending & blk_ok & in_ram & ~we)]

        w_fmt = Signal(DATA_WIDTH)
        with m.Switch(fmt):
            for j, (width, signed) in enumerate(formats):
                with m.Case(j):
                    word = bus.w_data[:width]
                    m.d.comb += w_fmt.eq(word.as_signed() if signed else word)
        # (never both: inc_rd waits for the walk's last load)
        m.d.comb += [
            wr.addr.eq(Mux(load_walk | inc_wr, dst, ram_addr)),
            wr.data.eq(Mux(load_walk | inc_wr, walk_data, w_fmt)),
            wr.en.eq((load & load_walk) | wr_pend | inc_wr),
        ]
        if self._mirror:
            # The staging RAM's writes of the mirrored slots (a write's t + 1, a walk's load):
            # the slot's mirror index looked up from the write address.
            mirror_of = {self._slot_of[a]: j for j, (a, _, _) in enumerate(self._mirror_words)}
            hit_c = Signal(name="mirror_hit")
            with m.Switch(wr.addr):
                for i, j in sorted(mirror_of.items()):
                    with m.Case(i):
                        m.d.comb += [hit_c.eq(1), self.mirror.index.eq(j)]
            m.d.comb += [self.mirror.valid.eq(wr.en & hit_c), self.mirror.data.eq(wr.data)]
        return {"hold": hold, "rd_data": rd_data, "pend": pend, "hit": hit, "staged": staged}

    def _sel_code(self, addr, r):
        """``staging="bram"``: the word select's code of the word at ``addr`` of register ``r``:
        its RAM address if it is in the RAM, else the flag bit with 1 (read-only) or 2
        (strobe)."""
        if addr in self._ram_addr:
            return self._ram_addr[addr]
        return self._sel_none | (1 if r.access in (Access.RO, Access.CONST) else 2)

    def _derive(self, r, word):
        """The Out member's value of a ``derived`` register ``r`` from ``word`` (its raw value
        in the low bits)."""
        raw = word[:r.width]
        return self._derived[r.name].value(raw.as_signed() if r.signed else raw)

    @staticmethod
    def _word_format(r, k):
        """``(width, sign-extended)`` of word ``k`` of register ``r`` as it is read."""
        lo, hi = r.word_slice(k)
        return hi - lo, bool(r.signed and k == r.words - 1 and hi - lo < DATA_WIDTH)

    def _formats(self):
        """The distinct word formats (:meth:`_word_format`) of the staged words, in slot order."""
        out = []
        for _, r, k in self._slots:
            if self._word_format(r, k) not in out:
                out.append(self._word_format(r, k))
        return out

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

    def _write(self, m, r, k, held):
        """A write to word ``k`` of ``rw`` / ``strobe`` register ``r`` holding ``held`` (inside
        its address ``Case`` of a write access, clock t)."""
        bus = self.bus
        lo, hi = r.word_slice(k)
        if r.access is Access.STROBE:
            m.d.sync += getattr(self, r.name).eq(bus.w_data[0])
        elif r.name in self._derived:           # (an immediate one: its Out member)
            m.d.sync += getattr(self, r.name).eq(self._derive(r, bus.w_data))
        else:
            m.d.sync += held[lo:hi].eq(bus.w_data[:hi - lo])
