"""Diffusion Policy's configuration (``DiffusionConfig``): observation history, horizon,
encoder, U-Net, noise scheduler, optimisation and normalisation settings, with units and
constraints."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

from sonogym.imitation.policies.base import ILConfig
from sonogym.imitation.processor import ACTION_KEY, STATE_KEY, PolicyFeatures


@dataclass(frozen=True)
class DiffusionConfig(ILConfig):
    """Diffusion Policy hyperparameters. ``paper()``: LeRobot's defaults with SonoGym's
    n_obs_steps 2 / horizon 16 / n_action_steps 8 and U-Net down dims 512/1024/2048; ``cpu()``:
    a small model that trains on 2 CPU cores."""

    #: about 4 M parameters; DDIM with 10 inference steps
    CPU_PRESET: ClassVar[dict[str, Any]] = dict(
        backbone_widths=(16, 32, 64, 128),
        backbone_blocks=(1, 1, 1, 1),
        num_keypoints=16,
        down_dims=(64, 128, 256),
        diffusion_step_embed_dim=64,
        scheduler="ddim",
        num_inference_steps=10,
        lr_warmup_steps=100,
    )

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

    @property
    def observation_steps(self) -> int:
        return self.n_obs_steps

    @property
    def chunk_length(self) -> int:
        return self.n_action_steps
