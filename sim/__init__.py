"""Everything simulated that is not gateware. Imported as ``foc_servo.sim``."""
