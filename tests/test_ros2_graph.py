"""Golden tests of the rmw_zenoh formats (service/ros2/graph.py, types.py): data keys,
liveliness tokens, QoS strings, GIDs, the 33-byte attachment, RIHS01 type hashes and CDR.
Expected values are written out by hand from rmw_zenoh's design document and sources, the
official type description hashes and the xxHash reference vectors, not computed by our code."""

from __future__ import annotations

import pytest

from reloc_service.service.ros2 import graph
from reloc_service.service.ros2 import types as ros

# The official RIHS01 hashes (rosidl-generated type description JSON of Jazzy).
OFFICIAL = {
    "geometry_msgs/msg/PoseWithCovarianceStamped":
        "RIHS01_26432f9803e43727d3c8f668d1fdb3c630f548af631e2f4e31382371bfea3b6e",
    "sensor_msgs/msg/CompressedImage":
        "RIHS01_15640771531571185e2efc8a100baf923961a4d15d5569652e6cb6691e8e371a",
    "sensor_msgs/msg/Image":
        "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47",
    "std_srvs/srv/Trigger":
        "RIHS01_eeff2cd6fa5ad9d27cdf4dec64818317839b62f212a91e6b5304b634b2062c5f",
}


@pytest.mark.parametrize("ros_type", sorted(OFFICIAL))
def test_type_hashes_are_the_official_ones(ros_type):
    assert ros.type_hash(ros_type) == OFFICIAL[ros_type]


def test_rosbags_own_hash_gets_char_wrong_and_ours_does_not():
    """rosbags gives ``char`` FIELD_TYPE_CHAR; rosidl writes uint8 (a .msg char is an IDL
    uint8). ServiceEventInfo (inside every service type) has a char[16]: the two hashes
    differ there, and only ours gives the official Trigger hash above."""
    store = ros.typestore()
    event_info = "service_msgs/msg/ServiceEventInfo"
    assert store.hash_rihs01(event_info) != ros.type_hash(event_info)
    for plain in ("nav_msgs/msg/Odometry", "sensor_msgs/msg/CameraInfo", "std_msgs/msg/Bool",
                  "geometry_msgs/msg/PoseStamped"):   # no char: both agree
        assert store.hash_rihs01(plain) == ros.type_hash(plain)


def test_key_hash_per_distro_and_overrides():
    pwcs = "geometry_msgs/msg/PoseWithCovarianceStamped"
    assert ros.key_hash(pwcs, "jazzy", {}) == OFFICIAL[pwcs]
    assert ros.key_hash(pwcs, "humble", {}) == "TypeHashNotSupported"
    assert ros.key_hash(pwcs, "jazzy", {pwcs: "RIHS01_00"}) == "RIHS01_00"
    with pytest.raises(ValueError, match="no type description"):
        ros.type_hash("my_msgs/msg/Unknown")
    with pytest.raises(ValueError, match="package/msg/Name"):
        ros.type_hash("Unknown")


def test_dds_names():
    assert ros.dds_name("geometry_msgs/msg/PoseWithCovarianceStamped") == \
        "geometry_msgs::msg::dds_::PoseWithCovarianceStamped_"
    assert ros.dds_name("std_srvs/srv/Trigger") == "std_srvs::srv::dds_::Trigger_"


def test_data_key_is_domain_name_type_hash():
    key = graph.data_key(0, "/reloc/pose", "geometry_msgs::msg::dds_::PoseWithCovarianceStamped_",
                         OFFICIAL["geometry_msgs/msg/PoseWithCovarianceStamped"])
    assert key == ("0/reloc/pose/geometry_msgs::msg::dds_::PoseWithCovarianceStamped_/"
                   "RIHS01_26432f9803e43727d3c8f668d1fdb3c630f548af631e2f4e31382371bfea3b6e")
    assert graph.data_key(7, "camera/image", "T_", "TypeHashNotSupported") == \
        "7/camera/image/T_/TypeHashNotSupported"


@pytest.mark.parametrize("qos, expected", [
    (graph.Qos(depth=10), "::,10:,:,:,,"),
    (graph.Qos(depth=42), "::,:,:,:,,"),                       # all rmw_zenoh defaults
    (graph.Qos(depth=5, reliability=graph.Reliability.BEST_EFFORT), "2::,5:,:,:,,"),
    (graph.Qos(depth=1, durability=graph.Durability.TRANSIENT_LOCAL), ":1:,1:,:,:,,"),
])
def test_qos_strings(qos, expected):
    assert qos.encode() == expected


def test_node_and_endpoint_tokens():
    node = graph.Node(0, "1f2e3d4c5b6a79880f1e2d3c4b5a6978", 3, "reloc", "/reloc/desk")
    assert node.token() == ("@ros2_lv/0/1f2e3d4c5b6a79880f1e2d3c4b5a6978/3/3/NN/%/%reloc%desk/"
                            "reloc")
    pose = node.endpoint_token(4, graph.EntityKind.PUBLISHER, "/reloc/desk/pose",
                               "geometry_msgs::msg::dds_::PoseWithCovarianceStamped_",
                               OFFICIAL["geometry_msgs/msg/PoseWithCovarianceStamped"],
                               graph.Qos(depth=10))
    assert pose == ("@ros2_lv/0/1f2e3d4c5b6a79880f1e2d3c4b5a6978/3/4/MP/%/%reloc%desk/reloc/"
                    "%reloc%desk%pose/geometry_msgs::msg::dds_::PoseWithCovarianceStamped_/"
                    "RIHS01_26432f9803e43727d3c8f668d1fdb3c630f548af631e2f4e31382371bfea3b6e/"
                    "::,10:,:,:,,")
    service = node.endpoint_token(9, graph.EntityKind.SERVICE, "/reloc/desk/relocalize",
                                  "std_srvs::srv::dds_::Trigger_", "TypeHashNotSupported",
                                  graph.Qos(depth=10))
    assert service.split("/")[5] == "SS" and service.endswith(
        "/%reloc%desk%relocalize/std_srvs::srv::dds_::Trigger_/TypeHashNotSupported/::,10:,:,:,,")
    parsed = graph.parse_token(pose)
    assert parsed == graph.Endpoint(
        zid="1f2e3d4c5b6a79880f1e2d3c4b5a6978", kind=graph.EntityKind.PUBLISHER,
        node="reloc", name="/reloc/desk/pose",
        dds_type="geometry_msgs::msg::dds_::PoseWithCovarianceStamped_",
        type_hash=OFFICIAL["geometry_msgs/msg/PoseWithCovarianceStamped"])
    assert graph.parse_token(node.token()) is None
    assert graph.parse_token("reloc/@live/a/b") is None
    with pytest.raises(ValueError):
        node.endpoint_token(1, graph.EntityKind.NODE, "/x", "T_", "H", graph.Qos())


def test_gid_is_xxh3_128_low_then_high_little_endian():
    # xxHash's reference: XXH3_128bits("") = high 99aa06d3014798d8, low 6001c324468d497f.
    assert graph.gid_of("") == bytes.fromhex("7f498d4624c30160" "d8984701d306aa99")
    token = "@ros2_lv/0/abc/0/0/NN/%/%/reloc"
    assert len(graph.gid_of(token)) == 16 and graph.gid_of(token) != graph.gid_of(token + "x")


def test_attachment_is_33_bytes_seq_stamp_len16_gid():
    gid = bytes(range(16))
    data = graph.Attachment(5, 1_700_000_000_123_456_789, gid).encode()
    assert data == bytes.fromhex("0500000000000000" "15cd853dfe9c9717" "10"
                                 "000102030405060708090a0b0c0d0e0f")
    assert graph.Attachment.decode(data) == graph.Attachment(5, 1_700_000_000_123_456_789, gid)
    with pytest.raises(ValueError, match="no attachment"):
        graph.Attachment.decode(None)
    with pytest.raises(ValueError, match="33 bytes"):
        graph.Attachment.decode(data[:-1])
    with pytest.raises(ValueError, match="length byte"):
        graph.Attachment.decode(data[:16] + b"\x0f" + data[17:])
    with pytest.raises(ValueError, match="16 bytes"):
        graph.Attachment(1, 2, b"short").encode()


def test_cdr_has_the_little_endian_header_and_rejects_garbage():
    response = ros.message("std_srvs/srv/Trigger_Response", success=True, message="hi")
    # header, bool, padding to 4, uint32 length with the NUL, "hi\0"
    assert ros.encode(response, "std_srvs/srv/Trigger_Response") == bytes.fromhex(
        "00010000" "01000000" "03000000" "686900")
    back = ros.decode(bytes.fromhex("0001000000000000050000006e6f706500"),
                      "std_srvs/srv/Trigger_Response")
    assert back.success is False and back.message == "nope"
    with pytest.raises(ValueError, match="header"):
        ros.decode(b"\x01\x02", "std_srvs/srv/Trigger_Response")
    with pytest.raises(ValueError, match="does not decode"):
        ros.decode(bytes.fromhex("00010000ff"), "geometry_msgs/msg/PoseWithCovarianceStamped")
