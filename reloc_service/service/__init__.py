"""The Zenoh relocalization service (``reloc serve``), in layers that import downwards only:

``config`` -> ``codec`` (wire <-> core types, error codes) -> ``durability`` (journal,
snapshots, replay) -> ``runtime`` (one served map) -> ``handlers`` (pure ``bytes -> bytes``)
-> ``replication`` (sharding, bootstrap from peers) -> ``zenoh_io`` / ``workers`` -> ``app``
(the service: life cycle, map registry, dispatch).

The wire format comes from ``reloc_client.protocol`` (one definition for both ends; the
distribution installs both packages, and pytest's ``pythonpath`` covers a source checkout).
Nothing is imported here, so ``import reloc_service.service.config`` loads neither Zenoh nor
OpenCV.
"""
