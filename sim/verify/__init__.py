"""Gateware-against-golden-model checks shared by the tests and ``foc-servo bench``."""
