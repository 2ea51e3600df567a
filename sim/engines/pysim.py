# Ref: issue 6 item 3 (Amaranth's simulator as the reference engine); Amaranth 0.5 simulator
#      API: amaranth/sim/_async.py (TriggerCombination: changed(), delay(), any-of wake-up) and
#      core.py (Simulator.advance: one time step per call)
"""The reference engine: Amaranth's simulator (pysim) on :class:`~.base.SimTop`.

One simulator lives as long as the engine. A single testbench serves the :meth:`run` calls: it
applies the events of a clock right after the previous edge and then sleeps until whichever comes
first, a change of ``pins_out`` (``ctx.changed``) or the point just after the edge before the
next event or the end of the run (``ctx.delay``); so Python wakes at input events and output
changes only, never once per clock (the design's own evaluation is pysim's per-clock cost). The
clock number comes from SimTop's edge counter ``cycle``. Between two calls the testbench
waits in a zero delay, so the next call resumes it right where the last one stopped (just after
an edge, before the next one).

The Python driver calls :meth:`Simulator.advance` (one time step: a clock edge or a testbench
wake-up) until the testbench reports the job done, which is what ``Simulator.run_until`` does
internally, with a stop condition the deadline alone cannot express.

Invariants written as ``Assert`` in the gateware are checked on every clock (an
:class:`AssertionError` from :meth:`run`).
"""

import numpy as np
from amaranth.hdl import Value
from amaranth.sim import Simulator

from .base import OUT_DTYPE, PORT_PINS_IN, Engine

__all__ = ["PysimEngine"]

#: Longest single wait of the testbench, clocks (keeps every delay far inside float precision).
_MAX_WAIT = 1 << 20


class PysimEngine(Engine):
    """Amaranth's simulator on a :class:`~.base.SimTop` (the API: :mod:`.base`).

    Parameters
    ----------
    simtop : SimTop
    """

    kind = "pysim"

    def __init__(self, simtop):
        super().__init__(simtop)
        # The clock toggles every period // 2 fs: use an even period so that clock k rises at
        # exactly period / 2 + (k − 1) · period. Times are passed with +0.5 fs because the
        # simulator truncates seconds to femtoseconds.
        self._period_fs = 2 * max(1, round(1e15 / simtop.clk_hz / 2))
        self._sim = Simulator(simtop)
        self._sim.add_clock((self._period_fs + 0.5) / 1e15,
                            phase=(self._period_fs // 2 + 0.5) / 1e15)
        self._sim.add_testbench(self._testbench)
        self._job = None
        self._result = None
        self._started = False
        self.reset()

    def _reset(self):
        if self._started:                       # restart it (a new testbench coroutine)
            self._sim.reset()
        self._started = True
        self._run_job(0, (), (), (), 0)          # start the testbench; read the initial outputs
        return self._result[5]

    def _edge_fs(self, k):
        """Simulation time of clock edge ``k`` (k >= 1), fs."""
        return self._period_fs // 2 + (k - 1) * self._period_fs

    async def _testbench(self, ctx):
        top = self._simtop
        sig_in = Value.cast(top.pins_in)
        sig_codes = Value.cast(top.adc_codes)
        sig_out = Value.cast(top.pins_out)
        cycle = top.cycle
        quarter = self._period_fs // 4
        t_fs = 0                        # the simulation time, tracked (no public getter)
        now = 0
        out_prev = ctx.get(sig_out)
        while True:
            until, ev_clock, ev_port, ev_value, stop_mask = self._job
            n = len(ev_clock)
            i = 0
            out_clock, out_value = [], []
            stopped = False
            while True:
                while i < n and ev_clock[i] == now + 1:
                    ctx.set(sig_in if ev_port[i] == PORT_PINS_IN else sig_codes, ev_value[i])
                    i += 1
                if now >= until:
                    break
                target = until if i == n else min(until, ev_clock[i] - 1)
                target = min(target, now + _MAX_WAIT)
                wake_fs = self._edge_fs(target) + quarter
                _, timeout = await ctx.changed(sig_out).delay((wake_fs - t_fs + 0.5) / 1e15)
                if timeout:
                    t_fs, now = wake_fs, target
                    continue
                now = ctx.get(cycle)
                t_fs = self._edge_fs(now)
                value = ctx.get(sig_out)
                if value != out_prev:   # (a glitch that settled back is no change)
                    out_clock.append(now)
                    out_value.append(value)
                    changed = value ^ out_prev
                    out_prev = value
                    if changed & stop_mask:
                        stopped = True
                        break
            self._result = (now, out_clock, out_value, stopped, i, out_prev)
            await ctx.delay(0)          # park: the next advance() continues with the next job

    def _run_job(self, until, ev_clock, ev_port, ev_value, stop_mask):
        self._job = (until, ev_clock, ev_port, ev_value, stop_mask)
        self._result = None
        while self._result is None:
            self._sim.advance()

    def _run(self, until, events, stop_mask):
        self._run_job(until, events["clock"].tolist(), events["port"].tolist(),
                      events["value"].tolist(), stop_mask)
        now, out_clock, out_value, stopped, used, _ = self._result
        out = np.zeros(len(out_clock), dtype=OUT_DTYPE)
        out["clock"] = out_clock
        out["value"] = out_value
        return now, out, stopped, used
