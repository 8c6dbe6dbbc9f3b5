"""Files: procedures, data, priors, results, the journal, exports, the one atomic writer."""

from setmem_hil.io.procedure_file import load_procedure
from setmem_hil.io.journal import Journal

__all__ = ["Journal", "load_procedure"]
