"""The bottom layer: what every other layer speaks in. Errors, SE(3) geometry, camera models,
frames and their features, the keyframe map and its landmark table, triangulation, map
building, plugin registries, atomic file writes, BLAS thread control and progress bars. It
imports nothing of reloc but itself."""
