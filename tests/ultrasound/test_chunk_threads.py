"""Chunks on several threads (``ChunkRunner``): same images and slices as one thread, errors
reach the caller, no nested fan-out, and a forked child still runs."""

from __future__ import annotations

import multiprocessing
import threading

import pytest
import torch
from us_synthetic import block_patient, random_poses

from sonogym.ultrasound import ModelBasedSimulator, Slicer
from sonogym.ultrasound._workspace import MAX_CHUNK_WORKERS, ChunkRunner


@pytest.fixture
def two_threads():
    old = torch.get_num_threads()
    torch.set_num_threads(2)
    yield
    torch.set_num_threads(old)


@pytest.mark.parametrize("model", ["physical", "reference"])
def test_two_threads_give_the_same_bits_as_one(model, two_threads):
    patient = block_patient(ct_noise=10.0)
    pos, rot = random_poses(7, seed=5)
    # small chunks so both the slicer (2 envs) and the simulator (2 images) split the batch
    slicer = Slicer(patient, chunk_samples=2 * 100 * 75)
    sim = ModelBasedSimulator(model, chunk_pixels=2 * 200 * 150)
    torch.set_num_threads(1)
    one = slicer(pos, rot)
    ct1, lab1 = one.ct.clone(), one.labels.clone()
    img1, raw1 = sim.simulate(one), sim.simulate_raw(one)
    torch.set_num_threads(2)
    two = slicer(pos, rot)
    assert len(slicer._chunks.workspaces) == 2 and len(sim._chunks.workspaces) == 1
    img2, raw2 = sim.simulate(two), sim.simulate_raw(two)
    assert len(sim._chunks.workspaces) == 2  # the second thread did run chunks
    assert torch.equal(two.ct, ct1) and torch.equal(two.labels, lab1)
    assert torch.equal(img2, img1) and torch.equal(raw2, raw1)


def test_chunks_cover_everything_once_and_errors_reach_the_caller(two_threads):
    runner = ChunkRunner(torch.device("cpu"))
    seen: list[tuple[int, int]] = []
    lock = threading.Lock()

    def record(i, ws):
        with lock:
            seen.append((i, threading.get_ident()))

    runner.run(record, list(range(9)))
    assert sorted(i for i, _ in seen) == list(range(9))
    assert len({t for _, t in seen}) == 2

    def fail_on_5(i, ws):
        if i == 5:
            raise RuntimeError("chunk 5 broke")

    with pytest.raises(RuntimeError, match="chunk 5 broke"):
        runner.run(fail_on_5, list(range(9)))

    inner: list[int] = []

    def nested(i, ws):
        inner.append(runner.workers(4))

    runner.run(nested, [0, 1])
    assert inner == [1, 1]  # a call from inside a chunk runs serially

    torch.set_num_threads(32)  # scratch per worker: many cores still fan out to at most 8
    assert runner.workers(100) == MAX_CHUNK_WORKERS == 8 and runner.workers(3) == 3
    assert ChunkRunner(torch.device("meta")).workers(100) == 1  # only CPU fans out


def _child_runs(queue) -> None:
    torch.set_num_threads(2)
    out = torch.zeros(6)

    def fill(i, ws):
        out[i] = i + 1

    ChunkRunner(torch.device("cpu")).run(fill, list(range(6)))
    queue.put(out.tolist())


@pytest.mark.skipif("fork" not in multiprocessing.get_all_start_methods(), reason="no fork")
def test_a_forked_child_gets_its_own_pool(two_threads):
    ChunkRunner(torch.device("cpu")).run(lambda i, ws: None, [0, 1, 2])  # parent's pool exists
    ctx = multiprocessing.get_context("fork")
    queue = ctx.Queue()
    child = ctx.Process(target=_child_runs, args=(queue,))
    child.start()
    child.join(timeout=60)
    alive = child.is_alive()
    if alive:
        child.kill()
    assert not alive, "the forked child hung on the parent's thread pool"
    assert queue.get(timeout=5) == [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]


def test_exp2_gives_each_element_the_same_bits_whatever_the_batch_and_threads(two_threads):
    # ATen's scalar exp2 (for a range's last elements) differs from its vectorised one by an
    # ulp: the value of an element must not depend on where the tensor or a thread's range ends
    from sonogym.ultrasound._workspace import exp2_

    x = -20 * torch.rand(3 * 30_000 + 17, generator=torch.Generator().manual_seed(0))
    torch.set_num_threads(1)
    whole = exp2_(x.clone())
    torch.set_num_threads(2)
    assert torch.equal(exp2_(x.clone()), whole)
    for lo, hi in ((0, 30_000), (30_000, 60_000), (5, 21), (60_000, x.numel())):
        assert torch.equal(exp2_(x[lo:hi].clone()), whole[lo:hi])
    assert torch.allclose(whole, torch.exp2(x), rtol=1e-6, atol=0)
