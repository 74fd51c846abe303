"""Tests of pd_tool.fit.schedule: warm-up + linear decay, AdamW groups, resume."""
from __future__ import annotations

import copy
import math

import pytest
import torch

from pd_tool.fit.fields import MaterialField, VelocityField
from pd_tool.fit.schedule import make_optimizer, make_tensor_optimizer, warmup_linear_decay


def test_schedule_values():
    f = [warmup_linear_decay(s, 10, 4, 0.1) for s in range(12)]
    assert f[:4] == pytest.approx([0.25, 0.5, 0.75, 1.0])
    # decay from 1 at step 4 to 0.1 at step 10 (6 steps of 0.15), then held
    assert f[4:] == pytest.approx([1.0, 0.85, 0.7, 0.55, 0.4, 0.25, 0.1, 0.1])
    assert [warmup_linear_decay(s, 3, 0) for s in range(3)] == pytest.approx([1.0, 2 / 3, 1 / 3])
    assert warmup_linear_decay(5, 5, 5) == 1.0
    with pytest.raises(ValueError, match="warmup_steps"):
        warmup_linear_decay(0, 5, 6)


def _lrs(opt, sched, steps):
    out = []
    for _ in range(steps):
        out.append(opt.param_groups[0]["lr"])
        opt.step()
        sched.step()
    return out


def test_optimizer_follows_schedule_and_resumes():
    torch.manual_seed(0)
    field = VelocityField(8, 1.0, channels=2, hidden=8)
    opt, sched = make_optimizer(field, 1e-2, 8, warmup_steps=2, final_factor=0.0)
    expect = [1e-2 * warmup_linear_decay(s, 8, 2) for s in range(8)]
    x = torch.rand(16, 3)
    lrs = []
    for s in range(8):
        lrs.append(opt.param_groups[0]["lr"])
        opt.zero_grad()
        (field(x) - 0.1).square().sum().backward()
        opt.step()
        sched.step()
        if s == 3:  # checkpoint in the middle
            # deepcopy: state_dict() returns live references (torch.save would copy)
            ckpt = copy.deepcopy({"field": field.state_dict(), "opt": opt.state_dict(),
                                  "sched": sched.state_dict()})
    assert lrs == pytest.approx(expect)
    # resume from the checkpoint into fresh objects: same lrs and same weights at the end
    field2 = VelocityField(8, 1.0, channels=2, hidden=8)
    field2.load_state_dict(ckpt["field"])
    opt2, sched2 = make_optimizer(field2, 1e-2, 8, warmup_steps=2, final_factor=0.0)
    opt2.load_state_dict(ckpt["opt"])
    sched2.load_state_dict(ckpt["sched"])
    lrs2 = []
    for _ in range(4, 8):
        lrs2.append(opt2.param_groups[0]["lr"])
        opt2.zero_grad()
        (field2(x) - 0.1).square().sum().backward()
        opt2.step()
        sched2.step()
    assert lrs2 == pytest.approx(expect[4:])
    for a, b in zip(field.parameters(), field2.parameters()):
        assert torch.allclose(a, b, atol=1e-7)


def test_weight_decay_only_on_linear_weights():
    torch.manual_seed(1)
    f = MaterialField(4, 5.0, 15.0, 10.0, channels=2, hidden=8)
    opt, _ = make_optimizer(f, 1e-3, 10, weight_decay=0.5)
    by_wd = {g["weight_decay"]: {id(p) for p in g["params"]} for g in opt.param_groups}
    assert id(f.net.triplane.planes) in by_wd[0.0]
    assert id(f.net.last_layer.bias) in by_wd[0.0]
    assert id(f.net.last_layer.weight) in by_wd[0.5]
    assert sum(len(v) for v in by_wd.values()) == len(list(f.parameters()))
    # a frozen field (stage 1 keeps E fixed) contributes nothing
    f.requires_grad_(False)
    with pytest.raises(ValueError, match="no trainable"):
        make_optimizer(f, 1e-3, 10)


def test_tensor_optimizer_is_plain_adam_on_the_same_schedule():
    t = torch.nn.Parameter(torch.zeros(4))
    opt, sched = make_tensor_optimizer(t, 0.2, 10, warmup_steps=3)
    assert type(opt) is torch.optim.Adam and opt.param_groups[0]["weight_decay"] == 0
    for step in range(12):
        assert opt.param_groups[0]["lr"] == pytest.approx(0.2 * warmup_linear_decay(step, 10, 3))
        t.grad = torch.ones(4)
        opt.step()
        sched.step()
    with pytest.raises(ValueError, match="learning rate"):
        make_tensor_optimizer(t, 0.0, 10)
    with pytest.raises(ValueError, match="warmup_steps"):
        make_tensor_optimizer(t, 0.1, 2, warmup_steps=3)


def test_tensor_optimizer_eps_sets_the_gradient_scale_of_a_full_step():
    # Adam's first step is lr * g / (|g| + eps): a gradient far below eps barely moves,
    # one far above it takes the whole step
    for eps, g, step in ((1e-8, 1e-9, 0.1 / 11), (1e-16, 1e-9, 0.1), (1e-8, 1e-3, 0.1)):
        t = torch.nn.Parameter(torch.zeros(1))
        opt, _ = make_tensor_optimizer(t, 0.1, 10, eps=eps)
        t.grad = torch.full((1,), g)
        opt.step()
        assert -float(t.detach()) == pytest.approx(step, rel=1e-4)
    with pytest.raises(ValueError, match="eps"):
        make_tensor_optimizer(t, 0.1, 10, eps=0.0)


def test_fit_settings_refuse_a_residual_eps_that_is_not_positive():
    from pd_tool.fit.settings import FitSettings

    for eps in (0.0, -1e-8):
        with pytest.raises(ValueError, match="residual_eps"):
            FitSettings(quality="draft", residual_eps=eps).resolved()
    assert FitSettings(quality="draft", residual_eps=1e-16).resolved().residual_eps == 1e-16


def test_tensor_optimizer_weight_decay_pulls_toward_zero_whatever_the_gradient_scale():
    # AdamW: p <- p (1 - lr wd) - lr m / (sqrt(v) + eps). With a zero gradient only the pull
    # acts; with gradients 1e-9 and 1e3 the Adam part is the same full step, so the decay's
    # share does not depend on the loss's scale (a penalty in the loss would)
    lr, wd = 0.1, 0.5
    t = torch.nn.Parameter(torch.full((1,), 2.0))
    opt, _ = make_tensor_optimizer(t, lr, 10, eps=1e-16, weight_decay=wd)
    t.grad = torch.zeros(1)
    opt.step()
    assert float(t.detach()) == pytest.approx(2.0 * (1 - lr * wd), rel=1e-6)
    for g in (1e-9, 1e3):
        t = torch.nn.Parameter(torch.full((1,), 2.0))
        opt, _ = make_tensor_optimizer(t, lr, 10, eps=1e-16, weight_decay=wd)
        t.grad = torch.full((1,), g)
        opt.step()
        assert float(t.detach()) == pytest.approx(2.0 * (1 - lr * wd) - lr, rel=1e-5)
    for bad in (-0.1, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="weight decay"):
            make_tensor_optimizer(t, lr, 10, weight_decay=bad)


def test_fit_settings_refuse_a_residual_decay_out_of_range_and_stage_two_uses_it():
    from pd_tool.fit.settings import FitSettings
    from pd_tool.fit.stages import stage_optimizers

    for bad in (-0.5, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="residual_decay"):
            FitSettings(quality="draft", residual_decay=bad).resolved()

    class Problem:  # the attributes stage_optimizers reads
        material = torch.nn.Linear(2, 1)
        velocities = [torch.nn.Linear(2, 1)]
        log_e_residual = torch.nn.Parameter(torch.zeros(3))
        pool_parts = None

    for decay, kind in ((0.0, torch.optim.Adam), (0.3, torch.optim.AdamW)):
        s = FitSettings(quality="draft", residual_decay=decay).resolved()
        opt, _ = stage_optimizers(Problem(), s, "material")["_r"]
        assert type(opt) is kind and opt.param_groups[0]["weight_decay"] == pytest.approx(decay)


def _pooled_adam_ref(x0: list[float], grads: list[list[float]], lr: float, pool: float, wd: float,
                     eps: float = 1e-16, groups: list[int] | None = None) -> list[float]:
    """PooledAdam in float64 plain Python: Adam's moments with the second one blended with its
    mean over the entries (over each group's entries; -1: the entry's own)."""
    x, m, v = list(x0), [0.0] * len(x0), [0.0] * len(x0)
    for t, g in enumerate(grads, start=1):
        m = [0.9 * a + 0.1 * b for a, b in zip(m, g)]
        v = [0.999 * a + 0.001 * b * b for a, b in zip(v, g)]
        mh = [a / (1 - 0.9**t) for a in m]
        vh = [a / (1 - 0.999**t) for a in v]
        lab = groups if groups is not None else [0] * len(x)
        shared = [b if k < 0 else sum(c for c, j in zip(vh, lab) if j == k) / lab.count(k) for b, k in zip(vh, lab)]
        x = [xi * (1 - lr * wd) - lr * a / (b ** (0.5 * (1 - pool)) * sh ** (0.5 * pool) + eps)
             for xi, a, b, sh in zip(x, mh, vh, shared)]
    return x


@pytest.mark.parametrize("pool", [0.5, 1.0])
def test_pooled_adam_matches_its_float64_reference(pool):
    grads = [[1e-3, 0.5, -2.0], [2e-3, -0.3, -1.0], [-1e-3, 0.4, 0.5], [5e-4, 0.1, -0.2]]
    x0, lr, wd = [0.2, -0.1, 1.0], 0.05, 0.3
    t = torch.nn.Parameter(torch.tensor(x0, dtype=torch.float64))
    opt, _ = make_tensor_optimizer(t, lr, 100, eps=1e-16, weight_decay=wd, pool=pool)
    for g in grads:
        t.grad = torch.tensor(g, dtype=torch.float64)
        opt.step()
    assert t.detach().tolist() == pytest.approx(_pooled_adam_ref(x0, grads, lr, pool, wd), rel=1e-12, abs=1e-15)


def test_pooled_adam_within_groups_matches_its_float64_reference():
    grads = [[1e-3, 0.5, -2.0, 3e-4, 0.2], [2e-3, -0.3, -1.0, -1e-4, 0.1], [-1e-3, 0.4, 0.5, 2e-4, -0.3]]
    x0, lr, wd, groups = [0.2, -0.1, 1.0, 0.0, 0.3], 0.05, 0.3, [0, 1, 1, 0, -1]
    t = torch.nn.Parameter(torch.tensor(x0, dtype=torch.float64))
    opt, _ = make_tensor_optimizer(t, lr, 100, eps=1e-16, weight_decay=wd, pool=0.7,
                                   pool_groups=torch.tensor(groups))
    for g in grads:
        t.grad = torch.tensor(g, dtype=torch.float64)
        opt.step()
    assert t.detach().tolist() == pytest.approx(_pooled_adam_ref(x0, grads, lr, 0.7, wd, groups=groups),
                                                rel=1e-12, abs=1e-15)
    with pytest.raises(ValueError, match="pool_groups"):
        make_tensor_optimizer(t, lr, 10, pool=0.5, pool_groups=torch.zeros(4, dtype=torch.long))


def test_pooled_adam_in_groups_steps_a_weak_region_as_adam_does():
    """A group whose gradients are all weak (a thin leaf) steps as far as a strong one; within
    a group the weaker entry steps less."""
    t = torch.nn.Parameter(torch.zeros(4, dtype=torch.float64))
    opt, _ = make_tensor_optimizer(t, 0.1, 10, eps=1e-16, pool=1.0, pool_groups=torch.tensor([0, 0, 1, 1]))
    t.grad = torch.tensor([1e-4, 1e-4, 1.0, 0.01], dtype=torch.float64)
    opt.step()
    step = (-t.detach()).tolist()
    assert step[0] == pytest.approx(0.1, rel=1e-6) and step[0] == pytest.approx(step[1], rel=1e-9)
    assert step[2] == pytest.approx(0.1 / math.sqrt((1 + 1e-4) / 2), rel=1e-6)
    assert step[3] / step[2] == pytest.approx(0.01, rel=1e-6)


def test_pooled_adam_steps_a_weak_gradient_less_than_adam():
    """Adam steps each entry about lr whatever its gradient; pooled fully, the steps keep the
    gradients' ratio; half way, its square root."""
    steps = {}
    for pool in (0.0, 0.5, 1.0):
        t = torch.nn.Parameter(torch.zeros(2, dtype=torch.float64))
        opt, _ = make_tensor_optimizer(t, 0.1, 10, eps=1e-16, pool=pool)
        t.grad = torch.tensor([1e-4, 1.0], dtype=torch.float64)
        opt.step()
        steps[pool] = (-t.detach()).tolist()
    assert steps[0.0][0] == pytest.approx(steps[0.0][1], rel=1e-6)
    assert steps[1.0][0] / steps[1.0][1] == pytest.approx(1e-4, rel=1e-6)
    assert steps[0.5][0] / steps[0.5][1] == pytest.approx(1e-2, rel=1e-6)
    with pytest.raises(ValueError, match="pool"):
        make_tensor_optimizer(t, 0.1, 10, pool=1.5)


def test_fit_settings_refuse_a_residual_pool_out_of_range_and_stage_two_uses_it():
    from pd_tool.fit.schedule import PooledAdam
    from pd_tool.fit.settings import FitSettings
    from pd_tool.fit.stages import stage_optimizers

    for bad in (-0.1, 1.1, float("nan")):
        with pytest.raises(ValueError, match="residual_pool"):
            FitSettings(quality="draft", residual_pool=bad).resolved()
    with pytest.raises(ValueError, match="residual_pool_parts"):
        FitSettings(quality="draft", residual_pool_parts=-1).resolved()

    class Problem:  # the attributes stage_optimizers reads
        material = torch.nn.Linear(2, 1)
        velocities = [torch.nn.Linear(2, 1)]
        log_e_residual = torch.nn.Parameter(torch.zeros(3))
        pool_parts = None

    for pool, kind in ((0.0, torch.optim.Adam), (0.5, PooledAdam)):
        opt, _ = stage_optimizers(Problem(), FitSettings(quality="draft", residual_pool=pool).resolved(), "material")["_r"]
        assert type(opt) is kind


def test_pooled_adam_resumes_from_its_state_dict():
    """A fit checkpoint holds the optimiser's state_dict: a fresh PooledAdam loaded from it
    takes the same next step as the one that wrote it."""
    grads = [torch.tensor([0.3, -1e-3, 2.0]), torch.tensor([0.1, 2e-3, -1.0]), torch.tensor([-0.2, 1e-3, 0.5])]
    a = torch.nn.Parameter(torch.zeros(3))
    opt_a, _ = make_tensor_optimizer(a, 0.05, 10, pool=0.5)
    for g in grads[:2]:
        a.grad = g.clone()
        opt_a.step()
    b = torch.nn.Parameter(a.detach().clone())
    opt_b, _ = make_tensor_optimizer(b, 0.05, 10, pool=0.5)
    opt_b.load_state_dict(copy.deepcopy(opt_a.state_dict()))  # a checkpoint holds copies
    for p, opt in ((a, opt_a), (b, opt_b)):
        p.grad = grads[2].clone()
        opt.step()
    assert torch.equal(a.detach(), b.detach())
