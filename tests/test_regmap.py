# amaranth: UnusedElaboratable=no
# Ref: issue 5 item 1 (register map declared once; generated HDL, host map, docs, C header)
import argparse
import math

import pytest
from amaranth.hdl import Shape

from foc_servo.hdl import bus, hostlink, protect
from foc_servo.hdl.clarke import Clarke
from foc_servo.hdl.encoder import EncoderFrontEnd
from foc_servo.hdl.fixed import Q, UQ
from foc_servo.hdl.gates import Gates
from foc_servo.hdl.mt_speed import MTSpeed
from foc_servo.hdl.pi import PI
from foc_servo.hdl.protect import Protection
from foc_servo.hdl.regmap import (GROUPS, LINK_COUNTER_WIDTH, LINK_COUNTERS, MT_EDGES,
                                  MT_EDGES_PER_LINE, REGMAP, WORD_WIDTH, Access, Mode, RegMap,
                                  Register, Scales, Window, build_regmap, scale_factor)
from foc_servo.hdl.regs import RegisterFile
from foc_servo.hdl.svpwm import DCBusCompensation, PWMTimer
from foc_servo.host import codegen
from foc_servo.host.registers import REGISTERS, host_map
from foc_servo.sim.models.mt_speed import k_for
from foc_servo.sim.models.regs import RegisterFileModel

SCALES = Scales()


def width_of(port):
    return Shape.cast(port.shape()).width if hasattr(port, "shape") else len(port)


def reg(**kw):
    base = dict(name="x", addr=0x20, fmt=UQ(8, 0), access=Access.RW, reset=0, desc="d")
    base.update(kw)
    return Register(**base)


# --- the declaration against the blocks it configures ------------------------------------

@pytest.mark.filterwarnings("ignore::amaranth.hdl.UnusedElaboratable")  # blocks only inspected
def test_regmap_widths_match_the_block_ports():
    def w(sig):
        return len(sig.as_value() if hasattr(sig, "as_value") else sig)
    pi, clarke, dcbus = PI(), Clarke(), DCBusCompensation()
    enc, gates, pwm = EncoderFrontEnd(), Gates(), PWMTimer()
    mt, prot = MTSpeed(), Protection(speed_width=32)
    pairs = [
        *((f"pi_{a}_kp", pi.kp) for a in "dq"), *((f"pi_{a}_kx", pi.kx) for a in "dq"),
        *((f"pi_{a}_lim_lo", pi.lim_lo) for a in "dq"),
        *((f"pi_{a}_lim_hi", pi.lim_hi) for a in "dq"),
        ("clarke_gain_a", clarke.gain_a), ("clarke_offset_a", clarke.offset_a),
        ("clarke_gain_b", clarke.gain_b), ("clarke_offset_b", clarke.offset_b),
        ("u_rated", dcbus.u_rated), ("dead_time", gates.dead_time),
        ("pwm_sample_point", pwm.sample_point), ("pwm_symmetric", pwm.symmetric),
        ("pwm_sample_custom", pwm.sample_custom), ("mt_k", mt.k),
        ("enc_lines", enc.lines), ("enc_pole_pairs", enc.pole_pairs),
        ("enc_z_offset", enc.z_offset), ("enc_hall_offset", enc.hall_offset),
        ("enc_filter", enc.length), ("enc_realign", enc.realign),
        ("prot_oc_limit", prot.oc_limit), ("prot_ov_limit", prot.ov_limit),
        ("prot_uv_limit", prot.uv_limit), ("prot_uv_enable", prot.uv_enable),
        ("prot_os_limit", prot.os_limit), ("prot_mask", prot.mask),
        ("clear_faults", prot.clear), ("st_trip", prot.trip),
        ("st_fault_present", prot.present), ("st_fault_first", prot.first),
        ("st_fault_seen", prot.seen), ("st_theta", enc.theta), ("st_position", enc.count),
        ("st_enc_aligned", enc.aligned), ("st_speed", mt.o.payload.speed),
    ]
    for name, port in pairs:
        assert REGMAP[name].width == w(port), name
    assert REGMAP["pi_d_kp"].fmt == UQ(16, 8) and REGMAP["pi_d_kx"].fmt == UQ(16, 16)
    assert REGMAP["clarke_gain_a"].fmt == Q(18, 15)
    for name in ("pi_d_lim_lo", "pi_q_lim_hi", "prot_ov_limit", "prot_uv_limit",
                 "clarke_offset_a"):
        assert REGMAP[name].signed


@pytest.mark.filterwarnings("ignore::amaranth.hdl.UnusedElaboratable")  # blocks only inspected
def test_regmap_names_and_resets_match_the_blocks():
    assert REGMAP["prot_mask"].fields == protect.FAULTS
    assert WORD_WIDTH == bus.DATA_WIDTH
    assert LINK_COUNTERS == hostlink.COUNTERS
    for name in LINK_COUNTERS:
        assert REGMAP[f"st_link_{name}"].width == LINK_COUNTER_WIDTH
    assert REGMAP["theta_lead"].reset == 0                           # delay compensation off
    assert REGMAP["pi_speed_lim_hi"].reset == -REGMAP["pi_speed_lim_lo"].reset == 1 << 13
    assert REGMAP["enc_lines"].reset == EncoderFrontEnd().lines.init
    assert REGMAP["enc_pole_pairs"].reset == EncoderFrontEnd().pole_pairs.init
    prot = Protection(speed_width=32)
    for name, port in (("prot_oc_limit", prot.oc_limit), ("prot_ov_limit", prot.ov_limit),
                       ("prot_uv_limit", prot.uv_limit), ("prot_os_limit", prot.os_limit)):
        assert REGMAP[name].reset == port.init, name
    # The default build counts MT_EDGES (x4: 4 edges per line).
    assert MT_EDGES == "x4" and MT_EDGES_PER_LINE == {"a_rising": 1, "x4": 4}
    assert REGMAP["mt_k"].reset == k_for(lines=5000, tclk_hz=SCALES.clk_hz,
                                         full_scale_rpm=SCALES.n_fs_rpm, out_width=32,
                                         edge_mode=MT_EDGES)
    assert REGMAP["pi_d_lim_hi"].reset == round(math.sqrt(3) / 2 * 2**15)


def test_regmap_groups_addresses_sensibly():
    starts = {title: base for base, title in GROUPS}
    assert REGMAP["id_magic"].addr == 0x0000
    assert REGMAP["mode"].addr == starts["Control, mode and references"] == 0x0010
    assert REGMAP["pi_d_kp"].addr == 0x0100
    assert REGMAP["st_mode"].addr == 0x0400
    assert REGMAP.windows[0].addr == 0x1000
    for r in REGMAP:
        if r.access is Access.RO:
            assert REGMAP.group_of(r.addr) in ("Status", "Scope control"), r.name
        if r.access is Access.CONST:
            assert REGMAP.group_of(r.addr) == "Identification", r.name
    assert REGMAP["mt_k"].words == 2
    assert len({a for a, _, _ in REGMAP.words()}) == len(REGMAP.words())


def test_regmap_shadows_control_parameters_and_not_protection():
    for r in REGMAP:
        if r.access is not Access.RW:
            assert r.shadow is None
        elif r.name.startswith(("prot_", "scope_")):
            assert r.shadow is None, r.name
        else:
            assert r.shadow is not None, r.name
    assert REGMAP["pi_q_kp"].shadow == REGMAP["pi_q_kx"].shadow == "pi_q"


def test_regmap_constants_follow_the_scales():
    s = Scales(clk_hz=33_333_333, pwm_hz=9997.999, n_fs_rpm=6000)
    m = build_regmap(s)
    assert m["id_clk_hz"].reset == 33_333_333 and m["id_pwm_mhz"].reset == 9_997_999
    assert m["dead_time"].reset == 33
    assert m["id_map_hash"].reset == REGMAP["id_map_hash"].reset      # layout unchanged
    assert Scales.from_id_raw({n: m[n].reset for n in s.id_raw()}) == s


# --- validation messages ---------------------------------------------------------------

def test_register_validation_messages():
    with pytest.raises(TypeError, match=r"^Register name must be a lower-case identifier, "
                                        r"not 'Bad'$"):
        reg(name="Bad")
    with pytest.raises(TypeError, match=r"^Register x address must be an integer from 0 to "
                                        r"65535, not 70000$"):
        reg(addr=70000)
    with pytest.raises(TypeError, match=r"^Register x format must be a QFormat, not 8$"):
        reg(fmt=8)
    with pytest.raises(ValueError, match=r"^Register x reset value must be an integer from 0 to "
                                         r"255, not 256$"):
        reg(reset=256)
    with pytest.raises(ValueError, match=r"^Register x is ro: only rw registers are shadowed, "
                                         r"not shadow='g'$"):
        reg(access=Access.RO, shadow="g")
    with pytest.raises(ValueError, match=r"^Register x is a strobe: its format must be "
                                         r"UQ\(1, 0\), not UQ\(8, 0\)$"):
        reg(access=Access.STROBE)
    with pytest.raises(ValueError, match=r"^Register x is read-only and 48 bits wide: status "
                                         r"registers are at most 32 bits \(no torn reads\)$"):
        reg(access=Access.RO, fmt=UQ(48, 0))
    with pytest.raises(ValueError, match=r"^Register x format must be UQ\(2, 0\) for its enum, "
                                         r"not UQ\(8, 0\)$"):
        reg(enum=Mode)
    with pytest.raises(ValueError, match=r"^Register x format must be UQ\(2, 0\) for its 2 "
                                         r"fields, not UQ\(8, 0\)$"):
        reg(fields=("a", "b"))
    with pytest.raises(ValueError, match=r"^Register scale 'I_FS\*volts' names 'volts', not one "
                                         r"of I_FS, U_FS, N_FS, clk_hz, pwm_hz$"):
        reg(scale="I_FS*volts")
    with pytest.raises(ValueError, match=r"^Register x at 0xffff spans 2 words beyond the 16-bit "
                                         r"address space$"):
        reg(addr=0xFFFF, fmt=UQ(40, 0))


def test_regmap_validation_messages():
    with pytest.raises(ValueError, match=r"^RegMap name 'x' is used twice or reserved$"):
        RegMap([reg(), reg(addr=0x30)])
    with pytest.raises(ValueError, match=r"^RegMap name 'commit' is used twice or reserved$"):
        RegMap([reg(name="commit")])
    with pytest.raises(ValueError, match=r"^RegMap register y word 0 at 0x0021 overlaps x$"):
        RegMap([reg(fmt=UQ(40, 0)), reg(name="y", addr=0x21)])
    with pytest.raises(ValueError, match=r"^RegMap window w overlaps register x at 0x0020$"):
        RegMap([reg()], [Window("w", 0x20, 16, "d")])
    with pytest.raises(TypeError, match=r"^Window w size must be a power of two from 1 to "
                                        r"32768, not 12$"):
        Window("w", 0x1000, 12, "d")
    with pytest.raises(ValueError, match=r"^Window w address must be a multiple of its size 16 "
                                         r"below 65536, not 8$"):
        Window("w", 8, 16, "d")
    with pytest.raises(TypeError, match=r"^Scales clk_hz must be a positive finite number, "
                                        r"not 0$"):
        Scales(clk_hz=0)
    with pytest.raises(KeyError, match=r"no register named 'nope'"):
        REGMAP.replace("nope", addr=1)


def test_scale_expressions():
    assert scale_factor("I_FS", SCALES) == 40.0
    assert scale_factor("1/clk_hz", SCALES) == 2e-8
    assert scale_factor("I_FS/32768", SCALES) == 40.0 / 32768
    assert scale_factor("360", SCALES) == 360.0


# --- host map ---------------------------------------------------------------------------

def test_host_map_converts_units_both_ways():
    r = REGISTERS["i_q_ref"]
    assert r.addr == REGMAP["i_q_ref"].addr and r.words == 1
    assert r.to_raw(2.5, SCALES) == round(2.5 / 40 * 2**15)
    assert r.from_raw(-16384, SCALES) == -20.0
    assert REGISTERS["speed_ref"].to_raw(1667, SCALES) == round(1667 / 12000 * 2**31)
    assert REGISTERS["dead_time"].to_raw(2e-6, SCALES) == 100
    assert REGISTERS["dead_time"].from_raw(50, SCALES) == pytest.approx(1e-6)
    assert REGISTERS["ol_freq"].to_raw(-50.0, SCALES) == round(-50 / 10e3 * 2**32)
    assert REGISTERS["mode"].to_raw("speed") == Mode.SPEED.value
    assert REGISTERS["mode"].to_raw(Mode.CURRENT) == 2
    assert REGISTERS["mode"].from_raw(1) is Mode.OPEN_LOOP
    assert REGISTERS["prot_mask"].to_raw(["external", "hall"]) == 0b10_0000_0001
    assert REGISTERS["prot_mask"].from_raw(0b10)["overcurrent_a"] is True
    assert REGISTERS["decouple_enable"].to_raw(True) == 1
    k = REGISTERS["mt_k"]
    assert k.from_words(k.to_words(0x123456789ABC)) == 0x123456789ABC
    ref = REGISTERS["speed_ref"]
    assert ref.to_words(-1) == [0xFFFFFFFF] and ref.from_words([0x80000000]) == -(1 << 31)
    lo = REGISTERS["pi_speed_lim_lo"]
    assert lo.to_words(-2) == [0xFFFFFFFE] and lo.from_words([0x12348000]) == -(1 << 15)


def test_host_map_errors_name_register_value_range_and_unit():
    with pytest.raises(ValueError, match=r"^i_q_ref 45 A is outside the range \[-40, 39\.9988\] "
                                         r"A$"):
        REGISTERS["i_q_ref"].to_raw(45, SCALES)
    with pytest.raises(ValueError, match=r"^speed_ref -13000 r/min is outside the range "
                                         r"\[-12000, 12000\] r/min$"):
        REGISTERS["speed_ref"].to_raw(-13000, SCALES)
    with pytest.raises(ValueError, match=r"^dead_time 1e-05 s is outside the range \[0, "
                                         r"5\.1e-06\] s$"):
        REGISTERS["dead_time"].to_raw(10e-6, SCALES)
    with pytest.raises(ValueError, match=r"^mode 'fast' is not one of disabled, open_loop, "
                                         r"current, speed$"):
        REGISTERS["mode"].to_raw("fast")
    with pytest.raises(ValueError, match=r"^prot_mask has no flag 'smoke'; flags: external, "):
        REGISTERS["prot_mask"].to_raw(["smoke"])
    with pytest.raises(ValueError, match=r"^st_i_d raw value 40000 is outside the range "
                                         r"\[-32768, 32767\] of Q\(16, 15\)$"):
        REGISTERS["st_i_d"].from_raw(40000, SCALES)


def test_scales_come_from_the_identification_registers():
    raw = {n: REGMAP[n].reset for n in SCALES.id_raw()}
    assert Scales.from_id_raw(raw) == SCALES


# --- generated files --------------------------------------------------------------------

def test_committed_docs_and_header_are_up_to_date():
    stale = codegen.stale()
    assert stale == [], f"{stale} stale: run `foc-servo regs`"


def test_regs_check_fails_when_stale_and_passes_after_regenerating(tmp_path, capsys):
    parser = argparse.ArgumentParser()
    codegen.add_arguments(parser)
    assert codegen.cmd_regs(parser.parse_args(["--check", "--root", str(tmp_path)])) == 1
    assert codegen.cmd_regs(parser.parse_args(["--root", str(tmp_path)])) == 0
    assert codegen.cmd_regs(parser.parse_args(["--check", "--root", str(tmp_path)])) == 0
    doc = tmp_path / codegen.DOC_PATH
    doc.write_text(doc.read_text().replace("| `0x0100` |", "| `0x0101` |"))
    assert codegen.cmd_regs(parser.parse_args(["--check", "--root", str(tmp_path)])) == 1
    assert "docs/REGISTERS.md is stale" in capsys.readouterr().err


def test_changing_one_register_changes_hdl_host_map_markdown_and_header_together():
    old = REGMAP["pi_q_kx"]
    changed = REGMAP.replace("pi_q_kx", addr=0x0108, fmt=UQ(18, 18))
    new = changed["pi_q_kx"]
    assert changed["id_map_hash"].reset != REGMAP["id_map_hash"].reset
    # HDL: the RegisterFile port width and the decoded address follow.
    rf_old, rf_new = RegisterFile(REGMAP), RegisterFile(changed)
    assert rf_old.signature.members["pi_q_kx"].shape.width == 16
    assert rf_new.signature.members["pi_q_kx"].shape.width == 18
    model = RegisterFileModel(changed)
    assert model.step(stb=1, addr=0x0108, we=1, w_data=0x3FFFF) == 0
    assert model.staged["pi_q_kx"] == 0x3FFFF
    assert model.step(stb=1, addr=old.addr, we=0, w_data=0) is None     # ack clock
    assert RegisterFileModel(changed).step(stb=1, addr=old.addr, we=0, w_data=0) == 1
    # Host map.
    hm = host_map(changed)
    assert hm["pi_q_kx"].addr == 0x0108 and hm["pi_q_kx"].width == 18
    assert REGISTERS["pi_q_kx"].addr == old.addr
    # Markdown and C header.
    md_old, md_new = codegen.markdown(REGMAP), codegen.markdown(changed)
    h_old, h_new = codegen.c_header(REGMAP), codegen.c_header(changed)
    assert "| `0x0105` | `pi_q_kx` | rw | 16 |" in md_old
    assert "| `0x0108` | `pi_q_kx` | rw | 18 |" in md_new and "`0x0105` | `pi_q_kx`" not in md_new
    assert "#define FOC_PI_Q_KX_ADDR 0x0105u" in h_old
    assert "#define FOC_PI_Q_KX_ADDR 0x0108u" in h_new
    assert "#define FOC_PI_Q_KX_WIDTH 18u" in h_new
    assert new.addr == 0x0108


def test_c_header_has_include_guard_and_every_register():
    h = codegen.c_header()
    assert h.startswith("/*") and "#ifndef FOC_SERVO_REGS_H\n#define FOC_SERVO_REGS_H" in h
    assert h.rstrip().endswith("#endif /* FOC_SERVO_REGS_H */")
    for r in REGMAP:
        assert f"#define FOC_{r.name.upper()}_ADDR 0x{r.addr:04X}u" in h
    assert "#define FOC_MT_K_RESET 0x640000000ULL" in h          # x4: 4 edges per line
    assert "#define FOC_PI_D_LIM_LO_RESET (-28378)" in h
    assert "#define FOC_MODE_SPEED 3" in h
    assert "#define FOC_SCOPE_WINDOW_ADDR 0x1000u" in h


@pytest.mark.filterwarnings("ignore::amaranth.hdl.UnusedElaboratable")  # blocks only inspected
def test_regmap_matches_the_controller_blocks():
    foc = pytest.importorskip("foc_servo.hdl.foc")
    servo = pytest.importorskip("foc_servo.hdl.servo")
    scope = pytest.importorskip("foc_servo.hdl.scope")

    def w(sig):
        return len(sig.as_value() if hasattr(sig, "as_value") else sig)
    loop, srv, scp = foc.CurrentLoop(), servo.Servo(), scope.Scope()
    pairs = [
        ("pi_d_kp", loop.kp_d), ("pi_d_kx", loop.kx_d), ("pi_q_kp", loop.kp_q),
        ("pi_q_kx", loop.kx_q), ("clarke_gain_a", loop.gain_a), ("clarke_offset_b", loop.offset_b),
        ("u_rated", loop.u_rated), ("decouple_enable", loop.ff_enable),
        ("decouple_l", loop.ff_l), ("decouple_psi", loop.ff_psi),
        ("mode", srv.mode), ("ol_angle_mode", srv.ol_src), ("ol_angle", srv.ol_theta),
        ("ol_freq", srv.ol_freq), ("ol_u_d", srv.ud_set), ("ol_u_q", srv.uq_set),
        ("i_d_ref", srv.id_set), ("i_q_ref", srv.iq_set), ("speed_ref", srv.speed_ref),
        ("pi_speed_kp", srv.speed_kp), ("pi_speed_kx", srv.speed_kx),
        ("theta_lead", loop.theta_lead),
        ("pi_speed_lim_lo", srv.iq_lim_lo), ("pi_speed_lim_hi", srv.iq_lim_hi),
        ("speed_div", srv.speed_rate_div),
        ("scope_decim", scp.decim), ("scope_trig_src", scp.trig_src),
        ("scope_state", scp.state),
    ]
    for name, port in pairs:
        assert REGMAP[name].width == w(port), name
    assert foc.FF_FORMAT == REGMAP["decouple_l"].fmt
    # The blocks' enums are the register map's (one definition, hdl/regmap.py).
    assert servo.Mode is Mode is REGMAP["mode"].enum
    assert servo.AngleMode is REGMAP["ol_angle_mode"].enum
    assert scope.TriggerSource is REGMAP["scope_trig_src"].enum
    assert scope.ScopeState is REGMAP["scope_state"].enum
    assert scp.addr_width == REGMAP.windows[0].addr_width


def test_every_shadow_group_is_one_contiguous_burst():
    """The host writes a shadow group in one frame (applied together); a hole or a read-only
    word inside a group's address span would split it."""
    from foc_servo.hdl.regmap import REGMAP
    spans = {}
    for reg in REGMAP:
        if getattr(reg, "shadow", None):
            lo, hi = spans.get(reg.shadow, (reg.addr, reg.addr))
            spans[reg.shadow] = (min(lo, reg.addr), max(hi, reg.addr + reg.words - 1))
    writable = {reg.addr + k for reg in REGMAP if reg.access.value in ("rw", "strobe")
                for k in range(reg.words)}
    for group, (lo, hi) in spans.items():
        holes = [hex(a) for a in range(lo, hi + 1) if a not in writable]
        assert not holes, f"shadow group {group!r} has unwritable words {holes}"
