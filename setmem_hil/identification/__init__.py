"""Set-membership identification of the modal model (thesis chapter 3, Algorithms 3.1/3.2)."""

from setmem_hil.identification.algorithm import IdentificationResult, IdentifySettings, identify

__all__ = ["IdentificationResult", "IdentifySettings", "identify"]
