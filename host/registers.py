# Ref: issue 5 item 1 (host map with unit conversion); hdl/regmap.py (the declaration)
"""The host's view of the register map: name → address, words, format and unit conversion.

Built from :mod:`foc_servo.hdl.regmap` (declarations and fixed-point formats only; no gateware).
Values in physical units convert to raw register values with the :class:`Scales` the drive
reports in its identification registers::

    scales = Scales.from_id_raw({n: read(n) for n in ID_SCALE_REGISTERS})
    raw = REGISTERS["i_q_ref"].to_raw(2.5, scales)          # 2.5 A
    words = REGISTERS["i_q_ref"].to_words(raw)               # bus words, low first
"""

import numbers

from ..hdl.fixed import Quantity
from ..hdl.regmap import REGMAP, Access, RegMap, Scales, scale_factor

__all__ = ["Scales", "HostRegister", "host_map", "REGISTERS", "BY_ADDRESS", "WINDOWS",
           "ID_SCALE_REGISTERS"]

#: Identification registers from which :meth:`Scales.from_id_raw` builds the scales.
ID_SCALE_REGISTERS = ("id_clk_hz", "id_pwm_mhz", "id_i_fs_ma", "id_u_fs_uv", "id_n_fs_rpm")


class HostRegister:
    """One register as the host sees it.

    Attributes
    ----------
    name, addr, words, width, access, reset, unit, desc, shadow, enum, fields
        From the declaration (``access`` is the string ``"rw"``, ``"ro"``, ``"const"`` or
        ``"strobe"``).
    kind : str
        ``"number"``, ``"enum"``, ``"flags"`` or ``"bool"``.
    writable : bool
    """

    def __init__(self, register):
        self._reg = register
        self.name = register.name
        self.addr = register.addr
        self.words = register.words
        self.width = register.width
        self.fmt = register.fmt
        self.access = register.access.value
        self.reset = register.reset
        self.unit = register.unit
        self.scale = register.scale
        self.desc = register.desc
        self.shadow = register.shadow
        self.enum = register.enum
        self.fields = register.fields
        self.kind = register.kind
        self.writable = register.access in (Access.RW, Access.STROBE)

    def quantity(self, scales):
        """The :class:`~foc_servo.hdl.fixed.Quantity` of a ``"number"`` register under
        ``scales``."""
        return Quantity(self.name, self.fmt, scale_factor(self.scale, scales), self.unit)

    def to_raw(self, value, scales=None):
        """Raw register value for ``value`` in the register's unit (``"number"``), an enum
        member or name (``"enum"``), a mapping or iterable of flag names or an int (``"flags"``),
        a bool (``"bool"``).

        Raises
        ------
        ValueError
            Naming the register, the value, the allowed range and the unit, when out of range or
            not a valid name.
        """
        if self.kind == "enum":
            if isinstance(value, self.enum):
                return value.value
            if isinstance(value, str):
                key = value.strip().upper().replace("-", "_")
                if key in self.enum.__members__:
                    return self.enum[key].value
            elif isinstance(value, numbers.Integral) and not isinstance(value, bool):
                if value in {m.value for m in self.enum}:
                    return int(value)
            names = ", ".join(m.name.lower() for m in self.enum)
            raise ValueError(f"{self.name} {value!r} is not one of {names}")
        if self.kind == "flags":
            if isinstance(value, numbers.Integral) and not isinstance(value, bool):
                if not 0 <= value <= self.fmt.max_raw:
                    raise ValueError(f"{self.name} {value!r} is outside the range "
                                     f"[0, {self.fmt.max_raw}]")
                return int(value)
            items = ([k for k, v in value.items() if v] if hasattr(value, "items")
                     else list(value))
            bad = [k for k in items if k not in self.fields]
            if bad:
                raise ValueError(f"{self.name} has no flag {bad[0]!r}; flags: "
                                 f"{', '.join(self.fields)}")
            return sum(1 << self.fields.index(k) for k in set(items))
        if self.kind == "bool":
            if value in (0, 1, False, True):
                return int(bool(value))
            raise ValueError(f"{self.name} {value!r} is not 0 or 1")
        if scales is None:
            raise TypeError(f"{self.name}: converting a value in {self.unit or 'units'} needs "
                            f"the Scales")
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            raise ValueError(f"{self.name} must be a number of {self.unit}, not {value!r}")
        return int(self.quantity(scales).to_raw(value))

    def from_raw(self, raw, scales=None):
        """Value in the register's unit (float), enum member, dict of flags or bool, from a raw
        register value.

        Raises
        ------
        ValueError
            ``raw`` is outside the format's raw range.
        """
        if (isinstance(raw, bool) or not isinstance(raw, numbers.Integral)
                or not self.fmt.min_raw <= raw <= self.fmt.max_raw):
            raise ValueError(f"{self.name} raw value {raw!r} is outside the range "
                             f"[{self.fmt.min_raw}, {self.fmt.max_raw}] of {self.fmt!r}")
        if self.kind == "enum":
            try:
                return self.enum(raw)
            except ValueError:
                return int(raw)
        if self.kind == "flags":
            return {f: bool(raw >> i & 1) for i, f in enumerate(self.fields)}
        if self.kind == "bool":
            return bool(raw)
        if scales is None:
            raise TypeError(f"{self.name}: converting to {self.unit or 'units'} needs the Scales")
        return float(self.quantity(scales).from_raw(raw))

    def to_words(self, raw):
        """Bus words (low first) of a raw value."""
        return self._reg.to_words(raw)

    def from_words(self, words):
        """Raw value from bus words (low first)."""
        return self._reg.from_words(list(words))

    def __repr__(self):
        return f"HostRegister({self.name!r}, {self.addr:#06x}, {self.fmt!r}, {self.access})"


def host_map(regmap=REGMAP):
    """``{name: HostRegister}`` in address order of a register map."""
    if not isinstance(regmap, RegMap):
        raise TypeError(f"host_map regmap must be a RegMap, not {regmap!r}")
    return {r.name: HostRegister(r) for r in sorted(regmap, key=lambda r: r.addr)}


#: The default map.
REGISTERS = host_map(REGMAP)
#: Word address of the (low) word → register.
BY_ADDRESS = {r.addr: r for r in REGISTERS.values()}
#: Address windows (the scope trace buffer): name → :class:`~foc_servo.hdl.regmap.Window`.
WINDOWS = {w.name: w for w in REGMAP.windows}
