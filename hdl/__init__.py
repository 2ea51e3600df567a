"""Gateware: one Amaranth component per block. Imported as ``foc_servo.hdl``."""
