"""The tomography tour section: runs, writes its figure, beats its nulls, meets the figures asked."""

import numpy as np

from fsjax.tour import Section
from fsjax.tour import tomography as T


def test_section_runs(tmp_path):
    sec = T.tomography(tmp_path, True)
    assert isinstance(sec, Section) and (tmp_path / sec.figure).stat().st_size > 0
    print(f"{sec.title}: {sec.fsjax_figure} | null: {sec.null_figure}")
    assert sec.beats_null


def test_ct_figures_full_size():
    r = T.measure_ct()
    print(f"CT tour (128 px, mis-centred 1.7 px): Dice {np.round(r['dice'], 3).tolist()}, axis error "
          f"{r['center_error']:+.4f} px, RMSE {r['rmse']:.4f} vs nulls {r['rmse24']:.4f} / {r['rmse_bp']:.4f}")
    assert np.all(r["dice"] >= 0.88)
    assert abs(r["center_error"]) <= 0.01
    assert r["rmse24"] >= 1.8 * r["rmse"] and r["rmse_bp"] >= 1.8 * r["rmse"]
