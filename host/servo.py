# Ref: issue 5 items 7–8 (host library); docs/PROTOCOL.md, docs/REGISTERS.md, docs/TUNING.md
"""The host library: :class:`Servo` talks to a drive in physical units over the host link.

The same class runs against a real drive (:meth:`Servo.open`, pyserial on a serial port) and
against the simulated gateware (:meth:`Servo.sim`: the real UART/link gateware in Amaranth's
simulator behind a pseudo-terminal, with pyserial as the client)::

    with Servo.sim() as drive:                      # or Servo.open("/dev/ttyUSB0")
        drive.set("mode", "current")
        drive.set_many({"pi_q_kp": 1.2, "pi_q_kx": 0.01})   # one frame: applied together
        drive.get("st_speed")                        # r/min
        capture = drive.scope_capture(["i_q_ref", "i_q"], pretrigger=100)

Values are in the register's unit (``docs/REGISTERS.md``): floats for numbers (ints for plain
integer registers), enum members (or their names, case-insensitive, when writing), dicts of
flags (or an iterable of the set flag names), bools. Conversion uses the scales the drive reports
in its identification registers, read on connect.
"""

import difflib
import json
import math
import numbers
import time
from pathlib import Path

import numpy as np

from ..hdl.regmap import MAGIC, Scales, TriggerSource
from .protocol import Client, SerialTransport
from .registers import ID_SCALE_REGISTERS, REGISTERS, WINDOWS

# (also ``RegisterLevelSim``, built on first access: see the end of the module)
__all__ = ["Servo", "ServoError", "MapMismatch", "SCOPE_SOURCES", "PARAMETER_FILE_FORMAT",
           "close_names"]

#: ``format`` key of a parameter file.
PARAMETER_FILE_FORMAT = "foc-servo-parameters/1"

#: Scope sources in select-code order (``hdl.scope.DEFAULT_SOURCES``; a test checks they agree):
#: name → (signed, scale name or None, unit). A sample is the source's top 16 bits: a Q1.15 of
#: the full scale for speeds, currents and modulation indices, a BinaryAngle(16) for ``theta``,
#: the ADC code for ``u_dc``.
SCOPE_SOURCES = {
    "speed": (True, "N_FS", "r/min"),
    "speed_ref": (True, "N_FS", "r/min"),
    "i_d": (True, "I_FS", "A"),
    "i_q": (True, "I_FS", "A"),
    "i_d_ref": (True, "I_FS", "A"),
    "i_q_ref": (True, "I_FS", "A"),
    "i_alpha": (True, "I_FS", "A"),
    "i_beta": (True, "I_FS", "A"),
    "u_d": (True, None, "pu"),
    "u_q": (True, None, "pu"),
    "u_alpha": (True, None, "pu"),
    "u_beta": (True, None, "pu"),
    "theta": (False, "turn", "deg"),
    "u_dc": (True, "U_FS", "V"),
}

_SCOPE_CHANNELS = tuple(n for n in REGISTERS if n.startswith("scope_chan"))


class ServoError(Exception):
    """A host-library error: a bad name or value, a drive that does not answer as expected."""


class MapMismatch(ServoError):
    """The drive's register map (``id_map_hash``) differs from this library's."""


def close_names(name, names=REGISTERS):
    """Names like ``name`` (for "did you mean" hints)."""
    return difflib.get_close_matches(str(name), list(names), n=3, cutoff=0.6)


def _unknown(name, what="register", names=REGISTERS):
    hint = close_names(name, names)
    more = f"; did you mean {', '.join(hint)}?" if hint else ""
    return ServoError(f"no {what} named {name!r}{more}")


def _plain(value):
    """A JSON/TOML-friendly form of a decoded value (enum → lower-case name)."""
    if hasattr(value, "name") and hasattr(value, "value") and not isinstance(value, bool):
        return value.name.lower()
    return value


class Servo:
    """A drive (real or simulated) seen through its registers, in physical units.

    Use :meth:`open` or :meth:`sim`; both connect at once (see :meth:`connect`). A context
    manager: leaving the ``with`` block closes the port (and stops a simulation).

    Parameters
    ----------
    client : Client
        The protocol client on the link.
    closers : list of callables
        Called by :meth:`close`, in order.

    Attributes
    ----------
    scales : Scales
        From the identification registers.
    map_version : int
        ``id_version``.
    max_words : int
        The drive's maximum burst (from the ping).
    """

    def __init__(self, client, closers=()):
        self.client = client
        self._closers = list(closers)
        self.scales = None
        self.map_version = None
        self.max_words = None
        self.sim = None

    # --- construction -------------------------------------------------------------------------

    @classmethod
    def open(cls, port, baud=115200, *, timeout_s=0.5):
        """Connect to a drive on serial port ``port`` (e.g. ``"/dev/ttyUSB0"``) at ``baud``."""
        import serial
        if not isinstance(baud, numbers.Integral) or isinstance(baud, bool) or baud < 1:
            raise ValueError(f"Servo baud must be a positive integer, not {baud!r}")
        try:
            ser = serial.Serial(port, baudrate=baud, timeout=timeout_s)
        except serial.SerialException as e:
            raise ServoError(f"cannot open serial port {port!r}: {e}") from None
        return cls._connected(ser, timeout_s)

    @classmethod
    def _connected(cls, ser, timeout_s, sim=None):
        """A Servo on the open pyserial port ``ser`` (closing it, then ``sim``, on close),
        connected; everything is closed again if connecting fails."""
        closers = [ser.close] + ([sim.close] if sim is not None else [])
        servo = cls(Client(SerialTransport(ser), timeout_s=timeout_s), closers)
        servo.sim = sim
        try:
            servo.connect()
        except BaseException:
            servo.close()
            raise
        return servo

    @classmethod
    def sim(cls, uart=False, *, clk_hz=50e6, timeout_s=120.0, bus_slave_factory=None):
        """Connect to the simulated gateware through a pseudo-terminal, pyserial as the client.

        This is a **register-level** simulation: the real host-link gateware
        (:class:`~foc_servo.hdl.hostlink.HostLink` with its UARTs if ``uart``, else the bare
        :class:`~foc_servo.hdl.hostlink.LinkCore`) in front of the real register file
        (:class:`~foc_servo.hdl.regs.RegisterFile`) and the real trace buffer
        (:class:`~foc_servo.hdl.scope.Scope`), wired as :class:`RegisterLevelSim` describes; the
        status registers read 0 and nothing turns. The whole drive with the motor is
        :meth:`drive_sim`.

        Parameters
        ----------
        uart : bool
            Simulate the UARTs (at ``clk_hz / 8``), not only the protocol engine (slower).
        clk_hz : float
            Simulated clock.
        timeout_s : float
            Reply timeout (wall time; the simulator is slow).
        bus_slave_factory : callable or None
            Builds the bus slave; default :class:`RegisterLevelSim`.
        """
        import serial

        from ..hdl.regmap import REGMAP
        from ..hdl.top import regmap_address_map
        from ..sim.link import LinkSim
        factory = (__getattr__("RegisterLevelSim") if bus_slave_factory is None
                   else bus_slave_factory)
        link = LinkSim(factory, clk_hz=clk_hz, uart=uart,
                       address_map=regmap_address_map(REGMAP))
        return cls._connected(serial.Serial(link.open_pty(), timeout=timeout_s), timeout_s, link)

    @classmethod
    def drive_sim(cls, *, engine="compiled", timeout_s=120.0, **cosim_kw):
        """Connect to the **simulated drive**: the whole controller gateware
        (:class:`~foc_servo.hdl.top.Top`, its UART at 3.125 Mbaud) driving the motor plant in the
        closed-loop co-simulation (:class:`~foc_servo.sim.closed_loop.CoSim`), through a
        pseudo-terminal with pyserial as the client. The simulation runs freely between
        transactions (as fast as the engine goes), so the motor turns while the host watches.

        Parameters
        ----------
        engine : str
            ``"compiled"`` (Verilator; builds once, then cached) or ``"pysim"``.
        timeout_s : float
            Reply timeout, wall seconds.
        cosim_kw
            More :class:`~foc_servo.sim.closed_loop.CoSim` parameters (motor, pwm_hz, …).
        """
        import serial

        from ..sim.closed_loop import CoSim
        cosim = CoSim(engine=engine, **cosim_kw)
        cosim.free_run = True
        ser = serial.Serial(cosim.open_pty(), baudrate=round(cosim.baud), timeout=timeout_s)
        return cls._connected(ser, timeout_s, cosim)

    def connect(self):
        """Ping, read the identification registers, check the magic number and the map hash
        against this library's map, build :attr:`scales`.

        Raises
        ------
        MapMismatch
            The drive's map hash differs from the local map's (different gateware version).
        ServoError
            No drive (wrong magic number).
        """
        self.max_words = self.client.ping()
        self.client.max_words = min(self.client.max_words, self.max_words)
        names = ("id_magic", "id_version", "id_map_hash") + ID_SCALE_REGISTERS
        raw = self._read_raw(names)
        if raw["id_magic"] != MAGIC:
            raise ServoError(f"not a foc-servo drive: id_magic reads 0x{raw['id_magic']:08X}, "
                             f"expected 0x{MAGIC:08X}")
        local = REGISTERS["id_map_hash"].reset
        if raw["id_map_hash"] != local:
            v = raw["id_version"]
            raise MapMismatch(
                f"register map mismatch: the drive's id_map_hash is 0x{raw['id_map_hash']:08X} "
                f"(map version {v >> 16}.{v & 0xFFFF}), this library's is 0x{local:08X}; use the "
                f"host library built with the drive's gateware")
        self.map_version = raw["id_version"]
        try:
            self.scales = Scales.from_id_raw(raw)
        except (TypeError, ValueError) as e:
            raise ServoError(f"the drive's identification registers hold no valid scales: {e}") \
                from None
        return self

    def close(self):
        """Close the port (and stop the simulation)."""
        closers, self._closers = self._closers, []
        for f in closers:
            f()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # --- registers ----------------------------------------------------------------------------

    @staticmethod
    def register(name):
        """The :class:`~foc_servo.host.registers.HostRegister` called ``name``.

        Raises
        ------
        ServoError
            Unknown name (suggesting close ones).
        """
        try:
            return REGISTERS[name]
        except (KeyError, TypeError):
            raise _unknown(name) from None

    def _decode(self, reg, raw):
        value = reg.from_raw(raw, self.scales)
        if reg.kind == "number" and reg.fmt.frac == 0 and reg.scale == "1":
            return int(raw)
        return value

    def _encode(self, reg, value):
        """Raw value of ``value`` for ``reg``, with an error naming register, value, range, unit."""
        if not reg.writable:
            raise ServoError(f"{reg.name} is {reg.access}: it cannot be written")
        if isinstance(value, str) and reg.kind in ("number", "bool"):
            try:
                value = float(value) if reg.kind == "number" else {
                    "1": 1, "0": 0, "true": 1, "false": 0, "on": 1, "off": 0}[value.lower()]
            except (ValueError, KeyError):
                raise ServoError(f"{reg.name} {value!r} is not a "
                                 f"{'number' if reg.kind == 'number' else 'bool'}") from None
        if reg.access == "strobe" and value not in (0, 1, True, False):
            raise ServoError(f"{reg.name} is a strobe: write 1 (or 0), not {value!r}")
        if reg.kind == "number" and isinstance(value, numbers.Real) and not math.isfinite(value):
            raise ServoError(f"{reg.name} {value!r} is not a finite number")
        try:
            return reg.to_raw(value, self.scales)
        except (ValueError, TypeError) as e:
            msg = str(e)
            if reg.kind == "number" and reg.unit == "" and "outside" in msg:
                msg += " (raw integer)"
            raise ServoError(msg) from None

    def _read_raw(self, names):
        """``{name: raw}`` of readable registers, one burst per run of consecutive words."""
        regs = sorted({self.register(n).addr: self.register(n) for n in names}.values(),
                      key=lambda r: r.addr)
        out = {}
        run = []

        def flush():
            if run:
                words = self.client.read(run[0].addr, run[-1].addr + run[-1].words - run[0].addr)
                for r in run:
                    out[r.name] = r.from_words(words[r.addr - run[0].addr:][:r.words])
                run.clear()

        for r in regs:
            if r.access == "strobe":
                out[r.name] = 0
                continue
            if run and (r.addr != run[-1].addr + run[-1].words
                        or r.addr + r.words - run[0].addr > self.client.max_words):
                flush()
            run.append(r)
        flush()
        return out

    def get(self, name):
        """Value of register ``name`` in its unit (see the module docstring)."""
        return self.get_many([name])[name]

    def get_many(self, names):
        """``{name: value}`` of the named registers (consecutive ones read in one burst)."""
        names = list(names)
        for n in names:
            self.register(n)
        raw = self._read_raw(names)
        return {n: self._decode(REGISTERS[n], raw[n]) for n in names}

    def set(self, name, value):
        """Write ``value`` (in the register's unit) to register ``name``.

        Raises
        ------
        ServoError
            Unknown or read-only register, or a value out of range (naming the register, the
            value, the range and the unit); nothing is written then.
        """
        self.set_many({name: value})

    def set_many(self, values):
        """Write several registers; all values are checked before anything is written.

        The words are written in as few frames as possible: registers at nearby addresses go
        in one burst, the writable registers between them completed with their current
        (read-back) values (strobes with 0), so the given registers of one shadow group
        (``docs/REGISTERS.md``) go out in **one frame** and take effect together at the next
        loop boundary. Only registers separated by an address with no register (or by a
        read-only one) need separate frames; no shadow group has such a gap (a test of the
        register map keeps it so).

        Returns
        -------
        list of (int, int)
            ``(address, word count)`` of each write frame sent.
        """
        values = dict(values)
        raw = {}
        for name, value in values.items():
            raw[name] = self._encode(self.register(name), value)
        words = {}
        for name, r in raw.items():
            reg = REGISTERS[name]
            for k, w in enumerate(reg.to_words(r)):
                words[reg.addr + k] = w
        return self._write_words(words)

    def _write_words(self, words):
        """Write ``{addr: word}``: consecutive writable words join a frame, gaps of writable
        registers up to the frame limit are filled with read-backs (strobes with 0)."""
        word_reg = {}
        for r in REGISTERS.values():
            for k in range(r.words):
                word_reg[r.addr + k] = r
        addrs = sorted(words)
        spans, start, end = [], None, None
        for a in addrs:
            if start is not None:
                gap = range(end, a)
                fillable = all(g in word_reg and word_reg[g].writable for g in gap)
                if fillable and a + 1 - start <= self.client.max_words:
                    end = a + 1
                    continue
                spans.append((start, end))
            start, end = a, a + 1
        if start is not None:
            spans.append((start, end))
        frames = []
        for s, e in spans:
            missing = [a for a in range(s, e) if a not in words]
            data = dict(words)
            if any(word_reg[a].access == "rw" for a in missing):
                current = self.client.read(s, e - s)
                for a in missing:
                    data[a] = 0 if word_reg[a].access == "strobe" else current[a - s]
            else:
                for a in missing:
                    data[a] = 0
            self.client.write(s, [data[a] for a in range(s, e)])
            frames.append((s, e - s))
        return frames

    def readable(self):
        """Names of the registers :meth:`dump` reads (every one but the strobes, which read 0)."""
        return [n for n, r in REGISTERS.items() if r.access != "strobe"]

    def dump(self):
        """``{name: value}`` of every readable register, in address order."""
        return self.get_many(self.readable())

    # --- parameter files ----------------------------------------------------------------------

    @staticmethod
    def parameters():
        """Names of the registers a parameter file holds (the ``rw`` ones)."""
        return [n for n, r in REGISTERS.items() if r.access == "rw"]

    def save(self, path):
        """Write the ``rw`` registers, in units, to a parameter file (``.toml`` or ``.json``).

        The file also records the map hash and the scales (for information: :meth:`load`
        converts from units with the drive's scales)."""
        path = Path(path)
        values = {n: _plain(v) for n, v in self.get_many(self.parameters()).items()}
        info = {"format": PARAMETER_FILE_FORMAT,
                "id_map_hash": f"0x{REGISTERS['id_map_hash'].reset:08X}",
                "scales": {k: getattr(self.scales, k) for k in
                           ("clk_hz", "pwm_hz", "i_fs_a", "u_fs_v", "n_fs_rpm")}}
        if path.suffix.lower() == ".json":
            path.write_text(json.dumps({**info, "registers": values}, indent=2) + "\n")
        elif path.suffix.lower() == ".toml":
            path.write_text(_to_toml(info, values))
        else:
            raise ServoError(f"parameter file {str(path)!r} must end in .toml or .json")
        return values

    @staticmethod
    def read_parameter_file(path):
        """``{name: value}`` of a parameter file (not yet checked against the ranges)."""
        path = Path(path)
        try:
            text = path.read_text()
            if path.suffix.lower() == ".json":
                doc = json.loads(text)
            elif path.suffix.lower() == ".toml":
                import tomllib
                doc = tomllib.loads(text)
            else:
                raise ServoError(f"parameter file {str(path)!r} must end in .toml or .json")
        except (OSError, ValueError) as e:
            raise ServoError(f"cannot read parameter file {str(path)!r}: {e}") from None
        if not isinstance(doc, dict) or doc.get("format") != PARAMETER_FILE_FORMAT or \
                not isinstance(doc.get("registers"), dict):
            raise ServoError(f"{str(path)!r} is not a foc-servo parameter file (format = "
                             f"{PARAMETER_FILE_FORMAT!r} and a registers table)")
        return doc["registers"]

    def load(self, path):
        """Restore the registers of a parameter file.

        Every name and value is checked (known ``rw`` register, value in range) before anything
        is written; then the values are written group-wise (:meth:`set_many`: a shadow group in
        one frame).

        Returns
        -------
        dict
            The values written.
        """
        values = self.read_parameter_file(path)
        errors = []
        for name, value in values.items():
            reg = REGISTERS.get(name)
            if reg is None:
                errors.append(str(_unknown(name)))
            elif reg.access != "rw":
                errors.append(f"{name} is {reg.access}: not a parameter")
            else:
                try:
                    self._encode(reg, value)
                except ServoError as e:
                    errors.append(str(e))
        if errors:
            raise ServoError(f"parameter file {str(path)!r}: nothing written: "
                             + "; ".join(errors))
        self.set_many(values)
        return values

    # --- faults -------------------------------------------------------------------------------

    def faults(self):
        """``{"trip": bool, "present": [...], "first": [...], "seen": [...]}`` (fault names)."""
        v = self.get_many(["st_trip", "st_fault_present", "st_fault_first", "st_fault_seen"])
        out = {"trip": v["st_trip"]}
        for key in ("present", "first", "seen"):
            out[key] = [f for f, on in v[f"st_fault_{key}"].items() if on]
        return out

    def clear_faults(self):
        """Release the trip latch and clear first/seen faults (if no cause is present);
        returns :meth:`faults` afterwards."""
        self.set("clear_faults", 1)
        return self.faults()

    # --- scope --------------------------------------------------------------------------------

    def scope_depth(self):
        """Samples per channel of the trace buffer (its window size over the channels)."""
        return WINDOWS["scope"].size // len(_SCOPE_CHANNELS)

    def scope_capture(self, channels, pretrigger=0, decimation=1, trigger="host", *, step=None,
                      timeout_s=10.0, poll_s=0.01):
        """Capture up to four signals at loop rate; returns ``{"t_s": ..., name: ...}`` (numpy
        arrays in units, ``t_s`` = 0 at the trigger sample).

        Arms the scope, triggers it (``"host"``: the ``scope_force`` strobe once the pre-trigger
        part is full; ``"step"``: a reference step: ``step``, a mapping of register values, is
        written once the pre-trigger part is full, e.g. ``{"speed_ref": 1000}``, or the drive
        is left to see one), polls ``scope_status.done`` and reads the window.

        Parameters
        ----------
        channels : list of str
            Source names (:data:`SCOPE_SOURCES`), at most 4.
        pretrigger : int
            Samples before the trigger sample, 0 … depth − 1.
        decimation : int
            One sample every ``decimation`` loop ticks, 1 … 65535.
        timeout_s : float
            Wall time to wait for the pre-trigger part and for the capture.

        Raises
        ------
        ServoError
            Bad arguments, or no complete capture within ``timeout_s``.
        """
        depth = self.scope_depth()
        if isinstance(channels, str):
            channels = [c for c in channels.split(",") if c]
        channels = list(channels)
        if not 1 <= len(channels) <= len(_SCOPE_CHANNELS):
            raise ServoError(f"scope channels must be 1 to {len(_SCOPE_CHANNELS)} source names, "
                             f"not {channels!r}")
        for c in channels:
            if c not in SCOPE_SOURCES:
                raise _unknown(c, "scope source", SCOPE_SOURCES)
        if len(set(channels)) != len(channels):
            raise ServoError(f"scope channels {channels!r} name a source twice")
        if not isinstance(pretrigger, int) or not 0 <= pretrigger < depth:
            raise ServoError(f"scope pretrigger must be an integer from 0 to {depth - 1}, "
                             f"not {pretrigger!r}")
        if not isinstance(decimation, int) or not 1 <= decimation <= 0xFFFF:
            raise ServoError(f"scope decimation must be an integer from 1 to 65535, "
                             f"not {decimation!r}")
        if trigger not in ("host", "step"):
            raise ServoError(f"scope trigger must be 'host' or 'step', not {trigger!r}")
        if step is not None and trigger != "step":
            raise ServoError("scope step values need trigger='step'")
        for n, v in (step or {}).items():
            self._encode(self.register(n), v)           # check before arming
        codes = list(SCOPE_SOURCES)
        setup = {f"scope_chan{i}": codes.index(c) for i, c in enumerate(channels)}
        setup.update(scope_decim=decimation, scope_pretrig=pretrigger,
                     scope_trig_src=TriggerSource.HOST if trigger == "host"
                     else TriggerSource.EXTERNAL)
        self.set_many(setup)
        self.set("scope_arm", 1)
        self._scope_wait("pre_full", timeout_s, poll_s)
        if trigger == "host":
            self.set("scope_force", 1)
        elif step:
            self.set_many(step)
        self._scope_wait("done", timeout_s, poll_s)
        out = {"t_s": (np.arange(depth) - pretrigger) * decimation / self.scales.pwm_hz}
        base = WINDOWS["scope"].addr
        for i, c in enumerate(channels):
            words = np.array(self.client.read(base + i * depth, depth), dtype=np.int64) & 0xFFFF
            out[c] = self._scope_units(c, words)
        return out

    def _scope_wait(self, flag, timeout_s, poll_s):
        deadline = time.monotonic() + timeout_s
        while True:
            status = self.get("scope_status")
            if status[flag] or (flag == "pre_full" and status["done"]):
                return
            if time.monotonic() > deadline:
                state = self.get("scope_state")
                what = "pre-trigger part full" if flag == "pre_full" else "capture complete"
                raise ServoError(f"scope: no {what} within {timeout_s} s (state "
                                 f"{getattr(state, 'name', state)}, flags {status})")
            time.sleep(poll_s)

    def _scope_units(self, name, words):
        signed, scale, _unit = SCOPE_SOURCES[name]
        if signed:
            words = np.where(words >= 1 << 15, words - (1 << 16), words)
        if scale == "turn":
            return words * (360.0 / (1 << 16))
        if scale == "U_FS":
            return words * self.scales.u_fs_v
        factor = 1.0 if scale is None else self.scales.value(scale)
        return words * (factor / (1 << 15))

    # --- tuning -------------------------------------------------------------------------------

    def tune(self, motor, *, current_bandwidth_hz=None, speed_a=3.0, dry_run=False, **kw):
        """PI gains for ``motor`` (:class:`~foc_servo.sim.motor.MotorParams`) by the rule of
        :func:`foc_servo.host.tuning.tune`, with the drive's scales, ``u_rated`` and
        ``speed_div``, and the feed-forward (decoupling, ``theta_lead``, dead-time compensation
        for the drive's ``dead_time`` register; ``feedforward=False`` in ``kw`` leaves them
        alone); written in one burst unless ``dry_run``.

        Parameters
        ----------
        current_bandwidth_hz : float or None
            Current-loop crossover ω_c/2π, Hz; ``None``: the technical optimum.
        speed_a : float
            Symmetric-optimum ``a``.
        kw
            Further keywords of :func:`~foc_servo.host.tuning.tune`.

        Returns
        -------
        Tuning
        """
        from .tuning import tune
        v = self.get_many(["u_rated", "speed_div", "dead_time"])
        bw = None if current_bandwidth_hz is None else 2 * math.pi * current_bandwidth_hz
        kw.setdefault("dead_time_s", v["dead_time"])    # compensate the drive's own dead time
        try:
            result = tune(motor, scales=self.scales, u_rated_v=v["u_rated"],
                          speed_div=max(v["speed_div"], 1), current_bandwidth_rad_s=bw,
                          a=speed_a, **kw)
        except ValueError as e:
            raise ServoError(f"tune: {e}") from None
        if not dry_run:
            words = {}
            for name, raw in {**result.registers, **result.feedforward}.items():
                reg = REGISTERS[name]
                for k, w in enumerate(reg.to_words(raw)):
                    words[reg.addr + k] = w
            self._write_words(words)
        return result


def _toml_value(value):
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{k} = {_toml_value(v)}" for k, v in value.items()) + " }"
    if isinstance(value, float):
        return repr(value)
    return str(value)


def _to_toml(info, values):
    lines = ["# foc-servo parameter file: rw registers in physical units (docs/REGISTERS.md)",
             f"format = {_toml_value(info['format'])}",
             f"id_map_hash = {_toml_value(info['id_map_hash'])}", "", "[scales]"]
    lines += [f"{k} = {_toml_value(float(v))}" for k, v in info["scales"].items()]
    lines += ["", "[registers]"]
    for name, value in values.items():
        reg = REGISTERS[name]
        unit = f"  # {reg.unit}" if reg.unit else ""
        lines.append(f"{name} = {_toml_value(value)}{unit}")
    return "\n".join(lines) + "\n"


# --- register-level simulation ---------------------------------------------------------------

def _register_level_sim_class():
    from amaranth.hdl import Cat, Module, Mux, Signal
    from amaranth.lib import wiring
    from amaranth.lib.wiring import In

    from ..hdl.bus import RegBusSignature
    from ..hdl.regmap import REGMAP
    from ..hdl.regs import RegisterFile
    from ..hdl.scope import Scope
    from ..hdl.top import REF_STEP_REGISTERS, _addr_in, regmap_address_map

    class RegisterLevelSim(wiring.Component):
        """Simulation-only bus slave for :meth:`Servo.sim`: the register file and the trace
        buffer without the control path.

        Every clock is a loop tick: ``commit`` is held high (shadowed writes apply after their
        frame, as on the drive) and the scope takes a sample per tick (per ``scope_decim``
        ticks). The scope's sources are the active ``speed_ref``, ``i_d_ref`` and ``i_q_ref``
        registers (their ``*_ref`` sources); every other source is 0. Its external trigger is the
        drive's reference step (:mod:`~foc_servo.hdl.top`, "Scope trigger"): a host write to the
        mode or a reference (``REF_STEP_REGISTERS``; an unchanged value too), in the clock after
        the one that applies it (the frame's end, ``lock`` low).
        ``st_mode`` reads the active ``mode``; every other status register reads 0.

        Members
        -------
        bus : In(RegBusSignature())
        """

        bus: In(RegBusSignature())
        address_map = regmap_address_map(REGMAP)

        def elaborate(self, platform):
            m = Module()
            m.submodules.regs = regs = RegisterFile(REGMAP)
            m.submodules.scope = scope = Scope()
            wiring.connect(m, wiring.flipped(self.bus), regs.bus)
            m.d.comb += [
                regs.commit.eq(1),
                scope.strobe.eq(1),
                scope.decim.eq(Mux(regs.scope_decim == 0, 0, regs.scope_decim - 1)),
                scope.pretrigger.eq(Mux(regs.scope_pretrig >= scope.depth, scope.depth - 1,
                                        regs.scope_pretrig)),
                scope.trig_src.as_value().eq(regs.scope_trig_src.as_value()),
                scope.arm.eq(regs.scope_arm),
                scope.force.eq(regs.scope_force),
                scope.rd_addr.eq(regs.scope_rd_addr),
                regs.scope_rd_data.eq(scope.rd_data),
                regs.scope_state.as_value().eq(scope.state.as_value()),
                regs.scope_status.as_value().eq(Cat(scope.done, scope.pre_full)),
                regs.st_mode.eq(regs.mode),
                scope.src.speed_ref.eq(regs.speed_ref),
                scope.src.i_d_ref.eq(regs.i_d_ref),
                scope.src.i_q_ref.eq(regs.i_q_ref),
            ]
            n_src = len(scope.source_names)
            unused = min(n_src, (1 << scope.sel_width) - 1)
            for c in range(scope.channels):
                chan = getattr(regs, f"scope_chan{c}")
                m.d.comb += scope.sel[c].eq(Mux(chan >= n_src, unused, chan))
            dirty = Signal()            # a reference write not yet applied
            write = regs.bus.ack & regs.bus.we & _addr_in(
                regs.bus.addr, [REGMAP[n].addr for n in REF_STEP_REGISTERS])
            applied = dirty & ~regs.bus.lock
            m.d.sync += [dirty.eq(write | (dirty & ~applied)), scope.trigger.eq(applied)]
            return m

    return RegisterLevelSim


def __getattr__(name):
    # RegisterLevelSim is built on first use, so that the host library proper imports no
    # gateware (hdl.regs, hdl.scope, hdl.top).
    if name == "RegisterLevelSim":
        cls = globals().get("_RegisterLevelSim") or _register_level_sim_class()
        globals()["_RegisterLevelSim"] = cls
        return cls
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
