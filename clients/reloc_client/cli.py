"""``reloc-client``: talk to a reloc service from the shell (maps, status, upload, train,
relocalize, export, import). Thin: parse, call :class:`RelocClient`, print JSON."""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from . import protocol as wire

T = TypeVar("T")

EXIT_OK, EXIT_NOT_RELOCALIZED, EXIT_ERROR, EXIT_NO_REPLY = 0, 1, 2, 3


def _positive_seconds(text: str) -> float:
    """An argparse type: a finite number of seconds > 0 (0 would mean "no wait at all")."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of seconds, got {text!r}") from None
    if not math.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive number of seconds, got {text!r}")
    return value


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="reloc-client",
                                description="Client of the reloc relocalization service.")
    p.add_argument("--connect", "-e", action="append", metavar="ENDPOINT",
                   help="Zenoh endpoint to connect to, e.g. tcp/192.168.1.10:7447 (repeatable; "
                        "default: scout the local network)")
    p.add_argument("--map", "-m", help="map name (required except for 'maps')")
    p.add_argument("--prefix", default=wire.DEFAULT_PREFIX,
                   help="key expression prefix (default: %(default)s)")
    p.add_argument("--mode", choices=["client", "peer"], default="client",
                   help="Zenoh mode (default: %(default)s)")
    p.add_argument("--timeout", type=_positive_seconds, default=10.0,
                   help="seconds to wait for a reply (default: %(default)s)")
    sub = p.add_subparsers(dest="command", required=True)
    sub.add_parser("maps", help="list live (instance, map) pairs")
    sub.add_parser("status", help="print the service's status for --map")
    up = sub.add_parser("upload", help="put the cameras and map keyframes of a reloc dataset v1")
    up.add_argument("dataset", type=Path, help="folder with cameras.json, map.txt [, depth.txt]")
    up.add_argument("--first-id", type=int, default=0,
                    help="keyframe id of the first map.txt line (default: %(default)s)")
    up.add_argument("--train", action="store_true", help="train after uploading")
    up.add_argument("--wait", action="store_true", help="with --train: wait until trained")
    tr = sub.add_parser("train", help="(re)train the map's relocalizers")
    tr.add_argument("--method", help="method to train (default: every trainable method)")
    tr.add_argument("--wait", action="store_true", help="wait until training is done")
    tr.add_argument("--train-timeout", type=_positive_seconds, default=3600.0,
                    help="with --wait: seconds to wait (default: %(default)s)")
    rl = sub.add_parser("relocalize", help="relocalize one image and print the result as JSON")
    rl.add_argument("image", type=Path, help="a PNG or JPEG file")
    cam = rl.add_mutually_exclusive_group(required=True)
    cam.add_argument("--camera-id", help="id of a camera known to the service")
    cam.add_argument("--camera-json", type=Path,
                     help="a camera dict, or a cameras.json with exactly one camera")
    rl.add_argument("--method", help="method or comma-separated fallback chain")
    rl.add_argument("--hypotheses", type=int, default=1, help="poses to return (default: 1)")
    ex = sub.add_parser("export", help="download map NAME as one file (resumable: run again "
                        "after a lost connection)")
    ex.add_argument("name", metavar="NAME", help="the map to export")
    ex.add_argument("file", type=Path, metavar="FILE", help="the export file to write")
    im = sub.add_parser("import", help="upload an export file; the service verifies it in full "
                        "before serving it (resumable)")
    im.add_argument("file", type=Path, metavar="FILE", help="a file of `reloc map export`")
    im.add_argument("--name", help="serve it under this name (default: --map, else the name "
                    "it was exported under)")
    im.add_argument("--replace", action="store_true", help="replace a stored map of that "
                    "name that is not being served")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command == "export":
        args.map = args.name
    elif args.command == "import":
        args.map = args.name or args.map or _exported_name(args.file)
    if args.map is None and args.command != "maps":
        parser.error(f"{args.command}: --map NAME is required")
    from .client import NoReplyError, RelocClient, ServiceError  # zenoh only when running

    try:
        # 'maps' lists every map; the client needs a (valid, unused) map name anyway.
        with RelocClient(args.connect, map=args.map or "any", prefix=args.prefix, mode=args.mode,
                         timeout=args.timeout) as client:
            return COMMANDS[args.command](client, args)
    except (NoReplyError, ConnectionError) as exc:
        print(f"reloc-client: {exc}", file=sys.stderr)
        return EXIT_NO_REPLY
    except (ServiceError, wire.ProtocolError, DatasetFileError, OSError) as exc:
        print(f"reloc-client: {exc}", file=sys.stderr)
        return EXIT_ERROR
    except TimeoutError as exc:
        print(f"reloc-client: {exc}", file=sys.stderr)
        return EXIT_NO_REPLY


def _print_json(obj: Any) -> None:
    print(json.dumps(obj, indent=2))


def cmd_maps(client: Any, args: argparse.Namespace) -> int:
    _print_json([{"instance": i, "map": m} for i, m in client.maps()])
    return EXIT_OK


def cmd_status(client: Any, args: argparse.Namespace) -> int:
    _print_json(client.status().to_wire())
    return EXIT_OK


def cmd_train(client: Any, args: argparse.Namespace) -> int:
    reply = client.train(method=args.method, wait=args.wait, timeout=args.train_timeout,
                         on_event=_print_train_event)
    _print_json(reply.to_wire())
    return EXIT_OK if reply.accepted else EXIT_ERROR


def _print_train_event(event: wire.Event) -> None:
    fields = " ".join(f"{k}={v}" for k, v in event.fields.items() if k != "job_id")
    print(f"[{event.kind.value}] {fields}", file=sys.stderr)


def cmd_relocalize(client: Any, args: argparse.Namespace) -> int:
    camera = read_camera_json(args.camera_json) if args.camera_json else None
    result = client.relocalize(args.image, camera_id=args.camera_id, camera=camera,
                               method=args.method, hypotheses=args.hypotheses)
    _print_json(result.to_dict())
    return EXIT_OK if result.ok else EXIT_NOT_RELOCALIZED


def cmd_upload(client: Any, args: argparse.Namespace) -> int:
    """Each camera and keyframe waits for the service's acknowledgement (journaled): a
    service that is down or stops answering ends the upload with exit status 3 and says
    which keyframe was the first not stored; a refused keyframe is reported and skipped."""
    from .errors import ServiceError

    data = read_dataset(args.dataset)
    rejected: list[wire.Event] = []
    sub = client.subscribe_events(rejected.append, kinds=["keyframe_rejected", "camera_rejected"])
    try:
        for camera_id, camera in data.cameras.items():
            client.set_camera(camera_id, camera, wait=True)
        by_id = _cameras_confirmed(client, data.cameras)
        for i, entry in enumerate(progress(data.entries, desc="upload")):
            depth = data.depth.get(entry.image_path)
            try:
                client.add_keyframe(args.first_id + i, _image(data, entry),
                                    entry.world_from_cam,
                                    camera_id=entry.camera_id if by_id else None,
                                    camera=None if by_id else data.cameras[entry.camera_id],
                                    depth=None if depth is None else _depth(data.root, *depth),
                                    wait=True)
            except ServiceError:
                pass   # its keyframe_rejected event is reported below
        status = _settle(client, expected=len(data.entries))
    finally:
        sub.undeclare()
    for event in rejected:
        print(f"rejected: {dict(event.fields)}", file=sys.stderr)
    print(f"uploaded {len(data.entries)} keyframes; the map now has {status.keyframes} "
          f"(version {status.map_version})", file=sys.stderr)
    if args.train:
        reply = client.train(wait=args.wait, on_event=_print_train_event)
        _print_json(reply.to_wire())
        if not reply.accepted:
            return EXIT_ERROR
    return EXIT_ERROR if rejected else EXIT_OK


def _cameras_confirmed(client: Any, cameras: dict[str, wire.WireCamera],
                       patience_s: float = 3.0) -> bool:
    """True once the service lists every camera (keyframes can then refer to them by id);
    False if it does not in time: keyframes then carry their camera inline."""
    from .errors import NoReplyError

    deadline = time.monotonic() + patience_s
    while time.monotonic() < deadline:
        try:
            known = client.cameras(timeout=1.0)
        except NoReplyError:
            return False
        if all(known.get(cid) == cam for cid, cam in cameras.items()):
            return True
        time.sleep(0.1)
    return False


def _settle(client: Any, expected: int, patience_s: float = 5.0) -> wire.StatusReply:
    """Puts have no reply: poll the status until the keyframe count stops growing."""
    status = client.status()
    deadline = time.monotonic() + patience_s
    while status.keyframes < expected and time.monotonic() < deadline:
        time.sleep(0.2)
        status = client.status()
    return status


def _image(data: UploadData, entry: Entry) -> wire.WireImage:
    path = data.root / entry.image_path
    try:
        image = wire.WireImage.from_bytes(path.read_bytes())
    except wire.ProtocolError:
        raise DatasetFileError(f"{path}: expected a PNG or JPEG file") from None
    camera = data.cameras[entry.camera_id]
    if (image.width, image.height) != (camera.width, camera.height):
        raise DatasetFileError(f"{path}: image is {image.width}x{image.height} px, but camera "
                               f"{entry.camera_id!r} expects {camera.width}x{camera.height}")
    return image


def _depth(root: Path, depth_path: str, metres_per_unit: float) -> wire.WireDepth:
    data = (root / depth_path).read_bytes()
    header = wire.png_header(data)
    if header is None:
        raise DatasetFileError(f"{root / depth_path}: expected a 16-bit PNG depth map")
    return wire.WireDepth(wire.DepthFormat.PNG, header[0], header[1], data, metres_per_unit)


def cmd_export(client: Any, args: argparse.Namespace) -> int:
    from .transfer import download_export

    start = time.perf_counter()
    done = download_export(client, args.file)
    _print_json({"file": str(done.path), "bytes": done.size, "sha256": done.sha256,
                 "map_id": done.map_id, "resumed_from": done.resumed_from,
                 "seconds": round(time.perf_counter() - start, 2)})
    return EXIT_OK


def cmd_import(client: Any, args: argparse.Namespace) -> int:
    from .transfer import upload_import

    start = time.perf_counter()
    done, reply = upload_import(client, args.file, replace=args.replace)
    _print_json({"map": client.map, "map_id": reply.map_id, "keyframes": reply.keyframes,
                 "bytes": done.size, "resumed_from": done.resumed_from,
                 "seconds": round(time.perf_counter() - start, 2)})
    return EXIT_OK


def _exported_name(file: Path) -> str | None:
    """The map name in an export file's manifest (its first member), None if unreadable."""
    import tarfile

    try:
        with tarfile.open(file, "r:") as tar:
            member = tar.next()
            fh = tar.extractfile(member) if member is not None else None
            name = json.loads(fh.read()).get("map_name") if fh is not None else None
            return name if isinstance(name, str) else None
    except (OSError, tarfile.TarError, ValueError, AttributeError):
        return None


COMMANDS = {"maps": cmd_maps, "status": cmd_status, "upload": cmd_upload, "train": cmd_train,
            "relocalize": cmd_relocalize, "export": cmd_export, "import": cmd_import}


# -- a minimal reader of reloc dataset v1 (the client must not import reloc_service) --------

class DatasetFileError(ValueError):
    """A dataset file is malformed; the message names the file and line."""


@dataclass(frozen=True)
class Entry:
    image_path: str
    camera_id: str
    world_from_cam: wire.WirePose


@dataclass(frozen=True)
class UploadData:
    root: Path
    cameras: dict[str, wire.WireCamera]
    entries: list[Entry]
    depth: dict[str, tuple[str, float]]


def _data_lines(path: Path) -> Iterator[tuple[str, list[str]]]:
    """("file:line", tokens) of each non-blank line, ``#`` comments removed."""
    for lineno, raw in enumerate(path.read_text(encoding="utf-8-sig").splitlines(), 1):
        tokens = raw.split()
        cut = next((i for i, t in enumerate(tokens) if t.startswith("#")), len(tokens))
        if tokens[:cut]:
            yield f"{path}:{lineno}", tokens[:cut]


def read_dataset(root: Path) -> UploadData:
    """``cameras.json``, ``map.txt`` and optional ``depth.txt`` of a reloc dataset v1."""
    cameras = read_cameras(root / "cameras.json")
    entries = []
    for where, tokens in _data_lines(_need(root / "map.txt")):
        if len(tokens) != 9:
            raise DatasetFileError(f"{where}: expected 9 fields '<image path> <camera id> "
                                   f"tx ty tz qx qy qz qw', got {len(tokens)}")
        if tokens[1] not in cameras:
            raise DatasetFileError(f"{where}: unknown camera id {tokens[1]!r}; expected one of "
                                   f"{sorted(cameras)}")
        entries.append(Entry(tokens[0], tokens[1], _pose(tokens[2:], where)))
    depth = {}
    if (root / "depth.txt").is_file():
        for where, tokens in _data_lines(root / "depth.txt"):
            if len(tokens) != 3:
                raise DatasetFileError(f"{where}: expected 3 fields '<image path> <depth png> "
                                       f"<metres per unit>', got {len(tokens)}")
            depth[tokens[0]] = (tokens[1], _positive(tokens[2], where))
    return UploadData(root, cameras, entries, depth)


def read_cameras(path: Path) -> dict[str, wire.WireCamera]:
    """``cameras.json``: camera id -> camera dict."""
    data = _json(_need(path))
    if not isinstance(data, dict) or not data:
        raise DatasetFileError(f"{path}: expected a JSON object mapping camera ids to camera dicts")
    try:
        return {wire.check_name(cid, "camera id"): wire.WireCamera.from_dict(d, f"camera {cid}")
                for cid, d in data.items()}
    except wire.ProtocolError as exc:
        raise DatasetFileError(f"{path}: {exc.message}") from None


def read_camera_json(path: Path) -> wire.WireCamera:
    """A camera dict, or a ``cameras.json`` holding exactly one camera."""
    data = _json(_need(path))
    if isinstance(data, dict) and "model" not in data and len(data) == 1:
        ((_, data),) = data.items()
    if not isinstance(data, dict):
        raise DatasetFileError(f"{path}: expected a camera dict")
    try:
        return wire.WireCamera.from_dict(data)
    except wire.ProtocolError as exc:
        raise DatasetFileError(f"{path}: {exc.message}") from None


def _pose(tokens: list[str], where: str) -> wire.WirePose:
    try:
        values = [float(t) for t in tokens]
        return wire.WirePose.from_tq(values[:3], values[3:], where)
    except ValueError as exc:  # float() or ProtocolError (a ValueError)
        raise DatasetFileError(f"{where}: expected tx ty tz qx qy qz qw as numbers with a unit "
                               f"quaternion ({exc})") from None


def _positive(token: str, where: str) -> float:
    try:
        value = float(token)
    except ValueError:
        value = float("nan")
    if not value > 0 or value == float("inf"):
        raise DatasetFileError(f"{where}: metres per unit {token!r}; expected a positive number")
    return value


def _json(path: Path) -> Any:
    try:
        return json.loads(path.read_text(encoding="utf-8-sig"))
    except json.JSONDecodeError as exc:
        raise DatasetFileError(f"{path}:{exc.lineno}: invalid JSON ({exc.msg})") from None


def _need(path: Path) -> Path:
    if not path.is_file():
        raise DatasetFileError(f"missing {path}")
    return path


def progress(items: Sequence[T] | Iterable[T], desc: str = "") -> Iterator[T]:
    """Yield ``items`` while drawing a progress bar on stderr (only on a terminal)."""
    items = list(items)
    tty = sys.stderr.isatty()
    for i, item in enumerate(items, 1):
        yield item
        if tty:
            filled = int(30 * i / max(len(items), 1))
            print(f"\r{desc} [{'#' * filled}{'.' * (30 - filled)}] {i}/{len(items)}",
                  end="" if i < len(items) else "\n", file=sys.stderr, flush=True)


if __name__ == "__main__":
    sys.exit(main())
