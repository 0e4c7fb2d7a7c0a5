"""SelectiveAdam (geer_ns/optim/selective_adam.py) against torch's Adam where every row is offered, and against
gsplat 1.5's SelectiveAdam on a visibility mask. gsplat 1.4 (installed) has none; its 1.5 kernel
(gsplat/cuda/csrc/AdamCUDA.cu) does, per element of a visible row, m = b1 m + (1 - b1) g, v = b2 v + (1 - b2) g^2,
p -= lr m / (sqrt(v) + eps), without bias correction, and leaves hidden rows untouched: `gsplat_step` below."""

from __future__ import annotations

import torch

from geer_ns.optim.selective_adam import SelectiveAdam, SelectiveAdamOptimizerConfig, offer_rows

F64 = torch.float64


def gsplat_step(param, grad, m, v, visible, lr, b1, b2, eps):
    """gsplat 1.5 SelectiveAdam's update, in place (module docstring)."""
    rows = visible.nonzero().squeeze(1)
    m[rows] = b1 * m[rows] + (1 - b1) * grad[rows]
    v[rows] = b2 * v[rows] + (1 - b2) * grad[rows] * grad[rows]
    param[rows] -= lr * m[rows] / (torch.sqrt(v[rows]) + eps)


def test_every_row_offered_is_torch_adam_exactly():
    torch.manual_seed(0)
    ours = torch.randn(50, 4, 3, requires_grad=True)
    dense = ours.detach().clone().requires_grad_()
    opt_ours, opt_dense = SelectiveAdam([ours], lr=1e-2, eps=1e-15), torch.optim.Adam([dense], lr=1e-2, eps=1e-15)
    for _ in range(30):
        grad = torch.randn(50, 4, 3)
        ours.grad, dense.grad = grad.clone(), grad.clone()
        opt_ours.use_rows(torch.arange(50))
        opt_ours.step()
        opt_dense.step()
    assert torch.equal(ours, dense)
    for key in ("exp_avg", "exp_avg_sq", "step"):
        assert torch.equal(opt_ours.state[ours][key], opt_dense.state[dense][key])


def test_the_row_step_on_every_row_is_torch_adam():
    """The gathered-row update itself (not the every-row shortcut to torch's step) on all of a parameter's rows:
    a second parameter of more rows in the group keeps the step on the row path."""
    gen = torch.Generator().manual_seed(3)
    ours, other = torch.randn(30, 3, generator=gen, dtype=F64, requires_grad=True), torch.zeros(40, 3, dtype=F64,
                                                                                                 requires_grad=True)
    dense = ours.detach().clone().requires_grad_()
    opt, opt_dense = SelectiveAdam([ours, other], lr=1e-2, eps=1e-15), torch.optim.Adam([dense], lr=1e-2, eps=1e-15)
    for _ in range(25):
        grad = torch.randn(30, 3, generator=gen, dtype=F64)
        ours.grad, other.grad, dense.grad = grad.clone(), torch.ones(40, 3, dtype=F64), grad.clone()
        opt.use_rows(torch.arange(30))
        opt.step()
        opt_dense.step()
    torch.testing.assert_close(ours.detach(), dense.detach(), rtol=1e-13, atol=1e-15)
    torch.testing.assert_close(opt.state[ours]["exp_avg_sq"], opt_dense.state[dense]["exp_avg_sq"], rtol=1e-13,
                               atol=1e-18)
    assert bool((other.detach()[30:] == 0).all())  # rows never offered: untouched


def test_visible_rows_step_as_gsplat_with_the_bias_correction_folded_in():
    """On a mask: hidden rows (and their moments) unchanged; visible rows take gsplat's step with learning rate
    lr sqrt(1 - b2^t) / (1 - b1^t) and epsilon eps sqrt(1 - b2^t), t the optimizer's step count."""
    gen = torch.Generator().manual_seed(1)
    n, lr, b1, b2, eps = 40, 3e-3, 0.9, 0.999, 1e-8
    ours = torch.randn(n, 3, generator=gen, dtype=F64, requires_grad=True)
    ref = ours.detach().clone()
    m, v = torch.zeros_like(ref), torch.zeros_like(ref)
    opt = SelectiveAdam([ours], lr=lr, betas=(b1, b2), eps=eps)
    for t in range(1, 60):
        grad = torch.randn(n, 3, generator=gen, dtype=F64)
        visible = torch.rand(n, generator=gen) < 0.2
        before = ours.detach().clone()
        ours.grad = grad.clone()
        opt.use_rows(visible.nonzero().squeeze(1))
        opt.step()
        c1, c2 = 1 - b1**t, 1 - b2**t
        gsplat_step(ref, grad, m, v, visible, lr * c2**0.5 / c1, b1, b2, eps * c2**0.5)
        assert torch.equal(ours.detach()[~visible], before[~visible])
        torch.testing.assert_close(ours.detach(), ref, rtol=1e-12, atol=1e-14)
        torch.testing.assert_close(opt.state[ours]["exp_avg"], m, rtol=1e-12, atol=1e-15)
        torch.testing.assert_close(opt.state[ours]["exp_avg_sq"], v, rtol=1e-12, atol=1e-18)


def test_a_row_seen_in_every_step_follows_torch_adam():
    gen = torch.Generator().manual_seed(2)
    ours = torch.randn(20, 2, generator=gen, dtype=F64, requires_grad=True)
    alone = ours.detach()[:1].clone().requires_grad_()
    opt, opt_alone = SelectiveAdam([ours], lr=1e-2, eps=1e-15), torch.optim.Adam([alone], lr=1e-2, eps=1e-15)
    for _ in range(40):
        grad = torch.randn(20, 2, generator=gen, dtype=F64)
        visible = torch.rand(20, generator=gen) < 0.3
        visible[0] = True
        ours.grad, alone.grad = grad, grad[:1].clone()
        opt.use_rows(visible.nonzero().squeeze(1))
        opt.step()
        opt_alone.step()
    torch.testing.assert_close(ours.detach()[:1], alone.detach(), rtol=1e-13, atol=1e-15)


def test_checkpoints_interchange_with_torch_adam():
    a = torch.randn(6, 3, requires_grad=True)
    b = a.detach().clone().requires_grad_()
    selective, dense = SelectiveAdam([a], lr=0.1), torch.optim.Adam([b], lr=0.1)
    for opt, p in ((selective, a), (dense, b)):
        p.grad = torch.ones(6, 3)
        opt.step()
    other_selective, other_dense = SelectiveAdam([b], lr=0.1), torch.optim.Adam([a], lr=0.1)
    other_selective.load_state_dict(dense.state_dict())
    other_dense.load_state_dict(selective.state_dict())
    assert torch.equal(other_selective.state[b]["exp_avg"], dense.state[b]["exp_avg"])
    assert torch.equal(other_dense.state[a]["exp_avg_sq"], selective.state[a]["exp_avg_sq"])


def test_offer_rows_reaches_only_selective_optimizers():
    p, q = torch.zeros(4, 1, requires_grad=True), torch.zeros(4, 1, requires_grad=True)
    selective = SelectiveAdamOptimizerConfig(lr=1.0).setup([p])
    dense = torch.optim.Adam([q], lr=1.0)
    asked = []
    assert offer_rows({"means": selective, "camera_opt": dense}, lambda: asked.append(1) or torch.tensor([2]))
    assert asked == [1]
    p.grad, q.grad = torch.ones(4, 1), torch.ones(4, 1)
    selective.step()
    dense.step()
    moved = p.detach().flatten()
    assert moved[2] < -0.99 and bool((moved[[0, 1, 3]] == 0).all()) and bool((q != 0).all())
    selective.step()  # the rows hold for one step only
    assert bool((p != 0).all())
    assert not offer_rows({"camera_opt": dense}, lambda: asked.append(2))
    assert asked == [1]


def test_the_batch_rule_scales_the_gaussian_groups_selective_adam():
    """Several images per step (processes x images per process): the square-root rule reaches the Gaussian groups'
    SelectiveAdam as every other Adam (lr x sqrt(k), eps / sqrt(k), betas ** k), and they stay selective."""
    from geer_ns.config import geer_trainer_config
    from geer_ns.distributed.schedule import EffectiveBatch, scaled_config
    from geer_ns.model import GeerModelConfig

    config = geer_trainer_config("geer", GeerModelConfig())
    before = config.optimizers["means"]["optimizer"]
    after = scaled_config(config, EffectiveBatch(processes=2, images_per_process=2)).optimizers["means"]["optimizer"]
    assert isinstance(before, SelectiveAdamOptimizerConfig) and isinstance(after, SelectiveAdamOptimizerConfig)
    assert after.lr == before.lr * 2.0 and after.eps == before.eps / 2.0
    assert after.betas == (0.9**4, 0.999**4)
    assert isinstance(after.setup([torch.zeros(2, 3, requires_grad=True)]), SelectiveAdam)
