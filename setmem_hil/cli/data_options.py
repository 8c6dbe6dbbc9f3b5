"""The data options every command that reads a measured FRF shares (identify, discrepancy, prior)."""

from __future__ import annotations

import argparse
import sys

from pathlib import Path

from setmem_hil.errors import InputFormatError
from setmem_hil.io.frf_file import QUANTITIES, load_frf_outputs
from setmem_hil.model.frequency_data import FrequencyData

__all__ = ["add_data_options", "load_outputs", "load_prior", "load_output_priors", "check_out_path"]


def add_data_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", required=True, action="append", metavar="DATA.csv|DATA.uff",
                   help="CSV with header omega,re,im,bound (rad/s), or a UFF 58 FRF file; once per output (sensor): "
                        "the modes' poles are shared, each output has its own residues")
    p.add_argument("--quantity", choices=QUANTITIES, default=None,
                   help="the response quantity of the data (default displacement; a UFF file's own declaration otherwise); "
                        "converted to receptance with its bound")
    p.add_argument("--bound-rel", type=float, metavar="R", help="UFF: bound = R |H| + A, in the file's units")
    p.add_argument("--bound-abs", type=float, metavar="A", help="UFF: see --bound-rel")
    p.add_argument("--averages", type=int, metavar="N", help="UFF with a coherence record: H1 random-error bound (3 sigma) for N averages")


def load_outputs(args: argparse.Namespace) -> list[tuple[str, FrequencyData]]:
    """Every ``--data`` file in the order given, one output each, named by its stem (issue 25).
    The same file twice is refused (it would count one sensor's evidence twice)."""
    files = args.data if isinstance(args.data, list) else [args.data]
    seen = {}
    for f in files:
        key = str(Path(f).resolve())
        if key in seen:
            raise InputFormatError(f, "--data", f"given twice (as {seen[key]} and {f}): each output once")
        seen[key] = f
    loaded = []  # (file, name, data): a UFF file with several FRF records of one reference is several outputs
    for f in files:
        for name, frf in load_frf_outputs(f, quantity=args.quantity, bound_rel=args.bound_rel, bound_abs=args.bound_abs,
                                          averages=args.averages):
            for note in frf.notes:
                print(f"setmem-hil: note: {f}: {note}", file=sys.stderr)
            loaded.append((f, name, frf.data))
    names = [name for _, name, _ in loaded]
    if len(set(names)) != len(names):  # e.g. point1/frf.csv and point2/frf.csv: the folder tells them apart
        names = [f"{Path(f).parent.name}/{name}" for f, name, _ in loaded]
    if len(set(names)) != len(names):
        names = [f"{name} ({i + 1})" for i, name in enumerate(names)]
    return [(name, data) for name, (_, _, data) in zip(names, loaded)]


PROCEDURE_TABLES = ("backend", "initial", "safety", "goal", "input_design", "weights", "discrepancy", "name", "seed")


def load_prior(path: str):
    """One output's prior: a PRIOR.toml, or a procedure file whose ``[[mode]]`` tables are the
    prior (its other tables are validated too, since a procedure with a typo is not a
    trustworthy prior)."""
    return load_output_priors(path, 1)[0][0]


def load_output_priors(path: str, n_outputs: int):
    """One prior per output (:func:`setmem_hil.model.prior.parse_output_priors`) and the names the
    prior gives them (or None). A procedure file's prior serves every output alike (its other
    tables are validated too, since a procedure with a typo is not a trustworthy prior)."""
    from setmem_hil.model.prior import load_toml, parse_output_priors

    mapping = load_toml(path)
    if any(key in mapping for key in PROCEDURE_TABLES):
        from setmem_hil.io.procedure_file import load_procedure

        return [load_procedure(path).prior] * n_outputs, None
    return parse_output_priors(mapping, str(path), n_outputs)


def check_out_path(path: str, option: str = "--out") -> Path:
    """Refuse an output path whose folder does not exist, before any computation."""
    out = Path(path)
    if out.is_dir():
        raise InputFormatError(str(out), option, "is a folder; give a file name")
    if not out.parent.is_dir():
        raise InputFormatError(str(out), option, f"folder {out.parent} does not exist (create it first)")
    return out
