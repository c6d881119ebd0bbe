"""Random ferns (thesis 3.2): a classifier with sparse counts and its warped training samples."""

from .classifier import FernClassifier, FernConf, FernScorer, FernTests
from .training import WarpConf, Warps, draw_warps, extract_patches, prepare_image, sample_leaves

__all__ = ["FernClassifier", "FernConf", "FernScorer", "FernTests", "WarpConf", "Warps",
           "draw_warps", "extract_patches", "prepare_image", "sample_leaves"]
