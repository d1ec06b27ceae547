#!/usr/bin/env python3
"""The default PPO update in PyTorch from Python, timed in turn with `learner bench --algo ippo`.

The reference is written the way a PyTorch user writes PPO (CleanRL's `ppo_continuous_action.py`
shape): the same work as one update of the learner at the default configuration, on a
synthetic batch of the same shape (`learner bench`'s: 6 fragments × 200 steps × 30 agents,
91 observations, every agent alive):
  fold the batch into the running observation normaliser (float64), normalise (clip ±10);
  V(s) of every row and of the bootstrap rows, GAE (γ 0.999, λ 0.95) per fragment;
  5 epochs over shuffled minibatches of 512: Gaussian log-prob of a [256, 256] tanh policy with
  a global log-std, clipped surrogate (ε 0.3) on per-minibatch standardised advantages, value
  loss of a separate [256, 256] tanh critic clipped at ±10 around the old value, the entropy
  (coefficient 0, still computed, as the learner does for its statistics), torch.optim.Adam
  (lr 3e-4, eps 1e-5, PyTorch's default implementation), global gradient-norm clip 0.5, and the
  update's statistics (losses, entropy, approx. KL, clip fraction, gradient norm).
The reference avoids what would handicap it: the Gaussian is written out (no
torch.distributions objects), observations are normalised once per update, and the statistics
are kept as tensors and read back once per update rather than synchronised per minibatch.

Both sides get the same thread count (default 2, this machine's cores) and take turns
`--rounds` times so that drift of a shared machine falls on both. Prints one JSON line:
agent-steps of rollout per second of updating for each side (median and range over rounds) and
their ratio (learner / PyTorch; > 1: the learner is faster).

  .venv/bin/python scripts/bench-update-torch.py [--rounds 5] [--updates 3] [--threads 2]
      [--fused-adam] [-- extra `learner bench` flags, e.g. --set ppo.minibatch_size=1024]
Needs `make build` (target/release/learner) and the venv's PyTorch (`make run` installs it).
`--fused-adam` times torch.optim.Adam(fused=True) instead of the default.
"""
import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import time

import torch
from torch import nn

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

OBS_DIM, ACTION_DIM = 91, 2
STEPS, AGENTS, FRAGMENTS = 200, 30, 6
HIDDEN = 256
GAMMA, LAMBDA = 0.999, 0.95
CLIP, VALUE_CLIP, MAX_GRAD_NORM = 0.3, 10.0, 0.5
EPOCHS, MINIBATCH = 5, 512
LEARNING_RATE, ADAM_EPS = 3e-4, 1e-5
VALUE_COEF, ENTROPY_COEF = 1.0, 0.0
OBS_CLIP, OBS_VAR_EPS = 10.0, 1e-8
HALF_LOG_2PI = 0.5 * math.log(2 * math.pi)


def mlp(out_dim, out_gain):
    layers = []
    width = OBS_DIM
    for size, gain in ((HIDDEN, 2**0.5), (HIDDEN, 2**0.5), (out_dim, out_gain)):
        layer = nn.Linear(width, size)
        nn.init.orthogonal_(layer.weight, gain)
        nn.init.zeros_(layer.bias)
        layers += [layer, nn.Tanh()]
        width = size
    return nn.Sequential(*layers[:-1])


class Agent(nn.Module):
    def __init__(self):
        super().__init__()
        self.actor_mean = mlp(ACTION_DIM, 0.01)
        self.actor_log_std = nn.Parameter(torch.zeros(ACTION_DIM))
        self.critic = mlp(1, 1.0)
        self.obs_mean = torch.zeros(OBS_DIM, dtype=torch.float64)
        self.obs_var = torch.ones(OBS_DIM, dtype=torch.float64)
        self.obs_count = 1e-4

    def fold(self, obs):
        """Chan et al.'s parallel update of the running mean and variance."""
        batch = obs.double()
        mean, var, count = batch.mean(0), batch.var(0, unbiased=False), batch.shape[0]
        delta = mean - self.obs_mean
        total = self.obs_count + count
        self.obs_mean = self.obs_mean + delta * count / total
        m2 = self.obs_var * self.obs_count + var * count + delta**2 * self.obs_count * count / total
        self.obs_var = m2 / total
        self.obs_count = total

    def normalize(self, obs):
        mean, std = self.obs_mean.float(), (self.obs_var + OBS_VAR_EPS).sqrt().float()
        return ((obs - mean) / std).clamp(-OBS_CLIP, OBS_CLIP)

    def log_prob(self, x, actions):
        """Gaussian log-density of `actions` and the entropy, by hand (torch.distributions
        costs a Python object and argument checks per call)."""
        mean = self.actor_mean(x)
        log_std = self.actor_log_std.expand_as(mean)
        z = (actions - mean) / log_std.exp()
        log_prob = (-0.5 * z.square() - log_std - HALF_LOG_2PI).sum(-1)
        return log_prob, (log_std + 0.5 + HALF_LOG_2PI).sum(-1)


def synthetic_batch(agent, generator):
    cells = FRAGMENTS * STEPS * AGENTS
    obs = torch.rand(cells, OBS_DIM, generator=generator)
    with torch.no_grad():
        mean = agent.actor_mean(agent.normalize(obs))
        actions = mean + torch.randn(mean.shape, generator=generator)
        log_probs, _ = agent.log_prob(agent.normalize(obs), actions)
    return {
        "obs": obs,
        "actions": actions,
        "log_probs": log_probs,
        "rewards": torch.rand(FRAGMENTS, STEPS, AGENTS, generator=generator) * 3 - 1,
        "dones": torch.zeros(FRAGMENTS, STEPS, AGENTS),
        "bootstrap_obs": torch.rand(FRAGMENTS * AGENTS, OBS_DIM, generator=generator),
    }


def update(agent, optimizer, batch, generator):
    agent.fold(batch["obs"])
    obs = agent.normalize(batch["obs"])
    with torch.no_grad():
        values = agent.critic(obs).view(FRAGMENTS, STEPS, AGENTS)
        next_values = agent.critic(agent.normalize(batch["bootstrap_obs"])).view(FRAGMENTS, AGENTS)
    rewards, dones = batch["rewards"], batch["dones"]
    advantages = torch.zeros_like(rewards)
    last = torch.zeros(FRAGMENTS, AGENTS)
    for t in reversed(range(STEPS)):
        next_value = next_values if t == STEPS - 1 else values[:, t + 1]
        not_done = 1.0 - dones[:, t]
        delta = rewards[:, t] + GAMMA * next_value * not_done - values[:, t]
        last = delta + GAMMA * LAMBDA * not_done * last
        advantages[:, t] = last
    returns = (advantages + values).reshape(-1)
    advantages, values = advantages.reshape(-1), values.reshape(-1)
    actions, old_log_probs = batch["actions"], batch["log_probs"]

    n = obs.shape[0]
    stats = []
    for _ in range(EPOCHS):
        order = torch.randperm(n, generator=generator)
        for start in range(0, n, MINIBATCH):
            idx = order[start : start + MINIBATCH]
            new_log_probs, entropy = agent.log_prob(obs[idx], actions[idx])
            entropy = entropy.mean()
            log_ratio = new_log_probs - old_log_probs[idx]
            ratio = log_ratio.exp()
            with torch.no_grad():
                approx_kl = ((ratio - 1) - log_ratio).mean()
                clip_fraction = ((ratio - 1.0).abs() > CLIP).float().mean()
            adv = advantages[idx]
            adv = (adv - adv.mean()) / (adv.std() + 1e-8)
            pg_loss = torch.max(-adv * ratio, -adv * ratio.clamp(1 - CLIP, 1 + CLIP)).mean()
            new_values = agent.critic(obs[idx]).view(-1)
            v_unclipped = (new_values - returns[idx]) ** 2
            v_clipped = values[idx] + (new_values - values[idx]).clamp(-VALUE_CLIP, VALUE_CLIP)
            v_loss = 0.5 * torch.max(v_unclipped, (v_clipped - returns[idx]) ** 2).mean()
            loss = pg_loss - ENTROPY_COEF * entropy + VALUE_COEF * v_loss
            optimizer.zero_grad()
            loss.backward()
            grad_norm = nn.utils.clip_grad_norm_(agent.parameters(), MAX_GRAD_NORM)
            optimizer.step()
            stats.append(torch.stack([pg_loss.detach(), v_loss.detach(), entropy.detach(),
                                      approx_kl, clip_fraction, grad_norm]))
    # The update's statistics read back once (not a sync per minibatch).
    return n, torch.stack(stats).mean(0).tolist()


def time_torch(updates, fused):
    generator = torch.Generator().manual_seed(1)
    torch.manual_seed(1)
    agent = Agent()
    optimizer = torch.optim.Adam(agent.parameters(), lr=LEARNING_RATE, eps=ADAM_EPS, fused=fused or None)
    batch = synthetic_batch(agent, generator)
    update(agent, optimizer, batch, generator)  # warm-up, as `learner bench` does
    started = time.perf_counter()
    agent_steps = sum(update(agent, optimizer, batch, generator)[0] for _ in range(updates))
    return agent_steps / (time.perf_counter() - started)


def time_learner(binary, updates, threads, extra):
    command = [binary, "bench", "--algo", "ippo", "--updates", str(updates),
               "--set", f"learner.torch_threads={threads}", *extra]
    out = subprocess.run(command, check=True, capture_output=True, text=True).stdout
    return json.loads(out.strip().splitlines()[-1])["agent_steps_per_s"]


def summary(values):
    return {"median": round(statistics.median(values)), "min": round(min(values)), "max": round(max(values))}


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--updates", type=int, default=3, help="timed updates per round and side")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--fused-adam", action="store_true")
    parser.add_argument("--learner", default=os.path.join(ROOT, "target/release/learner"))
    parser.add_argument("extra", nargs="*", help="flags after -- go to `learner bench`")
    args = parser.parse_args()
    if not os.access(args.learner, os.X_OK):
        sys.exit(f"bench-update-torch: {args.learner} not found; run `make build` first")
    torch.set_num_threads(args.threads)
    learner, reference = [], []
    for round_ in range(args.rounds):
        learner.append(time_learner(args.learner, args.updates, args.threads, args.extra))
        reference.append(time_torch(args.updates, args.fused_adam))
        print(f"round {round_ + 1}/{args.rounds}: learner {learner[-1]:,.0f}, "
              f"PyTorch {reference[-1]:,.0f} agent-steps/s", file=sys.stderr)
    ratios = [a / b for a, b in zip(learner, reference)]
    print(json.dumps({
        "bench": "update_vs_pytorch",
        "threads": args.threads,
        "torch": torch.__version__,
        "adam": "fused" if args.fused_adam else "default",
        "learner_agent_steps_per_s": summary(learner),
        "pytorch_agent_steps_per_s": summary(reference),
        "ratio_median": round(statistics.median(ratios), 3),
        "ratio_min": round(min(ratios), 3),
        "ratio_max": round(max(ratios), 3),
    }))


if __name__ == "__main__":
    main()
