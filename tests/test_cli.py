"""The ``fsjax`` command: ops listing, running a pipeline on a file, the tour."""

from __future__ import annotations

import numpy as np
import pytest

import fsjax
from fsjax.cli import main, parse_stage
from fsjax.synth import standard_scene


def test_parse_stage():
    assert parse_stage("gaussian") == "gaussian"
    assert parse_stage("gaussian:sigma=2,mode=nearest") == ("gaussian", {"sigma": 2, "mode": "nearest"})
    assert parse_stage("gaussian@0.3") == ("gaussian", 0.3)
    assert parse_stage("sauvola@0.3,0.7") == ("sauvola", 0.3, 0.7)


def test_ops_listing(capsys):
    assert main(["ops", "--family", "filters"]) == 0
    out = capsys.readouterr().out
    assert "gaussian" in out and "(Image) -> Image" in out
    n = len(fsjax.list_ops(family="filters"))
    assert f"{n} ops in 1 families" in out
    assert main(["ops", "--search", "otsu"]) == 0
    assert "otsu_level" in capsys.readouterr().out


@pytest.fixture
def png(tmp_path):
    from PIL import Image as PILImage

    img, _ = standard_scene(0, (48, 64), noise=0.0)
    path = tmp_path / "in.png"
    PILImage.fromarray((img * 255).round().astype(np.uint8)).save(path)
    return path


def test_run_pipeline_on_file(png, tmp_path, capsys):
    out = tmp_path / "out.png"
    assert main(["run", str(png), "gaussian:sigma=2", "sobel_amp", "otsu", "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "(uint8 / 255)" in text
    assert "stage 1: gaussian:sigma=2 -> Image" in text
    assert "stage 3: otsu -> Region" in text
    assert out.exists()
    # the written mask equals the library's own result on the same file
    from PIL import Image as PILImage

    from fsjax.io import read_image

    ref = fsjax.run_pipeline(read_image(png, as_grey=True), [("gaussian", {"sigma": 2}), "sobel_amp", "otsu"])
    got = np.asarray(PILImage.open(out)) > 127
    assert np.array_equal(got, np.asarray(ref.data))


def test_run_feature_result_is_printed(png, capsys):
    assert main(["run", str(png), "mean"]) == 0
    text = capsys.readouterr().out
    line = [ln for ln in text.splitlines() if ln.startswith("result:")][0]
    img, _ = standard_scene(0, (48, 64), noise=0.0)
    assert abs(float(line.split()[1]) - np.mean(np.round(img * 255) / 255)) < 1e-6


def test_run_errors(png, capsys):
    assert main(["run", str(png), "otsu", "sobel_amp"]) == 2
    assert "stage 2 (sobel_amp) takes Image but stage 1 (otsu) gives Region" in capsys.readouterr().err
    assert main(["run", str(png), "gausian"]) == 2
    assert "did you mean 'gaussian'" in capsys.readouterr().err


def test_run_output_refused_before_the_pipeline_runs(png, tmp_path, monkeypatch):
    """Issue 20 item 6: a JPEG name, a missing folder, --bits 16 on a Region and -o on a Feature
    result are refused before the image is read or any stage runs (before: after the pipeline)."""
    import fsjax.io

    def boom(*a, **k):
        raise AssertionError("the input was read although the output is refused")

    monkeypatch.setattr(fsjax.io, "read_image", boom)
    cases = [(["gaussian", "-o", str(tmp_path / "x.jpg")], "only PNG"),
             (["gaussian", "-o", str(tmp_path / "no_such_dir" / "x.png")], "does not exist"),
             (["otsu", "-o", str(tmp_path / "m.png"), "--bits", "16"], "grey Image results only"),
             (["mean", "-o", str(tmp_path / "m.png")], "gives a Feature")]
    for argv, msg in cases:
        with pytest.raises(SystemExit, match=msg):
            main(["run", str(png), *argv])


def test_run_bits_16(tmp_path, capsys):
    """A 16-bit input written back with --bits 16 keeps its 16-bit values (identity pipeline stage)."""
    from PIL import Image as PILImage

    src = (np.arange(48 * 64).reshape(48, 64) * 21).astype(np.uint16)
    inp, out = tmp_path / "in16.png", tmp_path / "out16.png"
    PILImage.fromarray(src).save(inp)
    assert main(["run", str(inp), "gaussian:sigma=0.01", "-o", str(out), "--bits", "16"]) == 0
    assert "(16-bit)" in capsys.readouterr().out
    back = np.asarray(PILImage.open(out))
    assert back.dtype in (np.uint16, np.int32) and int(np.abs(back.astype(np.int64) - src).max()) == 0
    assert main(["run", str(inp), "gaussian:sigma=0.01", "-o", str(out)]) == 0
    assert "--bits 16 keeps 16" in capsys.readouterr().out


def test_help_and_cached_ops_listing_do_not_load_the_library(tmp_path):
    """Issue 20 item 6: ``import fsjax`` is lazy (no JAX), so ``fsjax --help`` does not load the
    library, and a repeated ``fsjax ops --search`` reads the cached catalogue. Load, not time,
    is asserted (timing is never a test condition); fsjax.io is an attribute of the package."""
    import os
    import subprocess
    import sys

    env = dict(os.environ, FSJAX_CACHE_DIR=str(tmp_path))
    probe = ("import sys\nfrom fsjax.cli import main\n"
             "try:\n    main(sys.argv[1:])\nexcept SystemExit:\n    pass\n"
             "print('JAX_LOADED' if 'jax' in sys.modules else 'NO_JAX')\n")

    def run(*argv):
        return subprocess.run([sys.executable, "-c", probe, *argv], capture_output=True, text=True, env=env,
                              timeout=300).stdout

    assert run("--help").strip().endswith("NO_JAX")
    first = run("ops", "--search", "otsu")
    assert "otsu_level" in first and first.strip().endswith("JAX_LOADED")  # builds the cache
    again = run("ops", "--search", "otsu")
    assert again.replace("NO_JAX", "") == first.replace("JAX_LOADED", "") and again.strip().endswith("NO_JAX")
    code = "import fsjax, sys; print('jax' in sys.modules, fsjax.io.read_image.__name__)"
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=300).stdout.split() == ["False", "read_image"]


def test_tour_quick(tmp_path):
    """``run_tour`` end to end (report and figures) on the 2-D sections.

    The sections of the other tour modules each run in quick mode in their own test file
    (``tests/test_<module>.py``); running them all again here doubled the suite's longest test.
    """
    from pathlib import Path

    from fsjax import tour, tour_inspection

    todo = list(tour.SECTIONS) + list(tour_inspection.SECTIONS)
    secs = tour.run_tour(tmp_path, quick=True, sections=todo, log=lambda *a, **k: None)
    report = (tmp_path / "report.md").read_text()
    assert len(secs) == len(todo) >= 10
    for s in secs:
        print(f"{s.title}: fsjax {s.fsjax_figure} | null {s.null_figure}")
        assert s.beats_null, s.title
        assert s.title in report
        if s.figure:
            assert (tmp_path / s.figure).stat().st_size > 0
    # every other tour module's sections are part of the full tour and have their own test file
    tests_dir = Path(__file__).parent
    names = [f.__name__ for f in tour.all_sections()]
    assert names[: len(todo)] == [f.__name__ for f in todo]
    for mod in tour._TOUR_MODULES:
        if mod != "tour_inspection":
            assert (tests_dir / f"test_{mod}.py").exists(), f"no quick-mode test for fsjax.{mod}"
