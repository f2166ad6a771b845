"""ACT and Diffusion Policy: normalisation, temporal ensembling, training, env-side wrapper."""

from __future__ import annotations

import json
import math

import pytest
import torch
from il_datasets import BLOB_FEATURES

from sonogym.envs.policy import Policy
from sonogym.imitation.buffers import ActionQueue, ObsHistory, TemporalEnsembler
from sonogym.imitation.policies.act import ACTConfig, ACTPolicy
from sonogym.imitation.policies.diffusion import DiffusionConfig, DiffusionPolicy
from sonogym.imitation.policy import ILPolicy, load_il_policy
from sonogym.imitation.processor import Normalizer, PolicyFeatures
from sonogym.imitation.reader import load_stats
from sonogym.imitation.run import IL_RUN, load_checkpoint
from sonogym.imitation.train import ILTrainConfig, train_il
from sonogym.runs import RunFolder

CAM = "observation.images.cam"
STATE = "observation.state"

# test-sized models (a few 10 k parameters)
TINY_ACT = ACTConfig.cpu(
    chunk_size=4,
    n_action_steps=4,
    backbone_widths=(8, 16),
    backbone_blocks=(1, 1),
    dim_model=32,
    n_heads=2,
    dim_feedforward=64,
    n_encoder_layers=1,
    n_vae_encoder_layers=1,
    latent_dim=4,
    dropout=0.0,
    lr=1e-3,
    lr_backbone=1e-3,
)
TINY_DP = DiffusionConfig.cpu(
    horizon=8,
    n_action_steps=4,
    backbone_widths=(8, 16),
    backbone_blocks=(1, 1),
    num_keypoints=4,
    down_dims=(16, 32),
    diffusion_step_embed_dim=16,
    lr=1e-3,
    lr_warmup_steps=1,
)
FEATS = PolicyFeatures.from_info(BLOB_FEATURES)


def checkpoints(run):
    return RunFolder(run, IL_RUN).checkpoints()


def obs_batch(n, seed):
    g = torch.Generator().manual_seed(seed)
    return {CAM: torch.rand(n, 1, 16, 12, generator=g), STATE: torch.randn(n, 2, generator=g)}


def identity(obs, info):
    return obs


def test_normalizer_formulas_and_inverse():
    stats = {
        "a": {
            "mean": torch.tensor([1.0, -2.0]),
            "std": torch.tensor([2.0, 0.5]),
            "min": torch.tensor([-1.0, 3.0]),
            "max": torch.tensor([3.0, 3.0]),
        },
    }
    x = torch.tensor([[0.0, 3.0], [3.0, -1.0]])
    ms = Normalizer(stats, {"a": "mean_std"})
    torch.testing.assert_close(
        ms.normalize("a", x), (x - stats["a"]["mean"]) / (stats["a"]["std"] + 1e-8)
    )
    mm = Normalizer(stats, {"a": "min_max"})
    y = mm.normalize("a", x)
    assert y[0, 0] == pytest.approx(-0.5) and y[1, 0] == pytest.approx(1.0)  # 2 (x - min) / d - 1
    assert y[0, 1] == pytest.approx(0.0, abs=1e-6)  # max == min: eps denominator, x - min = 0
    for n in (ms, mm):
        torch.testing.assert_close(n.unnormalize("a", n.normalize("a", x)), x)
    assert torch.equal(Normalizer(stats, {"a": "identity"}).normalize("a", x), x)
    with pytest.raises(KeyError, match="stats.json"):
        Normalizer(stats, {"b": "mean_std"})


def test_temporal_ensemble_weights_match_hand_computation():
    coeff, k = 0.3, 3
    w = [math.exp(-coeff * i) for i in range(k)]  # w_0 for the OLDEST prediction
    ens = TemporalEnsembler(coeff, k, num_envs=2, action_dim=1, device="cpu")
    preds = [torch.tensor([[1.0, 2.0, 3.0], [7.0, 8.0, 9.0]]) * 10**j for j in range(4)]
    out = [ens.update(p[..., None])[:, 0] for p in preds]
    # env 0: step 0 sees only P0[0]; step 1: P0[1] (old) and P1[0] (new); step 2 and 3: three
    assert out[0][0] == pytest.approx(1.0)
    assert out[1][0] == pytest.approx((2 * w[0] + 10 * w[1]) / (w[0] + w[1]))
    assert out[2][0] == pytest.approx((3 * w[0] + 20 * w[1] + 100 * w[2]) / sum(w))
    assert out[3][0] == pytest.approx((30 * w[0] + 200 * w[1] + 1000 * w[2]) / sum(w))
    # resetting env 1 only: its next action is its new prediction alone, env 0 keeps averaging
    ens.reset(torch.tensor([False, True]))
    a = ens.update((preds[0] * 10**4)[..., None])[:, 0]
    assert a[1] == pytest.approx(7.0e4)
    assert a[0] == pytest.approx((300 * w[0] + 2000 * w[1] + 10**4 * w[2]) / sum(w))


def test_action_queue_and_obs_history_per_env():
    q = ActionQueue(2, num_envs=3, action_dim=1, device="cpu")
    assert q.empty().all()
    q.fill(
        torch.arange(3),
        torch.tensor([[[1.0], [2.0], [9.0]], [[3.0], [4.0], [9.0]], [[5.0], [6.0], [9.0]]]),
    )
    assert q.pop()[:, 0].tolist() == [1, 3, 5]
    q.reset(torch.tensor([False, True, False]))
    assert q.empty().tolist() == [False, True, False]
    q.fill(torch.tensor([1]), torch.tensor([[[7.0], [8.0]]]))
    assert q.pop()[:, 0].tolist() == [2, 7, 6] and q.empty().tolist() == [True, False, True]
    h = ObsHistory(3)
    assert h.push(torch.tensor([[1.0], [2.0]]))[:, :, 0].tolist() == [[1, 1, 1], [2, 2, 2]]
    h.push(torch.tensor([[3.0], [4.0]]))
    h.reset(torch.tensor([True, False]))
    assert h.push(torch.tensor([[5.0], [6.0]]))[:, :, 0].tolist() == [[5, 5, 5], [2, 4, 6]]


@pytest.mark.parametrize(
    "policy,config,ratio", [("act", TINY_ACT, 0.3), ("diffusion", TINY_DP, 0.6)]
)
def test_training_loss_falls_and_run_folder(blob_dataset, tmp_path, policy, config, ratio):
    torch.set_num_threads(1)
    cfg = ILTrainConfig(
        data=str(blob_dataset),
        out=str(tmp_path / "run"),
        policy=policy,
        policy_config=config,
        steps=200,
        batch_size=16,
        save_every=100,
        log_every=20,
        progress=False,
        image_cache="decoded",
    )
    res = train_il(cfg)
    first, last = res.history[0][1], res.history[-1][1]
    assert res.steps == 200 and last < ratio * first, res.history
    assert [s for s, _ in checkpoints(tmp_path / "run")] == [100, 200]
    state = load_checkpoint(checkpoints(tmp_path / "run")[-1][1])  # weights_only=True
    assert state["step"] == 200 and set(state) >= {"model", "optimizer", "scheduler", "rng"}
    rc = json.loads((tmp_path / "run" / "config.json").read_text())
    assert rc["policy"] == policy and rc["features"] == FEATS.to_dict()
    stats = load_stats(blob_dataset)
    assert rc["stats"]["action"]["min"] == stats["action"]["min"].tolist()
    assert list((tmp_path / "run" / "tb").glob("events.out.tfevents.*"))
    # an existing run is refused without resume, continued with it
    with pytest.raises(FileExistsError, match="il-train. run; pass --resume"):
        train_il(cfg)
    more = train_il(ILTrainConfig(**{**cfg.__dict__, "steps": 220, "resume": True}))
    assert more.steps == 220 and checkpoints(tmp_path / "run")[-1][0] == 220
    # the trained policy acts in a batched env through the wrapper
    pol = load_il_policy(tmp_path / "run", identity)
    assert isinstance(pol, Policy)
    assert pol.act(obs_batch(5, 0), {}).shape == (5, 3)


def test_force_replaces_only_run_folders(blob_dataset, tmp_path):
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "x.txt").write_text("keep")
    cfg = ILTrainConfig(
        data=str(blob_dataset),
        out=str(tmp_path / "mine"),
        policy_config=TINY_ACT,
        steps=1,
        progress=False,
        force=True,
    )
    with pytest.raises(FileExistsError, match="refusing"):
        train_il(cfg)
    assert (tmp_path / "mine" / "x.txt").exists()


def _act_model(**kw):
    torch.manual_seed(0)
    cfg = ACTConfig(**{**TINY_ACT.__dict__, **kw})
    stats = {
        CAM: {"mean": torch.full((1, 1, 1), 0.3), "std": torch.full((1, 1, 1), 0.2)},
        STATE: {"mean": torch.zeros(2), "std": torch.ones(2)},
        "action": {"mean": torch.tensor([0.1, -0.1, 0.0]), "std": torch.tensor([0.5, 0.5, 0.2])},
    }
    return ACTPolicy(cfg, FEATS, stats).eval()


def test_act_wrapper_resets_only_masked_envs_chunk_execution():
    model = _act_model(temporal_ensemble_coeff=None)
    pol = ILPolicy(model, identity)
    obs = [obs_batch(3, s) for s in range(3)]
    chunk0 = model.predict_chunk(obs[0])
    a0, a1 = pol.act(obs[0], {}), pol.act(obs[1], {})
    torch.testing.assert_close(a0, chunk0[:, 0])
    torch.testing.assert_close(a1, chunk0[:, 1])  # still the first chunk
    pol.reset(torch.tensor([False, True, False]))
    a2 = pol.act(obs[2], {})
    torch.testing.assert_close(a2[[0, 2]], chunk0[[0, 2], 2])  # untouched envs go on
    fresh = model.predict_chunk({k: v[[1]] for k, v in obs[2].items()})
    torch.testing.assert_close(a2[1], fresh[0, 0], atol=1e-6, rtol=1e-5)  # env 1 replanned


def test_act_wrapper_temporal_ensemble_and_reset():
    coeff = 0.5
    model = _act_model(temporal_ensemble_coeff=coeff)
    pol = ILPolicy(model, identity)
    obs = [obs_batch(2, s) for s in range(3)]
    p = [model.predict_chunk(o) for o in obs]
    w = [math.exp(-coeff * i) for i in range(3)]
    pol.act(obs[0], {})
    pol.act(obs[1], {})
    pol.reset(torch.tensor([False, True]))
    a = pol.act(obs[2], {})
    want0 = (p[0][0, 2] * w[0] + p[1][0, 1] * w[1] + p[2][0, 0] * w[2]) / sum(w)
    torch.testing.assert_close(a[0], want0, atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(a[1], p[2][1, 0], atol=1e-6, rtol=1e-5)


def test_diffusion_wrapper_history_and_replanning_per_env(monkeypatch):
    torch.manual_seed(0)
    stats = {
        CAM: {"mean": torch.full((1, 1, 1), 0.3), "std": torch.full((1, 1, 1), 0.2)},
        STATE: {"min": -torch.ones(2), "max": torch.ones(2)},
        "action": {"min": -torch.ones(3), "max": torch.ones(3)},
    }
    model = DiffusionPolicy(TINY_DP, FEATS, stats)
    pol = ILPolicy(model, identity, seed=1)
    calls = []
    real = model.predict_chunk

    def spy(obs, generator=None):
        calls.append({k: v.clone() for k, v in obs.items()})
        return real(obs, generator)

    monkeypatch.setattr(model, "predict_chunk", spy)
    obs = [obs_batch(3, s) for s in range(5)]
    for t in range(2):
        assert pol.act(obs[t], {}).shape == (3, 3)
    assert len(calls) == 1 and calls[0][STATE].shape == (3, 2, 2)  # one plan, 4 actions
    torch.testing.assert_close(calls[0][STATE][:, 0], obs[0][STATE])  # first obs fills history
    torch.testing.assert_close(calls[0][STATE][:, 1], obs[0][STATE])
    pol.reset(torch.tensor([False, True, False]))
    pol.act(obs[2], {})
    assert len(calls) == 2 and calls[1][STATE].shape == (1, 2, 2)  # only env 1 replans
    torch.testing.assert_close(calls[1][STATE][0, 0], obs[2][STATE][1])  # its history restarted
    torch.testing.assert_close(calls[1][STATE][0, 1], obs[2][STATE][1])
    hist = pol.history[STATE].buf  # the others kept theirs
    torch.testing.assert_close(hist[[0, 2]], torch.stack([obs[1][STATE], obs[2][STATE]], 1)[[0, 2]])
    pol.act(obs[3], {})
    assert len(calls) == 2
    pol.act(obs[4], {})  # envs 0 and 2 used their 4 actions: they replan together
    assert len(calls) == 3 and calls[2][STATE].shape == (2, 2, 2)
    torch.testing.assert_close(calls[2][STATE][:, 1], obs[4][STATE][[0, 2]])


@pytest.mark.parametrize("scheduler,steps", [("ddpm", None), ("ddim", 5)])
def test_diffusion_sampling_shapes_and_seeded(scheduler, steps):
    torch.manual_seed(0)
    stats = {
        CAM: {"mean": torch.full((1, 1, 1), 0.3), "std": torch.full((1, 1, 1), 0.2)},
        STATE: {"min": -torch.ones(2), "max": torch.ones(2)},
        "action": {"min": -2 * torch.ones(3), "max": 2 * torch.ones(3)},
    }
    cfg = DiffusionConfig(
        **{**TINY_DP.__dict__, "scheduler": scheduler, "num_inference_steps": steps}
    )
    model = DiffusionPolicy(cfg, FEATS, stats)
    hist = {k: torch.stack([v, v], 1) for k, v in obs_batch(2, 0).items()}
    a = model.predict_chunk(hist, torch.Generator().manual_seed(3))
    b = model.predict_chunk(hist, torch.Generator().manual_seed(3))
    assert a.shape == (2, 4, 3) and torch.equal(a, b)
    assert a.abs().max() <= 2.0 + 1e-5  # clip_sample keeps normalised actions in [-1, 1]


def test_config_constraints():
    with pytest.raises(ValueError, match="n_action_steps"):
        ACTConfig(chunk_size=4, n_action_steps=5)
    with pytest.raises(ValueError, match="divisible"):
        DiffusionConfig(horizon=10)
    with pytest.raises(ValueError, match="n_action_steps"):
        DiffusionConfig(horizon=16, n_obs_steps=2, n_action_steps=16)
    assert DiffusionConfig().drop_n_last_frames == 7  # 16 - 8 - 2 + 1
    assert ACTConfig.paper().dim_feedforward == 3200 and ACTConfig.paper().kl_weight == 10.0
