"""``fsjax sfm VIDEO``: frames chosen by the rotation estimated between consecutive frames, on a video
rendered by fsjax itself along a known orbit (``fsjax.synth._video.orbit_video``: slow, fast, slow),
written and read back through H.264 (PyAV). The chosen frames' accumulated rotation is checked
against the known poses, beside the null of every k-th frame; a still video is refused; a missing
PyAV is named; the whole command runs on the video."""

from __future__ import annotations

import sys

import jax
import numpy as np
import pytest

from fsjax.sfm.video import consecutive_rotations, read_video, select_video_frames, write_video
from fsjax.synth import orbit_video

N_FRAMES = 36
THRESHOLD = 8.0


def _angle(R):
    return np.degrees(np.arccos(np.clip((np.trace(R, axis1=-2, axis2=-1) - 1) / 2, -1, 1)))


@pytest.fixture(scope="module")
def video(tmp_path_factory):
    pytest.importorskip("av")
    d = orbit_video(N_FRAMES)
    path = tmp_path_factory.mktemp("video") / "orbit.mp4"
    write_video(path, d["frames"], fps=10)
    frames = read_video(path)
    # known steps camera_{k+1}_from_camera_k from the world_from_camera poses
    d["R_rel"] = np.einsum("nji,njk->nik", d["R"][1:], d["R"][:-1])
    return d, path, frames


@pytest.fixture(scope="module")
def rotations(video):
    d, _, frames = video
    with jax.enable_x64(False):  # float32 throughout, as a user runs it (the suite enables x64)
        return consecutive_rotations(frames, d["K"])


def test_video_round_trip(video):
    d, _, frames = video
    assert frames.shape == d["frames"].shape and frames.dtype == np.uint8
    # H.264 at qp 12 is lossy (and yuv420p halves the colour resolution) but close
    assert np.abs(frames.astype(int) - d["frames"]).mean() < 10


def test_consecutive_rotations_match_known_poses(video, rotations):
    d, _, _ = video
    rot = rotations
    assert rot.known.all(), rot.flag
    err = _angle(np.einsum("nji,njk->nik", rot.R, d["R_rel"]))  # geodesic error of each step
    true = _angle(d["R_rel"])
    assert true.min() > 0.5 and true.max() < 3.1  # the orbit: 0.6 .. 3 deg per frame
    # an orbit step confounds a small rotation with a sideways translation (bas-relief ambiguity):
    # measured median 0.095, max 0.63 deg at this size (the worst: least parallax)
    assert np.median(err) < 0.3 and err.max() < 1.25, np.round(err, 3)
    assert np.abs(rot.step_deg - true).mean() < 0.3 and np.abs(rot.step_deg - true).max() < 2.0


def test_selection_by_accumulated_rotation_against_known_poses(video, rotations):
    d, _, _ = video
    true = _angle(d["R_rel"])
    sel = select_video_frames(rotations, threshold_deg=THRESHOLD, max_gap=None)
    idx = sel.indices
    assert idx[0] == 0 and set(np.asarray(sel.why)[idx[1:]]) == {1}
    # the known rotation accumulated (path length) between consecutive chosen frames
    acc = np.array([true[a:b].sum() for a, b in zip(idx[:-1], idx[1:])])
    assert len(idx) >= 6
    # each reaches the threshold, overshooting by less than its last step, up to the estimation error
    # accumulated over the interval (measured up to ~1.1 deg)
    tol = 1.5
    last = true[idx[1:] - 1]
    assert np.all(acc > THRESHOLD - tol) and np.all(acc < THRESHOLD + last + tol), np.round(acc, 2)
    # and the frame before each chosen one had not yet reached it
    assert np.all(acc - last < THRESHOLD + tol)
    # null: every k-th frame, as many frames: the orbit's speed varies 5x, so its steps do not
    spread = np.abs(acc - THRESHOLD).max()
    k = max(1, (N_FRAMES - 1) // (len(idx) - 1))
    uni = np.arange(0, N_FRAMES, k)
    acc_u = np.array([true[a:b].sum() for a, b in zip(uni[:-1], uni[1:])])
    assert np.abs(acc_u - THRESHOLD).max() > 2 * spread, (np.round(acc, 2), np.round(acc_u, 2))
    assert acc_u.std() > 3 * acc.std()


def test_still_video_refused(video, tmp_path):
    d, _, _ = video
    still = np.repeat(d["frames"][:1], 5, axis=0)
    path = write_video(tmp_path / "still.mp4", still, fps=10)
    rot = consecutive_rotations(read_video(path), d["K"])
    assert rot.known.all()
    with pytest.raises(ValueError, match="the camera does not turn"):
        select_video_frames(rot)
    # through the command line: a clear error, exit code 2
    from fsjax.cli import main

    assert main(["sfm", str(path), "--out", str(tmp_path / "out")]) == 2


def test_missing_pyav_is_named(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "av", None)  # import av -> ImportError
    with pytest.raises(ImportError, match="'av'.*fsjax\\[video\\]"):
        read_video(tmp_path / "x.mp4")
    with pytest.raises(ImportError, match="'av'"):
        write_video(tmp_path / "x.mp4", np.zeros((2, 8, 8, 3), np.uint8))


@pytest.mark.slow
def test_cli_on_the_rendered_video(video, tmp_path):
    # the whole command: chosen frames reconstructed, report lists them with the reason
    from fsjax.cli import main

    d, path, _ = video
    K = d["K"]
    out = tmp_path / "out"
    code = main(["sfm", str(path), "--out", str(out), "--intrinsics", f"{K[0, 0]},{K[1, 1]},{K[0, 2]},{K[1, 2]}",
                 "--rotation-deg", str(THRESHOLD), "--max-features", "1024", "--octaves", "4"])
    assert code == 0
    report = (out / "report.md").read_text()
    assert "## Frames chosen from the video" in report and "rotation since the previous chosen frame" in report
    chosen = sorted(p.name for p in (out / "frames").iterdir())
    assert chosen[0] == "frame_000000.png" and len(chosen) >= 6
    for nm in chosen:
        assert f"| {nm} | yes" in report or f"| {nm} | no" in report
    assert (out / "sparse" / "images.txt").exists() and (out / "points.ply").exists()
    # measured: 8/8 registered
    n_reg = sum(f"| {nm} | yes" in report for nm in chosen)
    assert f"Registered **{n_reg}/{len(chosen)}**" in report and n_reg >= len(chosen) - 1
