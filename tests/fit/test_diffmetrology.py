"""Differentiable metrology: plumb-line distortion calibration through measure_pos, and the
sensitivity of a measured physical length to the intrinsics (FD-checked, non-zero gradients)."""

from __future__ import annotations

import numpy as np

from fsjax.tour.calibration import measure_length_sensitivity, measure_plumb_line


def test_plumb_line_through_caliper():
    r = measure_plumb_line()
    g, fd = r["grad"], r["fd"]
    rel = np.abs(g - fd) / np.abs(fd)
    print(f"plumb line: d(curvature)/d(k1, k2) through measure_pos {g} vs central FD {fd} (rel diff {rel.max():.1e})")
    print(f"  recovered (k1, k2) = {np.round(r['k'], 4)} (truth {r['truth']}), converged {r['converged']} in "
          f"{r['steps']} LM steps; distortion field error max {r['field_err_px']:.3f} px of {r['field_max_px']:.2f} px; "
          f"straightness RMS {r['straightness_fit']:.2e} vs null (no correction) {r['straightness_null']:.2e}")
    assert np.all(np.abs(g) > 1e-4) and rel.max() < 1e-4
    assert r["converged"] and r["measured_ok"]
    assert r["field_err_px"] < 0.01 * r["field_max_px"]  # distortion field to 1 % of its size
    assert abs(r["k"][0] - r["truth"][0]) < 0.01 * abs(r["truth"][0]) * 5
    assert r["straightness_fit"] < 0.1 * r["straightness_null"]


def test_length_sensitivity_to_intrinsics():
    r = measure_length_sensitivity()
    J, fd = r["jacobian"], r["fd"]
    names = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
    rel = np.abs(J - fd) / np.maximum(np.abs(fd), 1e-12)
    print(f"bar width {r['length_mm']:.4f} mm (truth {r['truth_mm']:.1f} mm); dL/dtheta (mm per unit): "
          + ", ".join(f"{n} {j:.3e}" for n, j in zip(names, J)) + f"; max rel diff vs FD {rel.max():.1e}")
    assert abs(r["length_mm"] - r["truth_mm"]) < 0.1
    assert np.all(np.abs(J) > 0) and rel.max() < 1e-3
    # the physics: a longer focal length makes the same pixels a shorter length, L ~ 1/fx
    assert J[0] < 0 and abs(J[0] * 516.2 / r["length_mm"] + 1) < 0.05
