"""The reloc wire protocol, version 1: msgpack messages, their strict decoders, Zenoh keys.

This module is the single definition of the wire format for both ends (the service imports
it); ``docs/protocol.md`` describes the same format field by field for other languages.

Every message is a msgpack map with string keys and ``"v": 1``. Decoding validates
everything and raises :class:`ProtocolError` with an :class:`ErrorCode` and a message that
names the field and what was expected. Optional fields may be absent or nil; encoders omit
them when unset. Unknown fields are refused (``UNKNOWN_FIELD``) so a typo cannot pass
silently. ``encode()`` validates its own output, so it only produces what ``decode`` accepts.

Image bytes are never decoded here (no OpenCV): only their container is checked (format,
stated size against the PNG/JPEG header or the raw length, pixel limits).
"""

from .checks import DEFAULT_LIMITS, PROTOCOL_VERSION, ErrorCode, Limits, ProtocolError
from .geometry import (
    CAMERA_MODELS,
    QUAT_NORM_TOL,
    ROTATION_TOL,
    WireCamera,
    WirePose,
    pose_covariance_problem,
    quat_xyzw_to_rotation,
    rotation_to_quat_xyzw,
    rotation_to_quat_xyzw_array,
)
from .images import DepthFormat, ImageFormat, WireDepth, WireFeatures, WireImage, jpeg_size, png_header
from .keyframe_messages import (
    CameraPut,
    KeyframeInfo,
    KeyframePut,
)
from .keys import DEFAULT_PREFIX, MAX_NAME_LEN, check_name, check_prefix, keys
from .message_base import (
    EventKind,
    Message,
    ReplyStatus,
    unpack_message,
)
from .messages import (
    MESSAGE_TYPES,
    ErrorReply,
    Event,
    StatusReply,
    TrainReply,
    TrainRequest,
    decode_camera_put,
    decode_error_reply,
    decode_event,
    decode_keyframe_info,
    decode_keyframe_put,
    decode_relocalize_reply,
    decode_relocalize_request,
    decode_status_reply,
    decode_train_reply,
    decode_train_request,
    encode_error,
)
from .methods import MethodSpec, MethodStep, split_chain
from .relocalize_messages import (
    Hypothesis,
    Prior,
    RelocalizeReply,
    RelocalizeRequest,
)

__all__ = [
    "PROTOCOL_VERSION", "DEFAULT_PREFIX", "CAMERA_MODELS", "ErrorCode", "ProtocolError", "Limits",
    "DEFAULT_LIMITS", "ImageFormat", "DepthFormat", "ReplyStatus", "EventKind", "keys",
    "check_name", "check_prefix", "WirePose", "WireCamera", "WireImage", "WireDepth",
    "WireFeatures", "Prior", "Hypothesis", "Message", "KeyframePut", "KeyframeInfo", "CameraPut",
    "RelocalizeRequest", "RelocalizeReply", "TrainRequest", "TrainReply", "Event", "StatusReply",
    "ErrorReply", "encode_error", "unpack_message", "png_header", "jpeg_size",
    "quat_xyzw_to_rotation", "rotation_to_quat_xyzw", "pose_covariance_problem",
    "rotation_to_quat_xyzw_array", "MESSAGE_TYPES", "QUAT_NORM_TOL",
    "ROTATION_TOL", "MAX_NAME_LEN", "decode_camera_put", "decode_error_reply", "decode_event",
    "decode_keyframe_info", "decode_keyframe_put", "decode_relocalize_reply",
    "decode_relocalize_request", "decode_status_reply", "decode_train_reply",
    "decode_train_request", "MethodSpec", "MethodStep", "split_chain"]
