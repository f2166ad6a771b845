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

import torch
import torch.nn.functional as F
from torch import nn

from sonogym.imitation.policies.act.configuration import ACTConfig
from sonogym.imitation.policies.base import ILModel, Stats
from sonogym.imitation.processor import ACTION_KEY, STATE_KEY, PolicyFeatures
from sonogym.imitation.vision import ResNetEncoder, resize, sine_position_1d, sine_position_2d


def _feed_forward(c: ACTConfig) -> nn.Sequential:
    """A transformer block's feed-forward part: Linear, activation, dropout, Linear."""
    return nn.Sequential(
        nn.Linear(c.dim_model, c.dim_feedforward),
        nn.ReLU() if c.feedforward_activation == "relu" else nn.GELU(),
        nn.Dropout(c.dropout),
        nn.Linear(c.dim_feedforward, c.dim_model),
    )


class _EncoderLayer(nn.Module):
    """Self-attention + feed-forward; positions are added to queries and keys only (DETR)."""

    def __init__(self, c: ACTConfig) -> None:
        super().__init__()
        self.attn = nn.MultiheadAttention(c.dim_model, c.n_heads, c.dropout, batch_first=True)
        self.ff = _feed_forward(c)
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
        self.ff = _feed_forward(c)
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


class ACTPolicy(ILModel):
    """ACT over a dataset's features (see the module doc); holds its ``Normalizer``."""

    config: ACTConfig

    def __init__(self, config: ACTConfig, features: PolicyFeatures, stats: Stats) -> None:
        super().__init__(config, features, stats)
        c = config
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

    def loss(
        self, nb: dict[str, torch.Tensor], generator: torch.Generator | None
    ) -> tuple[torch.Tensor, dict[str, float]]:
        """L1 + kl_weight KL of a normalised batch (``action`` (B, k, A) with
        ``action_is_pad`` (B, k)). Returns (loss, {"l1": .., "kl": ..})."""
        pred, post = self._forward(nb, generator)
        pad = nb[ACTION_KEY + "_is_pad"]
        l1 = (F.l1_loss(pred, nb[ACTION_KEY], reduction="none") * ~pad[..., None]).mean()
        logs = {"l1": float(l1.detach())}
        if post is None:
            return l1, logs
        mu, log_var = post
        kl = (-0.5 * (1 + log_var - mu.pow(2) - log_var.exp())).sum(-1).mean()
        logs["kl"] = float(kl.detach())
        return l1 + self.config.kl_weight * kl, logs

    def predict(
        self, obs: dict[str, torch.Tensor], generator: torch.Generator | None
    ) -> torch.Tensor:
        """Normalised actions (B, chunk_size, A) for normalised observations (images
        (B, C, H, W), state (B, D)); z = 0, so ``generator`` is not used."""
        return self._forward(obs)[0]

    def optimizer(self) -> torch.optim.Optimizer:
        """AdamW with LeRobot's two parameter groups (image encoder at ``lr_backbone``)."""
        bb = {id(p) for p in self.backbone_parameters()}
        rest = [p for p in self.parameters() if id(p) not in bb and p.requires_grad]
        groups = [{"params": rest}]
        if bb:
            groups.append({"params": self.backbone_parameters(), "lr": self.config.lr_backbone})
        return torch.optim.AdamW(groups, lr=self.config.lr, weight_decay=self.config.weight_decay)
