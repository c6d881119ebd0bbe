"""Sensor-like depth from exact Z-depth: what a structured-light or time-of-flight RGB-D camera
(Kinect, RealSense) would report for the same view (see :class:`~.presets.DepthSensor`).

Everything is a whole-image array operation; the random draws have fixed shapes, so the
result is a pure function of the inputs and the generator's state.
"""

from __future__ import annotations

import cv2
import numpy as np
import numpy.typing as npt

from .presets import DepthSensor

F32 = npt.NDArray[np.float32]
Mask = npt.NDArray[np.bool_]

REFERENCE_WIDTH_PX = 640  # DepthSensor.edge_band_px is given for a 640 px wide image


def sensor_depth(depth: F32, cos_incidence: F32, sensor: DepthSensor,
                 rng: np.random.Generator) -> F32:
    """(H, W) float32 sensor depth in metres, 0 where the sensor has no value, from the exact
    Z-depth ``depth`` (0: no surface) and the cosine of each pixel's incidence angle: axial
    noise ``k z^2``, then holes out of range, at grazing incidence, near discontinuities and at
    random. Quantisation happens when it is written in ``sensor.metres_per_unit``."""
    noise = rng.standard_normal(depth.shape, dtype=np.float32)
    dropout = rng.random(depth.shape) < sensor.dropout_fraction
    valid = ((depth >= sensor.min_range_m) & (depth <= sensor.max_range_m)
             & (cos_incidence >= np.float32(np.cos(np.radians(sensor.max_incidence_deg))))
             & ~near_discontinuity(depth, sensor) & ~dropout)
    noisy = depth + noise * np.float32(sensor.axial_noise_per_m2) * depth * depth
    return np.where(valid & (noisy > 0), noisy, np.float32(0.0)).astype(np.float32)


def near_discontinuity(depth: F32, sensor: DepthSensor) -> Mask:
    """Pixels within ``edge_band_px`` (scaled to the image width) of a depth discontinuity:
    a step to a 4-neighbour above ``discontinuity_rel`` of the nearer depth, or a neighbour
    without a surface."""
    z = depth.astype(np.float32)
    edge = np.zeros(z.shape, dtype=bool)
    for axis in (0, 1):
        a = z[:-1, :] if axis == 0 else z[:, :-1]
        b = z[1:, :] if axis == 0 else z[:, 1:]
        step = (np.abs(a - b) > np.float32(sensor.discontinuity_rel) * np.minimum(a, b)) | (
            (a > 0) != (b > 0))
        if axis == 0:
            edge[:-1, :] |= step
            edge[1:, :] |= step
        else:
            edge[:, :-1] |= step
            edge[:, 1:] |= step
    band = int(round(sensor.edge_band_px * z.shape[1] / REFERENCE_WIDTH_PX))
    if band < 1:
        return edge
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * band + 1, 2 * band + 1))
    return cv2.dilate(edge.astype(np.uint8), kernel).astype(bool)
