"""Bit-true numpy golden models, one module per ``hdl`` block, same fixed-point formats."""
