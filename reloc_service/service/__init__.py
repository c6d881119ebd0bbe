"""The Zenoh relocalization service (``reloc serve``), in layers; a module imports only the
layers above its own:

1. ``config``, ``workers``, ``codec`` (wire <-> core types, exceptions -> protocol error codes)
2. ``durability``: journal replay, snapshots, ``service.json``, the storage directory;
   ``served``: what a served map and its replica in a worker process share (the query face,
   the write operations and how a change is applied); ``quotas``: what the maps may hold
3. ``runtime``: one served map (engine front, cameras, deferral, training, stats, events)
4. ``handlers`` (pure ``bytes -> bytes``), ``processes`` (relocalize worker processes holding
   replicas), ``replication`` (sharding, bootstrap from peers), ``zenoh_io`` (queryables,
   subscribers, liveliness), ``storage_check``
5. ``registry``: the served maps (restored at start, created by a first put, or failed)
6. ``writes``: the write path (a writer pool shared by the maps, the puts, their rejections)
7. ``app``: the service (life cycle, dispatch); ``cli``, ``router``

The wire format comes from ``reloc_client.protocol`` (one definition for both ends; the
distribution installs both packages, and pytest's ``pythonpath`` covers a source checkout).
Nothing is imported here, so ``import reloc_service.service.config`` loads neither Zenoh nor
OpenCV.
"""
