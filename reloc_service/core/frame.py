"""Frames, keyframes and their features: grey image, camera, pyramid, small blurry image."""

from __future__ import annotations

import dataclasses
import functools
import threading
from collections import OrderedDict
from collections.abc import Callable, MutableMapping
from dataclasses import dataclass, field
from typing import Any, ClassVar, cast

import cv2
import numpy as np
import numpy.typing as npt

from .cameras import Camera
from .errors import ConfigError, GeometryError, MapError
from .geometry import check_pose, check_pose_covariance
from .numeric import numba_or_none

Array = npt.NDArray[np.float64]

#: Width of a SIFT descriptor. SIFT descriptors are kept as uint8 (OpenCV's values are
#: integers 0-255 stored as float32: lossless, 4x smaller), so uint8 alone no longer means
#: packed binary bits; :func:`is_binary_descriptor` tells the two apart by width.
SIFT_DIM = 128


def is_binary_descriptor(descriptors: npt.NDArray[Any]) -> bool:
    """True for packed binary descriptors (ORB: uint8, 32 bytes), compared by Hamming
    distance; False for SIFT (uint8 or float, 128 values), compared by L2."""
    return descriptors.dtype == np.uint8 and descriptors.shape[-1] != SIFT_DIM


@dataclass(frozen=True, eq=False)
class Features:
    """Keypoints of one kind (``"sift"``, ``"orb"``) in one image, with what is known of them.

    Attributes (N = number of keypoints):
        kind: name of the detector/descriptor.
        keypoints_px: (N, 2) float64 pixel positions in the full-resolution image.
        levels: (N,) int16 pyramid level (octave) where the keypoint was found.
        sizes: (N,) float32 keypoint diameter in pixels; angles: (N,) float32 degrees (OpenCV;
            -1 where unknown: given keypoints, and ORB keypoints of a loaded map).
        descriptors: (N, D) uint8: SIFT's 128 integer values 0-255 (see :data:`SIFT_DIM`),
            or ORB's packed bits; float32 SIFT (client-given, older maps) is accepted too.
        landmark_ids: (N,) int64 map landmark of each keypoint, -1 where none.
        points_world: (N, 3) float64 landmark positions in the world frame, NaN where none.
    """

    kind: str
    keypoints_px: Array
    levels: npt.NDArray[np.int16]
    sizes: npt.NDArray[np.float32]
    angles: npt.NDArray[np.float32]
    descriptors: npt.NDArray[Any]
    landmark_ids: npt.NDArray[np.int64]
    points_world: Array

    def __post_init__(self) -> None:
        n = len(self.keypoints_px)
        shapes = {"keypoints_px": (self.keypoints_px.shape, (n, 2)),
                  "levels": (self.levels.shape, (n,)), "sizes": (self.sizes.shape, (n,)),
                  "angles": (self.angles.shape, (n,)),
                  "landmark_ids": (self.landmark_ids.shape, (n,)),
                  "points_world": (self.points_world.shape, (n, 3))}
        for name, (got, want) in shapes.items():
            if got != want:
                raise GeometryError(f"Features.{name}: expected shape {want}, got {got}")
        if self.descriptors.ndim != 2 or len(self.descriptors) != n:
            raise GeometryError(f"Features.descriptors: expected ({n}, D), got {self.descriptors.shape}")

    def __len__(self) -> int:
        return len(self.keypoints_px)

    @classmethod
    def create(cls, kind: str, keypoints_px: npt.ArrayLike, descriptors: npt.ArrayLike, *,
               levels: npt.ArrayLike | None = None, sizes: npt.ArrayLike | None = None,
               angles: npt.ArrayLike | None = None, landmark_ids: npt.ArrayLike | None = None,
               points_world: npt.ArrayLike | None = None) -> Features:
        """Build features with defaults: level 0, size 8 px, angle -1, no landmarks."""
        kp = np.asarray(keypoints_px, dtype=np.float64).reshape(-1, 2)
        n = len(kp)
        return cls(
            kind=kind, keypoints_px=kp,
            levels=np.zeros(n, np.int16) if levels is None else np.asarray(levels, np.int16),
            sizes=np.full(n, 8.0, np.float32) if sizes is None else np.asarray(sizes, np.float32),
            angles=np.full(n, -1.0, np.float32) if angles is None else np.asarray(angles, np.float32),
            descriptors=np.asarray(descriptors).reshape(n, -1) if n else np.asarray(descriptors),
            landmark_ids=(np.full(n, -1, np.int64) if landmark_ids is None
                          else np.asarray(landmark_ids, np.int64)),
            points_world=(np.full((n, 3), np.nan) if points_world is None
                          else np.asarray(points_world, np.float64).reshape(n, 3)))

    @property
    def has_landmark(self) -> npt.NDArray[np.bool_]:
        """(N,) mask of keypoints associated with a landmark."""
        return self.landmark_ids >= 0

    def with_landmarks(self, indices: npt.ArrayLike, landmark_ids: npt.ArrayLike,
                       points_world: npt.ArrayLike) -> Features:
        """A copy where keypoints ``indices`` get ``landmark_ids`` and ``points_world``."""
        idx = np.asarray(indices, dtype=np.int64)
        ids = self.landmark_ids.copy()
        pts = self.points_world.copy()
        ids[idx] = np.asarray(landmark_ids, dtype=np.int64)
        pts[idx] = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
        return dataclasses.replace(self, landmark_ids=ids, points_world=pts)

    def take(self, rows: npt.ArrayLike) -> Features:
        """A copy of keypoints ``rows`` (indices) only."""
        idx = np.asarray(rows, dtype=np.int64)
        return dataclasses.replace(
            self, keypoints_px=self.keypoints_px[idx], levels=self.levels[idx],
            sizes=self.sizes[idx], angles=self.angles[idx], descriptors=self.descriptors[idx],
            landmark_ids=self.landmark_ids[idx], points_world=self.points_world[idx])

    def cv_keypoints(self, indices: npt.ArrayLike | None = None) -> list[cv2.KeyPoint]:
        """OpenCV keypoints (for computing descriptors at known positions)."""
        idx = range(len(self)) if indices is None else np.asarray(indices)
        return [cv2.KeyPoint(float(self.keypoints_px[i, 0]), float(self.keypoints_px[i, 1]),
                             float(self.sizes[i]), float(self.angles[i]), 0.0, int(self.levels[i]))
                for i in idx]


def check_grey_image(image: npt.ArrayLike, camera: Camera | None = None) -> npt.NDArray[np.uint8]:
    """Return ``image`` as a contiguous (H, W) uint8 array; check its size against ``camera``."""
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] in (3, 4):
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY if img.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    if img.ndim != 2 or img.dtype != np.uint8:
        raise GeometryError(f"image: expected (H, W) uint8 grey, got shape {img.shape} {img.dtype}")
    if camera is not None and (img.shape[1], img.shape[0]) != camera.size:
        raise GeometryError(f"image: size {img.shape[1]}x{img.shape[0]} does not match the "
                            f"camera's {camera.width}x{camera.height}")
    return np.ascontiguousarray(img)


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_JPEG_SIGNATURE = b"\xff\xd8\xff"


class EncodedImage:
    """A grey image kept compressed (bytes or a read-only memory map of a file) until a
    :class:`Frame` first needs its pixels: a loaded map holds 1000s of keyframe images that
    most queries never look at (the place finders read thumbnails, the pose finders
    features). PNG (its size read from IHDR) or JPEG (the size given: ``shape``, (H, W));
    decoded to grey as the service decodes a client's image (``cv2.IMREAD_GRAYSCALE``), so
    a keyframe kept as the JPEG a client sent has the pixels its features came from."""

    __slots__ = ("data", "shape", "format")

    def __init__(self, data: bytes | npt.NDArray[np.uint8],
                 shape: tuple[int, int] | None = None) -> None:
        head = bytes(data[:24])
        if len(head) >= 24 and head[:8] == _PNG_SIGNATURE and head[12:16] == b"IHDR":
            self.format = "png"
            # IHDR: big-endian width and height, so the size is known without decoding.
            png_shape = (int.from_bytes(head[20:24], "big"), int.from_bytes(head[16:20], "big"))
            if shape is not None and tuple(shape) != png_shape:
                raise GeometryError(f"encoded image: PNG of {png_shape}, expected {shape}")
            shape = png_shape
        elif head[:3] == _JPEG_SIGNATURE and shape is not None:
            self.format = "jpg"
        else:
            raise GeometryError("encoded image: expected a PNG file, or a JPEG file and its "
                                "(height, width)")
        self.data = data
        self.shape = (int(shape[0]), int(shape[1]))

    def decode(self) -> npt.NDArray[np.uint8]:
        """The grey pixels, read-only: the ones decoded last time while they are among the
        recently decoded (:data:`RECENT_PIXELS`), else decoded now (and remembered)."""
        image = RECENT_PIXELS.get(self)
        if image is None:
            decoded = cv2.imdecode(np.frombuffer(self.data, np.uint8), cv2.IMREAD_GRAYSCALE)
            if decoded is None or decoded.shape != self.shape or decoded.dtype != np.uint8:
                raise GeometryError(f"encoded image: expected a {self.format.upper()} that "
                                    f"decodes to {self.shape} grey pixels")
            # checked uint8 just above (OpenCV's stubs type every image as any numeric array)
            image = self.remember(cast(npt.NDArray[np.uint8], decoded))
        return image

    def remember(self, pixels: npt.NDArray[np.uint8]) -> npt.NDArray[np.uint8]:
        """Record ``pixels`` as what this image decodes to (the service decodes a client's
        JPEG to check it: the map then reuses those pixels instead of decoding again); returns
        a read-only view of them, which every later reader shares (``pixels`` itself stays as
        it was)."""
        if pixels.shape != self.shape or pixels.dtype != np.uint8:
            raise GeometryError(f"encoded image: pixels of {pixels.shape} {pixels.dtype}, "
                                f"expected {self.shape} uint8")
        pixels = np.asarray(pixels).view()
        pixels.flags.writeable = False
        RECENT_PIXELS.put(self, pixels)
        return pixels

    def tobytes(self) -> bytes:
        return bytes(self.data)

    def __len__(self) -> int:
        return len(self.data)


class RecentPixels:
    """The decoded pixels of the last few :class:`EncodedImage` s read, at most ``max_bytes``
    in all (least recently used dropped first). A keyframe keeps its image encoded (a live
    map of 1000 VGA keyframes would otherwise hold 300 MB of pixels nobody reads after
    mapping); the few readers of its pixels in a row (feature extraction, the place finders'
    thumbnails, ferns training) share one decode through this. Thread-safe."""

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = max_bytes
        self._lock = threading.Lock()
        # id -> (image, pixels): the image is held so its id is not reused while listed
        self._items: OrderedDict[int, tuple[EncodedImage, npt.NDArray[np.uint8]]] = OrderedDict()
        self._bytes = 0

    def get(self, image: EncodedImage) -> npt.NDArray[np.uint8] | None:
        with self._lock:
            item = self._items.get(id(image))
            if item is None or item[0] is not image:
                return None
            self._items.move_to_end(id(image))
            return item[1]

    def put(self, image: EncodedImage, pixels: npt.NDArray[np.uint8]) -> None:
        if pixels.nbytes > self.max_bytes:
            return
        with self._lock:
            old = self._items.pop(id(image), None)
            if old is not None:
                self._bytes -= old[1].nbytes
            self._items[id(image)] = (image, pixels)
            self._bytes += pixels.nbytes
            while self._bytes > self.max_bytes:
                _, (_, dropped) = self._items.popitem(last=False)
                self._bytes -= dropped.nbytes

    def __len__(self) -> int:
        return len(self._items)


#: Shared by every :class:`EncodedImage` of the process: 8 MiB, about 27 VGA images (a
#: burst of queued keyframe puts, each decoded by the service once to be checked).
RECENT_PIXELS = RecentPixels(8 << 20)


@dataclass(frozen=True)
class ThumbnailConf:
    """PTAM's small blurry image (thesis 3.1.1): size in pixels and Gaussian blur sigma."""

    width: int = 40
    height: int = 30
    blur_sigma: float = 2.5

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0 or self.blur_sigma < 0:
            raise ConfigError(f"small blurry image: expected positive width/height and "
                              f"blur_sigma >= 0, got {self.width}x{self.height}, "
                              f"sigma {self.blur_sigma}")


@dataclass(eq=False)
class Frame:
    """One image to relocalize (or the image part of a keyframe): grey (H, W) uint8 image and
    the camera that took it.

    ``cache`` holds derived data (pyramid, small blurry image, features of each kind), computed
    on first use by whichever module needs it; keys are namespaced by that module.
    """

    image: npt.NDArray[np.uint8]
    camera: Camera
    features: MutableMapping[str, Features] = field(default_factory=dict)
    cache: dict[str, Any] = field(default_factory=dict, repr=False)
    #: Ground-truth pose, set only by evaluation (the ``gt`` place finder refuses to run without).
    gt_world_from_cam: Array | None = None
    #: Whether an encoded image, once decoded, is replaced by its pixels (a query's: read
    #: all through the query) or stays encoded (a keyframe's: read while it is mapped, then
    #: hardly ever, and a map holds thousands).
    keeps_pixels: ClassVar[bool] = True

    def __post_init__(self) -> None:
        source = self.image_source
        if isinstance(source, EncodedImage):
            if (source.shape[1], source.shape[0]) != self.camera.size:
                raise GeometryError(f"image: size {source.shape[1]}x{source.shape[0]} does not "
                                    f"match the camera's {self.camera.width}x{self.camera.height}")
        else:
            self.image = check_grey_image(source, self.camera)
        if self.gt_world_from_cam is not None:
            self.gt_world_from_cam = check_pose(self.gt_world_from_cam, name="gt_world_from_cam")

    @property
    def image_source(self) -> npt.NDArray[np.uint8] | EncodedImage:
        """The image as held: pixels, or an :class:`EncodedImage` (not decoded yet, or a
        keyframe's: see :attr:`keeps_pixels`)."""
        return self.__dict__["_image"]  # type: ignore[no-any-return]

    @property
    def image_shape(self) -> tuple[int, int]:
        """(H, W) of the image, without decoding it."""
        source = self.image_source
        return source.shape if isinstance(source, EncodedImage) else source.shape[:2]

    def features_of(self, kind: str, extract: Callable[[], Features]) -> Features:
        """``features[kind]``: cached; else the extraction started ahead for it
        (:meth:`expect_features`), waited for; else ``extract()`` now, then cached. An
        extraction ahead that failed is run again here, so its error reaches this caller."""
        feats = self.features.get(kind)
        if feats is not None:
            return feats
        pending = self.cache.pop(_pending_key(kind), None)
        if pending is not None:
            try:
                pending.result()
            except Exception:  # noqa: BLE001, S110 (extract() below meets it again)
                pass
            feats = self.features.get(kind)
            if feats is not None:
                return feats
        feats = self.features[kind] = extract()
        return feats

    def expect_features(self, kind: str, pending: Any) -> None:
        """Note that ``features[kind]`` is being extracted elsewhere (another thread) and
        will be stored when ``pending.result()`` returns: :meth:`features_of` waits for it
        rather than extracting the same features twice."""
        self.cache[_pending_key(kind)] = pending

    def pending_features(self, kind: str) -> bool:
        """Whether an extraction of ``kind`` started ahead has not been waited for yet."""
        return _pending_key(kind) in self.cache

    def pyramid(self, levels: int) -> list[npt.NDArray[np.uint8]]:
        """``levels`` images, each half the size of the previous (level 0 = the image)."""
        key = f"pyramid:{levels}"
        if key not in self.cache:
            pyr = [self.image]
            for _ in range(levels - 1):
                # pyrDown keeps the uint8 dtype (OpenCV's stubs type every image as any numeric array)
                pyr.append(cast(npt.NDArray[np.uint8], cv2.pyrDown(pyr[-1])))
            self.cache[key] = pyr
        return self.cache[key]

    def small_blurry_image(self, width: int = 40, height: int = 30, sigma: float = 2.5) -> Array:
        """PTAM's small blurry image (thesis 3.1.1): resized to ``width`` x ``height``, Gaussian
        blurred with ``sigma``, zero mean; (height, width) float32."""
        key = f"sbi:{width}x{height}:{sigma}"
        if key not in self.cache:
            small = area_downscale(self.image, width, height)
            blurred = cv2.GaussianBlur(small.astype(np.float32), (0, 0), sigma)
            self.cache[key] = blurred - blurred.mean()
        return self.cache[key]


def _pending_key(kind: str) -> str:
    return f"features-pending:{kind}"


def area_downscale(image: npt.NDArray[np.uint8], width: int, height: int
                   ) -> npt.NDArray[np.uint8]:
    """``cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)`` of a grey uint8
    image: where the image is 4, 8, 16 or 32 times the size along both axes and numba is
    installed (the ``[jit]`` extra), one compiled pass with OpenCV's values (each block's
    sum over its area, rounded half to even: exact for a power-of-two area; 640x480 to
    40x30 about 0.05 ms against OpenCV's 0.13), else OpenCV."""
    h, w = image.shape[:2]
    factor = w // width
    kernel = _compiled_block_means() if image.ndim == 2 and image.dtype == np.uint8 else None
    if (kernel is None or factor not in (4, 8, 16, 32) or w != factor * width
            or h != factor * height):
        # resize keeps the uint8 dtype (OpenCV's stubs type every image as any numeric array)
        return cast(npt.NDArray[np.uint8], cv2.resize(image, (width, height),
                                                      interpolation=cv2.INTER_AREA))
    out = np.empty((height, width), np.uint8)
    kernel(np.ascontiguousarray(image), factor, 2 * factor.bit_length() - 2, out)
    return out


def _block_means(image: npt.NDArray[np.uint8], factor: int, shift: int,
                 out: npt.NDArray[np.uint8]) -> None:
    """Means of the ``factor`` x ``factor`` blocks of ``image`` into ``out``: the sum over
    ``2^shift`` pixels, rounded half to even (``cvRound`` of OpenCV's ``sum * (1.f / area)``,
    exact here). Rows are summed column by column first (a vectorised pass per row)."""
    rows, cols = out.shape
    acc = np.zeros(cols * factor, np.int32)
    half = 1 << (shift - 1)
    for oy in range(rows):
        acc[:] = 0
        for y in range(oy * factor, oy * factor + factor):
            row = image[y]
            for x in range(cols * factor):
                acc[x] += row[x]
        for ox in range(cols):
            total = 0
            for x in range(ox * factor, ox * factor + factor):
                total += acc[x]
            mean = total >> shift
            rest = total - (mean << shift)
            if rest > half or (rest == half and mean & 1):
                mean += 1
            out[oy, ox] = mean


@functools.cache
def _compiled_block_means() -> Callable[..., None] | None:
    """:func:`_block_means` compiled by numba (cached on disk), or None without numba."""
    numba = numba_or_none()
    if numba is None:
        return None
    kernel: Callable[..., None] = numba.njit(cache=True, nogil=True)(_block_means)
    return kernel


@dataclass(eq=False)
class Keyframe(Frame):
    """A mapped frame: a :class:`Frame` with an id, its ``world_from_cam`` pose and metadata.

    ``depth`` is an optional (H, W) float32 Z-depth in metres (NaN where unknown).
    ``encoded`` is the compressed image the pixels decode to exactly (what a client sent, or
    the file a snapshot holds), kept to be saved as it is: set from an encoded ``image``,
    or given with decoded pixels. A keyframe with one holds its image encoded only (its
    pixels are decoded when read, shared through :data:`RECENT_PIXELS` while read in a row).
    ``pose_covariance`` is the optional (6, 6) covariance of ``world_from_cam`` (twist
    (rho, omega), right perturbation ``world_from_cam @ exp(xi)``, metres and radians): how
    far the pose it was put with may be from the truth. None: not given (the map's default,
    :meth:`~.map.MapState.pose_covariances`, applies).
    """

    id: int = -1
    world_from_cam: Array = field(default_factory=lambda: np.eye(4))
    timestamp: float | None = None
    depth: npt.NDArray[np.float32] | None = None
    encoded: EncodedImage | None = field(default=None, repr=False)
    pose_covariance: Array | None = field(default=None, repr=False)
    keeps_pixels: ClassVar[bool] = False

    def __post_init__(self) -> None:
        source = self.image_source
        if isinstance(source, EncodedImage):
            self.encoded = source
        elif self.encoded is not None:
            if self.encoded.shape != np.shape(source)[:2]:
                raise GeometryError(f"keyframe {self.id}: encoded image of "
                                    f"{self.encoded.shape}, pixels of {np.shape(source)[:2]}")
            # Held encoded (the pixels are what it decodes to, shared while read in a row).
            self.image = self.encoded  # type: ignore[assignment]  # the property takes both
            if RECENT_PIXELS.get(self.encoded) is None:   # else they are remembered already
                self.encoded.remember(check_grey_image(source))
        super().__post_init__()
        if isinstance(self.id, bool) or not isinstance(self.id, int | np.integer) or self.id < 0:
            raise MapError(f"keyframe id must be a non-negative integer, got {self.id!r}")
        self.id = int(self.id)
        self.world_from_cam = check_pose(self.world_from_cam, name=f"keyframe {self.id} world_from_cam")
        if self.pose_covariance is not None:
            self.pose_covariance = check_pose_covariance(
                self.pose_covariance, name=f"keyframe {self.id} pose_covariance")
        if self.depth is not None and self.depth.shape != self.image_shape:
            raise GeometryError(f"keyframe {self.id}: depth shape {self.depth.shape} != image "
                                f"shape {self.image_shape}")

    @property
    def position_world(self) -> Array:
        """(3,) camera centre in the world frame."""
        return self.world_from_cam[:3, 3]

    def with_features(self, kind: str, features: Features) -> Keyframe:
        """A shallow copy whose ``features[kind]`` is replaced (image and cache are shared;
        an encoded image stays encoded)."""
        # ``image`` is typed as the pixels it reads as; its setter (the property below) also
        # takes an EncodedImage, which a dataclass field's type cannot say.
        new = dataclasses.replace(self, image=self.image_source,  # type: ignore[arg-type]
                                  features={**self.features, kind: features})
        new.cache = self.cache
        return new


def _get_image(frame: Frame) -> npt.NDArray[np.uint8]:
    """``Frame.image``: the pixels, decoded on first use when held encoded. A query frame
    then keeps them (two threads decoding at once each store the same pixels: a duplicate
    decode, no torn state); a keyframe stays encoded, its pixels shared through
    :data:`RECENT_PIXELS` while they are read in a row."""
    image = frame.__dict__["_image"]
    if isinstance(image, EncodedImage):
        pixels = check_grey_image(image.decode(), frame.camera)
        if frame.keeps_pixels:
            frame.__dict__["_image"] = pixels
        return pixels
    return image  # type: ignore[no-any-return]


def _set_image(frame: Frame, image: npt.NDArray[np.uint8] | EncodedImage) -> None:
    frame.__dict__["_image"] = image


# The dataclass field ``image`` (set by the generated __init__) goes through this property,
# so an EncodedImage given to a keyframe stays encoded until its pixels are read.
Frame.image = property(_get_image, _set_image)  # type: ignore[assignment,method-assign]
