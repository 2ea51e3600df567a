# Ref: issue 4 item 7; Analog Devices AD7380-4 data sheet, Specifications → Timing Specifications
#      table and serial interface timing diagrams (4-wire mode, SPI mode 3, two's complement
#      output); the limits used are the record :data:`foc_servo.hdl.adc.AD7380_4` (its comment
#      says which come from where).
"""Pin-level model of the AD7380-4 for the Amaranth simulator, with datasheet timing checks.

:class:`AdcPartModel` is a stand-in for the real part, run with ``sim.add_process`` (or
:func:`foc_servo.sim.harness.simulate`'s ``processes``). It watches ``CS`` and ``SCLK`` once per
system clock (the gateware drives both from registers, so every edge falls on a clock edge and the
clock count measures times exactly) and behaves as the part does:

* every CS falling edge samples the inputs (``source(n)`` gives the codes of conversion ``n``),
  starts conversion ``n`` (done ``t_CONVERT`` later) and loads the output shift registers with the
  result of the *previous* conversion;
* in a CS-low frame each SCLK falling edge launches the next bit (MSB first) on every SDOx line;
  the new bit appears one system clock after the edge (a pessimistic ``t_DSDO``), and before the
  first falling edge and after the 16th the lines carry junk;
* the datasheet limits are checked and the first violation raises :class:`AdcTimingError`, whose
  message names the parameter: ``t_CONVERT`` (a CS falling edge, i.e. a read, before the previous
  conversion has finished: reading during conversion), ``t_CYC``, ``t_CSH``, ``t_SCLK``
  (SCLK too fast), ``t_SCLKH``, ``t_SCLKL``, ``t_SCLKED``.

The log (:attr:`AdcPartModel.conversions`, :attr:`AdcPartModel.reads`) lets a test check which
conversion each frame returned.
"""

import numpy as np

from ..hdl.adc import PARTS, AdcPart

__all__ = ["AdcTimingError", "AdcPartModel"]


class AdcTimingError(Exception):
    """The gateware violated a datasheet timing parameter of the ADC."""


class AdcPartModel:
    """Pin-level model of an :class:`~foc_servo.hdl.adc.AdcPart` (default the AD7380-4).

    Parameters
    ----------
    cs_n, sclk : Signal
        The pins driven by the interface.
    sdo : Signal
        The SDO lines (``part.lines`` bits, bit 0 = SDOA), driven by the model.
    clk_hz : float
        The frequency of the simulation's clock (the truth, whatever the interface was told).
    source : callable
        ``source(n)`` returns the ``part.lines`` codes (signed integers) converted by the ``n``-th
        CS falling edge (``n`` from 0).
    part : str or AdcPart
        The datasheet limits checked (default ``"AD7380-4"``).
    seed : int
        Seed of the junk driven on SDO outside the data bits.

    Attributes
    ----------
    conversions : list of (float, tuple)
        Start time (s) and codes of every conversion.
    reads : list of (int, int)
        For every CS-low frame: the index of the conversion whose result was shifted out (−1
        before the first conversion) and the number of SCLK falling edges it had.
    """

    def __init__(self, *, cs_n, sclk, sdo, clk_hz, source, part="AD7380-4", seed=0):
        self._part = PARTS[part] if isinstance(part, str) else part
        if not isinstance(self._part, AdcPart):
            raise TypeError(f"AdcPartModel part must be a part name or an AdcPart, not {part!r}")
        self.cs_n, self.sclk, self.sdo = cs_n, sclk, sdo
        self._period = 1.0 / clk_hz
        self._source = source
        self._rng = np.random.default_rng(seed)
        self.conversions = []
        self.reads = []

    def _ns(self, clocks):
        return clocks * self._period * 1e9

    def _check(self, ok, param, what, clocks, limit_s):
        if not ok:
            raise AdcTimingError(
                f"{self._part.name} {param} violated: {what} was {self._ns(clocks):.1f} ns, "
                f"the data sheet requires at least {limit_s * 1e9:.1f} ns")

    def _junk(self):
        return int(self._rng.integers(0, 1 << self._part.lines))

    def _word(self, codes, bit):
        """The SDO lines while bit ``bit`` (0 = MSB) of ``codes`` is shifted out."""
        shift = self._part.bits - 1 - bit
        return sum(((c >> shift) & 1) << k for k, c in enumerate(codes))

    async def process(self, ctx):
        """The ``add_process`` coroutine."""
        part = self._part
        p = self._period
        eps = 1e-6 * p
        now = 0                       # clock edges seen
        cs, sclk = 1, 1
        last_fall = last_rise = None  # CS edges (clock index of the edge)
        conv_done = None              # clock index at which the running conversion completes
        result = None                 # index of the last completed conversion
        running = None                # index of the running conversion
        out_conv = -1                 # conversion being shifted out in this frame
        nfall = 0                     # SCLK falling edges in this frame
        sclk_fall = sclk_rise = None
        ctx.set(self.sdo, self._junk())

        async for _clk, _rst, new_cs, new_sclk in ctx.tick().sample(self.cs_n, self.sclk):
            now += 1
            edge = now - 1            # a change seen now happened at the previous clock edge
            if conv_done is not None and edge >= conv_done:
                result, running, conv_done = running, None, None

            if new_cs != cs:
                if not new_cs:        # CS falling edge: sample, convert, load the output
                    if last_fall is not None:
                        dt = edge - last_fall
                        self._check(dt * p + eps >= part.t_convert_s, "t_CONVERT",
                                    "the time from the conversion start to the next CS falling "
                                    "edge (reading during conversion)", dt, part.t_convert_s)
                        self._check(dt * p + eps >= part.t_cyc_s, "t_CYC",
                                    "the time between CS falling edges", dt, part.t_cyc_s)
                    if last_rise is not None:
                        dt = edge - last_rise
                        self._check(dt * p + eps >= part.t_csh_s, "t_CSH", "the CS high time",
                                    dt, part.t_csh_s)
                    if conv_done is not None:    # defensive: t_CONVERT above already failed
                        result, running, conv_done = running, None, None
                    out_conv = -1 if result is None else result
                    n = len(self.conversions)
                    codes = tuple(int(c) for c in self._source(n))
                    self.conversions.append((edge * p, codes))
                    running = n
                    conv_done = edge + max(1, int(np.ceil(part.t_convert_s / p - 1e-6)))
                    last_fall = edge
                    nfall = 0
                    sclk_fall = sclk_rise = None
                    ctx.set(self.sdo, self._junk())
                else:                 # CS rising edge: end of frame, SDO three-state (junk)
                    last_rise = edge
                    self.reads.append((out_conv, nfall))
                    ctx.set(self.sdo, self._junk())
                cs = new_cs

            if new_sclk != sclk:
                if not cs:
                    if not new_sclk:  # falling edge: launch the next bit
                        if nfall == 0:
                            dt = edge - last_fall
                            self._check(dt * p + eps >= part.t_sclked_s, "t_SCLKED",
                                        "the time from CS falling to the first SCLK falling edge",
                                        dt, part.t_sclked_s)
                        if sclk_fall is not None:
                            dt = edge - sclk_fall
                            self._check(dt * p + eps >= 1 / part.f_sclk_max_hz, "t_SCLK",
                                        "the SCLK period (SCLK too fast)", dt,
                                        1 / part.f_sclk_max_hz)
                        if sclk_rise is not None:
                            dt = edge - sclk_rise
                            self._check(dt * p + eps >= part.t_sclkh_s, "t_SCLKH",
                                        "the SCLK high time", dt, part.t_sclkh_s)
                        # Seen one clock after the edge: the new bit appears now (t_DSDO).
                        if nfall < part.bits and out_conv >= 0:
                            ctx.set(self.sdo, self._word(self.conversions[out_conv][1], nfall))
                        else:
                            ctx.set(self.sdo, self._junk())
                        nfall += 1
                        sclk_fall = edge
                    else:             # rising edge
                        if sclk_fall is not None:
                            dt = edge - sclk_fall
                            self._check(dt * p + eps >= part.t_sclkl_s, "t_SCLKL",
                                        "the SCLK low time", dt, part.t_sclkl_s)
                        sclk_rise = edge
                sclk = new_sclk
