"""Diffusion Policy (Chi et al. 2023), LeRobot 0.4's U-Net variant.

Observation encoder: each camera's image (optionally resampled and cropped: random crops in
training, centre crops at inference) goes through a shared ResNet-style trunk, spatial-softmax
keypoints (K (x, y) pairs) and Linear(2K, 2K) + ReLU; with the state this gives one feature
vector per observation step, and the n_obs_steps vectors, flattened, are the global
condition. Noise model: a 1-D conditional U-Net over the action sequence (B, horizon, A):
per level two residual blocks (Conv1d k, GroupNorm, Mish) with FiLM conditioning (scale and
bias from [sinusoidal step embedding -> MLP, global condition]), strided-conv downsampling,
two middle blocks, transposed-conv upsampling with skip connections, a final conv block and a
1x1 conv to A channels. Training: DDPM epsilon prediction, MSE between the true and the
predicted noise at a uniformly drawn step (diffusers' ``DDPMScheduler``: 100 steps,
squaredcos_cap_v2, betas 1e-4..0.02, samples clipped to ±1). Inference: start from Gaussian
noise and denoise with the DDPM scheduler over all train steps, or with ``DDIMScheduler`` over
``num_inference_steps`` (deterministic for eta = 0, much faster; the CPU preset uses 10).

Actions of a sample cover steps t - n_obs_steps + 1 .. t - n_obs_steps + horizon; the policy
executes the n_action_steps starting at step t. Normalisation (LeRobot's DP mapping): images
mean_std, state and action min_max (actions in [-1, 1], which the ±1 sample clip assumes).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from sonogym.imitation.processor import (
    ACTION_KEY,
    STATE_KEY,
    Normalizer,
    PolicyFeatures,
    norm_modes,
)
from sonogym.imitation.vision import ResNetEncoder, SpatialSoftmax, crop, resize


@dataclass(frozen=True)
class DiffusionConfig:
    """Diffusion Policy hyperparameters. ``paper()``: LeRobot's defaults with SonoGym's
    n_obs_steps 2 / horizon 16 / n_action_steps 8 and U-Net down dims 512/1024/2048; ``cpu()``:
    a small model that trains on 2 CPU cores."""

    n_obs_steps: int = 2  # observation steps conditioning a prediction (history length), >= 1
    horizon: int = 16  # actions per predicted sequence (env steps), divisible by 2^(levels-1)
    n_action_steps: int = 8  # actions executed per prediction, <= horizon - n_obs_steps + 1
    # image encoder
    image_size: tuple[int, int] | None = (
        None  # (H, W) px images are resampled to; None: stored size
    )
    crop_shape: tuple[int, int] | None = None  # (H, W) px crop after resampling; None: no crop
    crop_is_random: bool = True  # random crops in training (centre crops at inference)
    backbone_widths: tuple[int, ...] = (64, 128, 256, 512)  # channels per ResNet stage
    backbone_blocks: tuple[int, ...] = (2, 2, 2, 2)  # basic blocks per stage (ResNet-18: 2)
    backbone_norm: str = "group"  # "group" (LeRobot's use_group_norm) or "batch"
    num_keypoints: int = 32  # spatial-softmax keypoints per camera (feature = 2 K per camera)
    # U-Net
    down_dims: tuple[int, ...] = (512, 1024, 2048)  # channels per U-Net level
    kernel_size: int = 5  # Conv1d kernel (odd)
    n_groups: int = 8  # GroupNorm groups in the conv blocks (divides every down dim)
    diffusion_step_embed_dim: int = 128  # width of the step embedding
    use_film_scale_modulation: bool = True  # FiLM scale and bias (False: bias only)
    # noise scheduler (diffusers)
    num_train_timesteps: int = 100  # diffusion steps M
    beta_schedule: str = "squaredcos_cap_v2"
    beta_start: float = 1e-4
    beta_end: float = 0.02
    clip_sample: bool = True  # clip denoised samples to ±clip_sample_range
    clip_sample_range: float = 1.0
    scheduler: str = "ddpm"  # inference sampler: "ddpm" or "ddim"
    num_inference_steps: int | None = (
        None  # denoising steps at inference; None: num_train_timesteps
    )
    do_mask_loss_for_padding: bool = False  # leave padded actions out of the loss (LeRobot: off)
    # optimisation (Adam, cosine schedule with linear warm-up)
    lr: float = 1e-4  # peak learning rate (per step)
    betas: tuple[float, float] = (0.95, 0.999)
    eps: float = 1e-8
    weight_decay: float = 1e-6
    lr_warmup_steps: int = 500  # linear warm-up (optimiser steps)
    grad_clip_norm: float = 10.0
    # normalisation (processor)
    visual_norm: str = "mean_std"
    state_norm: str = "min_max"
    action_norm: str = "min_max"

    def __post_init__(self) -> None:
        if self.n_obs_steps < 1 or self.horizon < 1:
            raise ValueError("n_obs_steps and horizon must be >= 1")
        if not 1 <= self.n_action_steps <= self.horizon - self.n_obs_steps + 1:
            raise ValueError(
                f"n_action_steps {self.n_action_steps} must lie in 1..horizon - n_obs_steps + 1 "
                f"= {self.horizon - self.n_obs_steps + 1}"
            )
        down = 2 ** (len(self.down_dims) - 1)
        if self.horizon % down:
            raise ValueError(f"horizon {self.horizon} must be divisible by {down} (U-Net levels)")
        if self.kernel_size % 2 == 0 or any(d % self.n_groups for d in self.down_dims):
            raise ValueError("kernel_size must be odd and n_groups must divide every down dim")
        if self.scheduler not in ("ddpm", "ddim"):
            raise ValueError(f"scheduler {self.scheduler!r}: 'ddpm' or 'ddim'")
        steps = self.num_inference_steps
        if steps is not None and not 1 <= steps <= self.num_train_timesteps:
            raise ValueError(f"num_inference_steps {steps} must lie in 1..num_train_timesteps")

    @classmethod
    def paper(cls, **kw) -> DiffusionConfig:
        return cls(**kw)

    @classmethod
    def cpu(cls, **kw) -> DiffusionConfig:
        """About 4 M parameters; DDIM with 10 inference steps."""
        base = dict(
            backbone_widths=(16, 32, 64, 128),
            backbone_blocks=(1, 1, 1, 1),
            num_keypoints=16,
            down_dims=(64, 128, 256),
            diffusion_step_embed_dim=64,
            scheduler="ddim",
            num_inference_steps=10,
            lr_warmup_steps=100,
        )
        return cls(**{**base, **kw})

    def delta_indices(self, features: PolicyFeatures) -> dict[str, list[int]]:
        obs = list(range(1 - self.n_obs_steps, 1))
        d = {k: obs for k in features.image_keys}
        if features.state_dim:
            d[STATE_KEY] = obs
        d[ACTION_KEY] = list(range(1 - self.n_obs_steps, 1 - self.n_obs_steps + self.horizon))
        return d

    @property
    def drop_n_last_frames(self) -> int:
        """Frames at each episode's end not used as samples (LeRobot's DP sampler)."""
        return max(0, self.horizon - self.n_action_steps - self.n_obs_steps + 1)


def _sine_embedding(t: torch.Tensor, dim: int) -> torch.Tensor:
    """(B,) diffusion steps -> (B, dim) [sin, cos] embedding."""
    half = dim // 2
    freq = torch.exp(-math.log(10000.0) * torch.arange(half, device=t.device) / (half - 1))
    ang = t.float()[:, None] * freq[None]
    return torch.cat([ang.sin(), ang.cos()], dim=-1)


class _ConvBlock(nn.Sequential):
    def __init__(self, c_in: int, c_out: int, k: int, groups: int) -> None:
        super().__init__(
            nn.Conv1d(c_in, c_out, k, padding=k // 2), nn.GroupNorm(groups, c_out), nn.Mish()
        )


class _ResBlock(nn.Module):
    """Conv block, FiLM by the condition, conv block, plus a (1x1-projected) residual."""

    def __init__(self, c_in: int, c_out: int, cond_dim: int, k: int, groups: int, scale: bool):
        super().__init__()
        self.conv1 = _ConvBlock(c_in, c_out, k, groups)
        self.conv2 = _ConvBlock(c_out, c_out, k, groups)
        self.scale = scale
        self.cond = nn.Sequential(nn.Mish(), nn.Linear(cond_dim, c_out * (2 if scale else 1)))
        self.skip = nn.Conv1d(c_in, c_out, 1) if c_in != c_out else nn.Identity()

    def forward(self, x: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        h = self.conv1(x)
        film = self.cond(cond)[..., None]
        if self.scale:
            s, b = film.chunk(2, dim=1)
            h = s * h + b
        else:
            h = h + film
        return self.conv2(h) + self.skip(x)


class ConditionalUnet1d(nn.Module):
    """Noise prediction eps(x_m, m, cond): (B, T, A), (B,), (B, G) -> (B, T, A)."""

    def __init__(self, c: DiffusionConfig, action_dim: int, global_cond_dim: int) -> None:
        super().__init__()
        e = c.diffusion_step_embed_dim
        self.embed_dim = e
        self.step_mlp = nn.Sequential(nn.Linear(e, 4 * e), nn.Mish(), nn.Linear(4 * e, e))
        cond = e + global_cond_dim
        k, g, s = c.kernel_size, c.n_groups, c.use_film_scale_modulation
        dims = [action_dim, *c.down_dims]
        pairs = list(zip(dims[:-1], dims[1:], strict=True))
        self.down = nn.ModuleList()
        for i, (a, b) in enumerate(pairs):
            last = i == len(pairs) - 1
            self.down.append(
                nn.ModuleList(
                    [
                        _ResBlock(a, b, cond, k, g, s),
                        _ResBlock(b, b, cond, k, g, s),
                        nn.Conv1d(b, b, 3, 2, 1) if not last else nn.Identity(),
                    ]
                )
            )
        m = c.down_dims[-1]
        self.mid = nn.ModuleList([_ResBlock(m, m, cond, k, g, s), _ResBlock(m, m, cond, k, g, s)])
        self.up = nn.ModuleList()
        for a, b in reversed(pairs[1:]):  # every up level doubles the length back
            self.up.append(
                nn.ModuleList(
                    [
                        _ResBlock(2 * b, a, cond, k, g, s),
                        _ResBlock(a, a, cond, k, g, s),
                        nn.ConvTranspose1d(a, a, 4, 2, 1),
                    ]
                )
            )
        self.final = nn.Sequential(
            _ConvBlock(c.down_dims[0], c.down_dims[0], k, g),
            nn.Conv1d(c.down_dims[0], action_dim, 1),
        )

    def forward(self, x: torch.Tensor, steps: torch.Tensor, global_cond: torch.Tensor):
        cond = torch.cat([self.step_mlp(_sine_embedding(steps, self.embed_dim)), global_cond], -1)
        h = x.transpose(1, 2)  # (B, A, T)
        skips = []
        for r1, r2, down in self.down:
            h = r2(r1(h, cond), cond)
            skips.append(h)
            h = down(h)
        for r in self.mid:
            h = r(h, cond)
        for r1, r2, up in self.up:
            h = torch.cat([h, skips.pop()], dim=1)
            h = up(r2(r1(h, cond), cond))
        return self.final(h).transpose(1, 2)


class _RgbEncoder(nn.Module):
    """(B, C, H, W) -> (B, 2 K): trunk, spatial softmax, Linear + ReLU."""

    def __init__(self, c: DiffusionConfig, shape: tuple[int, int, int]) -> None:
        super().__init__()
        ch, h, w = shape
        self.image_size = c.image_size
        self.crop_shape = c.crop_shape
        self.crop_is_random = c.crop_is_random
        hw = c.crop_shape or c.image_size or (h, w)
        self.trunk = ResNetEncoder(ch, c.backbone_widths, c.backbone_blocks, c.backbone_norm)
        fc, fh, fw = self.trunk.out_shape(ch, *hw)
        self.pool = SpatialSoftmax(fc, fh, fw, c.num_keypoints)
        self.out = nn.Linear(2 * c.num_keypoints, 2 * c.num_keypoints)
        self.dim = 2 * c.num_keypoints

    def forward(self, x: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
        x = resize(x, self.image_size)
        if self.crop_shape is not None:
            random = self.training and self.crop_is_random
            x = crop(x, self.crop_shape, generator if random else None)
        return F.relu(self.out(self.pool(self.trunk(x)).flatten(1)))


class DiffusionPolicy(nn.Module):
    """Diffusion Policy over a dataset's features (see the module doc)."""

    name = "diffusion"

    def __init__(
        self,
        config: DiffusionConfig,
        features: PolicyFeatures,
        stats: dict[str, dict[str, torch.Tensor]],
    ) -> None:
        super().__init__()
        from diffusers import DDIMScheduler, DDPMScheduler

        c = self.config = config
        self.features = features
        if not features.image_keys and not features.state_dim:
            raise ValueError("Diffusion Policy needs image features or observation.state")
        self.normalizer = Normalizer(
            stats, norm_modes(features, c.visual_norm, c.state_norm, c.action_norm)
        )
        feat = features.state_dim
        if features.image_keys:
            shapes = set(features.image_shapes)
            if len(shapes) != 1:
                raise ValueError(f"cameras differ in shape {shapes}: one shared encoder needs one")
            self.rgb = _RgbEncoder(c, features.image_shapes[0])
            feat += self.rgb.dim * len(features.image_keys)
        self.unet = ConditionalUnet1d(c, features.action_dim, feat * c.n_obs_steps)
        kw = dict(
            num_train_timesteps=c.num_train_timesteps,
            beta_start=c.beta_start,
            beta_end=c.beta_end,
            beta_schedule=c.beta_schedule,
            clip_sample=c.clip_sample,
            clip_sample_range=c.clip_sample_range,
            prediction_type="epsilon",
        )
        self.train_scheduler = DDPMScheduler(**kw)
        self.sampler = DDIMScheduler(**kw) if c.scheduler == "ddim" else DDPMScheduler(**kw)

    def _global_cond(self, nb: dict[str, torch.Tensor], generator) -> torch.Tensor:
        """(B, n_obs_steps * feature) from normalised (B, n_obs_steps, ...) observations."""
        parts = []
        if self.features.state_dim:
            parts.append(nb[STATE_KEY])
        if self.features.image_keys:
            b, n = nb[self.features.image_keys[0]].shape[:2]
            imgs = torch.stack([nb[k] for k in self.features.image_keys], dim=2)  # B n cams C H W
            f = self.rgb(imgs.flatten(0, 2), generator)
            parts.append(f.reshape(b, n, -1))
        return torch.cat(parts, dim=-1).flatten(1)

    def compute_loss(
        self, batch: dict[str, torch.Tensor], generator: torch.Generator | None = None
    ) -> tuple[torch.Tensor, dict[str, float]]:
        """Noise-prediction MSE of a dataset batch (observations (B, n_obs_steps, ...), action
        (B, horizon, A)). Returns (loss, {"mse": ..})."""
        nb = self.normalizer(batch)
        cond = self._global_cond(nb, generator)
        a = nb[ACTION_KEY]
        dev = a.device
        noise = torch.randn(a.shape, generator=generator, device=dev)
        steps = torch.randint(
            0, self.config.num_train_timesteps, (a.shape[0],), generator=generator, device=dev
        )
        noisy = self.train_scheduler.add_noise(a, noise, steps)
        err = F.mse_loss(self.unet(noisy, steps, cond), noise, reduction="none")
        if self.config.do_mask_loss_for_padding:
            err = err * ~batch[ACTION_KEY + "_is_pad"][..., None]
        loss = err.mean()
        return loss, {"mse": float(loss.detach())}

    @torch.no_grad()
    def predict_chunk(
        self, obs: dict[str, torch.Tensor], generator: torch.Generator | None = None
    ) -> torch.Tensor:
        """The n_action_steps actions (B, n_action_steps, A), dataset units, to execute from the
        current step, for raw observation histories (B, n_obs_steps, ...) (oldest first)."""
        c = self.config
        was = self.training
        self.eval()
        nb = self.normalizer(obs)
        cond = self._global_cond(nb, None)
        b = cond.shape[0]
        x = torch.randn(
            b, c.horizon, self.features.action_dim, generator=generator, device=cond.device
        )
        self.sampler.set_timesteps(c.num_inference_steps or c.num_train_timesteps)
        for t in self.sampler.timesteps:
            steps = torch.full((b,), int(t), device=cond.device, dtype=torch.long)
            eps = self.unet(x, steps, cond)
            x = self.sampler.step(eps, t, x, generator=generator).prev_sample
        self.train(was)
        start = c.n_obs_steps - 1
        return self.normalizer.unnormalize(ACTION_KEY, x[:, start : start + c.n_action_steps])

    def optimizer(self) -> torch.optim.Optimizer:
        c = self.config
        return torch.optim.Adam(
            self.parameters(), lr=c.lr, betas=c.betas, eps=c.eps, weight_decay=c.weight_decay
        )


def config_from_dict(d: dict) -> DiffusionConfig:
    names = {f.name for f in dataclasses.fields(DiffusionConfig)}
    kw = {k: tuple(v) if isinstance(v, list) else v for k, v in d.items() if k in names}
    return DiffusionConfig(**kw)
