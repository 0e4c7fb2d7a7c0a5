"""The refinement benchmarks' LazyAdam (benchmarks/lazy_adam.py) against torch's Adam: the same steps where every row
has a gradient, and for each row, the steps torch's Adam takes on that row alone over only the steps that reach it."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from lazy_adam import LazyAdam, LazyAdamOptimizerConfig  # noqa: E402


def test_equals_torch_adam_when_every_row_has_a_gradient():
    torch.manual_seed(0)
    lazy = torch.randn(5, 6, dtype=torch.float64, requires_grad=True)
    dense = lazy.detach().clone().requires_grad_()
    lazy_opt, dense_opt = LazyAdam([lazy], lr=1e-2, eps=1e-15), torch.optim.Adam([dense], lr=1e-2, eps=1e-15)
    for _ in range(40):
        grad = torch.randn(5, 6, dtype=torch.float64)
        lazy.grad, dense.grad = grad.clone(), grad.clone()
        lazy_opt.step()
        dense_opt.step()
    torch.testing.assert_close(lazy, dense, rtol=0, atol=1e-14)


def test_each_row_steps_as_adam_over_its_own_visits_only():
    torch.manual_seed(1)
    rows, steps = 7, 120
    lazy = torch.randn(rows, 6, dtype=torch.float64, requires_grad=True)
    alone = [lazy[i].detach().clone().requires_grad_() for i in range(rows)]
    lazy_opt = LazyAdam([lazy], lr=3e-3, betas=(0.8, 0.99), eps=1e-12)
    alone_opts = [torch.optim.Adam([p], lr=3e-3, betas=(0.8, 0.99), eps=1e-12) for p in alone]
    untouched = lazy.detach().clone()
    for _ in range(steps):
        visited = torch.randperm(rows)[:2]  # two images a step, as an image-parallel step draws
        grad = torch.zeros(rows, 6, dtype=torch.float64)
        grad[visited] = torch.randn(len(visited), 6, dtype=torch.float64)
        lazy.grad = grad
        lazy_opt.step()
        for i in visited.tolist():
            alone[i].grad = grad[i].clone()
            alone_opts[i].step()
    torch.testing.assert_close(lazy.detach(), torch.stack([p.detach() for p in alone]), rtol=0, atol=1e-14)
    assert not torch.equal(lazy.detach(), untouched)


def test_a_row_first_reached_late_takes_a_full_first_step():
    """Bias correction by the row's own count: its first step is lr along the gradient's sign, as Adam's first."""
    param = torch.zeros(3, 2, requires_grad=True)
    opt = LazyAdam([param], lr=0.1, eps=0.0)
    for _ in range(50):
        param.grad = torch.tensor([[1.0, -2.0], [0.0, 0.0], [0.0, 0.0]])
        opt.step()
    param.grad = torch.tensor([[0.0, 0.0], [0.0, 0.0], [-3.0, 0.5]])
    opt.step()
    torch.testing.assert_close(param[1].detach(), torch.zeros(2))
    torch.testing.assert_close(param[2].detach(), torch.tensor([0.1, -0.1]))


def test_state_round_trips_and_nerfstudio_config_builds_it():
    param = torch.nn.Parameter(torch.zeros(4, 6))
    opt = LazyAdamOptimizerConfig(lr=1e-3, eps=1e-15).setup([param])
    assert isinstance(opt, LazyAdam) and opt.defaults["eps"] == 1e-15
    param.grad = torch.ones(4, 6)
    opt.step()
    again = LazyAdam([param], lr=1e-3)
    again.load_state_dict(opt.state_dict())
    assert torch.equal(again.state[param]["step"], opt.state[param]["step"])


@pytest.mark.parametrize("kwargs", [{"lr": -1.0}, {"betas": (0.9, 1.0)}, {"eps": -1e-8}])
def test_invalid_settings_are_refused(kwargs):
    with pytest.raises(ValueError, match="LazyAdam"):
        LazyAdam([torch.zeros(2, requires_grad=True)], **kwargs)
