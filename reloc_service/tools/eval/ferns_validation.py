"""The thesis's ferns validation (section 3.2, figure 3.10): recognition rate of warped patches
against the number of ferns M, one curve per number of tests S.

One image; ``num_patches`` random patches (centred on random SIFT keypoints, so that a patch
is not a flat region) train the classifier with ``train_warps`` random warps each; then
``test_warps`` new random warps of each patch are classified; repeated ``repetitions`` times
(the thesis: 100 patches, 100 warps, 100 repetitions). One classifier of max(S) tests and
max(M) ferns is trained per repetition: the ferns of S tests are the first S tests of each
fern (:meth:`FernClassifier.first_tests`), M ferns the first M (:meth:`first_ferns`).

``python -m reloc_service.tools.eval.ferns_validation --out DIR`` writes ``ferns_validation.json``
and ``ferns_validation.png`` (matplotlib, an optional extra) into DIR.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from ...algorithms.ferns.classifier import FernClassifier
from ...algorithms.ferns.fern_tests import FernConf
from ...algorithms.ferns.training import WarpConf, draw_warps, sample_leaves
from ...core.errors import ConfigError
from ...core.progress import progress


@dataclass(frozen=True)
class ValidationConf:
    """The experiment's sizes; ``image`` names a ``skimage.data`` photograph."""

    num_patches: int = 100
    train_warps: int = 100
    test_warps: int = 100
    repetitions: int = 10
    tests: tuple[int, ...] = (4, 6, 8, 10, 12)
    ferns: tuple[int, ...] = (1, 5, 10, 25, 50, 100)
    patch_size: int = 32
    image: str = "camera"
    seed: int = 0

    def __post_init__(self) -> None:
        if min(self.num_patches, self.train_warps, self.test_warps, self.repetitions) < 1:
            raise ConfigError("num_patches, train_warps, test_warps and repetitions must be >= 1")
        if not self.tests or not self.ferns or min(self.tests) < 1 or min(self.ferns) < 1:
            raise ConfigError("tests and ferns must be non-empty lists of positive integers")


def load_image(name: str) -> npt.NDArray[np.uint8]:
    """A ``skimage.data`` photograph as grey uint8."""
    import skimage.data

    try:
        img = getattr(skimage.data, name)()
    except AttributeError:
        raise ConfigError(f"skimage.data has no image {name!r}") from None
    if img.ndim == 3:
        img = cv2.cvtColor(np.ascontiguousarray(img[..., :3]), cv2.COLOR_RGB2GRAY)
    return np.ascontiguousarray(img.astype(np.uint8))


def random_patch_centres(image: npt.NDArray[np.uint8], count: int, patch_size: int,
                         rng: np.random.Generator) -> npt.NDArray[np.float64]:
    """(count, 2) distinct random SIFT keypoint positions at least half a patch from the border."""
    kps = cv2.SIFT.create().detect(image, None)
    px = cv2.KeyPoint.convert(kps)
    pts = np.unique(np.rint(px).astype(np.int64), axis=0).astype(np.float64)
    h, w = image.shape
    half = patch_size / 2
    inside = ((pts[:, 0] >= half) & (pts[:, 0] < w - half)
              & (pts[:, 1] >= half) & (pts[:, 1] < h - half))
    pts = pts[inside]
    if len(pts) < count:
        raise ConfigError(f"the image has {len(pts)} usable keypoints, fewer than {count}")
    return pts[rng.choice(len(pts), count, replace=False)]


def run_repetition(image: npt.NDArray[np.uint8], conf: ValidationConf, warp_conf: WarpConf,
                   repetition: int) -> npt.NDArray[np.float64]:
    """(len(tests), len(ferns)) recognition rates of one repetition."""
    rng = np.random.default_rng([conf.seed, repetition])
    centres = random_patch_centres(image, conf.num_patches, conf.patch_size, rng)
    s_max, m_max = max(conf.tests), max(conf.ferns)
    seed = conf.seed * 1000 + repetition
    clf = FernClassifier(FernConf(m_max, s_max, conf.patch_size, seed=seed))
    labels = np.arange(conf.num_patches)
    train = dataclasses.replace(warp_conf, num_warps=conf.train_warps, include_identity=True,
                                seed=conf.seed * 1000 + repetition)
    test = dataclasses.replace(warp_conf, num_warps=conf.test_warps, include_identity=False,
                               seed=conf.seed * 1000 + repetition)
    leaves = sample_leaves(clf, image, centres, draw_warps(train, 0), train)
    clf.add(leaves.reshape(-1, m_max), np.tile(labels, len(leaves)))
    probe = sample_leaves(clf, image, centres, draw_warps(test, 1), test).reshape(-1, m_max)
    truth = np.tile(labels, conf.test_warps)
    rates = np.zeros((len(conf.tests), len(conf.ferns)))
    for i, s in enumerate(conf.tests):
        by_tests = clf.first_tests(s)
        probe_s = probe >> (s_max - s)
        for j, m in enumerate(conf.ferns):
            predicted = by_tests.first_ferns(m).predict(probe_s[:, :m])
            rates[i, j] = float((predicted == truth).mean())
    return rates


def run_validation(conf: ValidationConf | None = None, warp_conf: WarpConf | None = None, *,
                   show_progress: bool = True) -> dict[str, Any]:
    """The figure 3.10 experiment: mean and std of the recognition rate per (S, M)."""
    conf = conf or ValidationConf()
    warp_conf = warp_conf or WarpConf()
    image = load_image(conf.image)
    start = time.perf_counter()
    reps: Iterable[int] = range(conf.repetitions)
    if show_progress:
        reps = progress(reps, total=conf.repetitions, desc="ferns validation")
    rates = np.stack([run_repetition(image, conf, warp_conf, r) for r in reps])
    return {"conf": dataclasses.asdict(conf), "warps": dataclasses.asdict(warp_conf),
            "tests": list(conf.tests), "ferns": list(conf.ferns),
            "rate_mean": rates.mean(0).round(4).tolist(),
            "rate_std": rates.std(0).round(4).tolist(),
            "seconds": round(time.perf_counter() - start, 1)}


def plot(result: dict[str, Any], path: Path) -> None:
    """Figure 3.10: recognition rate vs number of ferns, one curve per number of tests."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    ferns = result["ferns"]
    for s, mean, std in zip(result["tests"], result["rate_mean"], result["rate_std"], strict=True):
        ax.errorbar(ferns, mean, yerr=std, marker="o", capsize=3, label=f"S = {s} tests")
    ax.set_xlabel("number of ferns M")
    ax.set_ylabel("recognition rate of warped patches")
    c, w = result["conf"], result["warps"]
    kind = "affine" if w["affine"] else "similarity"
    ax.set_title(f"{c['num_patches']} patches, {c['test_warps']} test warps each, "
                 f"{c['repetitions']} repetitions\n{kind} warps: rotation "
                 f"+-{np.degrees(w['max_rotation_rad']):.0f} deg, scale {w['min_scale']}-"
                 f"{w['max_scale']}", fontsize=10)
    ax.set_ylim(0, 1)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _parse(argv: Sequence[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m reloc_service.tools.eval.ferns_validation",
                                description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, required=True, help="output directory")
    p.add_argument("--repetitions", type=int, default=ValidationConf.repetitions)
    p.add_argument("--patches", type=int, default=ValidationConf.num_patches)
    p.add_argument("--train-warps", type=int, default=ValidationConf.train_warps)
    p.add_argument("--test-warps", type=int, default=ValidationConf.test_warps)
    p.add_argument("--tests", type=int, nargs="+", default=list(ValidationConf.tests))
    p.add_argument("--ferns", type=int, nargs="+", default=list(ValidationConf.ferns))
    p.add_argument("--image", default=ValidationConf.image)
    p.add_argument("--max-rotation-deg", type=float,
                   default=float(np.degrees(WarpConf.max_rotation_rad)))
    p.add_argument("--similarity", action="store_true",
                   help="rotation and scale only (the thesis's simplified warps), no full affine")
    p.add_argument("--seed", type=int, default=0)
    return p.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    args = _parse(argv)
    conf = ValidationConf(num_patches=args.patches, train_warps=args.train_warps,
                          test_warps=args.test_warps, repetitions=args.repetitions,
                          tests=tuple(args.tests), ferns=tuple(args.ferns), image=args.image,
                          seed=args.seed)
    warp_conf = WarpConf(max_rotation_rad=float(np.radians(args.max_rotation_deg)),
                         affine=not args.similarity)
    result = run_validation(conf, warp_conf)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "ferns_validation.json").write_text(json.dumps(result, indent=1))
    print(format_table(result))
    try:
        plot(result, args.out / "ferns_validation.png")
    except ImportError:
        print("matplotlib is not installed: no plot (pip install reloc[plots])", file=sys.stderr)
    return 0


def format_table(result: dict[str, Any]) -> str:
    """The mean rates as a text table: one row per S, one column per M."""
    head = "S \\ M " + "".join(f"{m:>7d}" for m in result["ferns"])
    rows = [f"{s:>6d}" + "".join(f"{r:7.3f}" for r in rates)
            for s, rates in zip(result["tests"], result["rate_mean"], strict=True)]
    return "\n".join([head, *rows])


if __name__ == "__main__":
    raise SystemExit(main())
