# Ref: issue 6 item 3 (a compiled engine behind the same API as Amaranth's simulator, checked
#      cycle for cycle against it); DESIGN.md "Simulation is the product too"; docs/PROTOCOL.md
#      §Physical layer (UART 8N1, LSB first) for the UART codec
"""The simulated board (:class:`SimTop`), the engine API both engines implement, the UART codec.

:class:`SimTop` is :class:`~foc_servo.hdl.top.Top` plus an :class:`~foc_servo.sim.adc_chip.AdcChip`
on its ADC pins, with the other pins packed into two words: ``pins_in`` (:data:`IN_LAYOUT`) and
``pins_out`` (:data:`OUT_LAYOUT`), plus ``adc_codes`` (the four 16-bit codes the ADC converts).

Engine API
----------
``make_engine(kind, **top_kwargs)`` (:mod:`foc_servo.sim.engines`) builds an :class:`Engine`:
``"pysim"`` (:class:`~.pysim.PysimEngine`, Amaranth's simulator, the reference) or ``"compiled"``
(:class:`~.compiled.CompiledEngine`, Verilator). Both behave identically, cycle for cycle:

* **Clocks.** Clock ``k`` is the ``k``-th rising clock edge after the start (``k = 1, 2, …``);
  :attr:`Engine.now` is the number of edges simulated so far (0 at the start). The state starts
  at the design's init values (no reset pulse is applied).
* **Inputs** change only through events: a numpy array of :data:`EVENT_DTYPE`
  (``clock`` u8, ``port`` u1, ``value`` u8), sorted by clock; port :data:`PORT_PINS_IN` (0) sets
  the whole ``pins_in`` word, :data:`PORT_ADC_CODES` (1) the whole ``adc_codes`` word. An event at
  clock ``c`` takes effect before edge ``c`` (edge ``c`` samples it) and holds until changed; of
  several events for one port at one clock the last wins. ``pins_in`` starts at
  :data:`IN_INIT` (``uart_rx`` and ``fault_n`` high), ``adc_codes`` at 0.
* ``run(until, events=None, stop_mask=0)`` simulates edges ``now + 1 … until``. After each edge
  ``c`` it compares ``pins_out`` with its value before; each change is recorded as
  ``(c, new word)``. If the changed bits and ``stop_mask`` share a bit, the run stops after that
  edge (``now = c``). Events at a clock ``<= now`` raise :exc:`ValueError`; events after the clock
  where the run stops are not applied (the caller passes them again next time). It returns a
  :class:`RunResult`: ``now``, ``out`` (:data:`OUT_DTYPE` array of the changes), ``stopped``, and
  ``out_before`` (``pins_out`` before the call), so the caller can rebuild every level.
* :attr:`Engine.pins_in`, :attr:`Engine.adc_codes`, :attr:`Engine.pins_out`: the current words.
* ``reset()`` goes back to clock 0 without elaborating or compiling anything again.
* An exception from a run (a failed ``Assert`` of the design: :exc:`AssertionError`) leaves
  the engine unusable until ``reset()``.
* ``pins_out`` is read after each edge with the inputs of that edge: every output of
  :class:`~foc_servo.hdl.top.Top` is registered, so an input event never changes an output
  between edges.

The UART codec turns host bytes into ``uart_rx`` events (:func:`uart_events`) and ``uart_tx``
changes back into bytes (:class:`UartDecoder`), so the host link needs no UART gateware on the
host side and no Python per clock.
"""

import copy
import dataclasses
import math
import numbers

import numpy as np
from amaranth.hdl import ClockDomain, Module, Signal, Value
from amaranth.lib import data, wiring
from amaranth.lib.wiring import In, Out

from ...hdl.top import Top
from ...hdl.uart import PHASE_BITS, uart_params
from ..adc_chip import AdcChip

__all__ = [
    "IN_LAYOUT", "OUT_LAYOUT", "IN_BITS", "OUT_BITS", "IN_MASKS", "OUT_MASKS", "IN_INIT",
    "IN_WIDTH", "OUT_WIDTH", "EVENT_DTYPE", "OUT_DTYPE", "PORT_PINS_IN", "PORT_ADC_CODES",
    "SimTop", "RunResult", "Engine", "uart_events", "UartDecoder", "UartFramingError",
]

#: ``pins_in``: the controller's input pins except the ADC's SDO lines (driven by the AdcChip).
IN_LAYOUT = data.StructLayout({
    "uart_rx": 1, "enc_a": 1, "enc_b": 1, "enc_z": 1, "hall": 3, "fault_n": 1, "oc_comp": 1,
})
#: ``pins_out``: the controller's output pins except SCLK (it toggles too often to be an event).
OUT_LAYOUT = data.StructLayout({
    "uart_tx": 1, "gate_h": 3, "gate_l": 3, "adc_cs_n": 1, "led": 2,
})
#: Bit position of each field's bit 0 in the words, e.g. ``OUT_BITS["adc_cs_n"]``.
IN_BITS = {name: field.offset for name, field in IN_LAYOUT}
OUT_BITS = {name: field.offset for name, field in OUT_LAYOUT}
#: Each field's bits in place, e.g. ``(word & OUT_MASKS["gate_h"]) >> OUT_BITS["gate_h"]``.
IN_MASKS = {name: ((1 << field.width) - 1) << field.offset for name, field in IN_LAYOUT}
OUT_MASKS = {name: ((1 << field.width) - 1) << field.offset for name, field in OUT_LAYOUT}
IN_WIDTH = IN_LAYOUT.size
OUT_WIDTH = OUT_LAYOUT.size
#: ``pins_in`` at the start: the UART line idle (high), no driver fault (``fault_n`` high).
IN_INIT = (1 << IN_BITS["uart_rx"]) | (1 << IN_BITS["fault_n"])

#: Input events: (clock, port, value).
EVENT_DTYPE = np.dtype([("clock", "<u8"), ("port", "<u1"), ("value", "<u8")])
#: Output changes: (clock, pins_out word after that clock's edge).
OUT_DTYPE = np.dtype([("clock", "<u8"), ("value", "<u8")])
PORT_PINS_IN = 0
PORT_ADC_CODES = 1


class SimTop(wiring.Component):
    """The controller on a simulated board: :class:`~foc_servo.hdl.top.Top` and an
    :class:`~foc_servo.sim.adc_chip.AdcChip` on its ADC pins, the other pins packed in words.

    Parameters
    ----------
    **top_kwargs
        Passed to :class:`~foc_servo.hdl.top.Top` (``clk_hz``, ``pwm_hz``, ``baud``,
        ``dead_time_s``, ``scales``, …); its errors propagate.

    Members
    -------
    pins_in : In(IN_LAYOUT, init=IN_INIT)
        ``uart_rx``, ``enc_a``, ``enc_b``, ``enc_z``, ``hall`` (3), ``fault_n``, ``oc_comp``.
    adc_codes : In(64)
        The AdcChip's ``codes``: 16-bit two's complement codes of channels A (bits 0–15, phase a
        current), B (phase b current), C (U_dc), D (unused).
    pins_out : Out(OUT_LAYOUT)
        ``uart_tx``, ``gate_h`` (3), ``gate_l`` (3), ``adc_cs_n``, ``led`` (2).

    Attributes
    ----------
    top : Top
    clk_hz : float
    clk : Signal
        The clock of the design's only domain, ``sync``, which has no reset (the state starts at
        the init values); a port of the Verilog (:meth:`ports`).
    cycle : Signal(64)
        Clock edges so far (for testbenches; not a port, so Verilator drops it).
    top_kwargs : dict or None
        A copy of the parameters, taken at construction (the compiled engine's cache keys on
        them); ``None`` if they cannot be copied.
    """

    def __init__(self, **top_kwargs):
        self._top = Top(**top_kwargs)
        try:
            self._top_kwargs = copy.deepcopy(top_kwargs)
        except Exception:       # anything deepcopy cannot copy: no parameter-keyed cache
            self._top_kwargs = None
        self._chip = AdcChip()
        self._domain = ClockDomain("sync", reset_less=True)
        self.cycle = Signal(64)
        super().__init__({
            "pins_in": In(IN_LAYOUT, init={"uart_rx": 1, "fault_n": 1}),
            "adc_codes": In(64),
            "pins_out": Out(OUT_LAYOUT),
        })

    top = property(lambda self: self._top)
    clk_hz = property(lambda self: self._top.clk_hz)
    clk = property(lambda self: self._domain.clk)

    @property
    def top_kwargs(self):
        """A copy of the parameters given at construction (``None``: not copyable)."""
        return None if self._top_kwargs is None else copy.deepcopy(self._top_kwargs)

    def ports(self):
        """The ports for ``verilog.convert`` / ``rtlil.convert``: the members and the clock."""
        return [Value.cast(self.pins_in), Value.cast(self.adc_codes), Value.cast(self.pins_out),
                self.clk]

    def elaborate(self, platform):
        m = Module()
        # No reset: the state starts at the init values and nothing ever resets it. (With a
        # reset input, Verilator would recompute all the next-state logic that depends on it on
        # every evaluation: several times slower.)
        m.domains.sync = self._domain
        m.d.sync += self.cycle.eq(self.cycle + 1)
        m.submodules.top = top = self._top
        m.submodules.adc_chip = chip = self._chip
        pi, po = self.pins_in, self.pins_out
        m.d.comb += [
            top.uart_rx.eq(pi.uart_rx),
            top.enc_a.eq(pi.enc_a), top.enc_b.eq(pi.enc_b), top.enc_z.eq(pi.enc_z),
            top.hall.eq(pi.hall),
            top.fault_n.eq(pi.fault_n),
            top.oc_comp.eq(pi.oc_comp),
            chip.cs_n.eq(top.adc_cs_n),
            chip.sclk.eq(top.adc_sclk),
            top.adc_sdo.eq(chip.sdo),
            chip.codes.eq(self.adc_codes),
            po.uart_tx.eq(top.uart_tx),
            po.gate_h.eq(top.gate_h),
            po.gate_l.eq(top.gate_l),
            po.adc_cs_n.eq(top.adc_cs_n),
            po.led.eq(top.led),
        ]
        return m


@dataclasses.dataclass(frozen=True)
class RunResult:
    """What :meth:`Engine.run` returns.

    Attributes
    ----------
    now : int
        The clock reached (the engine's :attr:`Engine.now` after the call).
    out : numpy array of OUT_DTYPE
        Every change of ``pins_out`` in the call: (clock, new word), increasing clocks.
    stopped : bool
        The run stopped early on a change in ``stop_mask`` (at clock ``now``).
    out_before : int
        ``pins_out`` before the call.
    """
    now: int
    out: np.ndarray
    stopped: bool
    out_before: int


def _is_int(value):
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


class Engine:
    """A cycle-accurate simulation of :class:`SimTop` behind the API of the module docstring.

    Subclasses implement ``_reset`` and ``_run``; this class validates the arguments and keeps
    the words.

    Attributes
    ----------
    simtop : SimTop
    clk_hz : float
    now : int
        Clock edges simulated so far.
    pins_in, adc_codes, pins_out : int
        The current input and output words.
    """

    kind = None

    def __init__(self, simtop):
        if not isinstance(simtop, SimTop):
            raise TypeError(f"Engine simtop must be a SimTop, not {simtop!r}")
        self._simtop = simtop
        self._now = 0
        self._pins_in = IN_INIT
        self._adc_codes = 0
        self._pins_out = 0
        self._failed = None

    simtop = property(lambda self: self._simtop)
    clk_hz = property(lambda self: self._simtop.clk_hz)
    now = property(lambda self: self._now)
    pins_in = property(lambda self: self._pins_in)
    adc_codes = property(lambda self: self._adc_codes)
    pins_out = property(lambda self: self._pins_out)

    def reset(self):
        """Back to clock 0 and the init values (cheaper than a new engine: nothing is
        elaborated or compiled again)."""
        self._pins_out = int(self._reset())
        self._now = 0
        self._pins_in = IN_INIT
        self._adc_codes = 0
        self._failed = None

    def run(self, until, events=None, stop_mask=0):
        """Simulate edges ``now + 1 … until`` (module docstring).

        Parameters
        ----------
        until : int
            Last clock to simulate, ``>= now``.
        events : numpy array of EVENT_DTYPE, or None
            Input changes, sorted by clock, all at clocks ``> now``.
        stop_mask : int
            ``pins_out`` bits whose change stops the run (0: run to ``until``).

        Returns
        -------
        RunResult

        Raises
        ------
        TypeError
            An argument of the wrong type.
        ValueError
            ``until`` before ``now``, events unsorted, in the past, on an unknown port or too
            wide for it, a ``stop_mask`` outside ``pins_out``.
        AssertionError
            An ``Assert`` of the design failed (the engine cannot continue: a later call raises
            :exc:`RuntimeError`).
        """
        name = type(self).__name__
        if not _is_int(until):
            raise TypeError(f"{name} until must be an integer clock, not {until!r}")
        until = int(until)
        if until < self._now:
            raise ValueError(f"{name} until must be at least the clock reached, {self._now}, "
                             f"not {until}")
        if not _is_int(stop_mask):
            raise TypeError(f"{name} stop_mask must be an integer, not {stop_mask!r}")
        if not 0 <= stop_mask < 1 << OUT_WIDTH:
            raise ValueError(f"{name} stop_mask must be 0 … {(1 << OUT_WIDTH) - 1} "
                             f"(pins_out bits), not {stop_mask!r}")
        events = self._check_events(events)
        if self._failed is not None:
            raise RuntimeError(f"{name} cannot continue after the error in an earlier run "
                               f"({self._failed!r}): reset() first")
        before = self._pins_out
        # Events beyond `until` can never be applied in this call.
        events = events[:np.searchsorted(events["clock"], until, side="right")]
        try:
            now, out, stopped, used = self._run(until, events, int(stop_mask))
        except BaseException as exc:    # the simulation state is undefined from here on
            self._failed = exc
            raise
        applied = events[:used]
        for port, attr in ((PORT_PINS_IN, "_pins_in"), (PORT_ADC_CODES, "_adc_codes")):
            idx = np.flatnonzero(applied["port"] == port)
            if len(idx):
                setattr(self, attr, int(applied["value"][idx[-1]]))
        self._now = int(now)
        if len(out):
            self._pins_out = int(out["value"][-1])
        return RunResult(now=self._now, out=out, stopped=bool(stopped), out_before=before)

    def _check_events(self, events):
        name = type(self).__name__
        if events is None:
            return np.zeros(0, dtype=EVENT_DTYPE)
        if isinstance(events, np.ndarray):
            if events.dtype.names != EVENT_DTYPE.names:
                raise TypeError(f"{name} events must be an array of EVENT_DTYPE, not one of "
                                f"{events.dtype}")
            for field in EVENT_DTYPE.names:
                column = events[field]
                if column.dtype.kind not in "ui":
                    raise TypeError(f"{name} event {field}s must be integers, not "
                                    f"{column.dtype}")
                if column.dtype.kind == "i" and (column < 0).any():
                    raise ValueError(f"{name} event {field}s must not be negative, not "
                                     f"{int(column.min())}")
            events = np.ascontiguousarray(events.astype(EVENT_DTYPE, copy=False).reshape(-1))
        else:
            try:
                events = np.array(list(events), dtype=EVENT_DTYPE)
            except (TypeError, ValueError, OverflowError):
                raise TypeError(f"{name} events must be an array of EVENT_DTYPE or (clock, port, "
                                f"value) tuples, not {events!r}") from None
        if not len(events):
            return events
        clocks = events["clock"]
        if np.any(clocks[1:] < clocks[:-1]):
            k = int(np.flatnonzero(clocks[1:] < clocks[:-1])[0]) + 1
            raise ValueError(f"{name} events must be sorted by clock, but event {k} (clock "
                             f"{int(clocks[k])}) comes after clock {int(clocks[k - 1])}")
        if int(clocks[0]) <= self._now:
            raise ValueError(f"{name} event clocks must be after the clock reached, "
                             f"{self._now}, not {int(clocks[0])} (event 0: a past event)")
        bad = ~np.isin(events["port"], [PORT_PINS_IN, PORT_ADC_CODES])
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            raise ValueError(f"{name} event port must be {PORT_PINS_IN} (pins_in) or "
                             f"{PORT_ADC_CODES} (adc_codes), not {int(events['port'][k])} "
                             f"(event {k})")
        wide = (events["port"] == PORT_PINS_IN) & (events["value"] >> np.uint64(IN_WIDTH) != 0)
        if wide.any():
            k = int(np.flatnonzero(wide)[0])
            raise ValueError(f"{name} pins_in event value must be below 2**{IN_WIDTH}, "
                             f"not {int(events['value'][k])} (event {k})")
        return events

    def _reset(self):
        """Restart the simulation at clock 0; return ``pins_out`` there."""
        raise NotImplementedError

    def _run(self, until, events, stop_mask):
        """Simulate; return ``(now, out, stopped, events applied)`` (``events`` is validated and
        holds only clocks ``<= until``)."""
        raise NotImplementedError


# --- UART codec -----------------------------------------------------------------------------

def _bit_clocks(clk_hz, baud, name):
    """Clocks per bit as the gateware's phase accumulator makes them: ``2**PHASE_BITS / inc``."""
    inc = uart_params(name, clk_hz, baud)
    return (1 << PHASE_BITS) / inc, inc


def uart_events(data, *, start_clock, clk_hz, baud, current_pins_in=IN_INIT):
    """``uart_rx`` events that send ``data`` (8N1, LSB first, back to back) from ``start_clock``.

    Bit ``j`` of the stream (start, 8 data, stop, next start, …) begins at clock
    ``start_clock + ceil(j · 2**PHASE_BITS / inc)`` with ``inc`` the gateware's phase increment
    (:func:`~foc_servo.hdl.uart.uart_params`), i.e. at the rate the gateware's UART runs at and
    whose bits its receiver samples in their middle.

    Parameters
    ----------
    data : bytes
    start_clock : int
        Clock of the first start bit's falling edge (an event clock: ``> engine.now``).
    clk_hz, baud : float
        As the :class:`~foc_servo.hdl.top.Top` was built.
    current_pins_in : int
        The ``pins_in`` word the events modify (only ``uart_rx`` changes); its ``uart_rx`` must
        be high (idle).

    Returns
    -------
    numpy array of EVENT_DTYPE
        Port-0 events at each level change; the last one, at the end of the last stop bit (the
        earliest clock the next byte may start), repeats the idle level.

    Raises
    ------
    TypeError, ValueError
        Bad arguments (the baud-rate checks of :func:`~foc_servo.hdl.uart.uart_params`).
    """
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise TypeError(f"uart_events data must be bytes, not {data!r}")
    if not _is_int(start_clock):
        raise TypeError(f"uart_events start_clock must be an integer clock, not {start_clock!r}")
    if start_clock < 1:
        raise ValueError(f"uart_events start_clock must be at least 1, not {start_clock!r}")
    if not _is_int(current_pins_in) or not 0 <= current_pins_in < 1 << IN_WIDTH:
        raise TypeError(f"uart_events current_pins_in must be a pins_in word, "
                        f"not {current_pins_in!r}")
    rx = IN_MASKS["uart_rx"]
    if not current_pins_in & rx:
        raise ValueError("uart_events needs the uart_rx line idle (high) in current_pins_in")
    _, inc = _bit_clocks(clk_hz, baud, "uart_events")
    data = bytes(data)
    if not data:
        return np.zeros(0, dtype=EVENT_DTYPE)
    levels = []
    for byte in data:
        levels += [0] + [(byte >> k) & 1 for k in range(8)] + [1]
    levels.append(1)                                       # the idle line after the last stop
    j = np.arange(len(levels), dtype=np.int64)
    starts = start_clock + (j * (1 << PHASE_BITS) + inc - 1) // inc     # ceil(j · 2**24 / inc)
    levels = np.asarray(levels, dtype=np.int64)
    keep = np.concatenate([[True], levels[1:] != levels[:-1]])
    keep[-1] = True
    base = current_pins_in & ~rx
    ev = np.zeros(int(keep.sum()), dtype=EVENT_DTYPE)
    ev["clock"] = starts[keep]
    ev["port"] = PORT_PINS_IN
    ev["value"] = base | (levels[keep] << IN_BITS["uart_rx"])
    return ev


class UartFramingError(ValueError):
    """The decoded line had a low stop bit."""


class UartDecoder:
    """Bytes from the ``uart_tx`` changes in :attr:`RunResult.out` (8N1, LSB first).

    Samples each bit at its centre, ``(j + 0.5)`` bit times after the start bit's falling edge
    (bit time ``2**PHASE_BITS / inc`` clocks, as the gateware's transmitter), and looks for the
    next start edge after the stop bit's centre, as the gateware's receiver does. A start bit
    found high at its centre is a glitch and is ignored.

    Parameters
    ----------
    clk_hz, baud : float
        As the :class:`~foc_servo.hdl.top.Top` was built.

    Attributes
    ----------
    busy : bool
        A byte has begun and is not complete yet.
    bytes_out : int
        Bytes decoded so far.
    """

    def __init__(self, clk_hz, baud):
        self._bit, _ = _bit_clocks(clk_hz, baud, "UartDecoder")
        self._level = 1             # line level before the first pending change
        self._changes = []          # (clock, level) after self._level, increasing clocks
        self._known = 0             # the line is known up to (and including) this clock
        self._start = None          # clock of the pending byte's start edge
        self._after = 0             # the next start edge must come after this clock
        self.bytes_out = 0

    @property
    def busy(self):
        return self._start is not None

    def _level_at(self, t):
        level = self._level
        for c, v in self._changes:
            if c > t:
                break
            level = v
        return level

    def feed(self, out, *, tx_offset=OUT_BITS["uart_tx"], now=None):
        """Take the next output changes; return the bytes completed.

        Parameters
        ----------
        out : numpy array of OUT_DTYPE
            Changes in increasing clock order, after those fed before.
        tx_offset : int
            Bit of ``uart_tx`` in the words.
        now : int or None
            The clock up to which the line is known (the engine's ``now``); ``None``: the last
            change's clock (a byte whose stop bit centre lies beyond it completes on a later
            call).

        Raises
        ------
        UartFramingError
            A stop bit was low (the bytes completed before it are in its ``data``); the decoder
            then waits for the line to go high again.
        """
        if len(out):
            clocks = out["clock"].astype(np.int64)
            bits = ((out["value"] >> np.uint64(tx_offset)) & np.uint64(1)).astype(np.int64)
            prev = self._changes[-1][1] if self._changes else self._level
            lv = np.concatenate([[prev], bits])
            edge = np.flatnonzero(lv[1:] != lv[:-1])
            self._changes += list(zip(clocks[edge].tolist(), bits[edge].tolist()))
            self._known = max(self._known, int(clocks[-1]))
        if now is not None:
            self._known = max(self._known, int(now))
        got = bytearray()
        bit = self._bit
        while True:
            if self._start is None:
                # The next falling edge after self._after (changes alternate, so a falling edge
                # always follows a high line: after a framing error this waits for the line to
                # go high first, as the gateware's receiver does).
                self._start = next((c for c, v in self._changes if v == 0 and c > self._after),
                                   None)
                if self._start is None:
                    self._drop(self._known)
                    break
            start = self._start
            stop_centre = math.floor(start + 9.5 * bit)
            if self._known < stop_centre:
                break
            samples = [self._level_at(math.floor(start + (j + 0.5) * bit)) for j in range(10)]
            self._start = None
            if samples[0] != 0:         # a glitch, not a start bit: look for the next edge
                self._after = start
                continue
            self._after = stop_centre
            self._drop(stop_centre)
            if samples[9] != 1:
                err = UartFramingError(f"UART framing error: the stop bit of the byte that "
                                       f"started at clock {start} is low")
                err.data = bytes(got)   # the bytes completed before it
                raise err
            got.append(sum(b << k for k, b in enumerate(samples[1:9])))
            self.bytes_out += 1
        return bytes(got)

    def _drop(self, t):
        """Forget changes at clocks <= t (their level becomes the base level)."""
        k = 0
        while k < len(self._changes) and self._changes[k][0] <= t:
            self._level = self._changes[k][1]
            k += 1
        del self._changes[:k]
