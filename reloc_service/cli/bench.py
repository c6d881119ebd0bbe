"""``reloc bench``: run the benchmark suite.

Implemented in ``reloc_service.tools.bench.cli``, imported only when the subcommand is chosen.
"""

from __future__ import annotations

from ._delegate import Delegate

HELP = "run the benchmark suite"

_delegate = Delegate("bench", "reloc_service.tools.bench.cli")
add_arguments = _delegate.add_arguments
run = _delegate.run
