"""Progress on long fits (issue 20, item 6): ICP and camera calibration say what they are doing
when asked (``verbose=True``), from inside their compiled loops, one line per iteration; silent
by default."""

import re

import jax
import jax.numpy as jnp
import numpy as np

from fsjax.fit import icp, rotation_from_axis_angle
from fsjax.fit.calibrate import calibrate_camera, project_board
from fsjax.fit.chessboard import board_points


def _surface():
    u, v = jnp.meshgrid(jnp.linspace(-1, 1, 20), jnp.linspace(-1, 1, 20))
    tgt = jnp.stack([u.ravel(), v.ravel(), 0.3 * jnp.sin(2 * u.ravel()) * v.ravel() ** 2], -1)
    R = rotation_from_axis_angle(jnp.array([1.0, 1.0, 0.0]), 5.0)
    return (tgt - jnp.array([0.05, 0.0, 0.02])) @ R, tgt


def test_icp_prints_one_line_per_iteration_when_verbose(capsys):
    src, tgt = _surface()
    quiet = icp(src, tgt)
    jax.effects_barrier()
    assert capsys.readouterr().out == ""
    res = icp(src, tgt, verbose=True)
    jax.effects_barrier()
    out = capsys.readouterr().out
    lines = [ln for ln in out.splitlines() if ln.startswith("icp: iteration")]
    assert len(lines) == int(res.iterations) >= 2
    its = [int(re.search(r"iteration (\d+)", ln).group(1)) for ln in lines]
    assert its == list(range(int(res.iterations)))
    rms = [float(re.search(r"rms ([0-9.e+-]+)", ln).group(1)) for ln in lines]
    assert rms[0] > 10 * rms[-1] and "400 pairs" in lines[0]
    # the same answer with and without the progress lines
    np.testing.assert_array_equal(np.asarray(res.R), np.asarray(quiet.R))


def test_calibration_prints_stages_and_lm_steps_when_verbose(capsys):
    P = board_points((9, 6))
    truth = jnp.asarray([500.0, 505.0, 320.0, 240.0, -0.1, 0.01, 0.0, 0.0, 0.0])
    rv = [[0.3, 0.1, 0.0], [-0.2, 0.35, 0.1], [0.1, -0.3, -0.2], [0.4, 0.3, 0.05]]
    tv = [[-4.0, -2.5, 14.0], [-3.0, -3.0, 12.0], [-4.5, -2.0, 15.0], [-4.0, -3.5, 13.0]]
    uv = np.stack([np.asarray(project_board(truth, jnp.asarray(r), jnp.asarray(t), P)) for r, t in zip(rv, tv)])
    uv = uv + 0.1 * np.random.default_rng(0).standard_normal(uv.shape)
    cal = calibrate_camera(P, uv, (640, 480), verbose=True)
    jax.effects_barrier()
    out = capsys.readouterr().out
    assert "4 views x 54 points" in out and "Levenberg-Marquardt over 33 parameters" in out
    steps = [ln for ln in out.splitlines() if ln.strip().startswith("LM step")]
    assert len(steps) == int(cal.iterations) > 3
    assert f"{int(cal.iterations)} steps, converged True" in out
    quiet = calibrate_camera(P, uv, (640, 480))
    jax.effects_barrier()
    assert capsys.readouterr().out == ""
    np.testing.assert_allclose(np.asarray(quiet.K), np.asarray(cal.K), rtol=1e-12)
