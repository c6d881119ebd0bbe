"""Photoreal synthetic relocalization datasets with exact ground truth (``reloc synth``).

A room or desk scene of textured rectangles and boxes (real photographs from scikit-image,
at known physical sizes) is ray cast per pixel through the camera model, along a training lap
(map keyframes) and a different test lap (queries); poses and Z-depth are exact. The result is
a reloc dataset v1 (see :mod:`reloc_service.data.dataset`) plus ``synth.json``::

    from reloc_service.synth import render_dataset
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

from ..errors import ConfigError, DatasetError
from .cli import add_synth_arguments, main_synth
from .presets import PRESETS, Degradation, Preset, get_preset

if TYPE_CHECKING:
    from .renderer import Nuisance
    from .scene import Scene

__all__ = ["PRESETS", "Degradation", "Preset", "add_synth_arguments", "get_preset",
           "main_synth", "render_dataset"]

SYNTH_FILE = "synth.json"
CAMERA_ID = "cam0"
DEPTH_METRES_PER_UNIT = 0.001
_KIND_CODE = {"map": 0, "query": 1}


def render_dataset(preset: str | Preset, out: Path, *, seed: int = 0, workers: int = 2,
                   progress: bool = True, scale: float = 1.0) -> Path:
    """Render ``preset`` (a name of :data:`PRESETS` or a :class:`Preset`) into the dataset
    folder ``out`` and return it. Images and depth are a pure function of (preset, seed,
    scale): the same arguments give byte-identical PNGs whatever ``workers`` is. ``scale``
    shrinks the images (and the camera) for quick tests; ``workers`` processes render frames
    in parallel (1: in this process). The workers are spawned, so a script that calls this
    with ``workers > 1`` needs the usual ``if __name__ == "__main__":`` guard."""
    from ..data.dataset import DatasetEntry, write_dataset
    from .scene import build_scene
    from .trajectories import make_trajectories

    preset = get_preset(preset) if isinstance(preset, str) else preset
    if not 0.0 < scale <= 4.0 or workers < 1:
        raise ConfigError(f"render_dataset: expected 0 < scale <= 4 and workers >= 1, got "
                          f"scale={scale}, workers={workers}")
    out = Path(out)
    camera = preset.camera if scale == 1.0 else preset.camera.scaled(scale)
    _prepare_folder(out)
    scene = build_scene(preset.scene, seed)
    map_poses, query_poses = make_trajectories(preset.trajectory, preset.n_map, preset.n_query,
                                               seed)
    nuisances = _draw_nuisances(preset, camera, query_poses, scene, seed)
    jobs = ([_Job("map", i, pose, None) for i, pose in enumerate(map_poses)]
            + [_Job("query", i, pose, nuisances[i]) for i, pose in enumerate(query_poses)])
    _run_jobs(jobs, (scene, camera, preset, seed, out), workers=workers, show=progress)

    entries = {kind: [DatasetEntry(job.image_path, CAMERA_ID, job.world_from_cam)
                      for job in jobs if job.kind == kind] for kind in _KIND_CODE}
    depth = {job.image_path: (job.depth_path, DEPTH_METRES_PER_UNIT) for job in jobs}
    write_dataset(out, {CAMERA_ID: camera}, entries["map"], entries["query"], depth)
    _write_json(out / SYNTH_FILE, _synth_record(preset, camera, seed, scale, jobs))
    return out


# -- jobs ------------------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class _Job:
    """One frame to render and where its image and depth go (relative to the dataset)."""

    kind: str  # "map" or "query"
    index: int
    world_from_cam: npt.NDArray[np.float64]
    nuisance: Nuisance | None

    @property
    def image_path(self) -> str:
        return f"images/{self.kind}/{self.index:06d}.png"

    @property
    def depth_path(self) -> str:
        return f"depth/{self.kind}/{self.index:06d}.png"


_STATE: tuple[Any, ...] = ()  # (scene, camera, preset, seed, out) in a worker


def _init_worker(state: tuple[Any, ...], single_threaded: bool) -> None:
    global _STATE
    import cv2

    if single_threaded:  # one process per core already
        cv2.setNumThreads(1)
    _STATE = state


def _render_job(job: _Job) -> str:
    """Render one frame and write its 8-bit image and 16-bit depth (mm) PNGs."""
    import cv2

    from .renderer import render_frame

    scene, camera, preset, seed, out = _STATE
    rng = np.random.default_rng([seed, _KIND_CODE[job.kind], job.index])
    frame = render_frame(scene, camera, job.world_from_cam, rng=rng,
                         supersample=preset.supersample, noise_sigma=preset.noise_sigma,
                         nuisance=job.nuisance)
    depth_units = np.clip(np.rint(frame.depth / DEPTH_METRES_PER_UNIT), 0, 65535)
    for rel, data in ((job.image_path, frame.image), (job.depth_path,
                                                       depth_units.astype(np.uint16))):
        if not cv2.imwrite(str(out / rel), data):
            raise DatasetError(f"cannot write {out / rel}")
    return job.image_path


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
        futures = [pool.submit(_render_job, job) for job in jobs]
        try:
            _drain((f.result() for f in as_completed(futures)), len(jobs),
                   f"synth {state[2].name}", show)
        except BrokenProcessPool as exc:
            raise DatasetError(f"a synth worker process died ({exc}); rerun, or render with "
                               "one process (workers=1) to see its error") from exc


def _drain(done: Iterator[str], total: int, desc: str, show: bool) -> None:
    """Wait for every frame, with a progress bar if ``show``."""
    from ..progress import progress

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

def _prepare_folder(out: Path) -> None:
    """Create ``out``; clear the frames of an earlier synth run there; refuse other content."""
    if out.exists() and not out.is_dir():
        raise DatasetError(f"{out} exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not (out / SYNTH_FILE).is_file():
        raise DatasetError(f"{out} is not empty and holds no {SYNTH_FILE}; refusing to write a "
                           "synthetic dataset over other files (choose an empty or new folder)")
    for sub in ("images", "depth"):
        shutil.rmtree(out / sub, ignore_errors=True)
        for kind in _KIND_CODE:
            (out / sub / kind).mkdir(parents=True, exist_ok=True)


def _synth_record(preset: Preset, camera: Any, seed: int, scale: float,
                  jobs: list[_Job]) -> dict[str, Any]:
    """What ``synth.json`` records: enough to regenerate the dataset and to know its nuisances."""
    return {
        "generator": "reloc synth", "preset": preset.name, "description": preset.description,
        "seed": seed, "scale": scale, "scene": preset.scene, "trajectory": preset.trajectory,
        "n_map": preset.n_map, "n_query": preset.n_query, "supersample": preset.supersample,
        "noise_sigma_grey_levels": preset.noise_sigma,
        "degradation": asdict(preset.degradation) if preset.degradation else None,
        "camera_id": CAMERA_ID, "camera": camera.to_dict(),
        "depth": {"metres_per_unit": DEPTH_METRES_PER_UNIT, "kind": "z along the optical axis",
                  "no_hit": 0},
        "textures": "scikit-image sample photographs (bundled)",
        "query_nuisances": {job.image_path: job.nuisance.summary() for job in jobs
                            if job.nuisance is not None},
    }


def _write_json(path: Path, record: dict[str, Any]) -> None:
    path.write_text(json.dumps(record, indent=2) + "\n", encoding="utf-8")
