"""ACT: Action Chunking Transformer (Zhao et al. 2023), LeRobot 0.4's architecture.

A conditional VAE. Training: a transformer "VAE encoder" reads [CLS, state, a_t..a_{t+k-1}]
(fixed sine positions, padded actions masked) and gives the posterior N(mu, sigma) of a latent
z; the "decoder" is a DETR-style transformer: its encoder reads [z, state, image tokens]
(learned positions for z and state, 2-D sine positions for the image tokens, one token per
cell of each camera's ResNet feature map), its decoder turns k zero queries with learned
positions into k actions through cross-attention. Loss: L1 on the unpadded actions (mean over
all entries, LeRobot's form) + kl_weight * KL(N(mu, sigma) || N(0, I)) (summed over the latent,
mean over the batch). Inference: z = 0.

Inputs are normalised by the policy's ``Normalizer`` (mean_std by default, LeRobot's ACT
mapping; the reference normalised images with ImageNet statistics because it used a
pretrained ResNet, we have none and use the dataset's).
"""

from __future__ import annotations

import dataclasses
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
from sonogym.imitation.vision import ResNetEncoder, resize, sine_position_1d, sine_position_2d


@dataclass(frozen=True)
class ACTConfig:
    """ACT hyperparameters. ``paper()``: LeRobot's ACT defaults (what SonoGym trained with);
    ``cpu()``: a small model that trains on 2 CPU cores in minutes."""

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

    @classmethod
    def paper(cls, **kw) -> ACTConfig:
        """LeRobot's ACT defaults (SonoGym's ACT runs), with temporal ensembling (paper)."""
        return cls(**kw)

    @classmethod
    def cpu(cls, **kw) -> ACTConfig:
        """About 1.3 M parameters: 4 small ResNet stages, a 128-wide transformer, chunk 20."""
        base = dict(
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
        return cls(**{**base, **kw})

    def delta_indices(self, features: PolicyFeatures) -> dict[str, list[int]]:
        """Dataset offsets: the current observation, the next chunk_size actions."""
        return {ACTION_KEY: list(range(self.chunk_size))}

    @property
    def drop_n_last_frames(self) -> int:
        """ACT trains on every frame (``action_is_pad`` marks chunks past the episode end)."""
        return 0


class _EncoderLayer(nn.Module):
    """Self-attention + feed-forward; positions are added to queries and keys only (DETR)."""

    def __init__(self, c: ACTConfig) -> None:
        super().__init__()
        self.attn = nn.MultiheadAttention(c.dim_model, c.n_heads, c.dropout, batch_first=True)
        self.ff = nn.Sequential(
            nn.Linear(c.dim_model, c.dim_feedforward),
            nn.ReLU() if c.feedforward_activation == "relu" else nn.GELU(),
            nn.Dropout(c.dropout),
            nn.Linear(c.dim_feedforward, c.dim_model),
        )
        self.n1, self.n2 = nn.LayerNorm(c.dim_model), nn.LayerNorm(c.dim_model)
        self.d1, self.d2 = nn.Dropout(c.dropout), nn.Dropout(c.dropout)
        self.pre_norm = c.pre_norm

    def forward(self, x, pos, key_padding_mask=None):
        h = self.n1(x) if self.pre_norm else x
        q = h + pos
        x = x + self.d1(self.attn(q, q, h, key_padding_mask=key_padding_mask)[0])
        if not self.pre_norm:
            x = self.n1(x)
        h = self.n2(x) if self.pre_norm else x
        x = x + self.d2(self.ff(h))
        return x if self.pre_norm else self.n2(x)


class _DecoderLayer(nn.Module):
    def __init__(self, c: ACTConfig) -> None:
        super().__init__()
        self.self_attn = nn.MultiheadAttention(c.dim_model, c.n_heads, c.dropout, batch_first=True)
        self.cross_attn = nn.MultiheadAttention(c.dim_model, c.n_heads, c.dropout, batch_first=True)
        self.ff = nn.Sequential(
            nn.Linear(c.dim_model, c.dim_feedforward),
            nn.ReLU() if c.feedforward_activation == "relu" else nn.GELU(),
            nn.Dropout(c.dropout),
            nn.Linear(c.dim_feedforward, c.dim_model),
        )
        self.norms = nn.ModuleList(nn.LayerNorm(c.dim_model) for _ in range(3))
        self.drops = nn.ModuleList(nn.Dropout(c.dropout) for _ in range(3))
        self.pre_norm = c.pre_norm

    def forward(self, x, pos, memory, memory_pos):
        def block(i, x, f):
            h = self.norms[i](x) if self.pre_norm else x
            x = x + self.drops[i](f(h))
            return x if self.pre_norm else self.norms[i](x)

        x = block(0, x, lambda h: self.self_attn(h + pos, h + pos, h)[0])
        x = block(1, x, lambda h: self.cross_attn(h + pos, memory + memory_pos, memory)[0])
        return block(2, x, self.ff)


class ACTPolicy(nn.Module):
    """ACT over a dataset's features (see the module doc); holds its ``Normalizer``."""

    name = "act"

    def __init__(
        self,
        config: ACTConfig,
        features: PolicyFeatures,
        stats: dict[str, dict[str, torch.Tensor]],
    ) -> None:
        super().__init__()
        c = self.config = config
        self.features = features
        if not features.image_keys and not features.state_dim:
            raise ValueError("ACT needs image features or observation.state as input")
        self.normalizer = Normalizer(
            stats, norm_modes(features, c.visual_norm, c.state_norm, c.action_norm)
        )
        d, a = c.dim_model, features.action_dim
        # VAE encoder
        if c.use_vae:
            self.vae_cls = nn.Embedding(1, d)
            self.vae_state_proj = nn.Linear(features.state_dim, d) if features.state_dim else None
            self.vae_action_proj = nn.Linear(a, d)
            self.vae_layers = nn.ModuleList(_EncoderLayer(c) for _ in range(c.n_vae_encoder_layers))
            self.vae_latent_proj = nn.Linear(d, 2 * c.latent_dim)
            n_vae = 1 + (1 if features.state_dim else 0) + c.chunk_size
            self.register_buffer("vae_pos", sine_position_1d(n_vae, d)[None])
        # image encoder (shared by the cameras) and its projection to tokens
        if features.image_keys:
            channels = {s[0] for s in features.image_shapes}
            if len(channels) != 1:
                raise ValueError(f"cameras differ in channel count {channels}: one shared encoder")
            self.backbone = ResNetEncoder(
                channels.pop(), c.backbone_widths, c.backbone_blocks, c.backbone_norm
            )
            self.img_proj = nn.Conv2d(self.backbone.out_channels, d, 1)
            pos = []
            for s in features.image_shapes:
                hw = c.image_size or s[1:]
                _, fh, fw = self.backbone.out_shape(s[0], *hw)
                pos.append(sine_position_2d(fh, fw, d).flatten(1).T)
            self.register_buffer("img_pos", torch.cat(pos)[None])
        n_1d = 1 + (1 if features.state_dim else 0)
        self.latent_proj = nn.Linear(c.latent_dim, d)
        self.state_proj = nn.Linear(features.state_dim, d) if features.state_dim else None
        self.pos_1d = nn.Embedding(n_1d, d)
        self.encoder = nn.ModuleList(_EncoderLayer(c) for _ in range(c.n_encoder_layers))
        self.encoder_norm = nn.LayerNorm(d) if c.pre_norm else nn.Identity()
        self.decoder = nn.ModuleList(_DecoderLayer(c) for _ in range(c.n_decoder_layers))
        self.decoder_norm = nn.LayerNorm(d)
        self.query_pos = nn.Embedding(c.chunk_size, d)
        self.action_head = nn.Linear(d, a)
        self._reset_parameters()

    def _reset_parameters(self) -> None:
        """Xavier-uniform transformer weights (as ACT/DETR initialise them)."""
        for mod in [
            self.encoder,
            self.decoder,
            *([self.vae_layers] if self.config.use_vae else []),
        ]:
            for p in mod.parameters():
                if p.dim() > 1:
                    nn.init.xavier_uniform_(p)

    def backbone_parameters(self) -> list[nn.Parameter]:
        return list(self.backbone.parameters()) if self.features.image_keys else []

    # --- model ----------------------------------------------------------------------------

    def _encode_images(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """(B, tokens, d) image tokens of all cameras, in image_keys order."""
        toks = []
        for k in self.features.image_keys:
            x = resize(batch[k], self.config.image_size)
            toks.append(self.img_proj(self.backbone(x)).flatten(2).transpose(1, 2))
        return torch.cat(toks, dim=1)

    def _forward(self, batch: dict[str, torch.Tensor], generator: torch.Generator | None = None):
        """Normalised inputs -> (normalised actions (B, k, A), (mu, log_var) or None)."""
        c, f = self.config, self.features
        b = next(iter(batch.values())).shape[0]
        dev = self.action_head.weight.device
        state = batch.get(STATE_KEY) if f.state_dim else None
        mu = log_var = None
        if c.use_vae and ACTION_KEY in batch and self.training:
            toks = [self.vae_cls.weight[None].expand(b, 1, -1)]
            if state is not None:
                toks.append(self.vae_state_proj(state)[:, None])
            toks.append(self.vae_action_proj(batch[ACTION_KEY]))
            x = torch.cat(toks, dim=1)
            pad = torch.zeros(b, x.shape[1], dtype=torch.bool, device=dev)
            if ACTION_KEY + "_is_pad" in batch:
                pad[:, -c.chunk_size :] = batch[ACTION_KEY + "_is_pad"]
            for layer in self.vae_layers:
                x = layer(x, self.vae_pos, key_padding_mask=pad)
            mu, log_var = self.vae_latent_proj(x[:, 0]).chunk(2, dim=-1)
            eps = torch.randn(mu.shape, generator=generator, device=dev)
            z = mu + (0.5 * log_var).exp() * eps
        else:
            z = torch.zeros(b, c.latent_dim, device=dev)
        toks = [self.latent_proj(z)[:, None]]
        if state is not None:
            toks.append(self.state_proj(state)[:, None])
        pos = [self.pos_1d.weight[None].expand(b, -1, -1)]
        if f.image_keys:
            toks.append(self._encode_images(batch))
            pos.append(self.img_pos.expand(b, -1, -1))
        x, p = torch.cat(toks, dim=1), torch.cat(pos, dim=1)
        for layer in self.encoder:
            x = layer(x, p)
        memory = self.encoder_norm(x)
        qpos = self.query_pos.weight[None].expand(b, -1, -1)
        y = torch.zeros_like(qpos)
        for layer in self.decoder:
            y = layer(y, qpos, memory, p)
        actions = self.action_head(self.decoder_norm(y))
        return actions, (None if mu is None else (mu, log_var))

    def compute_loss(
        self, batch: dict[str, torch.Tensor], generator: torch.Generator | None = None
    ) -> tuple[torch.Tensor, dict[str, float]]:
        """Training loss of a dataset batch (raw values; ``action`` (B, k, A) with
        ``action_is_pad`` (B, k)). Returns (loss, {"l1": .., "kl": ..})."""
        nb = self.normalizer(batch)
        pred, post = self._forward(nb, generator)
        pad = batch[ACTION_KEY + "_is_pad"]
        l1 = (F.l1_loss(pred, nb[ACTION_KEY], reduction="none") * ~pad[..., None]).mean()
        logs = {"l1": float(l1.detach())}
        if post is None:
            return l1, logs
        mu, log_var = post
        kl = (-0.5 * (1 + log_var - mu.pow(2) - log_var.exp())).sum(-1).mean()
        logs["kl"] = float(kl.detach())
        return l1 + self.config.kl_weight * kl, logs

    @torch.no_grad()
    def predict_chunk(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        """Actions (B, chunk_size, A) in dataset units for raw observations (images (B, C, H, W)
        in [0, 1], state (B, D)); z = 0."""
        was = self.training
        self.eval()
        pred, _ = self._forward(self.normalizer(obs))
        self.train(was)
        return self.normalizer.unnormalize(ACTION_KEY, pred)

    def optimizer(self) -> torch.optim.Optimizer:
        """AdamW with LeRobot's two parameter groups (image encoder at ``lr_backbone``)."""
        bb = {id(p) for p in self.backbone_parameters()}
        rest = [p for p in self.parameters() if id(p) not in bb and p.requires_grad]
        groups = [{"params": rest}]
        if bb:
            groups.append({"params": self.backbone_parameters(), "lr": self.config.lr_backbone})
        return torch.optim.AdamW(groups, lr=self.config.lr, weight_decay=self.config.weight_decay)


def config_from_dict(d: dict) -> ACTConfig:
    names = {f.name for f in dataclasses.fields(ACTConfig)}
    kw = {k: tuple(v) if isinstance(v, list) else v for k, v in d.items() if k in names}
    return ACTConfig(**kw)
