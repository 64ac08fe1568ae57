"""Structure from motion on photographs: features, matching, two-view verification, incremental
reconstruction, COLMAP text and PLY export (see docs/sfm.md)."""

from .features import Features as Features
from .features import detect_and_describe as detect_and_describe
from .features import detect_and_describe_batch as detect_and_describe_batch
