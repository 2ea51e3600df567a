"""Running Amaranth simulations the same way from tests, benchmarks and the CLI.

``FOC_SERVO_VCD=DIR`` in the environment writes ``DIR/<name>.vcd`` for every simulation run
through :func:`simulate` (VCDs only on request: they slow the simulator down several times).
"""

import os
import sys
import time
from pathlib import Path

import numpy as np
from amaranth.sim import Simulator

__all__ = ["simulate", "Progress", "pack_words"]


def simulate(dut, testbenches=(), processes=(), *, clock_hz=50e6, name=None, vcd=None):
    """Simulate ``dut`` with one clock domain ``sync`` at ``clock_hz``.

    Parameters
    ----------
    dut : Elaboratable
    testbenches : iterable of async functions ``(ctx) -> None`` added with ``add_testbench``;
        the simulation ends when all of them return.
    processes : iterable of async functions added with ``add_process`` (stand-ins for outside
        hardware; they run forever).
    name : str
        Base name of the VCD file when ``vcd`` or ``FOC_SERVO_VCD`` asks for one.
    vcd : path, optional
        Write a VCD (and GTKW) file here.

    Returns
    -------
    float
        Wall-clock seconds the simulation took.
    """
    sim = Simulator(dut)
    sim.add_clock(1 / clock_hz, if_exists=True)  # combinational designs have no clock
    for tb in testbenches:
        sim.add_testbench(tb)
    for proc in processes:
        sim.add_process(proc)
    if vcd is None and os.environ.get("FOC_SERVO_VCD"):
        vcd = Path(os.environ["FOC_SERVO_VCD"]) / f"{name or type(dut).__name__.lower()}.vcd"
    start = time.perf_counter()
    if vcd is not None:
        vcd = Path(vcd)
        vcd.parent.mkdir(parents=True, exist_ok=True)
        with sim.write_vcd(str(vcd), str(vcd.with_suffix(".gtkw"))):
            sim.run()
    else:
        sim.run()
    return time.perf_counter() - start


class Progress:
    """A one-line progress indicator on stderr for long runs (silent when ``enabled`` is false)."""

    def __init__(self, label, total, *, enabled=True, stream=None):
        self.label, self.total, self.enabled = label, max(int(total), 1), enabled
        self.stream = stream or sys.stderr
        self._last = -1
        self._start = time.perf_counter()

    def update(self, done):
        if not self.enabled:
            return
        pct = int(100 * done / self.total)
        if pct != self._last:
            self._last = pct
            elapsed = time.perf_counter() - self._start
            self.stream.write(f"\r{self.label}: {pct:3d} % ({done}/{self.total}, {elapsed:5.1f} s)")
            self.stream.flush()

    async def ticks(self, ctx, clocks, *, step=5000):
        """Advance the simulation ``clocks`` clocks in runs of ``step`` (one Python call each),
        updating the indicator after each run."""
        done = 0
        while done < clocks:
            k = min(step, clocks - done)
            await ctx.tick().repeat(k)
            done += k
            self.update(min(done, self.total))

    def close(self):
        if self.enabled:
            self.update(self.total)
            self.stream.write("\n")
            self.stream.flush()


def pack_words(layout, columns, n):
    """Pack integer columns (``{field name: array of n}``) into ``n`` raw words of a
    :class:`~amaranth.lib.data.StructLayout` — the ``init=`` of a stimulus or expected-result ROM.
    Fields missing from ``columns`` are 0; values are truncated to their field (two's complement
    for signed fields)."""
    words = [0] * n
    for name, field in layout:
        if name not in columns:
            continue
        mask = (1 << field.width) - 1
        vals = (np.asarray(columns[name], dtype=np.int64) & mask).tolist()
        words = [w | (v << field.offset) for w, v in zip(words, vals)]
    return words
