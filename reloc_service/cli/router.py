"""``reloc router``: run a Zenoh router (ground-station set-up).

Implemented in ``reloc_service.service.router``, imported only when the subcommand is chosen.
"""

from __future__ import annotations

from ._delegate import Delegate

HELP = "run a Zenoh router (ground-station set-up)"

_delegate = Delegate("router", "reloc_service.service.router")
add_arguments = _delegate.add_arguments
run = _delegate.run
