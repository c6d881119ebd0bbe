"""``reloc serve``: run the Zenoh relocalization service.

Implemented in ``reloc_service.service.cli``, imported only when the subcommand is chosen.
"""

from __future__ import annotations

from ._delegate import Delegate

HELP = "run the Zenoh relocalization service"

_delegate = Delegate("serve", "reloc_service.service.cli")
add_arguments = _delegate.add_arguments
run = _delegate.run
