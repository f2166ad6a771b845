"""How well the navigation observation locates the goal: a supervised probe of what an image
policy could learn from the same training phantoms, given the answer as a label. The figures
in benchmarks/README.md ("Navigation: how much of the goal the image shows") come from

    python benchmarks/navigation_observability.py [--history 10]

It records the ``us_heading`` observation (image average-pooled 4x by default, as the ``cpu``
preset's policy sees it, and the heading) on a random walk pulled toward {G} (the expert's command
x 0.3 plus Gaussian noise of 1.5 action units per step: a stationary spread of ~13 mm per axis
and ~25 deg in yaw, the region a policy ends in), then fits an encoder (by default the
shipped policy's, ``net="lean"``) with a linear head to the goal seen from the probe (x_U,
y_U in mm and the rotation about z_U) by supervised regression on the training phantoms
(with imaging randomisation), and reports, on frames within 20 mm of {G}:

* the 2-D error of the regressed goal (mean, median, share within 10 mm) and per axis
  (x_U: across the image, y_U: out of plane, cranio-caudal at the goal's yaw);
* the same for the **zero predictor** ("the goal is where the probe is"), which knows only
  that the probe is near {G}: a regressor that does no better read nothing from the image.

``--history L`` adds the frame L steps earlier, its heading and the probe's motion since
(the arm knows its own pose), to measure what a short memory adds. ``--net`` (a network size
of ``sonogym.agents.networks``) and ``--pool`` (the image's average pooling) measure what a
larger encoder or a finer image adds. ``--tilt`` adds the beam's tilt from the patient's
vertical (``observe_tilt``; with ``--history``, at both frames): what the arm's pose says about
a patient rolled on the table. The model is the last epoch's (no selection on the test
sets).
"""

from __future__ import annotations

import argparse
import math
import time

import torch
import torch.nn.functional as F
from torch import nn

from sonogym.agents.adapter import ObsLayout
from sonogym.agents.networks import NET_SIZES, Encoder
from sonogym.envs.navigation import expert, goal_in_probe
from sonogym.envs.options import parse_patients
from sonogym.envs.registry import make_vec

ENVS = 64
POOL = 4  # the cpu preset's obs_downsample
EXPERT_PULL, NOISE = 0.3, 1.5  # action units
NEAR = 0.02  # m: frames whose probe lies this close to {G} across the skin are scored
# regression targets in units of order 1: goal x_U, y_U per 10 mm, rotation per 0.5 rad
TARGET_SCALE = torch.tensor([100.0, 100.0, 2.0])


def record(
    patients: list, steps: int, randomise: bool, seed: int, pool: int = POOL
) -> dict[str, torch.Tensor]:
    """Per step and env (index t * ENVS + env): pooled image, heading, beam tilt, goal seen from
    the probe (x_U, y_U, rotation about z_U), the probe's (x, y) in {G} and its step in the
    episode."""
    env = make_vec(
        "navigation", ENVS, patients=patients, obs_mode="us_heading",
        imaging_randomization=randomise, observe_tilt=True,
    ).unwrapped  # fmt: skip
    g = torch.Generator().manual_seed(seed)
    obs, info = env.reset(seed=seed)
    rows = {k: [] for k in ("image", "heading", "tilt", "goal", "probe", "step")}
    for _ in range(steps):
        p, q = info["state"][:, :3], info["state"][:, 3:]
        goal_u = goal_in_probe(info["state"])
        rows["image"].append(F.avg_pool2d(obs["image"].float(), pool).half())
        rows["heading"].append(obs["heading"].float())
        rows["tilt"].append(obs["tilt"].float())
        rows["goal"].append(torch.stack([goal_u[:, 0], goal_u[:, 1], q[:, 2]], -1).float())
        rows["probe"].append(p[:, :2].float())  # across the skin: z_G is the beam
        # the step counter is 0 on a reset frame, whose info still holds the ended episode
        rows["step"].append(env.episode_length_buf.clone())
        act = expert(env, info) * EXPERT_PULL
        act = act + NOISE * torch.randn(ENVS, 3, generator=g)
        obs, _, _, _, info = env.step(act.clamp(-2.0, 2.0))
    env.close()
    return {k: torch.cat(v) for k, v in rows.items()}


def samples(
    d: dict, lag: int, tilt: bool = False
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Flat inputs, scaled targets and each frame's distance to {G} (m); with ``lag`` > 0 only
    frames whose episode is at least ``lag`` steps old; ``tilt`` adds the beam's tilt."""
    i = torch.arange(lag * ENVS, len(d["step"]))
    j = i - lag * ENVS
    ok = (d["step"][i] - d["step"][j] == lag) & (d["step"][i] > 0)
    i, j = i[ok], j[ok]
    frames = [i, j] if lag else [i]

    def at_frames(key: str) -> torch.Tensor:  # this frame's entry, then the earlier frame's
        return torch.cat([d[key][k].float() for k in frames], 1)

    parts = [at_frames("heading"), at_frames("image").flatten(1)]
    if lag:
        parts.append((d["probe"][i] - d["probe"][j]) * 100.0)  # motion per 10 mm
    if tilt:
        parts.append(at_frames("tilt"))
    return torch.cat(parts, 1), d["goal"][i] * TARGET_SCALE, d["probe"][i].norm(dim=1)


def layout(d: dict, lag: int, tilt: bool = False) -> ObsLayout:
    h, w = d["image"].shape[-2:]
    frames = 2 if lag else 1
    keys, shapes = ["heading", "image"], [(2 * frames,), (frames, h, w)]
    if lag:
        keys, shapes = keys + ["motion"], shapes + [(2,)]
    if tilt:
        keys, shapes = keys + ["tilt"], shapes + [(2 * frames,)]
    return ObsLayout(tuple(keys), tuple(shapes))


def fit(
    x: torch.Tensor, y: torch.Tensor, lay: ObsLayout, epochs: int, seed: int, net: str = "lean"
) -> nn.Module:
    torch.manual_seed(seed)
    enc = Encoder("navigation", lay, net)
    model = nn.Sequential(enc, nn.Linear(enc.out_features, 3))
    opt = torch.optim.Adam(model.parameters(), 3e-4)
    for _ in range(epochs):
        for idx in torch.randperm(len(x)).split(256):
            loss = F.smooth_l1_loss(model(x[idx]), y[idx])
            opt.zero_grad()
            loss.backward()
            opt.step()
    return model.eval()


def score(model: nn.Module, x, y, dist) -> dict[str, float]:
    with torch.no_grad():
        pred = torch.cat([model(c) for c in x.split(2048)])
    near = dist < NEAR
    row = {"frames": int(near.sum())}
    for name, err in (("regressor", pred - y), ("zero", -y)):
        mm = err[near, :2] * 10.0  # target units are 10 mm
        d = mm.norm(dim=1)
        row |= {
            f"{name}_mean": float(d.mean()), f"{name}_median": float(d.median()),
            f"{name}_within10": float((d < 10).float().mean() * 100),
            f"{name}_x": float(mm[:, 0].abs().mean()), f"{name}_y": float(mm[:, 1].abs().mean()),
            f"{name}_yaw_deg": float(err[near, 2].abs().mean() / 2 * 180 / math.pi),
        }  # fmt: skip
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--train",
        default="100-131",
        help="training patients: phantom seeds A-B or a subject's variants DIR@A-B",
    )
    ap.add_argument("--held-out", default="5-9", help="held-out phantom seeds A-B")
    ap.add_argument("--real", default="tests/data/totalsegmentator_example")
    ap.add_argument("--steps", type=int, default=1500, help="recorded steps of the training walk")
    ap.add_argument("--test-steps", type=int, default=400)
    ap.add_argument("--epochs", type=int, default=3)
    ap.add_argument("--history", type=int, default=0, help="lag L of the earlier frame (0: none)")
    ap.add_argument(
        "--net", default="lean", choices=list(NET_SIZES), help="encoder size (lean: the shipped's)"
    )
    ap.add_argument("--pool", type=int, default=POOL, help="average pooling of the image")
    ap.add_argument("--tilt", action="store_true", help="add the beam's tilt (observe_tilt)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    t0 = time.process_time()
    train = record(parse_patients([args.train]), args.steps, True, args.seed, args.pool)
    x, y, _ = samples(train, args.history, args.tilt)
    model = fit(x, y, layout(train, args.history, args.tilt), args.epochs, args.seed, args.net)
    print(
        f"history {args.history}, tilt {args.tilt}, net {args.net}, image pooled {args.pool}x, "
        f"{len(x)} training frames from {args.train}, {args.epochs} epochs"
    )
    print("| test | frames | regressor mean / median [mm] | within 10 | x_U | y_U | yaw [deg] | "
          "zero predictor mean / median | within 10 | x_U | y_U |")  # fmt: skip
    print("|---|---:|---|---:|---:|---:|---:|---|---:|---:|---:|")
    tests = {
        # the same phantoms on a new walk without randomisation: what the regressor learned
        f"training patients {args.train}, new walk": parse_patients([args.train]),
        f"held-out phantoms {args.held_out}": parse_patients([args.held_out]),
    }
    if args.real:
        tests["real subject"] = parse_patients([args.real])
    for name, patients in tests.items():
        r = score(
            model,
            *samples(
                record(patients, args.test_steps, False, 1000, args.pool), args.history, args.tilt
            ),
        )
        print(
            f"| {name} | {r['frames']} | {r['regressor_mean']:.1f} / {r['regressor_median']:.1f}"
            f" | {r['regressor_within10']:.0f} % | {r['regressor_x']:.1f} | {r['regressor_y']:.1f}"
            f" | {r['regressor_yaw_deg']:.1f} | {r['zero_mean']:.1f} / {r['zero_median']:.1f} | "
            f"{r['zero_within10']:.0f} % | {r['zero_x']:.1f} | {r['zero_y']:.1f} |",
            flush=True,
        )
    print(f"CPU time {(time.process_time() - t0) / 60:.1f} min")


if __name__ == "__main__":
    main()
