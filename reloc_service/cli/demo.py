"""``reloc demo``: render desk, serve it over Zenoh and relocalize every query.

Implemented in ``reloc_service.tools.demo``, imported only when the subcommand is chosen.
"""

from __future__ import annotations

from ._delegate import Delegate

HELP = "render desk, serve it over Zenoh and relocalize every query"

_delegate = Delegate("demo", "reloc_service.tools.demo")
add_arguments = _delegate.add_arguments
run = _delegate.run
