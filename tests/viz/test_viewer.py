"""``sonogym view``: what each mode writes to an .rrd file, read back with Rerun's own reader
(``rerun.chunk.RrdReader``) and compared with the env, the episode log or the dataset it shows."""

from __future__ import annotations

import numpy as np
import pytest
import torch

pytest.importorskip(
    "rerun", reason="the viewer tests need rerun-sdk: pip install 'sonogym[viewer]'"
)

from sonogym.anatomy.labels import LUMBAR_VERTEBRAE, VERTEBRA_IDS  # noqa: E402
from sonogym.envs.policy import ExpertPolicy  # noqa: E402
from sonogym.envs.registry import get_task, make_vec  # noqa: E402
from sonogym.envs.rollout import rollout  # noqa: E402
from sonogym.viewer.command import ViewRequest, run_view  # noqa: E402
from sonogym.viewer.env_view import policy_choice, view_env  # noqa: E402
from sonogym.viewer.session import open_session  # noqa: E402

SMALL = dict(phantom_spacing=0.002)
LUMBAR_IDS = [VERTEBRA_IDS[lv] for lv in LUMBAR_VERTEBRAE]


def read_rrd(path) -> dict[str, list[tuple[int | None, dict]]]:
    """{entity: [(step, {component: value})]}, rows sorted by step (static rows: step None)."""
    from rerun.chunk import RrdReader

    out: dict[str, list] = {}
    for chunk in RrdReader(path).stream().to_chunks():
        rb = chunk.to_record_batch()
        names = rb.schema.names
        steps = rb.column("step").to_pylist() if "step" in names else [None] * rb.num_rows
        comps = [n for n in names if ":" in n]
        for i, s in enumerate(steps):
            out.setdefault(chunk.entity_path.lstrip("/"), []).append(
                (s, {n: rb.column(n)[i].as_py() for n in comps})
            )
    for rows in out.values():
        rows.sort(key=lambda r: -1 if r[0] is None else r[0])
    return out


def steps_of(rows) -> list[int]:
    """The timeline steps an entity was logged at (its static rows left out)."""
    return [s for s, _ in rows if s is not None]


def values(rows, component) -> dict[int | None, list]:
    """{step: the component's instances} of the rows that hold it."""
    return {s: v[component] for s, v in rows if v.get(component) is not None}


def image(row: dict, prefix: str) -> np.ndarray:
    """The (H, W, C) uint8 image of a row's ``<prefix>buffer`` / ``<prefix>format``."""
    (fmt,), (buf,) = row[f"{prefix}format"], row[f"{prefix}buffer"]
    return np.array(buf, np.uint8).reshape(fmt["height"], fmt["width"], -1)


def view(tmp_path, task, steps, seed=0, **options):
    session = open_session(task, save=tmp_path / f"{task}.rrd")
    res = view_env(session.rec, task, policy_choice("expert"), {**SMALL, **options}, steps, seed,
                   log=lambda m: None)  # fmt: skip
    session.close()
    return res, read_rrd(session.path)


def reference(task, steps, seed=0, **options):
    """The same rollout (expert, same seed), recording what the view should show."""
    env = make_vec(task, 1, **SMALL, **options)
    obs, info = env.reset(seed=seed)
    states = [dict(info=info, pos=env.scene.probe_pos[0].clone())]
    for step in rollout(env, ExpertPolicy(env, get_task(task).expert), steps, reset=False,
                        obs=obs, info=info):  # fmt: skip
        states.append(
            dict(
                step=step,
                pos=env.scene.probe_pos[0].clone(),
                info=step.next_info,
                tip=getattr(env.scene, "tip_pos", torch.zeros(1, 3))[0].clone(),
                volume=env.volume[0].clone() if task == "reconstruction" else None,
            )
        )
        # fmt: skip
    return env, states


def test_navigation_view_logs_the_scene_images_and_errors_step_by_step(tmp_path):
    torch.set_num_threads(1)
    # 6 steps of 4-step episodes: an autoreset after step 4
    res, rows = view(tmp_path, "navigation", 6, seed=3, episode_length=4)
    env, ref = reference("navigation", 6, seed=3, episode_length=4)
    assert res.timeline == 7
    for e in ("world/probe", "world/probe_arm", "image/us", "image/labels", "world/probe/image"):
        assert steps_of(rows[e]) == list(range(7)), e
    assert steps_of(rows["series/reward"]) == list(range(1, 7))
    for name in ("skin", "bone", "L4"):
        (s, mesh), *_ = rows[f"world/patient/{name}"]
        assert s is None and len(mesh["Mesh3D:triangle_indices"]) > 100  # static, once
    probe = values(rows["world/probe"], "Transform3D:translation")
    arm = values(rows["world/probe_arm"], "LineStrips3D:strips")
    for k in range(7):  # the pose the arm reached at step k, held by the arm's last link
        np.testing.assert_allclose(probe[k][0], ref[k]["pos"].numpy(), atol=1e-6)
        np.testing.assert_allclose(arm[k][0][-1], probe[k][0], atol=1e-5)
    goal = values(rows["world/goal"], "Transform3D:translation")
    np.testing.assert_allclose(goal[0][0], env.goal_pos[0].numpy(), atol=1e-6)
    # reward and the frontal-plane position error of step k (after the reset: the ended
    # episode's last state, as its final_info reports it)
    reward = values(rows["series/reward"], "Scalars:scalars")
    err = values(rows["series/position_error_mm"], "Scalars:scalars")
    g = env.goal_cmd[0, :2]
    for k in range(1, 7):
        step = ref[k]["step"]
        assert reward[k][0] == pytest.approx(float(step.reward[0]), abs=1e-6)
        want = float((step.next_info["measured_command"][0, :2] - g).norm() * 1e3)
        assert err[k][0] == pytest.approx(want, abs=1e-3)
    assert err[4][0] < err[1][0]  # the expert closes in within its episode
    # the probe's path restarts with the new episode: steps 4, 5, 6
    path = values(rows["world/probe_path"], "LineStrips3D:strips")
    assert len(path[3][0]) == 4 and len(path[6][0]) == 3
    # the 3-D image plane carries the 2-D image of the same step
    for k in (0, 5):
        us = image(dict(rows["image/us"])[k], "Image:")
        tex = image(dict(rows["world/probe/image"])[k], "Mesh3D:albedo_texture_")
        assert us.shape[:2] == (200, 150) and np.array_equal(tex[..., 0], us[..., 0])
    labels = image(dict(rows["image/labels"])[6], "SegmentationImage:")[..., 0]
    want = env.scene.observe("labels", torch.zeros(1, dtype=torch.long))[0, 0].numpy()
    # two steps into the second episode the probe is over the spine, ~30 mm above the goal
    assert np.array_equal(labels, want) and np.isin(labels, LUMBAR_IDS).any()
    (_, ctx), *_ = rows["image/labels"]
    assert ctx.get("AnnotationContext:context")  # names and colours of the label ids


def test_surgery_view_draws_the_drill_against_its_planned_corridor(tmp_path, small_phantom):
    torch.set_num_threads(1)
    res, rows = view(tmp_path, "surgery", 3)
    env, ref = reference("surgery", 3)
    assert res.timeline == 4
    for e in (0, 4):  # the probe is still: its five slices are logged once
        for base in ("image/us", "image/labels", "world/probe/image"):
            assert steps_of(rows[f"{base}/slice_{e}"]) == [0]
    assert image(rows["image/us/slice_2"][0][1], "Image:").shape[:2] == (50, 37)
    traj = small_phantom.landmarks.trajectory("L4", "right")
    (_, cyl), *_ = rows["world/goal/c_drill"]
    assert cyl["Cylinders3D:lengths"] == pytest.approx([0.05])
    assert cyl["Cylinders3D:radii"] == pytest.approx([traj.radius + 0.002], abs=1e-6)
    assert cyl["Cylinders3D:centers"] == [pytest.approx([0, 0, -0.025])]  # -l..0 along z_G
    (_, plan), *_ = rows["world/plan"]
    np.testing.assert_allclose(plan["LineStrips3D:strips"][0], [traj.entry, traj.target],
                               atol=1e-6)  # fmt: skip
    goal = values(rows["world/goal"], "Transform3D:translation")
    np.testing.assert_allclose(goal[None][0], traj.target, atol=1e-6)  # {G} at the target point
    tip = values(rows["world/drill"], "Transform3D:translation")
    arm = values(rows["world/drill_arm"], "LineStrips3D:strips")
    safe = values(rows["series/safe"], "Scalars:scalars")
    for k in range(1, 4):
        np.testing.assert_allclose(tip[k][0], ref[k]["tip"].numpy(), atol=1e-6)
        np.testing.assert_allclose(arm[k][0][-1], tip[k][0], atol=1e-5)  # the drill arm holds it
        assert safe[k][0] == float(ref[k]["info"]["safe"][0])
    assert "world/probe_arm" in rows and "series/insertion_error_mm" in rows


def test_reconstruction_view_accumulates_the_reconstructed_points(tmp_path):
    torch.set_num_threads(1)
    res, rows = view(tmp_path, "reconstruction", 5)
    env, ref = reference("reconstruction", 5)
    pts = values(rows["world/reconstruction"], "Points3D:positions")
    counts = [len(pts[k]) for k in range(6)]
    assert counts == [int(ref[k]["volume"].sum()) if k else 0 for k in range(6)]
    assert counts[-1] > counts[1] > 0 and counts == sorted(counts)  # V only grows
    lo = env.centre[0].numpy() - env.cfg.cube_half_extent
    p = np.array(pts[5])
    assert ((p > lo) & (p < lo + 2 * env.cfg.cube_half_extent)).all()  # inside the cube
    assert "series/coverage" in rows and "world/goal" not in rows


def _episode_log(tmp_path, task, trials, **options):
    """An evaluation episode log of the expert, written as ``evaluate_run`` writes it, and
    each episode's probe positions and drill tips as the env reached them."""
    from sonogym.evaluation.episodes import log_path, save_log

    spec, n = get_task(task), trials
    env = make_vec(task, n, **SMALL, **options)
    T = env.episode_length
    track = np.zeros((n, T + 1, len(spec.track.columns)), np.float32)
    probe, tip = np.zeros((n, T + 1, 3)), np.zeros((n, T + 1, 3))
    obs, info = env.reset(seed=7)
    track[:, 0] = spec.track.fn(env, info).numpy()
    probe[:, 0] = env.scene.probe_pos.numpy()
    tip[:, 0] = getattr(env.scene, "tip_pos", torch.zeros(n, 3)).numpy()
    policy = ExpertPolicy(env, spec.expert)
    for step in rollout(env, policy, T, reset=False, obs=obs, info=info):
        track[:, step.t + 1] = spec.track.fn(env, step.next_info).numpy()
        if step.t < T - 1:  # the last step resets the env: the last state is in the info only
            probe[:, step.t + 1] = env.scene.probe_pos.numpy()
            tip[:, step.t + 1] = getattr(env.scene, "tip_pos", torch.zeros(n, 3)).numpy()
    final = step.final_info
    meta = dict(task=task, algo="ppo", run="r", train_seed=0, protocol="idt", eval_seed=7,
                trials=n, num_envs=n, controllers=["expert"], checkpoint="agent_10.pt",
                train_env={**SMALL, **options}, test_env={**SMALL, **options},
                track_columns=list(spec.track.columns),
                track_units=list(spec.track.units))  # fmt: skip
    metrics = {k: v.numpy() for k, v in final.items() if k != "env_ids"}
    save_log(log_path(tmp_path / "run", "idt"), meta, {"expert": metrics}, {"expert": track})
    return tmp_path / "run", probe, tip, metrics


def test_run_replay_places_the_probe_and_drill_along_the_saved_track(tmp_path):
    torch.set_num_threads(1)
    run, probe, _, metrics = _episode_log(tmp_path, "navigation", 2, episode_length=5)
    out = tmp_path / "nav.rrd"
    res = run_view(ViewRequest(run=run, episode=1), save=out, log=lambda m: None)
    rows = read_rrd(out)
    assert res.timeline == 6 and steps_of(rows["world/probe"]) == list(range(6))
    pos = values(rows["world/probe"], "Transform3D:translation")
    for t in range(5):  # the saved surface command, put back on the skin: the reached pose
        np.testing.assert_allclose(pos[t][0], probe[1, t], atol=1e-3)
    assert values(rows["series/x"], "Scalars:scalars")[5] == pytest.approx(
        [float(np.load(run / "episodes" / "idt.npz")["expert/track"][1, 5, 0])]
    )
    (_, doc), *_ = rows["summary"]
    assert (
        f"| position_error_mm | {metrics['position_error_mm'][1]:.4g} |"
        in doc["TextDocument:text"][0]
    )
    assert "world/patient/L4" in rows and "image/us" not in rows  # no images in a log

    run, _, tip, _ = _episode_log(tmp_path / "s", "surgery", 1, episode_length=5)
    out = tmp_path / "surgery.rrd"
    run_view(ViewRequest(run=run, controller="expert"), save=out, log=lambda m: None)
    rows = read_rrd(out)
    drill = values(rows["world/drill"], "Points3D:positions")
    for t in range(5):
        np.testing.assert_allclose(drill[t][0], tip[0, t], atol=1e-5)
    assert "world/goal/c_drill" in rows and "world/plan" in rows
    with pytest.raises(ValueError, match=r"episodes 0\.\.0"):
        run_view(ViewRequest(run=run, episode=3), save=tmp_path / "x.rrd", log=lambda m: None)
    with pytest.raises(FileNotFoundError, match=r"episode logs \['idt'\]"):
        run_view(ViewRequest(run=run, protocol="odt-sim"), save=tmp_path / "y.rrd")


def test_dataset_replay_shows_the_saved_images_state_and_actions(tmp_path):
    from sonogym.imitation.record import dataset_spec, info_features
    from sonogym.imitation.writer import DatasetWriter

    torch.set_num_threads(1)
    spec = get_task("surgery")
    env = make_vec("surgery", 1, **SMALL)
    features = dataset_spec("surgery").features
    frames = {f.key: [] for f in features} | {"action": []}
    for step in rollout(env, ExpertPolicy(env, spec.expert), 9, seed=1):
        for f in features:
            frames[f.key].append(f.fn(step.obs, step.info)[0].numpy())
        frames["action"].append(step.action[0].numpy())
    frames = {k: np.stack(v) for k, v in frames.items()}
    with DatasetWriter(tmp_path / "ds", 60, info_features("surgery", 6), task="drill") as w:
        w.add_episode({k: v[:4] for k, v in frames.items()})
        w.add_episode({k: v[4:] for k, v in frames.items()})
    out = tmp_path / "ds.rrd"
    res = run_view(ViewRequest(dataset=tmp_path / "ds", episode=1), save=out, log=lambda m: None)
    rows = read_rrd(out)
    assert res.timeline == 5
    for e in range(5):
        assert steps_of(rows[f"image/slice_{e}"]) == list(range(5))
    img = image(dict(rows["image/slice_3"])[2], "Image:")[..., 0]
    want = np.round(frames["observation.images.slice_3"][6, 0] * 255)
    assert np.abs(img.astype(int) - want).max() <= 1  # the saved 8-bit image of frame 2
    act = values(rows["series/action"], "Scalars:scalars")
    np.testing.assert_allclose(act[4], frames["action"][8], rtol=1e-6)
    names = values(rows["series/action"], "SeriesLines:names")[None]
    assert names == list(spec.action_names)
    pose = values(rows["world/observation.state"], "Transform3D:translation")
    np.testing.assert_allclose(pose[0][0], frames["observation.state"][4, :3], atol=1e-6)
    with pytest.raises(IndexError, match="episode 2"):
        run_view(ViewRequest(dataset=tmp_path / "ds", episode=2), save=tmp_path / "z.rrd")


def test_web_viewer_is_served_from_the_wheel(unused_tcp_port_pair):
    import urllib.request

    web, grpc = unused_tcp_port_pair
    session = open_session("web", web=True, web_port=web, grpc_port=grpc)
    assert session.url.startswith(f"http://localhost:{web}/?url=rerun%2Bhttp")
    page = urllib.request.urlopen(f"http://127.0.0.1:{web}/", timeout=10).read().decode()
    assert "re_viewer.js" in page
    js = urllib.request.urlopen(f"http://127.0.0.1:{web}/re_viewer.js", timeout=10).read()
    assert len(js) > 10_000  # the viewer's code, from the installed package, not the network
    session.close()


@pytest.fixture
def unused_tcp_port_pair():
    import socket

    socks = [socket.socket() for _ in range(2)]
    for s in socks:
        s.bind(("127.0.0.1", 0))
    ports = [s.getsockname()[1] for s in socks]
    for s in socks:
        s.close()
    return ports


def test_a_view_is_named_for_its_default_file_by_its_source(tmp_path):
    assert ViewRequest(task="surgery", policy="random").name == "surgery-random"
    assert ViewRequest(run=tmp_path / "my run", protocol="odt-sim", episode=3).name == (
        "my_run-odt-sim-ep3"
    )
    assert ViewRequest(dataset=tmp_path / "ds").name == "ds-ep0"
