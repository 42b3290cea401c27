"""``cellcal import FORMAT SRC [SRC ...] -o OUT.csv``: a vendor or data-set export to the measurement CSV."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from cellcal.cli.common import counted, print_progress, writable_file
from cellcal.measurements.importers import IMPORTERS
from cellcal.measurements.table import DatasetError
from cellcal.measurements.writer import write_measurements


def add_parser(sub) -> None:
    p = sub.add_parser("import", help="convert a vendor or data-set export to the measurement CSV",
                       description="Formats: " + "; ".join(f"{k}: {d}" for k, (_, d) in sorted(IMPORTERS.items())))
    p.add_argument("format", choices=sorted(IMPORTERS), help="the export's format")
    p.add_argument("source", nargs="+", help="the export (several: their rows one after the other, in this order)")
    p.add_argument("-o", "--out", required=True, metavar="OUT.csv", help="the measurement CSV to write")
    p.set_defaults(func=run)


def merge(parts: list[tuple[str, dict]]) -> dict:
    """The rows of several imports of one format, in order. Setups (point form) must not repeat across
    sources: the same id would make two placements one."""
    if len(parts) == 1:
        return parts[0][1]
    keys = set(parts[0][1])
    names = parts[0][1].get("target_names")
    seen: dict[str, str] = {}
    for source, fields in parts:
        if set(fields) != keys or fields.get("target_names") != names:
            raise DatasetError(f"{source}: its columns differ from those of {parts[0][0]}")
        for s in dict.fromkeys(fields.get("setup", ())):
            if s in seen:
                raise DatasetError(f"{source}: setup {s!r} is also in {seen[s]} (two placements cannot share an id)")
        for s in fields.get("setup", ()):
            seen.setdefault(s, source)
    out = {}
    for k in keys:
        values = [fields[k] for _, fields in parts]
        out[k] = values[0] if k == "target_names" or values[0] is None else np.concatenate(values)
    return out


def run(args) -> int:
    writable_file(args.out, "-o")
    fields = merge([(src, IMPORTERS[args.format][0](Path(src))) for src in args.source])
    write_measurements(args.out, comment=f"imported from {', '.join(args.source)} ({args.format})", **fields)
    print_progress(f"wrote {args.out}: {counted(len(fields['q_rad']), 'row')}")
    return 0
