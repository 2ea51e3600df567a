"""Protection → Gates as wired in the top: every fault input takes all six gates low within ≤ 3
clocks of the synchronised fault signal, they stay low after the cause is gone, and only a clear
with the cause gone releases them."""

import pytest

from foc_servo.hdl.protect import FAULTS
from foc_servo.sim.verify.fault_chain import run


@pytest.mark.parametrize("trip_register", [True, False])
def test_fault_chain_latency_latch_and_clear(trip_register):
    result = run(trip_register=trip_register)
    assert set(result["latency_clk"]) == set(FAULTS)
    slow = {cause: n for cause, n in result["latency_clk"].items() if n > 3}
    assert not slow, f"faults slower than 3 clocks to gates off: {slow}"
    assert result["latched"], "gates came back on before a clear"
    assert result["released"], "a clear with the cause gone did not release the gates"
