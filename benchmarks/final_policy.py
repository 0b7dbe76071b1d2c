"""
What the final models of finished ``benchmarks/learning_curves.py`` runs do, beyond their learning curves: the
measurements behind section 7 of ``benchmarks/learning.md`` (DACERF against SAC on DMC reacher-easy).

For each checkpoint folder (``<out>/checkpoints/<env>/<variant>-seed<N>``, DACERF or any SB3 / sb3-contrib model)
it prints:

- ``episodes``: the return of ``--episodes`` unseen episodes (reset seeds 50,000 on), deterministic and stochastic
  actions, and how many of them end above ``--high`` and below ``--low``;
- ``replay``: the share of steps with a positive reward in each 10k-step block of the replay buffer (how often
  the agent's own rollouts found reward: the exploration side);
- ``critic``: at the state each deterministic episode has reached after ``--settle`` steps, the critic's
  ``min_j Q_j(s, π(s))``, its maximum over a grid of actions (action spaces of at most 2 dimensions), the distance
  to the target where the observation has a ``to_target`` part (DMC reacher), and for DACERF the mean move of the
  Langevin targets ``a* - a_B`` and their gain ``Q(s, a*) - Q(s, a_B)`` from replay-like actions ``π(s) + noise``::

    python benchmarks/final_policy.py benchmarks/results/heldout-100k/checkpoints/DMC-reacher-easy-v0/dacerf-seed0 \\
        benchmarks/results/heldout-100k/checkpoints/DMC-reacher-easy-v0/sac-seed0

A checkpoint holds pickles: read only checkpoints you made or trust.
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path
from typing import Any

import _checkout  # noqa: F401  (the repository's sb3_dacerf, not an installed copy)
import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))  # learning_curves.py

FIRST_EPISODE_SEED = 50_000


def load_final_model(folder: Path) -> Any:
    """The model of a checkpoint folder, its algorithm read from the folder's ``<variant>-seed<N>`` name."""
    from learning_curves import VARIANTS, algorithm_class

    match = re.fullmatch(r"(.+)-seed\d+", folder.name)
    if match is None or match.group(1) not in VARIANTS or not (folder / "model.zip").is_file():
        raise SystemExit(
            f"{folder} is not a checkpoint of learning_curves.py: expected a folder <variant>-seed<N> with a "
            f"model.zip, <variant> one of {', '.join(VARIANTS)}."
        )
    algorithm: Any = algorithm_class(VARIANTS[match.group(1)][0])
    return algorithm.load(folder / "model.zip", device="cpu")


def episodes(model: Any, env_id: str, n_episodes: int, high: float, low: float) -> list[str]:
    """Deterministic and stochastic returns of ``n_episodes`` unseen episodes."""
    import gymnasium as gym

    env = gym.make(env_id)
    lines = []
    for deterministic in (True, False):
        returns = []
        for episode in range(n_episodes):
            obs, _ = env.reset(seed=FIRST_EPISODE_SEED + episode)
            total, done = 0.0, False
            while not done:
                action, _ = model.predict(obs, deterministic=deterministic)
                obs, reward, terminated, truncated, _ = env.step(action)
                total += float(reward)
                done = terminated or truncated
            returns.append(total)
        values = np.array(returns)
        lines.append(
            f"  episodes ({'deterministic' if deterministic else 'stochastic'}): mean {values.mean():.1f}, "
            f"above {high:g} in {(values > high).sum()}/{n_episodes}, below {low:g} in {(values < low).sum()}/{n_episodes}"
        )
    env.close()
    return lines


def replay(folder: Path) -> list[str]:
    """Share of rewarded steps per 10k-step block of the checkpoint's replay buffer."""
    with np.load(folder / "replay_buffer.npz") as arrays:
        rewards = arrays["rewards"][:, 0]
    shares = " ".join(f"{(rewards[i : i + 10_000] > 0).mean():.3f}" for i in range(0, len(rewards), 10_000))
    return [f"  replay: share of steps with reward > 0 per 10k steps: {shares}"]


def critic(model: Any, env_id: str, n_episodes: int, settle: int, grid_points: int = 41) -> list[str]:
    """The critic at the states the deterministic episodes have reached after ``settle`` steps."""
    import gymnasium as gym
    import torch as th

    from sb3_dacerf import DACERF

    def min_q(critic: Any, observations: Any, actions: Any) -> Any:
        return critic.q_values(observations, actions).min(dim=0).values

    env = gym.make(env_id)
    action_dim = int(np.prod(env.action_space.shape or ()))
    grid = None
    if action_dim <= 2:
        axis = np.linspace(-1.0, 1.0, grid_points, dtype=np.float32)
        grid = th.as_tensor(np.stack(np.meshgrid(*[axis] * action_dim, indexing="ij"), -1).reshape(-1, action_dim))
    lines = []
    for episode in range(n_episodes):
        obs, _ = env.reset(seed=FIRST_EPISODE_SEED + episode)
        total = 0.0
        for _ in range(settle):
            action, _ = model.predict(obs, deterministic=True)
            obs, reward, *_ = env.step(action)
            total += float(reward)
        observation = th.as_tensor(obs[None], dtype=th.float32)
        action_pi = th.as_tensor(model.policy.scale_action(model.predict(obs, deterministic=True)[0])[None])
        with th.no_grad():
            columns = [f"  state after {settle} steps of episode {episode} (return so far {total:.0f})"]
            if obs.shape == (6,) and "reacher" in env_id:  # DMC reacher: position (2), to_target (2), velocity (2)
                columns.append(f"distance to target {np.linalg.norm(obs[2:4]):.2f}, |velocity| {np.abs(obs[4:6]).max():.2f}")
            columns.append(
                f"|π(s)| {action_pi.abs().max():.3f}, Q(s, π(s)) {min_q(model.critic, observation, action_pi).item():.1f}"
            )
            if grid is not None:
                q_grid = min_q(model.critic, observation.expand(len(grid), -1), grid).squeeze(1)
                columns.append(f"grid max Q {q_grid.max().item():.1f} at {np.round(grid[int(q_grid.argmax())].numpy(), 2)}")
        if isinstance(model, DACERF):
            th.manual_seed(episode)
            observations = observation.expand(256, -1)
            actions = (action_pi + model.actor.exploration_std.detach() * th.randn(256, action_dim)).clamp(-1.0, 1.0)
            targets = model.langevin_targets(observations, actions)
            with th.no_grad():
                gain = (min_q(model.critic, observations, targets) - min_q(model.critic, observations, actions)).mean().item()
            columns.append(f"Langevin mean move {np.round((targets - actions).mean(0).numpy(), 2)}, gain {gain:.2f}")
        lines.append("; ".join(columns))
    env.close()
    return lines


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folders", nargs="+", type=Path, help="checkpoint folders <out>/checkpoints/<env>/<variant>-seed<N>")
    parser.add_argument("--episodes", type=int, default=20, help="unseen episodes per model (default: 20)")
    parser.add_argument("--high", type=float, default=800.0, help="count the episodes above this return (default: 800)")
    parser.add_argument("--low", type=float, default=100.0, help="count the episodes below this return (default: 100)")
    parser.add_argument("--critic-episodes", type=int, default=8, help="episodes of the critic part (default: 8; 0: none)")
    parser.add_argument("--settle", type=int, default=500, help="steps before the critic part looks (default: 500)")
    args = parser.parse_args(argv)

    import torch as th

    import sb3_dacerf  # noqa: F401  (registers the DMC-* ids)

    th.set_num_threads(1)
    for folder in args.folders:
        model = load_final_model(folder)
        env_id = folder.parent.name
        print(f"{env_id} {folder.name} at {model.num_timesteps} steps", flush=True)
        for line in [*episodes(model, env_id, args.episodes, args.high, args.low), *replay(folder)]:
            print(line, flush=True)
        if args.critic_episodes > 0:
            for line in critic(model, env_id, args.critic_episodes, args.settle):
                print(line, flush=True)


if __name__ == "__main__":
    main()
