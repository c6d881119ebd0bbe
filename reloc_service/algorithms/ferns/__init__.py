"""Random ferns (thesis 3.2): a classifier with sparse counts, its warped training samples, and
the region models the ferns relocalizer trains incrementally."""

from .classifier import FernClassifier
from .fern_tests import FernConf, FernTests
from .scorer import FernScorer
from .training import WarpConf, Warps, draw_warps, extract_patches, prepare_image, sample_leaves

__all__ = ["FernClassifier", "FernConf", "FernScorer", "FernTests", "WarpConf", "Warps",
           "draw_warps", "extract_patches", "prepare_image", "sample_leaves"]
