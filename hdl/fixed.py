"""Fixed-point formats: the one place that defines them.

Gateware (``foc_servo.hdl``) and the bit-true golden models (``foc_servo.sim.models``) both import
this module, so changing a format here changes both.

Three kinds of thing live here:

* :class:`QFormat` — a two's-complement (or unsigned) fixed-point format ``Q(width, frac)``: a raw
  integer ``r`` of ``width`` bits stands for ``r · 2**-frac``. Conversions from and to float.
* :class:`BinaryAngle` — an unsigned angle of ``width`` bits, a full turn being ``2**width``. This is the
  *only* quantity in the design where wrap-around is correct (and wanted).
* :class:`Quantity` — a physical quantity (current, voltage, speed, ...) carried in a :class:`QFormat`,
  with its full-scale value and unit: the conversions at the user's edge, with clear errors.

And the arithmetic helpers, each in two flavours with identical semantics:

========================  ==========================  =================================================
gateware (Amaranth)       golden model (numpy)        meaning
========================  ==========================  =================================================
:func:`saturate`          :func:`saturate_np`         clamp to the range of a shape (never wrap)
:func:`clamp`             :func:`clamp_np`            clamp to run-time limits ``lo``, ``hi``
:func:`round_shift`       :func:`round_shift_np`      ``v / 2**shift``, rounded half away from zero
:func:`sat_add`           :func:`saturate_np`         saturating add
:func:`sat_sub`           :func:`saturate_np`         saturating subtract
:func:`mul_round`         :func:`mul_round_np`        product, rounded, saturated
========================  ==========================  =================================================

Rounding is *half away from zero* everywhere: it is odd-symmetric (``f(-v) == -f(v)``), so a
regulator fed a zero-mean error does not drift, and a rotation of a negated vector gives exactly the
negated result. It costs one carry-in (``half - sign``) over plain round-half-up.
"""

import math
import numbers

import numpy as np
from amaranth.hdl import Cat, Const, Mux, Shape, Value, signed, unsigned

__all__ = [
    "QFormat", "Q", "UQ", "BinaryAngle", "Quantity",
    "saturate", "clamp", "round_shift", "round_shift_plain", "sat_add", "sat_sub", "mul_round",
    "saturate_np", "clamp_np", "round_shift_np", "mul_round_np", "shape_range",
    "is_int", "check_param", "check_bool", "check_choice", "at_least",
]


def is_int(value):
    """An integer that is not a bool (the blocks' constructor parameters)."""
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def check_param(owner, name, value, lo, hi):
    """The blocks' constructor-parameter check: ``value`` an integer from ``lo`` to ``hi``, else
    ``TypeError("<owner> <name> must be an integer from <lo> to <hi>, not <value>")`` (the
    project's convention for structural parameters). Returns ``value``."""
    if not is_int(value) or not lo <= value <= hi:
        raise TypeError(f"{owner} {name} must be an integer from {lo} to {hi}, not {value!r}")
    return int(value)


def check_bool(owner, name, value):
    """The switch-parameter check: ``value`` a bool, else ``TypeError("<owner> <name> must be a
    bool, not <value>")``. Returns ``value``."""
    if not isinstance(value, bool):
        raise TypeError(f"{owner} {name} must be a bool, not {value!r}")
    return value


def check_choice(owner, name, value, choices):
    """The string-choice parameter check: ``value`` a string among ``choices``, else a
    ``TypeError`` (not a string) or ``ValueError`` (``"<owner> <name> must be one of 'a', 'b',
    not <value>"``). Returns ``value``."""
    allowed = ", ".join(map(repr, choices))
    if not isinstance(value, str):
        raise TypeError(f"{owner} {name} must be a string, one of {allowed}, not {value!r}")
    if value not in choices:
        raise ValueError(f"{owner} {name} must be one of {allowed}, not {value!r}")
    return value


def abs_exceeds(v, limit):
    """``|v| > limit`` for a signed ``v`` and an unsigned ``limit``, exactly (the most negative
    ``v`` included), on one carry chain and without forming ``|v|``.

    With ``s`` the sign of ``v`` and ``u = v XOR s`` its one's-complement magnitude (``|v|`` for
    ``v ≥ 0``, ``|v| − 1`` below; a LUT per bit, no adder), ``|v| = u + s``, so
    ``|v| ≤ limit ⟺ limit + ~u + ~s ≥ 2**n`` (``n`` bits wide): the carry out of one chain
    whose carry-in is ``~s``. The XOR LUT yields ``~u`` directly, so no inverter stands in front
    of the chain (iCE40: one logic cell per bit for the XOR, one for the carry; the two
    comparisons side by side that this replaces cost twice the chain and an inverter per bit)."""
    v = Value.cast(v)
    if not v.shape().signed:
        raise TypeError(f"abs_exceeds needs a signed value, not {v.shape()!r}")
    limit = Value.cast(limit)
    s = v[-1]
    n = max(len(v) - 1, len(limit))
    nu = ~(v[:-1] ^ s.replicate(len(v) - 1)).as_unsigned()
    nu = Cat(nu, Const((1 << (n - len(v) + 1)) - 1, n - len(v) + 1))    # ~u, n bits
    # The carry-in rides in a low bit of its own: ~s + 1 carries ~s into bit 1.
    total = Cat(~s, limit.as_unsigned(), Const(0, n - len(limit))) + Cat(Const(1, 1), nu)
    return ~total[n + 1]


def at_least(value, k):
    """``value ≥ k`` for an unsigned ``value`` and a constant integer ``k``, as plain logic.

    yosys maps every ``≥`` / ``<`` onto a carry chain (on the iCE40 a logic cell per bit that no
    LUT shares, and a feed-out cell for the result); against a constant the comparison is an
    AND/OR of the bits: from the LSB up, ``ge = v[i] & ge`` where ``k[i] = 1`` and
    ``v[i] | ge`` where it is 0 (``ge`` starting true) is ``v[:i+1] ≥ k[:i+1]``, a few LUT4s
    for a narrow ``value``. ``k ≤ 0`` is always true, ``k ≥ 2**len(value)`` never."""
    value = Value.cast(value)
    if value.shape().signed:
        raise TypeError(f"at_least needs an unsigned value, not {value.shape()!r}")
    if not is_int(k):
        raise TypeError(f"at_least needs an integer constant, not {k!r}")
    if k <= 0:
        return Const(1, 1)
    if k >= 1 << len(value):
        return Const(0, 1)
    ge = Const(1, 1)
    for i in range(len(value)):
        ge = (value[i] & ge) if (k >> i) & 1 else (value[i] | ge)
    return ge


def _check_int(name, value, minimum, maximum=None):
    if not isinstance(value, numbers.Integral) or isinstance(value, bool):
        raise TypeError(f"{name} must be an integer, not {value!r}")
    if value < minimum or (maximum is not None and value > maximum):
        upper = "" if maximum is None else f" and at most {maximum}"
        raise ValueError(f"{name} must be at least {minimum}{upper}, not {value!r}")
    return int(value)


def shape_range(shape):
    """Smallest and largest integer representable in ``shape`` (a :class:`Shape`-castable)."""
    shape = Shape.cast(shape)
    if shape.signed:
        return -(1 << (shape.width - 1)), (1 << (shape.width - 1)) - 1
    return 0, (1 << shape.width) - 1


class QFormat:
    """A fixed-point format: ``width`` raw bits, ``frac`` of them fractional.

    ``Q(16, 15)`` is the classic Q1.15 (range [-1, 1)); ``UQ(16, 8)`` an unsigned 8.8 format.

    Parameters
    ----------
    width : int
        Total number of bits, sign included, 1 … 64.
    frac : int
        Number of fractional bits; may exceed ``width`` (a small-valued format) or be negative.
    signed : bool
        Two's complement (default) or unsigned.
    """

    def __init__(self, width, frac, *, signed=True):
        self._width = _check_int("QFormat width", width, 1, 64)
        self._frac = _check_int("QFormat frac", frac, -64, 128)
        self._signed = bool(signed)

    width = property(lambda self: self._width)
    frac = property(lambda self: self._frac)
    signed = property(lambda self: self._signed)

    @property
    def shape(self):
        """The Amaranth shape of a raw value."""
        return signed(self._width) if self._signed else unsigned(self._width)

    @property
    def min_raw(self):
        return shape_range(self.shape)[0]

    @property
    def max_raw(self):
        return shape_range(self.shape)[1]

    @property
    def lsb(self):
        """Value of one raw step."""
        return 2.0 ** -self._frac

    @property
    def min(self):
        return self.min_raw * self.lsb

    @property
    def max(self):
        return self.max_raw * self.lsb

    def to_raw(self, value, *, saturate=False, name="value"):
        """Round a float (or array) to the nearest raw value, half away from zero.

        Out-of-range values raise :exc:`ValueError` naming ``name``, unless ``saturate`` is set.
        """
        v = np.asarray(value, dtype=np.float64)
        if not np.all(np.isfinite(v)):
            raise ValueError(f"{name} must be finite, not {value!r}")
        scaled = v * 2.0 ** self._frac
        raw = np.where(scaled >= 0, np.floor(scaled + 0.5), np.ceil(scaled - 0.5))
        if saturate:
            raw = np.clip(raw, self.min_raw, self.max_raw)
        elif np.any(raw < self.min_raw) or np.any(raw > self.max_raw):
            bad = float(v[(raw < self.min_raw) | (raw > self.max_raw)].flat[0])
            raise ValueError(f"{name} {bad!r} is outside the range [{self.min!r}, {self.max!r}] "
                             f"of {self!r}")
        raw = raw.astype(np.int64)
        return int(raw) if raw.ndim == 0 else raw

    def from_raw(self, raw):
        """Float value of a raw integer (or array)."""
        out = np.asarray(raw, dtype=np.float64) * self.lsb
        return float(out) if out.ndim == 0 else out

    def __eq__(self, other):
        return (isinstance(other, QFormat) and
                (self._width, self._frac, self._signed) ==
                (other._width, other._frac, other._signed))

    def __hash__(self):
        return hash((self._width, self._frac, self._signed))

    def __repr__(self):
        return f"{'Q' if self._signed else 'UQ'}({self._width}, {self._frac})"


def Q(width, frac):
    """Signed :class:`QFormat`."""
    return QFormat(width, frac, signed=True)


def UQ(width, frac):
    """Unsigned :class:`QFormat`."""
    return QFormat(width, frac, signed=False)


class BinaryAngle:
    """An angle as an unsigned ``width``-bit integer; a full turn is ``2**width``.

    Wrap-around is the point: adding angles modulo ``2**width`` is exact angle arithmetic. Read as a
    signed number the same bits are an angle in [-π, π).
    """

    def __init__(self, width):
        self._width = _check_int("BinaryAngle width", width, 2, 62)

    width = property(lambda self: self._width)

    @property
    def shape(self):
        return unsigned(self._width)

    @property
    def turn(self):
        """Raw value of one full turn (2π)."""
        return 1 << self._width

    @property
    def lsb_rad(self):
        return 2 * math.pi / self.turn

    def to_raw(self, theta_rad):
        """Nearest raw angle (ties away from zero), wrapped into [0, 2**width)."""
        v = np.asarray(theta_rad, dtype=np.float64)
        if not np.all(np.isfinite(v)):
            raise ValueError(f"angle must be finite, not {theta_rad!r}")
        scaled = v / self.lsb_rad
        raw = np.where(scaled >= 0, np.floor(scaled + 0.5), np.ceil(scaled - 0.5))
        raw = np.mod(raw, self.turn).astype(np.int64)
        return int(raw) if raw.ndim == 0 else raw

    def to_rad(self, raw, *, signed=True):
        """Angle in radians: in [-π, π) if ``signed`` (the bits read as two's complement), else
        [0, 2π)."""
        r = np.asarray(raw, dtype=np.int64) % self.turn
        if signed:
            r = np.where(r >= self.turn // 2, r - self.turn, r)
        out = r * self.lsb_rad
        return float(out) if out.ndim == 0 else out

    def __eq__(self, other):
        return isinstance(other, BinaryAngle) and self._width == other._width

    def __hash__(self):
        return hash(("angle", self._width))

    def __repr__(self):
        return f"BinaryAngle({self._width})"


class Quantity:
    """A physical quantity carried in a fixed-point format: the conversion at the user's edge.

    ``full_scale`` (in ``unit``) is the physical value of the format's value 1.0, so
    ``Quantity("i_q", Q(16, 15), 20.0, "A")`` maps ±20 A onto Q1.15.
    """

    def __init__(self, name, fmt, full_scale, unit):
        if not isinstance(fmt, QFormat):
            raise TypeError(f"Quantity format must be a QFormat, not {fmt!r}")
        if not isinstance(full_scale, numbers.Real) or not full_scale > 0:
            raise ValueError(f"Quantity full_scale must be a positive number, not {full_scale!r}")
        self.name, self.fmt, self.full_scale, self.unit = str(name), fmt, float(full_scale), unit

    @property
    def min(self):
        return self.fmt.min * self.full_scale

    @property
    def max(self):
        return self.fmt.max * self.full_scale

    def to_raw(self, value, *, saturate=False):
        """Raw value for a physical value; out of range raises a :exc:`ValueError` that names the
        quantity, the value, the range and the unit."""
        v = np.asarray(value, dtype=np.float64)
        if not saturate and (np.any(v < self.min) or np.any(v > self.max)):
            bad = float(v[(v < self.min) | (v > self.max)].flat[0])
            raise ValueError(f"{self.name} {bad:g} {self.unit} is outside the range "
                             f"[{self.min:g}, {self.max:g}] {self.unit}")
        return self.fmt.to_raw(v / self.full_scale, saturate=True, name=self.name)

    def from_raw(self, raw):
        return self.fmt.from_raw(raw) * self.full_scale

    def __repr__(self):
        return f"Quantity({self.name!r}, {self.fmt!r}, {self.full_scale:g}, {self.unit!r})"


# --- gateware helpers ---------------------------------------------------------------------------

def saturate(value, shape):
    """``value`` clamped to the range of ``shape`` and cast to it: never wraps.

    When ``value``'s own range already fits, this is only a cast (no logic). The range tests
    are bit tests, not compares: ``shape``'s bounds are ``hi = 2**k − 1`` and ``lo = −2**k``
    (or 0), so with ``m`` the bits of ``value`` below its sign, ``value > hi`` is "not negative
    and a bit of ``m`` at or above ``k`` set" and ``value < lo`` "negative and not all of those
    bits set" ("negative" for an unsigned ``shape``): an OR / AND in LUTs, where yosys maps a
    compare of a signed value with a constant onto a carry chain (iCE40: a logic cell per bit
    that no LUT shares; signed(33) to signed(16): 47 SB_CARRY and 35 LUT4 → 31 LUT4; xc7: 36 →
    26 LUT6, docs/AREA.md "Session 12"). The result is the same bit for bit.
    """
    value = Value.cast(value)
    shape = Shape.cast(shape)
    lo, hi = shape_range(shape)
    vlo, vhi = shape_range(value.shape())
    k = shape.width - shape.signed                      # hi = 2**k − 1, lo = −2**k or 0
    n = len(value) - value.shape().signed               # the bits below the sign: m
    negative = value[-1] if value.shape().signed else Const(0, 1)
    above = below = Const(0, 1)
    if vhi > hi:                                        # then n > k
        above = ~negative & value[k:n].any()
    if vlo < lo:                                        # value signed; n > k if shape signed
        below = negative & ~value[k:n].all() if shape.signed else negative
    value = Mux(above, hi, Mux(below, lo, value))[:shape.width]
    return value.as_signed() if shape.signed else value.as_unsigned()


def clamp(value, lo, hi):
    """``value`` clamped to the run-time limits: ``hi`` if ``value > hi``, else ``lo`` if
    ``value < lo``, else ``value``. With ``lo > hi`` the result is ``hi`` or ``lo``, as
    :func:`clamp_np` models. The result's shape is wide enough for all three operands."""
    value, lo, hi = Value.cast(value), Value.cast(lo), Value.cast(hi)
    return Mux(value > hi, hi, Mux(value < lo, lo, value))


def round_shift(value, shift):
    """``value / 2**shift`` rounded to the nearest integer, ties away from zero (exact, no
    saturation: the result is one bit wider than ``value >> shift``). ``shift <= 0`` shifts left."""
    value = Value.cast(value)
    shift = _check_int("shift", shift, -128, 128)
    if shift <= 0:
        return value << -shift
    if not value.shape().signed:
        return (value + (1 << (shift - 1))) >> shift
    # Add half, minus one for negative values, then floor: ties go away from zero.
    return (value + Const(1 << (shift - 1)) - value[-1]) >> shift


def round_shift_plain(value, shift):
    """:func:`round_shift` (ties away from zero, same value and width + 1) as one carry
    chain with ``value`` on its plain side: ``(2·value + ~sign + 2**shift − 1) >> (shift + 1)``
    ``= (value + 2**(shift−1) − sign) >> shift`` (the low bit carries ``~sign`` in). round_shift's
    ``− sign`` puts an inverter LUT in front of the chain on most bits when ``value`` is a
    flip-flop (iCE40: the speed register, 16 cells; docs/AREA.md §7.55). ``shift`` ≥ 1."""
    value = Value.cast(value)
    if not value.shape().signed or shift < 1:
        raise ValueError(f"round_shift_plain needs a signed value and shift >= 1, not "
                         f"{value.shape()!r} and {shift!r}")
    return (Cat(~value[-1], value).as_signed() + ((1 << shift) - 1)) >> (shift + 1)


def sat_add(a, b, shape):
    """``a + b`` saturated to ``shape``."""
    return saturate(Value.cast(a) + b, shape)


def sat_sub(a, b, shape):
    """``a - b`` saturated to ``shape``."""
    return saturate(Value.cast(a) - b, shape)


def mul_round(a, b, shift, shape):
    """``a * b / 2**shift``, rounded half away from zero, saturated to ``shape``."""
    return saturate(round_shift(Value.cast(a) * b, shift), shape)


# --- numpy golden-model helpers (int64, identical semantics) ----------------------------------

def _as_int(v):
    a = np.asarray(v)
    if a.dtype == object:
        return a
    return a.astype(np.int64)


def saturate_np(value, shape):
    """Model of :func:`saturate` (and of :func:`sat_add` / :func:`sat_sub` given ``a ± b``)."""
    lo, hi = shape_range(shape)
    out = np.clip(_as_int(value), lo, hi)
    return int(out) if np.ndim(out) == 0 else out


def clamp_np(value, lo, hi):
    """Model of :func:`clamp`."""
    v, lo, hi = _as_int(value), _as_int(lo), _as_int(hi)
    out = np.where(v > hi, hi, np.where(v < lo, lo, v))
    return int(out) if np.ndim(out) == 0 else out


def round_shift_np(value, shift):
    """Model of :func:`round_shift`."""
    v = _as_int(value)
    if shift <= 0:
        out = v << -shift
    else:
        out = (v + (1 << (shift - 1)) - (v < 0)) >> shift
    return int(out) if np.ndim(out) == 0 else out


def mul_round_np(a, b, shift, shape):
    """Model of :func:`mul_round`. Products must fit in int64 (|a·b| < 2**63)."""
    return saturate_np(round_shift_np(_as_int(a) * _as_int(b), shift), shape)
