# Ref: sim/motor.py (Yaskawa SGMSH-15A table, derivations); issue 6 item 1
"""MotorParams: the catalogue motor against its datasheet, validation, motor files."""

import json
import math

import pytest

from foc_servo.sim.motor import (DEFAULT_MOTOR, SGMSH_15A, MotorParams, psi_from_ke,
                                 psi_from_kt)

# The datasheet table (SGMSH-15A, 200 V), independent of the values typed in sim/motor.py.
SHEET = dict(p_w=1500.0, t_rated=4.9, t_peak=14.7, i_rated=9.7, i_peak=28.0, n_rated=3000.0,
             n_max=5000.0, kt=0.561, j=2.47e-4, power_rate=97.2e3, accel=19840.0,
             tau_m=0.74e-3, tau_e=7.7e-3)


def test_default_motor_is_the_catalogue_1500w_5000rpm_servo():
    m = DEFAULT_MOTOR
    assert m is SGMSH_15A
    assert m.n_max_rpm == SHEET["n_max"] and m.n_rated_rpm == SHEET["n_rated"]
    assert m.t_rated_nm == SHEET["t_rated"] and m.t_peak_nm == SHEET["t_peak"]
    assert m.i_rated_arms == SHEET["i_rated"] and m.i_peak_arms == SHEET["i_peak"]
    assert m.j_kgm2 == SHEET["j"]
    assert m.l_d_h == m.l_q_h                     # surface PM
    assert "SGMSH-15A" in m.name and "8.1.4" in m.source


def test_catalogue_motor_derived_constants_match_datasheet():
    m = SGMSH_15A
    # Torque constant: derived ψ reproduces the catalogue K_t exactly (it is derived from it).
    assert m.kt_nm_per_arms == pytest.approx(SHEET["kt"], rel=1e-12)
    assert m.kt_nm_per_a == pytest.approx(SHEET["kt"] / math.sqrt(2), rel=1e-12)
    # Derived R and L reproduce the table's time constants.
    assert m.tau_m_s == pytest.approx(SHEET["tau_m"], rel=1e-12)
    assert m.tau_e_s == pytest.approx(SHEET["tau_e"], rel=1e-12)
    # Rated and peak torque from K_t and current: within 12 % (K_t is a 20 °C, small-current
    # figure; the rated and peak torques include saturation).
    assert m.kt_nm_per_arms * m.i_rated_arms == pytest.approx(SHEET["t_rated"], rel=0.12)
    assert m.kt_nm_per_arms * m.i_peak_arms == pytest.approx(SHEET["t_peak"], rel=0.12)
    # Table-internal checks: power rate T²/J, angular acceleration T/J, rated power T·ω.
    assert m.t_rated_nm ** 2 / m.j_kgm2 == pytest.approx(SHEET["power_rate"], rel=0.005)
    assert m.t_rated_nm / m.j_kgm2 == pytest.approx(SHEET["accel"], rel=0.005)
    assert m.rated_power_w == pytest.approx(SHEET["p_w"], rel=0.03)
    # Plausible magnitudes of the derived values.
    assert 0.2 < m.r_ohm < 0.5 and 1.5e-3 < m.l_q_h < 3.5e-3


def test_flux_from_kt_and_ke_round_trip():
    m = SGMSH_15A
    assert psi_from_kt(m.kt_nm_per_arms, m.pole_pairs) == pytest.approx(m.psi_wb, rel=1e-12)
    assert psi_from_ke(m.ke_vrms_per_krpm, m.pole_pairs) == pytest.approx(m.psi_wb, rel=1e-12)
    # Independent: K_e (V rms line-to-line per rad/s) = K_t (N·m/A rms) / √3 for a sine machine.
    ke_per_rad_s = m.ke_vrms_per_krpm / (1000 * 2 * math.pi / 60)
    assert ke_per_rad_s == pytest.approx(m.kt_nm_per_arms / math.sqrt(3), rel=1e-12)


@pytest.mark.parametrize("field, value, message", [
    ("r_ohm", -1.0, r"MotorParams r_ohm -1\.0 Ω is outside the allowed range \(0\.0, 100\.0\] Ω"),
    ("r_ohm", 0.0, r"MotorParams r_ohm 0\.0 Ω is outside the allowed range \(0\.0, 100\.0\] Ω"),
    ("l_q_h", 2.0, r"MotorParams l_q_h 2\.0 H is outside the allowed range \(0\.0, 1\.0\] H"),
    ("l_d_h", math.nan, r"MotorParams l_d_h nan H is outside the allowed range \(0\.0, 1\.0\] H"),
    ("psi_wb", math.inf, r"MotorParams psi_wb inf Wb is outside the allowed range "
                         r"\(0\.0, 10\.0\] Wb"),
    ("j_kgm2", 0.0, r"MotorParams j_kgm2 0\.0 kg·m² is outside the allowed range "
                    r"\(0\.0, 10\.0\] kg·m²"),
    ("b_nms", -0.1, r"MotorParams b_nms -0\.1 N·m·s/rad is outside the allowed range "
                    r"\[0\.0, 10\.0\] N·m·s/rad"),
    ("n_max_rpm", 2e5, r"MotorParams n_max_rpm 200000\.0 r/min is outside the allowed range "
                       r"\(0\.0, 100000\.0\] r/min"),
    ("u_rated_v", "200", r"MotorParams u_rated_v must be a number in \(0\.0, 10000\.0\] V, "
                         r"not '200'"),
    ("i_rated_arms", True, r"MotorParams i_rated_arms must be a number in "
                           r"\(0\.0, 1000\.0\] A rms, not True"),
    ("pole_pairs", 2.5, r"MotorParams pole_pairs must be an integer in \[1, 64\], not 2\.5"),
    ("pole_pairs", 0, r"MotorParams pole_pairs 0 is outside the allowed range \[1, 64\]"),
    ("encoder_lines", 0, r"MotorParams encoder_lines 0 lines is outside the allowed range "
                         r"\[1, 1048576\] lines"),
    ("name", 3, r"MotorParams name must be a string, not 3"),
])
def test_motor_params_validation_messages(field, value, message):
    with pytest.raises(ValueError, match=rf"^{message}$"):
        SGMSH_15A.replace(**{field: value})


@pytest.mark.parametrize("small, large, unit", [
    ("i_rated_arms", "i_peak_arms", "A rms"), ("t_rated_nm", "t_peak_nm", "N·m"),
    ("n_rated_rpm", "n_max_rpm", "r/min")])
def test_motor_params_peak_below_rated_rejected(small, large, unit):
    value = getattr(SGMSH_15A, small) / 2
    with pytest.raises(ValueError, match=rf"^MotorParams {large} {value!r} {unit} is below "
                                         rf"{small} .* it must be at least {small}$"):
        SGMSH_15A.replace(**{large: value})


def test_motor_params_integer_fields_stay_integers():
    m = SGMSH_15A.replace(r_ohm=1, pole_pairs=3)
    assert isinstance(m.r_ohm, float) and isinstance(m.pole_pairs, int)


@pytest.mark.parametrize("suffix", [".toml", ".json"])
def test_motor_file_round_trip(tmp_path, suffix):
    path = tmp_path / f"motor{suffix}"
    SGMSH_15A.to_file(path)
    assert MotorParams.from_file(path) == SGMSH_15A


def test_motor_file_toml_with_catalogue_constants(tmp_path):
    d = SGMSH_15A.to_dict()
    del d["psi_wb"], d["l_d_h"], d["l_q_h"], d["name"], d["source"]
    lines = ["[motor]", "kt_nm_per_arms = 0.561", f"l_h = {SGMSH_15A.l_q_h!r}"]
    lines += [f"{k} = {v!r}" for k, v in d.items()]
    path = tmp_path / "m.toml"
    path.write_text("\n".join(lines) + "\n")
    m = MotorParams.from_file(path)
    assert m.psi_wb == pytest.approx(SGMSH_15A.psi_wb, rel=1e-12)
    assert m.l_d_h == m.l_q_h == SGMSH_15A.l_q_h


def test_motor_file_ke_instead_of_psi(tmp_path):
    d = SGMSH_15A.to_dict()
    d["ke_vrms_per_krpm"] = SGMSH_15A.ke_vrms_per_krpm
    del d["psi_wb"]
    path = tmp_path / "m.json"
    path.write_text(json.dumps(d))
    assert MotorParams.from_file(path).psi_wb == pytest.approx(SGMSH_15A.psi_wb, rel=1e-12)


@pytest.mark.parametrize("edit, message", [
    (lambda d: d.update(foo=1), r"motor file '.*' *: unknown parameter 'foo'; known: r_ohm, .*"),
    (lambda d: d.pop("j_kgm2"), r"motor file '.*': missing parameter 'j_kgm2'"),
    (lambda d: d.update(kt_nm_per_arms=0.5),
     r"motor file '.*' must give exactly one of psi_wb, kt_nm_per_arms, ke_vrms_per_krpm, "
     r"not \['psi_wb', 'kt_nm_per_arms'\]"),
    (lambda d: d.update(l_h=1e-3), r"motor file '.*' must give either l_h or l_d_h and l_q_h, "
                                   r"not both"),
    (lambda d: d.update(r_ohm=-2.0), r"MotorParams r_ohm -2\.0 Ω is outside the allowed range "
                                     r"\(0\.0, 100\.0\] Ω"),
])
def test_motor_file_bad_content_rejected(tmp_path, edit, message):
    d = SGMSH_15A.to_dict()
    edit(d)
    path = tmp_path / "m.json"
    path.write_text(json.dumps(d))
    with pytest.raises(ValueError, match=rf"^{message}$"):
        MotorParams.from_file(path)


def test_motor_file_bad_suffix_syntax_and_missing(tmp_path):
    with pytest.raises(ValueError, match=r"^motor file '.*m\.yaml' must end in \.toml or \.json, "
                                         r"not '\.yaml'$"):
        (tmp_path / "m.yaml").write_text("r_ohm: 1")
        MotorParams.from_file(tmp_path / "m.yaml")
    with pytest.raises(ValueError, match=r"^motor file '.*m\.yaml' must end in \.toml or \.json"):
        SGMSH_15A.to_file(tmp_path / "m.yaml")
    (tmp_path / "bad.toml").write_text("r_ohm = = 1\n")
    with pytest.raises(ValueError, match=r"^motor file '.*bad\.toml' is not valid TOML: "):
        MotorParams.from_file(tmp_path / "bad.toml")
    with pytest.raises(ValueError, match=r"^motor file '.*none\.json' cannot be read: "):
        MotorParams.from_file(tmp_path / "none.json")
    (tmp_path / "list.json").write_text("[1, 2]")
    with pytest.raises(ValueError, match=r"^motor file '.*list\.json' must be a table of "
                                         r"parameters, not list$"):
        MotorParams.from_file(tmp_path / "list.json")
