import pytest
import torch

from toolkit.encoding import (HashGrid, HashGridConfig, hash_grid_encode, hash_grid_encode_torch, hash_grid_resolutions,
                              hashgrid_kernel, positional_encoding)
from toolkit._checks import ConfigError


def test_positional_encoding_values():
    x = torch.tensor([[0.25, 0.0, -0.5]])
    e = positional_encoding(x, 2)
    assert e.shape == (1, 3 * 5)
    assert torch.allclose(e[0, :3], x[0])
    # layout: [x, sin(2^0 π x), cos(2^0 π x), sin(2^1 π x), cos(2^1 π x)] per frequency block of 3 dims
    assert torch.allclose(e[0, 3:6], torch.sin(torch.pi * x[0]))
    assert torch.allclose(e[0, 6:9], torch.cos(torch.pi * x[0]))
    assert torch.allclose(e[0, 9:12], torch.sin(2 * torch.pi * x[0]), atol=1e-6)


def test_resolutions_and_config():
    cfg = HashGridConfig(n_levels=8, base_resolution=16, max_resolution=1024)
    res = hash_grid_resolutions(cfg)
    assert res[0] == 16 and res[-1] == 1024 and all(b > a for a, b in zip(res, res[1:]))
    with pytest.raises(ConfigError, match="base_resolution"):
        HashGridConfig(base_resolution=64, max_resolution=32)


def test_dense_level_is_trilinear():
    # one dense level: features at grid vertices f(c) = c.x + 2 c.y + 3 c.z reproduce the linear function
    cfg = HashGridConfig(n_levels=1, features_per_level=1, log2_table_size=12, base_resolution=8, max_resolution=8)
    g = HashGrid(cfg, torch.tensor([[0.0, 0, 0], [1, 1, 1]]))
    r = 8
    idx = torch.arange((r + 1) ** 3)
    c = torch.stack([idx % (r + 1), (idx // (r + 1)) % (r + 1), idx // (r + 1) ** 2], -1).float()
    with torch.no_grad():
        g.table.zero_()
        g.table[: (r + 1) ** 3, 0] = c[:, 0] + 2 * c[:, 1] + 3 * c[:, 2]
    x = torch.rand(100, 3)
    out = hash_grid_encode_torch(x, g.table, g.resolutions, g.table_size)[:, 0]
    assert torch.allclose(out, (x * r) @ torch.tensor([1.0, 2, 3]), atol=1e-4)


@pytest.mark.skipif(hashgrid_kernel() is None, reason="compiled hash-grid kernel unavailable")
def test_kernel_matches_torch_reference():
    torch.manual_seed(0)
    cfg = HashGridConfig(n_levels=6, features_per_level=4, log2_table_size=12, base_resolution=4, max_resolution=256)
    g = HashGrid(cfg, torch.tensor([[-1.0, -1, -1], [1, 1, 1]]), init_scale=1.0)
    x = torch.rand(5000, 3)
    grad_out = torch.randn(5000, cfg.out_dim)
    outs, grads = [], []
    for backend in ("kernel", "torch"):
        t = g.table.detach().clone().requires_grad_()
        y = hash_grid_encode(x, t, g.resolutions, g.table_size, backend)
        y.backward(grad_out)
        outs.append(y.detach())
        grads.append(t.grad)
    assert torch.allclose(outs[0], outs[1], atol=1e-5)
    assert torch.allclose(grads[0], grads[1], atol=1e-4)
    # determinism: the kernel's backward gives the same bits twice
    t = g.table.detach().clone().requires_grad_()
    hash_grid_encode(x, t, g.resolutions, g.table_size, "kernel").backward(grad_out)
    assert torch.equal(t.grad, grads[0])


def test_position_gradient_uses_torch_path():
    cfg = HashGridConfig(n_levels=2, features_per_level=2, log2_table_size=10, base_resolution=4, max_resolution=8)
    g = HashGrid(cfg, torch.tensor([[0.0, 0, 0], [1, 1, 1]]), init_scale=1.0)
    x = torch.rand(10, 3, requires_grad=True)
    g(x).sum().backward()
    assert x.grad is not None and torch.isfinite(x.grad).all()
