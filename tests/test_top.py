# Ref: issue 5 item 6 (the top); docs/REGISTERS.md; docs/PROTOCOL.md
"""The whole controller on its pins: elaboration, Verilog, reset state, host link to the blocks,
fault path latency, one current-loop pass from the ADC model.

The simulations run at 100 kHz PWM (500 clocks per period at 50 MHz) and a UART at clk_hz / 8
(80 clocks per byte) to keep pysim cheap (~1.5 k clocks/s for the whole top)."""

import dataclasses
import itertools
import math
import re

import numpy as np
import pytest
from amaranth.back import verilog
from amaranth.hdl import Module, Signal, signed
from amaranth.lib import wiring
from amaranth.lib.wiring import In

from foc_servo.hdl.fixed import UQ, round_shift_np, saturate_np
from foc_servo.hdl.gates import dead_n_const
from foc_servo.hdl.regmap import LOOP_FLAG_FIELDS, Access, Mode, Scales
from foc_servo.hdl.top import LeadAngle, Top, _raw, regmap_address_map
from foc_servo.hdl.uart import UartRx, UartTx
from foc_servo.host.protocol import (Command, ReplyStatus, cobs_decode, cobs_encode, crc16,
                                     decode_reply, encode_request, frame)
from foc_servo.sim.adc_part import AdcPartModel
from foc_servo.sim.harness import simulate
from foc_servo.sim.models.clarke import clarke
from mt_pins import record_top_mt

CLK = 50e6
BAUD = CLK / 8
PWM = 100e3
HALL_OK = 0b101          # a valid Hall code (sector 0): 000 would trip the Hall fault


class _Bench(wiring.Component):
    """Top + a host-side UART pair on its uart pins; ``inject`` low pulls ``uart_rx`` low (a
    testbench bit-bangs frames through it, damaged ones included, while the host UART idles)."""

    def __init__(self, top, baud):
        self.top = top
        self.host_tx = UartTx(clk_hz=top.clk_hz, baud=baud)
        self.host_rx = UartRx(clk_hz=top.clk_hz, baud=baud)
        super().__init__({"inject": In(1, init=1)})

    def elaborate(self, platform):
        m = Module()
        m.submodules.top = top = self.top
        m.submodules.host_tx = tx = self.host_tx
        m.submodules.host_rx = rx = self.host_rx
        m.d.comb += [top.uart_rx.eq(tx.tx & self.inject), rx.rx.eq(top.uart_tx),
                     rx.o.ready.eq(1)]
        return m


class _Host:
    """Request / reply through the bench's host UART inside a testbench."""

    def __init__(self, bench):
        self.bench = bench
        self.seq = 0
        self.clocks = 0

    async def tick(self, ctx, n=1):
        await ctx.tick().repeat(n)
        self.clocks += n

    async def transact(self, ctx, cmd, addr, data=(), count=None, timeout=20_000):
        tx, rx = self.bench.host_tx.i, self.bench.host_rx.o
        self.seq = (self.seq + 1) & 0xFF
        for byte in frame(encode_request(cmd, self.seq, addr, count, data)):
            ctx.set(tx.payload, byte)
            ctx.set(tx.valid, 1)
            while True:
                ready = ctx.get(tx.ready)
                await self.tick(ctx)
                if ready:
                    break
        ctx.set(tx.valid, 0)
        got = bytearray()
        for _ in range(timeout):
            if ctx.get(rx.valid):
                byte = ctx.get(rx.payload)
                if byte == 0 and got:
                    break
                if byte:
                    got.append(byte)
            await self.tick(ctx)
        else:
            raise AssertionError(f"no reply within {timeout} clocks")
        raw = cobs_decode(bytes(got))
        assert crc16(raw) == 0, "reply CRC"
        reply = decode_reply(raw[:-2])
        assert reply.seq == self.seq
        return reply

    async def write(self, ctx, addr, *words):
        reply = await self.transact(ctx, Command.WRITE, addr, data=words)
        assert reply.status == ReplyStatus.OK, reply
        return reply

    async def read(self, ctx, addr, n=1):
        reply = await self.transact(ctx, Command.READ, addr, count=n)
        assert reply.status == ReplyStatus.OK, reply
        return reply.data

    async def next_period(self, ctx, top):
        """Tick until just after the next ``period_start`` (the register commit)."""
        while not ctx.get(top._timer.period_start):
            await self.tick(ctx)
        await self.tick(ctx)


def _addr(top, name):
    return top.regmap[name].addr


def _signed(word, bits=32):
    return word - (1 << bits) if word >> (bits - 1) else word


# --- construction -----------------------------------------------------------------------------

@pytest.mark.parametrize("kwargs, exc, msg", [
    ({"clk_hz": "50e6"}, TypeError, r"^Top clk_hz must be a positive number in Hz, not '50e6'$"),
    ({"pwm_hz": 0}, TypeError, r"^Top pwm_hz must be a positive number in Hz, not 0$"),
    ({"baud": True}, TypeError, r"^Top baud must be a positive number in Hz, not True$"),
    ({"clk_hz": 600e6}, ValueError, r"^Top clk_hz must be from 1 MHz to 500 MHz, "
                                    r"not 600000000\.0$"),
    ({"pwm_hz": 500}, ValueError, r"^Top pwm_hz must give a PWM period of 8 to 65534 clocks at "
                                  r"clk_hz 5e\+07 Hz, not 500 \(100000 clocks\)$"),
    ({"pwm_hz": 10e6}, ValueError, r"^Top pwm_hz must give a PWM period of 8 to 65534 clocks "
                                   r"at clk_hz 5e\+07 Hz, not 10000000\.0 \(4 clocks\)$"),
    ({"baud": 10e6}, ValueError, r"^Top baud must be at most clk_hz / 8 = 6\.25e\+06, "
                                 r"not 10000000\.0$"),
    ({"scales": 1}, TypeError, r"^Top scales must be a Scales or None, not 1$"),
    ({"scales": Scales(clk_hz=33e6)}, ValueError,
     r"^Top scales\.clk_hz must equal clk_hz 5e\+07, not 33000000\.0$"),
    ({"scales": Scales(pwm_hz=20e3)}, ValueError,
     r"^Top scales\.pwm_hz must equal pwm_hz 10000 or the actual 10000, not 20000\.0$"),
    ({"dead_time_s": "1us"}, TypeError,
     r"^Top dead_time_s must be a number of seconds or None, not '1us'$"),
    ({"dead_time_s": 10e-6}, ValueError,
     r"^Top dead_time_s must be 1 to 255 clocks at 5e\+07 Hz, not 1e-05 \(500 clocks\)$"),
    ({"max_words": 0}, TypeError, r"^Top max_words must be an integer from 1 to 255, not 0$"),
    ({"mt_edges": 4}, TypeError, r"^Top mt_edges must be a string, one of .*, not 4$"),
    ({"mt_edges": "x2"}, ValueError, r"^Top mt_edges must be one of 'a_rising', 'x4', "
                                     r"not 'x2'$"),
    ({"current_loop": 2}, TypeError, r"^Top current_loop must be a string, one of .*, not 2$"),
    ({"current_loop": "cordic"}, ValueError, r"^Top current_loop must be one of 'pipelined', "
                                             r"'engine', not 'cordic'$"),
    ({"resets": [1]}, TypeError, r"^Top resets must be a mapping of register names to raw "
                                 r"values or None, not \[1\]$"),
    ({"resets": {"st_mode": 1}}, ValueError, r"^Top resets may only set rw registers, "
                                             r"not 'st_mode'$"),
    ({"resets": {"theta_lead": 1 << 16}}, ValueError,
     r"^Register theta_lead reset value must be an integer from 0 to 65535, not 65536$"),
    ({"dead_time_s": 1e-6, "resets": {"dead_time": 5}}, ValueError,
     r"^Top dead_time_s and resets\['dead_time'\] both set the dead time: give one$"),
    ({"regs_staging": 1}, TypeError, r"^Top regs_staging must be a string, one of .*, not 1$"),
    ({"regs_staging": "spram"}, ValueError, r"^Top regs_staging must be one of 'ff', 'bram', "
                                            r"not 'spram'$"),
    ({"speed_loop": 1}, TypeError, r"^Top speed_loop must be a string, one of .*, not 1$"),
    ({"speed_loop": "pi"}, ValueError, r"^Top speed_loop must be one of 'sequential', "
                                       r"'engine', not 'pi'$"),
    ({"speed_loop": "engine"}, ValueError,
     r"^Top speed_loop='engine' needs current_loop='engine' and regs_staging='bram' \(the "
     r"speed run shares the engine and its configuration RAM\), not current_loop='pipelined', "
     r"regs_staging='ff'$"),
    ({"speed_loop": "engine", "current_loop": "engine", "regs_staging": "bram",
      "pwm_hz": 100e3}, ValueError,
     r"^Top speed_loop='engine' needs half a PWM period longer than M/T's latency \+ the "
     r"speed run \(\d+ clocks\), not 250 clocks \(pwm_hz 100000.0 at clk_hz 5e\+07\)$"),
    ({"current_loop": "engine", "pwm_hz": 294e3}, ValueError,
     r"^Top current_loop='engine' needs a PWM period longer than the ADC's latency \+ the "
     r"engine's sample hold \(179 clocks\), not 170 clocks$"),
    ({"ram_loop_count": 1}, TypeError, r"^Top ram_loop_count must be a bool, not 1$"),
    ({"regs_staging": "bram", "pwm_hz": 1.25e6}, ValueError,
     r"^Top regs_staging='bram' needs a PWM period longer than the register copy \(49 clocks\), "
     r"not 40 clocks$"),
    ({"prot_limits": "flops"}, ValueError,
     r"^Top prot_limits must be one of 'ports', 'ram', 'ram16', not 'flops'$"),
    ({"prot_limits": "ram"}, ValueError,
     r"^Top prot_limits='ram' needs regs_staging='bram' \(the limits are mirrored from its "
     r"staging RAM\), not regs_staging='ff'$"),
])
def test_top_parameter_validation(kwargs, exc, msg):
    with pytest.raises(exc, match=msg):
        Top(**kwargs)


def test_top_scales_and_identification_constants_at_33_333_mhz():
    top = Top(clk_hz=33.333e6, dead_time_s=0.5e-6)
    assert top.pwm_period == 3334
    assert top.scales.clk_hz == 33.333e6
    assert top.scales.pwm_hz == pytest.approx(33.333e6 / 3334)
    assert top.regmap["id_clk_hz"].reset == 33_333_000
    assert top.regmap["id_pwm_mhz"].reset == round(33.333e6 / 3334 * 1e3)
    assert top.regmap["dead_time"].reset == 17
    assert top.fault_latency == 4
    # Scales given with the requested PWM frequency are moved to the actual one.
    top = Top(clk_hz=33.333e6, scales=Scales(clk_hz=33.333e6, i_fs_a=5.0))
    assert top.scales.i_fs_a == 5.0 and top.scales.pwm_hz == pytest.approx(33.333e6 / 3334)


@pytest.mark.filterwarnings("ignore::amaranth.hdl.UnusedElaboratable")  # blocks only inspected
def test_top_blocks_take_their_formats_and_resets_from_the_register_map():
    top = Top(resets={"theta_lead": 5243, "mode": Mode.SPEED.value})
    rm = top.regmap
    assert rm["theta_lead"].reset == 5243 and rm["mode"].reset == Mode.SPEED.value
    assert rm["id_map_hash"].reset == Top().regmap["id_map_hash"].reset    # layout unchanged
    assert top._regs.signature.members["theta_lead"].init == 5243
    # The speed PI in the formats the host tunes for; the link counters as wide as theirs.
    assert top._servo._loop_params["kp_format"] == rm["pi_speed_kp"].fmt
    assert top._servo._loop_params["kx_format"] == rm["pi_speed_kx"].fmt == UQ(24, 20)
    assert top._link.core.counter_width == rm["st_link_frames_ok"].width == 16
    assert top.scales.i_fs_a == 40.0 and rm["id_i_fs_ma"].reset == 40_000


def test_top_address_map_matches_register_access():
    top = Top()
    amap = dict(((a, b), w) for a, b, w in regmap_address_map(top.regmap))
    assert amap[(_addr(top, "mode"), _addr(top, "mode") + 1)] is True
    assert amap[(_addr(top, "clear_faults"), _addr(top, "clear_faults") + 1)] is True
    assert amap[(_addr(top, "st_trip"), _addr(top, "st_trip") + 1)] is False
    assert amap[(0x0000, 0x0001)] is False                      # id_magic
    assert amap[(0x1000, 0x2000)] is False                      # scope window
    assert amap[(0x0205, 0x0206)] is True and amap[(0x0206, 0x0207)] is True   # mt_k, 2 words


@pytest.mark.parametrize("clk_hz", [pytest.param(50e6, marks=pytest.mark.slow), 33.333e6])
def test_top_elaborates_and_converts_to_verilog(clk_hz):
    # 50 MHz is elaborated and simulated by the tests below; its Verilog runs with -m slow.
    top = Top(clk_hz=clk_hz)
    text = verilog.convert(top, name="foc_servo_top")
    for pin, width in (("uart_rx", 1), ("uart_tx", 1), ("enc_a", 1), ("hall", 3),
                       ("adc_sdo", 4), ("gate_h", 3), ("gate_l", 3), ("fault_n", 1),
                       ("oc_comp", 1), ("led", 2)):
        vec = "" if width == 1 else rf"\[{width - 1}:0\]\s+"
        decl = rf"^\s*(input|output)\s+{vec}{pin};"
        assert re.search(decl, text, re.M), pin


def _wiring_table(top):
    """Register → (block port, expected port value from the register value) for every rw and
    strobe register of the map."""
    cl, servo, timer, gates = top._loop, top._servo, top._timer, top._gates
    mt, enc, prot, scope = top._mt, top._encoder, top._protect, top._scope
    same = (lambda v: v)
    minus_one = (lambda v: max(v, 1) - 1)          # "every n, 0 acts as 1" → "every x + 1"
    table = {
        "mode": (servo.mode, same), "speed_ref": (servo.speed_ref, same),
        "i_d_ref": (servo.id_set, same), "i_q_ref": (servo.iq_set, same),
        "ol_angle_mode": (servo.ol_src, same), "ol_u_d": (servo.ud_set, same),
        "ol_u_q": (servo.uq_set, same), "ol_angle": (servo.ol_theta, same),
        "ol_freq": (servo.ol_freq, same),
        "pi_speed_kp": (servo.speed_kp, same), "pi_speed_kx": (servo.speed_kx, same),
        "pi_speed_lim_lo": (servo.iq_lim_lo, same), "pi_speed_lim_hi": (servo.iq_lim_hi, same),
        "speed_div": (servo.speed_rate_div, minus_one), "mt_k": (mt.k, same),
        "speed_slew": (servo.speed_slew, same), "speed_ff_iq": (servo.iq_ff, same),
        "speed_ref_delay": (servo.speed_ref_delay, same),
        "speed_int_hold": (servo.speed_int_hold, same),
        "clarke_gain_a": (cl.gain_a, same), "clarke_offset_a": (cl.offset_a, same),
        "clarke_gain_b": (cl.gain_b, same), "clarke_offset_b": (cl.offset_b, same),
        "u_rated": (cl.u_rated, same), "decouple_enable": (cl.ff_enable, same),
        "theta_lead": (top._lead.k, same),
        "decouple_l": (cl.ff_l, same), "decouple_psi": (cl.ff_psi, same),
        "pwm_symmetric": (timer.symmetric, same), "pwm_sample_custom": (timer.sample_custom, same),
        "pwm_sample_point": (timer.sample_point, same),
        "dead_time": ((gates.dead_n, lambda v: ~(max(v, 1) - 1)) if top.gates_dead_n else
                      (gates.dead_time, same)),
        "dtc_clocks": (top._dtc.clocks, same), "dtc_band": (top._dtc.shift, same),
        "enc_lines": (enc.lines, same), "enc_pole_pairs": (enc.pole_pairs, same),
        "enc_z_offset": (enc.z_offset, same), "enc_hall_offset": (enc.hall_offset, same),
        "enc_filter": (enc.length, same), "enc_realign": (enc.realign, same),
        "prot_oc_limit": (prot.oc_limit, same), "prot_ov_limit": (prot.ov_limit, same),
        "prot_uv_limit": (prot.uv_limit, same), "prot_uv_enable": (prot.uv_enable, same),
        "prot_os_limit": (prot.os_limit, same), "prot_mask": (prot.mask, same),
        "prot_eh_tolerance": (enc.hall_tolerance, same), "prot_eh_misses": (enc.hall_misses, same),
        "clear_faults": (prot.clear, same),
        "scope_decim": (scope.decim, minus_one),
        "scope_pretrig": (scope.pretrigger, lambda v: min(v, scope.depth - 1)),
        "scope_trig_src": (scope.trig_src, same), "scope_arm": (scope.arm, same),
        "scope_force": (scope.force, same),
    }
    n_src = len(scope.source_names)
    for c in range(scope.channels):
        table[f"scope_chan{c}"] = (scope.sel[c], lambda v: min(v, n_src))
    for p in "dq":
        for reg, port in (("kp", "kp"), ("kx", "kx"), ("lim_lo", "lim_lo"), ("lim_hi", "lim_hi")):
            table[f"pi_{p}_{reg}"] = (getattr(cl, f"{port}_{p}"), same)
    return table


def _status_sources(top):
    """Read-only register → the signal it shows (counters kept in the top: None)."""
    cl, servo, enc, prot, scope, mt = (top._loop, top._servo, top._encoder, top._protect,
                                       top._scope, top._mt)
    return {
        "st_mode": servo.active, "st_trip": prot.trip, "st_fault_present": prot.present,
        "st_fault_first": prot.first, "st_fault_seen": prot.seen,
        # st_trip shows prot.trip one clock late (a register); st_theta is enc.theta itself
        "st_enc_aligned": enc.aligned, "st_position": enc.count, "st_theta": enc.theta,
        "st_speed": mt.o.payload.speed, "st_i_d": cl.i_d, "st_i_q": cl.i_q,
        "st_i_alpha": cl.i_alpha, "st_i_beta": cl.i_beta, "st_u_d": cl.u_d, "st_u_q": cl.u_q,
        "st_u_alpha": cl.u_alpha, "st_u_beta": cl.u_beta, "st_udc": cl.udc.payload,
        "st_current_loops": cl.count[:16], "st_speed_loops": None, "st_overruns": None,
        "st_adc_overruns": None, "st_loop_flags": None, "st_uv_armed": prot.uv_armed,
        "st_enc_config_error": enc.config_error, "st_enc_hall_error": enc.hall_error,
        **{f"st_link_{n}": getattr(top._link, n) for n in
           ("frames_ok", "crc_errors", "framing_errors", "rejected", "dropped")},
        "scope_state": scope.state, "scope_status": None,
    }


def test_top_every_rw_and_strobe_register_drives_its_block_port():
    top = Top(pwm_hz=PWM, baud=BAUD)
    table = _wiring_table(top)
    writable = {r.name for r in top.regmap if r.access in (Access.RW, Access.STROBE)}
    assert set(table) == writable
    rng = np.random.default_rng(5)
    rounds = [{n: int(rng.integers(0, 1 << top.regmap[n].width)) for n in table}
              for _ in range(3)]
    # The conversions' corners: 0 acts as 1, clamps, out-of-range scope channel codes.
    rounds.append({**rounds[0], "speed_div": 0, "scope_decim": 0, "scope_pretrig": 0xFFFF,
                   "scope_chan0": 13, "scope_chan1": 14, "scope_chan2": 255, "scope_chan3": 16})
    rounds.append({**rounds[1], "speed_div": 1, "scope_decim": 1, "scope_pretrig": 1023,
                   "scope_chan0": 0})
    bad = []

    async def testbench(ctx):
        ctx.set(top.hall, HALL_OK)
        await ctx.tick()
        for values in rounds:
            # The register file's outputs hold what is set here (their registers only load on
            # a bus write or a commit): the block ports follow combinationally.
            for name, v in values.items():
                ctx.set(_raw(getattr(top._regs, name)), v)
            for name, v in values.items():
                port, f = table[name]
                width = len(_raw(port))
                got = ctx.get(_raw(port).as_unsigned())
                want = f(v) & ((1 << width) - 1)
                if got != want:
                    bad.append((name, v, got, want))

    simulate(top, [testbench], name="test_top_wiring")
    assert not bad


def test_top_bram_register_file_holds_the_operands():
    """regs_staging="bram": the register file's flip-flops hold the blocks' operands
    (RegisterFile derived, hdl.top._operands), their gateware function equal to the Python
    one (on every 8-bit code, on the corners and random values of the 16-bit ones) and to the
    "ff" top's conversions (those of _wiring_table), the blocks' ports wired to them."""
    top = Top(pwm_hz=PWM, baud=BAUD, regs_staging="bram")
    ops, regs, scope = top._operands, top._regs, top._scope
    n_src = len(scope.source_names)
    conv = {"speed_div": lambda v: max(v, 1) - 1, "scope_decim": lambda v: max(v, 1) - 1,
            "scope_pretrig": lambda v: min(v, scope.depth - 1),     # as _wiring_table's
            **{f"scope_chan{c}": lambda v: min(v, n_src) for c in range(scope.channels)},
            "dead_time": lambda v: 255 - (max(v, 1) - 1)}          # Gates(dead_n=True)
    ports = {"speed_div": top._servo.speed_rate_div, "scope_decim": scope.decim,
             "scope_pretrig": scope.pretrigger,
             **{f"scope_chan{c}": scope.sel[c] for c in range(scope.channels)},
             "dead_time": top._gates.dead_n}
    assert top.gates_dead_n and len(top._gates.dead_n) == 8
    assert set(regs.derived) == set(ops) == {"speed_div", "scope_decim", "scope_pretrig",
                                             *(f"scope_chan{c}" for c in range(4)), "dead_time"}
    assert len(regs.scope_chan0) == top._scope.sel_width and len(regs.scope_pretrig) == 10
    m = Module()
    ins = {n: Signal(top.regmap[n].width, name=f"{n}_raw") for n in ops}
    outs = {n: Signal(op[0], name=f"{n}_op") for n, op in ops.items()}
    m.d.comb += [outs[n].eq(op[1](ins[n])) for n, op in ops.items()]
    rng = np.random.default_rng(3)
    bad = []

    async def functions(ctx):
        for n, op in ops.items():
            w = top.regmap[n].width
            values = (range(1 << w) if w <= 8 else
                      [0, 1, 2, 1022, 1023, 1024, 1025, (1 << w) - 1,
                       *(int(v) for v in rng.integers(0, 1 << w, 200))])
            for v in values:
                ctx.set(ins[n], v)
                got, want = ctx.get(outs[n]), op[2](v)
                if not got == want == conv[n](v):
                    bad.append((n, v, got, want, conv[n](v)))

    simulate(m, [functions], name="test_top_operands")
    assert not bad, bad[:5]

    async def wiring_(ctx):
        ctx.set(top.hall, HALL_OK)
        await ctx.tick()
        for n in ops:
            assert ctx.get(getattr(regs, n)) == ops[n][2](top.regmap[n].reset)   # init
            for v in (0, 5, (1 << len(getattr(regs, n))) - 1):
                ctx.set(getattr(regs, n), v)
                port = ports[n]
                assert ctx.get(_raw(port).as_unsigned()) == v & ((1 << len(_raw(port))) - 1), n

    simulate(top, [wiring_], name="test_top_bram_operands")


# --- simulations ------------------------------------------------------------------------------

def test_top_gates_stay_low_for_a_pwm_period_after_reset():
    top = Top(pwm_hz=PWM, baud=BAUD)
    on = []
    starts = []

    async def testbench(ctx):
        ctx.set(top.hall, HALL_OK)
        for t in range(top.pwm_period + 100):
            on.append(ctx.get(top.gate_h) | ctx.get(top.gate_l))
            if ctx.get(top._timer.period_start):
                starts.append(t)
            await ctx.tick()

    simulate(top, [testbench], name="test_top_reset")
    assert len(starts) >= 1                   # a whole period (and its boundary) was seen
    assert not any(on)


@pytest.mark.parametrize("link_compact", [False, True])
def test_top_register_writes_reach_blocks_through_the_host_link(link_compact):
    top = Top(pwm_hz=PWM, baud=BAUD, link_compact=link_compact)
    bench = _Bench(top, BAUD)
    host = _Host(bench)
    rm = top.regmap
    seen = {}

    async def testbench(ctx):
        ctx.set(top.hall, HALL_OK)
        # Identification constants, one burst.
        seen["ids"] = await host.read(ctx, 0x0000, 8)
        # Dead time (shadowed: staged at once, active after the next period start).
        await host.write(ctx, _addr(top, "dead_time"), 37)
        seen["dead_staged"] = (await host.read(ctx, _addr(top, "dead_time")))[0]
        await host.next_period(ctx, top)
        seen["dead_port"] = (ctx.get(top._gates.dead_n) if top.gates_dead_n else
                             ctx.get(top._gates.dead_time))
        # Mode and the open-loop set-points in one frame (0x0010 … 0x0017).
        await host.write(ctx, _addr(top, "mode"),
                         Mode.OPEN_LOOP.value, 0, 0, 0, 0, 0, 1000, 0xFFFF & -2000)
        await host.next_period(ctx, top)
        seen["servo_mode"] = ctx.get(top._servo.mode).value
        seen["ud_set"] = ctx.get(top._servo.ud_set)
        seen["uq_set"] = ctx.get(top._servo.uq_set)
        await host.next_period(ctx, top)
        seen["st_mode"] = (await host.read(ctx, _addr(top, "st_mode")))[0]
        # A write to a read-only register is refused by the link, before any access.
        seen["ro"] = await host.transact(ctx, Command.WRITE, _addr(top, "st_trip"), data=[1])

    simulate(bench, [testbench], name="test_top_regs")
    ids = seen["ids"]
    assert ids[0] == 0x464F4353
    assert ids[2] == rm["id_map_hash"].reset
    assert ids[3] == 50_000_000 and ids[4] == 100_000_000
    assert tuple(ids[5:8]) == (rm["id_i_fs_ma"].reset, rm["id_u_fs_uv"].reset,
                               rm["id_n_fs_rpm"].reset)
    assert seen["dead_staged"] == 37
    assert seen["dead_port"] == (dead_n_const(37) if top.gates_dead_n else 37)
    assert seen["servo_mode"] == Mode.OPEN_LOOP.value
    assert (seen["ud_set"], seen["uq_set"]) == (1000, -2000)
    assert seen["st_mode"] == Mode.OPEN_LOOP.value
    assert seen["ro"].status == ReplyStatus.READ_ONLY


class _TracingHost(_Host):
    """A :class:`_Host` that records ``probe(ctx)`` in every clock it ticks."""

    def __init__(self, bench, probe):
        super().__init__(bench)
        self.probe = probe
        self.trace = []

    async def tick(self, ctx, n=1):
        for _ in range(n):
            await ctx.tick()
            self.clocks += 1
            self.trace.append(self.probe(ctx))


def test_top_bram_staging_applies_a_frame_word_by_word_ending_at_period_start():
    """``regs_staging="bram"``: reads after reset return the reset values (the reset walk);
    a frame's words reach their blocks in the copy before the next ``period_start``, slot ``i``
    in the copy's clock ``i + 1``, all in place in the ``period_start`` clock, ``pwm_symmetric``
    last; the copy starts only with ``lock`` low; read-back returns what was written."""
    from foc_servo.hdl.regs import staging_slots
    top = Top(pwm_hz=PWM, baud=BAUD, regs_staging="bram")
    assert top.regs_staging == "bram" and top.commit_clocks == 49
    bench = _Bench(top, BAUD)
    rm = top.regmap
    regs, timer = top._regs, top._timer
    ports = {"pwm_symmetric": timer.symmetric, "pwm_sample_custom": timer.sample_custom,
             "pwm_sample_point": timer.sample_point,
             "dead_time": top._gates.dead_n if top.gates_dead_n else top._gates.dead_time,
             "pi_q_kp": top._loop.kp_q}
    slots = [r.name for _, r, _ in staging_slots(rm, ("pwm_symmetric",))]
    assert slots[-1] == "pwm_symmetric"

    def probe(ctx):
        return (ctx.get(timer.period_start), ctx.get(regs.bus.lock),
                {n: ctx.get(p) for n, p in ports.items()})
    host = _TracingHost(bench, probe)
    seen = {}
    new = {"pwm_symmetric": 0, "pwm_sample_custom": 1, "pwm_sample_point": 77, "dead_time": 37}

    async def testbench(ctx):
        ctx.set(top.hall, HALL_OK)
        seen["resets"] = await host.read(ctx, _addr(top, "pwm_symmetric"), 4)
        seen["pi_resets"] = await host.read(ctx, _addr(top, "pi_d_kp"), 8)
        host.trace.clear()
        await host.write(ctx, _addr(top, "pwm_symmetric"), *new.values())   # one frame
        seen["staged"] = await host.read(ctx, _addr(top, "pwm_symmetric"), 4)
        await host.next_period(ctx, top)
        await host.next_period(ctx, top)
        # Mode and the open-loop set-points in one frame: the servo's loop strobe at the
        # period_start after the copy takes the new mode (in place in that clock).
        await host.write(ctx, _addr(top, "mode"),
                         Mode.OPEN_LOOP.value, 0, 0, 0, 0, 0, 1000, 0xFFFF & -2000)
        await host.next_period(ctx, top)
        await host.next_period(ctx, top)
        seen["servo_mode"] = ctx.get(top._servo.mode).value
        seen["st_mode"] = (await host.read(ctx, _addr(top, "st_mode")))[0]

    simulate(bench, [testbench], name="test_top_regs_bram")
    assert list(seen["resets"]) == [rm[n].reset for n in new]
    assert list(seen["pi_resets"]) == [rm[a].read_word(rm[a].bits(rm[a].reset), 0) for a in (
        "pi_d_kp", "pi_d_kx", "pi_d_lim_lo", "pi_d_lim_hi", "pi_q_kp", "pi_q_kx", "pi_q_lim_lo",
        "pi_q_lim_hi")]
    assert list(seen["staged"]) == list(new.values())
    trace = host.trace
    # The first clock each port shows its new value, and the period_start after it.
    # (the gates' port with gates_dead_n, the default: the operand of the dead time)
    port_value = {**new, "dead_time": dead_n_const(new["dead_time"])} if top.gates_dead_n else new
    first = {n: next(t for t, (_, _, v) in enumerate(trace) if v[n] == port_value[n])
             for n in new}
    p = next(t for t, (start, _, _) in enumerate(trace) if start and t >= max(first.values()))
    s = p - top.commit_clocks                          # the copy's first clock
    assert trace[s][1] == 0                            # lock low when it starts
    assert all(not start for start, _, _ in trace[s:p])
    for n in new:
        assert first[n] == s + 2 + slots.index(n), (n, first[n] - s)
        assert all(v[n] == port_value[n] for _, _, v in trace[first[n]:p + 2])
    assert first["pwm_symmetric"] == p                 # the last word: after the timer's latch
    assert trace[p][2]["pi_q_kp"] == rm["pi_q_kp"].reset   # an unwritten register kept
    assert seen["servo_mode"] == Mode.OPEN_LOOP.value
    assert seen["st_mode"] == Mode.OPEN_LOOP.value


def test_regs_staging_threaded_from_top_and_board():
    import gc
    import warnings

    from amaranth.hdl import UnusedElaboratable

    from foc_servo.boards.build import BoardTop
    from foc_servo.boards.platforms import BOARDS
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UnusedElaboratable)    # only inspected, never elaborated
        top = Top()
        assert top.regs_staging == "ff" and top.commit_clocks == 1
        assert {name: BoardTop(name).top.regs_staging for name in BOARDS} == {
            name: "bram" if name in ("icebreaker", "arty_s7") else "ff" for name in BOARDS}
        del top
        gc.collect()


@pytest.mark.parametrize("kwargs", [{}, {"regs_staging": "bram", "prot_limits": "ram"}],
                         ids=["ports", "ram"])
def test_top_fault_n_low_forces_all_gates_off_within_fault_latency(kwargs):
    """The pin's fault_latency (4 clocks) in both forms of the protection's limits (the
    iCE40's sequential compare changes only the sampled causes' timing)."""
    top = Top(pwm_hz=PWM, baud=BAUD, **kwargs)
    bench = _Bench(top, BAUD)
    host = _Host(bench)
    seen = {}

    async def testbench(ctx):
        ctx.set(top.hall, HALL_OK)
        await host.write(ctx, _addr(top, "mode"), Mode.OPEN_LOOP.value)
        await host.next_period(ctx, top)
        # Wait for a clock with some gate on (the first duties reach the timer one period on).
        for _ in range(4 * top.pwm_period):
            if ctx.get(top.gate_h) | ctx.get(top.gate_l):
                break
            await host.tick(ctx)
        seen["on_before"] = ctx.get(top.gate_h) | ctx.get(top.gate_l)
        ctx.set(top.fault_n, 0)               # changes at the pin in this clock
        trace = []
        for _ in range(8):
            await host.tick(ctx)
            trace.append(ctx.get(top.gate_h) | ctx.get(top.gate_l))
        seen["trace"] = trace
        st = await host.read(ctx, _addr(top, "st_trip"), 4)
        seen["trip"], seen["present"], seen["first"] = st[0], st[1], st[2]
        seen["led"] = ctx.get(top.led)
        # Clearing while the fault is present does nothing; after it goes away it releases.
        await host.write(ctx, _addr(top, "clear_faults"), 1)
        seen["trip_held"] = (await host.read(ctx, _addr(top, "st_trip")))[0]
        ctx.set(top.fault_n, 1)
        await host.tick(ctx, 8)
        await host.write(ctx, _addr(top, "clear_faults"), 1)
        seen["trip_after"] = (await host.read(ctx, _addr(top, "st_trip")))[0]

    simulate(bench, [testbench], name="test_top_fault")
    assert seen["on_before"]
    trace = seen["trace"]
    # Pin low in clock t: 2 synchroniser flops, Protection's register, the gates' register.
    off_at = next(i for i, v in enumerate(trace, 1) if v == 0)
    assert off_at == top.fault_latency == 4
    assert not any(trace[off_at - 1:])
    assert seen["trip"] == 1 and seen["present"] & 1 and seen["first"] == 1    # bit 0: external
    assert seen["led"] & 1
    assert seen["trip_held"] == 1 and seen["trip_after"] == 0


def test_top_adc_model_drives_a_current_loop_pass_at_33_333_mhz():
    clk = 33.333e6          # the ADC model checks the datasheet timing at this clock
    top = Top(clk_hz=clk, pwm_hz=PWM, baud=clk / 8)
    bench = _Bench(top, clk / 8)
    host = _Host(bench)
    ia, ib, udc = 1000, 300, 16000
    model = AdcPartModel(cs_n=top.adc_cs_n, sclk=top.adc_sclk, sdo=top.adc_sdo, clk_hz=clk,
                         source=lambda n: (ia, ib, udc, 0))
    seen = {}

    async def testbench(ctx):
        ctx.set(top.hall, HALL_OK)
        await host.tick(ctx, 3 * top.pwm_period)
        first = await host.read(ctx, _addr(top, "st_i_d"), 9)       # st_i_d … st_udc
        c0, t0 = (await host.read(ctx, _addr(top, "st_current_loops")))[0], host.clocks
        await host.tick(ctx, 3 * top.pwm_period)
        c1, t1 = (await host.read(ctx, _addr(top, "st_current_loops")))[0], host.clocks
        seen.update(first=first, c0=c0, c1=c1, periods=(t1 - t0) / top.pwm_period)
        seen["overruns"] = (await host.read(ctx, _addr(top, "st_overruns")))[0]
        seen["speed_loops"] = (await host.read(ctx, _addr(top, "st_speed_loops")))[0]
        for name, src in _status_sources(top).items():
            if src is not None:
                reg = ctx.get(_raw(getattr(top._regs, name)).as_unsigned())
                if reg != ctx.get(_raw(src).as_unsigned()):
                    seen.setdefault("status_mismatch", []).append(name)

    simulate(bench, [testbench], [model.process], clock_hz=clk, name="test_top_adc")
    i_d, i_q, i_alpha, i_beta, u_d, u_q, u_alpha, u_beta, st_udc = (
        _signed(w) for w in seen["first"])
    ref = clarke(np.array([ia]), np.array([ib]), gain_a=1 << 15, gain_b=1 << 15,
                 offset_a=0, offset_b=0)
    assert (i_alpha, i_beta) == (ref["alpha"][0], ref["beta"][0])
    assert st_udc == udc
    # Park is a rotation: |i_dq| = |i_αβ| to CORDIC accuracy; disabled mode: zero voltages.
    assert abs(np.hypot(i_d, i_q) - np.hypot(i_alpha, i_beta)) < 3
    assert (u_d, u_q) == (0, 0)
    # One loop per PWM period.
    assert seen["c0"] >= 3
    assert abs((seen["c1"] - seen["c0"]) - seen["periods"]) <= 1
    assert seen["overruns"] == 0
    # Speed loop: runs only in SPEED mode (disabled here), so its counter stays 0.
    assert seen["speed_loops"] == 0
    assert "status_mismatch" not in seen
    assert set(_status_sources(top)) == {r.name for r in top.regmap if r.access is Access.RO}
    assert len(model.reads) >= 6


@pytest.mark.parametrize("current_loop, staging", [("pipelined", "ff"), ("pipelined", "bram"),
                                                   ("engine", "ff"), ("engine", "bram")])
def test_top_current_loop_duties_match_the_model(current_loop, staging):
    """Either current loop in the top (``Top(current_loop=...)``): closed current loop with
    decoupling feed-forward, the encoder turning, random ADC codes (over-modulation and PI
    saturation included) from the AD7380-4 model. Every sample the loop accepts is recorded at its
    ports (sample and configuration inputs), the whole sequence replayed through
    ``CurrentLoopModel``: the duties, voltages, currents and flags of every pass are bit-identical,
    each within the loop's latency, with no overrun. The pipelined loop with ``"bram"`` staging
    is the Arty S7's configuration; the engine with ``"bram"`` staging (the iCEBreaker's) reads its configuration from its RAM (written by the register file's reset
    walk): the configuration recorded is then the registers' reset values."""
    from foc_servo.hdl.foc_engine import CONFIG, CONFIG_PORTS
    from foc_servo.hdl.top import ENGINE_CONFIG
    from foc_servo.sim.models.engine import engine_fields, loop_model_inputs
    from foc_servo.sim.models.foc import CONFIG_FIELDS, SAMPLE_FIELDS, CurrentLoopModel
    clk = 33.333e6          # the ADC model checks the datasheet timing at this clock
    top = Top(clk_hz=clk, pwm_hz=50e3, baud=clk / 8, current_loop=current_loop,
              regs_staging=staging, resets={
        "mode": Mode.CURRENT.value, "i_d_ref": -3000, "i_q_ref": 9000,
        "pi_d_kp": 0x0480, "pi_q_kp": 0x0600, "pi_d_kx": 0x3000, "pi_q_kx": 0x2000,
        "decouple_enable": 1, "decouple_l": 3000, "decouple_psi": 2000, "u_rated": 16000,
        "enc_lines": 100, "theta_lead": 0x2000, "prot_mask": 0x7FF & ~(1 << 10)})
    assert top.current_loop == current_loop
    cl = top._loop
    rng = np.random.default_rng(7)
    codes = [(int(rng.integers(-14000, 14000)), int(rng.integers(-14000, 14000)),
              int(rng.integers(5000, 22000)), 0) for _ in range(64)]
    adc = AdcPartModel(cs_n=top.adc_cs_n, sclk=top.adc_sclk, sdo=top.adc_sdo, clk_hz=clk,
                       source=lambda n: codes[n % len(codes)])
    # The engine takes the theta_lead register (lead_k) and computes θ_lead from the speed it
    # latches at the sample (the pipelined loop: θ_lead from LeadAngle, at M/T's strobe).
    fields = SAMPLE_FIELDS if current_loop == "pipelined" else engine_fields()
    ports = {"ia": cl.i.payload.ia, "ib": cl.i.payload.ib, "udc": cl.i.payload.udc,
             **{f: getattr(cl, f) for f in fields + CONFIG_FIELDS
                if f not in ("ia", "ib", "udc") and hasattr(cl, f)}}
    # (The engine's references are words of its RAM only with its speed run: not here.)
    assert not hasattr(cl, "refs_mode") or cl.refs_mode == "ports"
    in_ram = {port: top.regmap[reg].reset for port, reg in
              zip((CONFIG_PORTS[n] for n in CONFIG), ENGINE_CONFIG)}
    assert (current_loop, staging) == ("engine", "bram") or not hasattr(cl, "config")
    if hasattr(cl, "config"):
        assert set(in_ram) == (set(CONFIG_FIELDS) | set(fields)) - set(ports)
    # The iCEBreaker's engine ("bram") keeps its status in its status RAM: its words (the RAM
    # is made when the top is elaborated: looked up in the testbench).
    from foc_servo.hdl.foc_engine import STATUS
    in_status_ram = (current_loop, staging) == ("engine", "bram")
    outs = {"duty_a": cl.o.payload.a, "duty_b": cl.o.payload.b, "duty_c": cl.o.payload.c,
            **{f: None if in_status_ram and f in STATUS else getattr(cl, f)
               for f in ("i_alpha", "i_beta", "i_d", "i_q", "u_d", "u_q", "u_alpha", "u_beta",
                         "sat_d", "sat_q")}}
    ins, got, lat, phase_lat, mt_seen = [], [], [], [], []

    async def testbench(ctx):
        if in_status_ram:
            outs.update({f: cl.status_memory.data[j] for j, f in enumerate(STATUS)})
        ctx.set(top.hall, HALL_OK)
        start = None
        mt_valid = None
        overruns = 0                # (the loop's overrun strobes: st_overruns counts them)
        for clock in range(14 * top.pwm_period):
            overruns += ctx.get(cl.overrun)
            if ctx.get(top._mt.o.valid):
                mt_valid = clock
            if ctx.get(cl.i.valid):             # accepted at the coming edge (never busy here)
                ins.append({**{f: ctx.get(p) for f, p in ports.items()},
                            **(in_ram if hasattr(cl, "config") else {})})
                mt_seen.append((ctx.get(top._mt.o.payload.speed),
                                None if mt_valid is None else clock - mt_valid))
                start = clock
            if ctx.get(cl.o.valid):             # o.ready is always high: a one-clock transfer
                got.append({f: ctx.get(p) for f, p in outs.items()})
                lat.append(clock - start)
            if ctx.get(cl.phase.valid) and start is not None:
                phase_lat.append(clock - start)
            await ctx.tick()
        got.append({"overruns": overruns})

    async def encoder(ctx):                     # forward, Z high over lines 10 and 11
        for k in itertools.count():
            ctx.set(top.enc_a, k % 4 in (1, 2))
            ctx.set(top.enc_b, k % 4 in (2, 3))
            ctx.set(top.enc_z, 40 <= k < 48)
            await ctx.delay(37 / clk)

    simulate(top, [testbench], [adc.process, encoder], clock_hz=clk,
             name=f"test_top_duties_{current_loop}_{staging}")
    overruns = got.pop()["overruns"]
    assert overruns == 0 and len(got) >= 10 and len(ins) in (len(got), len(got) + 1)
    assert max(lat) <= cl.latency and min(lat) >= (134 if current_loop == "engine" else 48)
    # The phase currents (dead-time compensation, over-current check): the loop's figure, 27 / 6.
    assert set(phase_lat) == {cl.phase_latency} == {27 if current_loop == "engine" else 6}
    recorded = {f: np.array([s[f] for s in ins]) for f in ins[0]}
    if current_loop == "engine":
        ks = recorded["lead_k"]
        recorded = loop_model_inputs(recorded)
        # The θ_lead the engine used is LeadAngle's: every sample came more than
        # LeadAngle.latency + 1 clocks after M/T's last result (LeadAngle's θ_lead of that speed
        # was in place), and the speed the engine latched (a clock behind M/T) is that result.
        for (mt_speed, since), s in zip(mt_seen, ins):
            assert since is None or since > LeadAngle.latency + 1
            assert s["speed"] == mt_speed
        assert all(recorded["theta_lead"] == _lead_model(recorded["speed"], ks))
    ref = CurrentLoopModel().run(**recorded)
    for f in outs:
        assert [g[f] for g in got] == list(ref[f][:len(got)]), f
    # The case mix the comparison covered: over-modulation, saturated PIs, varying angle.
    assert 0 < sum(ref["overmod"][:len(got)]) < len(got)
    assert any(ref["sat_q"][:len(got)]) and not all(ref["sat_q"][:len(got)])
    assert all(s["enable"] for s in ins) and len({s["theta"] for s in ins}) > 5
    assert ins[-1]["speed"] > 0 and recorded["theta_lead"][-1] > 0  # feed-forward, lead active


def test_top_hall_edges_with_a_still_encoder_trip_encoder_hall():
    """Issue 6 item 7: Hall sectors advancing while the encoder does not move (a broken encoder
    line before the first Z) raise the encoder_hall fault through the top: on the first missed
    Hall edge (the default prot_eh_misses 1), in the clock the latencies add up to, with the
    cause in st_fault_first; masking the cause ignores it."""
    from foc_servo.hdl.encoder import EncoderFrontEnd, hall_boundaries
    from foc_servo.hdl.protect import FAULTS, Protection
    from foc_servo.sim.models.encoder import hall_code

    top = Top(pwm_hz=PWM, baud=BAUD)
    regs = top._regs
    dwell = 40
    codes = [hall_code(b + 100) for b in hall_boundaries()]     # sectors 0, 1, 2, …
    seen = {}

    async def walk(ctx, sectors):
        trips, first_trip = [], None
        for k in sectors:
            ctx.set(top.hall, codes[k % 6])                      # the pin changes in this clock
            for t in range(dwell):
                await ctx.tick()
                trips.append(ctx.get(top._protect.trip))
                if trips[-1] and first_trip is None:
                    first_trip = (k, t + 1)
        return first_trip

    async def testbench(ctx):
        ctx.set(top.hall, codes[0])
        await ctx.tick().repeat(dwell)
        # Edges 0→1 (no reference yet), 1→2 (the encoder did not advance: a miss, the fault).
        seen["first_trip"] = await walk(ctx, [1, 2, 3])
        seen["first"] = ctx.get(_raw(regs.st_fault_first))
        seen["error"] = ctx.get(regs.st_enc_hall_error)
        # Masked, cleared: the same walk goes on without a trip.
        mask = (1 << len(FAULTS)) - 1 - (1 << FAULTS.index("encoder_hall"))
        ctx.set(_raw(regs.prot_mask), mask)
        ctx.set(regs.clear_faults, 1)                             # the strobe's pulse
        await ctx.tick()
        ctx.set(regs.clear_faults, 0)
        seen["masked_trip"] = await walk(ctx, [4, 5, 0, 1])

    simulate(top, [testbench], name="test_top_encoder_hall")
    length = top.regmap["enc_filter"].reset
    assert seen["first_trip"] == (2, EncoderFrontEnd.plausibility_latency + length - 1
                                  + Protection.latency)
    assert seen["first"] == 1 << FAULTS.index("encoder_hall")
    # The encoder angle (0: never moved, offset 0) against the 2 → 3 boundary (180°).
    assert seen["error"] == -(1 << 15)
    assert seen["masked_trip"] is None


# --- delay compensation (theta_lead) ----------------------------------------------------------

def _lead_n(speed):
    """The Q1.15 speed LeadAngle takes: Top's rounding of the Q1.31 M/T speed (``lead_n``)."""
    n = saturate_np(round_shift_np(np.asarray(speed, dtype=np.int64), 16), signed(16))
    return int(n) if np.ndim(n) == 0 else np.asarray(n, dtype=np.int64)


def _lead_model(speed, k):
    """Golden model of Top's θ_lead: BinaryAngle(16) advance of a Q1.31 speed times a UQ0.16 k
    (LeadAngle of ``_lead_n(speed)``)."""
    return round_shift_np(_lead_n(speed) * k, 15) & 0xFFFF


def test_lead_angle_bit_exact_latency_and_restart():
    dut = LeadAngle()
    rng = np.random.default_rng(11)
    cases = [(-(1 << 31), 0xFFFF), ((1 << 31) - 1, 0xFFFF), ((1 << 31) - 1, 0), (0, 0x8000),
             (-(1 << 16), 1), ((1 << 15), 0x8000), (-(1 << 15), 0x8000)]
    cases += [(int(rng.integers(-(1 << 31), 1 << 31)), int(rng.integers(0, 1 << 16)))
              for _ in range(40)]
    got, changed_at = [], []

    async def testbench(ctx):
        # A restart in the middle of a computation: only the second one completes.
        ctx.set(dut.n, _lead_n(1 << 30))
        ctx.set(dut.k, 0x4000)
        ctx.set(dut.start, 1)
        await ctx.tick()
        ctx.set(dut.start, 0)
        await ctx.tick().repeat(5)
        for speed, k in cases:
            ctx.set(dut.n, _lead_n(speed))
            ctx.set(dut.k, k)
            ctx.set(dut.start, 1)
            before = ctx.get(dut.theta)
            await ctx.tick()
            ctx.set(dut.start, 0)
            ctx.set(dut.n, 12345)               # latched at start: later changes do not matter
            ctx.set(dut.k, 0x1234)
            first = None
            for t in range(1, 30):
                if first is None and ctx.get(dut.theta) != before:
                    first = t
                await ctx.tick()
            changed_at.append(first)
            got.append(ctx.get(dut.theta))

    simulate(dut, [testbench], name="test_lead_angle")
    want = [_lead_model(sp, k) for sp, k in cases]
    assert got == want
    # Hand checks: +0.5 N_FS × a quarter turn = 1/8 turn; −N_FS × 0xFFFF ≈ −1 turn + 1 LSB.
    assert _lead_model(1 << 30, 0x4000) == 0x2000
    assert _lead_model(-(1 << 31), 0xFFFF) == 1
    # Latency: start in clock t → new theta in t + 17 (cases whose result differs).
    assert {t for t in changed_at if t is not None} == {LeadAngle.latency}
    assert changed_at.count(None) <= 3


def _encoder_process(top, clocks_per_edge):
    """Quadrature A/B stand-in: one edge every ``clocks_per_edge`` clocks, always forward."""
    async def process(ctx):
        states = ((0, 0), (1, 0), (1, 1), (0, 1))
        k = 0
        while True:
            a, b = states[k % 4]
            ctx.set(top.enc_a, a)
            ctx.set(top.enc_b, b)
            k += 1
            await ctx.delay(clocks_per_edge / top.clk_hz)
    return process


@pytest.mark.parametrize("current_loop", ["pipelined", "engine"])
def test_top_theta_lead_advances_the_inverse_park_angle(current_loop):
    """Open loop at the fixed angle 0 with u_d only (set at reset): u_αβ points along θ + θ_lead,
    θ_lead = speed/N_FS · theta_lead: 0 while M/T reads no speed yet, then ≈ 45° with the encoder
    at 6000 r/min = N_FS/2 and theta_lead = 90°; the Park rotation (i_d, i_q) is not advanced.
    The pipelined loop takes θ_lead from LeadAngle, the engine computes it in its program from
    the speed it latches at the sample (a PWM period above the engine's latency)."""
    k = 0x4000                          # a quarter turn at full-scale speed
    top = Top(pwm_hz=250e3 if current_loop == "pipelined" else 100e3, baud=BAUD,
              current_loop=current_loop,
              resets={"mode": Mode.OPEN_LOOP.value, "ol_u_d": 16000, "theta_lead": k})
    seen = []

    async def testbench(ctx):
        ctx.set(top.hall, HALL_OK)
        for _ in range(6):
            # Just after each current-loop pass: its θ_lead and the M/T speed it was made from.
            await ctx.tick().until(top._loop.done)
            await ctx.tick().repeat(2)
            lead = (ctx.get(top._loop.theta_lead) if current_loop == "pipelined" else
                    int(_lead_model(ctx.get(top._loop.speed), ctx.get(top._loop.lead_k))))
            seen.append((ctx.get(top._mt.o.payload.speed), lead,
                         ctx.get(top._loop.u_alpha), ctx.get(top._loop.u_beta)))

    simulate(top, [testbench], [_encoder_process(top, 25)],
             name=f"test_top_theta_lead_{current_loop}")
    angles = [math.degrees(math.atan2(ub, ua)) for _, _, ua, ub in seen]
    # The first pass: no speed measured yet, no advance; the vector is on the fixed angle 0.
    assert seen[0][:2] == (0, 0) and angles[0] == pytest.approx(0, abs=0.01)
    # Later passes: 25 clocks per edge, 4 edges per line, 5000 lines at 50 MHz = 6000 r/min.
    speed, lead, ua, ub = seen[-1]
    assert speed / 2**31 * 12000 == pytest.approx(6000, rel=0.005)
    assert lead == _lead_model(speed, k)
    lead_deg = speed / 2**31 * k / 2**16 * 360
    assert lead_deg == pytest.approx(45, rel=0.005)
    assert angles[-1] == pytest.approx(lead_deg, abs=0.02)
    assert math.hypot(ua, ub) == pytest.approx(16000, abs=2)


def test_top_engine_open_loop_voltages_are_words_of_the_engine_ram():
    """The iCEBreaker's top (engine current and speed loop, ``"bram"`` staging): ``ol_u_d`` and
    ``ol_u_q`` have no flip-flops in the register file and no port on the engine
    (:data:`~foc_servo.hdl.top.ENGINE_REFS`, words of its configuration RAM after
    :data:`ENGINE_CONFIG`): in open loop every pass's u_d, u_q (the engine's status RAM) are
    the reset values, then, from the first pass after the commit copy that follows a host
    frame writing both, the new ones (a pass before it keeps the old)."""
    from foc_servo.hdl.foc_engine import STATUS
    from foc_servo.hdl.top import ENGINE_CONFIG, ENGINE_REFS
    top = Top(pwm_hz=PWM / 2, baud=BAUD, current_loop="engine", regs_staging="bram",
              speed_loop="engine",
              resets={"mode": Mode.OPEN_LOOP.value, "ol_u_d": 12000, "ol_u_q": -3000})
    regs, cl = top._regs, top._loop
    names = [r.name for _, r, _ in regs.export_words]
    assert names[:len(ENGINE_CONFIG + ENGINE_REFS)] == list(ENGINE_CONFIG + ENGINE_REFS)
    assert not any(hasattr(regs, n) for n in ENGINE_REFS)
    assert not hasattr(cl, "ol_ud") and not hasattr(cl, "ol_uq")
    bench = _Bench(top, BAUD)
    passes, marks = [], {}

    def probe(ctx):
        if ctx.get(cl.done):
            mem = cl.status_memory
            passes.append((host.clocks, ctx.get(mem.data[STATUS.index("u_d")]),
                           ctx.get(mem.data[STATUS.index("u_q")])))
    host = _TracingHost(bench, probe)

    async def testbench(ctx):
        ctx.set(top.hall, HALL_OK)
        for _ in range(3):
            await host.next_period(ctx, top)
        await host.write(ctx, _addr(top, "ol_u_d"), 0xFFFF & -7000, 5000)
        marks["replied"] = host.clocks
        for _ in range(4):
            await host.next_period(ctx, top)

    simulate(bench, [testbench], name="test_top_engine_refs")
    before = [(u, v) for t, u, v in passes if t < marks["replied"]]
    after = [(u, v) for t, u, v in passes[-3:]]
    assert len(before) >= 3 and set(before) == {(12000, -3000)}
    assert set(after) == {(-7000, 5000)}


@pytest.mark.parametrize("mode, trip", [("current", "mid"), ("speed", "mid"),
                                        ("current", "edge")])
def test_top_scope_reads_the_engine_references_as_the_registers_held_them(mode, trip):
    """The iCEBreaker's top (:data:`~foc_servo.hdl.top.ENGINE_REFS`): the scope's ``i_d_ref``
    and ``i_q_ref`` are words of the engine's status RAM, written by its program with the
    references it used, masked in the top by the mode: in every clock ``c`` after a pass
    (``done`` … ``done + 3``, the clocks the scope samples in) in which the scope addresses one
    of them, the data in ``c + 1`` is what the top's reference registers held in ``c``: the
    Servo's reference of ``c − 1`` (CURRENT: ``i_d_ref`` and ``clamp(i_q_ref)``; SPEED: the
    speed run's i_q), 0 unless the mode was CURRENT or SPEED then: after a driver fault trips
    the drive in the middle of a pass, 0 although the RAM still holds the pass's values."""
    from foc_servo.hdl.foc_engine import STATUS
    from foc_servo.hdl.protect import FAULTS
    from foc_servo.hdl.scope import DEFAULT_SOURCES
    codes = list(DEFAULT_SOURCES)
    resets = {"mode": (Mode.CURRENT if mode == "current" else Mode.SPEED).value,
              "i_d_ref": -3000, "i_q_ref": 9000, "pi_speed_lim_lo": -4000,
              "pi_speed_lim_hi": 7000, "speed_ref": 1 << 28, "pi_speed_kp": 1 << 12,
              "prot_mask": 1 << FAULTS.index("external"),
              **{f"scope_chan{c}": codes.index("i_q_ref" if c % 2 else "i_d_ref")
                 for c in range(4)}}
    top = Top(pwm_hz=PWM / 2, baud=BAUD, current_loop="engine", regs_staging="bram",
              speed_loop="engine", resets=resets)
    cl, servo, scope = top._loop, top._servo, top._scope
    assert scope.ram_sources == STATUS + ("i_d_ref", "i_q_ref")
    assert not hasattr(top._regs, "i_d_ref") and not hasattr(cl, "iq_ref")

    dones = []

    def probe(ctx):
        if ctx.get(cl.done):
            dones.append(host.clocks)
        if trip == "mid" and ctx.get(cl.count) == 5 and ctx.get(cl.busy):
            ctx.set(top.fault_n, 0)                 # in the sixth pass: a driver fault
        # "edge": the pin so that the mode falls in the clock after the sixth pass's done
        # (passes a period apart; pin → Servo.enable 3 clocks here): the scope's channel 1
        # must still read the references (the mode of the clock before), channel 2 on 0.
        if trip == "edge" and len(dones) == 5 and host.clocks == dones[4] + top.pwm_period - 3:
            ctx.set(top.fault_n, 0)
        return (ctx.get(cl.done), ctx.get(scope.ram_rd.addr), ctx.get(scope.ram_rd.data),
                ctx.get(servo.enable) & ~ctx.get(servo.ol_enable), ctx.get(servo.active).value,
                ctx.get(cl.speed_o.payload), ctx.get(cl.probe_memory.data[len(STATUS)]),
                ctx.get(cl.probe_memory.data[len(STATUS) + 1]))
    host = _TracingHost(_Bench(top, BAUD), probe)

    async def testbench(ctx):
        ctx.set(top.hall, HALL_OK)
        ctx.set(top.fault_n, 1)
        await host.write(ctx, _addr(top, "scope_arm"), 1)       # (the scope latches sel)
        await host.tick(ctx, 8 * top.pwm_period)

    simulate(host.bench, [testbench], name=f"test_top_scope_refs_{mode}")
    done, addr, data, run, active, sl_iq, w_id, w_iq = (np.array(c) for c in zip(*host.trace))
    checked, masked = {8: 0, 9: 0}, 0
    for t in np.flatnonzero(done):
        for c in range(t, t + 4):
            a = int(addr[c])
            if a not in checked:
                continue
            checked[a] += 1
            if not run[c - 1]:
                want = 0
            elif a == 8:
                want = -3000
            elif active[c - 1] == Mode.CURRENT.value:
                want = 7000                                 # clamp(9000, −4000, 7000)
            else:
                want = int(sl_iq[c - 1])
            assert data[c + 1] == want, (t, c, a, int(data[c + 1]), want)
            masked += not run[c - 1] and (w_id[c] if a == 8 else w_iq[c]) != 0
    assert min(checked.values()) >= 6 and masked >= 2
    if trip == "edge":
        fall = int(np.flatnonzero(run[1:] < run[:-1])[0]) + 1
        assert fall == np.flatnonzero(done)[5] + 1 and addr[fall] == 9 and data[fall + 1] != 0
    assert run[:len(run) // 2].any() and not run[-1]           # tripped in the end
    if mode == "speed":
        assert len({int(v) for v in sl_iq[run.astype(bool)]}) >= 2


def test_top_speed_reaches_lead_angle_and_overspeed_one_clock_after_mt():
    """LeadAngle and the protection's overspeed check take M/T's result through a register, the
    strobe too (ECP5 Fmax; Top docstring, "The speed's consumers"), clock by clock: their
    ``start`` / ``valid`` is ``mt.o.valid`` of the clock before with the speed of that clock
    (LeadAngle's rounded to Q1.15);
    θ_lead follows ``1 + LeadAngle.latency`` clocks after ``mt.o.valid``, the overspeed fault
    (limit below the speed) ``1 + Protection.latency`` clocks after the first nonzero speed."""
    from foc_servo.hdl.protect import Protection
    k = 0x4000
    top = Top(pwm_hz=250e3, baud=BAUD,
              resets={"theta_lead": k, "prot_os_limit": 1 << 28})    # N_FS/8 = 1500 r/min
    lead, prot, mt = top._lead, top._protect, top._mt
    rec = []

    async def testbench(ctx):
        ctx.set(top.hall, HALL_OK)
        ctx.set(top.fault_n, 1)
        for _ in range(1500):
            rec.append((ctx.get(mt.o.valid), ctx.get(mt.o.payload.speed),
                        ctx.get(lead.start), ctx.get(lead.n), ctx.get(lead.theta),
                        ctx.get(prot.speed.valid), ctx.get(prot.speed.payload),
                        ctx.get(prot.present.overspeed)))
            await ctx.tick()

    simulate(top, [testbench], [_encoder_process(top, 25)], name="test_top_speed_consumers")
    valid, speed, start, lead_n, theta, pvalid, pspeed, os_ = (np.array(c) for c in zip(*rec))
    np.testing.assert_array_equal(start[1:], valid[:-1])
    np.testing.assert_array_equal(pvalid[1:], valid[:-1])
    np.testing.assert_array_equal(lead_n[1:], [_lead_n(int(v)) for v in speed[:-1]])
    np.testing.assert_array_equal(pspeed[1:], speed[:-1])
    strobes = np.flatnonzero(valid)
    fast = [t for t in strobes if speed[t] > 1 << 28]
    assert len(strobes) >= 4 and fast, "M/T must measure a speed above the limit"
    for t in strobes:
        if t + 1 + LeadAngle.latency < len(rec):
            assert theta[t + 1 + LeadAngle.latency] == _lead_model(int(speed[t]), k)
    t = fast[0]
    assert not os_[:t + 1 + Protection.latency].any()
    assert os_[t + 1 + Protection.latency]


@pytest.mark.parametrize("limits", ["ram", "ram16"])
def test_top_prot_limits_ram_overspeed_from_a_host_write(limits):
    """``prot_limits="ram"`` (the iCE40's): a host write of ``prot_os_limit`` reaches the
    protection's limit RAM through the register file's mirror port (one write, in the clock
    after the access); the overspeed fault rises ``1 + step_latency["overspeed"]`` clocks after
    the first M/T result above the limit after it (one clock more than the limit ports'
    ``1 + Protection.latency``), and not before."""
    top = Top(pwm_hz=250e3, baud=BAUD, regs_staging="bram", prot_limits=limits)
    bench = _Bench(top, BAUD)
    host = _Host(bench)
    prot, mt, regs = top._protect, top._mt, top._regs
    rec = []
    done = []

    async def testbench(ctx):
        ctx.set(top.hall, HALL_OK)
        ctx.set(top.fault_n, 1)
        await host.write(ctx, _addr(top, "prot_os_limit"), 1 << 28)   # N_FS/8
        await host.tick(ctx, 1500)
        done.append(1)

    async def recorder(ctx):
        while not done:
            rec.append((ctx.get(mt.o.valid), ctx.get(mt.o.payload.speed),
                        ctx.get(prot.present.overspeed), ctx.get(regs.mirror.valid),
                        ctx.get(regs.mirror.index), ctx.get(regs.mirror.data)))
            await ctx.tick()

    simulate(bench, [testbench, recorder], [_encoder_process(top, 25)], name="test_top_prot_ram")
    valid, speed, os_, m_valid, m_index, m_data = (np.array(c) for c in zip(*rec))
    writes = np.flatnonzero(m_valid)
    # the power-up walk's four words, then the host's one
    assert [(int(m_index[t]), int(m_data[t])) for t in writes] == [
        (0, 0xFFFF), (1, 0x7FFF), (2, 0xFFFF8000), (3, 0xFFFF_FFFF), (3, 1 << 28)]
    w = writes[-1]
    fast = [t for t in np.flatnonzero(valid) if speed[t] > 1 << 28 and t > w]
    assert fast, "M/T must measure a speed above the limit"
    t = fast[0]
    late = 1 + prot.step_latency["overspeed"]
    assert late == 3
    assert not os_[:t + late].any()
    assert os_[t + late]


def test_top_current_loop_latches_the_servo_references_a_clock_late():
    """The current loop's ``id_ref`` / ``iq_ref`` are the Servo's of the clock before, the
    registers the trace records (ECP5 Fmax; Top docstring, "References"), clock by clock while
    the register file's references change every clock in CURRENT mode (clamped by the Servo)."""
    top = Top(pwm_hz=250e3, baud=BAUD, resets={"mode": Mode.CURRENT.value,
                                               "pi_speed_lim_lo": -12000,
                                               "pi_speed_lim_hi": 11000})
    servo, cl, src, regs = top._servo, top._loop, top._scope.src, top._regs
    rng = np.random.default_rng(11)
    rec = []

    async def testbench(ctx):
        ctx.set(top.hall, HALL_OK)
        ctx.set(top.fault_n, 1)
        for _ in range(3 * top.pwm_period):
            ctx.set(regs.i_q_ref, int(rng.integers(-1 << 15, 1 << 15)))
            ctx.set(regs.i_d_ref, int(rng.integers(-1 << 15, 1 << 15)))
            rec.append((ctx.get(servo.iq_ref), ctx.get(servo.id_ref), ctx.get(cl.iq_ref),
                        ctx.get(cl.id_ref), ctx.get(src.i_q_ref), ctx.get(src.i_d_ref),
                        ctx.get(servo.active).value))
            await ctx.tick()

    simulate(top, [testbench], name="test_top_references")
    s_iq, s_id, c_iq, c_id, t_iq, t_id, active = (np.array(c) for c in zip(*rec))
    np.testing.assert_array_equal(c_iq[1:], s_iq[:-1])
    np.testing.assert_array_equal(c_id[1:], s_id[:-1])
    np.testing.assert_array_equal(t_iq, c_iq)
    np.testing.assert_array_equal(t_id, c_id)
    current = active == Mode.CURRENT.value
    assert current.sum() > top.pwm_period                    # the references moved each clock
    assert s_iq[current].min() == -12000 and s_iq[current].max() == 11000
    assert len(set(s_id[current])) > top.pwm_period // 2


# --- status registers -------------------------------------------------------------------------

def _bitbang(byte, stop=1):
    """UART levels of one byte, one per bit: start, 8 data bits LSB first, stop."""
    return [0] + [(byte >> k) & 1 for k in range(8)] + [stop]


def _uart_host(bench, wire, per_bit):
    """A host on ``bench``'s UART: ``replies()`` decodes the frames in ``wire`` (the bytes a
    monitor collected), ``send(ctx, data, bad_stop=None)`` bit-bangs bytes (byte ``bad_stop``
    with a framing error), ``reply(ctx, n)`` waits up to 8000 clocks for the n-th reply."""
    def replies():
        return [decode_reply(cobs_decode(bytes(r))[:-2]) for r in wire.split(b"\x00")[:-1]]

    async def send(ctx, data, bad_stop=None):
        for k, byte in enumerate(data):
            bits = _bitbang(byte, stop=0 if k == bad_stop else 1) + ([1] if k == bad_stop else [])
            for level in bits:
                ctx.set(bench.inject, level)
                await ctx.tick().repeat(per_bit)

    async def reply(ctx, n):
        for _ in range(400):                    # up to 8000 clocks: 100 reply bytes
            if len(replies()) >= n:
                return replies()[n - 1]
            await ctx.tick().repeat(20)
        raise AssertionError(f"no reply {n}")

    return replies, send, reply


def test_top_status_registers_read_provoked_values():
    """Every status register the top adds reads a provoked value. At reset (``resets``): current
    mode, references of I_FS/2 against 0 A measured and K_p ≈ 256 (both PIs saturate at their
    ±√3/2 limits: |u| = 1.22, beyond the hexagon once the DC-bus gain limit 2 applies to the 0 V
    bus), an invalid encoder configuration (0 lines), the under-voltage check on. A 40-clock
    PWM period is shorter than an ADC conversion (48 clocks): every other sample strobe is
    dropped. Over the link: a bad-CRC frame, a damaged (framing)
    frame, a bad-address read, then the read of the status block, then a frame sent while the
    link is busy replying (dropped)."""
    per_bit = round(CLK / BAUD)
    top = Top(pwm_hz=1.25e6, baud=BAUD, dead_time_s=0.1e-6, resets={
        "mode": Mode.CURRENT.value, "i_d_ref": 1 << 14, "i_q_ref": 1 << 14, "pi_d_kp": 0xFFFF,
        "pi_q_kp": 0xFFFF, "enc_lines": 0, "prot_uv_enable": 1})
    assert top.pwm_period == 40 and top._adc.latency + 1 > 40
    bench = _Bench(top, BAUD)
    regs = top._regs
    wire = bytearray()
    count = {"strobes": 0, "cs_falls": 0, "conversions": 0}
    seen = {}

    async def monitor(ctx):
        while True:
            *_, byte = await ctx.posedge(bench.host_rx.o.valid).sample(bench.host_rx.o.payload)
            wire.append(byte)

    async def strobes(ctx):
        while True:
            await ctx.posedge(top._timer.sample)
            count["strobes"] += 1

    async def conversions(ctx):
        # At the ADC pins: CS falls twice per conversion (convert pulse, then the read frame).
        while True:
            await ctx.negedge(top.adc_cs_n)
            count["cs_falls"] += 1
            count["conversions"] = (count["cs_falls"] + 1) // 2

    replies, send, reply = _uart_host(bench, wire, per_bit)

    async def testbench(ctx):
        ctx.set(top.hall, HALL_OK)
        await ctx.tick().repeat(200)
        payload = encode_request(Command.READ, 1, _addr(top, "st_trip"), 1)
        bad_crc = (crc16(payload) ^ 0x0100).to_bytes(2, "big")
        await send(ctx, b"\x00" + cobs_encode(payload + bad_crc) + b"\x00")
        seen["r1"] = await reply(ctx, 1)
        await send(ctx, frame(encode_request(Command.PING, 2)), bad_stop=3)
        seen["r2"] = await reply(ctx, 2)
        await send(ctx, frame(encode_request(Command.READ, 3, 0x0FFF, 1)))
        seen["r3"] = await reply(ctx, 3)
        # The status block, then at once a frame that arrives while the link is busy.
        await send(ctx, frame(encode_request(Command.READ, 4, _addr(top, "st_adc_overruns"), 9)))
        seen["lo"] = dict(count)                # the reads happen after the request's end ...
        await send(ctx, frame(encode_request(Command.PING, 5)))
        seen["r4"] = await reply(ctx, 4)
        seen["hi"] = dict(count)                # ... and before the reply
        await ctx.tick().repeat(1000)
        seen["n_replies"] = len(replies())
        seen["link"] = {n: ctx.get(getattr(regs, f"st_link_{n}")) for n in ("frames_ok", "dropped")}
        # Trip: the PIs are cleared, nothing saturates any more, but the flags stay set.
        ctx.set(top.fault_n, 0)
        await ctx.tick().repeat(300)
        seen["tripped"] = ctx.get(regs.st_trip)
        seen["sat_now"] = (ctx.get(top._loop.sat_d), ctx.get(top._loop.overmod))
        seen["flags_held"] = ctx.get(_raw(regs.st_loop_flags))
        ctx.set(regs.clear_faults, 1)           # the strobe's one-clock pulse
        await ctx.tick()
        seen["flags_cleared"] = ctx.get(_raw(regs.st_loop_flags))
        await ctx.tick().repeat(300)
        seen["flags_after"] = ctx.get(_raw(regs.st_loop_flags))

    simulate(bench, [testbench], [monitor, strobes, conversions], name="test_top_status")
    assert seen["r1"].status == ReplyStatus.BAD_CRC and seen["r2"].status == ReplyStatus.BAD_CRC
    assert seen["r3"].status == ReplyStatus.BAD_ADDRESS
    r4 = seen["r4"]
    assert r4.status == ReplyStatus.OK and r4.seq == 4
    adc_overruns, flags, uv_armed, config_error, *link = r4.data
    bit = {f: 1 << i for i, f in enumerate(LOOP_FLAG_FIELDS)}
    # Frames before the read: one BAD_CRC each for the CRC and the framing error, one rejected.
    assert dict(zip(("frames_ok", "crc_errors", "framing_errors", "rejected", "dropped"), link)) \
        == {"frames_ok": 0, "crc_errors": 1, "framing_errors": 1, "rejected": 1, "dropped": 0}
    # ... and after it: the read answered OK, the frame sent during its reply dropped unanswered.
    assert seen["n_replies"] == 4 and seen["link"] == {"frames_ok": 1, "dropped": 1}
    assert flags == bit["overmod"] | bit["sat_d"] | bit["sat_q"] | bit["dc_limited"]
    assert uv_armed == 1 and config_error == 1
    # Dropped strobes = strobes − conversions counted at the pins, between request and reply;
    # a conversion takes longer than a period, so every other strobe is dropped.
    lo, hi = seen["lo"], seen["hi"]
    assert lo["strobes"] - lo["conversions"] - 1 <= adc_overruns
    assert adc_overruns <= hi["strobes"] - hi["conversions"] + 1
    assert lo["strobes"] // 2 - 2 <= adc_overruns <= hi["strobes"] // 2 + 2
    # Sticky until clear_faults (the trip stopped saturation; a 0 V bus still limits the gain).
    assert seen["tripped"] == 1 and seen["sat_now"] == (0, 0)
    assert seen["flags_held"] == flags
    assert seen["flags_cleared"] & ~bit["dc_limited"] == 0
    assert seen["flags_after"] == bit["dc_limited"]


def test_top_engine_config_written_over_the_link_reaches_the_engine_ram():
    """The iCEBreaker's configuration path end to end (engine current loop, ``"bram"`` staging):
    a host frame writes the Clarke gains and offsets and, a frame later, the q-axis PI's gains
    and limits; the register file's export port carries them into the engine's configuration
    RAM, which the program reads. Every sample's outputs are replayed through
    ``CurrentLoopModel`` with each configuration taking effect at the first sample accepted
    after the ``period_start`` whose commit copy follows the frame: bit-identical. The
    same replay with either switch one sample earlier or later differs (the test sees when a
    word arrives, not only that it does). ("After its frame": after the register file's last
    write of the frame, with the commit copy starting after it.)"""
    from foc_servo.hdl.foc_engine import CONFIG, CONFIG_PORTS, STATUS
    from foc_servo.hdl.top import ENGINE_CONFIG
    from foc_servo.sim.models.engine import engine_fields, loop_model_inputs
    from foc_servo.sim.models.foc import CurrentLoopModel
    clk = 33.333e6
    resets = {"mode": Mode.CURRENT.value, "i_d_ref": -3000, "i_q_ref": 9000,
              "pi_d_kp": 0x0480, "pi_q_kp": 0x0600, "pi_d_kx": 0x3000, "pi_q_kx": 0x2000,
              "u_rated": 16000, "enc_lines": 100, "prot_mask": 0x7FF & ~(1 << 10)}
    top = Top(clk_hz=clk, pwm_hz=50e3, baud=clk / 8, current_loop="engine",
              regs_staging="bram", resets=resets)
    cl = top._loop
    assert hasattr(cl, "config")
    bench = _Bench(top, clk / 8)
    rm = top.regmap
    frames = [{"clarke_gain_a": 29000, "clarke_offset_a": -700, "clarke_gain_b": 36000,
               "clarke_offset_b": 450},
              {"pi_q_kp": 0x0C00, "pi_q_kx": 0x0800, "pi_q_lim_lo": -9000,
               "pi_q_lim_hi": 7000}]
    rng = np.random.default_rng(11)
    codes = [(int(rng.integers(-9000, 9000)), int(rng.integers(-9000, 9000)),
              int(rng.integers(12000, 20000)), 0) for _ in range(64)]
    adc = AdcPartModel(cs_n=top.adc_cs_n, sclk=top.adc_sclk, sdo=top.adc_sdo, clk_hz=clk,
                       source=lambda n: codes[n % len(codes)])
    # The sample's inputs at the loop's ports (the configuration is in its RAM, the status
    # outputs in its status RAM: looked up in the testbench, the RAM is made at elaboration).
    ports = {"ia": cl.i.payload.ia, "ib": cl.i.payload.ib, "udc": cl.i.payload.udc,
             **{f: getattr(cl, f) for f in engine_fields() + ("u_rated", "scale")
                if f not in ("ia", "ib", "udc") and hasattr(cl, f)}}
    outs = {"duty_a": cl.o.payload.a, "duty_b": cl.o.payload.b, "duty_c": cl.o.payload.c,
            **{f: getattr(cl, f) for f in ("i_alpha", "i_beta", "i_d", "i_q", "u_d", "u_q",
                                           "u_alpha", "u_beta", "sat_d", "sat_q")
               if f not in STATUS}}
    bus = top._regs.bus
    ins, got, accepted, starts, writes, replied = [], [], [], [], [], []

    def probe(ctx):
        clock = host.clocks
        if ctx.get(bus.stb) and ctx.get(bus.we) and ctx.get(bus.ack):
            writes.append(clock)
        if ctx.get(top._timer.period_start):
            starts.append(clock)
        if ctx.get(cl.i.valid):
            ins.append({f: ctx.get(p) for f, p in ports.items()})
            accepted.append(clock)
        if ctx.get(cl.o.valid):
            got.append({f: ctx.get(p) for f, p in outs.items()})
    host = _TracingHost(bench, probe)

    async def testbench(ctx):
        outs.update({f: cl.status_memory.data[j] for j, f in enumerate(STATUS)})
        ctx.set(top.hall, HALL_OK)
        await host.tick(ctx, 3 * top.pwm_period)
        for values in frames:
            addr = _addr(top, next(iter(values)))
            assert [_addr(top, n) for n in values] == list(range(addr, addr + len(values)))
            await host.write(ctx, addr, *(rm[n].to_words(v)[0] for n, v in values.items()))
            replied.append(host.clocks)
            await host.tick(ctx, 3 * top.pwm_period)

    simulate(bench, [testbench], [adc.process], clock_hz=clk, name="test_top_engine_config")
    assert len(got) >= len(ins) - 1 >= 12
    # The configuration in force: the reset values, then each frame from its commit on.
    port_of = {reg: CONFIG_PORTS[s] for s, reg in zip(CONFIG, ENGINE_CONFIG)}
    config = {port_of[reg]: rm[reg].reset for reg in ENGINE_CONFIG}
    switches = []
    for t in replied:
        # The frame's last register write; the commit copy that starts after it (the copy's
        # first clock is commit_clocks before its period_start).
        w = max(c for c in writes if c < t)
        commit = next(s for s in starts if s - top.commit_clocks > w)
        switches.append(next(i for i, a in enumerate(accepted) if a > commit))
    assert switches[0] < switches[1] < len(got)
    recorded = {f: np.array([s[f] for s in ins[:len(got)]]) for f in ins[0]}
    assert set(recorded) | set(config) >= set(engine_fields())

    def replay(at):
        cfg = {f: np.full(len(got), v) for f, v in config.items()}
        for k, values in zip(at, frames):
            for n, v in values.items():
                cfg[port_of[n]][k:] = v
        return CurrentLoopModel().run(**loop_model_inputs({**recorded, **cfg}))

    def matches(ref):
        return all([g[f] for g in got] == list(ref[f]) for f in outs)

    assert matches(replay(switches))
    for j in range(2):
        for d in (-1, 1):
            moved = list(switches)
            moved[j] += d
            assert not matches(replay(moved)), (j, d)


@pytest.mark.parametrize("current_loop, speed_loop", [("engine", "sequential"),
                                                      ("pipelined", "sequential"),
                                                      ("engine", "engine")])
def test_top_bram_speed_loop_configuration_written_through_the_register_file(current_loop,
                                                                              speed_loop):
    """``regs_staging="bram"``: the speed loop's gains, slew and feed-forward
    (:data:`SPEED_LOOP_CONFIG`) have no flip-flops in the register file; its export port writes them into the speed loop's
    configuration RAM (``Servo(config="ram")``, the export's words after the engine's), from the
    reset walk (no speed-loop run starts in it) and from each commit copy. Host writes of
    ``pi_speed_kp``, ``pi_speed_kx``, ``speed_slew`` and ``speed_ff_iq`` reach the loop at a
    period start, and
    the Servo's outputs are the model's clock by clock, the model taking what the export port
    wrote; read-back returns the written values. ``speed_loop="engine"`` (the iCEBreaker's):
    the words go into the loop engine's configuration RAM after its own, the speed run's inputs
    are the engine's ports, and the model is :class:`ServoModel` with the engine's timing."""
    from foc_servo.hdl.servo import SPEED_CONFIG
    from foc_servo.hdl.top import ENGINE_CONFIG, ENGINE_REFS, SPEED_LOOP_CONFIG
    from foc_servo.sim.models.servo import SERVO_INPUTS, ServoModel
    REF = (1 << 30) + (1 << 26)         # the encoder's 6000 r/min = 2^30 of N_FS, + 375 r/min
    eng = speed_loop == "engine"
    top = Top(pwm_hz=PWM if not eng else PWM / 2, baud=BAUD, current_loop=current_loop,
              regs_staging="bram", speed_loop=speed_loop, resets={
                  "mode": Mode.SPEED.value, "speed_ref": REF, "pi_speed_kp": 1 << 12,
                  "pi_speed_lim_lo": -9000, "pi_speed_lim_hi": 9000, "prot_mask": 0})
    regs, servo, rm, cl = top._regs, top._servo, top.regmap, top._loop
    names = [r.name for _, r, _ in regs.export_words]
    engine = (ENGINE_CONFIG + (ENGINE_REFS if eng else ()) if current_loop == "engine"
              else ())
    assert names == list(engine + SPEED_LOOP_CONFIG)
    assert not any(hasattr(regs, n) for n in SPEED_LOOP_CONFIG)
    assert servo.config_mode == ("ports" if eng else "ram") and servo.speed_loop == speed_loop
    config = dict(zip(SPEED_CONFIG, ("speed_kp", "speed_kx", "speed_slew", "iq_ff")))
    at_engine = {"speed_valid": "speed_valid", "speed": "speed", "speed_ref": "speed_ref",
                 "speed_rate_div": "speed_rate_div", "speed_ref_delay": "speed_ref_delay",
                 "speed_int_hold": "speed_int_hold"}
    ins = {n: getattr(cl, at_engine[n]) if eng and n in at_engine else
           servo.speed.valid if n == "speed_valid" else
           servo.speed.payload.speed if n == "speed" else getattr(servo, n)
           for n in SERVO_INPUTS if n not in config.values()}
    cfg = cl.config if eng else servo.speed_config
    off_cfg = len(ENGINE_CONFIG + ENGINE_REFS) if eng else 0    # the speed words' first index
    params = {k: v for k, v in servo.loop_params.items()
              if k not in ("mul_width", "config", "config_init")}
    if eng:
        params["speed_engine_timing"] = cl.speed_timing
    model = ServoModel(**params)
    outs = list(model.clock({**{n: 0 for n in SERVO_INPUTS}}))      # (a throw-away model)
    model = ServoModel(**params)

    def probe(ctx):
        return ({n: ctx.get(_raw(p)) for n, p in ins.items()},
                (ctx.get(cfg.valid), ctx.get(cfg.index), ctx.get(cfg.data)),
                {n: ctx.get(_raw(getattr(servo, n))) for n in outs})
    host = _TracingHost(bench := _Bench(top, BAUD), probe)
    new = {"pi_speed_kp": 3 << 12, "pi_speed_kx": 1 << 14, "speed_slew": 1 << 24,
           "speed_ff_iq": 700}
    seen = {}

    async def testbench(ctx):
        ctx.set(top.hall, HALL_OK)
        host.trace.append(probe(ctx))                           # clock 0
        for _ in range(3):
            await host.next_period(ctx, top)
        await host.write(ctx, _addr(top, "pi_speed_kp"), new["pi_speed_kp"], new["pi_speed_kx"])
        await host.write(ctx, _addr(top, "speed_slew"), new["speed_slew"], new["speed_ff_iq"])
        seen["read"] = [(await host.read(ctx, _addr(top, n)))[0] for n in new]
        await host.write(ctx, _addr(top, "speed_ref"), REF - (3 << 24))
        for _ in range(5):
            await host.next_period(ctx, top)

    simulate(bench, [testbench], [_encoder_process(top, 25)],
             name=f"test_top_speed_config_{current_loop}_{speed_loop}")
    assert seen["read"] == list(new.values())
    ram = [rm[n].reset for n in SPEED_LOOP_CONFIG]
    # The engine's speed run takes the i_q limits from its RAM too (ENGINE_REFS: not from the
    # Servo's ports, which have no driver there): the model takes the words written.
    at_lim = {names.index(f"pi_speed_lim_{s}"): f"iq_lim_{s}" for s in ("lo", "hi")
              if eng}
    lims = {port: rm[names[j]].reset for j, port in at_lim.items()}
    runs, mismatches, writes = [], [], []
    for t, (i, (valid, index, data), got) in enumerate(host.trace):
        want = model.clock({**i, **dict(zip(config.values(), ram)), **lims})
        if valid and index in at_lim:
            lims[at_lim[index]] = data - ((data >> 31) << 32)
        if want != got:
            mismatches.append((t, got, want))
        if got["speed_valid"]:
            runs.append((t, dict(zip(SPEED_CONFIG, ram)), got["iq_ref"], got["speed_ref_int"]))
        if valid and index >= off_cfg:
            writes.append((t, index - off_cfg, data))
            ram[index - off_cfg] = data
    assert not mismatches, mismatches[0]
    # The reset walk's words first (no run in it), then every period's copy; the new values
    # from the period after the writes.
    assert writes[0][0] < runs[0][0] and len(runs) >= 5
    assert runs[0][1] == {"kp": 1 << 12, "kx": 0, "speed_slew": 0, "iq_ff": 0}
    assert runs[-1][1] == dict(zip(SPEED_CONFIG, new.values()))
    # kp 1 (the encoder's speed is exactly 2^30): i_q = 2^26 / 2^16 = 1024; kp 3 with kx 1/64
    # from the period after the writes: 3072 + 32 per run; then the reference ramps by the
    # slew, 2^24 per run, to the new speed_ref (with the feed-forward −700 while it moves).
    iq = [r[2] for r in runs]
    k = next(j for j, r in enumerate(runs) if r[1]["kp"] != 1 << 12)
    assert k >= 3 and iq[:k] == [1024] * k and iq[k:k + 3] == [3104, 3136, 3168]
    ramp = [r[3] - REF for r in runs if r[3] != REF]
    assert ramp[:3] == [-(1 << 24), -(2 << 24), -(3 << 24)]
    assert len(ramp) > 3 and set(ramp[3:]) == {-(3 << 24)}
    # The feed-forward counts: the same trace with speed_ff_iq left at 0 is not the model's.
    model, ram, off = ServoModel(**params), [rm[n].reset for n in SPEED_LOOP_CONFIG], 0
    lims = {port: rm[names[j]].reset for j, port in at_lim.items()}
    for i, (valid, index, data), got in host.trace:
        off += model.clock({**i, **dict(zip(config.values(), ram)), **lims, "iq_ff": 0}) != got
        if valid and index >= off_cfg:
            ram[index - off_cfg] = data
    assert off > 0


@pytest.mark.parametrize("staging", ["ff", "bram"])
def test_top_mode_write_reaches_the_servo_one_period_earlier_with_bram_staging(staging):
    """A host frame writing ``mode`` whose ``lock`` falls before the copy window of the next
    period boundary ``p``: with ``"ff"`` the commit is in ``p`` and the Servo's loop strobe in
    ``p`` still sees the old mode, so its active mode (the gates, the current and speed loops)
    changes at the strobe one period later, ``p + 2N``; with ``"bram"`` the copy ends in ``p``
    and the strobe in ``p`` takes the new mode: the same write acts one PWM period earlier
    (module docstring, "Register commit with regs_staging="bram""; docs/AREA.md §7.60: the
    reason ``sim step``'s ss_err_pct differs between the two)."""
    top = Top(pwm_hz=PWM, baud=BAUD, regs_staging=staging)
    bench = _Bench(top, BAUD)
    regs, servo, timer = top._regs, top._servo, top._timer

    def probe(ctx):
        return (ctx.get(timer.period_start), ctx.get(regs.bus.lock),
                ctx.get(servo.active).value)
    host = _TracingHost(bench, probe)

    async def testbench(ctx):
        ctx.set(top.hall, HALL_OK)
        await host.next_period(ctx, top)
        await host.write(ctx, _addr(top, "mode"), Mode.OPEN_LOOP.value)
        for _ in range(3):
            await host.next_period(ctx, top)

    simulate(bench, [testbench], name=f"test_top_mode_write_{staging}")
    trace = host.trace
    n2 = top.pwm_period
    last_lock = max(t for t, c in enumerate(trace) if c[1])
    p = next(t for t, c in enumerate(trace) if c[0] and t > last_lock)
    assert p - top.commit_clocks > last_lock + 1        # the copy window after the frame
    changed = next(t for t, c in enumerate(trace) if c[2] == Mode.OPEN_LOOP.value)
    assert all(c[2] == Mode.DISABLED.value for c in trace[:changed])
    # (trace[t] is sampled after clock t's edge: the strobe in p loads the mode seen in p + 1.)
    assert changed == (p + 1 if staging == "bram" else p + n2 + 1), (staging, changed - p)


@pytest.mark.parametrize("staging", ["ff", "bram"])
def test_top_reference_writes_strobe_ref_step_at_the_loop_that_sees_them(staging):
    """The Servo's ``ref_step`` (module docstring, "Scope trigger"): one per host frame that
    writes the mode or a reference, at the first loop strobe (``period_start``) that sees the
    written value ("ff": the one after the commit; "bram": the commit's own), a write of an
    unchanged value included; none for a frame writing other registers; the scope's trigger is
    ``ref_step`` a clock later."""
    top = Top(pwm_hz=PWM, baud=BAUD, regs_staging=staging)
    bench = _Bench(top, BAUD)
    regs, servo = top._regs, top._servo

    def probe(ctx):
        return (ctx.get(top._timer.period_start), ctx.get(servo.ref_step),
                ctx.get(top._scope.trigger), ctx.get(regs.i_q_ref), ctx.get(regs.speed_ref))
    host = _TracingHost(bench, probe)
    frames = []                                 # (first clock, last clock) of each write

    async def write(ctx, name, *words):
        start = host.clocks
        await host.write(ctx, _addr(top, name), *words)
        frames.append((start, host.clocks))
        for _ in range(3):                      # the commit and the loop strobe after it
            await host.next_period(ctx, top)

    async def testbench(ctx):
        ctx.set(top.hall, HALL_OK)
        await host.next_period(ctx, top)
        await write(ctx, "i_q_ref", 1000)                       # a new value
        await write(ctx, "i_q_ref", 1000)                       # the same value again
        await write(ctx, "ol_angle", 0x1234, 0x5678)            # not a reference: no step
        await write(ctx, "speed_ref", 1 << 24)                  # a new value
        await write(ctx, "i_d_ref", 5, 0xFFFF & -7)             # i_d_ref, i_q_ref: one step

    simulate(bench, [testbench], name="test_top_ref_step")
    trace = host.trace
    steps = [t for t, c in enumerate(trace) if c[1]]
    triggers = [t for t, c in enumerate(trace) if c[2]]
    assert triggers == [t + 1 for t in steps]
    assert all(trace[t][0] for t in steps)                      # at loop strobes only
    # One step per reference frame, none for the ol_angle frame.
    per_frame = [[t for t in steps if a <= t < (frames[k + 1][0] if k + 1 < len(frames)
                                                  else len(trace))]
                 for k, (a, _) in enumerate(frames)]
    assert [len(f) for f in per_frame] == [1, 1, 0, 1, 1]
    # Changed values: the step is the first loop strobe at which the active value is the new one.
    for k, col, value in ((0, 3, 1000), (3, 4, 1 << 24), (4, 3, -7)):
        a, _ = frames[k]
        seen = next(t for t in range(a, len(trace)) if trace[t][0] and trace[t][col] == value)
        assert per_frame[k] == [seen], (k, per_frame[k], seen)
    # The unchanged value's step: within two periods of its frame's end (commit, loop strobe).
    assert per_frame[1][0] - frames[1][1] < 2 * top.pwm_period


def test_top_mt_k_from_the_export_port_is_the_flip_flops_clock_for_clock():
    """``mt_k_export`` (the iCEBreaker's): ``mt_k`` has no flip-flops in the register file; its
    two export-port words load three registers that feed M/T's multipliers as they are
    (``MTSpeed(k_steady=True)``). Against the same top with the flip-flops, the same host
    writes (``mt_k`` halved two periods in, read back) and encoder: the same ``k`` at M/T from
    the end of the reset walk on, the same M/T outputs in every clock, and ``k`` steady from
    each accepted update to its result."""
    lat = None
    traces, reads = [], []
    for export in (False, True):
        top = Top(pwm_hz=PWM, baud=BAUD, regs_staging="bram", mt_k_export=export)
        regs, mt = top._regs, top._mt
        assert top.mt_k_export is export and mt.k_steady is export
        names = [r.name for _, r, _ in regs.export_words]
        assert (names.count("mt_k"), hasattr(regs, "mt_k")) == ((2, False) if export else
                                                                (0, True))
        lat = mt.latency
        k0 = top.regmap["mt_k"].reset
        new = k0 // 2 + 12345

        def probe(ctx, mt=mt, top=top):
            p = ctx.get(mt.o.payload)
            return (ctx.get(mt.k), ctx.get(mt.update), ctx.get(mt.o.valid), p.speed, p.stopped,
                    p.fresh)
        host = _TracingHost(bench := _Bench(top, BAUD), probe)

        async def testbench(ctx, host=host, top=top, new=new):
            ctx.set(top.hall, HALL_OK)
            for _ in range(2):
                await host.next_period(ctx, top)
            await host.write(ctx, _addr(top, "mt_k"), new & 0xFFFF_FFFF, new >> 32)
            reads.append(tuple(await host.read(ctx, _addr(top, "mt_k"), 2)))
            for _ in range(4):
                await host.next_period(ctx, top)

        simulate(bench, [testbench], [_encoder_process(top, 25)],
                 name=f"test_top_mt_k_export_{export}")
        traces.append(host.trace)
    assert reads == [(new & 0xFFFF_FFFF, new >> 32)] * 2
    ff, ex = traces
    n = min(len(ff), len(ex))
    assert n > 6 * top.pwm_period
    walk = top._regs.reset_clocks + 2
    assert all(ex[t][0] == ff[t][0] for t in range(walk, n)), \
        next(t for t in range(walk, n) if ex[t][0] != ff[t][0])
    assert [t[1:] for t in ex[:n]] == [t[1:] for t in ff[:n]]
    ks = [t[0] for t in ex[walk:n]]
    assert ks[0] == k0 and ks[-1] == new    # (and the low word alone for a clock, as the FFs)
    fresh = [t for t in ex[:n] if t[2] and t[5]]
    assert len(fresh) >= 4 and fresh[0][3] != fresh[-1][3]
    # k is steady through every computation (update accepted in u, result in u + latency)
    # after the walk; the one in the walk is a stopped one (its product 0 whatever k).
    valid_at = [t for t in range(n) if ex[t][2]]
    assert all(len({ex[s][0] for s in range(v - lat, v + 1)}) == 1
               for v in valid_at if v - lat >= walk)
    assert all(ex[v][4] and ex[v][3] == 0 for v in valid_at if v - lat < walk)
    assert len(valid_at) >= 6
def test_top_link_compact_form_same_ports_clock_by_clock():
    """``Top(link_compact=True)`` (the iCEBreaker's link) and the default, fed the same UART
    bits (writes, a burst across the mode registers, reads of the identification words and the
    scope window, a write to a read-only register, a hole, a damaged frame): every output port
    of the two tops is equal in every clock."""
    tops = [Top(pwm_hz=PWM, baud=BAUD, link_compact=c) for c in (False, True)]
    m = Module()
    for k, top in enumerate(tops):
        m.submodules[f"top{k}"] = top
    rx = Signal(init=1)
    m.d.comb += [top.uart_rx.eq(rx) for top in tops]
    outs = [name for name, member in tops[0].signature.members.items()
            if member.is_port and member.flow == wiring.Out]
    t0 = tops[0]
    frames = [
        encode_request(Command.WRITE, 1, _addr(t0, "dead_time"), 1, [37]),
        encode_request(Command.WRITE, 2, _addr(t0, "mode"), 8,
                       [Mode.OPEN_LOOP.value, 0, 0, 0, 0, 0, 1000, 0xFFFF & -2000]),
        encode_request(Command.READ, 3, 0x0000, 8),
        encode_request(Command.READ, 4, 0x1000, 16),
        encode_request(Command.WRITE, 5, _addr(t0, "st_trip"), 1, [1]),
        encode_request(Command.READ, 6, 0x0030, 2),
        encode_request(Command.READ, 7, _addr(t0, "mode"), 8),
    ]
    wire = b"".join(frame(f) for f in frames) + b"\x00\x12\x34\x00"
    per_bit = int(CLK / BAUD)
    bits = []
    for b in wire:
        bits += [0] + [(b >> k) & 1 for k in range(8)] + [1, 1]
    mismatches, seen = [], {"tx": 0}

    async def bench(ctx):
        for t in range(len(bits) * per_bit + 6000):
            ctx.set(rx, bits[t // per_bit] if t // per_bit < len(bits) else 1)
            await ctx.delay(1e-9)
            a = [ctx.get(getattr(tops[0], n)) for n in outs]
            b = [ctx.get(getattr(tops[1], n)) for n in outs]
            seen["tx"] += ctx.get(tops[0].uart_tx) == 0
            if a != b and len(mismatches) < 5:
                mismatches.append((t, [n for n, x, y in zip(outs, a, b) if x != y]))
            await ctx.tick()

    simulate(m, [bench], clock_hz=CLK, name="test_top_link_compact")
    assert mismatches == []
    assert seen["tx"] > 1000                    # the replies went out


def test_top_mt_engine_speed_matches_the_model():
    """``Top(mt_engine=True)``: M/T's window logic (``MTSpeed(arith="engine")``, 27-bit TC)
    with its multiply and divide as the engine's run ``mt`` (``k`` the reset value's two words
    in the engine's configuration RAM), beside the current loop's samples: the edge strobes
    from the encoder pins (forward, a pause of more than two periods, backward, fast forward)
    and the top's update strobes into ``MTSpeedModel`` with the 27-bit TC give every output
    (fresh, bounded, stopped), in the clock ``Top.mt_latency`` after its update (the engine
    idle at ``period_start``)."""
    from foc_servo.hdl.engine_mt import MT_ENGINE_PARAMS
    from foc_servo.sim.models import mt_speed as model

    top = Top(pwm_hz=50e3, baud=BAUD, current_loop="engine", regs_staging="bram",
              mt_k_export=True, mt_chunk_multipliers=False, mt_engine=True)
    mt = top._mt
    assert top.mt_engine and mt.arith == "engine" and mt.tc_width == 27
    assert top.mt_latency == 1 + top._loop.mt_latency == 113
    k = top.regmap["mt_k"].reset
    plan = [(300, 0)] + [(60 + 7 * (i % 5), 1) for i in range(40)]
    plan += [(2600, 0)] + [(70 + 5 * (i % 3), -1) for i in range(30)]
    plan += [(21 + (i % 4), 1) for i in range(40)]
    clock, pos, at = 0, 0, {}
    for dwell, step in plan:
        clock += dwell
        if step:
            pos += step
            at[clock] = pos
    end = clock + 2000
    r = record_top_mt(top, at, end, hall=HALL_OK, name="test_top_mt_engine",
                      extra=(("cl_start", top._loop.done),))
    assert r["cl_start"].sum() >= 10                    # the current loop ran beside it
    edges = np.flatnonzero(r["step"])
    ups = np.flatnonzero(r["update"])
    assert len(edges) == 110 and 0 < r["neg"][edges].sum() < len(edges)

    @dataclasses.dataclass(frozen=True)
    class Params(model.MTParams):
        @property
        def latency(self):
            return top.mt_latency

    params = Params(1, MT_ENGINE_PARAMS["tc_width"], 32, 48, 16)
    want = model.simulate(edges, r["neg"][edges].astype(bool), ups, k=k, params=params,
                          end_cycle=end)
    got_v = np.flatnonzero(r["valid"])
    np.testing.assert_array_equal(got_v, want["cycle"])
    np.testing.assert_array_equal(got_v - want["update"], top.mt_latency)
    for f in ("speed", "stopped", "fresh"):
        np.testing.assert_array_equal(r[f][got_v], want[f], err_msg=f)
    kinds = set(zip(want["stopped"].tolist(), want["fresh"].tolist()))
    assert kinds == {(1, 0), (0, 1), (0, 0)}, kinds
    assert (want["speed"] < 0).any() and (want["speed"] > 0).any()


def test_top_mt_engine_with_the_speed_run_same_pins_clock_by_clock():
    """The iCEBreaker's configuration (the speed loop on the engine, its references in the
    engine's RAM) with ``mt_engine`` against the same top with M/T's own arithmetic, in SPEED
    mode with the encoder turning: every output pin equal in every clock (the M/T result
    ``Top.mt_latency`` − ``MTSpeed.latency`` clocks later, the speed run after it, its i_q
    reference still before the centred sample), the M/T speeds and the speed run's i_q
    references the same values in the same order (one run more after the reset, below)."""
    from foc_servo.hdl.protect import FAULTS
    resets = {"mode": Mode.SPEED.value, "pi_speed_lim_lo": -4000, "pi_speed_lim_hi": 7000,
              "speed_ref": 1 << 28, "pi_speed_kp": 1 << 12,
              "prot_mask": 1 << FAULTS.index("external")}
    kw = dict(pwm_hz=PWM / 2, baud=BAUD, current_loop="engine", regs_staging="bram",
              speed_loop="engine", resets=resets, mt_k_export=True)
    tops = [Top(**kw), Top(**kw, mt_chunk_multipliers=False, mt_engine=True)]
    assert [t.mt_engine for t in tops] == [False, True]
    assert tops[1].mt_latency - tops[0].mt_latency == 75
    m = Module()
    for k, top in enumerate(tops):
        m.submodules[f"top{k}"] = top
    outs = [name for name, member in tops[0].signature.members.items()
            if member.is_port and member.flow == wiring.Out]
    seen = {"mismatch": None, "clocks": 0, "speeds": ([], []), "iq": ([], []), "gates": 0}

    async def testbench(ctx):
        states = ((0, 0), (1, 0), (1, 1), (0, 1))
        for top in tops:
            ctx.set(top.hall, HALL_OK)
            ctx.set(top.fault_n, 1)
        pos, nxt = 0, 0
        for c in range(12 * tops[0].pwm_period):
            if c == nxt:                # fast forward, then slowly backward
                fast = c < 5 * tops[0].pwm_period
                pos += 1 if fast else -1
                nxt += 37 if fast else 240
            a, b = states[pos % 4]
            for top in tops:
                ctx.set(top.enc_a, a)
                ctx.set(top.enc_b, b)
            got = [[ctx.get(getattr(top, n)) for n in outs] for top in tops]
            if got[0] != got[1] and seen["mismatch"] is None:
                seen["mismatch"] = (c, [(n, x, y) for n, x, y in zip(outs, *got) if x != y])
            seen["gates"] += got[0][outs.index("gate_h")] != 0
            for k, top in enumerate(tops):
                if ctx.get(top._mt.o.valid):
                    seen["speeds"][k].append(ctx.get(top._mt.o.payload.speed))
                if ctx.get(top._loop.speed_o.valid):
                    seen["iq"][k].append(ctx.get(top._loop.speed_o.payload))
            seen["clocks"] += 1
            await ctx.tick()

    simulate(m, [testbench], name="test_top_mt_engine_speed_run")
    assert seen["mismatch"] is None, seen["mismatch"]
    n = min(len(seen["speeds"][0]), len(seen["speeds"][1]))
    assert n >= 10 and seen["speeds"][0][:n] == seen["speeds"][1][:n]
    # One speed run more after the reset: M/T's first (stopped) result falls in the register
    # file's reset walk (which holds off the speed run) 38 clocks after the first
    # period_start, mt_engine's 113 clocks after it, past the walk's 72: a speed run then.
    assert tops[0].mt_latency < tops[0]._regs.reset_clocks < tops[1].mt_latency
    iq0, iq1 = seen["iq"][0], seen["iq"][1][1:]
    n = min(len(iq0), len(iq1))
    assert n >= 8 and iq0[:n] == iq1[:n]
    assert len(set(iq0)) >= 2 and seen["gates"] > 0
    assert min(seen["speeds"][0]) < 0 < max(seen["speeds"][0])


def test_top_mt_engine_parameters_and_the_speed_run_check():
    """``mt_engine``'s needs (clear errors) and the speed-run check with its latency: half a
    PWM period must exceed ``mt_latency + 1 + speed_latency`` (347 clocks: 47.9 kHz at
    33.333 MHz passes, 48.5 kHz fails; without ``mt_engine`` 38 + 1 + 233)."""
    kw = dict(clk_hz=33.333e6, current_loop="engine", regs_staging="bram", speed_loop="engine",
              mt_k_export=True, mt_chunk_multipliers=False, mt_engine=True)
    top = Top(pwm_hz=47.9e3, **kw)
    assert top.mt_latency + 1 + top._loop.speed_latency == 347
    with pytest.raises(ValueError, match=r"M/T's latency \+ the speed run \(347 clocks\)"):
        Top(pwm_hz=48.5e3, **kw)
    Top(pwm_hz=48.5e3, **{**kw, "mt_engine": False, "mt_chunk_multipliers": True})
    for bad in ({"mt_k_export": False}, {"mt_chunk_multipliers": True},
                {"current_loop": "pipelined", "speed_loop": "sequential"}):
        with pytest.raises(ValueError, match="Top mt_engine needs current_loop='engine'"):
            Top(pwm_hz=10e3, **{**kw, **bad})
    with pytest.raises(TypeError, match="Top mt_engine must be a bool"):
        Top(pwm_hz=10e3, **{**kw, "mt_engine": 1})
