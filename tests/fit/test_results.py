"""The one result vocabulary of the fits: RESULTS, base fields, NamedParams, deprecated names."""

from __future__ import annotations

import dataclasses
import inspect
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fsjax
import fsjax.fit
from fsjax.types import RESULTS, FitResult, NamedParams, reason_code, reason_message
from fsjax.types.results import result_item

# records of fsjax.fit that are not fit results, each with its docstring's reason
NOT_FITS = {"FrameSelection", "ModelSelection", "MultiViewData"}


def _records():
    out = {}
    for name in dir(fsjax.fit):
        obj = getattr(fsjax.fit, name)
        if inspect.isclass(obj) and issubclass(obj, eqx.Module) and obj.__module__.startswith("fsjax.fit"):
            out[name] = obj
    return out


def _has(cls, name):
    return name in {f.name for f in dataclasses.fields(cls)} or isinstance(getattr(cls, name, None), property)


def test_every_member_has_a_message_and_a_stable_code():
    names = [n for n in RESULTS._name_to_item]
    assert len(names) == len(RESULTS) >= 15
    codes = [reason_code(n) for n in names]
    assert sorted(codes) == list(range(len(names)))
    for n in names:
        msg = reason_message(reason_code(n))
        assert isinstance(msg, str) and len(msg) >= 2, n
        assert RESULTS[getattr(RESULTS, n)] == msg
    # the registration codes of the old REGISTRATION_REASONS keep their numbers
    assert [reason_code(n) for n in ("ok", "max_iterations", "too_few", "degenerate", "invalid_input",
                                     "poor_fit", "no_hypothesis")] == list(range(7))
    assert reason_message(99).startswith("unknown reason code")


def test_results_are_jit_and_vmap_safe():
    codes = jnp.arange(len(RESULTS), dtype=jnp.int32)
    ok = jax.jit(jax.vmap(lambda c: result_item(c) == RESULTS.ok))(codes)
    assert ok.tolist() == [True] + [False] * (len(RESULTS) - 1)
    # a record built inside jit and vmap: reason batches like any leaf, messages read per element
    src = jnp.array([[0.0, 0, 0], [1, 0, 0], [0, 2, 0], [0, 0, 3], [1, 1, 1]])
    w = jnp.stack([jnp.ones(5), jnp.array([1.0, 1, 0, 0, 0])])
    res = jax.jit(jax.vmap(lambda w: fsjax.fit.kabsch_umeyama(src, src + 1.0, weights=w)))(w)
    assert res.reason.shape == (2,) and res.reason.dtype == jnp.int32
    assert res.converged.tolist() == [True, False]
    assert list(res.message) == ["ok", reason_message(reason_code("too_few"))]
    assert (res.result == RESULTS.too_few).tolist() == [False, True]


def test_every_fit_result_has_the_base_fields():
    recs = _records()
    fits = {n: c for n, c in recs.items() if n not in NOT_FITS}
    assert len(fits) == 15, sorted(fits)
    for name, cls in fits.items():
        assert issubclass(cls, FitResult), name
        for field in ("converged", "reason", "iterations"):
            assert _has(cls, field), (name, field)
        rn = cls.residual_name
        if rn is None:  # the docstring says why there is no residual
            assert "residual" in cls.__doc__, name
        else:
            assert rn.startswith(("rms_", "sampson_rms_")) and rn.split("_")[-1] in ("px", "len"), (name, rn)
            assert _has(cls, rn), (name, rn)
    for name in NOT_FITS & set(recs):
        if name != "MultiViewData":  # input data, not a result
            assert "Not a fit result" in recs[name].__doc__, name


def test_named_params_once():
    assert issubclass(fsjax.Fit, NamedParams)
    assert issubclass(fsjax.fit.Fit3D, NamedParams) and issubclass(fsjax.fit.RansacResult, NamedParams)
    f = fsjax.fit.fit_sphere(jnp.array([[3.0, 0, 0], [-1, 0, 0], [1, 2, 0], [1, -2, 0], [1, 0, 2], [1, 0, -2]]))
    assert abs(float(f["r"]) - 2.0) < 1e-9 and abs(float(f["cx"]) - 1.0) < 1e-9
    with pytest.raises(KeyError, match="Fit3D: no parameter 'q'; parameters: cx, cy, cz, r"):
        f["q"]
    batched = jax.vmap(lambda s: fsjax.fit.fit_sphere(s * jnp.array([[3.0, 0, 0], [-1, 0, 0], [1, 2, 0], [1, -2, 0],
                                                                        [1, 0, 2], [1, 0, -2]])))(jnp.array([1.0, 2.0]))
    assert np.allclose(np.asarray(batched["r"]), [2.0, 4.0])


def _deprecated(obj, old, new):
    with pytest.warns(DeprecationWarning, match=new.replace(".", r"\.")):
        value = getattr(obj, old)
    return value


def test_deprecated_fields_warn_and_give_the_same_value():
    src = jnp.array([[0.0, 0, 0], [1, 0, 0], [0, 2, 0], [0, 0, 3], [1, 1, 1]])
    fit = fsjax.fit.kabsch_umeyama(src, src + 1.0)
    assert _deprecated(fit, "rms", "rms_len") is fit.rms_len
    assert _deprecated(fit, "valid", "converged") is fit.converged
    f3 = fsjax.fit.fit_plane(src[:4] * jnp.array([1.0, 1, 0]))
    assert _deprecated(f3, "rms", "rms_len") is f3.rms_len
    ransac = fsjax.fit.ransac_plane(jax.random.key(0), src * jnp.array([1.0, 1, 0]), threshold=0.1, n_hypotheses=8)
    assert _deprecated(ransac, "rms", "rms_len") is ransac.rms_len
    assert int(_deprecated(ransac, "legacy_reason", "RansacResult.reason")) == 0
    with pytest.warns(DeprecationWarning, match="RansacResult.message"):
        assert ransac.reason_text() == ransac.message == "ok"
    # old code tables: same codes as the records now carry (messages of RESULTS)
    for name in ("REGISTRATION_REASONS", "PNP_REASONS", "TWOVIEW_REASONS", "REASONS", "BA_REASONS"):
        table = _deprecated(fsjax.fit, name, "fsjax.types.RESULTS")
        assert table[0] == "ok" and all(table[c] == reason_message(c) for c in table)


def test_deprecated_names_warn_and_are_the_same_function():
    x = jnp.asarray(np.random.default_rng(0).normal(size=(50, 3)))
    knn = _deprecated(fsjax.fit, "knn", "fsjax.ops.knn")
    i_old, d_old = knn(x, x[:5], 4)
    i_new, d_new = fsjax.ops.knn(x, x[:5], 4)
    assert np.array_equal(np.asarray(i_old), np.asarray(i_new)) and np.allclose(d_old, d_new)
    assert _deprecated(fsjax.fit, "fit_line", "fsjax.fit.fit_line3d") is fsjax.fit.fit_line3d
    en = _deprecated(fsjax.fit, "estimate_normals", "fsjax.ops.estimate_normals")
    plane = jnp.asarray(np.c_[np.random.default_rng(1).uniform(size=(40, 2)), np.zeros(40)])
    n_old = np.abs(np.asarray(en(plane, k=8)))
    n_new = np.abs(np.asarray(fsjax.ops.estimate_normals(fsjax.Points(plane), k=8).normals))
    assert np.allclose(n_old, n_new, atol=1e-9) and np.allclose(n_new[:, 2], 1.0)
    psnr = _deprecated(fsjax.fit, "psnr", "fsjax.ops.psnr")
    a, b = jnp.full((4, 4, 3), 0.5), jnp.full((4, 4, 3), 0.6)
    assert abs(float(psnr(a, b)) - 20.0) < 1e-9
    assert abs(float(psnr(a, b)) - float(fsjax.ops.psnr(fsjax.Image(a[..., 0]), fsjax.Image(b[..., 0])).value)) < 1e-12


def test_no_warning_on_the_new_names():
    src = jnp.array([[0.0, 0, 0], [1, 0, 0], [0, 2, 0], [0, 0, 3], [1, 1, 1]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fit = fsjax.fit.kabsch_umeyama(src, src)
        _ = (fit.converged, fit.reason, fit.iterations, fit.rms_len, fit.message, fit.result, fit.residual)
        _ = fsjax.fit.fit_line3d(src)


def test_docs_list_every_reason_once():
    from pathlib import Path

    text = (Path(__file__).resolve().parents[2] / "docs" / "results.md").read_text()
    for n in RESULTS._name_to_item:
        row = f"| {reason_code(n)} | `{n}` | {reason_message(reason_code(n))} |"
        assert text.count(row) == 1, n


def test_evolve_skeleton_renamed():
    import fsjax.evolve

    with pytest.warns(DeprecationWarning, match="fsjax.evolve.type_skeleton"):
        sk = fsjax.evolve.skeleton
    assert sk is fsjax.evolve.type_skeleton
