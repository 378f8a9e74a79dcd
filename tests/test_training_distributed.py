"""Two gloo processes split the batch and the replayed PSF chunks: their summed gradients equal the
single-process gradients (lens/DOE and network) on a real ray-wave hybrid lens."""

import os
import socket
import sys
import warnings
from pathlib import Path

import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp

sys.path.insert(0, str(Path(__file__).parent))
from test_training_replay import fft_conv, field_grid, make_step, small_hybrid  # noqa: E402

from raywave.training.distributed import allreduce_, allreduce_grads, batch_share, shard  # noqa: E402


def _problem():
    torch.manual_seed(0)
    hl = small_hybrid()
    net = torch.nn.Sequential(torch.nn.Conv2d(3, 4, 3, padding=1), torch.nn.Tanh(),
                              torch.nn.Conv2d(4, 3, 3, padding=1)).double()
    g = torch.Generator().manual_seed(1)
    batch = torch.rand(3, 4, 3, 24, 24, dtype=torch.float64, generator=g)  # 3 images × 4 patches (2×2 map)
    return hl, net, batch


def _loss(psf, imgs, net):
    """Mean over the images of an L2 loss of the network's output on the patch-wise blurred image."""
    out = net(fft_conv(imgs.reshape(-1, 3, 24, 24), psf.repeat(imgs.shape[0], 1, 1, 1)))
    return (out - imgs.reshape(-1, 3, 24, 24)).square().mean()


def _grads(hl, net, rank=0, world=1):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        hl_, net_, batch = hl, net, _problem()[2]
        step = make_step(hl_, 2, 1, torch.Generator().manual_seed(7))
        psf, center = step.leaves()
        share = batch_share(batch.shape[0], rank, world)
        mine = batch[share]
        (_loss(psf, mine, net_) * mine.shape[0] / batch.shape[0]).backward()
        allreduce_(psf.grad)
        step.backward(chunks=shard(step.n_chunks, rank, world))
        allreduce_grads(list(hl_.parameters()) + list(net_.parameters()))
    return [hl_.doe.phase_map.grad.clone(), hl_.lens.surfaces[0].interaction.focal_length.grad.clone()] + \
           [p.grad.clone() for p in net_.parameters()]


def _worker(rank, world, port, out):
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), OMP_NUM_THREADS="1")
    torch.set_num_threads(1)
    dist.init_process_group("gloo", rank=rank, world_size=world)
    try:
        hl, net, _ = _problem()
        g = _grads(hl, net, rank, world)
        if rank == 0:
            torch.save(g, out)
    finally:
        dist.destroy_process_group()


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_shard_and_batch_share():
    assert [shard(5, r, 2) for r in range(2)] == [[0, 2, 4], [1, 3]]
    assert [batch_share(5, r, 2) for r in range(2)] == [slice(0, 3), slice(3, 5)]
    with pytest.raises(ValueError):
        shard(3, 2, 2)


def test_two_gloo_processes_match_one(tmp_path):
    hl, net, _ = _problem()
    single = _grads(hl, net)
    out = tmp_path / "g.pt"
    mp.spawn(_worker, args=(2, _free_port(), str(out)), nprocs=2, join=True)
    multi = torch.load(out, weights_only=True)
    for a, b in zip(single, multi):
        scale = float(a.abs().max())
        assert scale > 0
        assert float((a - b).abs().max()) <= 1e-12 * scale
