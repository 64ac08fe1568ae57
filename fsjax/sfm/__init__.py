"""Structure from motion on photographs: features, matching, two-view verification, incremental
reconstruction, COLMAP text and PLY export (see docs/sfm.md)."""

from .bundle import bundle_adjust_masked as bundle_adjust_masked
from .bundle import observation_pairs as observation_pairs
from .features import Features as Features
from .features import detect_and_describe as detect_and_describe
from .features import detect_and_describe_batch as detect_and_describe_batch
from .matching import match_descriptors as match_descriptors
from .matching import match_pairs as match_pairs
from .reconstruct import Reconstruction as Reconstruction
from .reconstruct import align_to_ground_truth as align_to_ground_truth
from .reconstruct import reconstruct as reconstruct
