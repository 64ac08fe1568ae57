"""Vendor compact copies of the real meshes in ``../shared/data/meshes`` into ``fsjax/data``.

Run once from the repository root: ``python tools/vendor_meshes.py``. Reads the
OBJ files (vertices and triangular faces only), stores float32 vertices and
int32 faces in compressed ``.npz`` files with the source and licence line.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

SOURCES = {
    "bunny": ("stanford-bunny.obj",
              "Stanford Bunny, range-scan reconstruction; Stanford 3D Scanning Repository "
              "(via A. Jacobson's common-3d-test-models); free for research use, credit Stanford "
              "Computer Graphics Laboratory"),
    "spot": ("spot.obj", "Spot cow, Keenan Crane's 3D model repository; CC0 1.0"),
    "fandisk": ("fandisk.obj", "Fandisk CAD part, H. Hoppe, 'Mesh optimization' (SIGGRAPH 1993) test model; "
                "research use, widely redistributed"),
}


def read_obj(path: Path) -> tuple[np.ndarray, np.ndarray]:
    verts, faces = [], []
    for line in path.read_text().splitlines():
        if line.startswith("v "):
            verts.append([float(x) for x in line.split()[1:4]])
        elif line.startswith("f "):
            idx = [int(tok.split("/")[0]) for tok in line.split()[1:]]
            for k in range(1, len(idx) - 1):  # fan-triangulate polygons
                faces.append([idx[0], idx[k], idx[k + 1]])
    v = np.asarray(verts, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    f = np.where(f < 0, f + len(v), f - 1)
    return v, f


def main(src: str = "../shared/data/meshes") -> None:
    out = Path(__file__).resolve().parents[1] / "fsjax" / "data"
    for name, (fname, licence) in SOURCES.items():
        v, f = read_obj(Path(src) / fname)
        np.savez_compressed(out / f"{name}.npz", vertices=v.astype(np.float32), faces=f.astype(np.int32),
                            source=np.array(licence))
        print(name, v.shape, f.shape, (out / f"{name}.npz").stat().st_size, "bytes")


if __name__ == "__main__":
    main(*sys.argv[1:])
