"""RGB frames of env 0 for ``render()`` and the demo's video: NumPy drawing over the envs'
public state (no plotting library). Images are uint8 H x W x 3.

* probe tasks: the ultrasound image beside a top-down view of the back around the goal, with
  the probe's path (red), its footprint (yellow) and the goal (green);
* surgery: the volume's elevation slices side by side beside a side view of the corridor in
  {G} with the drill tip's path.
"""

from __future__ import annotations

import numpy as np
import torch


def pad16(frame: np.ndarray) -> np.ndarray:
    """Pad an RGB frame with black to sides that are multiples of 16 (video codecs)."""
    return np.pad(frame, ((0, (-frame.shape[0]) % 16), (0, (-frame.shape[1]) % 16), (0, 0)))


def gray_rgb(img: torch.Tensor, zoom: int = 1) -> np.ndarray:
    """A 2-D image in [0, 1] -> uint8 RGB, each pixel repeated ``zoom`` times per axis."""
    u = (img.clamp(0, 1) * 255).to(torch.uint8).cpu().numpy()
    if zoom > 1:
        u = u.repeat(zoom, 0).repeat(zoom, 1)
    return np.repeat(u[..., None], 3, -1)


# ----------------------------------------------------------------------------- probe tasks


def topdown(env, path: np.ndarray, size: int = 200, span: float = 0.1) -> np.ndarray:
    """RGB top-down view (x right, z up) of the back around env 0's goal: skin height, the
    probe's path (red; ``path`` (T, >= 3) probe positions in {P}, m), its current footprint
    (yellow) and the goal (green)."""
    g = env.goal_cmd[0].cpu().numpy()
    xs = g[0] + np.linspace(-span, span, size)
    zs = g[1] + np.linspace(span, -span, size)
    xx, zz = np.meshgrid(xs, zs)
    pid = torch.zeros(xx.shape, dtype=torch.long, device=env.device)
    h = env.scene.skin.height(
        torch.tensor(xx, device=env.device), torch.tensor(zz, device=env.device), pid
    )
    h = h.cpu().numpy()
    gray = (h - h.min()) / max(h.max() - h.min(), 1e-9)
    img = (np.stack([gray] * 3, -1) * 160 + 40).astype(np.uint8)

    def px(x, z):
        i = np.clip(((g[1] + span - z) / (2 * span) * (size - 1)).round().astype(int), 0, size - 1)
        j = np.clip(((x - g[0] + span) / (2 * span) * (size - 1)).round().astype(int), 0, size - 1)
        return i, j

    if len(path):
        i, j = px(path[:, 0], path[:, 2])
        img[i, j] = (230, 40, 40)
    gi, gj = px(np.array([g[0]]), np.array([g[1]]))
    img[max(gi[0] - 3, 0) : gi[0] + 4, gj[0]] = (40, 220, 40)
    img[gi[0], max(gj[0] - 3, 0) : gj[0] + 4] = (40, 220, 40)
    rot = env.scene.probe_rot[0].cpu().numpy()
    p = env.scene.probe_pos[0].cpu().numpy()
    for s in np.linspace(-0.0375, 0.0375, 40):
        fi, fj = px(np.array([p[0] + s * rot[0, 0]]), np.array([p[2] + s * rot[2, 0]]))
        img[fi, fj] = (240, 220, 40)
    return img


def probe_frame(env, image: torch.Tensor, path: np.ndarray) -> np.ndarray:
    """The ultrasound ``image`` beside ``topdown``, doubled in size, padded to 16."""
    u = gray_rgb(image)
    top = topdown(env, path, size=u.shape[0])
    frame = np.concatenate([u, np.zeros((u.shape[0], 4, 3), np.uint8), top], 1)
    return pad16(frame.repeat(2, 0).repeat(2, 1))


def probe_position(env, info) -> np.ndarray:
    """Env 0's reached probe position in {P} (m), the point ``topdown`` draws."""
    return env.scene.probe_pos[0].cpu().numpy().copy()


def first_image(obs) -> torch.Tensor:
    """Env 0's 2-D image of an image observation (N, 1, H, W), or of a Dict observation's
    ``image`` (``obs_mode="us_heading"``)."""
    if isinstance(obs, dict):
        obs = obs["image"]
    return obs[0, 0]


# ----------------------------------------------------------------------------- surgery


def side_view(
    path: np.ndarray, half_width: float, skin_distance: float, size: int = 200
) -> np.ndarray:
    """RGB side view in {G} (horizontal p_x, vertical p_z pointing down, -150 ... +20 mm):
    the corridor C_drill (green outline), the planned trajectory (green), the boundary of
    C_free (gray), the tip's path (red) and the current tip (yellow). Metres in, uint8 out."""
    img = np.full((size, size, 3), 30, np.uint8)
    z_lo, z_hi, x_half = -0.15, 0.02, 0.085

    def px(x, z):
        i = np.clip(((z - z_lo) / (z_hi - z_lo) * (size - 1)).round().astype(int), 0, size - 1)
        j = np.clip(((x + x_half) / (2 * x_half) * (size - 1)).round().astype(int), 0, size - 1)
        return i, j

    xs = np.linspace(-x_half, x_half, size)
    i, j = px(xs, np.full(size, -skin_distance))
    img[i, j] = (110, 110, 110)
    zs = np.linspace(z_lo, 0.0, size)
    i, j = px(np.zeros(size), zs)
    img[i, j] = (40, 160, 40)
    zc = np.linspace(-skin_distance, 0.0, size)
    for x in (-half_width, half_width):
        i, j = px(np.full(size, x), zc)
        img[i, j] = (60, 230, 60)
    i, j = px(np.linspace(-half_width, half_width, 20), np.zeros(20))
    img[i, j] = (60, 230, 60)
    if len(path):
        i, j = px(path[:, 0], path[:, 2])
        img[i, j] = (230, 40, 40)
        i, j = px(path[-1:, 0], path[-1:, 2])
        img[max(i[0] - 2, 0) : i[0] + 3, max(j[0] - 2, 0) : j[0] + 3] = (240, 220, 40)
    return img


def volume_strip(vol: torch.Tensor, gap: int = 1) -> torch.Tensor:
    """(E, H, W) volume -> (H, E W + (E - 1) gap) image: the elevation slices side by side."""
    if vol.dtype == torch.uint8:
        vol = vol.float() / max(float(vol.max()), 1.0)
    e, h, _ = vol.shape
    sep = torch.zeros(h, gap, dtype=vol.dtype, device=vol.device)
    parts = []
    for i in range(e):
        parts += [vol[i], sep] if i < e - 1 else [vol[i]]
    return torch.cat(parts, 1)


def surgery_frame(env, path: np.ndarray, image: torch.Tensor | None = None, zoom: int = 3):
    """Env 0's RGB frame: a 2-D image in [0, 1] (default: its volume's slices side by side),
    upsampled ``zoom`` times, beside the side view of the tip's ``path`` in {G} (metres)."""
    img = volume_strip(env.volume(0)) if image is None else image
    u = gray_rgb(img, zoom)
    side = side_view(path, float(env.half_width[0]), env.cfg.skin_distance, size=u.shape[0])
    return np.concatenate([u, np.zeros((u.shape[0], 4, 3), np.uint8), side], 1)


def surgery_demo_frame(env, image: torch.Tensor, path: np.ndarray) -> np.ndarray:
    """The demo's surgery frame: ``surgery_frame`` at zoom 4, padded to 16."""
    return pad16(surgery_frame(env, path, image, zoom=4))


def surgery_image(obs) -> torch.Tensor:
    """Env 0's volume, its elevation slices side by side."""
    return volume_strip(obs["image"][0])


def drill_tip(env, info) -> np.ndarray:
    """Env 0's drill tip in {G} (m), the point the side view draws."""
    return info["state"][0, :3].cpu().numpy().copy()


# ----------------------------------------------------------------------------- reconstruction


def reconstruction_image(obs) -> torch.Tensor:
    """The reconstruction in the probe frame, projected over elevation: (depth, lateral),
    upsampled x5 to 200 x 200 (bone surface near the image plane shows as bright points)."""
    v = obs["reconstruction"][0].amax(1).T  # (z_U depth, x_U lateral)
    return v.repeat_interleave(5, 0).repeat_interleave(5, 1)
