"""The data options every command that reads a measured FRF shares (identify, discrepancy, prior)."""

from __future__ import annotations

import argparse
import sys

from setmem_hil.io.frf_file import QUANTITIES, load_frf
from setmem_hil.model.frequency_data import FrequencyData

__all__ = ["add_data_options", "load_data"]


def add_data_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", required=True, metavar="DATA.csv|DATA.uff",
                   help="CSV with header omega,re,im,bound (rad/s), or a UFF 58 FRF file")
    p.add_argument("--quantity", choices=QUANTITIES, default=None,
                   help="the response quantity of the data (default displacement; a UFF file's own declaration otherwise); "
                        "converted to receptance with its bound")
    p.add_argument("--bound-rel", type=float, metavar="R", help="UFF: bound = R |H| + A, in the file's units")
    p.add_argument("--bound-abs", type=float, metavar="A", help="UFF: see --bound-rel")
    p.add_argument("--averages", type=int, metavar="N", help="UFF with a coherence record: H1 random-error bound (3 sigma) for N averages")


def load_data(args: argparse.Namespace) -> FrequencyData:
    loaded = load_frf(args.data, quantity=args.quantity, bound_rel=args.bound_rel, bound_abs=args.bound_abs, averages=args.averages)
    for note in loaded.notes:
        print(f"setmem-hil: note: {args.data}: {note}", file=sys.stderr)
    return loaded.data
