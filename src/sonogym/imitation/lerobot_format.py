"""LeRobotDataset v3.0 on disk: paths, ``info.json``, feature specs, PNG frames, parquet schemas.

The layout (what LeRobot 0.4's ``LeRobotDataset`` reads, codebase version "v3.0")::

    root/
      meta/info.json                          codebase_version, fps, features, totals, paths
      meta/stats.json                         per-feature min/max/mean/std/count/q01..q99
      meta/tasks.parquet                      task string (pandas index) -> task_index
      meta/episodes/chunk-000/file-000.parquet  one row per episode (indices, length, stats/...)
      data/chunk-000/file-000.parquet         one row per frame, one row group per episode

File ``(chunk c, file f)`` is ``chunk-{c:03d}/file-{f:03d}``; a chunk folder holds at most
``chunks_size`` files. Rows are sorted by the global frame ``index`` across files in path order
(LeRobot concatenates the files in sorted path order and indexes rows by position).

Features follow LeRobot's ``info.json`` form ``{key: {"dtype", "shape", "names"}}``:
image features have dtype ``"image"``, shape ``(H, W, C)`` with ``C`` 1 (grey) or 3 (RGB) and
names ``["height", "width", "channels"]``; they are stored in parquet as HF ``datasets.Image``
structs ``{bytes: PNG, path: null}`` (8-bit PNG, grey mode "L" or "RGB"). Numeric features are
1-D (``shape (D,)``) float32/float64/int32/int64; shape ``(1,)`` is stored as a scalar column
(as LeRobot does), longer ones as fixed-size lists.

Quantisation: float frames in [0, 1] become ``uint8 = rint(x * 255)`` (round half to even);
a reader returns ``uint8 / 255`` as float32, so a round trip returns exactly the quantised
frame. Values outside [0, 1] or NaN are refused, not clipped.
"""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

#: The one LeRobotDataset codebase version written and read here.
CODEBASE_VERSION = "v3.0"
INFO_PATH = "meta/info.json"
STATS_PATH = "meta/stats.json"
TASKS_PATH = "meta/tasks.parquet"
EPISODES_DIR = "meta/episodes"
DATA_DIR = "data"
CHUNK_FILE = "chunk-{chunk_index:03d}/file-{file_index:03d}"
DATA_PATH = DATA_DIR + "/" + CHUNK_FILE + ".parquet"
EPISODES_PATH = EPISODES_DIR + "/" + CHUNK_FILE + ".parquet"
#: LeRobot's defaults: at most 1000 files per chunk folder, data files of about 100 MB.
DEFAULT_CHUNKS_SIZE = 1000
DEFAULT_DATA_FILES_SIZE_IN_MB = 100
DEFAULT_VIDEO_FILES_SIZE_IN_MB = 200  # written for completeness; no videos here
#: Suffix of files being written; never matched by LeRobot's ``*/*.parquet`` glob.

#: The bookkeeping columns every frame has (LeRobot's DEFAULT_FEATURES).
DEFAULT_FEATURES: dict[str, dict[str, Any]] = {
    "timestamp": {"dtype": "float32", "shape": [1], "names": None},
    "frame_index": {"dtype": "int64", "shape": [1], "names": None},
    "episode_index": {"dtype": "int64", "shape": [1], "names": None},
    "index": {"dtype": "int64", "shape": [1], "names": None},
    "task_index": {"dtype": "int64", "shape": [1], "names": None},
}
IMAGE_NAMES = ["height", "width", "channels"]
NUMERIC_DTYPES = ("float32", "float64", "int32", "int64")
#: Quantiles written to stats.json (LeRobot 0.4's DEFAULT_QUANTILES and key names).
QUANTILES = (0.01, 0.10, 0.50, 0.90, 0.99)
QUANTILE_KEYS = tuple(f"q{round(q * 100):02d}" for q in QUANTILES)


class DatasetFormatError(ValueError):
    """A dataset folder, feature spec or frame that does not fit LeRobotDataset v3.0."""


class DatasetVersionError(DatasetFormatError):
    """A dataset whose ``codebase_version`` is not v3.0."""


def chunk_file(i: int, chunks_size: int) -> tuple[int, int]:
    """(chunk index, file index) of the ``i``-th file (0-based) for ``chunks_size`` per chunk."""
    return i // chunks_size, i % chunks_size


def data_file(root: Path, chunk: int, file: int) -> Path:
    return Path(root) / DATA_PATH.format(chunk_index=chunk, file_index=file)


def episodes_file(root: Path, chunk: int, file: int) -> Path:
    return Path(root) / EPISODES_PATH.format(chunk_index=chunk, file_index=file)


# --- features -------------------------------------------------------------------------------


def is_image(ft: dict[str, Any]) -> bool:
    return ft["dtype"] == "image"


def validate_features(features: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """User features in LeRobot's form, checked and normalised (shapes as lists).

    Raises DatasetFormatError naming the feature for: a "/" in a key (LeRobot flattens stats
    keys with "/"), a reserved key, video features, image shapes other than (H, W, 1|3),
    non-1-D numeric shapes, unsupported dtypes, or a names list of the wrong length.
    """
    out: dict[str, dict[str, Any]] = {}
    if not features:
        raise DatasetFormatError("features is empty: give at least an action feature")
    for key, ft in features.items():
        if "/" in key:
            raise DatasetFormatError(f"feature key {key!r} contains '/'; LeRobot forbids it")
        if key in DEFAULT_FEATURES:
            raise DatasetFormatError(f"feature key {key!r} is reserved (written by the writer)")
        dtype, shape = ft.get("dtype"), [int(s) for s in ft.get("shape", ())]
        names = ft.get("names")
        if dtype == "video":
            raise DatasetFormatError(
                f"feature {key!r}: video features are not supported; use dtype 'image' "
                "(PNG frames embedded in parquet)"
            )
        if dtype == "image":
            if len(shape) != 3 or shape[2] not in (1, 3) or min(shape) < 1:
                raise DatasetFormatError(
                    f"feature {key!r}: image shape must be (H, W, C) with C 1 or 3, got {shape}"
                )
            if names is not None and list(names) != IMAGE_NAMES:
                raise DatasetFormatError(
                    f"feature {key!r}: image names must be {IMAGE_NAMES} (LeRobot reads the "
                    f"channel axis from them), got {names}"
                )
            names = list(IMAGE_NAMES)
        elif dtype in NUMERIC_DTYPES:
            if len(shape) != 1 or shape[0] < 1:
                raise DatasetFormatError(
                    f"feature {key!r}: numeric features must be 1-D (D,), got shape {shape}"
                )
            if names is not None and len(names) != shape[0]:
                raise DatasetFormatError(f"feature {key!r}: {len(names)} names for shape {shape}")
        else:
            raise DatasetFormatError(
                f"feature {key!r}: dtype {dtype!r} not supported; use 'image' or one of "
                f"{NUMERIC_DTYPES}"
            )
        out[key] = {"dtype": dtype, "shape": shape, "names": None if names is None else list(names)}
    return out


def all_features(features: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """User features followed by the five bookkeeping features (LeRobot's order)."""
    return {**validate_features(features), **{k: dict(v) for k, v in DEFAULT_FEATURES.items()}}


def arrow_type(ft: dict[str, Any]) -> pa.DataType:
    """The parquet column type LeRobot (via HF datasets) expects for a feature."""
    if is_image(ft):
        return pa.struct([("bytes", pa.binary()), ("path", pa.string())])
    value = pa.from_numpy_dtype(np.dtype(ft["dtype"]))
    if list(ft["shape"]) == [1]:
        return value
    return pa.list_(value, int(ft["shape"][0]))


def data_schema(features: dict[str, dict[str, Any]]) -> pa.Schema:
    """Schema of the data files, with the HF ``datasets`` feature metadata LeRobot writes."""
    hf: dict[str, Any] = {}
    fields = []
    for key, ft in features.items():
        fields.append(pa.field(key, arrow_type(ft)))
        if is_image(ft):
            hf[key] = {"_type": "Image"}
        elif list(ft["shape"]) == [1]:
            hf[key] = {"dtype": ft["dtype"], "_type": "Value"}
        else:
            hf[key] = {
                "feature": {"dtype": ft["dtype"], "_type": "Value"},
                "length": int(ft["shape"][0]),
                "_type": "List",
            }
    meta = {b"huggingface": json.dumps({"info": {"features": hf}}).encode()}
    return pa.schema(fields, metadata=meta)


# --- info.json --------------------------------------------------------------------------------


def new_info(
    fps: int,
    features: dict[str, dict[str, Any]],
    robot_type: str | None,
    chunks_size: int,
    data_files_size_in_mb: int = DEFAULT_DATA_FILES_SIZE_IN_MB,
) -> dict[str, Any]:
    """``info.json`` of an empty dataset (LeRobot 0.4's key set and order)."""
    if int(fps) != fps or fps <= 0:
        raise DatasetFormatError(
            f"fps must be a positive integer (LeRobot stores an int), got {fps}"
        )
    return {
        "codebase_version": CODEBASE_VERSION,
        "robot_type": robot_type,
        "total_episodes": 0,
        "total_frames": 0,
        "total_tasks": 0,
        "chunks_size": int(chunks_size),
        "data_files_size_in_mb": int(data_files_size_in_mb),
        "video_files_size_in_mb": DEFAULT_VIDEO_FILES_SIZE_IN_MB,
        "fps": int(fps),
        "splits": {},
        "data_path": DATA_PATH,
        "video_path": None,
        "features": all_features(features),
    }


def check_version(info: dict[str, Any], where: Path | str) -> None:
    """Refuse any dataset that is not LeRobotDataset v3.0, saying how to get one."""
    version = info.get("codebase_version")
    if version != CODEBASE_VERSION:
        raise DatasetVersionError(
            f"{where}: codebase_version {version!r}, but sonogym reads and writes LeRobotDataset "
            f"{CODEBASE_VERSION} only. Convert older datasets with LeRobot's "
            "`lerobot.datasets.v30.convert_dataset_v21_to_v30`, or record the data again."
        )


def read_info(root: str | Path) -> dict[str, Any]:
    """``meta/info.json`` of the dataset at ``root``, version-checked (v3.0 only).

    Raises FileNotFoundError (naming the path) when there is no dataset, DatasetVersionError
    for another codebase version.
    """
    path = Path(root) / INFO_PATH
    if not path.exists():
        raise FileNotFoundError(f"{path} not found: is {root} a LeRobotDataset folder?")
    info = json.loads(path.read_text())
    check_version(info, root)
    if info.get("video_path") is not None or any(
        ft["dtype"] == "video" for ft in info["features"].values()
    ):
        raise DatasetFormatError(
            f"{root}: video features are not supported by this reader (images only)"
        )
    return info


# --- frames ---------------------------------------------------------------------------------


def quantize(images: np.ndarray, key: str = "image") -> np.ndarray:
    """uint8 frames: uint8 input unchanged; float input in [0, 1] -> ``rint(x * 255)``."""
    if images.dtype == np.uint8:
        return images
    if not np.issubdtype(images.dtype, np.floating):
        raise DatasetFormatError(
            f"{key}: images must be uint8 or float in [0, 1], got {images.dtype}"
        )
    x = images.astype(np.float32, copy=False)
    if not np.isfinite(x).all():
        raise DatasetFormatError(f"{key}: NaN or inf in the float images; they must lie in [0, 1]")
    if x.min(initial=0.0) < 0.0 or x.max(initial=0.0) > 1.0:
        raise DatasetFormatError(
            f"{key}: float images must lie in [0, 1] (range [{x.min():.4g}, {x.max():.4g}]); "
            "clip them before writing"
        )
    return np.rint(x * 255.0).astype(np.uint8)


def to_hwc(images: np.ndarray, shape: list[int], key: str) -> np.ndarray:
    """(T, H, W, C) view of an episode's frames given as (T, H, W, C), (T, C, H, W) or, for
    one channel, (T, H, W)."""
    h, w, c = shape
    if images.ndim == 4 and tuple(images.shape[1:]) == (h, w, c):
        return images
    if images.ndim == 4 and tuple(images.shape[1:]) == (c, h, w):
        return images.transpose(0, 2, 3, 1)
    if c == 1 and images.ndim == 3 and tuple(images.shape[1:]) == (h, w):
        return images[..., None]
    raise DatasetFormatError(
        f"{key}: frames of shape {tuple(images.shape)} do not match the feature shape "
        f"(H, W, C) = {tuple(shape)}; give (T, H, W, C) or (T, C, H, W)"
    )


def encode_png(frame_hwc: np.ndarray, compress_level: int) -> bytes:
    """8-bit PNG of one (H, W, C) uint8 frame (grey "L" for C = 1, "RGB" for C = 3)."""
    from PIL import Image

    img = Image.fromarray(frame_hwc[..., 0] if frame_hwc.shape[2] == 1 else frame_hwc)
    buf = io.BytesIO()
    img.save(buf, format="PNG", compress_level=compress_level)
    return buf.getvalue()


def decode_png(data: bytes) -> np.ndarray:
    """(H, W, C) uint8 array of a PNG (C = 1 for grey, 3 for RGB; RGBA/palette to RGB)."""
    from PIL import Image

    img = Image.open(io.BytesIO(data))
    if img.mode not in ("L", "RGB"):
        img = img.convert("RGB")
    arr = np.asarray(img)
    return arr[..., None] if arr.ndim == 2 else arr
