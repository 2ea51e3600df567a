# Ref: issue 6 items 2, 5, 6, 7; paper §4, Fig. 8 (speed step) and Fig. 9 (ramp, α-axis current);
#      DESIGN.md "Simulation is the product too"
"""Closed-loop co-simulation: the whole controller gateware ⇄ the PMSM, inverter and sensors.

:class:`CoSim` runs :class:`~foc_servo.sim.engines.base.SimTop` (the real :class:`~foc_servo.hdl.top.Top`
plus a gateware model of the ADC's pins) in one of the engines (``"pysim"``: Amaranth's simulator,
the reference; ``"compiled"``: Verilator) against :class:`~foc_servo.sim.pmsm.Plant`. Python runs
once per *chunk*, never once per clock:

1. the plant predicts the encoder and Hall edges up to the chunk's end from its state;
2. the engine runs the chunk with those edges (and the host link's UART bits, the fault pins) as a
   schedule, and stops early at an ADC CS falling edge (the sampling instant);
3. the plant integrates exactly between the gate edges the engine returns;
4. at a CS fall, the plant's currents and U_dc at that clock become the ADC's codes (the
   :class:`~foc_servo.sim.adc_chip.AdcChip` takes them after the fall, as the real part
   converts after sampling).

A chunk ends at the next CS fall, the caller's deadline or after :attr:`CoSim.max_chunk` clocks;
at 10 kHz PWM that is two engine calls per period (the convert and the read frame of the ADC).

The host talks to the gateware through its UART, in simulated time: :class:`CoSim` is a
:class:`~foc_servo.sim.link.ByteSim`, so :meth:`~foc_servo.sim.link.ByteSim.transport` (in
process) and :meth:`~foc_servo.sim.link.ByteSim.open_pty` (pyserial as the client) work, and
:meth:`CoSim.servo` gives the host library's :class:`~foc_servo.host.servo.Servo` on it: the
scenarios configure and command the drive exactly as a user does, in physical units.
"""

import math
import time

import numpy as np

from ..hdl.regmap import Scales
from .engines import make_engine
from .engines.base import (EVENT_DTYPE, IN_BITS, IN_INIT, IN_LAYOUT, IN_MASKS, OUT_BITS,
                           OUT_DTYPE, OUT_LAYOUT, OUT_MASKS, PORT_ADC_CODES, PORT_PINS_IN,
                           UartDecoder, uart_events)
from .harness import Progress
from .link import ByteSim
from .motor import DEFAULT_MOTOR
from .pmsm import GATE_DTYPE, Plant, Sensors

__all__ = ["CoSim", "SAMPLE_FIELDS"]

#: Columns of :meth:`CoSim.series` (one row per ADC conversion, at its sampling instant).
SAMPLE_FIELDS = ("t_s", "speed_rpm", "theta_e", "i_a_a", "i_b_a", "i_c_a", "i_alpha_a",
                 "i_beta_a", "i_d_a", "i_q_a", "udc_v", "torque_nm")
#: Input pins the co-simulation drives from a schedule (the plant drives the sensor pins, the
#: host link ``uart_rx``).
SCHEDULED_PINS = ("fault_n", "oc_comp")
_SENSOR_PINS = (("enc_a", "a"), ("enc_b", "b"), ("enc_z", "z"), ("hall", "hall"))


class CoSim(ByteSim):
    """The controller gateware and the plant, advanced together (module docstring).

    Parameters
    ----------
    engine : str
        ``"compiled"`` (Verilator, fast) or ``"pysim"`` (Amaranth's simulator, the reference).
    motor : MotorParams
        The motor (default the Yaskawa SGMSH-15A, :data:`~foc_servo.sim.motor.DEFAULT_MOTOR`).
    clk_hz, pwm_hz : float
        System clock and PWM frequency, Hz.
    baud : float or None
        Host-link UART bit rate; ``None``: ``clk_hz / 16`` (3.125 Mbaud at 50 MHz, the issue's
        "≥ 3 Mbaud must work" rate; keeps the set-up frames short in simulated time).
    i_fs_a : float
        The drive's current full scale ``I_FS``, A; the ADC's too (the Clarke gains stay 1.0).
    udc_v : float
        DC-bus voltage, V (a stiff source unless ``dc_link`` is given).
    dc_link : DcLink or None
        A capacitor fed by a rectifier (no brake resistor), see :class:`~foc_servo.sim.pmsm.Plant`.
    load_nm : float or callable
        Load torque, N·m, or a function of time (s).
    sensors : Sensors or None
        Sensor models (encoder faults, ADC noise); ``None``: defaults at ``i_fs_a``.
    theta_m0, omega_m0 : float
        Initial rotor angle (rad) and speed (rad/s).
    rotor : str
        ``"free"`` or ``"held"`` (a stiff dynamometer at ``omega_m0``), see the plant.
    oc_threshold_a : float or None
        The fast over-current comparator's trip level, A (``oc_comp`` pin, evaluated once per
        chunk); ``None``: no comparator (the pin stays low).
    seed : int
        Noise seed of the sensors.
    max_chunk : int or None
        Longest chunk, clocks; ``None``: one PWM period.
    record_pins : bool
        Keep every pin change (for :meth:`write_vcd`).
    progress : bool
        Show the compiled engine's build on stderr.
    top_kwargs
        More :class:`~foc_servo.hdl.top.Top` parameters (``dead_time_s``, ``resets``, …).
    """

    def __init__(self, *, engine="compiled", motor=DEFAULT_MOTOR, clk_hz=50e6, pwm_hz=10e3,
                 baud=None, i_fs_a=40.0, udc_v=310.0, dc_link=None, load_nm=0.0, sensors=None,
                 theta_m0=0.0, omega_m0=0.0, rotor="free", oc_threshold_a=None, seed=0,
                 max_chunk=None, record_pins=False, progress=False, **top_kwargs):
        baud = clk_hz / 16 if baud is None else baud
        scales = Scales(clk_hz=float(clk_hz), pwm_hz=float(pwm_hz), i_fs_a=float(i_fs_a))
        self.engine = make_engine(engine, clk_hz=clk_hz, pwm_hz=pwm_hz, baud=baud, scales=scales,
                                  progress=progress, **top_kwargs)
        top = self.engine.simtop.top
        self.top = top
        self.scales = top.scales
        self.clk_hz = float(clk_hz)
        self.baud = float(baud)
        self.pwm_period = top.pwm_period
        if sensors is None:
            sensors = Sensors(i_fs_a=float(i_fs_a), u_lsb_v=self.scales.u_fs_v)
        self.plant = Plant(motor, clk_hz=clk_hz, udc_v=udc_v, dc_link=dc_link, load_nm=load_nm,
                           sensors=sensors, theta_m0=theta_m0, omega_m0=omega_m0, seed=seed,
                           rotor=rotor)
        self.motor = motor
        self.oc_threshold_a = oc_threshold_a
        if max_chunk is None:
            max_chunk = self.pwm_period
        if not isinstance(max_chunk, int) or isinstance(max_chunk, bool) or max_chunk < 1:
            raise ValueError(f"CoSim max_chunk must be a positive number of clocks, "
                             f"not {max_chunk!r}")
        self.max_chunk = max_chunk
        self.record_pins = bool(record_pins)

        self._init_bytes()
        self._decoder = UartDecoder(self.clk_hz, self.baud)
        self._uart = np.zeros(0, dtype=EVENT_DTYPE)     # scheduled uart_rx events
        self._uart_end = 0                              # clock of the last scheduled rx level
        self._quiet_after = 0                           # a reply is possible until this clock
        self._pin_sched = {name: [] for name in SCHEDULED_PINS}
        self._codes_pending = None                      # ADC codes for the next clock
        self._last_fall = -(1 << 62)
        self.pin_log_in = []                            # applied pins_in events (record_pins)
        self.pin_log_out = []                           # pins_out changes (record_pins)
        self.samples = {name: [] for name in SAMPLE_FIELDS}
        self.wall_s = 0.0
        self.engine_s = 0.0
        self.plant_s = 0.0
        self.trip_clock = None                          # first clock the trip LED was on
        self.gates_off_clock = None                     # first clock ≥ trip with all gates off

    # --- time ---------------------------------------------------------------------------------

    @property
    def now(self):
        """Clocks simulated so far."""
        return self.engine.now

    @property
    def clocks(self):
        return self.engine.now

    @property
    def t_s(self):
        """Simulated time, s."""
        return self.engine.now / self.clk_hz

    def clocks_of(self, seconds):
        """``seconds`` of simulated time in whole clocks."""
        return int(round(seconds * self.clk_hz))

    def run_for(self, seconds, *, progress=None):
        """Advance ``seconds`` of simulated time (``progress``: a label for a progress bar)."""
        self.advance(self.now + self.clocks_of(seconds), progress=progress)

    def advance(self, until, *, progress=None):
        """Advance to clock ``until``, chunk by chunk (module docstring)."""
        bar = Progress(progress, until - self.now) if progress else None
        start = self.now
        t0 = time.perf_counter()
        while self.now < until:
            self._chunk(min(until, self.now + self.max_chunk))
            if bar is not None:
                bar.update(self.now - start)
        self.wall_s += time.perf_counter() - t0
        if bar is not None:
            bar.close()

    # --- pins ---------------------------------------------------------------------------------

    def set_pin(self, name, level, at=None):
        """Drive input pin ``name`` (one of :data:`SCHEDULED_PINS`) to ``level`` from clock
        ``at`` (default: the next clock) on."""
        if name not in SCHEDULED_PINS:
            raise ValueError(f"CoSim set_pin name must be one of {', '.join(SCHEDULED_PINS)}, "
                             f"not {name!r}")
        at = self.now + 1 if at is None else at
        if not isinstance(at, int) or isinstance(at, bool) or at <= self.now:
            raise ValueError(f"CoSim set_pin at must be a clock after {self.now}, not {at!r}")
        if level not in (0, 1):
            raise ValueError(f"CoSim set_pin level must be 0 or 1, not {level!r}")
        sched = self._pin_sched[name]
        sched.append((at, level))
        sched.sort()

    def _sources(self, end, sensor):
        """(clocks, words with the source's bits in place, level now) of every input source."""
        now = self.now
        edges, lv = sensor
        clocks = np.asarray(edges["clock"], dtype=np.int64)
        words = np.zeros(len(edges), dtype=np.int64)
        level = 0
        for pin, col in _SENSOR_PINS:
            words |= edges[col].astype(np.int64) << IN_BITS[pin]
            level |= int(lv[col]) << IN_BITS[pin]
        yield clocks, words, level
        u = self._uart = self._uart[self._uart["clock"] > now]
        sel = u[u["clock"] <= end]
        rx = IN_MASKS["uart_rx"]
        yield (sel["clock"].astype(np.int64), sel["value"].astype(np.int64) & rx,
               self.engine.pins_in & rx)
        if self.oc_threshold_a is not None:
            self._pin_sched["oc_comp"] = [(now + 1, int(self.plant.oc_level(
                self.oc_threshold_a)))]
        for name in SCHEDULED_PINS:
            sched = self._pin_sched[name]
            mask = IN_MASKS[name]
            here = [(c, v) for c, v in sched if c <= end]
            self._pin_sched[name] = [(c, v) for c, v in sched if c > end]
            yield (np.asarray([c for c, _ in here], dtype=np.int64),
                   np.asarray([v << IN_BITS[name] for _, v in here], dtype=np.int64),
                   self.engine.pins_in & mask)

    def _events(self, end, sensor):
        """The engine's events for clocks in (now, end]: a pins_in word wherever it changes,
        and the ADC codes of the last conversion at the next clock."""
        sources = list(self._sources(end, sensor))
        clocks = np.unique(np.concatenate([c for c, _, _ in sources]))
        words = np.zeros(len(clocks), dtype=np.int64)
        for c, v, lvl in sources:
            if len(c):
                idx = np.searchsorted(c, clocks, side="right") - 1
                words |= np.where(idx >= 0, v[np.maximum(idx, 0)], lvl)
            else:
                words |= lvl
        prev = np.concatenate([[self.engine.pins_in], words[:-1]])
        change = words != prev
        codes = self._codes_pending is not None
        ev = np.zeros(int(change.sum()) + codes, dtype=EVENT_DTYPE)
        if codes:
            ev[0] = (self.now + 1, PORT_ADC_CODES, self._codes_pending)
            self._codes_pending = None
        ev["clock"][codes:] = clocks[change]
        ev["port"][codes:] = PORT_PINS_IN
        ev["value"][codes:] = words[change]
        if codes and len(ev) > 1:
            ev = ev[np.argsort(ev["clock"], kind="stable")]
        return ev

    # --- the chunk ----------------------------------------------------------------------------

    def _chunk(self, end):
        eng, plant = self.engine, self.plant
        t0 = time.perf_counter()
        events = self._events(end, plant.sensor_events(end))
        t1 = time.perf_counter()
        res = eng.run(end, events, stop_mask=OUT_MASKS["adc_cs_n"])
        t2 = time.perf_counter()
        out = res.out
        gates = np.zeros(len(out), dtype=GATE_DTYPE)
        gates["clock"] = out["clock"]
        gates["gate_h"] = (out["value"] >> np.uint64(OUT_BITS["gate_h"])) & np.uint64(7)
        gates["gate_l"] = (out["value"] >> np.uint64(OUT_BITS["gate_l"])) & np.uint64(7)
        before = res.out_before
        plant.advance(res.now, gates, ((before >> OUT_BITS["gate_h"]) & 7,
                                       (before >> OUT_BITS["gate_l"]) & 7))
        data = self._decoder.feed(out, now=res.now)
        if data:
            self._received(bytes(data))
            self._quiet_after = max(self._quiet_after, res.now + 4 * self._byte_clocks)
        if len(out) and self.trip_clock is None:
            trip = (out["value"] >> np.uint64(OUT_BITS["led"])) & np.uint64(1)
            if trip.any():
                self.trip_clock = int(out["clock"][int(np.argmax(trip))])
        if self.trip_clock is not None and self.gates_off_clock is None:
            self._find_gates_off(out, before)
        if self.record_pins:
            self.pin_log_in.append(events[events["clock"] <= res.now])
            self.pin_log_out.append(out)
        if res.stopped and not eng.pins_out & OUT_MASKS["adc_cs_n"]:
            codes = plant.adc_codes()
            self._codes_pending = sum((int(c) & 0xFFFF) << (16 * k) for k, c in enumerate(codes))
            if res.now - self._last_fall > self.pwm_period // 4:
                self._record()
            self._last_fall = res.now
        self.engine_s += t2 - t1
        self.plant_s += time.perf_counter() - t2 + (t1 - t0)

    def _find_gates_off(self, out, before):
        gates = OUT_MASKS["gate_h"] | OUT_MASKS["gate_l"]
        clocks = out["clock"].astype(np.int64)
        words = out["value"].astype(np.int64)
        # The gate word at the trip clock and at every later change.
        k = int(np.searchsorted(clocks, self.trip_clock, side="right")) - 1
        cand = [(self.trip_clock, int(words[k]) if k >= 0 else int(before))]
        cand += [(int(c), int(w)) for c, w in zip(clocks[k + 1:], words[k + 1:])]
        for c, w in cand:
            if not w & gates:
                self.gates_off_clock = c
                return

    def _record(self):
        p, s = self.plant, self.samples
        i_a, i_b, i_c = p.i_abc
        i_alpha, i_beta = p.i_alpha_beta
        i_d, i_q = p.i_dq
        for key, value in (("t_s", self.t_s), ("speed_rpm", p.speed_rpm),
                           ("theta_e", p.theta_e), ("i_a_a", i_a), ("i_b_a", i_b),
                           ("i_c_a", i_c), ("i_alpha_a", i_alpha), ("i_beta_a", i_beta),
                           ("i_d_a", i_d), ("i_q_a", i_q), ("udc_v", p.udc_v),
                           ("torque_nm", p.torque_nm)):
            s[key].append(float(value))

    def series(self):
        """The recorded samples as numpy arrays (:data:`SAMPLE_FIELDS`)."""
        return {k: np.asarray(v, dtype=float) for k, v in self.samples.items()}

    def write_vcd(self, path):
        """Write the pins (needs ``record_pins``) and the recorded analog values as a VCD;
        return the number of value changes."""
        from .vcd import write_vcd
        if not self.record_pins:
            raise RuntimeError("CoSim.write_vcd needs record_pins=True")
        ev = (np.concatenate(self.pin_log_in) if self.pin_log_in
              else np.zeros(0, dtype=EVENT_DTYPE))
        ev = ev[ev["port"] == PORT_PINS_IN]
        out = (np.concatenate(self.pin_log_out) if self.pin_log_out
               else np.zeros(0, dtype=OUT_DTYPE))
        digital = []
        for layout, words, init in ((IN_LAYOUT, ev, IN_INIT), (OUT_LAYOUT, out, 0)):
            for name, field in layout:
                vals = (words["value"].astype(np.int64) >> field.offset) & ((1 << field.width) - 1)
                keep = np.concatenate([[True], vals[1:] != vals[:-1]]) if len(vals) else []
                init_v = (init >> field.offset) & ((1 << field.width) - 1)
                digital.append((name, field.width, words["clock"][keep], vals[keep], init_v))
        s = self.series()
        analog = [(k, s["t_s"], s[k]) for k in SAMPLE_FIELDS if k != "t_s"]
        return write_vcd(path, clk_hz=self.clk_hz, digital=digital, analog=analog)

    # --- the host link (ByteSim) -----------------------------------------------------------

    def _queue(self, data):
        start = max(self.now + 1, self._uart_end)
        ev = uart_events(data, start_clock=start, clk_hz=self.clk_hz, baud=self.baud)
        if len(ev):
            self._uart = np.concatenate([self._uart, ev])
            self._uart_end = int(ev["clock"][-1])
        # The link answers within a few byte times of a frame's end.
        self._quiet_after = max(self._quiet_after, self._uart_end + 8 * self._byte_clocks + 2000)

    @property
    def _byte_clocks(self):
        return int(math.ceil(10 * self.clk_hz / self.baud))

    @property
    def idle(self):
        """No host bytes in flight and the link quiet long enough that no reply is pending."""
        return self.now >= self._quiet_after and not self._decoder.busy

    def step(self):
        """Advance one chunk (at most a PWM period)."""
        self.advance(self.now + min(self.max_chunk, self._byte_clocks * 4))

    def servo(self, *, timeout_s=1.0):
        """The host library's :class:`~foc_servo.host.servo.Servo` on this co-simulation (in
        process; ``timeout_s`` is simulated-time-free: a read runs the simulation until the
        reply is there)."""
        from ..host.protocol import Client
        from ..host.servo import Servo
        servo = Servo(Client(self.transport(), timeout_s=timeout_s))
        servo.connect()
        return servo
