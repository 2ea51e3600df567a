"""The host library (Servo) and the `foc-servo host` commands against the simulated gateware
(register level: link gateware + register file + scope, pyserial on a pty)."""

import json

import numpy as np
import pytest

from foc_servo.hdl.regmap import MAP_VERSION, Mode
from foc_servo.hdl.scope import DEFAULT_SOURCES
from foc_servo.host import host_cli
from foc_servo.host.registers import REGISTERS
from foc_servo.host.servo import SCOPE_SOURCES, MapMismatch, Servo, ServoError
from foc_servo.sim.motor import SGMSH_15A


@pytest.fixture(scope="module")
def servo():
    with Servo.sim() as s:
        yield s


def raw_of(servo, name):
    reg = REGISTERS[name]
    return reg.from_words(servo.client.read(reg.addr, reg.words))


def test_connect_reads_scales_from_id_registers(servo):
    assert servo.scales.clk_hz == 50e6 and servo.scales.i_fs_a == 40.0
    assert servo.scales.n_fs_rpm == 12000.0 and servo.max_words == 64


def test_round_trip_in_units_q_formats_enums_flags_and_48_bit(servo):
    servo.set_many({"i_q_ref": 2.5, "speed_ref": -1234.5, "pi_d_lim_lo": -0.5, "ol_angle": 90.0,
                    "mode": "speed", "ol_angle_mode": Mode.OPEN_LOOP.value,
                    "prot_mask": ["external", "hall"], "decouple_enable": True,
                    "mt_k": (1 << 48) - 5, "u_rated": 300.0})
    v = servo.get_many(["i_q_ref", "speed_ref", "pi_d_lim_lo", "ol_angle", "mode",
                        "ol_angle_mode", "prot_mask", "decouple_enable", "mt_k", "u_rated"])
    assert v["i_q_ref"] == 2.5 and raw_of(servo, "i_q_ref") == 2048
    assert v["speed_ref"] == pytest.approx(-1234.5, abs=12000 / 2**31)
    assert v["pi_d_lim_lo"] == -0.5 and raw_of(servo, "pi_d_lim_lo") == -16384
    assert v["ol_angle"] == 90.0 and raw_of(servo, "ol_angle") == 16384
    assert v["mode"] is Mode.SPEED and v["ol_angle_mode"].name == "ROTATING"
    assert [f for f, on in v["prot_mask"].items() if on] == ["external", "hall"]
    assert v["decouple_enable"] is True
    assert v["mt_k"] == (1 << 48) - 5 and raw_of(servo, "mt_k") == (1 << 48) - 5
    assert v["u_rated"] == pytest.approx(300.0, abs=0.0125 / 2)
    assert servo.get("st_mode") is Mode.SPEED       # the sim's commit applied the shadow


def test_random_rw_registers_round_trip(servo):
    rng = np.random.default_rng(5)
    names = [n for n in Servo.parameters() if n not in ("mode",)]
    for _ in range(3):
        raws = {n: int(rng.integers(REGISTERS[n].fmt.min_raw, REGISTERS[n].fmt.max_raw + 1))
                for n in names}
        raws = {n: r for n, r in raws.items()
                if REGISTERS[n].kind != "enum" or r in {m.value for m in REGISTERS[n].enum}}
        values = {n: REGISTERS[n].from_raw(r, servo.scales) for n, r in raws.items()}
        servo.set_many(values)
        back = servo._read_raw(list(raws))
        assert back == raws


def test_out_of_range_rejected_without_any_write(servo):
    before = servo.sim.bus_writes
    old = servo.get("pi_d_kp")
    with pytest.raises(ServoError, match=r"^i_q_ref 45 A is outside the range \[-40, 39\.99"):
        servo.set_many({"pi_d_kp": old + 1.0, "i_q_ref": 45.0})
    with pytest.raises(ServoError, match=r"^mode 'fast' is not one of disabled, open_loop"):
        servo.set("mode", "fast")
    with pytest.raises(ServoError, match=r"^prot_mask has no flag 'nope'"):
        servo.set("prot_mask", ["nope"])
    with pytest.raises(ServoError, match=r"^st_speed is ro: it cannot be written"):
        servo.set("st_speed", 1.0)
    with pytest.raises(ServoError, match=r"^no register named 'i_q_rf'; did you mean i_q_ref"):
        servo.set("i_q_rf", 1.0)
    servo.get("mode")
    assert servo.sim.bus_writes == before and servo.get("pi_d_kp") == old


def test_burst_group_write_is_one_frame(servo):
    servo.set_many({"pi_d_kp": 1.0, "pi_d_kx": 0.25, "pi_d_lim_lo": -0.75, "pi_d_lim_hi": 0.75})
    frames = servo.set_many({"pi_q_kp": 2.0, "pi_q_kx": 0.5, "pi_q_lim_lo": -0.5,
                             "pi_q_lim_hi": 0.5})
    assert frames == [(REGISTERS["pi_q_kp"].addr, 4)]
    # a partial group: the registers between are filled with their read-back values
    frames = servo.set_many({"pi_d_kp": 3.0, "pi_d_lim_hi": 0.5})
    assert frames == [(REGISTERS["pi_d_kp"].addr, 4)]
    assert servo.get_many(["pi_d_kp", "pi_d_kx", "pi_d_lim_lo", "pi_d_lim_hi"]) == {
        "pi_d_kp": 3.0, "pi_d_kx": 0.25, "pi_d_lim_lo": -0.75, "pi_d_lim_hi": 0.5}
    # the setpoint group spans the clear_faults strobe: filled with 0, no pulse
    frames = servo.set_many({"mode": "current", "i_q_ref": 1.0})
    assert frames == [(REGISTERS["mode"].addr, 5)]


def test_dump_contains_every_readable_register(servo):
    d = servo.dump()
    assert set(d) == {n for n, r in REGISTERS.items() if r.access != "strobe"}
    assert d["id_magic"] == 0x464F4353 and d["id_n_fs_rpm"] == 12000


@pytest.mark.parametrize("suffix", [".json", ".toml"])
def test_save_modify_load_restores(servo, tmp_path, suffix):
    servo.set_many({"i_d_ref": -1.5, "mode": "open_loop", "prot_mask": ["overvoltage"],
                    "mt_k": 987654321, "dead_time": 2e-6})
    path = tmp_path / f"params{suffix}"
    saved = servo.save(path)
    assert set(saved) == set(Servo.parameters())
    before = servo.dump()
    servo.set_many({"i_d_ref": 3.0, "mode": "speed", "prot_mask": 0x3FF, "mt_k": 5,
                    "dead_time": 1e-7, "pi_speed_kp": 7.0})
    servo.load(path)
    assert servo.dump() == before


def test_load_checks_everything_before_writing(servo, tmp_path):
    path = tmp_path / "bad.json"
    doc = {"format": "foc-servo-parameters/1",
           "registers": {"i_d_ref": 1.0, "i_q_ref": 99.0, "pi_dkp": 1.0}}
    path.write_text(json.dumps(doc))
    before = servo.sim.bus_writes
    with pytest.raises(ServoError, match=r"nothing written: i_q_ref 99 A is outside the range"
                                         r".*no register named 'pi_dkp'; did you mean pi_d_kp"):
        servo.load(path)
    servo.get("mode")
    assert servo.sim.bus_writes == before


def test_map_hash_mismatch_detected(monkeypatch):
    monkeypatch.setattr(REGISTERS["id_map_hash"], "reset", 0x12345678)
    with pytest.raises(MapMismatch, match=r"^register map mismatch: the drive's id_map_hash is "
                                          r"0x[0-9A-F]{8} \(map version "
                                          rf"{MAP_VERSION >> 16}\.{MAP_VERSION & 0xFFFF}\), "
                                          r"this library's "
                                          r"is 0x12345678"):
        Servo.sim()


def test_faults_decoded_and_clear(servo):
    assert servo.clear_faults() == {"trip": False, "present": [], "first": [], "seen": []}


def test_scope_sources_match_gateware():
    assert list(SCOPE_SOURCES) == list(DEFAULT_SOURCES)
    for name, shape in DEFAULT_SOURCES.items():
        assert SCOPE_SOURCES[name][0] == shape.signed


def test_scope_capture_step_trigger_arm_and_read(servo):
    servo.set_many({"i_q_ref": 2.5, "speed_ref": 0.0})
    cap = servo.scope_capture(["i_q_ref"], pretrigger=20, trigger="step",
                              step={"i_q_ref": -5.0}, timeout_s=60)
    i = cap["i_q_ref"]
    assert len(i) == 1024 and cap["t_s"][20] == 0.0
    assert np.all(i[:20] == 2.5) and np.all(i[20:] == -5.0)
    assert servo.get("scope_status") == {"done": True, "pre_full": False}
    with pytest.raises(ServoError, match=r"^no scope source named 'iq'; did you mean i_q"):
        servo.scope_capture(["iq"])


def test_scope_step_trigger_on_an_unchanged_write(servo):
    # The drive's reference step is a host write to a reference (hdl.top, "Scope trigger"),
    # not a change of its value: the simulated drive triggers on an unchanged write too.
    servo.set_many({"i_q_ref": 2.5, "speed_ref": 0.0})
    cap = servo.scope_capture(["i_q_ref"], pretrigger=20, trigger="step",
                              step={"i_q_ref": 2.5}, timeout_s=60)
    assert np.all(cap["i_q_ref"] == 2.5)
    assert servo.get("scope_status") == {"done": True, "pre_full": False}


def test_tune_dry_run_writes_nothing_then_writes(servo):
    servo.set_many({"pi_d_kp": 0.0, "pi_speed_kx": 0.0, "u_rated": 310.0})
    t = servo.tune(SGMSH_15A, dry_run=True)
    assert servo.get_many(["pi_d_kp", "pi_speed_kx"]) == {"pi_d_kp": 0.0, "pi_speed_kx": 0.0}
    servo.tune(SGMSH_15A)
    assert raw_of(servo, "pi_d_kp") == t.registers["pi_d_kp"]
    assert raw_of(servo, "pi_speed_kx") == t.registers["pi_speed_kx"]


def last_json(capsys):
    out = capsys.readouterr().out
    return out, json.loads(out.strip().splitlines()[-1])


def test_cli_get_set_json(capsys):
    host_cli.main(["host", "--port", "sim", "--sim-level", "registers", "set", "i_q_ref=2.5", "mode=current",
                   "prot_mask=external|hall", "--json"])
    out, fig = last_json(capsys)
    assert "i_q_ref = 2.5 A" in out
    assert fig["written"]["mode"] == "current" and fig["written"]["i_q_ref"] == 2.5
    host_cli.main(["host", "--port", "sim", "--sim-level", "registers", "get", "id_magic", "mode", "--json"])
    out, fig = last_json(capsys)
    assert fig == {"id_magic": 0x464F4353, "mode": "disabled"}


def test_cli_unknown_register_suggests_names():
    with pytest.raises(SystemExit, match=r"^foc-servo host get: no register named 'pi_d_kpp'; "
                                         r"did you mean pi_d_kp"):
        host_cli.main(["host", "--port", "sim", "--sim-level", "registers", "get", "pi_d_kpp"])
    with pytest.raises(SystemExit, match=r"^foc-servo host set: i_q_ref 100 A is outside"):
        host_cli.main(["host", "--port", "sim", "--sim-level", "registers", "set", "i_q_ref=100"])


def test_cli_dump_save_load_watch_clear_faults(capsys, tmp_path):
    base = ["host", "--port", "sim", "--sim-level", "registers"]
    host_cli.main(base + ["dump", "--json"])
    _, fig = last_json(capsys)
    assert fig["id_clk_hz"] == 50_000_000 and fig["scope_trig_src"] == "host"
    path = str(tmp_path / "p.toml")
    host_cli.main(base + ["save", path, "--json"])
    _, fig = last_json(capsys)
    assert fig["registers"] == len(Servo.parameters())
    host_cli.main(base + ["load", path, "--json"])
    _, fig = last_json(capsys)
    assert fig == {"file": path, "registers": len(Servo.parameters())}
    host_cli.main(base + ["watch", "st_mode", "i_q_ref", "--interval", "0.01", "--count", "3",
                          "--json"])
    _, fig = last_json(capsys)
    assert fig["st_mode"] == ["disabled"] * 3 and len(fig["t_s"]) == 3
    host_cli.main(base + ["clear-faults", "--json"])
    _, fig = last_json(capsys)
    assert fig == {"trip": False, "present": [], "first": [], "seen": []}


def test_cli_tune_dry_run_prints_values(capsys, tmp_path):
    motor = tmp_path / "motor.toml"
    SGMSH_15A.to_file(motor)
    host_cli.main(["host", "--port", "sim", "--sim-level", "registers", "tune", "--motor", str(motor), "--dry-run",
                   "--json"])
    out, fig = last_json(capsys)
    assert "dry run: nothing written" in out and fig["written"] is False
    assert set(fig["raw"]) == {"pi_d_kp", "pi_d_kx", "pi_q_kp", "pi_q_kx", "pi_speed_kp",
                               "pi_speed_kx"}
    assert all(v > 0 for v in fig["raw"].values())
    assert f"pi_d_kp      = {fig['registers']['pi_d_kp']:.9g} pu" in out


def test_cli_scope_writes_csv_and_png(capsys, tmp_path):
    csv, png = tmp_path / "s.csv", tmp_path / "s.png"
    host_cli.main(["host", "--port", "sim", "--sim-level", "registers", "scope", "--channels", "i_q_ref", "--pretrigger",
                   "5", "--png", str(png), "--csv", str(csv), "--json"])
    _, fig = last_json(capsys)
    assert fig["samples"] == 1024 and fig["channels"]["i_q_ref"]["unit"] == "A"
    rows = csv.read_text().splitlines()
    assert rows[0] == "t_s,i_q_ref_A" and len(rows) == 1025
    assert png.read_bytes()[:4] == b"\x89PNG"


def test_cli_port_sim_is_the_whole_drive(capsys):
    """--port sim (default level): the whole controller gateware with the motor plant: the
    DC-bus voltage reads the plant's 310 V through the ADC, and a written register reads back."""
    host_cli.main(["host", "--port", "sim", "set", "speed_ref=100"])
    capsys.readouterr()
    host_cli.main(["host", "--port", "sim", "get", "st_udc", "id_magic", "--json"])
    values = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert abs(values["st_udc"] - 310.0) < 0.5
