"""Type stubs of the native module (called through ``svkernel``; arrays are
flat, contiguous float64, already checked by the Python half)."""

from os import PathLike
from typing import Any, Dict, List, Optional, Tuple, Union

import numpy as np
import numpy.typing as npt

_F = npt.NDArray[np.float64]

DEFAULT_MAX_EVENTS: int

class MetaModel:
    """A kernel meta-model: the default one, one read from a file, or one fitted by ``fit_kernels``."""

    @staticmethod
    def default() -> MetaModel:
        """The meta-model in use by default (``SVKERNEL_MODEL`` if set, else the built-in one)."""
    @staticmethod
    def load(path: Union[str, PathLike[str]]) -> MetaModel:
        """Reads a meta-model file."""
    @staticmethod
    def from_json(text: str, origin: str = "<json>") -> MetaModel:
        """Parses a meta-model document from its JSON text."""
    def to_json(self) -> str:
        """The document as JSON text."""
    def save(self, path: Union[str, PathLike[str]]) -> None:
        """Writes the document to ``path`` (atomically)."""
    @property
    def origin(self) -> str:
        """Where the model came from."""
    @property
    def components(self) -> int:
        """Components K of the all-vertex kernel."""

class _SvBssrdf:
    def __init__(
        self,
        albedo: _F,
        channels: int,
        ny: int,
        nx: int,
        texel: float,
        method: str,
        incidence: str,
        density_constant: float,
        density_map: Optional[_F] = None,
        meta: Optional[MetaModel] = None,
    ) -> None: ...
    @property
    def channels(self) -> int: ...
    def eval(self, xi: _F, xe: _F) -> _F: ...
    def sample(self, xe: _F, u: _F) -> Tuple[_F, _F]: ...

def kernel(
    d: _F, albedo: _F, density: _F, vertices: str, manual: bool, meta: Optional[MetaModel] = None
) -> Tuple[_F, _F, _F, npt.NDArray[np.bool_]]: ...
def profile(albedo: _F, radii: _F, incidence: str) -> Dict[str, _F]: ...
def render(
    text: Optional[str],
    origin: str,
    methods: Optional[List[str]],
    spp: Optional[int],
    reference_paths: Optional[int],
    seed: int,
    progress: bool,
    meta: Optional[MetaModel] = None,
    allocation: Optional[str] = None,
) -> List[Dict[str, Any]]: ...
def simulate_profile(
    albedo: float,
    g: float,
    eta: float,
    density: float,
    source: str,
    paths: int,
    seed: int,
    max_events: int,
    thickness: Optional[float],
    progress: bool,
) -> str: ...
def simulate_kernels(
    albedos: List[float], distances: List[float], g: float, eta: float, paths: int, seed: int, progress: bool
) -> str: ...
def fit_kernels(
    tally: str, components: int, degrees: Tuple[int, int], progress: bool, start: Optional[MetaModel] = ...
) -> Tuple[MetaModel, str]: ...
def design_maps(
    target: _F,
    channels: int,
    ny: int,
    nx: int,
    texel: float,
    albedo_range: Tuple[float, float],
    illumination: str,
    method: str,
    iterations: int,
    warm_start: int,
    rounds: int,
    smoothness: float,
    progress: bool,
    meta: Optional[MetaModel] = None,
) -> Dict[str, Any]: ...
def info() -> Dict[str, str]: ...
