"""Board platforms, pin maps, synthesis and build reports. Imported as ``foc_servo.boards``."""
