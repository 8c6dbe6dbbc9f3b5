"""Input design: effects of a candidate input on the intervals and the ranking (thesis chapters 4 and 5)."""

from setmem_hil.design.input_design import InputChoice, choose_input

__all__ = ["InputChoice", "choose_input"]
