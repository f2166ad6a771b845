"""Per-env inference state of chunking policies, batched over envs, reset per env.

* ``TemporalEnsembler``: ACT's temporal ensembling (ACT paper, Algorithm 2, in LeRobot's online
  form). Every step the policy predicts a chunk a_t..a_{t+k-1}; the action executed at step t
  is the weighted mean of all predictions made for step t, with weights w_i = exp(-coeff i)
  where i = 0 is the OLDEST prediction (coeff > 0 favours old predictions; 0: plain mean).
  Online: for each future step j the running mean E_j and the count c_j of predictions so
  far are kept; a new prediction P_j enters as E_j <- (E_j S_{c_j - 1} + P_j w_{c_j}) / S_{c_j}
  with S_m = w_0 + ... + w_m (S_{-1} = 0), then E_0 is executed and everything shifts by one.
* ``ActionQueue``: plain chunk execution: the first ``n`` actions of a chunk are executed one
  per step; an env asks for a new chunk when its queue is empty.
* ``ObsHistory``: the last ``n`` observations per env; an env's first observation after a
  reset fills all ``n`` slots (LeRobot fills its queues the same way).

``reset(mask)`` clears the state of the masked envs only ((N,) bool; None: all envs).
"""

from __future__ import annotations

import torch


def _mask(mask: torch.Tensor | None, n: int, device) -> torch.Tensor:
    if mask is None:
        return torch.ones(n, dtype=torch.bool, device=device)
    mask = torch.as_tensor(mask, device=device).bool()
    if mask.shape != (n,):
        raise ValueError(f"env_mask must have shape ({n},), got {tuple(mask.shape)}")
    return mask


class TemporalEnsembler:
    """Temporal ensemble over ``num_envs`` envs of ``chunk``-step, ``action_dim`` predictions."""

    def __init__(self, coeff: float, chunk: int, num_envs: int, action_dim: int, device) -> None:
        self.chunk = int(chunk)
        w = torch.exp(-float(coeff) * torch.arange(chunk, dtype=torch.float64))
        self.weights = w.float().to(device)  # w_i, i = 0 oldest
        self.cumsum = torch.cumsum(w, 0).float().to(device)  # S_i
        self.mean = torch.zeros(num_envs, chunk, action_dim, device=device)
        self.count = torch.zeros(num_envs, chunk, dtype=torch.long, device=device)

    def reset(self, mask: torch.Tensor | None = None) -> None:
        m = _mask(mask, len(self.count), self.count.device)
        self.mean[m] = 0.0
        self.count[m] = 0

    def update(self, chunk: torch.Tensor) -> torch.Tensor:
        """Add each env's new prediction (N, chunk, A); the action (N, A) to execute now."""
        c = self.count  # predictions so far per future step, <= chunk - 1 before this one
        prev = torch.where(c > 0, self.cumsum[(c - 1).clamp(min=0)], 0.0)  # S_{c-1}
        new = (self.mean * prev[..., None] + chunk * self.weights[c][..., None]) / self.cumsum[c][
            ..., None
        ]
        action = new[:, 0]
        # shift by one step: position j now is step t + 1 + j; the last one has no prediction
        self.mean = torch.cat([new[:, 1:], torch.zeros_like(new[:, :1])], dim=1)
        self.count = torch.cat([c[:, 1:] + 1, torch.zeros_like(c[:, :1])], dim=1)
        return action


class ActionQueue:
    """Per-env queues of ``n`` actions taken from predicted chunks."""

    def __init__(self, n: int, num_envs: int, action_dim: int, device) -> None:
        self.n = int(n)
        self.actions = torch.zeros(num_envs, n, action_dim, device=device)
        self.remaining = torch.zeros(num_envs, dtype=torch.long, device=device)

    def reset(self, mask: torch.Tensor | None = None) -> None:
        self.remaining[_mask(mask, len(self.remaining), self.remaining.device)] = 0

    def empty(self) -> torch.Tensor:
        """(N,) bool: envs that need a new chunk before ``pop``."""
        return self.remaining == 0

    def fill(self, idx: torch.Tensor, chunk: torch.Tensor) -> None:
        """Give envs ``idx`` (long) new queues: the first ``n`` steps of ``chunk`` (B, >= n, A)."""
        self.actions[idx] = chunk[:, : self.n]
        self.remaining[idx] = self.n

    def pop(self) -> torch.Tensor:
        """Each env's next action (N, A); every queue must hold one."""
        if bool((self.remaining <= 0).any()):
            raise RuntimeError("ActionQueue.pop with an empty queue: fill it first")
        pos = self.n - self.remaining
        a = self.actions[torch.arange(len(pos), device=pos.device), pos]
        self.remaining -= 1
        return a


class ObsHistory:
    """The last ``n`` values of one observation feature per env: (N, n, ...), oldest first."""

    def __init__(self, n: int) -> None:
        self.n = int(n)
        self.buf: torch.Tensor | None = None
        self.fresh: torch.Tensor | None = None

    def reset(self, mask: torch.Tensor | None = None) -> None:
        if self.fresh is not None:
            self.fresh[_mask(mask, len(self.fresh), self.fresh.device)] = True

    def push(self, x: torch.Tensor) -> torch.Tensor:
        """Append this step's (N, ...) values; the history (N, n, ...)."""
        if self.buf is None or self.buf.shape[0] != x.shape[0] or self.buf.shape[2:] != x.shape[1:]:
            self.buf = x[:, None].expand(x.shape[0], self.n, *x.shape[1:]).clone()
            self.fresh = torch.zeros(x.shape[0], dtype=torch.bool, device=x.device)
            return self.buf
        self.buf = torch.cat([self.buf[:, 1:], x[:, None]], dim=1)
        if bool(self.fresh.any()):
            f = self.fresh
            self.buf[f] = x[f][:, None].expand(int(f.sum()), self.n, *x.shape[1:])
            self.fresh = torch.zeros_like(f)
        return self.buf
