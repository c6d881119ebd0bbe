"""Maps on disk: the snapshot of a map (``snapshot``: what it holds, written and read back),
its checksummed files and atomic ``CURRENT`` (``snapshot_files``), the feature and landmark
columns it stores (``feature_columns``, ``landmark_codec``), and the write-ahead journal of
the service's edits between snapshots (``journal``). Imports only the core."""
