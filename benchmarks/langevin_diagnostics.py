"""
What the Langevin targets and the critics of a DACERF run do, measured on its replay data: the figures behind the
diagnoses of the scaling and driving results pages.

Reads a checkpoint that ``learning_curves.py --checkpoint-freq`` keeps (``<out>/checkpoints/<env>/<variant>-seed<k>``:
model, replay buffer, VecNormalize statistics; the checkpoint is unpickled, so only your own runs) of DACERF or SAC
and, on ``--batch`` transitions drawn from the last ``--last`` of the buffer, prints (the first three for DACERF):

- ``|∇_a Q|``: the mean and median magnitude per action coordinate of ``∇_a min_j Q_j`` at the replay actions;
- the Langevin targets ``a*`` of the model's own settings (Algorithm 1), their displacement from the replay actions
  split into what the gradient steps and what the noise contribute (summed over the steps, before the clip), the
  share of target and replay coordinates at an action bound, and ``min_j Q_j(s, a*) - min_j Q_j(s, a_B)``;
- the actor loss's weights on the same batch (:meth:`~sb3_dacerf.DACERF.actor_loss_terms`): ``κ`` beside the spread of
  ``Q(s, a_B)``, the mean ``λ_f``, both terms, and the norm of the imitation term's gradient on the actor over the
  improvement term's;
- the share of the policy's deterministic action coordinates beyond ±0.99 on the same states;
- on the last ``--episodes`` complete training episodes of the buffer: the critics' ``min_j Q_j(s_t, a_t)`` against the
  discounted return (at a time limit continued by the critics, as their targets are), both averaged over the steps.

    python benchmarks/langevin_diagnostics.py benchmarks/results/dmc-scaling/checkpoints/DMC-humanoid-stand-v0/dacerf-seed1
"""

import argparse
import sys
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import _checkout  # noqa: F401  (the repository's sb3_dacerf)
import numpy as np
import torch as th
from learning_curves import load_checkpoint
from stable_baselines3 import SAC

from sb3_dacerf import DACERF
from sb3_dacerf.common.persistence import saved_algorithm_name
from sb3_dacerf.common.twin_critic import frozen
from sb3_dacerf.dacerf.dacerf import langevin_targets, q_value_spread
from sb3_dacerf.dacerf.policies import MinQActionGradient

ALGORITHMS: dict[str, type] = {"dacerf": DACERF, "sac": SAC}


def langevin_parts(model: DACERF, observations: th.Tensor, actions: th.Tensor) -> dict[str, th.Tensor]:
    """
    The model's Langevin targets from ``actions`` (its own loop, :func:`~sb3_dacerf.dacerf.dacerf.langevin_targets`),
    with the sums over the steps of its gradient steps and of its noise (the noise drawn again from the same random
    state), ``∇_a Q`` at the replay actions and ``min_j Q_j`` at both ends.
    """
    gradient_of = MinQActionGradient(model.critic, observations)
    gradients: list[th.Tensor] = []

    def recorded(action: th.Tensor) -> th.Tensor:
        gradients.append(gradient_of(action))
        return gradients[-1]

    steps, step_size = model.langevin_steps, model.langevin_step_size
    before = th.get_rng_state()
    targets = langevin_targets(recorded, actions, steps, step_size, model.langevin_temperature)
    after = th.get_rng_state()
    th.set_rng_state(before)
    diffusion = th.randn((steps, *actions.shape)).sum(dim=0) * (2.0 * step_size * model.langevin_temperature) ** 0.5
    th.set_rng_state(after)
    q_replay = gradient_of.start_min_q if gradients else gradient_of.min_q(actions)  # Q(s, a_B) of the first step
    return dict(
        targets=targets,
        gradient=gradients[0] if gradients else gradient_of(actions),
        drift=step_size * sum(gradients, th.zeros_like(actions)),
        diffusion=diffusion,
        q_targets=gradient_of.min_q(targets),
        q_replay=q_replay,
    )


def episode_bounds(dones: np.ndarray, count: int) -> list[tuple[int, int]]:
    """The last ``count`` complete episodes of a buffer's flat ``dones`` (time order): (first index, end index)."""
    ends = np.flatnonzero(dones) + 1
    if count <= 0 or len(ends) <= count:
        return []
    return [(int(start), int(end)) for start, end in zip(ends[-count - 1 : -1], ends[-count:], strict=True)]


def min_q(model: Any, normalize: Any, observations: np.ndarray, actions: np.ndarray | None = None) -> np.ndarray:
    """``min_j Q_j(s, a)`` at raw ``observations``, of the given ``actions`` or of the policy's (with its noise)."""
    if normalize is not None:
        observations = normalize.normalize_obs(observations)
    with th.no_grad():
        states = th.as_tensor(observations, dtype=th.float32)
        chosen = model.actor(states) if actions is None else th.as_tensor(actions, dtype=th.float32)
        return th.cat(model.critic(states, chosen), dim=1).min(dim=1).values.numpy()


def critic_against_returns(model: Any, normalize: Any, arrays: dict[str, np.ndarray], count: int) -> tuple[float, float, float]:
    """
    Over the last ``count`` episodes of the buffer: the mean ``min_j Q_j(s_t, a_t)``, the mean discounted return to
    the episode's end (at a time limit continued, as the critics' targets do, by ``γ^(T-t) min_j Q_j(s_T, a')``,
    ``a' ~ π``), and the share of those episodes that ended at a time limit.
    """
    q_values, returns, truncated = [], [], []
    for start, end in episode_bounds(arrays["dones"], count):
        at_time_limit = bool(arrays["timeouts"][end - 1])
        last = arrays["next_observations"][end - 1 : end]
        running = float(min_q(model, normalize, last)[0]) if at_time_limit else 0.0
        to_go = np.zeros(end - start)
        for index in range(end - start - 1, -1, -1):
            running = arrays["rewards"][start + index] + model.gamma * running
            to_go[index] = running
        q_values.append(min_q(model, normalize, arrays["observations"][start:end], arrays["actions"][start:end]))
        returns.append(to_go)
        truncated.append(at_time_limit)
    return float(np.concatenate(q_values).mean()), float(np.concatenate(returns).mean()), float(np.mean(truncated))


def print_langevin(model: DACERF, obs: th.Tensor, actions: th.Tensor) -> None:
    """The Langevin lines of the report, on the replay states ``obs`` and actions ``actions``."""
    with frozen(model._critic_parameters()):
        parts = langevin_parts(model, obs, actions)
    gradient = parts["gradient"].abs()
    print(f"|grad_a Q| per coordinate: mean {gradient.mean():.4f}, median {gradient.median():.4f}")
    print(
        f"Langevin ({model.langevin_steps} steps of {model.langevin_step_size}, temperature {model.langevin_temperature}): "
        f"per coordinate the gradient moves {parts['drift'].abs().mean():.4f}, the noise "
        f"{parts['diffusion'].abs().mean():.4f}, |a* - a_B| {(parts['targets'] - actions).abs().mean():.4f}"
    )
    at_bound = (parts["targets"].abs() >= 0.999).float().mean()
    print(f"coordinates at a bound: targets {at_bound:.1%}, replay actions {(actions.abs() >= 0.999).float().mean():.1%}")
    gain = parts["q_targets"] - parts["q_replay"]
    print(f"Q(s, a*) - Q(s, a_B): mean {gain.mean():.4f}, median {gain.median():.4f}, > 0 in {(gain > 0).float().mean():.0%}")


def print_actor_loss(model: DACERF, obs: th.Tensor, actions: th.Tensor) -> None:
    """The actor loss's weights and the balance of its two terms' gradients on the replay batch ``obs``, ``actions``."""
    terms = model.actor_loss_terms(SimpleNamespace(observations=obs, actions=actions))
    spread = q_value_spread(terms["q_values_buffer"])
    print(
        f"actor loss ({model.flow_matching_weights} weights): kappa {terms['kappa'].item():.4g} "
        f"(spread of Q(s, a_B) {spread.item():.4g}), mean lambda_f {terms['lambda_f'].mean().item():.3g}, "
        f"improvement term {terms['improvement_term'].item():.4g}, imitation term {terms['imitation_term'].item():.4g}"
    )
    print(f"actor gradient norm, imitation over improvement: {model._actor_gradient_ratio(terms):.4g}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkpoint", type=Path, help="a learning_curves.py checkpoint folder of a dacerf or sac run")
    parser.add_argument("--batch", type=int, default=4096, help="replay transitions measured (default 4096)")
    parser.add_argument("--last", type=int, default=100_000, help="drawn from the buffer's last that many (default 100k)")
    parser.add_argument("--episodes", type=int, default=10, help="last complete episodes for the critic (default 10)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    if not (args.checkpoint / "state.pkl").exists():
        sys.exit(f"{args.checkpoint} holds no checkpoint (no state.pkl): give a folder that learning_curves.py wrote")
    th.set_num_threads(1)
    th.manual_seed(args.seed)
    name = saved_algorithm_name(args.checkpoint / "model.zip")
    if name not in ALGORITHMS:
        sys.exit(f"{args.checkpoint} holds a {name} model: this script reads DACERF and SAC checkpoints")
    model, rows, _ = load_checkpoint(ALGORITHMS[name], args.checkpoint, "cpu")
    normalize = model.get_vec_normalize_env()
    buffer = model.replay_buffer
    size = buffer.buffer_size if buffer.full else buffer.pos
    # The buffer's arrays in time order, one environment: (steps, 1, ...) -> (steps, ...)
    order = np.roll(np.arange(size), -buffer.pos) if buffer.full else np.arange(size)
    arrays = {
        name: getattr(buffer, name)[order][:, 0]
        for name in ("observations", "next_observations", "actions", "rewards", "dones", "timeouts")
    }
    rng = np.random.default_rng(args.seed)
    picked = rng.choice(np.arange(max(0, size - args.last), size), size=min(args.batch, size), replace=False)
    observations = arrays["observations"][picked]
    if normalize is not None:
        observations = normalize.normalize_obs(observations)
    obs = th.as_tensor(observations, dtype=th.float32)
    actions = th.as_tensor(arrays["actions"][picked], dtype=th.float32)  # stored scaled to [-1, 1]

    evaluated = f" (last evaluation {rows[-1]['mean_return']:.1f})" if rows else ""
    print(
        f"{args.checkpoint} at {model.num_timesteps} steps{evaluated}, "
        f"{len(picked)} transitions of the last {min(args.last, size)}"
    )
    if isinstance(model, DACERF):
        print_langevin(model, obs, actions)
        print_actor_loss(model, obs, actions)
    with th.no_grad():
        policy_actions = model.actor(obs, deterministic=True)
    print(
        f"policy coordinates beyond ±0.99: {(policy_actions.abs() > 0.99).float().mean():.1%} "
        f"(replay actions {(actions.abs() > 0.99).float().mean():.1%})"
    )
    if episode_bounds(arrays["dones"], args.episodes):
        q_model, discounted, truncated = critic_against_returns(model, normalize, arrays, args.episodes)
        print(
            f"last {args.episodes} training episodes ({truncated:.0%} at a time limit): min_j Q_j(s_t, a_t) "
            f"{q_model:.2f}, discounted return {discounted:.2f}"
        )
    else:
        print(f"critic against returns: not measured (the buffer holds fewer than {args.episodes + 1} episode ends)")


if __name__ == "__main__":
    main()
