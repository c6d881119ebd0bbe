"""How soon a restarted ``reloc serve`` answers for a map with a journal backlog: seconds from
the process start to the map's first answered ``status``, its first answered relocalize, and
the end of the replay (``keyframes`` == N, no longer ``replaying``).

    python scripts/replay_first_answer.py [--keyframes 60] [--root CHECKOUT]

The map directory holds camera cam0 and N keyframe puts of the tests' synthetic scene
(320x240) in a journal with an identity and sequence numbers, no snapshot, as a service
killed before its first snapshot leaves it. ``--root`` runs the service of another checkout
(e.g. the main branch, to compare); the journal format is the same.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))

from conftest import PINHOLE, make_scene  # noqa: E402
from reloc_client import protocol as wire  # noqa: E402
from reloc_client.client import (  # noqa: E402
    NoReplyError,
    RelocClient,
    to_wire_camera,
    to_wire_image,
    to_wire_pose,
)
from service_support import endpoint, free_port  # noqa: E402

from reloc_service.service.durability import MapStore  # noqa: E402

MAP = "backlog"


def write_backlog(map_dir: Path, scene, n: int) -> None:
    """Camera cam0 and ``n`` keyframe puts journaled as the service journals them."""
    store = MapStore(MAP, map_dir)
    store.journal.identity = uuid.uuid4()
    store.journal.open()
    store.append({"op": "cam", "id": "cam0",
                  "payload": wire.CameraPut("cam0", to_wire_camera(scene.camera)).encode()})
    for kf_id in range(n):
        i = kf_id % len(scene.keyframe_images)
        store.append({"op": "kf", "id": kf_id, "payload": wire.KeyframePut(
            id=kf_id, image=to_wire_image(scene.keyframe_images[i]),
            world_from_cam=to_wire_pose(scene.keyframe_poses[i]), camera_id="cam0").encode()})
    store.close()


def first(what, deadline: float, interval: float = 0.1):
    """Call ``what`` until it returns without NoReplyError (or ConnectionError)."""
    while time.monotonic() < deadline:
        try:
            return what()
        except (NoReplyError, ConnectionError):
            time.sleep(interval)
    raise TimeoutError("no answer in time")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--keyframes", type=int, default=60)
    parser.add_argument("--root", type=Path, default=REPO)
    args = parser.parse_args()
    scene = make_scene(PINHOLE)
    tmp = Path(tempfile.mkdtemp(prefix="replay-first-answer-"))
    write_backlog(tmp / "storage" / MAP, scene, args.keyframes)
    port = free_port()
    config = tmp / "service.toml"
    config.write_text("\n".join([
        "[zenoh]", 'mode = "peer"', f'listen = ["{endpoint(port)}"]',
        "multicast_scouting = false", "[service]", 'instance = "replay"',
        f'storage = "{tmp / "storage"}"', "train_on_load = false", "snapshot_every = 0"]) + "\n")
    root = args.root.resolve()
    env = {**os.environ, "PYTHONPATH": f"{root}{os.pathsep}{root / 'clients'}"}
    log = (tmp / "serve.log").open("ab")
    start = time.monotonic()
    proc = subprocess.Popen([sys.executable, "-m", "reloc_service.cli.main", "serve",
                             "--config", str(config)], cwd=root, env=env, stdout=log,
                            stderr=subprocess.STDOUT)
    deadline = start + 1800
    try:
        client = first(lambda: RelocClient(endpoint(port), map=MAP, timeout=30), deadline)
        with client:
            status = first(lambda: client.status(timeout=1), deadline)
            status_s = time.monotonic() - start
            at_status = status.keyframes
            first(lambda: client.relocalize(scene.query_images[0], camera_id="cam0",
                                            timeout=300), deadline)
            relocalize_s = time.monotonic() - start
            while True:
                status = client.status(timeout=30)
                if status.keyframes == args.keyframes and not getattr(status, "replaying",
                                                                      False):
                    break
                time.sleep(0.5)
            replayed_s = time.monotonic() - start
        print(json.dumps({"root": str(root), "keyframes": args.keyframes,
                          "first_status_s": round(status_s, 1),
                          "keyframes_at_first_status": at_status,
                          "first_relocalize_s": round(relocalize_s, 1),
                          "replayed_s": round(replayed_s, 1)}))
    finally:
        proc.terminate()
        proc.wait(120)
        log.close()


if __name__ == "__main__":
    main()
