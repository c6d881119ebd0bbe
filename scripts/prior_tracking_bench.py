"""Localization with a prior, measured: now the ``prior`` section of ``reloc bench``
(:mod:`reloc_service.tools.bench.prior`); this runs it alone on the datasets named.

    .venv/bin/python scripts/prior_tracking_bench.py /work/shared/data/real/* /work/data/room \\
        --json out/prior.json

is ``reloc bench --only prior --dataset DIR ... --json out/prior.json``.
"""

from __future__ import annotations

import sys

from reloc_service.cli.main import main as reloc_main


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    split = next((i for i, a in enumerate(args) if a.startswith("-")), len(args))
    datasets, options = args[:split], args[split:]
    if not datasets:
        print("usage: prior_tracking_bench.py DATASET [DATASET ...] [reloc bench options, "
              "e.g. --json OUT --markdown OUT]", file=sys.stderr)
        return 2
    return reloc_main(["bench", "--only", "prior",
                       *[x for d in datasets for x in ("--dataset", d)], *options])

if __name__ == "__main__":
    sys.exit(main())
