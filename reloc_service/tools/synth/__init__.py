"""Photoreal synthetic relocalization datasets with exact ground truth (``reloc synth``).

A room or desk scene of textured rectangles and boxes (real photographs from scikit-image,
at known physical sizes) is ray cast per pixel through the camera model, along a training lap
(map keyframes) and a different test lap (queries); poses and Z-depth are exact. The result is
a reloc dataset v1 (see :mod:`reloc_service.tools.data.dataset`) plus ``synth.json``. The exact
depth is listed in ``truth_depth.txt`` (for scoring only); only a preset with an RGB-D
``depth_sensor`` writes ``depth.txt``, with sensor-like depth. A preset with a ``rig`` renders
every map pose with each of its cameras (``images/<kind>/<camera id>/``)::

    from reloc_service.tools.synth import render_dataset
    render_dataset("room", Path("data/room"), seed=0)

Importing this package is light (NumPy only); OpenCV and scikit-image load when rendering.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from ...core.errors import ConfigError, DatasetError
from .presets import CAMERA_ID, PRESETS, Degradation, Preset, get_preset

if TYPE_CHECKING:
    from .renderer import Nuisance
    from .scene import Scene

# The ``reloc synth`` glue is reloc_service.tools.synth.cli: it imports render_dataset from here,
# so this package does not import it back (that was an import cycle).
__all__ = ["PRESETS", "Degradation", "Preset", "get_preset", "render_dataset"]

SYNTH_FILE = "synth.json"
DEPTH_METRES_PER_UNIT = 0.001  # exact depth in mm: 65.5 m range, 0.5 mm rounding
_KIND_CODE = {"map": 0, "query": 1}


def render_dataset(preset: str | Preset, out: Path, *, seed: int = 0, workers: int = 2,
                   progress: bool = True, scale: float = 1.0) -> Path:
    """Render ``preset`` (a name of :data:`PRESETS` or a :class:`Preset`) into the dataset
    folder ``out`` and return it. Images and depth are a pure function of (preset, seed,
    scale): the same arguments give byte-identical PNGs whatever ``workers`` is. ``scale``
    shrinks the images (and the camera) for quick tests; ``workers`` processes render frames
    in parallel (1: in this process). The workers are spawned, so a script that calls this
    with ``workers > 1`` needs the usual ``if __name__ == "__main__":`` guard."""
    from ..data.dataset import DatasetEntry
    from ..data.dataset_write import write_dataset
    from .scenes import build_scene
    from .trajectories import make_trajectories

    preset = get_preset(preset) if isinstance(preset, str) else preset
    if not 0.0 < scale <= 4.0 or workers < 1:
        raise ConfigError(f"render_dataset: expected 0 < scale <= 4 and workers >= 1, got "
                          f"scale={scale}, workers={workers}")
    out = Path(out)
    _check_folder(out)
    cameras = {cid: cam if scale == 1.0 else cam.scaled(scale)
               for cid, cam in preset.cameras.items()}
    scene = build_scene(preset.scene, seed)
    map_poses, query_poses = make_trajectories(preset.trajectory, preset.n_map, preset.n_query,
                                               seed)
    nuisances = _draw_nuisances(preset, cameras[CAMERA_ID], query_poses, scene, seed)
    jobs = _make_jobs(preset, map_poses, query_poses, nuisances)
    _prepare_folder(out, jobs, sensor_depth=preset.depth_sensor is not None)
    _run_jobs(jobs, (scene, cameras, preset, seed, out), workers=workers, show=progress)

    entries = {kind: [DatasetEntry(job.image_path, job.camera_id, job.world_from_cam)
                      for job in jobs if job.kind == kind] for kind in _KIND_CODE}
    truth = {job.image_path: (job.truth_depth_path, DEPTH_METRES_PER_UNIT) for job in jobs}
    sensor = ({job.image_path: (job.sensor_depth_path, preset.depth_sensor.metres_per_unit)
               for job in jobs} if preset.depth_sensor is not None else {})
    # Rendered through the exact cameras written: their calibration is exact.
    write_dataset(out, cameras, entries["map"], entries["query"], sensor, truth_depth=truth,
                  calibration_sigma=(0.0, 0.0))
    _write_json(out / SYNTH_FILE, _synth_record(preset, cameras, seed, scale, jobs))
    return out


# -- jobs ------------------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class _Job:
    """One frame to render and where its image and depth go (relative to the dataset). Rig
    presets put each camera's frames in a folder of its own (``folder`` = ``"cam1/"``)."""

    kind: str  # "map" or "query"
    index: int  # of the trajectory pose (both images of a stereo pair share it)
    world_from_cam: npt.NDArray[np.float64]
    nuisance: Nuisance | None
    camera_id: str = CAMERA_ID
    camera_index: int = 0  # 0 for cam0, k for the preset's rig[k - 1]
    folder: str = ""

    @property
    def image_path(self) -> str:
        return f"images/{self.kind}/{self.folder}{self.index:06d}.png"

    @property
    def truth_depth_path(self) -> str:
        return f"truth_depth/{self.kind}/{self.folder}{self.index:06d}.png"

    @property
    def sensor_depth_path(self) -> str:
        return f"depth/{self.kind}/{self.folder}{self.index:06d}.png"

    def rng(self, seed: int, stream: int) -> np.random.Generator:
        """Stream 0: image noise (cam0's keeps the key it always had, so single-camera presets
        render as before); stream 2: the depth sensor (1 is the query nuisances', drawn in
        :func:`_draw_nuisances`)."""
        key = [seed, _KIND_CODE[self.kind], self.index]
        if stream or self.camera_index:
            key += [stream, self.camera_index]
        return np.random.default_rng(key)


def _make_jobs(preset: Preset, map_poses: list[npt.NDArray[np.float64]],
               query_poses: list[npt.NDArray[np.float64]],
               nuisances: list[Nuisance | None]) -> list[_Job]:
    """Map jobs pose by pose (cam0, then each rig camera: a stereo pair is two consecutive
    rows), then the cam0 query jobs."""
    from ...core.geometry import compose

    folder = f"{CAMERA_ID}/" if preset.rig else ""
    jobs = []
    for i, pose in enumerate(map_poses):
        jobs.append(_Job("map", i, pose, None, folder=folder))
        for k, rig_cam in enumerate(preset.rig, 1):
            cam0_from_cam = np.eye(4)
            cam0_from_cam[:3, 3] = rig_cam.offset_m
            jobs.append(_Job("map", i, compose(pose, cam0_from_cam), None, rig_cam.camera_id, k,
                             f"{rig_cam.camera_id}/"))
    jobs += [_Job("query", i, pose, nuisances[i], folder=folder)
             for i, pose in enumerate(query_poses)]
    return jobs


_STATE: tuple[Any, ...] = ()  # (scene, cameras, preset, seed, out) in a worker


def _init_worker(state: tuple[Any, ...], single_threaded: bool) -> None:
    global _STATE
    import cv2

    if single_threaded:  # one process per core already
        cv2.setNumThreads(1)
    _STATE = state


def _render_job(job: _Job) -> str:
    """Render one frame and write its 8-bit image, its exact 16-bit depth (mm) and, for an
    RGB-D preset, its sensor depth PNGs."""
    import cv2

    from .renderer import render_frame

    scene, cameras, preset, seed, out = _STATE
    frame = render_frame(scene, cameras[job.camera_id], job.world_from_cam,
                         rng=job.rng(seed, 0), supersample=preset.supersample,
                         noise_sigma=preset.noise_sigma, nuisance=job.nuisance)
    truth = _depth_png(frame.depth, DEPTH_METRES_PER_UNIT)
    files: list[tuple[str, npt.NDArray[Any]]] = [(job.image_path, frame.image),
                                                  (job.truth_depth_path, truth)]
    if preset.depth_sensor is not None:
        from .depth_sensor import sensor_depth

        sensed = sensor_depth(frame.depth, frame.cos_incidence, preset.depth_sensor,
                              job.rng(seed, 2))
        files.append((job.sensor_depth_path,
                       _depth_png(sensed, preset.depth_sensor.metres_per_unit)))
    for rel, data in files:
        if not cv2.imwrite(str(out / rel), data):
            raise DatasetError(f"cannot write {out / rel}")
    return job.image_path


def _depth_png(depth: npt.NDArray[np.float32], metres_per_unit: float) -> npt.NDArray[np.uint16]:
    """Metres (0: none) to 16-bit units, rounded to the nearest unit (the quantisation)."""
    return np.clip(np.rint(depth / metres_per_unit), 0, 65535).astype(np.uint16)


def _run_jobs(jobs: list[_Job], state: tuple[Any, ...], *, workers: int, show: bool) -> None:
    """Render every job, in this process or in a pool of ``workers`` spawned processes."""
    if workers <= 1:
        _init_worker(state, single_threaded=False)
        _drain(map(_render_job, jobs), len(jobs), f"synth {state[2].name}", show)
        return
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor, as_completed
    from concurrent.futures.process import BrokenProcessPool

    # "spawn": a forked child inherits OpenCV's thread pool in a broken state and can hang.
    # An executor, not multiprocessing.Pool: a worker that dies (killed, out of memory) fails
    # the run with an error instead of leaving it waiting forever for the lost frame.
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(workers, mp_context=context, initializer=_init_worker,
                             initargs=(state, True)) as pool:
        try:   # a worker that dies while the jobs are still being submitted breaks submit too
            futures = [pool.submit(_render_job, job) for job in jobs]
            _drain((f.result() for f in as_completed(futures)), len(jobs),
                   f"synth {state[2].name}", show)
        except BrokenProcessPool as exc:
            raise DatasetError(f"a synth worker process died ({exc}); rerun, or render with "
                               "one process (workers=1) to see its error") from exc


def _drain(done: Iterator[str], total: int, desc: str, show: bool) -> None:
    """Wait for every frame, with a progress bar if ``show``."""
    from ...core.progress import progress

    for _ in progress(done, total=total, desc=desc) if show else done:
        pass


def _draw_nuisances(preset: Preset, camera: Any, query_poses: list[npt.NDArray[np.float64]],
                    scene: Scene, seed: int) -> list[Nuisance | None]:
    """Per-query degradations of a ``-hard`` preset (None each for the others)."""
    if preset.degradation is None:
        return [None] * len(query_poses)
    from .renderer import draw_nuisance

    return [draw_nuisance(np.random.default_rng([seed, _KIND_CODE["query"], i, 1]),
                          preset.degradation, camera, pose, scene.occluder_textures)
            for i, pose in enumerate(query_poses)]


# -- files -----------------------------------------------------------------------------------

def _check_folder(out: Path) -> None:
    """Refuse an ``out`` that is a file or holds anything but an earlier synth run."""
    if out.exists() and not out.is_dir():
        raise DatasetError(f"{out} exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not (out / SYNTH_FILE).is_file():
        raise DatasetError(f"{out} is not empty and holds no {SYNTH_FILE}; refusing to write a "
                           "synthetic dataset over other files (choose an empty or new folder)")


def _prepare_folder(out: Path, jobs: list[_Job], *, sensor_depth: bool) -> None:
    """Clear the frames of an earlier synth run in ``out``; create the folders the ``jobs``
    write into."""
    _check_folder(out)
    for sub in ("images", "depth", "truth_depth"):
        shutil.rmtree(out / sub, ignore_errors=True)
    for job in jobs:
        paths = [job.image_path, job.truth_depth_path] + ([job.sensor_depth_path]
                                                          if sensor_depth else [])
        for rel in paths:
            (out / rel).parent.mkdir(parents=True, exist_ok=True)


def _synth_record(preset: Preset, cameras: dict[str, Any], seed: int, scale: float,
                  jobs: list[_Job]) -> dict[str, Any]:
    """What ``synth.json`` records: enough to regenerate the dataset and to know its nuisances."""
    return {
        "generator": "reloc synth", "preset": preset.name, "description": preset.description,
        "seed": seed, "scale": scale, "scene": preset.scene, "trajectory": preset.trajectory,
        "n_map": preset.n_map, "n_query": preset.n_query, "supersample": preset.supersample,
        "noise_sigma_grey_levels": preset.noise_sigma,
        "degradation": asdict(preset.degradation) if preset.degradation else None,
        "camera_id": CAMERA_ID, "camera": cameras[CAMERA_ID].to_dict(),
        "rig": {c.camera_id: {"cam0_from_cam_translation_m": list(c.offset_m),
                              "camera": cameras[c.camera_id].to_dict()} for c in preset.rig},
        "depth": {"metres_per_unit": DEPTH_METRES_PER_UNIT, "kind": "z along the optical axis",
                  "no_hit": 0, "file": "truth_depth.txt"},
        "depth_sensor": ({**asdict(preset.depth_sensor), "file": "depth.txt"}
                         if preset.depth_sensor else None),
        "textures": "scikit-image sample photographs (bundled)",
        "query_nuisances": {job.image_path: job.nuisance.summary() for job in jobs
                            if job.nuisance is not None},
    }


def _write_json(path: Path, record: dict[str, Any]) -> None:
    path.write_text(json.dumps(record, indent=2) + "\n", encoding="utf-8")
