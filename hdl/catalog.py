"""The blocks with their default parameters: what ``foc-servo verilog`` writes and what
``foc-servo bench`` synthesises. Add a block here and both commands pick it up."""

from .adc import AdcInterface
from .clarke import Clarke
from .cordic import Cordic
from .deadtime_comp import DeadTimeComp
from .divider import Divider
from .encoder import EncoderFrontEnd
from .foc import CurrentLoop
from .gates import Gates
from .mt_speed import MTSpeed
from .pi import PI
from .protect import Protection
from .regs import RegisterFile
from .rotator import Rotator
from .scope import Scope
from .servo import Servo
from .svpwm import SVPWM, DCBusCompensation, PWMTimer
from .top import Top

__all__ = ["ARITH_BLOCKS", "IO_BLOCKS", "CONTROL_BLOCKS", "BLOCKS"]

#: The foundation's arithmetic blocks, name -> factory of a fresh instance (defaults).
ARITH_BLOCKS = {
    "cordic": lambda: Cordic(),
    "rotator": lambda: Rotator(),
    "pi": lambda: PI(),
    "clarke": lambda: Clarke(),
    "divider": lambda: Divider(),
}

#: The motor-side blocks (issue 4), name -> factory of a fresh instance (defaults).
IO_BLOCKS = {
    "encoder": lambda: EncoderFrontEnd(),
    "mt_speed": lambda: MTSpeed(),
    "dcbus": lambda: DCBusCompensation(),
    "svpwm": lambda: SVPWM(),
    "pwm_timer": lambda: PWMTimer(),
    "gates": lambda: Gates(),
    "deadtime_comp": lambda: DeadTimeComp(),
    "adc": lambda: AdcInterface(),
    "protect": lambda: Protection(),
}

#: The controller blocks (issue 5), name -> factory of a fresh instance (defaults).
CONTROL_BLOCKS = {
    "foc": lambda: CurrentLoop(),
    "servo": lambda: Servo(),
    "scope": lambda: Scope(),
    "regs": lambda: RegisterFile(),
    "top": lambda: Top(),
}

#: Every block.
BLOCKS = {**ARITH_BLOCKS, **IO_BLOCKS, **CONTROL_BLOCKS}
