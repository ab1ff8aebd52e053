"""Type stubs of the native module (python/src/lib.rs); use the wrappers in ``v2ce``."""

from typing import Optional, Tuple

import numpy as np

RECORD_BYTES: int

def version() -> str: ...
def convert_path(
    source: str,
    settings: dict,
    config: Optional[str] = ...,
    size: Optional[Tuple[int, int]] = ...,
    fps: Optional[float] = ...,
    color: str = ...,
    max_frames: Optional[int] = ...,
) -> Tuple[np.ndarray, Tuple[int, int]]: ...
def convert_frames(
    frames: np.ndarray,
    times_us: np.ndarray,
    settings: dict,
    config: Optional[str] = ...,
    size: Optional[Tuple[int, int]] = ...,
    linear: bool = ...,
    max_frames: Optional[int] = ...,
) -> Tuple[np.ndarray, Tuple[int, int]]: ...
def read(path: str) -> Tuple[np.ndarray, Tuple[int, int]]: ...
def write(
    path: str,
    t: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    p: np.ndarray,
    width: int,
    height: int,
    evt: int = ...,
    compression: str = ...,
) -> None: ...

class Simulator:
    def __init__(
        self, width: int, height: int, settings: dict, config: Optional[str] = ..., linear: bool = ...
    ) -> None: ...
    @property
    def size(self) -> Tuple[int, int]: ...
    def push(self, frame: np.ndarray, t_us: int) -> np.ndarray: ...
    def finish(self) -> np.ndarray: ...

class Reader:
    def __init__(self, path: str) -> None: ...
    @property
    def size(self) -> Optional[Tuple[int, int]]: ...
    def read(self, n: int) -> np.ndarray: ...

Columns = Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]

def voxelize(
    events: Columns, frame_times_us: np.ndarray, width: int, height: int, bins: int = ...
) -> np.ndarray: ...
def sample(
    voxels: np.ndarray, frame_times_us: np.ndarray, sampler: str = ..., seed: int = ...
) -> np.ndarray: ...
def eval_stage1(
    real: Columns, sim: Columns, frame_times_us: np.ndarray, width: int, height: int
) -> str: ...
def eval_stage2(
    events: Columns,
    frame_times_us: np.ndarray,
    width: int,
    height: int,
    sampler: str = ...,
    bins: int = ...,
    seed: int = ...,
) -> str: ...
