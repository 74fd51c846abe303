"""Learning-rate schedule (linear warm-up, then linear decay) and the AdamW set-up for fields
(and plain Adam for a single tensor).

The authors' stage 2 used AdamW at lr 1e-3 with warm-up and linear decay and a gradient
clip of 1.0 (method.md). `make_optimizer` builds that for any set of fields; the returned
optimiser and scheduler have the usual `state_dict()` / `load_state_dict()` so a fit can
resume where it stopped.
"""
from __future__ import annotations

import math
from functools import partial
from typing import Iterable

import torch
from torch import nn

from pd_tool.fit.diffusion import part_means

DEFAULT_BETAS = (0.9, 0.999)


def warmup_linear_decay(step: int, total_steps: int, warmup_steps: int, final_factor: float = 0.0) -> float:
    """Learning-rate multiplier at optimiser step `step` (0-based).

    Warm-up: (step + 1) / warmup_steps for step < warmup_steps (so step 0 already moves and
    step warmup_steps - 1 reaches 1). Then linear from 1 at step = warmup_steps down to
    final_factor at step = total_steps; held at final_factor beyond.
    """
    if total_steps < 1:
        raise ValueError(f"total_steps must be >= 1, got {total_steps}")
    if not 0 <= warmup_steps <= total_steps:
        raise ValueError(f"warmup_steps must be in [0, total_steps={total_steps}], got {warmup_steps}")
    if not 0.0 <= final_factor <= 1.0:
        raise ValueError(f"final_factor must be in [0, 1], got {final_factor}")
    if step < warmup_steps:
        return (step + 1) / warmup_steps
    span = total_steps - warmup_steps
    if span <= 0:
        return 1.0
    frac = min(1.0, (step - warmup_steps) / span)
    return 1.0 - (1.0 - final_factor) * frac


def _param_groups(modules: Iterable[nn.Module], weight_decay: float) -> list[dict]:
    # Decay only the Linear weights. Decaying biases would pull the material field's last
    # bias, hence log E, toward the middle of its bounds regardless of the video; decaying
    # planes would fight the TV term's own smoothing.
    decay, no_decay = [], []
    for m in modules:
        for sub in m.modules():
            for name, p in sub.named_parameters(recurse=False):
                if not p.requires_grad:
                    continue
                (decay if isinstance(sub, nn.Linear) and name == "weight" else no_decay).append(p)
    groups = [{"params": no_decay, "weight_decay": 0.0}]
    if decay:
        groups.append({"params": decay, "weight_decay": weight_decay})
    return groups


def make_optimizer(
    modules: nn.Module | Iterable[nn.Module],
    lr: float,
    total_steps: int,
    *,
    warmup_steps: int = 0,
    final_factor: float = 0.0,
    weight_decay: float = 0.0,
    betas: tuple[float, float] = DEFAULT_BETAS,
) -> tuple[torch.optim.AdamW, torch.optim.lr_scheduler.LambdaLR]:
    """AdamW over the trainable parameters of `modules` with a warm-up + linear-decay schedule.

    Call `optimizer.step()` then `scheduler.step()` once per iteration (clip gradients
    before, e.g. torch.nn.utils.clip_grad_norm_(params, 1.0)).

    Args:
        modules: a field or several (e.g. one material field, or one velocity field per video).
        lr: peak learning rate.
        total_steps: iterations of this stage; warmup_steps: of those, warm-up.
        final_factor: lr at the end as a fraction of lr.
        weight_decay: AdamW decoupled decay, applied to Linear weights only (default 0).
    Returns:
        (optimizer, scheduler).
    """
    if isinstance(modules, nn.Module):
        modules = [modules]
    if not lr > 0:
        raise ValueError(f"learning rate must be > 0, got {lr}")
    warmup_linear_decay(0, total_steps, warmup_steps, final_factor)  # validate early
    groups = _param_groups(list(modules), weight_decay)
    if not any(g["params"] for g in groups):
        raise ValueError("no trainable parameters in the given modules")
    opt = torch.optim.AdamW(groups, lr=lr, betas=betas)
    return opt, _scheduler(opt, total_steps, warmup_steps, final_factor)


class PooledAdam(torch.optim.Optimizer):
    """Adam whose step divides each entry's first moment by a blend of its own second moment
    and the mean second moment over the whole tensor:

        step = lr * m_hat / (v_hat^((1 - pool) / 2) * mean(v_hat)^(pool / 2) + eps)

    with torch Adam's moments and bias corrections (betas 0.9, 0.999). pool 0 is Adam: every
    entry steps about lr whatever its gradient's size. pool 1 is momentum gradient descent
    scaled by one number: an entry with a gradient 100x weaker steps 100x less. Decoupled
    weight decay as AdamW's. State per tensor: "step" (0-d), "exp_avg", "exp_avg_sq".

    groups: an optional [Q] int64 label per entry of a one-tensor optimiser; the mean is then
    taken over each label's entries instead of the whole tensor, and an entry labelled -1
    keeps its own second moment (Adam). The labels are not part of the state_dict: the caller
    rebuilds them as it did the tensor."""

    def __init__(self, params, lr: float, pool: float, *, eps: float = 1e-8, weight_decay: float = 0.0,
                 betas: tuple[float, float] = DEFAULT_BETAS, groups: torch.Tensor | None = None) -> None:
        super().__init__(params, dict(lr=lr, pool=pool, eps=eps, weight_decay=weight_decay, betas=betas))
        self.groups = groups

    def _pooled(self, v: torch.Tensor) -> torch.Tensor:
        return v.mean() if self.groups is None else part_means(v, self.groups.to(v.device))

    @torch.no_grad()
    def step(self, closure=None):
        for group in self.param_groups:
            b1, b2 = group["betas"]
            for p in group["params"]:
                if p.grad is None:
                    continue
                st = self.state[p]
                if not st:
                    st["step"] = torch.zeros((), dtype=torch.float64)
                    st["exp_avg"], st["exp_avg_sq"] = torch.zeros_like(p), torch.zeros_like(p)
                st["step"] += 1
                t = float(st["step"])
                g = p.grad
                st["exp_avg"].mul_(b1).add_(g, alpha=1 - b1)
                st["exp_avg_sq"].mul_(b2).addcmul_(g, g, value=1 - b2)
                m_hat = st["exp_avg"] / (1 - b1**t)
                v_hat = st["exp_avg_sq"] / (1 - b2**t)
                pool = group["pool"]
                den = v_hat.pow(0.5 * (1 - pool)) * self._pooled(v_hat).pow(0.5 * pool) + group["eps"]
                if group["weight_decay"]:
                    p.mul_(1 - group["lr"] * group["weight_decay"])
                p.addcdiv_(m_hat, den, value=-group["lr"])


def make_tensor_optimizer(
    param: torch.Tensor, lr: float, total_steps: int, *, warmup_steps: int = 0, final_factor: float = 0.0,
    eps: float = 1e-8, weight_decay: float = 0.0, pool: float = 0.0, pool_groups: torch.Tensor | None = None,
) -> tuple[torch.optim.Optimizer, torch.optim.lr_scheduler.LambdaLR]:
    """Adam over one tensor, e.g. the fit's per-driver log-E residuals or its stage-1 level,
    with make_optimizer's schedule. Arguments as make_optimizer's; eps is Adam's (added to
    sqrt of the second moment), in the gradient's units. weight_decay > 0 makes it AdamW:
    each step also multiplies the tensor by 1 - lr_t * weight_decay, a pull toward zero in
    the tensor's own units that the gradient's scale does not change. pool in (0, 1] makes it
    PooledAdam: the second moment is partly shared over the tensor's entries (over each
    label's entries of pool_groups [numel] when given)."""
    if not lr > 0:
        raise ValueError(f"learning rate must be > 0, got {lr}")
    if not eps > 0:  # a zero eps divides 0 by 0 wherever a gradient is zero
        raise ValueError(f"Adam eps must be > 0, got {eps}")
    if not (math.isfinite(weight_decay) and weight_decay >= 0.0):
        raise ValueError(f"weight decay must be >= 0, got {weight_decay}")
    if not 0.0 <= pool <= 1.0:
        raise ValueError(f"pool must be in [0, 1], got {pool}")
    warmup_linear_decay(0, total_steps, warmup_steps, final_factor)  # validate early
    if pool > 0:
        if pool_groups is not None and pool_groups.shape != (param.numel(),):
            raise ValueError(f"pool_groups must hold one label per entry ({param.numel()}), got {tuple(pool_groups.shape)}")
        opt = PooledAdam([param], lr, pool, eps=eps, weight_decay=weight_decay, groups=pool_groups)
    elif weight_decay > 0:
        opt = torch.optim.AdamW([param], lr=lr, eps=eps, weight_decay=weight_decay)
    else:
        opt = torch.optim.Adam([param], lr=lr, eps=eps)
    return opt, _scheduler(opt, total_steps, warmup_steps, final_factor)


def _scheduler(opt: torch.optim.Optimizer, total_steps: int, warmup_steps: int,
               final_factor: float) -> torch.optim.lr_scheduler.LambdaLR:
    return torch.optim.lr_scheduler.LambdaLR(
        opt, partial(warmup_linear_decay, total_steps=total_steps, warmup_steps=warmup_steps,
                     final_factor=final_factor))
