import os
from typing import Any, Union

from . import BakeResult

def terrain(src: Union[str, os.PathLike, Any], *, band: int = ..., **params: Any) -> BakeResult: ...
def write(result: BakeResult, path: Union[str, os.PathLike], product: str = ...) -> None: ...
