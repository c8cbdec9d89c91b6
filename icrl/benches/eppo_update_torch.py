"""One EPPO update (discrete actions, SafeDarkRoom shapes) in PyTorch eager:
the same model, losses and optimiser step as icrl/src/eppo/ (losses.rs,
replay.rs, mod.rs::Learner::update), for the benchmark in
icrl/benches/model.rs, which runs this script with the shapes of the preset
it measures and compares.

Mirrors the current update: tokens carry the arrived observation (token width
2 * obs + actions + 4), n-step TD targets whose sums stop where the bootstrap
masks stop, a cost target that never bootstraps past an episode's end, the
penalty in reward units (lambda x reward_scale x Qc), critic_weight, global
gradient-norm clipping, Adam, the Polyak update.

Usage: python eppo_update_torch.py --batch 8 --seq 480 --layers 2 --d-ff 128 \
    --reps 5 --threads 1
Prints `torch_update_seconds <median wall>` and `torch_update_cpu_seconds
<median process CPU time>` (CPU time is the fair figure on a loaded machine).
"""

import argparse
import copy
import math
import statistics
import time

import torch
import torch.nn as nn
import torch.nn.functional as F

OBS, ACTIONS = 2, 5
TOKEN = 2 * OBS + ACTIONS + 4


class Block(nn.Module):
    def __init__(self, d, heads, d_ff):
        super().__init__()
        self.heads = heads
        self.ln_1 = nn.LayerNorm(d)
        self.c_attn = nn.Linear(d, 3 * d)
        self.c_proj = nn.Linear(d, d)
        self.ln_2 = nn.LayerNorm(d)
        self.c_fc = nn.Linear(d, d_ff)
        self.mlp_proj = nn.Linear(d_ff, d)

    def forward(self, x):
        b, t, d = x.shape
        q, k, v = self.c_attn(self.ln_1(x)).split(d, dim=2)
        q, k, v = (z.view(b, t, self.heads, d // self.heads).transpose(1, 2) for z in (q, k, v))
        y = F.scaled_dot_product_attention(q, k, v, is_causal=True)
        x = x + self.c_proj(y.transpose(1, 2).contiguous().view(b, t, d))
        return x + self.mlp_proj(F.gelu(self.c_fc(self.ln_2(x))))


def head(d, hidden, out):
    return nn.Sequential(nn.Linear(d, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, out))


class Net(nn.Module):
    def __init__(self, d, heads, layers, d_ff, max_len, hidden, critics=2):
        super().__init__()
        self.critics = critics
        self.enc_1 = nn.Linear(TOKEN, hidden)
        self.enc_2 = nn.Linear(hidden, d)
        pos = torch.arange(max_len).float().unsqueeze(1)
        inv = torch.exp(torch.arange(0, d, 2).float() * (-math.log(10000.0) / d))
        ang = pos * inv
        self.register_buffer("pe", torch.stack([ang.sin(), ang.cos()], 2).view(max_len, d))
        self.h = nn.ModuleList(Block(d, heads, d_ff) for _ in range(layers))
        self.ln_f = nn.LayerNorm(d)
        self.actor = head(d, hidden, ACTIONS)
        self.critic = head(d, hidden, critics * ACTIONS)
        self.cost_critic = head(d, hidden, critics * ACTIONS)

    def encode(self, tokens):
        t = tokens.shape[1]
        x = F.dropout(self.enc_2(F.gelu(self.enc_1(tokens))) + self.pe[:t], 0.05, self.training)
        for block in self.h:
            x = block(x)
        return self.ln_f(x)

    def values(self, head, h):
        return head(h).view(*h.shape[:-1], self.critics, ACTIONS)


def next_step(x):
    return torch.cat([x[:, 1:], torch.zeros_like(x[:, :1])], 1)


def n_step_targets(r, boot, td_valid, v_next, gamma, n):
    y = r + gamma * boot * v_next
    valid_next = next_step(td_valid)
    for _ in range(1, n):
        ahead = valid_next * next_step(y) + (1 - valid_next) * v_next
        y = r + gamma * boot * ahead
    return y


def masked_mean(x, m):
    return (x * m).sum() / m.sum().clamp_min(1.0)


def update(net, target, opt, batch, lam, args):
    tokens, actions, rewards, costs, violated, valid, td_valid, boot, cost_boot = batch
    h = net.encode(tokens)
    with torch.no_grad():
        ht = target.encode(tokens)
        pi_t = target.actor(ht).softmax(-1).unsqueeze(2)
        v = (target.values(target.critic, ht) * pi_t).sum(-1).amin(-1)
        vc = (target.values(target.cost_critic, ht) * pi_t).sum(-1).mean(-1)
        y = n_step_targets(rewards, boot, td_valid, next_step(v), args.gamma, args.n_step)
        yc = n_step_targets(costs, cost_boot, td_valid, next_step(vc), args.gamma, args.n_step)
    q_all = net.values(net.critic, h)
    qc_all = net.values(net.cost_critic, h)
    idx = actions.view(*actions.shape, 1, 1).expand(-1, -1, net.critics, 1)
    q_taken = q_all.gather(3, idx).squeeze(3)
    qc_taken = qc_all.gather(3, idx).squeeze(3)
    logp = net.actor(h).log_softmax(-1)
    pi = logp.exp()
    penalty = lam * args.reward_scale
    per_action = -q_all.detach().amin(2) + qc_all.detach().mean(2) * violated.unsqueeze(-1) * penalty
    entropy = -(pi * logp).sum(-1)
    objective = (pi * per_action).sum(-1) - args.entropy_coef * entropy
    m = td_valid.unsqueeze(-1).expand(-1, -1, net.critics)
    lv = masked_mean((q_taken - y.unsqueeze(-1)) ** 2, m)
    lc = masked_mean((qc_taken - yc.unsqueeze(-1)) ** 2, m)
    lp = masked_mean(objective, valid)
    loss = (lv + lc) * args.critic_weight + lp
    opt.zero_grad()
    loss.backward()
    torch.nn.utils.clip_grad_norm_(net.parameters(), 1.0)
    opt.step()
    with torch.no_grad():
        for t, o in zip(target.parameters(), net.parameters()):
            t.mul_(1 - args.tau).add_(o, alpha=args.tau)
    return float(lv), float(lc), float(lp)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--seq", type=int, default=480)
    ap.add_argument("--d-model", type=int, default=64)
    ap.add_argument("--heads", type=int, default=8)
    ap.add_argument("--layers", type=int, default=2)
    ap.add_argument("--d-ff", type=int, default=128)
    ap.add_argument("--hidden", type=int, default=64)
    ap.add_argument("--n-step", type=int, default=1)
    ap.add_argument("--gamma", type=float, default=0.99)
    ap.add_argument("--tau", type=float, default=0.005)
    ap.add_argument("--entropy-coef", type=float, default=0.05)
    ap.add_argument("--reward-scale", type=float, default=10.0)
    ap.add_argument("--critic-weight", type=float, default=1.0)
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    b, l = args.batch, args.seq
    net = Net(args.d_model, args.heads, args.layers, args.d_ff, l, args.hidden)
    target = copy.deepcopy(net).eval()
    for p in target.parameters():
        p.requires_grad_(False)
    opt = torch.optim.Adam(net.parameters(), lr=3e-4, betas=(0.9, 0.99), eps=1e-8)
    ones = torch.ones(b, l)
    ends = torch.zeros(b, l)
    ends[:, 29::30] = 1.0  # episodes of 30 steps
    batch = (
        torch.randn(b, l, TOKEN),
        torch.randint(0, ACTIONS, (b, l)),
        (torch.rand(b, l) < 0.01).float() * args.reward_scale,
        (torch.rand(b, l) < 0.2).float(),
        (torch.rand(b, l) < 0.5).float(),
        ones,
        ones,
        ones,
        ones - ends,
    )
    update(net, target, opt, batch, 0.5, args)  # warm-up
    times, cpu = [], []
    for _ in range(args.reps):
        start, start_cpu = time.perf_counter(), time.process_time()
        update(net, target, opt, batch, 0.5, args)
        times.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    print(f"torch_update_seconds {statistics.median(times):.4f}")
    print(f"torch_update_cpu_seconds {statistics.median(cpu):.4f}")


if __name__ == "__main__":
    main()
