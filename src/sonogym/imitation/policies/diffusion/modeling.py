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

import math
from collections.abc import Callable

import torch
import torch.nn.functional as F
from torch import nn

from sonogym.imitation.policies.base import ILModel, Stats
from sonogym.imitation.policies.diffusion.configuration import DiffusionConfig
from sonogym.imitation.processor import ACTION_KEY, STATE_KEY, PolicyFeatures
from sonogym.imitation.vision import ResNetEncoder, SpatialSoftmax, crop, resize


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


class DiffusionPolicy(ILModel):
    """Diffusion Policy over a dataset's features (see the module doc)."""

    config: DiffusionConfig

    def __init__(self, config: DiffusionConfig, features: PolicyFeatures, stats: Stats) -> None:
        super().__init__(config, features, stats)
        from diffusers import DDIMScheduler, DDPMScheduler

        c = config
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

    def loss(
        self, nb: dict[str, torch.Tensor], generator: torch.Generator | None
    ) -> tuple[torch.Tensor, dict[str, float]]:
        """Noise-prediction MSE of a normalised batch (observations (B, n_obs_steps, ...),
        action (B, horizon, A)). Returns (loss, {"mse": ..})."""
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
            err = err * ~nb[ACTION_KEY + "_is_pad"][..., None]
        loss = err.mean()
        return loss, {"mse": float(loss.detach())}

    def predict(
        self, obs: dict[str, torch.Tensor], generator: torch.Generator | None
    ) -> torch.Tensor:
        """The n_action_steps normalised actions (B, n_action_steps, A) to execute from the
        current step, denoised from ``generator``'s noise, for normalised observation
        histories (B, n_obs_steps, ...) (oldest first)."""
        c = self.config
        cond = self._global_cond(obs, None)
        b = cond.shape[0]
        x = torch.randn(
            b, c.horizon, self.features.action_dim, generator=generator, device=cond.device
        )
        self.sampler.set_timesteps(c.num_inference_steps or c.num_train_timesteps)
        for t in self.sampler.timesteps:
            steps = torch.full((b,), int(t), device=cond.device, dtype=torch.long)
            eps = self.unet(x, steps, cond)
            x = self.sampler.step(eps, t, x, generator=generator).prev_sample
        start = c.n_obs_steps - 1
        return x[:, start : start + c.n_action_steps]

    def optimizer(self) -> torch.optim.Optimizer:
        c = self.config
        return torch.optim.Adam(
            self.parameters(), lr=c.lr, betas=c.betas, eps=c.eps, weight_decay=c.weight_decay
        )

    def lr_lambda(self, total_steps: int) -> Callable[[int], float]:
        """Linear warm-up over ``lr_warmup_steps``, then cosine decay to 0 at
        ``total_steps``."""
        warm = self.config.lr_warmup_steps

        def f(step: int) -> float:
            if step < warm:
                return (step + 1) / warm
            progress = (step - warm) / max(1, total_steps - warm)
            return max(0.0, 0.5 * (1.0 + math.cos(math.pi * min(progress, 1.0))))

        return f
