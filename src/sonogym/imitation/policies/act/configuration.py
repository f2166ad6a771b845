"""ACT's configuration (``ACTConfig``): architecture, inference, optimisation and
normalisation settings, with units and constraints."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

from sonogym.imitation.policies.base import ILConfig
from sonogym.imitation.processor import ACTION_KEY, PolicyFeatures


@dataclass(frozen=True)
class ACTConfig(ILConfig):
    """ACT hyperparameters. ``paper()``: LeRobot's ACT defaults (what SonoGym trained with),
    with temporal ensembling (the paper's); ``cpu()``: a small model that trains on 2 CPU
    cores in minutes."""

    #: about 1.3 M parameters: 4 small ResNet stages, a 128-wide transformer, chunk 20
    CPU_PRESET: ClassVar[dict[str, Any]] = dict(
        chunk_size=20,
        n_action_steps=20,
        backbone_widths=(16, 32, 64, 128),
        backbone_blocks=(1, 1, 1, 1),
        dim_model=128,
        n_heads=4,
        dim_feedforward=512,
        n_encoder_layers=2,
        n_vae_encoder_layers=2,
        latent_dim=16,
        lr=1e-4,
        lr_backbone=1e-4,
    )

    # chunking and inference
    chunk_size: int = 100  # actions predicted per forward pass (env steps), >= 1
    n_action_steps: int = 100  # actions executed per chunk without ensembling, 1..chunk_size
    temporal_ensemble_coeff: float | None = 0.01  # w_i = exp(-coeff i), i = 0 oldest; None:
    # execute n_action_steps of each chunk (the reference's play configs: None; paper: on)
    # image encoder
    image_size: tuple[int, int] | None = (
        None  # (H, W) px the images are resampled to; None: as stored
    )
    backbone_widths: tuple[int, ...] = (64, 128, 256, 512)  # channels per ResNet stage
    backbone_blocks: tuple[int, ...] = (2, 2, 2, 2)  # basic blocks per stage (ResNet-18: 2)
    backbone_norm: str = "group"  # "group" (GroupNorm, channels / 16 groups) or "batch"
    # transformer
    dim_model: int = 512  # token width, multiple of 4 and of n_heads
    n_heads: int = 8  # attention heads
    dim_feedforward: int = 3200  # hidden width of the feed-forward blocks
    feedforward_activation: str = "relu"  # "relu" or "gelu"
    n_encoder_layers: int = 4  # transformer encoder layers, >= 1
    n_decoder_layers: int = 1  # decoder layers (LeRobot: 1; the original ACT used 1 of its 7)
    pre_norm: bool = False  # LayerNorm before (True) or after (False) each block
    dropout: float = 0.1  # dropout probability in the transformer, [0, 1)
    # VAE
    use_vae: bool = True  # train as a CVAE (False: plain L1 regression, z absent)
    latent_dim: int = 32  # size of z
    n_vae_encoder_layers: int = 4  # layers of the VAE's transformer encoder
    kl_weight: float = 10.0  # weight of the KL term in the loss, >= 0
    # optimisation (AdamW)
    lr: float = 1e-5  # learning rate of everything but the image encoder (per step)
    lr_backbone: float = 1e-5  # learning rate of the image encoder
    weight_decay: float = 1e-4  # AdamW weight decay
    grad_clip_norm: float = 10.0  # gradient-norm clip (LeRobot's default)
    # normalisation (processor)
    visual_norm: str = "mean_std"  # images: "mean_std", "min_max" or "identity"
    state_norm: str = "mean_std"
    action_norm: str = "mean_std"

    def __post_init__(self) -> None:
        if self.chunk_size < 1 or not 1 <= self.n_action_steps <= self.chunk_size:
            raise ValueError(
                f"need chunk_size >= 1 and 1 <= n_action_steps <= chunk_size, got "
                f"{self.chunk_size}, {self.n_action_steps}"
            )
        if self.dim_model % 4 or self.dim_model % self.n_heads:
            raise ValueError(f"dim_model {self.dim_model}: multiple of 4 and of n_heads")
        if min(self.n_encoder_layers, self.n_decoder_layers, self.n_vae_encoder_layers) < 1:
            raise ValueError("every transformer needs at least one layer")
        if not 0 <= self.dropout < 1 or self.kl_weight < 0:
            raise ValueError("dropout in [0, 1) and kl_weight >= 0 required")
        if self.feedforward_activation not in ("relu", "gelu"):
            raise ValueError(f"feedforward_activation {self.feedforward_activation!r}: relu|gelu")

    def delta_indices(self, features: PolicyFeatures) -> dict[str, list[int]]:
        """Dataset offsets: the current observation, the next chunk_size actions (ACT trains on
        every frame: ``action_is_pad`` marks chunks past the episode end)."""
        return {ACTION_KEY: list(range(self.chunk_size))}

    @property
    def chunk_length(self) -> int:
        return self.chunk_size
