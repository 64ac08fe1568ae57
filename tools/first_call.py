"""First-call cost of one library call in a fresh process: CPU seconds and programs compiled.

An eager function that runs op by op compiles one XLA program per primitive and shape on its
first call; jitted whole it compiles one. This measures that cost as a user (or a test) meets it:
``time.process_time`` around the first call (less load-sensitive than wall time on a shared
machine), and the number and seconds of JAX's backend-compile events. Compare two trees by
running it in each, alternating (docs/compile_times.md, "Where the suite's time goes")::

    PYTHONPATH=/path/to/old/tree python tools/first_call.py curvature
    PYTHONPATH=$PWD python tools/first_call.py curvature

NAME: ``curvature`` (2,000 points on a sphere, k 16), ``voxel`` (the fandisk scan of
``synth.cad_scan_pair``, 21,774 points), ``index`` (``build_index`` + ``query_knn``: 5,000 refs,
3,000 queries, k 8), ``normals`` (``estimate_normals``: 3,000 points on a sphere, k 16), ``decode``
(``synth.decode_depth`` on the structured-light still life).
"""

from __future__ import annotations

import argparse
import time

import jax

_EV = {"n": 0, "s": 0.0}


def _listen(name, secs, **kw):
    if name == "/jax/core/compile/backend_compile_duration":
        _EV["n"] += 1
        _EV["s"] += float(secs)


def _call(name):
    import jax.numpy as jnp
    import numpy as np

    import fsjax

    rng = np.random.default_rng(0)
    if name == "curvature":
        i = np.arange(2000) + 0.5
        phi, th = np.arccos(1 - 2 * i / 2000), np.pi * (1 + 5**0.5) * i
        p = fsjax.Points(jnp.asarray(2.0 * np.c_[np.cos(th) * np.sin(phi), np.sin(th) * np.sin(phi), np.cos(phi)]))
        return lambda: fsjax.ops.curvature(p, k=16)
    if name == "voxel":
        pair = fsjax.synth.cad_scan_pair("fandisk", angle_deg=50.0, seed=0)
        p, vx = fsjax.Points(jnp.asarray(pair["scan"])), 0.02 * pair["diag"]
        return lambda: fsjax.ops.voxel_downsample(p, voxel=vx, capacity=4096)
    if name == "normals":
        sp = rng.normal(size=(3000, 3))
        p = fsjax.Points(jnp.asarray(sp / np.linalg.norm(sp, axis=1, keepdims=True)))
        return lambda: fsjax.ops.estimate_normals(p, k=16)
    if name == "index":
        ref, q = jnp.asarray(rng.uniform(size=(5000, 3))), jnp.asarray(rng.uniform(size=(3000, 3)))
        return lambda: fsjax.ops.query_knn(fsjax.ops.build_index(ref, k=8), q, 8)
    rig = fsjax.synth.standard_rig()
    frames = fsjax.synth.capture_patterns(fsjax.synth.capture_geometry(fsjax.synth.still_life_mm(), rig))
    return lambda: fsjax.synth.decode_depth(frames, rig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("name", choices=("curvature", "voxel", "index", "normals", "decode"))
    name = ap.parse_args().name
    jax.config.update("jax_enable_x64", True)
    jax.monitoring.register_event_duration_secs_listener(_listen)
    f = _call(name)  # inputs are built (and their programs compiled) before the measured call
    n0, s0, c0, w0 = _EV["n"], _EV["s"], time.process_time(), time.perf_counter()
    jax.block_until_ready(f())
    print(f"{name}: {_EV['n'] - n0} programs, {_EV['s'] - s0:.2f} s in backend compiles, "
          f"first call {time.process_time() - c0:.2f} s CPU, {time.perf_counter() - w0:.2f} s wall")


if __name__ == "__main__":
    main()
