"""Adam (Kingma & Ba, 2015) for the map, the dense tracker and the motion classifier, without
``torch.optim``.

The update is ``torch.optim.Adam``'s, op for op: its fused kernel (``fused=True``, CPU and CUDA)
or its single-tensor code (otherwise), so results are bit-identical to ``torch.optim.Adam`` with
the same arguments on CPU (on CUDA the non-fused path is torch's single-tensor one, not its default
multi-tensor one).  Why not ``torch.optim``: the first call into any of its optimisers imports
``torch._dynamo`` (every method is wrapped in ``torch._disable_dynamo``), 1.9 s on a 2-core CPU,
paid by every run at its first frame.  Only what the library uses is here: no weight decay,
AMSGrad, maximisation, gradient scaling or parameter groups.

``state_dict`` / ``load_state_dict`` use ``torch.optim``'s layout (``state`` keyed by parameter
position with ``step``, ``exp_avg``, ``exp_avg_sq``; ``param_groups``), so checkpoints written with
either load into the other.
"""

from __future__ import annotations

from typing import Iterable

import torch


class Adam:
    """Adam over ``params`` (tensors with ``requires_grad``); parameters whose ``grad`` is None at
    a step are left alone, their moments created at their first gradient (as ``torch.optim``)."""

    def __init__(self, params: Iterable[torch.Tensor], lr: float, betas: tuple = (0.9, 0.999),
                 eps: float = 1e-8, fused: bool = False):
        self.params = list(params)
        if not self.params:
            raise ValueError("Adam got an empty parameter list")
        if not lr >= 0 or not eps >= 0 or not all(0 <= b < 1 for b in betas):
            raise ValueError(f"Adam: invalid lr={lr}, betas={betas} or eps={eps}")
        self.lr, self.betas, self.eps = float(lr), (float(betas[0]), float(betas[1])), float(eps)
        self.fused = bool(fused)
        if self.fused and any(p.device.type not in ("cpu", "cuda") or not p.is_floating_point() for p in self.params):
            raise ValueError("Adam(fused=True) needs floating-point parameters on the CPU or a CUDA device")
        self.state: list[dict] = [{} for _ in self.params]

    def _moments(self, i: int) -> dict:
        st = self.state[i]
        if not st:
            p = self.params[i]
            # torch.optim keeps the fused kernel's step on the parameter's device, the single-tensor one's on the CPU
            st["step"] = torch.zeros((), dtype=torch.float32, device=p.device if self.fused else "cpu")
            st["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
            st["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
        return st

    @torch.no_grad()
    def step(self) -> None:
        live = [i for i, p in enumerate(self.params) if p.grad is not None]
        if not live:
            return
        beta1, beta2 = self.betas
        states = [self._moments(i) for i in live]
        if self.fused:
            for dev in dict.fromkeys(self.params[i].device for i in live):  # one kernel call per device
                idx = [k for k, i in enumerate(live) if self.params[i].device == dev]
                steps = [states[k]["step"] for k in idx]
                torch._foreach_add_(steps, 1)
                torch._fused_adam_([self.params[live[k]] for k in idx], [self.params[live[k]].grad for k in idx],
                                   [states[k]["exp_avg"] for k in idx], [states[k]["exp_avg_sq"] for k in idx],
                                   [], steps, amsgrad=False, lr=self.lr, beta1=beta1, beta2=beta2,
                                   weight_decay=0.0, eps=self.eps, maximize=False, grad_scale=None,
                                   found_inf=None)
            return
        for k, i in enumerate(live):
            p, st = self.params[i], states[k]
            grad, exp_avg, exp_avg_sq = p.grad, st["exp_avg"], st["exp_avg_sq"]
            st["step"] += 1
            exp_avg.lerp_(grad, 1 - beta1)
            exp_avg_sq.mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
            step = st["step"].item()
            step_size = self.lr / (1 - beta1 ** step)
            denom = (exp_avg_sq.sqrt() / (1 - beta2 ** step) ** 0.5).add_(self.eps)
            p.addcdiv_(exp_avg, denom, value=-step_size)

    def zero_grad(self, set_to_none: bool = True) -> None:
        for p in self.params:
            if p.grad is None:
                continue
            if set_to_none:
                p.grad = None
            else:
                p.grad.detach_().zero_()

    def state_dict(self) -> dict:
        return {"state": {i: dict(st) for i, st in enumerate(self.state) if st},
                "param_groups": [{"lr": self.lr, "betas": self.betas, "eps": self.eps, "weight_decay": 0,
                                  "amsgrad": False, "maximize": False, "foreach": None, "capturable": False,
                                  "differentiable": False, "fused": self.fused, "decoupled_weight_decay": False,
                                  "params": list(range(len(self.params)))}]}

    def load_state_dict(self, d: dict) -> None:
        """The moments and step counts of ``d`` (this class's or ``torch.optim.Adam``'s state dict of
        the same parameters); the learning rate and betas stay this optimiser's."""
        saved = d["state"]
        if any(int(i) >= len(self.params) for i in saved):
            raise ValueError(f"optimiser state for {len(saved)} parameters does not fit {len(self.params)}")
        self.state = [{} for _ in self.params]
        for i, st in saved.items():
            p = self.params[int(i)]
            if st["exp_avg"].shape != p.shape:
                raise ValueError(f"optimiser state of parameter {i} has shape {tuple(st['exp_avg'].shape)}, "
                                 f"the parameter {tuple(p.shape)}")
            self.state[int(i)] = {
                "step": st["step"].detach().to(torch.float32).to(p.device if self.fused else "cpu").clone(),
                "exp_avg": st["exp_avg"].detach().to(p.device, p.dtype).clone(),
                "exp_avg_sq": st["exp_avg_sq"].detach().to(p.device, p.dtype).clone(),
            }
