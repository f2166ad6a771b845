"""LeRobotDataset v3.0 writer and reader: round trip, metadata, stats, safety, deltas."""

from __future__ import annotations

import json

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch
from il_datasets import FEATURES, FPS, random_episodes, set_value, write

from sonogym.imitation import lerobot_format as fmt
from sonogym.imitation.reader import LeRobotFrames, load_stats, read_episodes
from sonogym.imitation.writer import DatasetWriter, read_tasks

IMG = "observation.images.us"
RGB = "observation.images.rgb"


def quantised_hwc(ep, key):
    """What the dataset must hold for ``ep[key]``: uint8 (T, H, W, C)."""
    x = ep[key]
    if x.dtype != np.uint8:
        x = np.rint(x * 255).astype(np.uint8)
    return x.transpose(0, 2, 3, 1) if key == IMG else x


def test_round_trip_equals_quantised_frames_and_values(tmp_path):
    eps = random_episodes(3)
    write(tmp_path / "ds", eps)
    ds = LeRobotFrames(tmp_path / "ds")
    assert len(ds) == sum(len(e["action"]) for e in eps) == ds.num_frames
    i = 0
    for e, ep in enumerate(eps):
        for t in range(len(ep["action"])):
            item = ds[i]
            for key in (IMG, RGB):
                want = torch.from_numpy(quantised_hwc(ep, key)[t].transpose(2, 0, 1)).float() / 255
                assert item[key].dtype == torch.float32
                assert torch.equal(item[key], want), (key, e, t)
            assert torch.equal(
                item["observation.state"], torch.from_numpy(ep["observation.state"][t])
            )
            assert torch.equal(item["action"], torch.from_numpy(ep["action"][t]))
            assert int(item["index"]) == i and int(item["episode_index"]) == e
            assert int(item["frame_index"]) == t and int(item["task_index"]) == 0
            assert float(item["timestamp"]) == pytest.approx(t / FPS)
            i += 1


def test_quantisation_is_rint_of_x_times_255_and_refuses_out_of_range():
    x = np.array([0.0, 0.5 / 255, 1.5 / 255, 0.2, 1.0], np.float32)
    assert fmt.quantize(x).tolist() == np.rint(x * 255).astype(np.uint8).tolist()
    assert fmt.quantize(x)[1] == 0 and fmt.quantize(x)[2] == 2  # round half to even
    u = np.array([3, 250], np.uint8)
    assert fmt.quantize(u) is u
    for bad in ([1.0001], [-0.01], [np.nan]):
        with pytest.raises(fmt.DatasetFormatError, match=r"\[0, 1\]"):
            fmt.quantize(np.array(bad, np.float32))


def test_info_json_tasks_and_episode_metadata(tmp_path):
    eps = random_episodes(3)
    root = tmp_path / "ds"
    w = DatasetWriter(root, FPS, FEATURES, task="navigate", robot_type="kuka-med14")
    w.add_episode(eps[0])
    w.add_episode(eps[1], task="other")
    w.add_episode(eps[2])
    info = json.loads((root / fmt.INFO_PATH).read_text())
    lengths = [len(e["action"]) for e in eps]
    assert info["codebase_version"] == "v3.0" and info["fps"] == FPS
    assert info["robot_type"] == "kuka-med14"
    assert (info["total_episodes"], info["total_frames"], info["total_tasks"]) == (
        3,
        sum(lengths),
        2,
    )
    assert info["splits"] == {"train": "0:3"}
    assert info["data_path"] == "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
    assert info["video_path"] is None and info["chunks_size"] == 1000
    assert info["data_files_size_in_mb"] == 100
    assert list(info["features"]) == [*FEATURES, *fmt.DEFAULT_FEATURES]
    assert info["features"][IMG] == {
        "dtype": "image",
        "shape": [12, 9, 1],
        "names": ["height", "width", "channels"],
    }
    assert info["features"]["action"]["names"] == ["dx", "dz", "dyaw"]
    assert info["features"]["index"] == {"dtype": "int64", "shape": [1], "names": None}
    assert read_tasks(root) == ["navigate", "other"]
    rows = read_episodes(root)
    assert [r["length"] for r in rows] == lengths
    assert [r["tasks"] for r in rows] == [["navigate"], ["other"], ["navigate"]]
    bounds = np.cumsum([0, *lengths])
    assert [(r["dataset_from_index"], r["dataset_to_index"]) for r in rows] == list(
        zip(bounds[:-1].tolist(), bounds[1:].tolist(), strict=True)
    )
    # each row points at the data file holding its frames: a file of its own per episode
    assert [(r["data/chunk_index"], r["data/file_index"]) for r in rows] == [(0, 0), (0, 1), (0, 2)]
    for r in rows:
        path = fmt.data_file(root, r["data/chunk_index"], r["data/file_index"])
        t = pq.read_table(path, columns=["episode_index", "index", "task_index"]).to_pydict()
        mine = [i for i, e in enumerate(t["episode_index"]) if e == r["episode_index"]]
        assert [t["index"][i] for i in mine] == list(
            range(r["dataset_from_index"], r["dataset_to_index"])
        )
    assert pq.ParquetFile(fmt.data_file(root, 0, 0)).num_row_groups == 1
    schema = pq.read_schema(fmt.data_file(root, 0, 0))
    assert str(schema.field(IMG).type) == "struct<bytes: binary, path: string>"
    assert str(schema.field("action").type) == "fixed_size_list<element: float>[3]"
    assert b"huggingface" in schema.metadata


def test_stats_json_matches_the_data(tmp_path):
    eps = random_episodes(3)
    write(tmp_path / "ds", eps)
    stats = json.loads((tmp_path / "ds" / fmt.STATS_PATH).read_text())
    assert set(stats) == set(FEATURES) | set(fmt.DEFAULT_FEATURES)
    n = sum(len(e["action"]) for e in eps)
    for key in ("observation.state", "action"):
        v = np.concatenate([e[key] for e in eps]).astype(np.float64)
        s = stats[key]
        assert s["count"] == [n]
        np.testing.assert_allclose(s["min"], v.min(0), rtol=0, atol=0)
        np.testing.assert_allclose(s["max"], v.max(0), rtol=0, atol=0)
        np.testing.assert_allclose(s["mean"], v.mean(0), rtol=1e-12)
        np.testing.assert_allclose(s["std"], v.std(0), rtol=1e-9)
        # quantiles: LeRobot's rule, the count-weighted mean of per-episode quantiles
        for q, name in zip(fmt.QUANTILES, fmt.QUANTILE_KEYS, strict=True):
            per = [np.quantile(e[key].astype(np.float64), q, axis=0) * len(e[key]) for e in eps]
            np.testing.assert_allclose(s[name], np.sum(per, 0) / n, rtol=1e-12)
    for key in (IMG, RGB):
        px = np.concatenate([quantised_hwc(e, key) for e in eps]).astype(np.float64) / 255
        px = px.reshape(-1, px.shape[-1])
        s = stats[key]
        c = px.shape[1]
        assert np.asarray(s["mean"]).shape == (c, 1, 1) and s["count"] == [n]
        np.testing.assert_allclose(np.ravel(s["min"]), px.min(0), atol=1e-15)
        np.testing.assert_allclose(np.ravel(s["max"]), px.max(0), atol=1e-15)
        np.testing.assert_allclose(np.ravel(s["mean"]), px.mean(0), rtol=1e-12)
        np.testing.assert_allclose(np.ravel(s["std"]), px.std(0), rtol=1e-9)
    assert stats["index"]["max"] == [n - 1] and stats["index"]["min"] == [0]
    # per-episode quantiles of images are exact (a histogram gives np.quantile's values)
    write(tmp_path / "one", eps[:1])
    one = json.loads((tmp_path / "one" / fmt.STATS_PATH).read_text())
    px = quantised_hwc(eps[0], RGB).reshape(-1, 3).astype(np.float64) / 255
    for q, name in zip(fmt.QUANTILES, fmt.QUANTILE_KEYS, strict=True):
        np.testing.assert_allclose(np.ravel(one[RGB][name]), np.quantile(px, q, axis=0), rtol=1e-12)
    loaded = load_stats(tmp_path / "ds")
    assert loaded[RGB]["std"].shape == (3, 1, 1) and loaded["action"]["mean"].dtype == torch.float32


def test_appending_never_rewrites_earlier_data_and_the_reader_spans_the_files(tmp_path):
    eps = random_episodes(4)
    root = tmp_path / "ds"
    w = write(root, eps[:3])
    files = sorted((root / "data").glob("*/*.parquet"))
    before = {f: (f.stat().st_ino, f.read_bytes()) for f in files}
    w.add_episode(eps[3])
    # the earlier episodes' files are the same files, byte for byte (not rewritten and renamed)
    assert {f: (f.stat().st_ino, f.read_bytes()) for f in files} == before
    files = sorted((root / "data").glob("*/*.parquet"))
    assert [f.name for f in files] == [f"file-{i:03d}.parquet" for i in range(4)]
    rows = read_episodes(root)
    assert [r["data/file_index"] for r in rows] == [0, 1, 2, 3]
    ds = LeRobotFrames(root)
    want = np.concatenate([e["action"] for e in eps])
    assert torch.equal(
        torch.stack([ds[i]["action"] for i in range(len(ds))]), torch.from_numpy(want)
    )


def _as_one_data_file(root):
    """Rewrite a dataset the way earlier writers laid it out: every episode in file-000 (one
    row group each), meta/episodes pointing there."""
    files = sorted((root / "data").glob("*/*.parquet"))
    tables = [pq.read_table(f) for f in files]
    with pq.ParquetWriter(root / "one.parquet", tables[0].schema) as w:
        for t in tables:
            w.write_table(t, row_group_size=len(t))
    for f in files:
        f.unlink()
    (root / "one.parquet").rename(fmt.data_file(root, 0, 0))
    for f in (root / fmt.EPISODES_DIR).glob("*/*.parquet"):
        t = pq.read_table(f)
        i = t.schema.get_field_index("data/file_index")
        t = t.set_column(i, t.schema.field(i), [[0] * len(t)])
        pq.write_table(t, f)


def test_a_dataset_in_one_data_file_is_read_and_appended_to_without_rewriting_it(tmp_path):
    eps = random_episodes(4)
    root = tmp_path / "ds"
    write(root, eps[:3])
    _as_one_data_file(root)
    one = fmt.data_file(root, 0, 0)
    assert pq.ParquetFile(one).num_row_groups == 3
    before = (one.stat().st_ino, one.read_bytes())
    w = DatasetWriter(root, FPS, FEATURES, task="navigate", resume=True)
    w.add_episode(eps[3])
    assert (one.stat().st_ino, one.read_bytes()) == before
    assert [r["data/file_index"] for r in read_episodes(root)] == [0, 0, 0, 1]
    write(tmp_path / "clean", eps)
    a, b = LeRobotFrames(root), LeRobotFrames(tmp_path / "clean")
    assert len(a) == len(b)
    for i in range(len(a)):
        for k in b[i]:
            assert torch.equal(a[i][k], b[i][k]), (i, k)


class Killed(BaseException):
    """Stands for the process dying (not an Exception: nothing may catch it)."""


def _snapshot(root):
    ds = LeRobotFrames(root)
    items = [ds[i] for i in range(len(ds))]
    frames = {k: torch.stack([it[k] for it in items]) for k in items[0]}
    meta = (
        json.loads((root / fmt.INFO_PATH).read_text()),
        json.loads((root / fmt.STATS_PATH).read_text()),
    )
    return frames, meta, read_episodes(root)


@pytest.mark.parametrize("kill_in", ["_commit_metadata", "_write_info"])
def test_interrupted_write_resumes_without_duplicates_or_gaps(tmp_path, monkeypatch, kill_in):
    eps = random_episodes(4)
    root = tmp_path / "ds"
    w = write(root, eps[:2])

    def die(*a, **k):
        raise Killed

    # killed after the data file of episode 2 landed (and, for _write_info, after its
    # meta/episodes row and stats), before info.json counted it
    monkeypatch.setattr(DatasetWriter, kill_in, die)
    with pytest.raises(Killed):
        w.add_episode(eps[2])
    monkeypatch.undo()
    with pytest.raises(RuntimeError, match="resume=True"):
        w.add_episode(eps[2])
    on_disk = pq.read_metadata(root / "data/chunk-000/file-002.parquet").num_rows
    assert on_disk == len(eps[2]["action"])  # episode 2's rows landed, uncommitted
    # the killed folder still reads as the two committed episodes
    assert len(LeRobotFrames(root)) == sum(len(e["action"]) for e in eps[:2])
    w = DatasetWriter(root, FPS, FEATURES, task="navigate", resume=True)
    assert (w.num_episodes, w.num_frames) == (2, sum(len(e["action"]) for e in eps[:2]))
    for ep in eps[2:]:
        w.add_episode(ep)
    assert not list(root.rglob("*.tmp"))
    n = sum(len(e["action"]) for e in eps)
    files = sorted((root / "data").glob("*/*.parquet"))
    assert len(files) == 4
    rows = [i for f in files for i in pq.read_table(f, columns=["index"])["index"].to_pylist()]
    assert rows == list(range(n))  # no orphan, duplicate, gap
    write(tmp_path / "clean", eps)
    got, clean = _snapshot(root), _snapshot(tmp_path / "clean")
    assert got[0].keys() == clean[0].keys()
    for k in got[0]:
        assert torch.equal(got[0][k], clean[0][k]), k
    assert got[1] == clean[1] and got[2] == clean[2]


def test_existing_folder_rules(tmp_path):
    eps = random_episodes(2)
    root = tmp_path / "ds"
    write(root, eps)
    with pytest.raises(FileExistsError, match="resume=True"):
        DatasetWriter(root, FPS, FEATURES)
    with pytest.raises(ValueError, match="exclude"):
        DatasetWriter(root, FPS, FEATURES, resume=True, force=True)
    other = {**FEATURES, "action": {"dtype": "float32", "shape": [4], "names": None}}
    with pytest.raises(ValueError, match="features differ"):
        DatasetWriter(root, FPS, other, resume=True)
    with pytest.raises(ValueError, match="fps"):
        DatasetWriter(root, FPS + 1, FEATURES, resume=True)
    w = DatasetWriter(root, FPS, FEATURES, force=True)
    assert w.num_episodes == 0 and not (root / "data").exists()
    junk = tmp_path / "junk"
    junk.mkdir()
    (junk / "notes.txt").write_text("mine")
    with pytest.raises(FileExistsError, match="not a dataset"):
        DatasetWriter(junk, FPS, FEATURES, force=True)
    assert (junk / "notes.txt").exists()
    fresh = DatasetWriter(tmp_path / "new", FPS, FEATURES, resume=True)  # nothing to resume
    assert fresh.num_episodes == 0


def test_codebase_version_is_pinned(tmp_path):
    root = tmp_path / "ds"
    write(root, random_episodes(1))
    info = json.loads((root / fmt.INFO_PATH).read_text())
    info["codebase_version"] = "v2.1"
    (root / fmt.INFO_PATH).write_text(json.dumps(info))
    for call in (
        lambda: fmt.read_info(root),
        lambda: LeRobotFrames(root),
        lambda: DatasetWriter(root, FPS, FEATURES, resume=True),
    ):
        with pytest.raises(fmt.DatasetVersionError, match="v2.1.*v3.0 only"):
            call()


def test_bad_features_and_frames_are_refused(tmp_path):
    for feats, msg in [
        ({"a/b": {"dtype": "float32", "shape": [1]}}, "'/'"),
        ({"index": {"dtype": "int64", "shape": [1]}}, "reserved"),
        ({"observation.images.x": {"dtype": "image", "shape": [4, 4, 2]}}, "C 1 or 3"),
        ({"observation.images.x": {"dtype": "video", "shape": [4, 4, 3]}}, "video"),
        ({"action": {"dtype": "float16", "shape": [2]}}, "dtype"),
    ]:
        with pytest.raises(fmt.DatasetFormatError, match=msg):
            DatasetWriter(tmp_path / "x", FPS, feats)
    w = DatasetWriter(tmp_path / "ds", FPS, FEATURES)
    ep = random_episodes(1)[0]
    with pytest.raises(fmt.DatasetFormatError, match="missing"):
        w.add_episode({k: v for k, v in ep.items() if k != "action"})
    with pytest.raises(fmt.DatasetFormatError, match="NaN"):
        w.add_episode({**ep, "action": np.full_like(ep["action"], np.nan)})
    with pytest.raises(fmt.DatasetFormatError, match="do not match"):
        w.add_episode({**ep, IMG: ep[IMG][:, :, :5]})
    with pytest.raises(fmt.DatasetFormatError, match="length"):
        w.add_episode({**ep, "action": ep["action"][:-1]})
    assert w.num_episodes == 0 and not (tmp_path / "ds" / "data").exists()


# -2e6: twice the documented bound, reader.MAX_ABS_VALUE
@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf, 1e30, -2e6])
@pytest.mark.parametrize(("key", "component"), [("action", 2), ("observation.state", 0)])
def test_non_finite_or_absurd_values_are_refused_naming_file_episode_frame_column(
    tmp_path, value, key, component
):
    """One such value trained a policy whose weights were all NaN, with exit 0."""
    root = tmp_path / "ds"
    write(root, random_episodes(3))  # lengths 4, 6, 8: frame 7 is episode 1's frame 3
    path = set_value(root, key, 7, component, value)
    with pytest.raises(fmt.DatasetFormatError) as e:
        LeRobotFrames(root)
    msg = str(e.value)
    assert str(path) in msg and "episode 1, frame 3" in msg
    assert f"column {key}[{component}] is" in msg and "re-record" in msg


def test_values_within_the_bound_read_back_exactly(tmp_path):
    from sonogym.imitation.reader import MAX_ABS_VALUE

    assert MAX_ABS_VALUE == 1e6  # the bound the docs state
    root = tmp_path / "ds"
    write(root, random_episodes(3))
    set_value(root, "action", 7, 2, 0.5 * MAX_ABS_VALUE)
    assert LeRobotFrames(root).frame(7)["action"][2].item() == 0.5 * MAX_ABS_VALUE


@pytest.mark.parametrize("value", [float("nan"), float("inf"), 1e30])
def test_stats_json_with_non_finite_or_absurd_values_is_refused(tmp_path, value):
    root = tmp_path / "ds"
    write(root, random_episodes(2))
    path = root / fmt.STATS_PATH
    stats = json.loads(path.read_text())
    stats["action"]["mean"][1] = value  # json writes NaN / Infinity, and reads them back
    path.write_text(json.dumps(stats))
    with pytest.raises(fmt.DatasetFormatError, match=r"stats.json: action/mean holds"):
        load_stats(root)


def test_an_info_json_that_does_not_describe_the_data_is_refused(tmp_path):
    root = tmp_path / "ds"
    write(root, random_episodes(2))
    path = root / fmt.INFO_PATH
    good = json.loads(path.read_text())
    # another action shape: the data hold 3 values per frame
    info = json.loads(path.read_text())
    info["features"]["action"]["shape"] = [4]
    info["features"]["action"]["names"] = ["a", "b", "c", "d"]
    path.write_text(json.dumps(info))
    with pytest.raises(fmt.DatasetFormatError, match=r"action/min has shape \(3,\).*needs \(4,\)"):
        load_stats(root)
    with pytest.raises(fmt.DatasetFormatError, match="'action' holds 3 values per frame.*\\[4\\]"):
        LeRobotFrames(root)
    # another robot's features: a camera the stats (and the data) do not have
    info = json.loads(json.dumps(good))
    info["features"]["observation.images.wrist"] = {"dtype": "image", "shape": [8, 8, 3],
                                                    "names": fmt.IMAGE_NAMES}  # fmt: skip
    path.write_text(json.dumps(info))
    with pytest.raises(fmt.DatasetFormatError, match="no statistics of 'observation.images.wrist'"):
        load_stats(root)


def test_delta_indices_stack_history_and_chunks_with_pads(tmp_path):
    eps = random_episodes(2, lengths=[5, 6])
    write(tmp_path / "ds", eps)
    deltas = {"action": [-1, 0, 1, 2, 3], IMG: [-1, 0]}
    ds = LeRobotFrames(tmp_path / "ds", delta_indices=deltas)
    a = np.concatenate([e["action"] for e in eps])
    bounds = [(0, 5), (5, 11)]
    for idx in range(11):
        lo, hi = bounds[0] if idx < 5 else bounds[1]
        item = ds[idx]
        q = [idx + d for d in deltas["action"]]
        assert item["action_is_pad"].tolist() == [not lo <= j < hi for j in q]
        want = a[[min(max(j, lo), hi - 1) for j in q]]
        assert torch.equal(item["action"], torch.from_numpy(want))
        assert item[IMG].shape == (2, 1, 12, 9)
        assert item[IMG + "_is_pad"].tolist() == [idx - 1 < lo, False]
        assert torch.equal(item[IMG][1], ds.frame(idx)[IMG])
    same = LeRobotFrames(tmp_path / "ds", delta_timestamps={"action": [-0.1, 0, 0.1, 0.2, 0.3]})
    assert torch.equal(same[7]["action"], ds[7]["action"])
    with pytest.raises(ValueError, match="multiples"):
        LeRobotFrames(tmp_path / "ds", delta_timestamps={"action": [0.05]})
    dropped = LeRobotFrames(tmp_path / "ds", drop_n_last_frames=2)
    assert len(dropped) == 11 - 4
    assert [int(dropped[i]["index"]) for i in range(len(dropped))] == [0, 1, 2, 5, 6, 7, 8]
    sub = LeRobotFrames(tmp_path / "ds", episodes=[1])
    assert [int(sub[i]["episode_index"]) for i in range(len(sub))] == [1] * 6


def test_decoded_cache_equals_bytes_cache(tmp_path):
    write(tmp_path / "ds", random_episodes(2))
    with pytest.warns(UserWarning, match="do not fit"):  # no cache: every access re-reads
        a = LeRobotFrames(tmp_path / "ds", image_cache="bytes", cache_mb=0)
    b = LeRobotFrames(tmp_path / "ds", image_cache="decoded")
    for i in range(len(a)):
        for k in (IMG, RGB):
            assert torch.equal(a[i][k], b[i][k])


def test_the_default_image_cache_reads_each_data_file_once(tmp_path, monkeypatch):
    import sonogym.imitation.reader as reader

    write(tmp_path / "ds", random_episodes(6))
    files = sorted((tmp_path / "ds" / "data").glob("*/*.parquet"))
    assert len(files) > 2  # one data file per episode
    reads = []
    real = reader.pq.read_table
    monkeypatch.setattr(
        reader.pq, "read_table", lambda path, **kw: reads.append(path) or real(path, **kw)
    )
    ds = LeRobotFrames(tmp_path / "ds")  # budget: the data files' size
    reads.clear()
    for i in torch.randperm(len(ds), generator=torch.Generator().manual_seed(0)).tolist() * 2:
        ds[i]
    assert sorted(reads) == files  # random order, two passes: each file read once
    # a budget below the data files' size says so (random sampling re-reads files)
    with pytest.warns(UserWarning, match="do not fit the image cache"):
        small = LeRobotFrames(tmp_path / "ds", cache_mb=0)
    reads.clear()
    for i in torch.randperm(len(small), generator=torch.Generator().manual_seed(0)).tolist():
        small[i]
    assert len(reads) > len(files)
    # ... and so does a machine with too little memory for them
    monkeypatch.setattr(reader, "available_memory", lambda: 2 * 1024)
    with pytest.warns(UserWarning, match="half the memory available"):
        LeRobotFrames(tmp_path / "ds")
