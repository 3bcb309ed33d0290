# Type stubs of the extension module blockhash_cl._core (python/bindings.cpp). Use the package
# blockhash_cl; these are its building blocks.
from typing import Any, Dict, List, Tuple

import numpy as np
import numpy.typing as npt

__version__: str
HAVE_FLANN: bool
MAX_K: int

class Error(ValueError): ...
class OpenCLError(Error, RuntimeError): ...

def method_names() -> List[str]: ...
def method_table() -> List[Dict[str, Any]]: ...
def set_build_option(options: MethodOptions, method: str, name: str, text: str, value: int) -> None: ...
def list_devices() -> List[Dict[str, Any]]: ...
def select_device(spec: str) -> Dict[str, Any]: ...
def default_runtime() -> Runtime: ...

class Runtime:
    def __init__(self, spec: str = "") -> None: ...
    @property
    def device(self) -> Dict[str, Any]: ...
    @property
    def build_seconds(self) -> float: ...

class SearchParams:
    k: int
    max_radius: float
    A: float
    recall_target: float
    neighbour_probes: int
    local_size: int
    max_batch: int
    sort_queries: int
    def __init__(self) -> None: ...

class RadiusParams:
    budget: int
    neighbour_probes: int
    max_results: int
    sorted: bool
    local_size: int
    max_batch: int
    sort_queries: int
    count_examined: bool
    max_batch_results: int
    def __init__(self) -> None: ...

class MethodOptions:
    preset: str
    L: int
    P: int
    B: int
    X: int
    threads: int
    leaf_size: int
    seed: int
    load_index: str
    save_index: str
    def __init__(self) -> None: ...

class Index:
    @property
    def method(self) -> str: ...
    @property
    def exact(self) -> bool: ...
    @property
    def size(self) -> int: ...
    @property
    def memory_bytes(self) -> int: ...
    @property
    def build_seconds(self) -> float: ...
    @property
    def runtime(self) -> Runtime: ...
    @property
    def build_info(self) -> Dict[str, Any]: ...
    def query(
        self, queries: npt.NDArray[np.float32], params: SearchParams
    ) -> Tuple[npt.NDArray[np.float32], npt.NDArray[np.int32], npt.NDArray[np.int32], Dict[str, Any]]: ...
    def radius_search(
        self, queries: npt.NDArray[np.float32], r: float, squared: bool, params: RadiusParams
    ) -> Tuple[npt.NDArray[np.int64], npt.NDArray[np.float32], npt.NDArray[np.int32],
               npt.NDArray[np.int64], Dict[str, Any]]: ...
    def save(self, path: str) -> None: ...
    def warm_up(self, params: SearchParams) -> float: ...

def make_index(method: str, runtime: Runtime, points: npt.NDArray[np.float32],
               options: MethodOptions) -> Index: ...
