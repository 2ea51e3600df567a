# Ref: SPEC.md §1 (T_e = 3/2·P·ψ_F·i_q), §3 (test motor: 1.5 kW, 5000 r/min); issue 6 item 1;
#      Yaskawa Σ-II Series SGM□H/SGDH User's Manual, §8.1.4 "SGMSH Servomotors", table "SGMSH
#      Standard Servomotor Ratings and Specifications" (200 V, model SGMSH-15A), p. 8-15
"""Motor parameter sets: :class:`MotorParams` (SI units) and the default catalogue motor.

The default motor, :data:`SGMSH_15A`, is the Yaskawa Σ-II **SGMSH-15A** surface-PM servomotor
(1.5 kW, 3000 r/min rated, 5000 r/min maximum: the class of the paper's test motor). Source:
Yaskawa *Σ-II Series SGM□H/SGDH User's Manual*, §8.1.4 "SGMSH Servomotors", table "SGMSH Standard
Servomotor Ratings and Specifications", 200 V, column 15A (page 8-15), values "at an armature
winding temperature of 20 °C" with an SGDH amplifier; read at
https://manualarchiveguide.com/manuals/YASKAWA-SGMAH-User-Manual-4781235?page=341 .

From the table (taken as is):

=============================  ===================  =========================================
rated output                   1.5 kW
rated torque                   4.9 N·m               ``t_rated_nm``
instantaneous peak torque      14.7 N·m              ``t_peak_nm``
rated current                  9.7 A rms             ``i_rated_arms``
instantaneous maximum current  28 A rms              ``i_peak_arms``
rated speed                    3000 r/min            ``n_rated_rpm``
maximum speed                  5000 r/min            ``n_max_rpm``
torque constant                0.561 N·m/A rms       → ``psi_wb`` (below)
moment of inertia              2.47·10⁻⁴ kg·m²       ``j_kgm2``
rated power rate               97.2 kW/s             (check: T_rated²/J)
rated angular acceleration     19 840 rad/s²         (check: T_rated/J)
inertia time constant          0.74 ms               → ``r_ohm`` (below)
inductive time constant        7.7 ms                → ``l_d_h``, ``l_q_h`` (below)
voltage class                  200 V                 ``u_rated_v`` (AC supply, line-to-line rms)
=============================  ===================  =========================================

Not in the table, derived (documented in docs/TUNING.md, "Motor"):

* ``pole_pairs = 4`` — **assumed** (8 poles; the table gives no pole count). It scales only the
  electrical frequency; ``psi_wb`` is derived with it so the torque constant is exact.
* ``psi_wb`` from the torque constant: with amplitude-invariant dq currents (``i_q`` = phase
  current amplitude = √2·I_rms), ``K_t,rms = √2 · 1.5 · P · ψ``, so
  ``ψ = 0.561 / (1.5·√2·4) = 0.06612 Wb``.
* ``r_ohm`` (per phase, star equivalent) from the inertia (mechanical) time constant of the dq model
  driven by a voltage, ``τ_m = J·R / (1.5·P²·ψ²) = 3·J·R / K_t,rms²``:
  ``R = τ_m · K_t,rms² / (3·J) = 0.3143 Ω``.
* ``l_d_h = l_q_h = τ_e · R = 2.420 mH`` from the inductive time constant (surface PM: L_d = L_q).
* ``b_nms = 0``: no viscous friction figure in the table.
* ``encoder_lines = 5000``: the paper's encoder (the catalogue motor ships with a serial encoder).
"""

import dataclasses
import json
import math
import numbers
from pathlib import Path

try:
    import tomllib                      # Python 3.11+
except ImportError:                     # pragma: no cover (Python 3.10)
    tomllib = None

__all__ = ["MotorParams", "SGMSH_15A", "DEFAULT_MOTOR", "psi_from_kt", "psi_from_ke"]

_SQRT2 = math.sqrt(2.0)


def psi_from_kt(kt_nm_per_arms, pole_pairs):
    """Magnet flux linkage ψ (Wb, amplitude) from a torque constant in N·m per A rms.

    ``T = 1.5·P·ψ·i_q`` with ``i_q = √2·I_rms`` (amplitude-invariant dq), so
    ``ψ = K_t,rms / (1.5·√2·P)``."""
    return kt_nm_per_arms / (1.5 * _SQRT2 * pole_pairs)


def psi_from_ke(ke_vrms_per_krpm, pole_pairs):
    """Magnet flux linkage ψ (Wb, amplitude) from a back-EMF constant in V rms line-to-line per
    1000 r/min.

    Phase EMF amplitude ``ω_e·ψ = √2/√3 · K_e · n/1000`` with ``ω_e = P·n·2π/60``."""
    e_ph_peak = ke_vrms_per_krpm * _SQRT2 / math.sqrt(3.0)          # at 1000 r/min
    return e_ph_peak / (pole_pairs * 1000.0 * 2.0 * math.pi / 60.0)


#: name → (unit, lower bound, lower inclusive, upper bound, kind). Upper bounds are inclusive.
_LIMITS = {
    "r_ohm":         ("Ω", 0.0, False, 100.0, float),
    "l_d_h":         ("H", 0.0, False, 1.0, float),
    "l_q_h":         ("H", 0.0, False, 1.0, float),
    "psi_wb":        ("Wb", 0.0, False, 10.0, float),
    "pole_pairs":    ("", 1, True, 64, int),
    "j_kgm2":        ("kg·m²", 0.0, False, 10.0, float),
    "b_nms":         ("N·m·s/rad", 0.0, True, 10.0, float),
    "i_rated_arms":  ("A rms", 0.0, False, 1000.0, float),
    "i_peak_arms":   ("A rms", 0.0, False, 3000.0, float),
    "t_rated_nm":    ("N·m", 0.0, False, 10000.0, float),
    "t_peak_nm":     ("N·m", 0.0, False, 30000.0, float),
    "n_rated_rpm":   ("r/min", 0.0, False, 100000.0, float),
    "n_max_rpm":     ("r/min", 0.0, False, 100000.0, float),
    "u_rated_v":     ("V", 0.0, False, 10000.0, float),
    "encoder_lines": ("lines", 1, True, 1 << 20, int),
}

#: Pairs (smaller, larger) that must be ordered.
_ORDER = (("i_rated_arms", "i_peak_arms"), ("t_rated_nm", "t_peak_nm"),
          ("n_rated_rpm", "n_max_rpm"))


def _fmt(value, unit):
    return f"{value!r} {unit}".rstrip()


@dataclasses.dataclass(frozen=True)
class MotorParams:
    """Parameters of a surface (or interior) PMSM and its rating, in SI units.

    Parameters
    ----------
    r_ohm : float
        Phase resistance (star equivalent: half the line-to-line value), Ω, (0, 100].
    l_d_h, l_q_h : float
        d- and q-axis inductance (star equivalent), H, (0, 1].
    psi_wb : float
        Magnet flux linkage, amplitude per phase (the ψ_F of ``T = 1.5·P·ψ_F·i_q``), Wb, (0, 10].
        :func:`psi_from_kt` and :func:`psi_from_ke` convert catalogue constants.
    pole_pairs : int
        Pole pairs P, 1 … 64.
    j_kgm2 : float
        Rotor moment of inertia, kg·m², (0, 10].
    b_nms : float
        Viscous friction coefficient, N·m·s/rad, [0, 10].
    i_rated_arms, i_peak_arms : float
        Rated (continuous) and instantaneous maximum phase current, A rms; peak ≥ rated.
    t_rated_nm, t_peak_nm : float
        Rated and instantaneous peak torque, N·m; peak ≥ rated.
    n_rated_rpm, n_max_rpm : float
        Rated and maximum speed, r/min; maximum ≥ rated.
    u_rated_v : float
        Rated supply voltage (AC, line-to-line rms; 200 for the 200 V class), V.
    encoder_lines : int
        Incremental encoder lines per revolution, 1 … 2²⁰.
    name, source : str
        Model name and where the values come from (datasheet, table).

    Raises
    ------
    ValueError
        For a value that is not a number (an integer for ``pole_pairs``/``encoder_lines``), not
        finite, or outside its range, naming the parameter, the value, the range and the unit;
        and when a peak value is below its rated value.
    """
    r_ohm: float
    l_d_h: float
    l_q_h: float
    psi_wb: float
    pole_pairs: int
    j_kgm2: float
    b_nms: float
    i_rated_arms: float
    i_peak_arms: float
    t_rated_nm: float
    t_peak_nm: float
    n_rated_rpm: float
    n_max_rpm: float
    u_rated_v: float
    encoder_lines: int
    name: str = ""
    source: str = ""

    def __post_init__(self):
        for field, (unit, lo, lo_incl, hi, kind) in _LIMITS.items():
            value = getattr(self, field)
            rng = f"{'[' if lo_incl else '('}{lo}, {hi}] {unit}".rstrip()
            if kind is int:
                ok_type = isinstance(value, numbers.Integral) and not isinstance(value, bool)
                what = "an integer"
            else:
                ok_type = isinstance(value, numbers.Real) and not isinstance(value, bool)
                what = "a number"
            if not ok_type:
                raise ValueError(f"MotorParams {field} must be {what} in {rng}, not {value!r}")
            if not math.isfinite(value) or value < lo or (value == lo and not lo_incl) \
                    or value > hi:
                raise ValueError(f"MotorParams {field} {_fmt(value, unit)} is outside the allowed "
                                 f"range {rng}")
            object.__setattr__(self, field, kind(value))
        for small, large in _ORDER:
            a, b = getattr(self, small), getattr(self, large)
            if b < a:
                unit = _LIMITS[small][0]
                raise ValueError(f"MotorParams {large} {_fmt(b, unit)} is below {small} "
                                 f"{_fmt(a, unit)}; it must be at least {small}")
        for field in ("name", "source"):
            if not isinstance(getattr(self, field), str):
                raise ValueError(f"MotorParams {field} must be a string, "
                                 f"not {getattr(self, field)!r}")

    # --- derived quantities ---------------------------------------------------------------

    @property
    def kt_nm_per_a(self):
        """Torque per ampere of ``i_q`` (amplitude-invariant dq, i.e. per A of phase amplitude):
        ``K_t = 1.5·P·ψ``, N·m/A."""
        return 1.5 * self.pole_pairs * self.psi_wb

    @property
    def kt_nm_per_arms(self):
        """Torque per A rms of phase current, ``√2·K_t``, N·m/A rms (the catalogue's
        constant)."""
        return _SQRT2 * self.kt_nm_per_a

    @property
    def ke_vrms_per_krpm(self):
        """Back-EMF constant, V rms line-to-line per 1000 r/min (inverse of
        :func:`psi_from_ke`)."""
        return (self.psi_wb * self.pole_pairs * 1000.0 * 2.0 * math.pi / 60.0
                * math.sqrt(3.0) / _SQRT2)

    @property
    def i_rated_a(self):
        """Rated current as a dq (phase amplitude) current, A."""
        return _SQRT2 * self.i_rated_arms

    @property
    def i_peak_a(self):
        """Instantaneous maximum current as a dq (phase amplitude) current, A."""
        return _SQRT2 * self.i_peak_arms

    @property
    def tau_e_s(self):
        """Electrical time constant ``L_q/R``, s."""
        return self.l_q_h / self.r_ohm

    @property
    def tau_m_s(self):
        """Mechanical time constant of the voltage-driven dq model, ``J·R/(1.5·P²·ψ²)``, s."""
        return self.j_kgm2 * self.r_ohm / (1.5 * self.pole_pairs ** 2 * self.psi_wb ** 2)

    @property
    def rated_power_w(self):
        """``t_rated_nm`` at ``n_rated_rpm``, W."""
        return self.t_rated_nm * self.n_rated_rpm * 2.0 * math.pi / 60.0

    def replace(self, **changes):
        """A copy with ``changes`` applied (validated)."""
        return dataclasses.replace(self, **changes)

    # --- files -----------------------------------------------------------------------------

    def to_dict(self):
        """The parameters as a plain dict (field name → value)."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data, *, what="motor parameters"):
        """Parameters from a mapping of field names.

        Instead of ``psi_wb`` the mapping may give ``kt_nm_per_arms`` (N·m/A rms) or
        ``ke_vrms_per_krpm`` (V rms line-to-line per 1000 r/min) — exactly one of the three —
        and instead of ``l_d_h`` and ``l_q_h`` a single ``l_h`` (surface PM). Unknown or missing
        keys raise :exc:`ValueError` naming them.
        """
        if not isinstance(data, dict):
            raise ValueError(f"{what} must be a table of parameters, not {type(data).__name__}")
        data = dict(data)
        flux = [k for k in ("psi_wb", "kt_nm_per_arms", "ke_vrms_per_krpm") if k in data]
        if len(flux) != 1:
            raise ValueError(f"{what} must give exactly one of psi_wb, kt_nm_per_arms, "
                             f"ke_vrms_per_krpm, not {flux or 'none'}")
        if "l_h" in data:
            if "l_d_h" in data or "l_q_h" in data:
                raise ValueError(f"{what} must give either l_h or l_d_h and l_q_h, not both")
            data["l_d_h"] = data["l_q_h"] = data.pop("l_h")
        if flux[0] != "psi_wb":
            pp = data.get("pole_pairs")
            if not isinstance(pp, numbers.Integral) or isinstance(pp, bool) or pp < 1:
                raise ValueError(f"{what}: pole_pairs must be an integer of at least 1 to "
                                 f"convert {flux[0]}, not {pp!r}")
            value = data.pop(flux[0])
            if not isinstance(value, numbers.Real) or isinstance(value, bool) or value <= 0:
                raise ValueError(f"{what}: {flux[0]} must be a positive number, not {value!r}")
            conv = psi_from_kt if flux[0] == "kt_nm_per_arms" else psi_from_ke
            data["psi_wb"] = conv(float(value), int(pp))
        names = [f.name for f in dataclasses.fields(cls)]
        unknown = sorted(set(data) - set(names))
        if unknown:
            raise ValueError(f"{what}: unknown parameter {unknown[0]!r}; known: "
                             f"{', '.join(names)}")
        required = [f.name for f in dataclasses.fields(cls)
                    if f.default is dataclasses.MISSING]
        missing = [n for n in required if n not in data]
        if missing:
            raise ValueError(f"{what}: missing parameter {missing[0]!r}")
        return cls(**data)

    @classmethod
    def from_file(cls, path):
        """Load a motor file: TOML (``.toml``) or JSON (``.json``), one flat table of the
        fields (see :meth:`from_dict`); in TOML the table may also be ``[motor]``."""
        path = Path(path)
        suffix = path.suffix.lower()
        if suffix not in (".toml", ".json"):
            raise ValueError(f"motor file {str(path)!r} must end in .toml or .json, "
                             f"not {suffix or 'no suffix'!r}")
        if suffix == ".toml" and tomllib is None:            # pragma: no cover (Python 3.10)
            raise ValueError(f"motor file {str(path)!r}: reading TOML needs Python 3.11 or "
                             f"later; use a .json motor file")
        try:
            text = path.read_bytes()
        except OSError as e:
            raise ValueError(f"motor file {str(path)!r} cannot be read: {e.strerror}") from None
        try:
            text = text.decode("utf-8")
            data = tomllib.loads(text) if suffix == ".toml" else json.loads(text)
        except ValueError as e:         # TOMLDecodeError, JSONDecodeError, UnicodeDecodeError
            raise ValueError(f"motor file {str(path)!r} is not valid {suffix[1:].upper()}: "
                             f"{e}") from None
        if isinstance(data, dict) and set(data) == {"motor"}:
            data = data["motor"]
        return cls.from_dict(data, what=f"motor file {str(path)!r}")

    def to_file(self, path):
        """Write the parameters to ``path`` as TOML (``.toml``) or JSON (``.json``), all fields,
        SI units; :meth:`from_file` reads it back to an equal object."""
        path = Path(path)
        suffix = path.suffix.lower()
        data = self.to_dict()
        if suffix == ".json":
            path.write_text(json.dumps(data, indent=2) + "\n", encoding="utf-8")
        elif suffix == ".toml":
            lines = ["# foc-servo motor parameters (SI units; see docs/TUNING.md)"]
            for key, value in data.items():
                if isinstance(value, str):
                    lines.append(f"{key} = {json.dumps(value, ensure_ascii=False)}")
                elif isinstance(value, int):
                    lines.append(f"{key} = {value}")
                else:
                    lines.append(f"{key} = {value!r}")
            path.write_text("\n".join(lines) + "\n", encoding="utf-8")
        else:
            raise ValueError(f"motor file {str(path)!r} must end in .toml or .json, "
                             f"not {suffix or 'no suffix'!r}")


# --- the default catalogue motor ----------------------------------------------------------------

_KT_NM_PER_ARMS = 0.561        # table: torque constant
_J_KGM2 = 2.47e-4              # table: moment of inertia
_TAU_M_S = 0.74e-3             # table: inertia time constant
_TAU_E_S = 7.7e-3              # table: inductive time constant
_POLE_PAIRS = 4                # assumed (not in the table)
_R_OHM = _TAU_M_S * _KT_NM_PER_ARMS ** 2 / (3.0 * _J_KGM2)        # derived: 0.3143 Ω
_L_H = _TAU_E_S * _R_OHM                                          # derived: 2.420 mH

#: Yaskawa Σ-II SGMSH-15A (module docstring: table, source, derivations).
SGMSH_15A = MotorParams(
    r_ohm=_R_OHM,
    l_d_h=_L_H,
    l_q_h=_L_H,
    psi_wb=psi_from_kt(_KT_NM_PER_ARMS, _POLE_PAIRS),
    pole_pairs=_POLE_PAIRS,
    j_kgm2=_J_KGM2,
    b_nms=0.0,
    i_rated_arms=9.7,
    i_peak_arms=28.0,
    t_rated_nm=4.9,
    t_peak_nm=14.7,
    n_rated_rpm=3000.0,
    n_max_rpm=5000.0,
    u_rated_v=200.0,
    encoder_lines=5000,
    name="Yaskawa SGMSH-15A",
    source="Yaskawa Sigma-II SGM*H/SGDH User's Manual, 8.1.4, SGMSH Standard Servomotor "
           "Ratings and Specifications, 200 V, 15A (p. 8-15); R, L, psi derived, P assumed",
)

#: The motor the simulations use unless told otherwise.
DEFAULT_MOTOR = SGMSH_15A
