"""A trained map written where ``reloc serve --storage`` finds it, and copies of it: the one
template builder of the many-maps measurements (``reloc bench --only fleet``) and of the lazy
map tests.

:func:`stored_template` writes an engine's map as a service writes it at a snapshot: a
journal segment under a new map identity, rotated, the engine's snapshot, then
``service.json`` naming it (cameras, the camera of each keyframe). A service restores it as
one of its own maps, with nothing to replay. :func:`copy_map` serves the same map under
another name: the snapshot's files are hard links (a snapshot file is written once and
renamed into place, never changed after: a later snapshot is a new directory), the journal,
``service.json`` and the name file are copies, which the service does change.
"""

from __future__ import annotations

import os
import shutil
import uuid
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from ...core.cameras import Camera
from ...engine import Engine, EngineConf

#: The camera id every keyframe of a template is put with (the id queries name).
CAMERA_ID = "cam0"


@dataclass(frozen=True)
class StoredMap:
    """A map in a service storage: its directory, keyframes, and the bytes it counts once a
    service has loaded it (its quota usage, what ``[service] max_resident_mb`` weighs)."""

    directory: Path
    keyframes: int
    counted_bytes: int


def engine_from_images(camera: Camera, images: Sequence[npt.NDArray[np.uint8]],
                       world_from_cams: Sequence[npt.ArrayLike], conf: EngineConf, *,
                       train: bool = True) -> Engine:
    """An engine with ``images`` ((H, W) uint8) put as keyframes 0.. at ``world_from_cams``
    ((4, 4) each), every method of ``conf`` trained (unless ``train`` is False)."""
    engine = Engine(conf)
    for kf_id, (image, world_from_cam) in enumerate(zip(images, world_from_cams, strict=True)):
        engine.add_keyframe(kf_id, image, camera, np.asarray(world_from_cam, np.float64))
    if train:
        engine.train()
    return engine


def stored_template(storage: Path, name: str, engine: Engine,
                    cameras: Mapping[str, Camera] | None = None,
                    camera_of: Mapping[int, str] | None = None) -> StoredMap:
    """Write ``engine``'s map (and its trained models) as map ``name`` of service storage
    ``storage`` (see module docstring). ``cameras``: the registered cameras by id (default:
    the first keyframe's as :data:`CAMERA_ID`); ``camera_of``: each keyframe's camera id
    (default: the only camera's). FileExistsError if ``name`` is stored there already."""
    from ...service.durability import MapStore, ServiceMeta
    from ...service.map_dirs import map_dirname, record_map_name

    keyframes = engine.map.snapshot().keyframes
    if cameras is None:
        first = next(iter(keyframes.values()), None)
        if first is None:
            raise ValueError("a template needs at least one keyframe (or its cameras given)")
        cameras = {CAMERA_ID: first.camera}
    if camera_of is None:
        if len(cameras) != 1:
            raise ValueError(f"camera_of is needed with {len(cameras)} cameras; expected "
                             "each keyframe's camera id")
        only = next(iter(cameras))
        camera_of = {kf_id: only for kf_id in keyframes}
    directory = storage / map_dirname(name)
    directory.mkdir(parents=True, exist_ok=False)
    record_map_name(directory, name)
    store = MapStore(name, directory, fsync=False, snapshot_every=0)
    store.journal.identity = uuid.uuid4()
    store.journal.open()
    try:
        segment = store.rotate()
        store.save(engine, ServiceMeta(cameras=dict(cameras), keyframe_camera_ids=dict(camera_of),
                                       next_segment=segment))
    finally:
        store.close()
    return StoredMap(directory, len(keyframes), counted_bytes(directory))


def counted_bytes(directory: Path) -> int:
    """What map directory ``directory`` counts once loaded from its snapshot (the quotas'
    usage of the loaded map, which the residency budget weighs)."""
    from ...service.quotas import MapUsage
    from ...storage.snapshot import load_map

    state, _ = load_map(directory / "map")
    return MapUsage.of(state).total


def copy_map(template: StoredMap, storage: Path, name: str, *, link: bool = True) -> Path:
    """``template`` stored again as map ``name`` in ``storage`` (see module docstring):
    snapshot files hard-linked when ``link`` (copied where the file system refuses a link),
    everything else copied; directory locks are not copied. The new map directory."""
    from ...service.map_dirs import MAP_NAME_FILE, map_dirname

    target = storage / map_dirname(name)

    def place(source: str, dest: str) -> object:
        if link and f"{os.sep}snapshots{os.sep}" in source:
            try:
                os.link(source, dest)
                return dest
            except OSError:
                pass
        return shutil.copy2(source, dest)

    shutil.copytree(template.directory, target, copy_function=place,
                    ignore=shutil.ignore_patterns("*.lock", "LOCK"))
    (target / MAP_NAME_FILE).write_text(name)
    return target


def copies(template: StoredMap, storage: Path, names: Sequence[str], *,
           link: bool = True) -> list[Path]:
    """:func:`copy_map` of ``template`` under each of ``names``."""
    return [copy_map(template, storage, name, link=link) for name in names]


def disk_bytes(root: Path) -> tuple[int, int]:
    """(apparent, allocated) bytes of the files under ``root``: the sum of their sizes, and
    the blocks they take on disk with each hard-linked file counted once."""
    apparent, allocated, seen = 0, 0, set()
    for path in root.rglob("*"):
        st = path.lstat()
        if not path.is_file():
            continue
        apparent += st.st_size
        if (st.st_dev, st.st_ino) not in seen:
            seen.add((st.st_dev, st.st_ino))
            allocated += st.st_blocks * 512
    return apparent, allocated
