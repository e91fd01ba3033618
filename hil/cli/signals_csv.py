"""`hil csv`: write a run's signals.csv from its signal blocks (signals.parquet).

A run writes signals.csv when it ends, also when it fails or is stopped; a run killed hard
(SIGKILL, the machine gone) leaves only the blocks written every 0.25 s of wall time. This
command writes the CSV from them: the same bytes the run would have written for those rows.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from hil.errors import HilError

SIGNALS = "signals.csv"


def add_parser(commands: argparse._SubParsersAction) -> None:
    from hil.cli.parsers import example_parser

    parser = example_parser(
        commands,
        "csv",
        "write a run's signals.csv from its signal blocks (signals.parquet), e.g. after a run "
        "killed hard",
        "  hil csv runs/default-1          runs/default-1/signals.csv from its blocks\n",
    )
    parser.add_argument("run", type=Path, help="results folder of a run")
    parser.set_defaults(handler=_csv)


def _csv(args: argparse.Namespace) -> int:
    from hil.blocks import blocks_folder, write_csv
    from hil.results import list_in_manifest, locked, manifest_names

    out: Path = args.run
    if not out.is_dir():
        raise HilError(f"{out}: no such results folder")
    path = out / SIGNALS
    if not blocks_folder(path).is_dir():
        raise HilError(f"{out}: no signal blocks ({blocks_folder(path).name}) to write {SIGNALS}")
    if path.exists() and SIGNALS not in manifest_names(out):
        raise HilError(f"{path}: was not written by softhil; hil csv replaces only its own")
    writes = f"hil csv writes {SIGNALS} there; copy the folder somewhere writable"
    with locked(out, writes):  # not while a run writes there; a killed run's lock is taken over
        list_in_manifest(out, [SIGNALS])
        rows = write_csv(path)
    print(f"{path}: {rows} rows from {blocks_folder(path)}")
    return 0
