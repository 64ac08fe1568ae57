"""The bundled three-view fountain crop (tests/data/sfm) and its ground-truth cameras."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

DATA = Path(__file__).resolve().parents[1] / "data" / "sfm"
NAMES = ("fountain_0003.jpg", "fountain_0004.jpg", "fountain_0005.jpg")


def grey(name: str) -> np.ndarray:
    from PIL import Image
    return np.asarray(Image.open(DATA / name).convert("L"), np.float32) / 255.0


def cameras():
    """(K at 384x256, [world_from_camera R], [centre]) of the three views."""
    js = json.loads((DATA / "cameras.json").read_text())
    d = js["downsample"]
    K = np.array(js["cameras"][0]["K_full"], float)
    Ks = np.array([[K[0, 0] / d, 0, (K[0, 2] + 0.5) / d - 0.5], [0, K[1, 1] / d, (K[1, 2] + 0.5) / d - 0.5], [0, 0, 1]])
    Rs = [np.array(c["world_from_camera_R"], float) for c in js["cameras"]]
    Cs = [np.array(c["centre_m"], float) for c in js["cameras"]]
    return Ks, Rs, Cs
