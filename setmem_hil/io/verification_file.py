"""``verify.json``, the file of one closed-loop verification (issue 63 item 6).

The verification plan defines the document (:mod:`setmem_hil.verify.document` builds it); this
module is its file: the name, the keys every reader may rely on, the atomic write into the
verification's directory and the run's, and the checked read the run's report uses.
"""

from __future__ import annotations

import json
from pathlib import Path

from setmem_hil.errors import InputFormatError
from setmem_hil.io.atomic_file import write_json_atomic

__all__ = ["VERIFICATION_FILENAME", "REQUIRED_KEYS", "write_verification", "read_verification"]

VERIFICATION_FILENAME = "verify.json"
REQUIRED_KEYS = ("verified", "target", "steps", "performance", "first_outside", "discrepancy")
"""The keys every reader may rely on (the report's section reads these)."""


def write_verification(doc: dict, out_dir: Path, run_dir: Path) -> Path:
    """``out_dir/verify.json`` and its copy in the run directory (the run's report shows the latest)."""
    path = Path(out_dir) / VERIFICATION_FILENAME
    write_json_atomic(doc, path)
    write_json_atomic(doc, Path(run_dir) / VERIFICATION_FILENAME)
    return path


def read_verification(directory: Path) -> dict | None:
    """The verification stored in ``directory`` (None where there is none); a file that is not a
    verification document is refused with a sentence naming it and what it lacks."""
    path = Path(directory) / VERIFICATION_FILENAME
    if not path.is_file():
        return None
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise InputFormatError(str(path), "", f"is not readable JSON ({exc})") from exc
    missing = [k for k in REQUIRED_KEYS if not isinstance(doc, dict) or k not in doc]
    if missing:
        raise InputFormatError(str(path), "", f"is not a verification document: no {', '.join(missing)}")
    return doc
