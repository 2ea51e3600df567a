"""The blocks with their default parameters: what ``foc-servo verilog`` writes and what
``foc-servo bench`` synthesises. Add a block here and both commands pick it up."""

from .clarke import Clarke
from .cordic import Cordic
from .divider import Divider
from .pi import PI

__all__ = ["ARITH_BLOCKS", "BLOCKS"]

#: The foundation's arithmetic blocks, name -> factory of a fresh instance (defaults).
ARITH_BLOCKS = {
    "cordic": lambda: Cordic(),
    "pi": lambda: PI(),
    "clarke": lambda: Clarke(),
    "divider": lambda: Divider(),
}

#: Every block.
BLOCKS = {**ARITH_BLOCKS}

