"""The native module (Rust, PyO3): what horizon_bake's Python code calls."""

from typing import Any, Callable, Dict, List, Optional, Tuple

import numpy as np

CRATE_VERSION: str

Georef = Tuple[Tuple[float, float, float, float, float, float], str, int, int]

def bake_array(
    heights: np.ndarray,
    pairs: List[Tuple[str, str]],
    georef: Optional[Georef] = ...,
    normalise: bool = ...,
    precision: str = ...,
    progress: Optional[Callable[[float], Any]] = ...,
) -> Dict[str, Any]: ...
def bake_block(
    block: np.ndarray,
    interior: Tuple[int, int, int, int],
    pairs: List[Tuple[str, str]],
    stats: Tuple[float, float, bool],
    radius: int,
    georef: Optional[Georef] = ...,
) -> Tuple[Optional[np.ndarray], Optional[np.ndarray]]: ...
def resolve(
    pairs: List[Tuple[str, str]], width: int, height: int, georef: Optional[Georef] = ...
) -> Tuple[Dict[str, str], Optional[int]]: ...
def cube_map(size: int) -> np.ndarray: ...
def run_cli(args: List[str]) -> None: ...
