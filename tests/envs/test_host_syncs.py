"""An env step reads tensors on the host only where it must: each such read (``bool(t)``,
``int(t)``, ``.item()``, ``.tolist()``, boolean masks, ``unique``, ``nonzero``) makes the CPU wait
for a CUDA device. Counted here on CPU with the input checks in their device mode
(``sonogym.checks``: queued, not read)."""

from __future__ import annotations

import collections
import traceback

import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

import sonogym.checks
from sonogym.checks import expect_all
from sonogym.envs.registry import make_vec

#: aten ops whose result size or value the host must read.
_SYNC_OPS = {"_local_scalar_dense", "nonzero", "masked_select", "_unique2", "unique_dim",
             "unique_consecutive", "repeat_interleave", "is_nonzero", "equal"}  # fmt: skip
_INDEX_OPS = {"index", "index_put", "index_put_", "_index_put_impl_"}

#: (file, function) of the reads a step keeps, and why:
ALLOWED = {
    # Gymnasium's autoreset must know whether any env finished (one read per step)
    ("envs/base.py", "step"),
    # the IK re-solve without pinned joints is skipped on CPU when none is pinned; on CUDA it
    # always runs, without the read (see Arm.ik_step)
    ("robots/arm.py", "ik_step"),
}


def _site() -> tuple[str, str]:
    frames = [f for f in traceback.extract_stack() if "/sonogym/" in f.filename]
    f = frames[-1]
    return f.filename.split("/sonogym/")[-1], f.name


class HostReads(TorchDispatchMode):
    """Counts host reads by (file, function) of the innermost sonogym frame."""

    def __init__(self) -> None:
        super().__init__()
        self.sites: collections.Counter = collections.Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        name = func.overloadpacket.__name__
        hit = name in _SYNC_OPS
        if name in _INDEX_OPS and len(args) > 1:  # a boolean mask is a nonzero inside
            hit = any(isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in args[1])
        if hit:
            self.sites[_site()] += 1
        return func(*args, **(kwargs or {}))


@pytest.fixture
def device_mode_checks(monkeypatch):
    """Input checks as on CUDA (queued asserts) and ``.tolist()`` counted too."""
    monkeypatch.setattr(sonogym.checks, "sync_checks", lambda device: False)


def _count_step_reads(env, monkeypatch, steps: int = 4):
    """(host reads by site, ``tolist`` calls by site) of ``steps`` random steps of ``env``."""
    env.reset(seed=0)
    gen = torch.Generator().manual_seed(1)
    low, high = (torch.as_tensor(b) for b in (env.action_space.low, env.action_space.high))
    act = lambda: low + (high - low) * torch.rand(env.action_space.shape, generator=gen)  # noqa: E731
    env.step(act())  # first-call allocations
    counter = HostReads()
    lists = collections.Counter()
    original = torch.Tensor.tolist

    def counted_tolist(self):
        lists[_site()] += 1
        return original(self)

    monkeypatch.setattr(torch.Tensor, "tolist", counted_tolist)
    with counter:
        for _ in range(steps):
            env.step(act())
    monkeypatch.setattr(torch.Tensor, "tolist", original)
    return counter.sites, lists


@pytest.mark.parametrize("task", ["navigation", "reconstruction", "surgery"])
def test_a_step_reads_the_host_only_where_it_must(task, device_mode_checks, monkeypatch):
    torch.set_num_threads(1)
    steps = 4
    sites, lists = _count_step_reads(make_vec(task, 4, phantom_spacing=0.002), monkeypatch, steps)
    assert not lists, f"tolist() in a step: {dict(lists)}"
    extra = {k: v for k, v in sites.items() if k not in ALLOWED}
    assert not extra, f"host reads in {task}'s step: {extra}"
    assert sites[("envs/base.py", "step")] == steps  # the autoreset check, once


@pytest.mark.parametrize(
    "task, option", [("navigation", {"force_action": True}), ("surgery", {"contact_force": 10.0})]
)
def test_a_step_with_compressed_tissue_reads_no_more(task, option, device_mode_checks,
                                                       monkeypatch):  # fmt: skip
    torch.set_num_threads(1)
    env = make_vec(task, 4, phantom_spacing=0.002, **option)
    sites, lists = _count_step_reads(env, monkeypatch, 3)
    assert not lists, f"tolist() in a step: {dict(lists)}"
    extra = {k: v for k, v in sites.items() if k not in ALLOWED}
    assert not extra, f"host reads in {task}'s step with {option}: {extra}"


def test_a_learned_step_reads_only_the_sizes_of_its_net_groups(device_mode_checks, monkeypatch):
    """With the learned simulator a step adds one read: how many envs each net images (the
    envs of a net run as one batch)."""
    torch.set_num_threads(1)
    steps = 4
    env = make_vec("navigation", 4, phantom_spacing=0.002, simulator="learned",
                   learned_nets=(0, 1))  # fmt: skip
    sites, lists = _count_step_reads(env, monkeypatch, steps)
    assert dict(lists) == {("ultrasound/learned/simulator.py", "_groups"): steps}
    extra = {k: v for k, v in sites.items() if k not in ALLOWED}
    assert not extra, f"host reads in a learned step: {extra}"


def test_checks_raise_the_same_message_on_both_paths(monkeypatch):
    bad = torch.tensor([True, False])
    with pytest.raises(ValueError, match="joints out of range"):
        expect_all(bad, "joints out of range")
    with pytest.raises(ValueError, match="envs \\[1\\]"):
        expect_all(bad, lambda: f"bad envs {torch.nonzero(~bad).flatten().tolist()}")
    expect_all(torch.ones(3, dtype=torch.bool), lambda: pytest.fail("message built on success"))
    monkeypatch.setattr(sonogym.checks, "sync_checks", lambda device: False)
    # the device path: a queued assert (on CPU it fires at once, as a RuntimeError)
    with pytest.raises(RuntimeError, match="joints out of range"):
        expect_all(bad, "joints out of range")
    expect_all(torch.ones(3, dtype=torch.bool), "never raised")


def test_sync_checks_follow_the_device_and_the_switch(monkeypatch):
    monkeypatch.delenv("SONOGYM_SYNC_CHECKS", raising=False)
    assert sonogym.checks.sync_checks(torch.device("cpu"))
    assert not sonogym.checks.sync_checks(torch.device("cuda", 0))
    monkeypatch.setenv("SONOGYM_SYNC_CHECKS", "1")
    assert sonogym.checks.sync_checks(torch.device("cuda", 0))


def test_nan_actions_still_name_the_env():
    env = make_vec("navigation", 3, phantom_spacing=0.002)
    env.reset(seed=0)
    a = torch.zeros(env.action_space.shape)
    a[2, 1] = float("nan")
    with pytest.raises(ValueError, match=r"actions contain NaN or inf \(envs \[2\]\)"):
        env.step(a)
