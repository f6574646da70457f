"""The attention policy network (SPEC §5): encoders, cross encoders, glimpses, pointer decoder."""
from __future__ import annotations

import math
import threading
import warnings
from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F
from torch import nn

from ..reading import short
from .features import AGENT_FEATURES, K_MAX, MAX_AGENTS, MAX_TASKS, SCALES, TASK_FEATURES, task_features

TASK_POS = slice(2 * K_MAX, 2 * K_MAX + 2)  # task rows: position relative to the decider
AGENT_POS = slice(K_MAX + 3, K_MAX + 5)  # agent rows: position relative to the decider
TRAVEL_SLOPE_SCALE = 50.0  # travel_bias slopes per unit of distance (positions are in the unit square)
# parameters of options that start at zero (the same function as without them): a checkpoint that
# lacks them may be loaded into a network that has them
ZERO_INIT_PARAMS = frozenset({"travel_slope"})
GREEDY_DEPOT = ("argmax", "majority")  # the values of ModelConfig.greedy_depot


@dataclass
class ModelConfig:
    d_model: int = 128
    heads: int = 8
    ff_hidden: int = 256
    clip: float = 10.0
    task_features: int = TASK_FEATURES
    agent_features: int = AGENT_FEATURES
    # project option (off in every shipped config): the two cross encoders add -slope_h x the
    # robot-task distance to each head's attention scores (slopes learnt, starting at 0, so a
    # checkpoint without them loads unchanged and starts from the same function)
    travel_bias: bool = False
    # units of the observation (rl/features.py): "fixed" (the paper generators' scales) or
    # "mission" (scale-free: times, lengths and capabilities in units of the mission itself)
    scale: str = "fixed"
    # the observation window (rl/features.py): a mission with more tasks or robots is observed
    # through its decider's nearest ``window_tasks`` tasks and ``window_agents`` robots. The
    # network attends over any number of rows, so the window is a choice made at inference as
    # much as in training (docs/training.md, "The observation window")
    window_tasks: int = MAX_TASKS
    window_agents: int = MAX_AGENTS
    # greedy decoding (RL(g.), lookahead's own choice, live agents, validation): "argmax" takes
    # the most likely row of [depot, tasks]; "majority" goes to the depot only when its
    # probability is at least 1/2 and otherwise takes the most likely task, so that many
    # similar tasks sharing the probability do not lose to the one depot row
    # (rl/rollout.py:greedy_rows; docs/training.md, "Deciding the depot on its total probability")
    greedy_depot: str = "argmax"

    def to_dict(self) -> dict:
        return asdict(self)

    def view(self) -> dict:
        """The keyword arguments of ``features.observe`` / ``batch_observations`` that this network
        was built to read: units and window."""
        return {"scale": self.scale, "max_tasks": self.window_tasks, "max_agents": self.window_agents}

    @classmethod
    def from_dict(cls, d: object, where: str = "model") -> "ModelConfig":
        """A validated config (from a training config or a checkpoint): every value of the right
        type and range. Raises ValueError("<where>.<key>: expected ...") naming the key."""
        if not isinstance(d, dict):
            raise ValueError(f"{where}: expected a mapping, got {type(d).__name__}")
        fields = cls.__dataclass_fields__
        for k in d:
            if k not in fields:
                raise ValueError(f"{where}: unknown key {short(k)} (expected one of {sorted(fields)})")
        c = cls(**d)

        def whole(k: str, lo: int, hi: int) -> None:
            v = getattr(c, k)
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
                raise ValueError(f"{where}.{k}: expected an integer in [{lo}, {hi}], got {short(v)}")

        whole("d_model", 1, 4096)
        whole("heads", 1, 64)
        if c.d_model % c.heads:
            raise ValueError(f"{where}.heads: expected a divisor of d_model ({c.d_model}), got {c.heads}")
        whole("ff_hidden", 1, 16384)
        whole("window_tasks", 1, 100_000)
        whole("window_agents", 1, 100_000)
        for k, want in (("task_features", task_features(c.scale)), ("agent_features", AGENT_FEATURES)):
            if type(getattr(c, k)) is not int or getattr(c, k) != want:
                raise ValueError(f"{where}.{k}: expected {want} (the observation of this hmrta version), "
                                 f"got {short(getattr(c, k))}")
        if isinstance(c.clip, bool) or not isinstance(c.clip, (int, float)) or not 0 < c.clip <= 1e4:
            raise ValueError(f"{where}.clip: expected a number in (0, 10000], got {short(c.clip)}")
        if not isinstance(c.travel_bias, bool):
            raise ValueError(f"{where}.travel_bias: expected true or false, got {short(c.travel_bias)}")
        if c.scale not in SCALES:
            raise ValueError(f"{where}.scale: expected one of {', '.join(SCALES)}, got {short(c.scale)}")
        if c.greedy_depot not in GREEDY_DEPOT:
            raise ValueError(f"{where}.greedy_depot: expected one of {', '.join(GREEDY_DEPOT)}, "
                             f"got {short(c.greedy_depot)}")
        return c


class Block(nn.Module):
    """MHA -> residual + LayerNorm -> gated (GLU) feed-forward -> residual + LayerNorm."""

    def __init__(self, d: int, heads: int, ff: int | None):
        super().__init__()
        self.mha = nn.MultiheadAttention(d, heads, batch_first=True)
        self.ln1 = nn.LayerNorm(d)
        self.ff = ff is not None
        if self.ff:
            self.ff_in = nn.Linear(d, 2 * ff)
            self.ff_out = nn.Linear(ff, d)
            self.ln2 = nn.LayerNorm(d)

    def forward(self, q: torch.Tensor, kv: torch.Tensor, kv_ignore: torch.Tensor,
                bias: torch.Tensor | None = None) -> torch.Tensor:
        # q [B, Lq, d], kv [B, Lk, d], kv_ignore [B, Lk] (True = padding / masked),
        # bias [B * heads, Lq, Lk] added to the attention scores (optional)
        att = self.attend(q, kv, kv_ignore, bias)  # [B, Lq, d]
        h = self.ln1(q + att)  # [B, Lq, d]
        if not self.ff:
            return h
        x, g = self.ff_in(h).chunk(2, dim=-1)  # [B, Lq, ff] x2
        return self.ln2(h + self.ff_out(x * F.gelu(g)))  # [B, Lq, d]

    def attend(self, q: torch.Tensor, kv: torch.Tensor, kv_ignore: torch.Tensor,
               bias: torch.Tensor | None) -> torch.Tensor:
        """Multi-head attention of ``q`` over ``kv`` with the parameters of ``self.mha``: what
        ``nn.MultiheadAttention`` computes, written out so that training, evaluation and the traced
        inference graph run one path. (In evaluation without gradients the module would switch
        self-attention to its fused kernel, whose masked softmax costs a fifth of a forward at 100
        tasks; docs/results.md#scale-offline.)"""
        mha = self.mha
        B, Lq, d = q.shape
        Lk, h = kv.shape[1], mha.num_heads
        w, b = mha.in_proj_weight, mha.in_proj_bias  # [3d, d], [3d]
        if q is kv:  # self-attention: one packed projection
            qp, kp, vp = F.linear(q, w, b).chunk(3, dim=-1)  # [B, Lq, d] x3
        else:
            qp = F.linear(q, w[:d], b[:d])  # [B, Lq, d]
            kp, vp = F.linear(kv, w[d:], b[d:]).chunk(2, dim=-1)  # [B, Lk, d] x2
        qp = qp.view(B, Lq, h, d // h).transpose(1, 2)  # [B, h, Lq, d/h]
        kp = kp.view(B, Lk, h, d // h).transpose(1, 2)  # [B, h, Lk, d/h]
        vp = vp.view(B, Lk, h, d // h).transpose(1, 2)  # [B, h, Lk, d/h]
        if bias is None:
            mask = ~kv_ignore[:, None, None, :]  # [B, 1, 1, Lk] True = attend
        else:
            mask = bias.view(B, h, Lq, Lk).masked_fill(kv_ignore[:, None, None, :], float("-inf"))
        out = F.scaled_dot_product_attention(qp, kp, vp, attn_mask=mask)  # [B, h, Lq, d/h]
        return mha.out_proj(out.transpose(1, 2).reshape(B, Lq, d))  # [B, Lq, d]

    def forward_one(self, q: torch.Tensor, kv: torch.Tensor, kv_ignore: torch.Tensor) -> torch.Tensor:
        """The block (built without feed-forward) for one query row ``q`` [B, 1, d], with the key
        and value projections folded into the query side. Per head, the score q_h . (W_k,h x + b_k,h) is
        (W_k,h^T q_h) . x plus a term equal for every row x, which the softmax cancels; and the
        attention-weighted values sum(p x W_v,h + b_v,h) are W_v,h (sum p x) + b_v,h, the weights
        summing to one. So the rows are read twice (scores, weighted sum) instead of being
        projected, O(h L d) instead of O(L d^2): the same function as ``forward`` in exact
        arithmetic, equal to float rounding (tests/policy/rl/test_rl.py). The decoder's two
        layers over 126 context rows and 101 task rows were a fifth of a forward's arithmetic
        (docs/results.md#scale-offline)."""
        mha = self.mha
        B, _, d = q.shape
        h = mha.num_heads
        w, b = mha.in_proj_weight, mha.in_proj_bias  # [3d, d], [3d]
        qp = F.linear(q[:, 0], w[:d], b[:d]).view(B, h, d // h)  # [B, h, d/h]
        u = torch.einsum("bhe,hed->bhd", qp, w[d:2 * d].view(h, d // h, d))  # [B, h, d]
        s = torch.bmm(u, kv.transpose(1, 2)) / math.sqrt(d // h)  # [B, h, L]
        p = torch.softmax(s.masked_fill(kv_ignore[:, None, :], float("-inf")), dim=-1)  # [B, h, L]
        z = torch.bmm(p, kv)  # [B, h, d] the attention-weighted rows of each head
        o = torch.einsum("bhd,hed->bhe", z, w[2 * d:].view(h, d // h, d)) + b[2 * d:].view(h, d // h)  # [B, h, d/h]
        return self.ln1(q + mha.out_proj(o.reshape(B, 1, d)))  # [B, 1, d]


class PolicyNet(nn.Module):
    def __init__(self, cfg: ModelConfig = ModelConfig()):
        super().__init__()
        d, h, ff = cfg.d_model, cfg.heads, cfg.ff_hidden
        self.cfg = cfg
        self.task_embed = nn.Linear(cfg.task_features, d)
        self.agent_embed = nn.Linear(cfg.agent_features, d)
        self.task_enc = Block(d, h, ff)  # tasks attend to tasks
        self.agent_enc = Block(d, h, ff)  # agents attend to agents
        self.task_cross = Block(d, h, ff)  # tasks attend to agents
        self.agent_cross = Block(d, h, ff)  # agents attend to tasks
        self.query = nn.Linear(3 * d, d)
        self.dec1 = Block(d, h, None)  # decider attends to the task-agent context
        self.dec2 = Block(d, h, None)  # ... then to the admissible tasks
        self.wq = nn.Linear(d, d, bias=False)
        self.wk = nn.Linear(d, d, bias=False)
        if cfg.travel_bias:
            self.travel_slope = nn.Parameter(torch.zeros(2, h))  # [task_cross / agent_cross, heads]

    def forward(self, tasks, agents, task_valid, agent_valid, action_mask, decider) -> torch.Tensor:
        """Logits over [depot, tasks] ([B, T]); inadmissible entries are -inf."""
        t_ign, a_ign = ~task_valid, ~agent_valid  # [B, T], [B, N]
        te = self.task_embed(tasks)  # [B, T, d]
        ae = self.agent_embed(agents)  # [B, N, d]
        te = self.task_enc(te, te, t_ign)  # [B, T, d]
        ae = self.agent_enc(ae, ae, a_ign)  # [B, N, d]
        tb = ab = None
        if self.cfg.travel_bias:
            dist = torch.cdist(tasks[..., TASK_POS].float(), agents[..., AGENT_POS].float())  # [B, T, N]
            s = TRAVEL_SLOPE_SCALE * self.travel_slope  # [2, h] (scaled: Adam moves each slope by ~lr per step)
            tb = (-s[0, None, :, None, None] * dist[:, None]).flatten(0, 1)  # [B*h, T, N]
            ab = (-s[1, None, :, None, None] * dist.transpose(1, 2)[:, None]).flatten(0, 1)  # [B*h, N, T]
        tx = self.task_cross(te, ae, a_ign, tb)  # [B, T, d]
        ax = self.agent_cross(ae, te, t_ign, ab)  # [B, N, d]
        tg = _masked_mean(tx, task_valid)  # [B, d]
        ag = _masked_mean(ax, agent_valid)  # [B, d]
        me = ax[torch.arange(ax.shape[0], device=decider.device), decider]  # [B, d]
        q = self.query(torch.cat([me, tg, ag], dim=-1)).unsqueeze(1)  # [B, 1, d]
        ctx = torch.cat([tx, ax], dim=1)  # [B, T + N, d]
        q = self.dec1.forward_one(q, ctx, torch.cat([t_ign, a_ign], dim=1))  # [B, 1, d]
        q = self.dec2.forward_one(q, tx, ~action_mask)  # [B, 1, d]
        r = self.wq(q[:, 0]) @ self.wk.weight  # [B, d] wq(q) . wk(x) = (wk^T wq(q)) . x
        compat = torch.bmm(tx, r[:, :, None])[:, :, 0] / math.sqrt(self.cfg.d_model)  # [B, T]
        logits = self.cfg.clip * torch.tanh(compat)  # [B, T]
        return logits.masked_fill(~action_mask, float("-inf"))


class TracedPolicy(nn.Module):
    """The inference form of a :class:`PolicyNet`: the same network traced by TorchScript on its
    first call and frozen (weights folded in as constants). One graph serves every batch size and
    observation window; what goes is the per-operation Python cost of the modules, about a third of
    a forward at the observation window (docs/results.md#scale-offline). The operations are the
    same, so the logits are bitwise equal to the network's (tests/policy/rl/test_rl.py). For
    inference only: the weights are frozen and no gradient flows. A network with the travel-bias
    option (off in every shipped config) runs as it is: its traced batches differ in the last bits.

    TorchScript is deprecated upstream; torch is pinned (requirements.txt), and the deprecation
    notices of the trace are silenced here."""

    def __init__(self, net: PolicyNet):
        super().__init__()
        self.net = net.eval()
        self.cfg = net.cfg
        object.__setattr__(self, "_graph", None)  # not a submodule: no second copy in state_dict
        object.__setattr__(self, "_lock", threading.Lock())

    def forward(self, tasks, agents, task_valid, agent_valid, action_mask, decider) -> torch.Tensor:
        args = (tasks, agents, task_valid, agent_valid, action_mask, decider)
        if self.cfg.travel_bias:
            return self.net(*args)
        if self._graph is None:
            with self._lock:
                if self._graph is None:
                    with torch.no_grad(), warnings.catch_warnings():
                        warnings.simplefilter("ignore", DeprecationWarning)
                        warnings.simplefilter("ignore", torch.jit.TracerWarning)  # shape checks inside attention
                        graph = torch.jit.freeze(torch.jit.trace(self.net, args, check_trace=False))
                    object.__setattr__(self, "_graph", graph)
        return self._graph(*args)


def _masked_mean(x: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    # x [B, L, d], valid [B, L] -> [B, d]
    w = valid.to(x.dtype).unsqueeze(-1)  # [B, L, 1]
    return (x * w).sum(1) / w.sum(1).clamp_min(1.0)
