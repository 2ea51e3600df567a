"""PC side: command-line tool (and later the protocol client). Imported as ``foc_servo.host``."""
