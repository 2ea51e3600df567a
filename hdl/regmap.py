# Ref: paper §3 (every control parameter adjustable on line); issue 5 item 1; hdl/bus.py
"""The register map: the ONE declaration of every host-visible register.

The gateware register file (:class:`~foc_servo.hdl.regs.RegisterFile`), its golden model
(:mod:`foc_servo.sim.models.regs`), the host library's map (:mod:`foc_servo.host.registers`),
``docs/REGISTERS.md`` and ``include/foc_servo_regs.h`` (:mod:`foc_servo.host.codegen`) are all
generated from :data:`REGMAP`; nothing else spells an address. This module imports only the
fixed-point formats (:mod:`.fixed`) and ``amaranth.lib.enum``/``data``, never a gateware block, so
host code may import it.

Conventions
-----------
* Addresses are 16-bit word addresses; a word is 32 bits (:data:`.bus.DATA_WIDTH`). A register
  wider than 32 bits spans consecutive addresses, low word first.
* A register's raw value is an integer of its :class:`~.fixed.QFormat`. A read returns the raw
  bits, sign-extended to 32 bits in the top word of a signed register; a write takes the low bits
  of each word and ignores the rest.
* Access: ``rw`` (read/write; a read returns the value the host wrote, see shadowing), ``ro``
  (status from the control path), ``const`` (read-only identification fixed when the gateware is
  built), ``strobe`` (write-1: writing a word with bit 0 set gives one clock pulse; reads 0).
* Shadowing: a ``rw`` register with a ``shadow`` group is written into a staging register and
  copied to the control path (its *active* value) only at a loop boundary (the register file's
  ``commit`` strobe) while no host frame is in progress (``bus.lock`` low), so all the registers
  one frame writes take effect together. The group names registers that belong together (write
  them in one frame); all groups commit on the same strobe. ``shadow=None`` registers act at
  once (protection thresholds, scope control), as do strobes.
* Physical value = raw · 2**-frac · *scale*, *scale* an expression over the named system scales
  :data:`SCALE_NAMES` (``I_FS``: current full scale, A; ``U_FS``: volts per LSB of the U_dc
  code; ``N_FS``: full-scale speed, r/min; ``clk_hz``; ``pwm_hz``), e.g. ``"I_FS"``,
  ``"1/clk_hz"``, ``"I_FS/32768"``. The identification registers carry the scales, so a host needs
  no out-of-band knowledge (:meth:`Scales.from_id_raw`).
* ``pu`` (per unit): modulation indices (1.0 = (2/3)·U_dc, the hexagon vertex) and gains between
  per-unit quantities.
"""

import dataclasses
import math
import numbers
import re
import zlib

from amaranth.lib import data, enum

from .fixed import Q, UQ, QFormat

__all__ = [
    "Access", "Mode", "AngleMode", "TriggerSource", "ScopeState", "FAULT_FIELDS",
    "SCOPE_STATUS_FIELDS", "LOOP_FLAG_FIELDS", "LINK_COUNTERS", "LINK_COUNTER_WIDTH",
    "SCALE_NAMES", "Scales", "Register", "Window", "RegMap", "build_regmap", "REGMAP",
    "WORD_WIDTH", "MAGIC", "MAP_VERSION", "scale_factor", "mt_k_for", "MT_EDGES",
    "MT_EDGES_PER_LINE",
]

#: Bits per bus word (``hdl.bus.DATA_WIDTH``; repeated here so that host code need not import the
#: bus; a test checks they agree).
WORD_WIDTH = 32
#: ``id_magic``: "FOCS" in ASCII.
MAGIC = 0x464F4353
#: ``id_version``: major << 16 | minor of the register map; bump the major on incompatible change
#: (2.0: ``pi_speed_kx`` UQ(24, 24) → UQ(24, 20), I_FS 20 A → 40 A; status registers, theta_lead;
#: 2.1: the ``encoder_hall`` fault, ``prot_eh_tolerance``, ``prot_eh_misses``,
#: ``st_enc_hall_error``; 2.2: dead-time compensation ``dtc_clocks``, ``dtc_band``; the status
#: counters ``st_current_loops``, ``st_speed_loops``, ``st_overruns``, ``st_adc_overruns`` 16 bit; 2.3: the M/T block counts four
#: edges per line by default, ``mt_k``'s reset value is a quarter of 2.2's).
MAP_VERSION = (2 << 16) | 3

#: Fault causes in bit order (bit 0 first), as ``hdl.protect.FAULTS`` (a test checks they agree).
FAULT_FIELDS = ("external", "overcurrent_a", "overcurrent_b", "overcurrent_c",
                "overcurrent_comparator", "overvoltage", "undervoltage", "overspeed", "encoder",
                "hall", "encoder_hall")
#: Scope status flags in bit order.
SCOPE_STATUS_FIELDS = ("done", "pre_full")
#: Sticky control-loop flags (``st_loop_flags``) in bit order.
LOOP_FLAG_FIELDS = ("overmod", "sat_d", "sat_q", "dc_limited", "sat_speed")
#: Host-link status counters in the order of ``hdl.hostlink.COUNTERS`` (a test checks they agree);
#: registers ``st_link_<name>``.
LINK_COUNTERS = ("frames_ok", "crc_errors", "framing_errors", "rejected", "dropped")
#: Width of the host-link counters (they wrap): the link's ``counter_width``.
LINK_COUNTER_WIDTH = 16


class Access(enum.Enum):
    """Host access to a register."""
    RW = "rw"
    RO = "ro"
    CONST = "const"
    STROBE = "strobe"


class Mode(enum.Enum, shape=2):
    """Operating mode (``mode`` register; the Servo's ``mode`` input)."""
    DISABLED = 0    # gates off, regulators cleared
    OPEN_LOOP = 1   # u_d, u_q from ol_u_d, ol_u_q at the angle ol_angle_mode selects
    CURRENT = 2     # i_d, i_q references from i_d_ref, i_q_ref (torque control)
    SPEED = 3       # i_q reference from the speed loop, i_d from i_d_ref


class AngleMode(enum.Enum, shape=2):
    """Angle used in the open-loop mode (``ol_angle_mode`` register; the Servo's ``ol_src``
    input). The unused code 3 acts as ``FIXED``."""
    FIXED = 0       # ol_angle
    ROTATING = 1    # phase accumulator: starts at ol_angle, advances ol_freq per loop tick
    MEASURED = 2    # the measured θ_e (encoder / Hall check with a voltage vector)


class TriggerSource(enum.Enum, shape=1):
    """Scope trigger (``scope_trig_src`` register; the Scope's ``trig_src`` input), besides the
    host's ``scope_force``."""
    HOST = 0        # the scope_force strobe only
    EXTERNAL = 1    # the scope's trigger input (a reference step detected by the mode logic)


class ScopeState(enum.Enum, shape=2):
    """Scope capture state (``scope_state`` register; the Scope's ``state`` output)."""
    IDLE = 0        # not capturing (scope_status.done tells whether the buffer holds a capture)
    PRE = 1         # armed, filling the pre-trigger part / waiting for the trigger
    POST = 2        # triggered, taking the post-trigger samples


# --- system scales --------------------------------------------------------------------------

#: Names usable in a register's ``scale`` expression.
SCALE_NAMES = ("I_FS", "U_FS", "N_FS", "clk_hz", "pwm_hz")


@dataclasses.dataclass(frozen=True)
class Scales:
    """The named system scales the physical units are expressed in.

    Parameters
    ----------
    clk_hz : float
        System clock, Hz.
    pwm_hz : float
        PWM frequency (the current-loop rate), Hz.
    i_fs_a : float
        Current full scale ``I_FS``: the current of Q1.15 value 1.0, A. Default 40 A: the default
        motor's peak current is 28 A rms = 39.6 A amplitude (docs/TUNING.md), which 20 A clipped.
    u_fs_v : float
        ``U_FS``: volts per LSB of the U_dc code.
    n_fs_rpm : float
        Full-scale speed ``N_FS``: the speed of Q1.31 value 1.0, r/min.
    """
    clk_hz: float = 50e6
    pwm_hz: float = 10e3
    i_fs_a: float = 40.0
    u_fs_v: float = 12.5e-3
    n_fs_rpm: float = 12000.0

    def __post_init__(self):
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if (not isinstance(v, numbers.Real) or isinstance(v, bool) or not math.isfinite(v)
                    or not v > 0):
                raise TypeError(f"Scales {f.name} must be a positive finite number, not {v!r}")

    def value(self, name):
        """The scale called ``name`` (one of :data:`SCALE_NAMES`)."""
        return {"I_FS": self.i_fs_a, "U_FS": self.u_fs_v, "N_FS": self.n_fs_rpm,
                "clk_hz": self.clk_hz, "pwm_hz": self.pwm_hz}[name]

    def id_raw(self):
        """Raw values of the identification registers that carry the scales."""
        return {
            "id_clk_hz": round(self.clk_hz),
            "id_pwm_mhz": round(self.pwm_hz * 1e3),
            "id_i_fs_ma": round(self.i_fs_a * 1e3),
            "id_u_fs_uv": round(self.u_fs_v * 1e6),
            "id_n_fs_rpm": round(self.n_fs_rpm),
        }

    @classmethod
    def from_id_raw(cls, raw):
        """Scales from the raw identification registers (a mapping name → raw value, e.g. read
        over the link)."""
        try:
            return cls(clk_hz=float(raw["id_clk_hz"]), pwm_hz=raw["id_pwm_mhz"] / 1e3,
                       i_fs_a=raw["id_i_fs_ma"] / 1e3, u_fs_v=raw["id_u_fs_uv"] / 1e6,
                       n_fs_rpm=float(raw["id_n_fs_rpm"]))
        except TypeError as e:
            raise ValueError(f"identification registers do not hold valid scales: {e}") from None


_SCALE_TOKEN = re.compile(
    r"\s*([*/])?\s*([A-Za-z_][A-Za-z_0-9]*|[0-9]+(?:\.[0-9]*)?(?:e-?[0-9]+)?)")


def _parse_scale(expr):
    """``[(op, token), ...]`` of a scale expression: numbers and scale names joined by * and /."""
    if not isinstance(expr, str) or not expr.strip():
        raise TypeError(f"Register scale must be a non-empty string, not {expr!r}")
    terms, pos = [], 0
    while pos < len(expr):
        m = _SCALE_TOKEN.match(expr, pos)
        if m is None or (m.group(1) is None) != (pos == 0):
            raise ValueError(f"Register scale {expr!r} is not a product of numbers and scale names")
        op, tok = m.group(1) or "*", m.group(2)
        if not tok[0].isdigit() and tok not in SCALE_NAMES:
            raise ValueError(f"Register scale {expr!r} names {tok!r}, not one of "
                             f"{', '.join(SCALE_NAMES)}")
        terms.append((op, tok))
        pos = m.end()
    return terms


def scale_factor(expr, scales):
    """Value of the scale expression ``expr`` under ``scales`` (:class:`Scales`)."""
    factor = 1.0
    for op, tok in _parse_scale(expr):
        v = float(tok) if tok[0].isdigit() else scales.value(tok)
        factor = factor * v if op == "*" else factor / v
    return factor


#: Encoder edges the M/T speed block counts, per line, for each edge mode (``MTSpeed``'s
#: ``edge_mode``, ``Top``'s ``mt_edges``): ``"x4"`` every quadrature state change,
#: ``"a_rising"`` the A-rising position only. The one table of edges per line.
MT_EDGES_PER_LINE = {"a_rising": 1, "x4": 4}
#: The edge mode of the default build (``Top(mt_edges=...)``), which the ``mt_k`` reset value and
#: the host's ``mt_k`` assume.
MT_EDGES = "x4"


def mt_k_for(scales, *, lines=5000, edges_per_line=None, out_width=32):
    """M/T ``k`` for f_TCLK = ``clk_hz``: ``round(60·2**(out_width−1)·clk_hz / (lines·
    edges_per_line·N_FS))`` (as :func:`foc_servo.sim.models.mt_speed.k_for`);
    ``edges_per_line=None``: the default build's, ``MT_EDGES_PER_LINE[MT_EDGES]`` (4)."""
    if edges_per_line is None:
        edges_per_line = MT_EDGES_PER_LINE[MT_EDGES]
    return round(60 * (1 << (out_width - 1)) * scales.clk_hz /
                 (lines * edges_per_line * scales.n_fs_rpm))


# --- declarations ---------------------------------------------------------------------------

_NAME = re.compile(r"[a-z][a-z0-9_]*\Z")


@dataclasses.dataclass(frozen=True)
class Register:
    """One register.

    Parameters
    ----------
    name : str
        Lower-case identifier: the register file's port name and the host's key.
    addr : int
        Word address of the (low) word.
    fmt : QFormat
        Raw format; ``fmt.width`` is the register width (1 … 64).
    access : Access
    reset : int
        Raw value after reset (for ``const``: the constant).
    desc : str
        One line.
    unit : str
        Physical unit of ``raw · 2**-frac · scale``; ``""`` for flags, enums and bit fields.
    scale : str
        Scale expression (see the module docstring).
    shadow : str or None
        Shadow group of a ``rw`` register (``None``: acts at once).
    enum : type or None
        An ``amaranth.lib.enum.Enum`` the raw value encodes.
    fields : tuple of str or None
        Names of one-bit flags, bit 0 first.
    """
    name: str
    addr: int
    fmt: QFormat
    access: Access
    reset: int
    desc: str
    unit: str = ""
    scale: str = "1"
    shadow: str = None
    enum: type = None
    fields: tuple = None

    def __post_init__(self):
        if not isinstance(self.name, str) or not _NAME.match(self.name):
            raise TypeError(f"Register name must be a lower-case identifier, not {self.name!r}")
        if (not isinstance(self.addr, int) or isinstance(self.addr, bool)
                or not 0 <= self.addr < 1 << 16):
            raise TypeError(f"Register {self.name} address must be an integer from 0 to 65535, "
                            f"not {self.addr!r}")
        if not isinstance(self.fmt, QFormat):
            raise TypeError(f"Register {self.name} format must be a QFormat, not {self.fmt!r}")
        if not isinstance(self.access, Access):
            raise TypeError(f"Register {self.name} access must be an Access, not "
                            f"{self.access!r}")
        if self.addr + self.words > 1 << 16:
            raise ValueError(f"Register {self.name} at {self.addr:#06x} spans {self.words} words "
                             f"beyond the 16-bit address space")
        if (not isinstance(self.reset, int) or isinstance(self.reset, bool)
                or not self.fmt.min_raw <= self.reset <= self.fmt.max_raw):
            raise ValueError(f"Register {self.name} reset value must be an integer from "
                             f"{self.fmt.min_raw} to {self.fmt.max_raw}, not {self.reset!r}")
        if not isinstance(self.desc, str) or not self.desc or "\n" in self.desc:
            raise TypeError(f"Register {self.name} description must be one non-empty line, not "
                            f"{self.desc!r}")
        _parse_scale(self.scale)
        if self.shadow is not None:
            if self.access is not Access.RW:
                raise ValueError(f"Register {self.name} is {self.access.value}: only rw "
                                 f"registers are shadowed, not shadow={self.shadow!r}")
            if not isinstance(self.shadow, str) or not _NAME.match(self.shadow):
                raise TypeError(f"Register {self.name} shadow group must be a lower-case "
                                f"identifier or None, not {self.shadow!r}")
        if self.access is Access.STROBE and self.fmt != UQ(1, 0):
            raise ValueError(f"Register {self.name} is a strobe: its format must be UQ(1, 0), "
                             f"not {self.fmt!r}")
        if self.access is Access.RO and self.width > WORD_WIDTH:
            raise ValueError(f"Register {self.name} is read-only and {self.width} bits wide: "
                             f"status registers are at most {WORD_WIDTH} bits (no torn reads)")
        if self.enum is not None:
            if not (isinstance(self.enum, enum.EnumType) and
                    getattr(self.enum, "_amaranth_shape_", None) is not None):
                raise TypeError(f"Register {self.name} enum must be an amaranth.lib.enum.Enum "
                                f"with a shape, not {self.enum!r}")
            if self.fmt != UQ(self.enum.as_shape().width, 0):
                raise ValueError(f"Register {self.name} format must be "
                                 f"{UQ(self.enum.as_shape().width, 0)!r} for its enum, not "
                                 f"{self.fmt!r}")
        if self.fields is not None:
            if (not isinstance(self.fields, tuple) or not self.fields
                    or not all(isinstance(f, str) and _NAME.match(f) for f in self.fields)
                    or len(set(self.fields)) != len(self.fields)):
                raise TypeError(f"Register {self.name} fields must be a tuple of distinct "
                                f"lower-case names, not {self.fields!r}")
            if self.fmt != UQ(len(self.fields), 0):
                raise ValueError(f"Register {self.name} format must be "
                                 f"{UQ(len(self.fields), 0)!r} for its {len(self.fields)} fields, "
                                 f"not {self.fmt!r}")

    width = property(lambda self: self.fmt.width)
    signed = property(lambda self: self.fmt.signed)

    @property
    def words(self):
        """Number of consecutive word addresses."""
        return -(-self.width // WORD_WIDTH)

    @property
    def kind(self):
        """``"enum"``, ``"flags"`` (bit fields), ``"bool"`` (one bit) or ``"number"``."""
        if self.enum is not None:
            return "enum"
        if self.fields is not None:
            return "flags"
        if self.width == 1 and self.unit == "":
            return "bool"
        return "number"

    @property
    def shape(self):
        """The Amaranth shape of the register file port: the enum, a StructLayout of the fields,
        or ``fmt.shape``."""
        if self.enum is not None:
            return self.enum
        if self.fields is not None:
            return data.StructLayout({f: 1 for f in self.fields})
        return self.fmt.shape

    @property
    def init(self):
        """The reset value as an ``init=`` for :attr:`shape`."""
        if self.enum is not None:
            return self.enum(self.reset)
        if self.fields is not None:
            return {f: (self.reset >> i) & 1 for i, f in enumerate(self.fields)}
        return self.reset

    @property
    def mask(self):
        return (1 << self.width) - 1

    def bits(self, raw):
        """The unsigned bit pattern of a raw value."""
        return raw & self.mask

    def raw(self, bits):
        """The raw (signed, for a signed format) value of a bit pattern."""
        bits &= self.mask
        if self.signed and bits >> (self.width - 1):
            bits -= 1 << self.width
        return bits

    def word_slice(self, k):
        """``(lo, hi)`` bit range of word ``k``."""
        lo = k * WORD_WIDTH
        return lo, min(lo + WORD_WIDTH, self.width)

    def read_word(self, bits, k):
        """The bus word ``k`` of a register holding ``bits`` (top word of a signed register
        sign-extended)."""
        lo, hi = self.word_slice(k)
        word = (bits >> lo) & ((1 << (hi - lo)) - 1)
        if self.signed and k == self.words - 1 and word >> (hi - lo - 1):
            word |= ((1 << WORD_WIDTH) - 1) ^ ((1 << (hi - lo)) - 1)
        return word

    def write_word(self, bits, k, word):
        """The bits after writing bus word ``k`` (its low bits; the rest ignored)."""
        lo, hi = self.word_slice(k)
        m = ((1 << (hi - lo)) - 1) << lo
        return (bits & ~m) | ((word << lo) & m)

    def to_words(self, raw):
        """Bus words of a raw value, low first."""
        return [self.read_word(self.bits(raw), k) for k in range(self.words)]

    def from_words(self, words):
        """Raw value from bus words, low first."""
        if len(words) != self.words:
            raise ValueError(f"Register {self.name} takes {self.words} words, not {len(words)}")
        bits = 0
        for k, w in enumerate(words):
            bits = self.write_word(bits, k, w)
        return self.raw(bits)


@dataclasses.dataclass(frozen=True)
class Window:
    """A read-only address window onto a memory (the scope's trace buffer).

    ``size`` words from ``addr`` (a power of two, ``addr`` aligned to it); the register file gives
    ``{name}_rd_addr`` = word offset and reads ``{name}_rd_data`` one clock later.
    """
    name: str
    addr: int
    size: int
    desc: str

    def __post_init__(self):
        if not isinstance(self.name, str) or not _NAME.match(self.name):
            raise TypeError(f"Window name must be a lower-case identifier, not {self.name!r}")
        if (not isinstance(self.size, int) or isinstance(self.size, bool) or self.size < 1
                or self.size & (self.size - 1) or self.size > 1 << 15):
            raise TypeError(f"Window {self.name} size must be a power of two from 1 to 32768, "
                            f"not {self.size!r}")
        if (not isinstance(self.addr, int) or isinstance(self.addr, bool)
                or not 0 <= self.addr < 1 << 16 or self.addr % self.size):
            raise ValueError(f"Window {self.name} address must be a multiple of its size "
                             f"{self.size} below 65536, not {self.addr!r}")

    @property
    def addr_width(self):
        return self.size.bit_length() - 1


class RegMap:
    """An ordered, validated collection of :class:`Register` and :class:`Window` declarations.

    Raises
    ------
    ValueError
        Duplicate names, overlapping addresses, or a name that is not a valid port name.
    """

    _RESERVED = frozenset({"bus", "commit", "signature"})

    def __init__(self, registers, windows=()):
        registers, windows = tuple(registers), tuple(windows)
        for r in registers:
            if not isinstance(r, Register):
                raise TypeError(f"RegMap registers must be Register declarations, not {r!r}")
        for w in windows:
            if not isinstance(w, Window):
                raise TypeError(f"RegMap windows must be Window declarations, not {w!r}")
        names = set()
        ports = {r.name for r in registers} | {f"{w.name}_rd_{x}" for w in windows
                                               for x in ("addr", "data")}
        for item in registers + windows:
            if item.name in names or item.name in self._RESERVED:
                raise ValueError(f"RegMap name {item.name!r} is used twice or reserved")
            names.add(item.name)
        if len(ports) != len(registers) + 2 * len(windows):
            raise ValueError("RegMap window port names collide with register names")
        owner = {}
        for r in registers:
            for k in range(r.words):
                if r.addr + k in owner:
                    raise ValueError(f"RegMap register {r.name} word {k} at {r.addr + k:#06x} "
                                     f"overlaps {owner[r.addr + k]}")
                owner[r.addr + k] = r.name
        for w in windows:
            for a in owner:
                if w.addr <= a < w.addr + w.size:
                    raise ValueError(f"RegMap window {w.name} overlaps register {owner[a]} at "
                                     f"{a:#06x}")
            for v in windows:
                if v is not w and v.addr < w.addr + w.size and w.addr < v.addr + v.size:
                    raise ValueError(f"RegMap windows {w.name} and {v.name} overlap")
        self._registers = registers
        self._windows = windows
        self._by_name = {r.name: r for r in registers}

    registers = property(lambda self: self._registers)
    windows = property(lambda self: self._windows)

    def __iter__(self):
        return iter(self._registers)

    def __len__(self):
        return len(self._registers)

    def __contains__(self, name):
        return name in self._by_name

    def __getitem__(self, name):
        try:
            return self._by_name[name]
        except KeyError:
            raise KeyError(f"no register named {name!r}") from None

    def words(self):
        """Every word address: ``[(addr, register, k), ...]`` in address order."""
        return sorted(((r.addr + k, r, k) for r in self._registers for k in range(r.words)),
                      key=lambda t: t[0])

    def replace(self, name, **changes):
        """A copy of the map with register ``name``'s declaration changed (and ``id_map_hash``,
        if there is one, recomputed)."""
        self[name]
        new = RegMap([dataclasses.replace(r, **changes) if r.name == name else r
                      for r in self._registers], self._windows)
        if "id_map_hash" in new:
            new = new.with_constants({"id_map_hash": new.layout_hash})
        return new

    def with_constants(self, values):
        """A copy with the reset values (for ``const``: the values) of the named registers
        replaced."""
        for n in values:
            self[n]
        return RegMap([dataclasses.replace(r, reset=values[r.name]) if r.name in values else r
                       for r in self._registers], self._windows)

    @property
    def layout_hash(self):
        """CRC-32 of the layout (names, addresses, formats, access, enum and field names;
        not the reset values): the ``id_map_hash`` constant."""
        parts = []
        for r in self._registers:
            en = ",".join(f"{m.name}={m.value}" for m in r.enum) if r.enum else ""
            parts.append(f"{r.name}@{r.addr}:{r.fmt!r}:{r.access.value}:{r.scale}:{r.unit}:"
                         f"{r.shadow}:{en}:{','.join(r.fields or ())}")
        for w in self._windows:
            parts.append(f"{w.name}@{w.addr}+{w.size}")
        return zlib.crc32(";".join(parts).encode())

    def group_of(self, addr):
        """The address group heading of an address (``docs``)."""
        for base, title in reversed(GROUPS):
            if addr >= base:
                return title
        return GROUPS[0][1]


#: Address groups, for the documentation (base address, title).
GROUPS = (
    (0x0000, "Identification"),
    (0x0010, "Control, mode and references"),
    (0x0100, "Current loop"),
    (0x0180, "PWM and gate drive"),
    (0x0200, "Speed loop"),
    (0x0280, "Encoder and Hall sensors"),
    (0x0300, "Protection"),
    (0x0400, "Status"),
    (0x0500, "Scope control"),
    (0x1000, "Scope trace buffer"),
)


def build_regmap(scales=Scales()):
    """The register map of a drive built for ``scales``: the identification constants and the
    reset values that depend on the clock or the full-scale speed (dead time, M/T ``k``, filter)
    follow ``scales``; addresses and formats do not."""
    if not isinstance(scales, Scales):
        raise TypeError(f"build_regmap scales must be Scales, not {scales!r}")
    RW, RO, CONST, STROBE = Access.RW, Access.RO, Access.CONST, Access.STROBE
    ids = scales.id_raw()
    cur, mod, spd = Q(16, 15), Q(16, 15), Q(32, 31)
    angle = UQ(16, 16)
    lin = round(math.sqrt(3) / 2 * (1 << 15))        # linear-modulation limit √3/2, Q1.15
    dead_clk = round(1e-6 * scales.clk_hz)           # 1 µs
    if not dead_clk < 1 << 8:
        raise ValueError(f"build_regmap: a 1 µs dead time is {dead_clk} clocks at "
                         f"{scales.clk_hz:g} Hz, more than the 8-bit dead_time register holds")
    k = mt_k_for(scales)
    if not 0 < k < 1 << 48:
        raise ValueError(f"build_regmap: M/T k {k} for {scales.n_fs_rpm:g} r/min does not fit "
                         f"48 bits")

    def reg(name, addr, fmt, access, reset, desc, **kw):
        return Register(name, addr, fmt, access, reset, desc, **kw)

    def pi(prefix, base, lim_fmt, lim_reset, unit_in, unit_out, out_scale,
           kp_fmt=UQ(16, 8), kx_fmt=UQ(16, 16), kx_note=""):
        what = {"pi_d": "d-axis current", "pi_q": "q-axis current", "pi_speed": "speed"}[prefix]
        return [
            reg(f"{prefix}_kp", base, kp_fmt, RW, 0,
                f"{what} PI proportional gain K_p (per unit: {unit_out} per {unit_in})",
                unit="pu", shadow=prefix),
            reg(f"{prefix}_kx", base + 1, kx_fmt, RW, 0,
                f"{what} PI integral gain K_x = K_i·T_s/2 (Tustin; per unit){kx_note}",
                unit="pu", shadow=prefix),
            reg(f"{prefix}_lim_lo", base + 2, lim_fmt, RW, -lim_reset,
                f"{what} PI output lower limit", unit=out_scale[1], scale=out_scale[0],
                shadow=prefix),
            reg(f"{prefix}_lim_hi", base + 3, lim_fmt, RW, lim_reset,
                f"{what} PI output upper limit", unit=out_scale[1], scale=out_scale[0],
                shadow=prefix),
        ]

    registers = [
        # --- identification ---
        reg("id_magic", 0x0000, UQ(32, 0), CONST, MAGIC, "magic number 0x464F4353 (\"FOCS\")"),
        reg("id_version", 0x0001, UQ(32, 0), CONST, MAP_VERSION,
            "register map version, major << 16 | minor"),
        reg("id_map_hash", 0x0002, UQ(32, 0), CONST, 0,
            "CRC-32 of the register map layout (host and gateware must agree)"),
        reg("id_clk_hz", 0x0003, UQ(32, 0), CONST, ids["id_clk_hz"],
            "system clock frequency clk_hz", unit="Hz"),
        reg("id_pwm_mhz", 0x0004, UQ(32, 0), CONST, ids["id_pwm_mhz"],
            "PWM frequency pwm_hz (actual), in mHz", unit="Hz", scale="1/1000"),
        reg("id_i_fs_ma", 0x0005, UQ(32, 0), CONST, ids["id_i_fs_ma"],
            "current full scale I_FS (Q1.15 value 1.0), in mA (default 40 A: the default motor's "
            "peak is 39.6 A)", unit="A", scale="1/1000"),
        reg("id_u_fs_uv", 0x0006, UQ(32, 0), CONST, ids["id_u_fs_uv"],
            "U_FS: DC-bus volts per LSB of the U_dc code, in µV", unit="V", scale="1/1000000"),
        reg("id_n_fs_rpm", 0x0007, UQ(32, 0), CONST, ids["id_n_fs_rpm"],
            "full-scale speed N_FS (Q1.31 value 1.0)", unit="r/min"),
        # --- control, mode and references ---
        reg("mode", 0x0010, UQ(2, 0), RW, Mode.DISABLED.value,
            "operating mode: disabled, open-loop voltage, current, speed", enum=Mode,
            shadow="setpoint"),
        reg("clear_faults", 0x0011, UQ(1, 0), STROBE, 0,
            "write 1: release the trip latch and clear first/seen faults (if no cause present); "
            "clear st_loop_flags"),
        reg("speed_ref", 0x0012, spd, RW, 0, "speed reference", unit="r/min", scale="N_FS",
            shadow="setpoint"),
        reg("i_d_ref", 0x0013, cur, RW, 0, "d-axis current reference (current mode and speed "
            "mode)", unit="A", scale="I_FS", shadow="setpoint"),
        reg("i_q_ref", 0x0014, cur, RW, 0, "q-axis current reference (current mode)",
            unit="A", scale="I_FS", shadow="setpoint"),
        reg("ol_angle_mode", 0x0015, UQ(2, 0), RW, AngleMode.FIXED.value,
            "open-loop angle: fixed ol_angle, rotating at ol_freq, or the measured θ_e",
            enum=AngleMode, shadow="setpoint"),
        reg("ol_u_d", 0x0016, mod, RW, 0, "open-loop d-axis voltage (modulation index)",
            unit="pu", shadow="setpoint"),
        reg("ol_u_q", 0x0017, mod, RW, 0, "open-loop q-axis voltage (modulation index)",
            unit="pu", shadow="setpoint"),
        reg("ol_angle", 0x0018, angle, RW, 0, "open-loop fixed electrical angle "
            "(BinaryAngle(16))", unit="deg", scale="360", shadow="setpoint"),
        reg("ol_freq", 0x0019, Q(32, 32), RW, 0, "open-loop electrical frequency: 32-bit phase "
            "increment per loop tick (turns per PWM period)", unit="Hz", scale="pwm_hz",
            shadow="setpoint"),
        # --- current loop ---
        *pi("pi_d", 0x0100, mod, lin, "I_FS", "(2/3)·U_dc", ("1", "pu")),
        *pi("pi_q", 0x0104, mod, lin, "I_FS", "(2/3)·U_dc", ("1", "pu")),
        reg("clarke_gain_a", 0x0110, Q(18, 15), RW, 1 << 15,
            "phase a current scale: current per ADC LSB", unit="A/LSB", scale="I_FS/32768",
            shadow="clarke"),
        reg("clarke_offset_a", 0x0111, Q(17, 0), RW, 0, "phase a zero-current ADC code",
            unit="LSB", shadow="clarke"),
        reg("clarke_gain_b", 0x0112, Q(18, 15), RW, 1 << 15,
            "phase b current scale: current per ADC LSB", unit="A/LSB", scale="I_FS/32768",
            shadow="clarke"),
        reg("clarke_offset_b", 0x0113, Q(17, 0), RW, 0, "phase b zero-current ADC code",
            unit="LSB", shadow="clarke"),
        reg("u_rated", 0x0118, UQ(16, 0), RW, 1 << 14,
            "rated DC-bus voltage of the bus compensation (u · u_rated / U_dc)", unit="V",
            scale="U_FS", shadow="dcbus"),
        reg("decouple_enable", 0x0120, UQ(1, 0), RW, 0, "d–q decoupling feed-forward on",
            shadow="decouple"),
        reg("decouple_l", 0x0121, UQ(16, 14), RW, 0,
            "decoupling inductance term ω_e,FS·L·I_FS / ((2/3)·U_rated)", unit="pu",
            shadow="decouple"),
        reg("decouple_psi", 0x0122, UQ(16, 14), RW, 0,
            "back-EMF term ω_e,FS·ψ_F / ((2/3)·U_rated)", unit="pu", shadow="decouple"),
        reg("theta_lead", 0x0124, angle, RW, 0,
            "inverse-Park angle advance at full-scale speed, ω_e,FS·t_lead (θ + speed/N_FS · "
            "theta_lead; t_lead = 1/pwm_hz compensates the PWM delay; 0: off)", unit="deg",
            scale="360", shadow="lead"),
        # --- PWM and gate drive ---
        reg("pwm_symmetric", 0x0180, UQ(1, 0), RW, 1, "SVPWM symmetric (centre-aligned) mode",
            shadow="pwm"),
        reg("pwm_sample_custom", 0x0181, UQ(1, 0), RW, 0,
            "ADC sample at pwm_sample_point instead of the period centre", shadow="pwm"),
        reg("pwm_sample_point", 0x0182, UQ(16, 0), RW, 0,
            "ADC sample time from the period start (with pwm_sample_custom)", unit="s",
            scale="1/clk_hz", shadow="pwm"),
        reg("dead_time", 0x0183, UQ(8, 0), RW, dead_clk, "gate dead time", unit="s",
            scale="1/clk_hz", shadow="pwm"),
        # Dead-time compensation (hdl/deadtime_comp.py): off at reset.
        reg("dtc_clocks", 0x0184, UQ(8, 0), RW, 0,
            "dead-time compensation: high time added per period beyond the band, the effective "
            "dead time max(dead_time, 1) (0: off)", unit="s", scale="1/clk_hz", shadow="pwm"),
        reg("dtc_band", 0x0185, UQ(4, 0), RW, 4,
            "dead-time compensation slope shift: linear up to |i| = dtc_clocks · 2^dtc_band "
            "current LSB (I_FS/32768), saturated beyond", unit="", shadow="pwm"),
        # --- speed loop ---
        # Reset limit ±I_FS/4 (±10 A at the default 40 A); kx UQ4.20: the default motor's
        # symmetric-optimum kx is 0.0091 … 9.10 for 50 … 500 Hz at 10 kHz (docs/TUNING.md).
        *pi("pi_speed", 0x0200, cur, 1 << 13, "N_FS", "I_FS", ("I_FS", "A"),
            kp_fmt=UQ(24, 12), kx_fmt=UQ(24, 20), kx_note=", 0 … 16"),
        reg("speed_div", 0x0204, UQ(8, 0), RW, 1,
            "speed loop every speed_div PWM periods (0 acts as 1)", unit="periods",
            shadow="speed"),
        reg("mt_k", 0x0205, UQ(48, 0), RW, k,
            "M/T scale k = 60·2^31·f_TCLK / (lines·edges·N_FS), f_TCLK = clk_hz, edges per "
            "line 4 (x4 build; 1 for mt_edges='a_rising')", unit="",
            shadow="speed"),
        # Reference profile (hdl/servo.py): off at reset (slew 0, no feed-forward).
        reg("speed_slew", 0x0207, UQ(32, 31), RW, 0,
            "largest change of the speed loop's reference per speed-loop run (0: steps)",
            unit="r/min", scale="N_FS", shadow="speed"),
        reg("speed_ff_iq", 0x0208, cur, RW, 0,
            "acceleration feed-forward J·α/K_t, added while the reference profile moves",
            unit="A", scale="I_FS", shadow="speed"),
        reg("speed_ref_delay", 0x0209, UQ(5, 3), RW, 0,
            "the speed PI compares with the profile this many runs ago (0 … 3.875)",
            unit="runs", shadow="speed"),
        reg("speed_int_hold", 0x020A, UQ(1, 0), RW, 0,
            "hold the speed PI's integrator while the profile moves", shadow="speed"),
        # --- encoder and Hall sensors ---
        reg("enc_lines", 0x0280, UQ(16, 0), RW, 5000, "encoder lines per revolution",
            unit="lines", shadow="encoder"),
        reg("enc_pole_pairs", 0x0281, UQ(8, 0), RW, 4, "motor pole pairs", unit="pairs",
            shadow="encoder"),
        reg("enc_z_offset", 0x0282, UQ(18, 0), RW, 0,
            "electrical angle at the Z index, in encoder counts (0 … 4·lines − 1)",
            unit="counts", shadow="encoder"),
        reg("enc_hall_offset", 0x0283, angle, RW, 0, "Hall angle offset (BinaryAngle(16))",
            unit="deg", scale="360", shadow="encoder"),
        reg("enc_filter", 0x0284, UQ(8, 0), RW, 4, "glitch filter length of the encoder and "
            "Hall inputs", unit="s", scale="1/clk_hz", shadow="encoder"),
        reg("enc_realign", 0x0285, UQ(1, 0), STROBE, 0,
            "write 1: forget the alignment, realign at the next Z index"),
        # --- protection (act at once) ---
        reg("prot_oc_limit", 0x0300, UQ(16, 15), RW, (1 << 16) - 1,
            "over-current threshold on |i_a|, |i_b|, |i_c| (reset: never trips)", unit="A",
            scale="I_FS"),
        reg("prot_ov_limit", 0x0301, Q(16, 0), RW, (1 << 15) - 1,
            "DC-bus over-voltage threshold (reset: never trips)", unit="V", scale="U_FS"),
        reg("prot_uv_limit", 0x0302, Q(16, 0), RW, -(1 << 15),
            "DC-bus under-voltage threshold (reset: never trips)", unit="V", scale="U_FS"),
        reg("prot_uv_enable", 0x0303, UQ(1, 0), RW, 0,
            "under-voltage check on (armed by the first sample above prot_uv_limit)"),
        reg("prot_os_limit", 0x0304, UQ(32, 31), RW, (1 << 32) - 1,
            "over-speed threshold on |speed| (reset: never trips)", unit="r/min",
            scale="N_FS"),
        reg("prot_mask", 0x0305, UQ(len(FAULT_FIELDS), 0), RW, (1 << len(FAULT_FIELDS)) - 1,
            "fault causes acted on (a cleared bit ignores that cause)", fields=FAULT_FIELDS),
        reg("prot_eh_tolerance", 0x0306, angle, RW, 1 << 13,
            "encoder/Hall plausibility: largest |θ_e(encoder) − Hall edge angle| at a Hall edge, "
            "and largest error of the encoder's advance over a Hall sector, that is not a miss",
            unit="deg", scale="360"),
        reg("prot_eh_misses", 0x0307, UQ(4, 0), RW, 1,
            "encoder/Hall plausibility: consecutive missed Hall edges that raise the "
            "encoder_hall fault (0 acts as 1)", unit="edges"),
        # --- status ---
        reg("st_mode", 0x0400, UQ(2, 0), RO, 0,
            "mode in force (disabled while tripped; mode changes at a loop boundary)",
            enum=Mode),
        reg("st_trip", 0x0401, UQ(1, 0), RO, 0, "trip latch: gates forced off"),
        reg("st_fault_present", 0x0402, UQ(len(FAULT_FIELDS), 0), RO, 0,
            "fault causes present now", fields=FAULT_FIELDS),
        reg("st_fault_first", 0x0403, UQ(len(FAULT_FIELDS), 0), RO, 0,
            "fault cause(s) that tripped the latch", fields=FAULT_FIELDS),
        reg("st_fault_seen", 0x0404, UQ(len(FAULT_FIELDS), 0), RO, 0,
            "every fault cause since the last clear", fields=FAULT_FIELDS),
        reg("st_enc_aligned", 0x0405, UQ(1, 0), RO, 0,
            "encoder aligned by a Z index (else θ_e from the Hall sensors)"),
        reg("st_position", 0x0406, UQ(18, 0), RO, 0,
            "mechanical position, encoder counts (×4) since the Z index", unit="counts"),
        reg("st_theta", 0x0407, angle, RO, 0, "electrical angle θ_e (BinaryAngle(16))",
            unit="deg", scale="360"),
        reg("st_speed", 0x0408, spd, RO, 0, "measured speed (M/T)", unit="r/min",
            scale="N_FS"),
        reg("st_i_d", 0x0409, cur, RO, 0, "d-axis current", unit="A", scale="I_FS"),
        reg("st_i_q", 0x040A, cur, RO, 0, "q-axis current", unit="A", scale="I_FS"),
        reg("st_i_alpha", 0x040B, cur, RO, 0, "α current", unit="A", scale="I_FS"),
        reg("st_i_beta", 0x040C, cur, RO, 0, "β current", unit="A", scale="I_FS"),
        reg("st_u_d", 0x040D, mod, RO, 0, "d-axis voltage command (modulation index)",
            unit="pu"),
        reg("st_u_q", 0x040E, mod, RO, 0, "q-axis voltage command (modulation index)",
            unit="pu"),
        reg("st_u_alpha", 0x040F, mod, RO, 0, "α voltage command (modulation index)",
            unit="pu"),
        reg("st_u_beta", 0x0410, mod, RO, 0, "β voltage command (modulation index)",
            unit="pu"),
        reg("st_udc", 0x0411, Q(16, 0), RO, 0, "DC-bus voltage", unit="V", scale="U_FS"),
        # 16-bit counters (area, issue 7): st_current_loops wraps every 6.5 s at 10 kHz, so a
        # rate is the difference of two reads less than that apart, modulo 2**16.
        reg("st_current_loops", 0x0418, UQ(16, 0), RO, 0,
            "current-loop computations since reset (wraps at 2^16)", unit="counts"),
        reg("st_speed_loops", 0x0419, UQ(16, 0), RO, 0,
            "speed-loop computations since reset (wraps at 2^16)", unit="counts"),
        reg("st_overruns", 0x041A, UQ(16, 0), RO, 0,
            "ADC samples arriving while the current loop was busy (wraps at 2^16)",
            unit="counts"),
        reg("st_adc_overruns", 0x041B, UQ(16, 0), RO, 0,
            "ADC sample strobes dropped because a conversion was in progress (wraps at 2^16)",
            unit="counts"),
        reg("st_loop_flags", 0x041C, UQ(len(LOOP_FLAG_FIELDS), 0), RO, 0,
            "sticky: a loop since the last clear_faults over-modulated / saturated PI_d, PI_q / "
            "hit the DC-bus gain limit / saturated the speed PI", fields=LOOP_FLAG_FIELDS),
        reg("st_uv_armed", 0x041D, UQ(1, 0), RO, 0,
            "under-voltage check armed (prot_uv_enable and a U_dc sample above prot_uv_limit)"),
        reg("st_enc_config_error", 0x041E, UQ(1, 0), RO, 0,
            "encoder configuration invalid (lines 0, pole pairs 0 or ≥ 4·lines, or z offset ≥ "
            "4·lines): nothing counts"),
        *[reg(f"st_link_{name}", 0x041F + k, UQ(LINK_COUNTER_WIDTH, 0), RO, 0, desc,
              unit="frames")
          for k, (name, desc) in enumerate(zip(LINK_COUNTERS, (
              "host-link frames answered OK before this one (wraps)",
              "host-link frames answered BAD_CRC for a CRC mismatch (wraps)",
              "host-link frames answered BAD_CRC for a UART framing or COBS error (wraps)",
              "host-link frames answered BAD_LENGTH, BAD_COMMAND, BAD_ADDRESS or READ_ONLY "
              "(wraps)",
              "host-link frames skipped without a reply: bytes arrived while busy (wraps)")))],
        reg("st_enc_hall_error", 0x0424, Q(16, 16), RO, 0,
            "θ_e(encoder) − Hall edge angle (with enc_hall_offset) at the last Hall edge; once "
            "aligned, the error of enc_hall_offset", unit="deg", scale="360"),
        # --- scope control (acts at once) ---
        *[reg(f"scope_chan{c}", 0x0500 + c, UQ(8, 0), RW, c,
              f"scope channel {c} signal select (index into the scope's signal list)")
          for c in range(4)],
        reg("scope_decim", 0x0504, UQ(16, 0), RW, 1,
            "scope samples every scope_decim loop ticks (0 acts as 1)", unit="ticks"),
        reg("scope_pretrig", 0x0505, UQ(16, 0), RW, 0, "scope samples kept before the trigger",
            unit="samples"),
        reg("scope_trig_src", 0x0506, UQ(1, 0), RW, TriggerSource.HOST.value,
            "scope trigger: host strobe only, or also the external (reference step) trigger",
            enum=TriggerSource),
        reg("scope_arm", 0x0507, UQ(1, 0), STROBE, 0, "write 1: arm the scope"),
        reg("scope_force", 0x0508, UQ(1, 0), STROBE, 0, "write 1: trigger the scope now"),
        reg("scope_state", 0x0509, UQ(2, 0), RO, 0, "scope capture state", enum=ScopeState),
        reg("scope_status", 0x050A, UQ(len(SCOPE_STATUS_FIELDS), 0), RO, 0,
            "scope flags: a capture is complete; the pre-trigger part is full",
            fields=SCOPE_STATUS_FIELDS),
    ]
    windows = [Window("scope", 0x1000, 0x1000,
                      "scope trace buffer: channel c sample s at 0x1000 + c·1024 + s (read-only)")]
    regmap = RegMap(registers, windows)
    return regmap.with_constants({"id_map_hash": regmap.layout_hash})


#: The register map of the default build (50 MHz, 10 kHz PWM, the default :class:`Scales`).
REGMAP = build_regmap()
