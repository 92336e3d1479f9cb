"""Tests of the Python package: values against the command line (the Rust
side), shapes, errors, and a round trip through a render."""

from __future__ import annotations

import json
import os
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest

import svkernel as sk

ROOT = Path(__file__).resolve().parents[2]


def cli_binary() -> Path:
    """The command line built from the same sources (``cargo build --release``)."""
    path = Path(os.environ.get("SVKERNEL_BIN", ROOT / "target" / "release" / "svkernel"))
    if not path.exists():
        if "SVKERNEL_BIN" in os.environ:  # CI names it: it must be there
            pytest.fail(f"SVKERNEL_BIN={path} does not exist")
        pytest.skip(f"{path} not built (cargo build --release)")
    return path


def cli(*args: str, cwd: Path | None = None) -> str:
    out = subprocess.run(
        [str(cli_binary()), *args], capture_output=True, text=True, cwd=cwd, check=True
    )
    return out.stdout


MINI = {
    "name": "mini",
    "texel": 0.05,
    "albedo": {"pattern": "stripes", "values": [0.3, 0.95], "width": 0.5},
    "methods": ["point", "learned"],
    "light": {"kind": "collimated", "radius": 1.0},
    "image": {"resolution": 12, "half_width": 2.0},
}

MINI_TOML = """name = "mini"
texel = 0.05
albedo = { pattern = "stripes", values = [0.3, 0.95], width = 0.5 }
methods = ["point", "learned"]
[light]
kind = "collimated"
radius = 1.0
[image]
resolution = 12
half_width = 2.0
"""


# ----------------------------------------------------------------- kernel


@pytest.mark.parametrize(
    "d, albedo, density, vertices, manual",
    [
        (1.0, 0.9, 1.0, "all", False),
        (0.3, 0.5, 1.0, "last", False),
        (4.0, 0.99, 2.0, "all", False),
        (2.0, 0.8, 0.5, "all", True),
    ],
)
def test_kernel_matches_the_command_line(d, albedo, density, vertices, manual):
    args = ["kernel", "--d", str(d), "--albedo", str(albedo), "--density", str(density)]
    args += ["--vertices", vertices, "--json"] + (["--manual"] if manual else [])
    want = json.loads(cli(*args))
    k = sk.kernel(d, albedo, density, vertices=vertices, manual=manual)
    comps = want["components"]
    assert k.weights.shape == (len(comps),)
    for j, c in enumerate(comps):
        assert k.weights[j] == c["weight"]
        assert tuple(k.centres[j]) == (c["t"], c["s"])
        assert k.widths[j] == c["sigma"]
    assert bool(k.clamped) == want.get("clamped", False)


def test_kernel_broadcasts_and_has_unit_mass():
    d = np.array([[0.5], [1.0], [3.0]])
    a = np.array([0.6, 0.8, 0.9, 0.99])
    k = sk.kernel(d, a, density=1.0)
    kk = k.weights.shape[-1]
    assert k.weights.shape == (3, 4, kk)
    assert k.centres.shape == (3, 4, kk, 2)
    assert k.widths.shape == (3, 4, kk)
    assert k.clamped.shape == (3, 4)
    np.testing.assert_allclose(k.weights.sum(-1), 1.0, atol=1e-9)
    # One element equals its scalar query.
    one = sk.kernel(1.0, 0.9)
    np.testing.assert_array_equal(k.weights[1, 2], one.weights)


def test_kernel_density_scaling_law():
    # ρ = 4 at a quarter of the distance: the same kernel, lengths / 4.
    a = sk.kernel(1.0, 0.9, 1.0)
    b = sk.kernel(0.25, 0.9, 4.0)
    np.testing.assert_allclose(b.weights, a.weights, rtol=1e-12)
    np.testing.assert_allclose(b.centres, a.centres / 4, rtol=1e-12, atol=1e-15)


def test_kernel_refuses_bad_input():
    with pytest.raises(sk.InvalidParameter) as e:
        sk.kernel(np.nan, 0.9)
    assert e.value.key == "d" and "NaN" in str(e.value)
    with pytest.raises(sk.InvalidParameter, match="albedo"):
        sk.kernel(1.0, 1.2)
    with pytest.raises(sk.InvalidParameter) as e:
        sk.kernel(1.0, 0.9, vertices="middle")
    assert e.value.key == "vertices" and "all, first or last" in str(e.value)
    with pytest.raises(ValueError):  # InvalidParameter is a ValueError
        sk.kernel(-1.0, 0.9)


# ----------------------------------------------------------------- profile


def test_profile_matches_the_command_line():
    radii = [0.05, 0.5, 2.0]
    want = json.loads(cli("profile", "--albedo", "0.9", "--radii", "0.05,0.5,2", "--json"))
    p = sk.profile(0.9, radii)
    assert float(p.R_d) == want["R_d"]
    assert float(p.R_1) == want["R_1"] and float(p.R_m) == want["R_m"]
    np.testing.assert_array_equal(p.density, want["density"])
    np.testing.assert_array_equal(p.cdf, want["cdf"])


def test_profile_shapes_and_relations():
    a = np.array([0.3, 0.8, 0.99])
    r = np.linspace(0.0, 10.0, 51)
    p = sk.profile(a, r, incidence="diffuse")
    assert p.R_d.shape == (3,) and p.density.shape == (3, 51)
    np.testing.assert_allclose(p.R_1 + p.R_m, p.R_d, rtol=1e-12)
    assert np.all(np.diff(p.cdf, axis=1) >= 0)
    np.testing.assert_allclose(p.density[:, 1:], 2 * np.pi * r[1:] * p.exitance[:, 1:], rtol=1e-9)
    assert np.all(np.diff(p.R_d) > 0)  # brighter with albedo
    with pytest.raises(sk.InvalidParameter):
        sk.profile(0.5, [-1.0])
    with pytest.raises(sk.InvalidParameter) as e:
        sk.profile(0.5, [1.0], incidence="sideways")
    assert e.value.key == "incidence"


# ----------------------------------------------------------------- SvBssrdf


@pytest.mark.parametrize("method", ["point", "factorized", "manual", "learned"])
def test_svbssrdf_on_a_homogeneous_map_is_the_profile(method):
    s = sk.SvBssrdf(np.full((64, 64), 0.8), texel=0.1, method=method)
    r = np.array([0.1, 0.5, 1.0, 2.0])
    xe = np.stack([r, np.zeros(4)], axis=1)
    v = s.eval(np.zeros((4, 2)), xe)
    # The renderer reads the profile from a table: equal to its interpolation.
    np.testing.assert_allclose(v, sk.profile(0.8, r).exitance, rtol=1e-7)


def test_svbssrdf_colour_channels_are_independent_bssrdfs():
    rng = np.random.default_rng(5)
    rgb = rng.uniform(0.3, 0.95, size=(16, 16, 3))
    s = sk.SvBssrdf(rgb, texel=0.25)
    assert s.channels == 3
    xi = rng.uniform(-1.5, 1.5, size=(50, 2))
    xe = rng.uniform(-1.5, 1.5, size=(50, 2))
    v = s.eval(xi, xe)
    assert v.shape == (50, 3)
    for c in range(3):
        grey = sk.SvBssrdf(rgb[:, :, c], texel=0.25).eval(xi, xe)
        np.testing.assert_array_equal(v[:, c], grey)


def test_svbssrdf_sampling_integrates_to_the_reflectance():
    # Homogeneous: S/pdf is the importance weight; its mean is ∫S dA = R_d.
    s = sk.SvBssrdf(np.full((32, 32), 0.8), texel=0.1)
    rng = np.random.default_rng(3)
    n = 20000
    xe = np.zeros((n, 2))
    xi, pdf = s.sample(xe, rng.random((n, 2)))
    assert xi.shape == (n, 2) and pdf.shape == (n,) and np.all(pdf > 0)
    w = s.eval(xi, xe) / pdf
    assert abs(w.mean() / float(sk.profile(0.8, [1.0]).R_d) - 1) < 1e-6


def test_svbssrdf_density_map_and_edge():
    albedo = np.where(np.arange(32)[None, :] < 16, 0.3, 0.95) * np.ones((32, 1))
    dense = sk.SvBssrdf(albedo, density=np.full((32, 32), 2.0), texel=0.1)
    const = sk.SvBssrdf(albedo, density=2.0, texel=0.1)
    xi = np.array([[-0.3, 0.0], [0.3, 0.0]])
    xe = np.array([[0.2, 0.0], [-0.2, 0.0]])
    np.testing.assert_allclose(dense.eval(xi, xe), const.eval(xi, xe), rtol=1e-9)
    # Paths exiting on the bright side carry more light than on the dark side.
    v = const.eval(np.array([[0.0, 0.0], [0.0, 0.0]]), np.array([[0.5, 0.0], [-0.5, 0.0]]))
    assert v[0] > v[1]


def test_svbssrdf_refuses_bad_maps_and_points():
    with pytest.raises(sk.InvalidParameter, match="albedo"):
        sk.SvBssrdf(np.full((4, 4), 1.5))
    with pytest.raises(sk.InvalidParameter, match="NaN"):
        sk.SvBssrdf(np.array([[0.5, np.nan]]))
    with pytest.raises(sk.InvalidParameter) as e:
        sk.SvBssrdf(np.full((4, 4), 0.5), method="bogus")
    assert e.value.key == "method"
    with pytest.raises(sk.InvalidParameter, match="density"):
        sk.SvBssrdf(np.full((4, 4), 0.5), density=np.ones((3, 4)))
    s = sk.SvBssrdf(np.full((4, 4), 0.5))
    with pytest.raises(sk.InvalidParameter, match=r"shape \(3, 3\)"):
        s.eval(np.zeros((3, 3)), np.zeros((3, 3)))
    with pytest.raises(sk.InvalidParameter, match="differs"):
        s.eval(np.zeros((3, 2)), np.zeros((2, 2)))
    with pytest.raises(sk.InvalidParameter, match=r"\[0, 1\)"):
        s.sample(np.zeros((1, 2)), np.ones((1, 2)))


def test_eval_releases_the_gil():
    s = sk.SvBssrdf(np.full((64, 64), 0.8), texel=0.1)
    n = 1_000_000
    xi = np.zeros((n, 2))
    xe = np.column_stack([np.linspace(0.0, 3.0, n), np.zeros(n)])
    span: list[float] = []

    def work():
        t0 = time.perf_counter()
        s.eval(xi, xe)
        span.extend([t0, time.perf_counter()])

    ticks = []
    t = threading.Thread(target=work)
    t.start()
    while t.is_alive():
        ticks.append(time.perf_counter())
    t.join()
    t0, t1 = span
    mid = (t0 + t1) / 2
    # This thread ran while the other was inside the call.
    assert any(t0 < x < t1 for x in ticks), "no Python work ran during eval"
    assert any(abs(x - mid) < (t1 - t0) / 2 for x in ticks)


# ----------------------------------------------------------------- render


def test_render_round_trip_equals_the_command_line(tmp_path):
    (tmp_path / "mini.toml").write_text(MINI_TOML)
    cli("render", "mini.toml", "--out", "out", "--spp", "32", "--paths", "100000", cwd=tmp_path)
    from_dict = sk.render(MINI, spp=32, reference_paths=100_000)
    from_file = sk.render(tmp_path / "mini.toml", spp=32, reference_paths=100_000)
    for method in ["reference", "point", "learned"]:
        want = np.load(tmp_path / "out" / "main" / f"{method}_mean.npy")
        for r in (from_dict, from_file):
            got = r[method]["mean"]
            assert got.shape == (12, 12, 1)
            np.testing.assert_array_equal(got.reshape(want.shape), want)
            assert r[method]["stderr"].shape == got.shape
    doc = json.loads((tmp_path / "out" / "render.json").read_text())
    rows = {m["method"]: m for m in doc["passes"][0]["methods"]}
    for key in ["rel_rmse", "resolution"]:
        assert from_dict["learned"][key] == pytest.approx(rows["learned"]["metrics"][key])
    assert from_dict["learned"]["resolution"] > 0
    assert "rel_rmse" not in from_dict["reference"]
    assert len(from_dict["passes"]) == 1


def test_render_allocation_follows_the_command_line(tmp_path):
    (tmp_path / "mini.toml").write_text(MINI_TOML)
    cli("render", "mini.toml", "--out", "out", "--spp", "16", "--method", "learned",
        "--allocation", "uniform", cwd=tmp_path)
    want = np.load(tmp_path / "out" / "main" / "learned_mean.npy")
    uniform = sk.render(MINI, methods=["learned"], spp=16, allocation="uniform")
    np.testing.assert_array_equal(uniform["learned"]["mean"].reshape(want.shape), want)
    adaptive = sk.render(MINI, methods=["learned"], spp=16)
    assert not np.array_equal(adaptive["learned"]["mean"], uniform["learned"]["mean"])
    with pytest.raises(sk.InvalidParameter) as e:
        sk.render(MINI, spp=16, allocation="everywhere")
    assert e.value.key == "allocation"


def test_render_canonical_scene_and_methods():
    r = sk.render("stripes", methods=["factorized"], spp=4)
    assert set(r) == {"factorized", "passes"}
    assert r["factorized"]["mean"].shape == (64, 64, 1)
    assert np.all(r["factorized"]["mean"] >= 0)


def test_render_errors_name_file_and_key(tmp_path):
    bad = dict(MINI, texel=-1.0)
    with pytest.raises(sk.FormatError) as e:
        sk.render(bad)
    assert e.value.key == "texel" and "<dict>" in str(e.value)
    (tmp_path / "s.toml").write_text(MINI_TOML.replace("radius = 1.0", "radius = 0.0"))
    with pytest.raises(sk.FormatError) as e:
        sk.render(tmp_path / "s.toml")
    assert e.value.path.endswith("s.toml") and e.value.key == "light.radius"
    with pytest.raises(sk.FileError):
        sk.render(tmp_path / "missing.toml")
    with pytest.raises(sk.InvalidParameter):
        sk.render(dict(MINI, texel=float("nan")))


# ----------------------------------------------------------------- simulation and fits


def test_simulate_profile_equals_the_command_line(tmp_path):
    p = sk.simulate_profile(0.9, paths=50_000, seed=3)
    cli("simulate", "profile", "--albedo", "0.9", "--paths", "50000", "--seed", "3",
        "--out", str(tmp_path / "p.json"))
    want = json.loads((tmp_path / "p.json").read_text())
    assert p.R_d == want["R_d"] and p.doc["tally"] == want["tally"]
    assert p.edges.shape[0] == p.density.shape[0] + 1
    # Against the basis model (fitted to 1e8-path tallies): within the noise.
    assert abs(p.R_d - float(sk.profile(0.9, [1.0]).R_d)) < 5 * p.R_d_stderr + 2e-3
    p.save(tmp_path / "again.json")
    assert json.loads((tmp_path / "again.json").read_text())["R_d"] == p.R_d
    with pytest.raises(sk.InvalidParameter) as e:
        sk.simulate_profile(0.9, g=1.5, paths=10)
    assert e.value.key == "g"


def test_simulate_and_fit_kernels_give_a_usable_meta_model(tmp_path):
    tally = sk.simulate_kernels([0.8, 0.9, 0.95], [0.5, 1.0, 2.0], paths=400_000, seed=11)
    assert len(tally.cells) == 9
    model, report = sk.fit_kernels(tally, components=2, degrees=(1, 1))
    assert model.components == 2 and model.origin == "<fit>"
    assert report["joint"] and report["aggregation"]
    k = sk.kernel(1.0, 0.9, model=model)
    assert k.weights.shape == (2,)
    np.testing.assert_allclose(k.weights.sum(), 1.0, atol=1e-9)
    # Save, load and parse: the same kernels.
    model.save(tmp_path / "meta.json")
    for again in (sk.MetaModel.load(tmp_path / "meta.json"), sk.MetaModel.from_json(model.to_json())):
        np.testing.assert_array_equal(sk.kernel(1.0, 0.9, model=again).centres, k.centres)
    # The CLI reads the saved model.
    want = json.loads(cli("kernel", "--d", "1", "--albedo", "0.9", "--model", str(tmp_path / "meta.json"), "--json"))
    assert [c["weight"] for c in want["components"]] == list(k.weights)
    # A fitted model renders.
    s = sk.SvBssrdf(np.full((8, 8), 0.9), texel=0.2, model=model)
    assert s.eval([[0.0, 0.0]], [[0.5, 0.0]])[0] > 0
    tally.save(tmp_path / "tally.json")
    assert json.loads((tmp_path / "tally.json").read_text())["paths"] == tally.doc["paths"]
    # A refit from the model starts where its fit ended: no higher χ².
    again, refit = sk.fit_kernels(tally, start=model)
    assert again.components == 2
    for a, b in zip(refit["joint"], report["joint"]):
        assert a["chi2_per_dof"] <= b["chi2_per_dof"]
    # Any cell it calls stuck is far worse under the start than its own fit.
    for _, cells in refit["stuck"]:
        assert all(c["chi2"] > 100 * c["own_chi2"] for c in cells)
    # The shipped model's box is not this tally's.
    with pytest.raises(sk.FitError) as e:
        sk.fit_kernels(tally, start=sk.MetaModel.default())
    assert "box" in str(e.value)


def test_meta_model_default_and_errors(tmp_path):
    m = sk.MetaModel.default()
    assert m.components >= 1 and "MetaModel" in repr(m)
    np.testing.assert_array_equal(sk.kernel(1.0, 0.9, model=m).weights, sk.kernel(1.0, 0.9).weights)
    (tmp_path / "bad.json").write_text("{}")
    with pytest.raises(sk.FormatError) as e:
        sk.MetaModel.load(tmp_path / "bad.json")
    assert "bad.json" in str(e.value)
    with pytest.raises(sk.FileError):
        sk.MetaModel.load(tmp_path / "missing.json")
    with pytest.raises(sk.InvalidParameter):
        sk.fit_kernels("not a tally")


# ----------------------------------------------------------------- design


def test_design_beats_the_naive_map():
    # Reflectance 0.17 ± 0.07 in sines of period 2 MFP: detail at the transport's scale.
    y, x = np.mgrid[0:40, 0:40]
    target = 0.17 + 0.07 * np.sin(2 * np.pi * y / 20) * np.sin(2 * np.pi * x / 20)
    d = sk.design(target, texel=0.1)
    assert d.albedo.shape == target.shape and d.predicted.shape == target.shape
    assert np.all((d.albedo >= 0.2 - 1e-12) & (d.albedo <= 0.99 + 1e-12))
    err = lambda m: np.sqrt(np.mean((m - target) ** 2))  # noqa: E731
    assert err(d.predicted) < 0.5 * err(d.predicted_naive)
    assert d.history and d.evaluations > 0 and d.stops
    rgb = sk.design(np.stack([target] * 3, axis=2), texel=0.1, iterations=3, warm_start=5)
    assert rgb.albedo.shape == (40, 40, 3)
    np.testing.assert_array_equal(rgb.albedo[:, :, 0], rgb.albedo[:, :, 2])


def test_design_refuses_bad_targets_and_settings():
    with pytest.raises(sk.InvalidParameter, match="NaN"):
        sk.design(np.array([[0.1, np.nan]]))
    with pytest.raises(sk.InvalidParameter, match=r"\[0, 1\]"):
        sk.design(np.full((4, 4), 1.2))
    with pytest.raises(sk.InvalidParameter) as e:
        sk.design(np.full((4, 4), 0.2), albedo_range=(0.9, 0.2))
    assert e.value.key == "albedo-range"
    with pytest.raises(sk.InvalidParameter):
        sk.design(np.full((4, 4), 0.2), illumination="spot")


# ----------------------------------------------------------------- package


def test_info_names_the_models():
    i = sk.info()
    assert i["version"] == sk.__version__
    assert {"basis", "basis_diffuse", "meta"} <= set(i)


def test_every_public_name_is_documented():
    for name in sk.__all__:
        obj = getattr(sk, name)
        assert obj.__doc__ and obj.__doc__.strip(), name
        for attr in dir(obj):
            if not attr.startswith("_") and callable(getattr(obj, attr, None)) and isinstance(obj, type):
                member = getattr(obj, attr)
                if attr in ("count", "index"):  # NamedTuple's tuple methods
                    continue
                assert member.__doc__, f"{name}.{attr}"


def test_errors_are_a_hierarchy():
    assert issubclass(sk.InvalidParameter, sk.Error) and issubclass(sk.InvalidParameter, ValueError)
    assert issubclass(sk.FileError, OSError) and issubclass(sk.FormatError, ValueError)
    assert issubclass(sk.FitError, RuntimeError)


def test_docstring_examples_run():
    import doctest

    failures, tried = doctest.testmod(sk, optionflags=doctest.NORMALIZE_WHITESPACE)
    assert tried >= 3 and failures == 0
