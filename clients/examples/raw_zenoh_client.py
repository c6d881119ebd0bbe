"""Relocalize one image with nothing but zenoh, msgpack and OpenCV (written from
docs/protocol.md alone, without reloc_client): a template for clients in other languages.

    python clients/examples/raw_zenoh_client.py --connect tcp/127.0.0.1:7447 --map lab \
        --camera-id cam0 query.png
"""

from __future__ import annotations

import argparse
import json
import sys

import cv2
import msgpack
import zenoh


def build_request(image_path: str, camera_id: str | None, camera: dict | None,
                  method: str | None) -> dict:
    """A RelocalizeRequest map (docs/protocol.md): grey JPEG image and one camera field."""
    grey = cv2.imread(image_path, cv2.IMREAD_GRAYSCALE)
    if grey is None:
        raise SystemExit(f"cannot read image {image_path}")
    ok, jpeg = cv2.imencode(".jpg", grey, [cv2.IMWRITE_JPEG_QUALITY, 95])
    if not ok:
        raise SystemExit("JPEG encoding failed")
    height, width = grey.shape
    request = {"v": 1,
               "image": {"format": "jpeg", "width": width, "height": height,
                         "data": jpeg.tobytes()}}
    if camera_id is not None:
        request["camera_id"] = camera_id
    else:
        request["camera"] = camera
    if method:
        request["method"] = method
    return request


def print_reply(answer: dict) -> int:
    """Print a RelocalizeReply; exit code 0 if relocalized, 1 otherwise."""
    if answer["status"] != "ok":
        print(f"not relocalized ({answer['status']}): {answer.get('reason', '')}")
        return 1
    pose = answer["world_from_cam"]
    tx, ty, tz = pose["t"]
    qx, qy, qz, qw = pose["q"]
    print(f"world_from_cam: t = [{tx:.4f} {ty:.4f} {tz:.4f}] m, "
          f"q (x y z w) = [{qx:.5f} {qy:.5f} {qz:.5f} {qw:.5f}]")
    print(f"method {answer.get('method')}, confidence {answer.get('confidence', 0):.2f}, "
          f"inliers {answer.get('inliers', 0)}, map version {answer.get('map_version')}")
    print("timings (s):", answer.get("timings", {}))
    return 0


def main(conf: zenoh.Config, key: str, request: dict, timeout: float) -> int:
    with zenoh.open(conf) as session:
        for reply in session.get(key, payload=msgpack.packb(request, use_bin_type=True),
                                 timeout=timeout):
            if reply.ok is not None:
                return print_reply(msgpack.unpackb(reply.ok.payload.to_bytes(), raw=False))
            payload = reply.err.payload.to_bytes()
            try:
                error = msgpack.unpackb(payload, raw=False)["error"]
                print(f"service error {error['code']}: {error['message']}", file=sys.stderr)
            except Exception:  # e.g. Zenoh's own "Timeout"
                print(f"error reply: {payload!r}", file=sys.stderr)
            return 2
    print(f"no reply on {key}: is a service serving this map reachable?", file=sys.stderr)
    return 3


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("image", help="PNG or JPEG image to relocalize")
    parser.add_argument("--connect", "-e", action="append", help="Zenoh endpoint(s)")
    parser.add_argument("--map", required=True)
    parser.add_argument("--prefix", default="reloc")
    group = parser.add_mutually_exclusive_group(required=True)
    group.add_argument("--camera-id")
    group.add_argument("--camera-json", help="file with a camera dict")
    parser.add_argument("--method")
    parser.add_argument("--timeout", type=float, default=10.0)
    args = parser.parse_args()

    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    if args.connect:
        conf.insert_json5("connect/endpoints", json.dumps(args.connect))
        conf.insert_json5("scouting/multicast/enabled", "false")
    camera = None
    if args.camera_json:
        with open(args.camera_json) as f:
            camera = json.load(f)
    request = build_request(args.image, args.camera_id, camera, args.method)
    sys.exit(main(conf, f"{args.prefix}/{args.map}/relocalize", request, args.timeout))
