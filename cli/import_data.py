"""``cellcal import FORMAT SRC -o OUT.csv``: a vendor or data-set export to the measurement CSV."""
from __future__ import annotations

from pathlib import Path

from cellcal.cli.common import counted, print_progress, writable_file
from cellcal.measurements.importers import IMPORTERS
from cellcal.measurements.writer import write_measurements


def add_parser(sub) -> None:
    p = sub.add_parser("import", help="convert a vendor or data-set export to the measurement CSV",
                       description="Formats: " + "; ".join(f"{k}: {d}" for k, (_, d) in sorted(IMPORTERS.items())))
    p.add_argument("format", choices=sorted(IMPORTERS), help="the export's format")
    p.add_argument("source", help="the export file")
    p.add_argument("-o", "--out", required=True, metavar="OUT.csv", help="the measurement CSV to write")
    p.set_defaults(func=run)


def run(args) -> int:
    writable_file(args.out, "-o")
    fields = IMPORTERS[args.format][0](Path(args.source))
    write_measurements(args.out, comment=f"imported from {args.source} ({args.format})", **fields)
    print_progress(f"wrote {args.out}: {counted(len(fields['q_rad']), 'row')}")
    return 0
