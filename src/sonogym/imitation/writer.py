"""Write LeRobotDataset v3.0 folders episode by episode, safely.

Layout and quantisation: ``sonogym.imitation.lerobot_format``. Statistics:
``sonogym.imitation.dataset_stats``.

Safety:

* Each episode lands whole or not at all. Every file is written to ``<name>.tmp<pid>``, fsynced
  and renamed over its target (``sonogym.runs.atomic_write``); LeRobot's ``*/*.parquet`` glob
  never sees a temporary file.
* The order of an episode's commit is: data file, then ``meta/episodes`` file, ``tasks.parquet``,
  ``stats.json``, and last ``info.json``, whose ``total_episodes`` is the commit point. A writer
  killed anywhere in between leaves a folder that both readers read as the episodes before
  (rows past ``total_frames`` are ignored), and ``resume=True`` drops the uncommitted rest
  (orphan data rows and episode rows, temporary files) and continues with the next index: no
  duplicate or missing episode or frame index.
* An existing dataset folder is refused unless ``resume=True`` (append) or ``force=True``
  (delete and start over, by ``sonogym.runs.clear_output``: only a folder carrying sonogym's
  dataset marker and holding nothing but ``meta/`` and ``data/``). A new dataset folder is
  marked as one (``sonogym.runs.MARKER``).

Files: every episode gets a data file of its own (``data/chunk-XXX/file-YYY.parquet``, 1000 per
chunk folder, as LeRobot v3.0 allows), so appending never rewrites earlier data: a dataset
needs no free disk space beyond its next episode, and a full disk costs at most that episode.
Datasets whose data files hold several episodes (earlier sonogym, LeRobot) are read and
appended to the same way. ``meta/episodes`` files hold up to 1000 episodes each.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from sonogym.imitation import dataset_stats as st
from sonogym.imitation import lerobot_format as fmt
from sonogym.runs import (
    atomic_write,
    atomic_write_bytes,
    atomic_write_json,
    clear_output,
    output_entries,
    read_marker,
    remove_stale_temporaries,
    write_marker,
)

EPISODES_PER_META_FILE = 1000
DATASET = "dataset"  # the output-folder kind (``sonogym.runs.KINDS``)


def _to_numpy(x: Any) -> np.ndarray:
    if hasattr(x, "detach"):  # torch tensor, without importing torch here
        x = x.detach().cpu().numpy()
    return np.asarray(x)


def _write_parquet(path: Path, tables: list[pa.Table], schema: pa.Schema, image_cols: list[str]):
    """Atomically write ``tables`` (one row group each) to ``path``."""
    # PNG bytes do not compress: store them plain, compress the small numeric columns.
    compression = {f.name: ("none" if f.name in image_cols else "snappy") for f in schema}
    dictionary = [f.name for f in schema if f.name not in image_cols]

    def write(fh) -> None:
        writer = pq.ParquetWriter(fh, schema, compression=compression, use_dictionary=dictionary)
        for t in tables:
            writer.write_table(t.cast(schema), row_group_size=max(len(t), 1))
        writer.close()

    atomic_write(path, write)


def _tasks_table(tasks: list[str]) -> pa.Table:
    """``meta/tasks.parquet`` as pandas writes LeRobot's DataFrame (task strings as the index)."""
    pandas_meta = {
        "index_columns": ["__index_level_0__"],
        "column_indexes": [
            {
                "name": None,
                "field_name": None,
                "pandas_type": "unicode",
                "numpy_type": "object",
                "metadata": {"encoding": "UTF-8"},
            }
        ],
        "columns": [
            {
                "name": "task_index",
                "field_name": "task_index",
                "pandas_type": "int64",
                "numpy_type": "int64",
                "metadata": None,
            },
            {
                "name": None,
                "field_name": "__index_level_0__",
                "pandas_type": "unicode",
                "numpy_type": "object",
                "metadata": None,
            },
        ],
        "attributes": {},
        "creator": {"library": "pyarrow", "version": pa.__version__},
        "pandas_version": "2.2.0",
    }
    schema = pa.schema(
        [("task_index", pa.int64()), ("__index_level_0__", pa.string())],
        metadata={b"pandas": json.dumps(pandas_meta).encode()},
    )
    return pa.table(
        {"task_index": list(range(len(tasks))), "__index_level_0__": list(tasks)}, schema=schema
    )


def _write_tasks(root: Path, tasks: list[str]) -> None:
    sink = pa.BufferOutputStream()
    pq.write_table(_tasks_table(tasks), sink)
    atomic_write_bytes(Path(root) / fmt.TASKS_PATH, sink.getvalue().to_pybytes())


def read_tasks(root: Path) -> list[str]:
    """Task strings in task_index order, from a tasks.parquet written by us or by LeRobot."""
    path = Path(root) / fmt.TASKS_PATH
    if not path.exists():
        return []
    t = pq.read_table(path)
    col = "task"
    meta = (t.schema.metadata or {}).get(b"pandas")
    if meta is not None:
        idx = json.loads(meta)["index_columns"]
        if idx and isinstance(idx[0], str):
            col = idx[0]
    if col not in t.column_names:
        raise fmt.DatasetFormatError(f"{path}: no task column (looked for {col!r})")
    order = np.argsort(np.asarray(t.column("task_index").to_pylist()))
    names = t.column(col).to_pylist()
    return [names[i] for i in order]


def _episodes_schema(features: dict[str, dict[str, Any]]) -> pa.Schema:
    fields = [
        ("episode_index", pa.int64()),
        ("tasks", pa.list_(pa.string())),
        ("length", pa.int64()),
        ("data/chunk_index", pa.int64()),
        ("data/file_index", pa.int64()),
        ("dataset_from_index", pa.int64()),
        ("dataset_to_index", pa.int64()),
    ]
    for key, ft in features.items():
        val = (
            pa.list_(pa.list_(pa.list_(pa.float64())))
            if fmt.is_image(ft)
            else pa.list_(pa.float64())
        )
        ival = pa.list_(pa.int64())
        for name in st.STAT_KEYS:
            if name == "count":
                fields.append((f"stats/{key}/count", ival))
            elif name in ("min", "max") and ft["dtype"].startswith("int"):
                fields.append((f"stats/{key}/{name}", ival))
            else:
                fields.append((f"stats/{key}/{name}", val))
    fields += [("meta/episodes/chunk_index", pa.int64()), ("meta/episodes/file_index", pa.int64())]
    return pa.schema(fields)


class DatasetWriter:
    """Append episodes to a LeRobotDataset v3.0 folder (see the module doc for the guarantees).

    Args:
        root: dataset folder (created; see ``resume``/``force`` for an existing one).
        fps: frame rate (frames per second, integer as LeRobot stores it); timestamps are
            ``frame_index / fps`` seconds.
        features: ``{key: {"dtype", "shape", "names"}}`` in LeRobot's info.json form, without
            the five bookkeeping features (the writer adds them). Images: dtype "image", shape
            (H, W, C), C 1 or 3.
        task: default task string of the episodes (LeRobot's natural-language task).
        robot_type: info.json ``robot_type`` (free text, e.g. "kuka-med14").
        resume: continue an existing dataset (its fps and features must match).
        force: delete an existing dataset folder first.
        chunks_size: files per chunk folder (LeRobot: 1000).
        png_compress_level: zlib level 0-9 of the PNG frames (1: fast, LeRobot's choice).
    """

    def __init__(
        self,
        root: str | Path,
        fps: int,
        features: dict[str, dict[str, Any]],
        task: str = "",
        robot_type: str | None = None,
        *,
        resume: bool = False,
        force: bool = False,
        chunks_size: int = fmt.DEFAULT_CHUNKS_SIZE,
        png_compress_level: int = 1,
    ) -> None:
        if resume and force:
            raise ValueError("resume=True and force=True exclude each other: append or replace")
        if not 0 <= png_compress_level <= 9:
            raise ValueError(f"png_compress_level must be in 0..9, got {png_compress_level}")
        self.root = Path(root)
        self.task = task
        self.png_compress_level = int(png_compress_level)
        self._broken: str | None = None
        # info.json's file size limit is LeRobot's default, for LeRobot's writer appending
        fresh = fmt.new_info(fps, features, robot_type, chunks_size)
        info_path = self.root / fmt.INFO_PATH
        marked = (read_marker(self.root) or {}).get("kind") == DATASET
        if output_entries(self.root) and not info_path.exists() and not marked:
            raise FileExistsError(
                f"{self.root} exists, is not empty and holds no {fmt.INFO_PATH}: not a dataset "
                "folder; refusing to write into it or delete it. Choose another folder."
            )
        # a folder marked as a dataset without info.json has nothing committed: a new one
        exists = info_path.exists()
        if exists and force:
            clear_output(self.root, DATASET)
            exists = False
        if exists and not resume:
            n = fmt.read_info(self.root).get("total_episodes")
            raise FileExistsError(
                f"{self.root} already holds a dataset ({n} episodes); pass resume=True "
                "(--resume) to append to it or force=True (--force) to replace it"
            )
        self.features = fresh["features"]
        self._image_cols = [k for k, ft in self.features.items() if fmt.is_image(ft)]
        self._user_keys = [k for k in self.features if k not in fmt.DEFAULT_FEATURES]
        self._schema = fmt.data_schema(self.features)
        self._ep_schema = _episodes_schema(self.features)
        if exists:
            self._recover(fresh, robot_type)
        else:
            self.info = fresh
            self.tasks: list[str] = []
            self._meta_rows: list[dict[str, Any]] = []  # rows of the current episodes file
            self._meta_file_no = 0
            self._next_data_file = 0  # number of the next episode's data file
            self._agg = st.StatsAggregator()
            self.root.mkdir(parents=True, exist_ok=True)
            if not marked:
                write_marker(self.root, DATASET)
            atomic_write_json(self.root / fmt.INFO_PATH, self.info, indent=4)

    # --- public -----------------------------------------------------------------------------

    def set_info(self, key: str, value: Any) -> None:
        """Add a field of sonogym's own, named ``sonogym_*`` so as never to take one of
        LeRobot's (its readers ignore unknown fields), to info.json: written now and kept with
        every commit."""
        if not key.startswith("sonogym_"):
            raise ValueError(f"info.json fields of sonogym's own are named sonogym_*, not {key!r}")
        self.info[key] = value
        self._write_info(self.info)

    @property
    def num_episodes(self) -> int:
        return int(self.info["total_episodes"])

    @property
    def num_frames(self) -> int:
        return int(self.info["total_frames"])

    def add_episode(self, frames: Mapping[str, Any], task: str | None = None) -> int:
        """Write one episode and return its episode index.

        ``frames[key]`` holds the episode's T frames of each user feature: images (T, H, W, C)
        or (T, C, H, W) (or (T, H, W) for C = 1), uint8 or float in [0, 1]; numeric features
        (T, D) (or (T,) for D = 1). numpy arrays or torch tensors.
        """
        if self._broken is not None:
            raise RuntimeError(
                f"this writer failed earlier ({self._broken}); open the folder again with "
                "resume=True to continue from the last whole episode"
            )
        task = self.task if task is None else task
        columns = self._check_frames(frames)
        t = len(next(iter(columns.values())))
        ep = self.num_episodes
        if task not in self.tasks:
            new_tasks = [*self.tasks, task]
        else:
            new_tasks = self.tasks
        columns["timestamp"] = (np.arange(t) / self.info["fps"]).astype(np.float32)
        columns["frame_index"] = np.arange(t, dtype=np.int64)
        columns["episode_index"] = np.full(t, ep, dtype=np.int64)
        columns["index"] = np.arange(self.num_frames, self.num_frames + t, dtype=np.int64)
        columns["task_index"] = np.full(t, new_tasks.index(task), dtype=np.int64)
        stats = st.episode_stats(columns, self.features)
        table = self._episode_table(columns)
        try:
            chunk, file = self._write_data(table)
            self._commit_metadata(ep, t, task, new_tasks, stats, chunk, file)
        except BaseException as e:  # a kill-like failure: the folder is consistent, we are not
            self._broken = repr(e)
            raise
        return ep

    def close(self) -> None:
        """Nothing is buffered: every episode is on disk when ``add_episode`` returns."""

    def __enter__(self) -> DatasetWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # --- frames -> table --------------------------------------------------------------------

    def _check_frames(self, frames: Mapping[str, Any]) -> dict[str, np.ndarray]:
        missing = set(self._user_keys) - set(frames)
        extra = set(frames) - set(self._user_keys)
        if missing or extra:
            raise fmt.DatasetFormatError(
                f"episode keys differ from the features: missing {sorted(missing)}, "
                f"extra {sorted(extra)}"
            )
        out: dict[str, np.ndarray] = {}
        lengths = {}
        for key in self._user_keys:
            ft = self.features[key]
            x = _to_numpy(frames[key])
            if fmt.is_image(ft):
                x = fmt.to_hwc(fmt.quantize(x, key), ft["shape"], key)
            else:
                d = ft["shape"][0]
                if x.ndim == 1 and d == 1:
                    x = x[:, None]
                if x.ndim != 2 or x.shape[1] != d:
                    raise fmt.DatasetFormatError(
                        f"{key}: expected (T, {d}) values, got shape {tuple(x.shape)}"
                    )
                if np.issubdtype(x.dtype, np.floating) and not np.isfinite(x).all():
                    raise fmt.DatasetFormatError(f"{key}: NaN or inf in the episode's values")
                x = x.astype(ft["dtype"])
            out[key] = x
            lengths[key] = len(x)
        if len(set(lengths.values())) != 1 or min(lengths.values()) < 1:
            raise fmt.DatasetFormatError(
                f"episode features differ in length or are empty: {lengths}"
            )
        return out

    def _episode_table(self, columns: dict[str, np.ndarray]) -> pa.Table:
        arrays = []
        for key, ft in self.features.items():
            x = columns[key]
            typ = fmt.arrow_type(ft)
            if fmt.is_image(ft):
                pngs = [fmt.encode_png(f, self.png_compress_level) for f in x]
                arrays.append(
                    pa.StructArray.from_arrays(
                        [pa.array(pngs, pa.binary()), pa.nulls(len(pngs), pa.string())],
                        names=["bytes", "path"],
                    )
                )
            elif ft["shape"] == [1]:
                arrays.append(pa.array(x.reshape(-1), typ))
            else:
                flat = pa.array(np.ascontiguousarray(x).reshape(-1), typ.value_type)
                arrays.append(pa.FixedSizeListArray.from_arrays(flat, ft["shape"][0]))
        return pa.Table.from_arrays(arrays, schema=self._schema)

    # --- commit steps (separate so tests can simulate a kill between them) -------------------

    def _write_data(self, table: pa.Table) -> tuple[int, int]:
        """Write the episode's rows to a new data file of its own; its (chunk, file)."""
        chunk, file = fmt.chunk_file(self._next_data_file, self.info["chunks_size"])
        _write_parquet(fmt.data_file(self.root, chunk, file), [table], self._schema,
                       self._image_cols)  # fmt: skip
        self._next_data_file += 1
        return chunk, file

    def _commit_metadata(self, ep, length, task, new_tasks, stats, chunk, file) -> None:
        cs = self.info["chunks_size"]
        if len(self._meta_rows) >= EPISODES_PER_META_FILE:
            self._meta_file_no += 1
            self._meta_rows = []
        mchunk, mfile = fmt.chunk_file(self._meta_file_no, cs)
        row = {
            "episode_index": ep,
            "tasks": [task],
            "length": length,
            "data/chunk_index": chunk,
            "data/file_index": file,
            "dataset_from_index": self.num_frames,
            "dataset_to_index": self.num_frames + length,
            **st.flatten_episode_stats(stats),
            "meta/episodes/chunk_index": mchunk,
            "meta/episodes/file_index": mfile,
        }
        rows = [*self._meta_rows, row]
        _write_parquet(
            fmt.episodes_file(self.root, mchunk, mfile),
            [pa.Table.from_pylist(rows, schema=self._ep_schema)],
            self._ep_schema,
            [],
        )
        if new_tasks is not self.tasks:
            _write_tasks(self.root, new_tasks)
        agg = st.StatsAggregator()
        agg._acc = {k: dict(v) for k, v in self._agg._acc.items()}  # commit only on success
        agg.add(stats)
        atomic_write_json(self.root / fmt.STATS_PATH, st.to_json(agg.result()), indent=4)
        info = dict(self.info)
        info["total_episodes"] = ep + 1
        info["total_frames"] = self.num_frames + length
        info["total_tasks"] = len(new_tasks)
        info["splits"] = {"train": f"0:{ep + 1}"}
        self._write_info(info)
        # committed: update the in-memory state
        self.info, self.tasks, self._agg, self._meta_rows = info, list(new_tasks), agg, rows

    def _write_info(self, info: dict[str, Any]) -> None:
        atomic_write_json(self.root / fmt.INFO_PATH, info, indent=4)

    # --- resume -----------------------------------------------------------------------------

    def _recover(self, fresh: dict[str, Any], robot_type: str | None) -> None:
        """Load an existing dataset and drop whatever its last writer left uncommitted."""
        info = fmt.read_info(self.root)
        if info["fps"] != fresh["fps"]:
            raise ValueError(f"{self.root}: recorded at {info['fps']} fps, not {fresh['fps']}")
        old = {k: {**v, "shape": list(v["shape"])} for k, v in info["features"].items()}
        if old != fresh["features"]:
            raise ValueError(
                f"{self.root}: features differ from the existing dataset's; cannot resume.\n"
                f"existing: {old}\nnew: {fresh['features']}"
            )
        if robot_type is not None and info.get("robot_type") != robot_type:
            raise ValueError(
                f"{self.root}: robot_type {info.get('robot_type')!r}, not {robot_type!r}"
            )
        n, total = int(info["total_episodes"]), int(info["total_frames"])
        remove_stale_temporaries(self.root, recursive=True)
        # meta/episodes: keep rows < n, rewrite files holding later rows
        rows: list[dict[str, Any]] = []
        for path in sorted((self.root / fmt.EPISODES_DIR).glob("*/*.parquet")):
            t = pq.read_table(path)
            keep = [r for r in t.to_pylist() if r["episode_index"] < n]
            if len(keep) < t.num_rows:
                if keep:
                    _write_parquet(
                        path,
                        [pa.Table.from_pylist(keep, schema=self._ep_schema)],
                        self._ep_schema,
                        [],
                    )
                else:
                    path.unlink()
            rows += keep
        rows.sort(key=lambda r: r["episode_index"])
        if [r["episode_index"] for r in rows] != list(range(n)):
            raise fmt.DatasetFormatError(
                f"{self.root}: meta/episodes does not hold episodes 0..{n - 1}; cannot resume"
            )
        # data: drop rows of uncommitted episodes
        seen = 0
        for path in sorted((self.root / fmt.DATA_DIR).glob("*/*.parquet")):
            pf = pq.ParquetFile(path)
            groups = [
                pf.read_row_group(i, columns=["episode_index"]) for i in range(pf.num_row_groups)
            ]
            keep = [i for i, g in enumerate(groups) if g.num_rows and g.column(0)[0].as_py() < n]
            if len(keep) < pf.num_row_groups:
                if keep:
                    tables = [pf.read_row_group(i) for i in keep]
                    _write_parquet(path, tables, self._schema, self._image_cols)
                else:
                    path.unlink()
            seen += sum(groups[i].num_rows for i in keep)
        if seen != total or (rows and rows[-1]["dataset_to_index"] != total):
            raise fmt.DatasetFormatError(
                f"{self.root}: data holds {seen} committed frames, info.json says {total}; "
                "cannot resume"
            )
        self.info = info
        self.tasks = read_tasks(self.root)[: int(info["total_tasks"])]
        if len(self.tasks) < int(info["total_tasks"]):
            raise fmt.DatasetFormatError(f"{self.root}: tasks.parquet lacks tasks; cannot resume")
        if self.tasks:  # drop tasks an uncommitted episode added
            _write_tasks(self.root, self.tasks)
        self._agg = st.StatsAggregator()
        for r in rows:
            self._agg.add(st.unflatten_episode_stats(r))
        cs = info["chunks_size"]
        if rows:
            last = rows[-1]
            # the next episode starts a new file, also after a file that holds several
            self._next_data_file = last["data/chunk_index"] * cs + last["data/file_index"] + 1
            self._meta_file_no = (
                last["meta/episodes/chunk_index"] * cs + last["meta/episodes/file_index"]
            )
            self._meta_rows = [
                r
                for r in rows
                if r["meta/episodes/chunk_index"] * cs + r["meta/episodes/file_index"]
                == self._meta_file_no
            ]
            atomic_write_json(self.root / fmt.STATS_PATH, st.to_json(self._agg.result()), indent=4)
        else:
            self._next_data_file = self._meta_file_no = 0
            self._meta_rows = []
