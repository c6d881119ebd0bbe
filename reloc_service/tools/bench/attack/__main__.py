"""One or more attack cases by name, for a quick look:
``python -m reloc_service.tools.bench.attack NAME ...`` (all cases without a name)."""

from __future__ import annotations

import json
import sys

from . import run_attack

print(json.dumps(run_attack(sys.argv[1:] or None, on_progress=print), indent=1))
