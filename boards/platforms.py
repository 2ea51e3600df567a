# Ref: issue 7 item 1 (boards: pin maps on real connectors); amaranth-boards platform files
# (icebreaker.py, ulx3s.py, arty_s7.py, atlys.py: connector → FPGA pin tables); Digilent Pmod
# Interface Specification 1.2.0 (12-pin Pmod: I/O 1–4 and 7–10, 5/11 GND, 6/12 VCC).
"""The boards the controller is built for, each with its motor power-stage pin map.

Every board is an amaranth-boards platform plus one :class:`~amaranth.build.Resource`,
``motor``, whose subsignals are named exactly as :class:`~foc_servo.hdl.top.Top`'s pins
(``gate_h``, ``gate_l``, ``fault_n``, ``oc_comp``, ``adc_cs_n``, ``adc_sclk``, ``adc_sdo``,
``enc_a``, ``enc_b``, ``enc_z``, ``hall``): the board top connects them by name. All of them sit
on real connectors of the board (Pmod ports or a pin header), declared with ``conn=`` so the
FPGA pins come from the board's own connector table. The host link uses the board's USB-UART
and ``Top.led`` (bit 0 trip, bit 1 encoder aligned) its first two user LEDs.

Electrical choices (the same on every board, where the FPGA has the pull):

* ``fault_n`` has a pull-down and ``oc_comp`` a pull-up: an unplugged power stage reads as a
  fault, so the gates cannot be enabled without one (fail-safe).
* Encoder and Hall inputs have pull-ups (open-collector sensors).
* Gate outputs have no pull: the FPGA pins float during configuration, so the power stage must
  hold its gate inputs low with its own pull-downs (as every gate-driver board does).

iCE40 I/O has pull-ups only: on the iCEBreaker ``fault_n`` needs an external pull-down on the
power-stage side.

``python -m foc_servo.boards.platforms`` prints the pin tables of docs/BOARDS.md.
"""

from dataclasses import dataclass, field

from amaranth.build import Attrs, Pins, Resource, Subsignal
from amaranth_boards.arty_s7 import ArtyS7_50Platform
from amaranth_boards.atlys import AtlysPlatform
from amaranth_boards.icebreaker import ICEBreakerPlatform
from amaranth_boards.ulx3s import ULX3S_85F_Platform

__all__ = ["MOTOR_PORTS", "Board", "BOARDS", "get_board", "pin_map"]

#: Top's motor-side pins: name → (width, direction), in pin-table order.
MOTOR_PORTS = {
    "gate_h": (3, "o"),
    "gate_l": (3, "o"),
    "fault_n": (1, "i"),
    "oc_comp": (1, "i"),
    "adc_cs_n": (1, "o"),
    "adc_sclk": (1, "o"),
    "adc_sdo": (4, "i"),
    "enc_a": (1, "i"),
    "enc_b": (1, "i"),
    "enc_z": (1, "i"),
    "hall": (3, "i"),
}

#: Which pull each input gets (see the module docstring); outputs get none.
_PULL = {"fault_n": "down", "oc_comp": "up", "enc_a": "up", "enc_b": "up", "enc_z": "up",
         "hall": "up"}


def _motor(pins, conns, io_attrs, pull_attrs):
    """The ``motor`` resource: ``pins`` maps a Top pin to ``(connector key, "pin numbers")``,
    ``conns`` a connector key to its ``(name, number)``; ``pull_attrs`` maps "up"/"down" to the
    family's pull attributes (a missing key: no such pull on this family)."""
    if set(pins) != set(MOTOR_PORTS):
        raise ValueError(f"Motor pin map must cover {sorted(MOTOR_PORTS)}, not {sorted(pins)}")
    subsignals = []
    for name, (width, direction) in MOTOR_PORTS.items():
        conn, numbers = pins[name]
        attrs = pull_attrs.get(_PULL.get(name), {})
        subsignals.append(Subsignal(name, Pins(numbers, dir=direction, conn=conns[conn],
                                               assert_width=width), Attrs(**attrs)))
    return Resource("motor", 0, *subsignals, Attrs(**io_attrs))


@dataclass(frozen=True)
class Board:
    """A board: its amaranth-boards platform and the motor pin map on its connectors.

    Attributes
    ----------
    name : str
        The ``foc-servo build --board`` name.
    title : str
        Board and FPGA, for reports.
    family : str
        ``"ice40"``, ``"ecp5"``, ``"xc7"`` (Spartan-7) or ``"xc6s"`` (Spartan-6): selects the PLL
        and the flow.
    flow : str
        ``"bitstream"`` (open toolchain, run here) or ``"vendor"`` (Vivado / ISE build tree).
    platform_class : type
        The amaranth-boards platform.
    platform_kwargs : dict
        Its constructor arguments.
    motor : Resource
        The ``motor`` resource (module docstring).
    connectors : dict
        Connector ``(name, number)`` → the board's label for it (for the pin tables).
    capacity : dict or None
        Device resources for the ``fits`` check of a vendor flow (``lut``, ``ff``, ``dsp``,
        ``bram_bits``); ``None`` where place-and-route decides.
    notes : tuple of str
        Wiring notes printed under the pin table.
    scope_ram : str
        ``Top(scope_ram=…)``: ``"ice40_spram"`` on a part with ``SB_SPRAM256KA`` (iCE40 UP5K: the
        trace buffer in one SPRAM instead of 16 block RAMs), else ``"bram"``.
    regs_staging : str
        ``Top(regs_staging=…)``: ``"bram"`` where logic is short and block RAM is not (iCE40
        UP5K: the register file's ≈ 600 staging flip-flops in 2 block RAMs; Spartan-7: one
        RAMB18 for ≈ 700 FF and ≈ 400 LUT6, docs/AREA.md "Session 11: Spartan-7"), else
        ``"ff"`` (the ECP5: its Fmax).
    current_loop : str
        The default ``Top(current_loop=…)`` of ``foc-servo build`` for this board (``--current-loop``
        overrides it): ``"engine"`` where LUTs and multipliers are short (iCE40 UP5K: the loop
        engine, 5 SB_MAC16 in the whole top instead of 25), else ``"pipelined"``.
    speed_loop : str
        ``Top(speed_loop=…)`` when the build's current loop is the engine (with block-RAM
        staging): ``"engine"`` where logic is short (iCE40 UP5K: the speed loop as a run of the
        loop engine, no :class:`~foc_servo.hdl.servo.SpeedLoop`; docs/AREA.md §7.57), else
        ``"sequential"`` (the SpeedLoop; also whenever the build runs the pipelined loop).
    clk_hz : float
        The system clock ``foc-servo build`` asks the PLL for when ``--clk-mhz`` is not given,
        Hz: 50 MHz, the paper's 33.333 MHz on the iCE40 UP5K (its logic does not reach 50).
    """
    name: str
    title: str
    family: str
    flow: str
    platform_class: type
    motor: Resource
    connectors: dict
    platform_kwargs: dict = field(default_factory=dict)
    capacity: dict = None
    notes: tuple = ()
    scope_ram: str = "bram"
    regs_staging: str = "ff"
    current_loop: str = "pipelined"
    speed_loop: str = "sequential"
    clk_hz: float = 50e6

    def platform(self, *, file_templates=None):
        """A fresh platform instance with the ``motor`` resource added; ``file_templates``
        (name template → content template) are added to the toolchain's own."""
        cls = self.platform_class
        if file_templates:
            base = cls
            cls = type(base.__name__, (base,), {"file_templates": property(
                lambda platform: {**super(cls, platform).file_templates, **file_templates})})
        platform = cls(**self.platform_kwargs)
        platform.add_resources([self.motor])
        return platform

    @property
    def clock(self):
        """The board oscillator: ``(resource name, frequency in Hz)``."""
        platform = self.platform_class(**self.platform_kwargs)
        return platform.default_clk, platform.default_clk_frequency

    @property
    def reset(self):
        """The board's reset button resource name, or ``None``."""
        return self.platform_class.default_rst


# --- iCEBreaker: iCE40UP5K-SG48, 12 MHz oscillator, FTDI FT2232H channel B UART -------------------
# PMOD1A carries the power stage (gates + its two fault lines), PMOD1B the ADC, PMOD2 the
# encoder and Hall sensors: inputs only, so the snap-off LED/button section (wired to PMOD2) may
# stay attached without any output fighting it.
_ICE40_IO = {"IO_STANDARD": "SB_LVCMOS"}
_ICE40_PULL = {"up": {"PULLUP": 1}}
ICEBREAKER = Board(
    name="icebreaker",
    title="1BitSquared iCEBreaker v1.0 (Lattice iCE40UP5K-SG48)",
    family="ice40",
    flow="bitstream",
    platform_class=ICEBreakerPlatform,
    scope_ram="ice40_spram",
    regs_staging="bram",
    current_loop="engine",
    speed_loop="engine",
    clk_hz=33.333e6,
    connectors={"pmod1a": ("pmod", 0), "pmod1b": ("pmod", 1), "pmod2": ("pmod", 2)},
    motor=_motor({
        "gate_h": ("pmod1a", "1 2 3"), "gate_l": ("pmod1a", "7 8 9"),
        "fault_n": ("pmod1a", "4"), "oc_comp": ("pmod1a", "10"),
        "adc_cs_n": ("pmod1b", "1"), "adc_sclk": ("pmod1b", "4"),
        "adc_sdo": ("pmod1b", "2 3 7 8"),
        "enc_a": ("pmod2", "1"), "enc_b": ("pmod2", "2"), "enc_z": ("pmod2", "3"),
        "hall": ("pmod2", "7 8 9"),
    }, {"pmod1a": ("pmod", 0), "pmod1b": ("pmod", 1), "pmod2": ("pmod", 2)},
        _ICE40_IO, _ICE40_PULL),
    notes=(
        "PMOD2 carries inputs only: the snap-off LED/button section wired to it may stay "
        "attached (its LEDs and buttons then load the encoder/Hall lines: snap it off for "
        "a real motor).",
        "iCE40 I/O has no pull-downs: fit a pull-down (e.g. 10 kΩ) on fault_n on the "
        "power-stage side, so that an unplugged cable reads as a fault.",
        "Red LED (pin 11) = trip, green LED (pin 37) = encoder aligned; UART on the FT2232H "
        "(FPGA pins 6 RX, 9 TX).",
    ),
)

# --- ULX3S 85F: LFE5U-85F-6BG381, 25 MHz oscillator, FT231X USB-UART ------------------------------
_ECP5_IO = {"IO_TYPE": "LVCMOS33"}
_ECP5_PULL = {"up": {"PULLMODE": "UP"}, "down": {"PULLMODE": "DOWN"}}
ULX3S = Board(
    name="ulx3s",
    title="Radiona ULX3S 85F (Lattice LFE5U-85F-6BG381)",
    family="ecp5",
    flow="bitstream",
    platform_class=ULX3S_85F_Platform,
    connectors={"gpio": ("gpio", 0)},
    motor=_motor({
        "gate_h": ("gpio", "0+ 1+ 2+"), "gate_l": ("gpio", "0- 1- 2-"),
        "fault_n": ("gpio", "3+"), "oc_comp": ("gpio", "3-"),
        "adc_cs_n": ("gpio", "4+"), "adc_sclk": ("gpio", "4-"),
        "adc_sdo": ("gpio", "5+ 5- 6+ 6-"),
        "enc_a": ("gpio", "7+"), "enc_b": ("gpio", "7-"), "enc_z": ("gpio", "8+"),
        "hall": ("gpio", "8- 9+ 9-"),
    }, {"gpio": ("gpio", 0)}, _ECP5_IO, _ECP5_PULL),
    notes=(
        "Connector pins n+ / n- are the GPIO header's GPn / GNn (silkscreen); each high-side "
        "gate shares a differential pair with its low side.",
        "LED 0 (B2) = trip, LED 1 (C2) = encoder aligned; UART on the FT231X (FPGA pins M1 RX, "
        "L4 TX).",
    ),
)

# --- Arty S7-50: XC7S50-1CSGA324, 100 MHz oscillator, FT2232HQ USB-UART ---------------------------
# JA: power stage; JB: ADC (a high-speed port: the 25 MHz SCLK and the four SDO lines);
# JD: encoder and Hall. JC stays free.
_XC_IO = {"IOSTANDARD": "LVCMOS33"}
_XC_PULL = {"up": {"PULLUP": "TRUE"}, "down": {"PULLDOWN": "TRUE"}}
ARTY_S7 = Board(
    name="arty_s7",
    title="Digilent Arty S7-50 (Xilinx XC7S50-1CSGA324)",
    family="xc7",
    flow="vendor",
    platform_class=ArtyS7_50Platform,
    connectors={"ja": ("pmod", 0), "jb": ("pmod", 1), "jd": ("pmod", 3)},
    motor=_motor({
        "gate_h": ("ja", "1 2 3"), "gate_l": ("ja", "7 8 9"),
        "fault_n": ("ja", "4"), "oc_comp": ("ja", "10"),
        "adc_cs_n": ("jb", "1"), "adc_sclk": ("jb", "4"),
        "adc_sdo": ("jb", "2 3 7 8"),
        "enc_a": ("jd", "1"), "enc_b": ("jd", "2"), "enc_z": ("jd", "3"),
        "hall": ("jd", "7 8 9"),
    }, {"ja": ("pmod", 0), "jb": ("pmod", 1), "jd": ("pmod", 3)}, _XC_IO, _XC_PULL),
    # DS180 (7 Series FPGAs Data Sheet: Overview), Table 3: XC7S50.
    # Register-file staging in a RAMB18: −≈ 400 LUT6, −≈ 700 FF; the timing the Arty promises
    # stays (50 MHz, current loop 48 clocks, ADC + loop 95; the commit copy ends at the period
    # boundary, hdl/top.py). The loop engine would save ≈ 1 700 LUT6 more but takes 134–232
    # clocks, over issue 5's 50-clock current-loop budget: `--current-loop engine` only.
    regs_staging="bram",
    capacity={"lut": 32_600, "ff": 65_200, "dsp": 120, "bram_bits": 75 * 36_864},
    notes=(
        "JB (a high-speed Pmod port per Digilent's reference manual) carries the ADC's 25 MHz "
        "SCLK and SDO lines; JA and JD the slow signals; JC stays free.",
        "User LED 0 (E18) = trip, LED 1 (F13) = encoder aligned; UART on the FT2232HQ (FPGA "
        "pins V12 RX, R12 TX); the RESET button (C18) resets the controller.",
    ),
)

# --- Atlys: XC6SLX45-3CSG324, 100 MHz oscillator, Exar XR21V1410 USB-UART ------------------------
# (amaranth-boards has no Numato Mimas V2; its Numato Mimas (v1, XC6SLX9) has no USB-UART.)
# Pmod JB: power stage; VHDCI JC (odd "P" row of the pairs): ADC, encoder, Hall.
_ATLYS_IO = {"IOSTANDARD": AtlysPlatform.bank2_iostandard}   # bank 2: 3.3 V with JP12 = 3V3
ATLYS = Board(
    name="atlys",
    title="Digilent Atlys (Xilinx XC6SLX45-3CSG324)",
    family="xc6s",
    flow="vendor",
    platform_class=AtlysPlatform,
    platform_kwargs={"JP12": "3V3"},
    connectors={"jb": ("pmod", 0), "jc": ("vhdci", 0)},
    motor=_motor({
        "gate_h": ("jb", "1 2 3"), "gate_l": ("jb", "7 8 9"),
        "fault_n": ("jb", "4"), "oc_comp": ("jb", "10"),
        "adc_cs_n": ("jc", "1"), "adc_sclk": ("jc", "3"),
        "adc_sdo": ("jc", "4 6 7 9"),
        "enc_a": ("jc", "10"), "enc_b": ("jc", "12"), "enc_z": ("jc", "13"),
        "hall": ("jc", "15 20 22"),
    }, {"jb": ("pmod", 0), "jc": ("vhdci", 0)}, _ATLYS_IO, _XC_PULL),
    # DS160 (Spartan-6 Family Overview), Table 1: XC6SLX45 (6 822 slices × 4 LUT6, 8 FF).
    capacity={"lut": 27_288, "ff": 54_576, "dsp": 58, "bram_bits": 116 * 18_432},
    notes=(
        "Set jumper JP12 to 3V3: Pmod JB and the VHDCI connector JC are in bank 2, whose "
        "supply JP12 selects.",
        "Pmod JB shares its pins with the HDMI-D connector JA: leave JA unplugged.",
        "VHDCI pin numbers as in the amaranth-boards connector (1…68; pairs n / n + 34); only "
        "single-ended use of the first row.",
        "LED LD0 (U18) = trip, LD1 (M14) = encoder aligned; UART on the USB-UART port J17 "
        "(FPGA pins A16 RX, B16 TX); the RESET button (T15) resets the controller.",
    ),
)

#: Every board, by its ``--board`` name.
BOARDS = {b.name: b for b in (ICEBREAKER, ULX3S, ARTY_S7, ATLYS)}


def get_board(name):
    """The :class:`Board` called ``name``.

    Raises
    ------
    TypeError
        If ``name`` is not a string.
    ValueError
        If there is no such board.
    """
    if isinstance(name, Board):
        return name
    if not isinstance(name, str):
        raise TypeError(f"Board must be a board name string, not {name!r}")
    if name not in BOARDS:
        raise ValueError(f"Board must be one of {', '.join(BOARDS)}, not {name!r}")
    return BOARDS[name]


def pin_map(board):
    """The resolved motor pin map of ``board``: one row per bit, in :data:`MOTOR_PORTS` order.

    Returns
    -------
    list of dict
        ``signal`` (``"gate_h[0]"``), ``port`` (Top pin), ``bit``, ``dir`` (``"i"``/``"o"``),
        ``connector`` (the board's label), ``conn`` ((name, number)), ``conn_pin`` (the pin
        number on that connector), ``fpga_pin`` (package pin, resolved through the platform's
        own connector table) and ``attrs`` (I/O attributes, callables resolved).
    """
    board = get_board(board)
    platform = board.platform()
    labels = {conn: label for label, conn in board.connectors.items()}
    res_attrs = dict(board.motor.attrs)
    rows = []
    for sub in board.motor.ios:
        width, direction = MOTOR_PORTS[sub.name]
        pins = sub.ios[0]
        attrs = {**res_attrs, **dict(sub.attrs)}
        attrs = {k: (v(platform) if callable(v) else v) for k, v in attrs.items()}
        for bit, conn_name in enumerate(pins.names):
            # "pmod_0:7" → connector ("pmod", 0), pin "7"
            conn_id, conn_pin = conn_name.split(":", 1)
            conn = next(c for c in board.connectors.values() if f"{c[0]}_{c[1]}" == conn_id)
            fpga_pin = platform.connectors[conn].mapping[conn_pin]
            rows.append({
                "signal": f"{sub.name}[{bit}]" if width > 1 else sub.name,
                "port": sub.name, "bit": bit, "dir": direction,
                "connector": labels[conn], "conn": conn, "conn_pin": conn_pin,
                "fpga_pin": fpga_pin, "attrs": attrs,
            })
    return rows


def _table(board):
    rows = pin_map(board)
    out = ["| Signal | Dir | Connector pin | FPGA pin | Pull |", "|---|---|---|---|---|"]
    for r in rows:
        pull = next((f"{k}={v}" for k, v in r["attrs"].items()
                     if k in ("PULLUP", "PULLDOWN", "PULLMODE")), "—")
        out.append(f"| `{r['signal']}` | {'out' if r['dir'] == 'o' else 'in'} | "
                   f"{r['connector'].upper()}-{r['conn_pin']} | {r['fpga_pin']} | {pull} |")
    return out


if __name__ == "__main__":
    for b in BOARDS.values():
        print(f"### {b.title}\n")
        print("\n".join(_table(b)))
        print()
