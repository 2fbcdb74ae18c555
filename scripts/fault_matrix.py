"""`make faults`: every fault of tests/fault_matrix.py injected into the real
drivers and the service, then cleared; the table goes into
docs/reliability.md (between its table markers) and to stdout.

    .venv/bin/python scripts/fault_matrix.py [--no-write] [FAULT ...]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))

import fault_matrix as fm  # noqa: E402

DOC = REPO / "docs" / "reliability.md"
BEGIN, END = "<!-- fault-matrix:begin -->", "<!-- fault-matrix:end -->"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("faults", nargs="*", help=f"default: all ({', '.join(fm.FAULTS)})")
    ap.add_argument("--no-write", action="store_true", help="print only")
    args = ap.parse_args()
    unknown = [f for f in args.faults if f not in fm.FAULTS]
    if unknown:
        ap.error(f"unknown fault {unknown[0]!r}")
    t0 = time.monotonic()
    with tempfile.TemporaryDirectory() as tmp:
        rows = fm.run_matrix(args.faults or list(fm.FAULTS), Path(tmp))
    text = fm.table(rows)
    print(text)
    bad = [r.fault for r in rows if r.passed_on or r.lost != "none" or r.recover_s > 3.0]
    print(f"{len(rows)} faults in {time.monotonic() - t0:.0f} s; "
          f"{'all met the bars' if not bad else 'NOT met: ' + ', '.join(bad)}")
    if not args.no_write and not args.faults:
        doc = DOC.read_text()
        head, _, rest = doc.partition(BEGIN)
        _, _, tail = rest.partition(END)
        stamp = time.strftime("%Y-%m-%d")
        DOC.write_text(f"{head}{BEGIN}\n<!-- made by `make faults` on {stamp} -->\n\n{text}\n\n"
                       f"{END}{tail}")
        print(f"written into {DOC.relative_to(REPO)}")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
