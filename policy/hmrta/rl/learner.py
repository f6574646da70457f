"""The learner every training algorithm shares: the network, its Adam optimiser, the moving
average of the weights (``train.ema``), the clipped update, the device and the training random
streams (numpy for data and decision orders, a torch generator for sampled rollouts)."""
from __future__ import annotations

import copy
from typing import Callable

import numpy as np
import torch

from .config import TrainConfig
from .model import PolicyNet


class Learner:
    def __init__(self, cfg: TrainConfig, device: torch.device, log: Callable[[str], None] = print):
        self.cfg, self.device, self.log = cfg, device, log
        seed = int(cfg.seed)
        torch.manual_seed(seed)
        self.model = PolicyNet(cfg.model).to(device)
        self.opt = torch.optim.Adam(self.model.parameters(), lr=cfg.train.lr)
        self.np_rng = np.random.default_rng(seed)
        self.torch_gen = torch.Generator().manual_seed(seed)
        self.ema: dict[str, torch.Tensor] | None = None  # averaged weights (train.ema > 0), from the first update

    @property
    def amp(self) -> bool:
        """bfloat16 autocast for collection, re-scoring and replay (``train.amp``, on the CPU only)."""
        return self.cfg.train.amp and self.device.type == "cpu"

    def set_lr(self, lr: float) -> None:
        for g in self.opt.param_groups:
            g["lr"] = lr

    def optimizer_step(self) -> None:
        """One optimiser update, then (``train.ema`` > 0) the moving average of the weights."""
        self.opt.step()
        decay = float(self.cfg.train.ema)
        if decay <= 0:
            return
        with torch.no_grad():
            if self.ema is None:
                self.ema = {k: v.detach().clone() for k, v in self.model.state_dict().items()}
            else:
                for k, v in self.model.state_dict().items():
                    if v.is_floating_point():
                        self.ema[k].mul_(decay).add_(v.detach(), alpha=1.0 - decay)
                    else:
                        self.ema[k].copy_(v)

    def clipped_step(self, clip: float, where: str) -> None:
        """Clip the gradient norm, update unless it is non-finite (never let one bad batch poison
        the weights; ``where`` names the iteration in the log), clear the gradients."""
        gnorm = torch.nn.utils.clip_grad_norm_(self.model.parameters(), clip)
        if torch.isfinite(gnorm):
            self.optimizer_step()
        else:
            self.log(f"{where}: non-finite gradient, update skipped")
        self.opt.zero_grad(set_to_none=True)

    def replay_steps(self, buffer: list[dict[str, torch.Tensor]], steps: int, batch_size: int, clip: float,
                     where: str) -> float:
        """Cross-entropy minibatch steps on replayed (observation, target) rows: target actions
        (long) or target distributions over the admissible actions (float, zero elsewhere);
        autocast as collection (:attr:`amp`)."""
        self.model.train()
        losses = []
        for _ in range(steps):
            entry = buffer[int(self.np_rng.integers(len(buffer)))]
            n = len(entry["target"])
            idx = torch.as_tensor(self.np_rng.permutation(n)[:batch_size])
            batch = {k: v[idx].to(self.device) for k, v in entry.items()}
            target = batch.pop("target")
            with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.amp):
                logits = self.model(**batch).float()  # [b, T]
            if target.dtype == torch.long:  # target actions
                loss = torch.nn.functional.cross_entropy(logits, target)
            else:  # target distributions over the admissible actions (zero elsewhere)
                logp = torch.log_softmax(logits, -1).masked_fill(~batch["action_mask"], 0.0)  # [b, T]
                loss = -(target * logp).sum(-1).mean()
            loss.backward()
            self.clipped_step(clip, where)
            losses.append(float(loss.detach()))
        return float(np.mean(losses))

    def policy_weights(self) -> dict[str, torch.Tensor]:
        """The weights that are validated and shipped: the moving average when there is one."""
        return self.ema if self.ema is not None else self.model.state_dict()

    def eval_model(self) -> PolicyNet:
        """The network with ``policy_weights`` (the training model itself without averaging)."""
        if self.ema is None:
            return self.model.eval()
        m = copy.deepcopy(self.model)
        m.load_state_dict(self.ema)
        return m.eval()
