"""Value penalization: sign and size of the penalty and its gradient, and the median-filtered Q_max."""

import pytest
import torch

from shiftkit.policies.trainers.vpace.value_penalty import MedianFilter, ValueBounds, value_penalty


def test_penalty_above_q_max_pushes_q_down():
    q = torch.tensor([[5.0, 1.0, -2.0]], requires_grad=True)  # one task, batch of 3
    q_max, q_min = torch.tensor([[3.0]]), torch.tensor([[-10.0]])
    loss = value_penalty(q, q_max, q_min, weight=10.0)
    assert loss.item() == pytest.approx(10.0 * (2.0**2) / 3)  # only the first row is over the bound, by 2
    loss.sum().backward()
    # d/dq of 10 * (q - 3)^2 / 3 at q = 5 is positive: gradient descent lowers Q; rows inside get nothing.
    assert q.grad[0, 0].item() == pytest.approx(10.0 * 2 * 2.0 / 3)
    assert q.grad[0, 1].item() == 0.0 and q.grad[0, 2].item() == 0.0


def test_penalty_below_q_min_pushes_q_up():
    q = torch.tensor([[-12.0, 0.0]], requires_grad=True)
    loss = value_penalty(q, torch.tensor([[10.0]]), torch.tensor([[-10.0]]), weight=10.0)
    assert loss.item() == pytest.approx(10.0 * 4.0 / 2)
    loss.sum().backward()
    assert q.grad[0, 0].item() < 0.0  # descent raises Q towards Q_min
    assert q.grad[0, 1].item() == 0.0


def test_penalty_zero_inside_bounds():
    q = torch.linspace(-9.9, 9.9, 50).reshape(2, 25).requires_grad_(True)
    loss = value_penalty(q, torch.full((2, 1), 10.0), torch.full((2, 1), -10.0), weight=10.0)
    assert torch.all(loss == 0.0)
    loss.sum().backward()
    assert torch.all(q.grad == 0.0)


def test_penalty_bounds_are_per_task():
    q = torch.tensor([[2.0, 2.0], [2.0, 2.0]])
    loss = value_penalty(q, torch.tensor([[1.0], [3.0]]), torch.tensor([[-1.0], [-1.0]]), weight=1.0)
    assert loss.tolist() == [1.0, 0.0]


def test_q_max_filter_is_median_of_last_50():
    f = MedianFilter(num_tasks=2, size=50)
    values = torch.arange(120, dtype=torch.float32)
    for v in values:
        out = f.update(torch.stack([v, -v]))
    window = values[-50:]
    assert out[0].item() == window.median().item()
    assert out[1].item() == (-window).median().item()
    # One outlier cannot move a median of 50 equal values.
    g = MedianFilter(1, 50)
    for v in [1.0] * 49:
        g.update(torch.tensor([v]))
    assert g.update(torch.tensor([1e9])).item() == 1.0


def test_filter_uses_values_seen_so_far_and_restores():
    f = MedianFilter(1, 50)
    assert f.update(torch.tensor([4.0])).item() == 4.0
    f.update(torch.tensor([2.0]))
    assert f.update(torch.tensor([3.0])).item() == 3.0
    g = MedianFilter(1, 50)
    g.load_state_dict(f.state_dict())
    assert g.update(torch.tensor([10.0])).item() == f.update(torch.tensor([10.0])).item()


def test_value_bounds_q_min_from_reward_scale_and_gamma():
    bounds = ValueBounds(num_tasks=1, reward_scale=0.1, gamma=0.99)
    q_max, q_min = bounds.update(torch.tensor([5.0]), torch.tensor([-1.0]), learned_reward=False)
    assert q_max.item() == 5.0
    assert abs(q_min.item() - (-10.0)) < 1e-4  # SQIL: 0.1 * -1 / (1 - 0.99)
