"""The Zenoh relocalization service (``reloc serve``), in layers; a module imports only the
layers above its own:

1. ``config``, ``journal`` (the journal file format), ``workers``, ``codec`` (wire <-> core
   types, exceptions -> protocol error codes)
2. ``durability``: journal replay, snapshots, ``service.json``, the storage directory
3. ``runtime``: one served map (engine front, cameras, deferral, training, stats, events)
4. ``handlers`` (pure ``bytes -> bytes``), ``replication`` (sharding, bootstrap from peers),
   ``zenoh_io`` (queryables, subscribers, liveliness), ``storage_check``
5. ``app``: the service (life cycle, map registry, dispatch); ``cli``, ``router``

The wire format comes from ``reloc_client.protocol`` (one definition for both ends; the
distribution installs both packages, and pytest's ``pythonpath`` covers a source checkout).
Nothing is imported here, so ``import reloc_service.service.config`` loads neither Zenoh nor
OpenCV.
"""
