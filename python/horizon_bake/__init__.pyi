"""Type stubs of horizon_bake (see the module's docstring for what each does)."""

import os
from typing import Any, Callable, Dict, Iterable, Iterator, List, Mapping, Optional, Sequence, Tuple, Union

import numpy as np

from ._errors import (
    Canceled as Canceled,
    HorizonBakeError as HorizonBakeError,
    InputError as InputError,
    LimitError as LimitError,
    NotFound as NotFound,
    ParameterError as ParameterError,
    ServiceError as ServiceError,
)
from .client import Client as Client

__version__: str
PARAMETERS: Tuple[str, ...]
ProgressCallback = Callable[[float], Optional[bool]]
ParamValue = Union[str, int, float, bool, Sequence[str], None]

def param_text(name: str, value: Any) -> Optional[str]: ...
def param_pairs(params: Mapping[str, Any]) -> List[Tuple[str, str]]: ...
def gdal_transform(transform: Any) -> Tuple[float, ...]: ...

class BakeResult:
    width: int
    height: int
    layers: Optional[Tuple[np.ndarray, np.ndarray]]
    fourier: Optional[Dict[str, Any]]
    angles: Optional[np.ndarray]
    svf: Optional[np.ndarray]
    horizon_distance: Optional[np.ndarray]
    openness_positive: Optional[np.ndarray]
    openness_negative: Optional[np.ndarray]
    sun_hours: Optional[np.ndarray]
    insolation: Optional[np.ndarray]
    normal: Optional[np.ndarray]
    ao: Optional[np.ndarray]
    bent_normal: Optional[np.ndarray]
    params: Dict[str, str]
    resolved_radius: Optional[Dict[str, Any]]
    timings_ms: Dict[str, float]
    warnings: Sequence[str]
    holes: int
    nodata: Optional[float]
    product_nodata: Optional[float]
    transform: Optional[Tuple[float, ...]]
    crs: Any
    def cube_map(self, size: int = ...) -> np.ndarray: ...

def bake(
    heights: Any,
    *,
    dtype: str = ...,
    progress: Optional[ProgressCallback] = ...,
    transform: Any = ...,
    crs: Any = ...,
    height_scale: Optional[float] = ...,
    channel: Optional[str] = ...,
    edge: Optional[str] = ...,
    y_axis: Optional[str] = ...,
    method: Optional[str] = ...,
    radius: Union[int, str, None] = ...,
    bins: Optional[int] = ...,
    reduce: Optional[str] = ...,
    min_elevation_deg: Optional[float] = ...,
    encoding: Optional[str] = ...,
    outputs: Union[str, Sequence[str], None] = ...,
    fourier_terms: Optional[int] = ...,
    fourier_range: Optional[str] = ...,
    nodata: Union[float, str, None] = ...,
    cell_size: Optional[float] = ...,
    max_distance: Optional[float] = ...,
    earth_curvature: Union[bool, str, None] = ...,
    refraction: Optional[float] = ...,
    angle_unit: Optional[str] = ...,
    azimuth_from: Optional[str] = ...,
    svf_model: Optional[str] = ...,
    band: Union[int, str, None] = ...,
    normal_convention: Optional[str] = ...,
    bent_normal_encoding: Optional[str] = ...,
    date: Optional[str] = ...,
    date_from: Optional[str] = ...,
    date_to: Optional[str] = ...,
    time_step_minutes: Optional[int] = ...,
    latitude: Optional[float] = ...,
    longitude: Optional[float] = ...,
) -> BakeResult: ...
def terrain(
    dem: Any,
    *,
    transform: Any = ...,
    crs: Any = ...,
    nodata: Union[float, str, None] = ...,
    outputs: Union[str, Iterable[str]] = ...,
    progress: Optional[ProgressCallback] = ...,
    **params: ParamValue,
) -> BakeResult: ...
def bake_file(path: Union[str, os.PathLike], out_dir: Union[str, os.PathLike], **flags: Any) -> Dict[str, Any]: ...
def cube_map(size: int = ...) -> np.ndarray: ...
