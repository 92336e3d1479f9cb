"""svkernel from Python: learned aggregation kernels for spatially varying BSSRDFs.

The library behind the ``svkernel`` command line, called directly on numpy
arrays. Lengths are in mean free paths (MFP) of the reference medium; maps are
row-major ``(ny, nx)`` or ``(ny, nx, 3)`` arrays, row 0 at +y, column 0 at -x,
the texture centred on the origin.

* :func:`kernel` -- the learned (or manual) aggregation kernel at (d, albedo, density);
* :func:`profile` -- the homogeneous diffuse profile of the basis BSSRDF;
* :class:`SvBssrdf` -- the SV-BSSRDF of an albedo (and density) map: ``eval``, ``sample``;
* :func:`render` -- a scene (file, canonical name or dict), every method and the reference;
* :func:`simulate_profile`, :func:`simulate_kernels`, :func:`fit_kernels` -- Monte Carlo and fits;
* :func:`design` -- the albedo map whose appearance after scattering matches a target.

Heavy work releases the GIL. Errors are :class:`Error` subclasses that name the
parameter, or the file and key, that was refused.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Dict, List, NamedTuple, Optional, Sequence, Tuple, Union

import numpy as np

from . import _svkernel
from ._errors import Error, FileError, FitError, FormatError, InvalidParameter
from ._svkernel import MetaModel

__all__ = [
    "Design",
    "Error",
    "FileError",
    "FitError",
    "FormatError",
    "InvalidParameter",
    "Kernel",
    "KernelSimulation",
    "MetaModel",
    "Profile",
    "ProfileSimulation",
    "SvBssrdf",
    "design",
    "fit_kernels",
    "info",
    "kernel",
    "profile",
    "render",
    "simulate_kernels",
    "simulate_profile",
]

__version__ = "0.1.0"

ArrayLike = Union[float, Sequence[float], np.ndarray]


def _finite(name: str, a: Any, shape: Optional[Tuple[Optional[int], ...]] = None) -> np.ndarray:
    """``a`` as a float64 array, refused (naming it) if not finite or of the wrong shape."""
    try:
        arr = np.asarray(a, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise InvalidParameter(f"invalid {name}: not a float array ({e})", key=name) from None
    if shape is not None:
        ok = arr.ndim == len(shape) and all(s is None or s == n for s, n in zip(shape, arr.shape))
        if not ok:
            want = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"
            raise InvalidParameter(
                f"invalid {name}: shape {arr.shape}, must be {want}", key=name
            )
    if not np.all(np.isfinite(arr)):
        raise InvalidParameter(f"invalid {name}: holds NaN or infinite values", key=name)
    return arr


def _flat(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float64).reshape(-1)


def info() -> Dict[str, str]:
    """The library version and where each model in use came from.

    Models are found as the command line finds them: the files named by the
    ``SVKERNEL_*`` environment variables if set, else the built-in copies.
    """
    return dict(_svkernel.info())


# --------------------------------------------------------------------------- kernels


class Kernel(NamedTuple):
    """A Gaussian-mixture kernel per query, in the pair frame (t from x_i toward x_e, s across).

    ``weights`` (..., K) are the components' masses; ``centres`` (..., K, 2) their
    (t, s) in MFP; ``widths`` (..., K) their isotropic standard deviations in MFP;
    ``clamped`` (...) is True where (d, albedo) lay outside the range the
    meta-model covers (that of its outer model, fitted over a wider box, where it
    carries one) and was clamped to it. Unused components have zero weight.
    """

    weights: np.ndarray
    centres: np.ndarray
    widths: np.ndarray
    clamped: np.ndarray


def kernel(
    d: ArrayLike,
    albedo: ArrayLike,
    density: ArrayLike = 1.0,
    vertices: str = "all",
    manual: bool = False,
    model: Optional[MetaModel] = None,
) -> Kernel:
    """The aggregation kernel for pair distance ``d`` (MFP), albedo and density.

    The inputs broadcast against each other (numpy rules); the result has their
    broadcast shape plus the component axes. ``vertices`` is ``"all"`` (the
    kernel of every scattering vertex), ``"last"`` or ``"first"``. ``manual=True``
    gives the fixed manual kernel instead of the learned one (it depends on
    ``d`` and the density only). ``model`` replaces the meta-model in use
    (:meth:`MetaModel.default`).

    >>> k = kernel([0.5, 1.0, 4.0], 0.9)
    >>> k.weights.shape[0], bool(np.allclose(k.weights.sum(-1), 1.0))
    (3, True)
    """
    d_, a_, r_ = np.broadcast_arrays(
        _finite("d", d), _finite("albedo", albedo), _finite("density", density)
    )
    if np.any(d_ <= 0):
        raise InvalidParameter("invalid d: must be > 0 (MFP)", key="d")
    if np.any((a_ < 0) | (a_ > 1)):
        raise InvalidParameter("invalid albedo: must be in [0, 1]", key="albedo")
    if np.any(r_ <= 0):
        raise InvalidParameter("invalid density: must be > 0", key="density")
    w, c, s, clamped = _svkernel.kernel(
        _flat(d_), _flat(a_), _flat(r_), vertices, bool(manual), model
    )
    shape = d_.shape
    k = w.shape[1]
    return Kernel(
        w.reshape(shape + (k,)),
        c.reshape(shape + (k, 2)),
        s.reshape(shape + (k,)),
        clamped.reshape(shape),
    )


# --------------------------------------------------------------------------- profiles


class Profile(NamedTuple):
    """The basis BSSRDF's homogeneous profile (exitance per unit incident power).

    ``R_d``, ``R_1``, ``R_m`` have the albedo's shape: diffuse reflectance, and
    its single- and multiple-scattering parts. ``exitance`` R(r) (1/MFP²),
    ``density`` p(r) = 2πr·R(r) (1/MFP) and ``cdf`` ∫₀ʳ p / R_d have shape
    ``albedo.shape + radii.shape``.
    """

    R_d: np.ndarray
    R_1: np.ndarray
    R_m: np.ndarray
    exitance: np.ndarray
    density: np.ndarray
    cdf: np.ndarray


def profile(albedo: ArrayLike, radii: ArrayLike, incidence: str = "collimated") -> Profile:
    """The homogeneous profile at ``albedo`` for radii ``radii`` (MFP).

    ``incidence`` is ``"collimated"`` (normal incidence, the default) or
    ``"diffuse"``. Albedos outside [0, 1] and negative radii are refused.

    >>> p = profile(0.9, np.linspace(0.0, 5.0, 11))
    >>> p.density.shape, 0.0 < float(p.R_d) < 1.0
    ((11,), True)
    """
    a = _finite("albedo", albedo)
    r = _finite("radii", radii)
    if np.any((a < 0) | (a > 1)):
        raise InvalidParameter("invalid albedo: must be in [0, 1]", key="albedo")
    if np.any(r < 0):
        raise InvalidParameter("invalid radii: must be >= 0 (MFP)", key="radii")
    out = _svkernel.profile(_flat(a), _flat(r), incidence)
    shape = a.shape + r.shape
    return Profile(
        out["R_d"].reshape(a.shape),
        out["R_1"].reshape(a.shape),
        out["R_m"].reshape(a.shape),
        out["exitance"].reshape(shape),
        out["density"].reshape(shape),
        out["cdf"].reshape(shape),
    )


# --------------------------------------------------------------------------- SV-BSSRDF


def _planes(name: str, a: Any) -> Tuple[np.ndarray, int, int, int]:
    """A map (ny, nx) or (ny, nx, C) as channel-major planes (C, ny, nx)."""
    arr = _finite(name, a)
    if arr.ndim == 2:
        arr = arr[None, :, :]
    elif arr.ndim == 3:
        arr = np.moveaxis(arr, 2, 0)
    else:
        raise InvalidParameter(
            f"invalid {name}: shape {arr.shape}, must be (ny, nx) or (ny, nx, C)", key=name
        )
    c, ny, nx = arr.shape
    if nx == 0 or ny == 0 or c == 0:
        raise InvalidParameter(f"invalid {name}: empty map {arr.shape}", key=name)
    return arr, c, ny, nx


class SvBssrdf:
    """The SV-BSSRDF S(x_i, x_e) of an albedo map (and a density), by any method.

    ``albedo`` is ``(ny, nx)`` (grey) or ``(ny, nx, C)`` (one BSSRDF per channel)
    with values in [0, 1]; ``density`` is None (1), a positive constant or a
    ``(ny, nx)`` map of ρ (σ_t = ρ). ``texel`` is the texel size τ in MFP; the
    texture is centred on the origin. ``method`` is one of ``point``,
    ``factorized``, ``line``, ``ellipse``, ``manual``, ``learned``. ``incidence``
    selects the basis profiles (``"collimated"`` or ``"diffuse"`` lights);
    ``model`` replaces the meta-model.

    >>> s = SvBssrdf(np.array([[0.3, 0.9]]), texel=1.0)
    >>> v = s.eval([[-0.5, 0.0]], [[0.5, 0.0]])
    >>> v.shape, bool(v[0] > 0)
    ((1,), True)
    """

    def __init__(
        self,
        albedo: Any,
        density: Union[None, float, np.ndarray] = None,
        texel: float = 0.1,
        method: str = "learned",
        incidence: str = "collimated",
        model: Optional[MetaModel] = None,
    ) -> None:
        planes, c, ny, nx = _planes("albedo", albedo)
        if np.any((planes < 0) | (planes > 1)):
            raise InvalidParameter("invalid albedo: must be in [0, 1]", key="albedo")
        texel = float(texel)
        if not (texel > 0 and np.isfinite(texel)):
            raise InvalidParameter(f"invalid texel = {texel}: must be > 0 (MFP)", key="texel")
        constant, density_map = 1.0, None
        if density is not None and np.ndim(density) == 0:
            constant = float(density)
            if not (constant > 0 and np.isfinite(constant)):
                raise InvalidParameter(f"invalid density = {constant}: must be > 0", key="density")
        elif density is not None:
            dm = _finite("density", density, (ny, nx))
            if np.any(dm <= 0):
                raise InvalidParameter("invalid density: must be > 0", key="density")
            density_map = _flat(dm)
        self._inner = _svkernel._SvBssrdf(
            _flat(planes), c, ny, nx, texel, method, incidence, constant, density_map, model
        )
        self.method = method
        self.shape = (ny, nx) if np.ndim(albedo) == 2 else (ny, nx, c)
        self.texel = texel

    @property
    def channels(self) -> int:
        """Colour channels (1 for a grey map)."""
        return int(self._inner.channels)

    def eval(self, xi: Any, xe: Any) -> np.ndarray:
        """S(x_i, x_e) (1/MFP²) for pairs of points, arrays of shape (N, 2) (MFP).

        Returns shape (N,) for a grey map, (N, C) for a C-channel map.
        """
        xi_ = _finite("xi", xi, (None, 2))
        xe_ = _finite("xe", xe, (None, 2))
        if xi_.shape != xe_.shape:
            raise InvalidParameter(
                f"invalid xe: shape {xe_.shape} differs from xi's {xi_.shape}", key="xe"
            )
        out = self._inner.eval(_flat(xi_), _flat(xe_))
        n = xi_.shape[0]
        return out if len(self.shape) == 2 else out.reshape(n, self.channels)

    def sample(self, xe: Any, u: Any) -> Tuple[np.ndarray, np.ndarray]:
        """Importance-samples entry points for exit points ``xe`` (N, 2).

        ``u`` (N, 2) holds uniform numbers in [0, 1). Returns ``(xi, pdf)``: the
        entry points (N, 2) and their density per unit area (1/MFP²), the
        sampler a renderer uses (the homogeneous profile at the local albedo).
        """
        xe_ = _finite("xe", xe, (None, 2))
        u_ = _finite("u", u, (None, 2))
        if u_.shape != xe_.shape:
            raise InvalidParameter(f"invalid u: shape {u_.shape} differs from xe's", key="u")
        if np.any((u_ < 0) | (u_ >= 1)):
            raise InvalidParameter("invalid u: must be in [0, 1)", key="u")
        xi, pdf = self._inner.sample(_flat(xe_), _flat(u_))
        return xi.reshape(-1, 2), pdf

    def __repr__(self) -> str:
        return f"SvBssrdf(method={self.method!r}, shape={self.shape}, texel={self.texel})"


# --------------------------------------------------------------------------- render


def _toml_value(v: Any, key: str) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        f = float(v)
        if not np.isfinite(f):
            raise InvalidParameter(f"invalid {key}: {f} is not finite", key=key)
        return repr(f)
    if isinstance(v, (str, os.PathLike)):
        return json.dumps(str(v))
    if isinstance(v, (list, tuple, np.ndarray)):
        return "[" + ", ".join(_toml_value(x, key) for x in v) + "]"
    if isinstance(v, dict):
        items = ", ".join(f"{json.dumps(str(k))} = {_toml_value(x, f'{key}.{k}')}" for k, x in v.items())
        return "{" + items + "}"
    raise InvalidParameter(f"invalid {key}: {type(v).__name__} has no TOML form", key=key)


def _scene_text(scene: Union[str, os.PathLike, Dict[str, Any]]) -> Tuple[Optional[str], str]:
    """(TOML text, origin) of a scene dict; (None, path or name) otherwise."""
    if isinstance(scene, dict):
        lines = [f"{json.dumps(str(k))} = {_toml_value(v, str(k))}" for k, v in scene.items()]
        return "\n".join(lines) + "\n", str(Path.cwd() / "<dict>.toml")
    return None, os.fspath(scene)


def render(
    scene: Union[str, os.PathLike, Dict[str, Any]],
    methods: Optional[Sequence[str]] = None,
    spp: Optional[int] = None,
    reference_paths: Optional[int] = None,
    seed: int = 1,
    progress: bool = False,
    model: Optional[MetaModel] = None,
    allocation: str = "adaptive",
) -> Dict[str, Any]:
    """Renders a scene with its methods and the brute-force reference.

    ``scene`` is a scene file, a canonical scene name (``"stripes"``, ...) or a
    dict with the scene file's TOML schema (texture paths relative to the
    current folder). ``methods`` overrides the scene's (``"reference"`` is one
    of them; default: the scene's methods and the reference). ``spp`` and
    ``reference_paths`` override the scene's budgets. ``allocation`` shares
    the model methods' samples among the pixels: ``"adaptive"`` (``spp`` is
    the mean over the image, each pixel's share following its value in a
    pilot render) or ``"uniform"`` (``spp`` in every pixel), as the command
    line's ``--allocation``.

    Returns a dict with one entry per method (``"reference"``, ``"learned"``,
    ...), each a dict of ``mean`` and ``stderr`` images of shape
    ``(resolution, resolution, channels)``, ``seconds``, and for the model
    methods the metrics against the reference: ``rel_rmse`` (relative RMSE
    with both images' noise subtracted), ``rel_bias``, ``resolution`` (the
    smallest ``rel_rmse`` the two images' noise resolves: below it the
    error is at most ``hypot(rel_rmse, resolution)``) and ``channels``
    (per-channel pairs of ``rel_rmse`` and ``rel_bias``). ``passes`` lists one such dict per pass (``tag``,
    ``density``, ``methods``) for scenes with a density sweep; the top-level
    entries are the first pass's.
    """
    text, origin = _scene_text(scene)
    passes = _svkernel.render(
        text,
        origin,
        None if methods is None else list(methods),
        None if spp is None else int(spp),
        None if reference_paths is None else int(reference_paths),
        int(seed),
        bool(progress),
        model,
        str(allocation),
    )
    result: Dict[str, Any] = dict(passes[0]["methods"])
    result["passes"] = list(passes)
    return result


# --------------------------------------------------------------------------- simulation and fits


class ProfileSimulation:
    """A simulated homogeneous profile: the document ``svkernel simulate-profile`` writes.

    ``doc`` is the whole document (a dict); the common numbers are attributes:
    ``R_d``, ``R_d_stderr``, ``R_1``, ``R_m`` (reflectances), ``edges`` (bin edges,
    MFP), ``density`` and ``density_stderr`` (p(r) = 2πr·R(r) per bin, single
    plus multiple scattering, 1/MFP). :meth:`save` writes the document for the
    command line (``svkernel fit-profiles`` reads it).
    """

    def __init__(self, text: str) -> None:
        self._text = text
        self.doc: Dict[str, Any] = json.loads(text)
        bins = self.doc["bins"]
        self.R_d = float(self.doc["R_d"])
        self.R_d_stderr = float(self.doc["R_d_stderr"])
        self.R_1 = float(self.doc["R_1"])
        self.R_m = float(self.doc["R_m"])
        self.edges = np.asarray(bins["edges"], dtype=np.float64)
        p1, pm = np.asarray(bins["p_1"]), np.asarray(bins["p_m"])
        self.density = p1 + pm
        self.density_stderr = np.hypot(bins["p_1_stderr"], bins["p_m_stderr"])

    def save(self, path: Union[str, os.PathLike]) -> None:
        """Writes the document (JSON) to ``path``."""
        _write_text(path, self._text)

    def __repr__(self) -> str:
        m = self.doc["config"]["medium"]
        return (
            f"ProfileSimulation(albedo={m['alpha']}, paths={self.doc['paths']}, "
            f"R_d={self.R_d:.5f} ± {self.R_d_stderr:.5f})"
        )


def _write_text(path: Union[str, os.PathLike], text: str) -> None:
    """Writes ``text`` through a temporary file, so a failure leaves nothing behind."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.partial")
    try:
        tmp.write_text(text)
        os.replace(tmp, path)
    except OSError as e:
        tmp.unlink(missing_ok=True)
        raise FileError(f"{path}: {e}", path=str(path)) from None


def simulate_profile(
    albedo: float,
    g: float = 0.3,
    eta: float = 1.5,
    density: float = 1.0,
    source: str = "pencil",
    paths: int = 1_000_000,
    seed: int = 1,
    max_events: int = _svkernel.DEFAULT_MAX_EVENTS,
    thickness: Optional[float] = None,
    progress: bool = False,
) -> ProfileSimulation:
    """Simulates the radial profile of a homogeneous half-space (or slab) by analog Monte Carlo.

    ``source`` is ``"pencil"``, ``"diffuse"``, ``"collimated:R"`` or
    ``"diffuse:R"`` (disk of radius R MFP). The result is bitwise the same for
    any thread count and equals the command line's for the same arguments.
    """
    return ProfileSimulation(
        _svkernel.simulate_profile(
            float(albedo), float(g), float(eta), float(density), source,
            int(paths), int(seed), int(max_events),
            None if thickness is None else float(thickness), bool(progress),
        )
    )


class KernelSimulation:
    """A simulated kernel tally: the document ``svkernel simulate-kernels`` writes.

    ``doc`` is the whole document; ``cells`` its per-cell summary (albedo,
    distance, contributing paths, vertex means). Pass it to :func:`fit_kernels`,
    or :meth:`save` it for ``svkernel fit-kernels``.
    """

    def __init__(self, text: str) -> None:
        self._text = text
        self.doc: Dict[str, Any] = json.loads(text)
        self.cells: List[Dict[str, Any]] = self.doc["summary"]
        self.albedos: List[float] = self.doc["config"]["albedos"]
        self.distances: List[float] = self.doc["config"]["distances"]

    def save(self, path: Union[str, os.PathLike]) -> None:
        """Writes the document (JSON) to ``path``."""
        _write_text(path, self._text)

    def __repr__(self) -> str:
        return (
            f"KernelSimulation(albedos={self.albedos}, distances={self.distances}, "
            f"paths={self.doc['paths']})"
        )


def simulate_kernels(
    albedos: Sequence[float],
    distances: Sequence[float],
    g: float = 0.3,
    eta: float = 1.5,
    paths: int = 1_000_000,
    seed: int = 1,
    progress: bool = False,
) -> KernelSimulation:
    """Simulates where the paths between x_i and x_e scatter, at unit density.

    One cell per (albedo, distance d in MFP); the pair grid, window and
    scattering order are the shipped training configuration's.
    """
    return KernelSimulation(
        _svkernel.simulate_kernels(
            [float(a) for a in albedos], [float(d) for d in distances],
            float(g), float(eta), int(paths), int(seed), bool(progress),
        )
    )


def fit_kernels(
    tally: KernelSimulation,
    components: int = 3,
    degrees: Tuple[int, int] = (2, 2),
    progress: bool = False,
    start: Optional[MetaModel] = None,
) -> Tuple[MetaModel, Dict[str, Any]]:
    """Fits a meta-model (K Gaussians; polynomial degrees in ln d and √(1 − α)) to a tally.

    With ``start``, a fitted model over the same box of (d, α) and the same
    medium, the joint fits start from its coefficients, at its K and
    degrees (``components`` and ``degrees`` are then not used): a refit of
    new data, as ``svkernel fit kernels --from``.

    Returns the model (usable as ``model=`` everywhere, :meth:`MetaModel.save`)
    and the fit report: the joint fits (``termination``, ``evaluations``,
    ``chi2_per_dof``) and every cell's aggregation error (``aggregation``:
    ``meta`` and ``manual`` are the RMS errors of the aggregated albedo, in
    albedo units, of the meta-model and of the manual kernel). ``stuck``
    lists, per vertex class, the cells where the joint fit's start (``start``,
    or the top of the ladder of degrees) was stuck far above their own
    per-cell fit and which it refitted with a width floor first (``alpha``,
    ``d``, the cell's ``chi2`` there and its per-cell fit's ``own_chi2``).
    """
    if not isinstance(tally, KernelSimulation):
        raise InvalidParameter("invalid tally: must be a KernelSimulation", key="tally")
    if start is not None and not isinstance(start, MetaModel):
        raise InvalidParameter("invalid start: must be a MetaModel", key="start")
    model, report = _svkernel.fit_kernels(
        tally._text, int(components), (int(degrees[0]), int(degrees[1])), bool(progress), start
    )
    return model, json.loads(report)


# --------------------------------------------------------------------------- design


class Design(NamedTuple):
    """A designed albedo map (arrays in the target's shape).

    ``albedo`` is the map to print; ``naive`` the per-texel inverse of the
    homogeneous reflectance (the baseline); ``predicted`` and
    ``predicted_naive`` the model's appearance of each; ``history`` the
    objective per step (stage, objective, seconds); ``stops`` why each
    channel stopped.
    """

    albedo: np.ndarray
    naive: np.ndarray
    predicted: np.ndarray
    predicted_naive: np.ndarray
    history: List[Dict[str, Any]]
    evaluations: int
    setup_seconds: float
    solve_seconds: float
    stops: List[str]


def design(
    target: Any,
    texel: float = 0.05,
    albedo_range: Tuple[float, float] = (0.2, 0.99),
    illumination: Union[str, float] = "uniform",
    method: str = "learned",
    iterations: int = 10,
    warm_start: int = 30,
    rounds: int = 1,
    smoothness: float = 0.0,
    progress: bool = False,
    model: Optional[MetaModel] = None,
) -> Design:
    """The albedo map whose appearance after sub-surface scattering matches ``target``.

    ``target`` is ``(ny, nx)`` or ``(ny, nx, 3)``, diffuse reflectance in [0, 1].
    It minimises the mean squared difference of the model's appearance and the
    target (+ ``smoothness`` · squared gradient) over albedos in
    ``albedo_range``, as ``svkernel design`` does (without the files and the
    brute-force validation). ``illumination`` is ``"uniform"``, ``"disk:R"`` or
    a disk radius in MFP.
    """
    planes, c, ny, nx = _planes("target", target)
    if np.any((planes < 0) | (planes > 1)):
        raise InvalidParameter("invalid target: reflectances must be in [0, 1]", key="target")
    if not isinstance(illumination, str):
        illumination = f"disk:{float(illumination)}"
    lo, hi = albedo_range
    out = _svkernel.design_maps(
        _flat(planes), c, ny, nx, float(texel), (float(lo), float(hi)), illumination, method,
        int(iterations), int(warm_start), int(rounds), float(smoothness), bool(progress), model,
    )
    grey = np.ndim(target) == 2

    def shaped(a: np.ndarray) -> np.ndarray:
        return a[0] if grey else np.moveaxis(a, 0, 2)

    return Design(
        shaped(out["albedo"]),
        shaped(out["naive"]),
        shaped(out["predicted"]),
        shaped(out["predicted_naive"]),
        json.loads(out["history"]),
        int(out["evaluations"]),
        float(out["setup_seconds"]),
        float(out["solve_seconds"]),
        list(out["stops"]),
    )
