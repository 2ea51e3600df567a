# Ref: issue 6 (the default `pytest` run within 15 minutes on 2 cores); sim/engines/compiled.py
#      (the model cache and the source key)
"""Test-session set-up shared by every test file.

The compiled engine (Verilator) builds one model per distinct gateware configuration, 2–3
minutes each on a loaded 2-core machine, and caches it under ``$FOC_SERVO_CACHE`` (default
``~/.cache/foc-servo``); after the first build, an engine of the same configuration takes its
model by the source key without even converting to Verilog. The default suite uses two
configurations: the co-simulation's (``CoSim``: 50 MHz, 10 kHz PWM, UART at clk/16 — the
closed-loop, link, CLI and host tests) and tests/test_engines.py's (100 kHz PWM, UART at clk/8,
so that the pysim reference covers many PWM periods in few clocks). A test that needs another
configuration costs another build on a fresh machine: prefer one of these two.

The session's summary line reports how many models were built and how many Verilog conversions
ran or were skipped (``compiled engine: …``), so a new configuration shows up in the CI log.
"""

import sys


def pytest_terminal_summary(terminalreporter):
    compiled = sys.modules.get("foc_servo.sim.engines.compiled")
    if compiled is None:
        return
    terminalreporter.write_line(
        f"compiled engine: {compiled.builds} Verilator model(s) built, "
        f"{compiled.conversions} Verilog conversion(s), {compiled.source_hits} taken from the "
        f"cache by source key (cache: {compiled.cache_dir()})")
