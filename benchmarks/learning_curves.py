"""
Learning curves at equal environment steps: DACER-F against SAC (and variants), several seeds.

Each run trains one (variant, seed) pair and evaluates the deterministic policy every ``--eval-freq`` steps on a
separate environment. Runs are spread over ``--workers`` processes (one torch thread each). Results go to
``<out>/<env>.csv`` (one row per evaluation) and ``<out>/<env>.png`` (mean and 95% bootstrap interval over seeds);
a markdown table of the final evaluations is printed.

Every run also keeps its own evaluations in ``<out>/runs/<env>/<variant>-seed<k>.csv``, rewritten after each
evaluation: a finished run (last row at ``--timesteps``) is not trained again when the command is repeated, so long
comparisons can be run in pieces (one variant or seed range at a time) and ``--report-only`` plots what is there.

    python benchmarks/learning_curves.py --quick                       # Pendulum, 2 seeds, 3k steps, < 5 min
    python benchmarks/learning_curves.py --env Pendulum-v1 --timesteps 20000 --seeds 3 --variants dacerf sac
    python benchmarks/learning_curves.py --env DACERF-Intersection-v0 --variants dacerf sac --timesteps 50000

Environment ids registered by ``sb3_dacerf`` (driving, DMC) work too; for environments whose ``info`` carries
``is_success`` / ``collision`` / ``off_road`` the arrival, collision and off-road rates of the evaluation
episodes are reported as well.
"""

import argparse
import json
import multiprocessing as mp
import time
from pathlib import Path
from typing import Any

import numpy as np

VARIANTS: dict[str, tuple[str, dict[str, Any]]] = {
    # name: (algorithm, constructor kwargs); "action_noise_std" becomes a NormalActionNoise
    "dacerf": ("DACERF", {}),
    "dacerf-paper": ("DACERF", dict(learning_rate=1e-4, batch_size=512, policy_kwargs=dict(optimizer_class="RAD"))),
    "dacerf-noise": ("DACERF", dict(action_noise_std=0.1)),
    "dacerf-steps3": ("DACERF", dict(n_sampling_steps=3)),
    "dacerf-tau005": ("DACERF", dict(tau=0.005)),
    "dacerf-tau005-fm01": ("DACERF", dict(tau=0.005, flow_matching_coef=0.1)),
    # the short-budget remedy: SAC's tau and Gaussian action noise (see README, "Exploration")
    "dacerf-tuned": ("DACERF", dict(tau=0.005, action_noise_std=0.1)),
    "dacerf-tuned-rad": ("DACERF", dict(tau=0.005, action_noise_std=0.1, policy_kwargs=dict(optimizer_class="RAD"))),
    "dacerf-tuned-rad-zeta1": (
        "DACERF",
        dict(tau=0.005, action_noise_std=0.1, policy_kwargs=dict(optimizer_class="RAD", optimizer_kwargs=dict(zeta=1.0))),
    ),
    "dacer": ("DACER", {}),
    "sac": ("SAC", {}),
    "td3": ("TD3", {}),
    "tqc": ("TQC", {}),
}


def algorithm_class(name: str) -> type:
    import sb3_dacerf

    if name in ("SAC", "TD3"):
        import stable_baselines3

        return getattr(stable_baselines3, name)
    if name == "TQC":
        from sb3_contrib import TQC

        return TQC
    return getattr(sb3_dacerf, name)


def run_file(out: Path, env_id: str, variant: str, seed: int) -> Path:
    """Where one run keeps its evaluations."""
    return out / "runs" / env_id.replace("/", "_") / f"{variant}-seed{seed}.csv"


def read_rows(path: Path) -> list[dict[str, Any]]:
    import pandas as pd

    return pd.read_csv(path).to_dict("records") if path.exists() else []


def run_one(job: dict[str, Any]) -> list[dict[str, Any]]:
    """Train one variant with one seed; return one row per evaluation (read back if the run already finished)."""
    path = run_file(Path(job["out"]), job["env"], job["variant"], job["seed"])
    done_rows = read_rows(path)
    if done_rows and done_rows[-1]["timesteps"] >= job["timesteps"]:
        print(f"{path}: already finished, not trained again", flush=True)
        return done_rows

    import gymnasium as gym
    import pandas as pd
    import torch as th
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.noise import NormalActionNoise

    import sb3_dacerf  # noqa: F401  (registers the package's environment ids)

    th.set_num_threads(1)
    algorithm, kwargs = VARIANTS[job["variant"]]
    kwargs = dict(kwargs)
    env = gym.make(job["env"], **job["env_kwargs"])
    eval_env = gym.make(job["env"], **job["env_kwargs"])
    if "action_noise_std" in kwargs:
        dim = env.action_space.shape[0]
        kwargs["action_noise"] = NormalActionNoise(np.zeros(dim), kwargs.pop("action_noise_std") * np.ones(dim))
    model = algorithm_class(algorithm)("MlpPolicy", env, seed=job["seed"], device=job["device"], **kwargs)
    rows: list[dict[str, Any]] = []
    start = time.perf_counter()

    def evaluate() -> None:
        returns, lengths, successes, collisions, off_road = [], [], [], [], []
        for episode in range(job["eval_episodes"]):
            observation, _ = eval_env.reset(seed=10_000 * job["seed"] + episode)
            done, total, length, info = False, 0.0, 0, {}
            while not done:
                action, _ = model.predict(observation, deterministic=True)
                observation, reward, terminated, truncated, info = eval_env.step(action)
                total += float(reward)
                length += 1
                done = terminated or truncated
            returns.append(total)
            lengths.append(length)
            successes.append(float(info.get("is_success", np.nan)))
            collisions.append(float(info.get("collision", np.nan)))
            off_road.append(float(info.get("off_road", np.nan)))
        spread = model.logger.name_to_value.get("train/action_spread", np.nan)
        rows.append(
            dict(
                env=job["env"],
                variant=job["variant"],
                seed=job["seed"],
                timesteps=model.num_timesteps,
                mean_return=float(np.mean(returns)),
                episode_length=float(np.mean(lengths)),
                arrival_rate=float(np.mean(successes)),
                collision_rate=float(np.mean(collisions)),
                off_road_rate=float(np.mean(off_road)),
                action_spread=float(spread),
                wall_seconds=time.perf_counter() - start,
            )
        )
        path.parent.mkdir(parents=True, exist_ok=True)
        pd.DataFrame(rows).to_csv(path, index=False)
        print(json.dumps(rows[-1]), flush=True)

    class Evaluate(BaseCallback):
        def _on_step(self) -> bool:
            if self.num_timesteps % job["eval_freq"] == 0:
                evaluate()
            return True

    model.learn(job["timesteps"], callback=Evaluate())
    return rows


def bootstrap_interval(values: np.ndarray, rng: np.random.Generator, n_resamples: int = 2000) -> tuple[float, float]:
    """95% percentile-bootstrap interval of the mean over seeds."""
    if len(values) < 2:
        return float(values.mean()), float(values.mean())
    means = rng.choice(values, size=(n_resamples, len(values)), replace=True).mean(axis=1)
    return float(np.percentile(means, 2.5)), float(np.percentile(means, 97.5))


def report(rows: list[dict[str, Any]], env_id: str, out: Path) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import pandas as pd

    frame = pd.DataFrame(rows)
    rng = np.random.default_rng(0)
    rates = ("arrival_rate", "collision_rate", "off_road_rate")  # off_road_rate: runs from 2026-11-23 on
    metrics = ["mean_return"] + [m for m in rates if m in frame and frame[m].notna().any()]
    figure, axes = plt.subplots(1, len(metrics), figsize=(5.5 * len(metrics), 3.8), squeeze=False)
    lines = [
        "| variant | seeds | steps | final return (mean [95% CI]) | "
        + " | ".join(m.replace("_", " ") for m in metrics[1:])
        + (" | " if len(metrics) > 1 else "")
        + "action spread | train minutes |",
        "|---|---|---|---|" + "---|" * (len(metrics) - 1) + "---|---|",
    ]
    for variant, group in frame.groupby("variant", sort=False):
        curve = group.groupby("timesteps")
        for axis, metric in zip(axes[0], metrics):
            steps = np.array(sorted(curve.groups))
            values = [curve.get_group(step)[metric].to_numpy() for step in steps]
            intervals = np.array([bootstrap_interval(v, rng) for v in values])
            axis.plot(steps, [v.mean() for v in values], label=variant)
            axis.fill_between(steps, intervals[:, 0], intervals[:, 1], alpha=0.2)
            axis.set_xlabel("environment steps")
            axis.set_ylabel(metric.replace("_", " "))
        final = group[group.timesteps == group.timesteps.max()]
        low, high = bootstrap_interval(final.mean_return.to_numpy(), rng)
        cells = [f"{final[m].mean():.2f}" for m in metrics[1:]]
        lines.append(
            f"| {variant} | {final.seed.nunique()} | {int(final.timesteps.max())} | "
            f"{final.mean_return.mean():.1f} [{low:.1f}, {high:.1f}] | "
            + "".join(f"{c} | " for c in cells)
            + f"{final.action_spread.mean():.3f} | {final.wall_seconds.mean() / 60:.1f} |"
        )
    axes[0][0].legend()
    figure.suptitle(f"{env_id}: deterministic evaluation\nmean and 95% bootstrap CI over seeds", fontsize=10)
    figure.tight_layout()
    stem = env_id.replace("/", "_")
    figure.savefig(out / f"{stem}.png", dpi=110)
    frame.to_csv(out / f"{stem}.csv", index=False)
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="Pendulum-v1")
    parser.add_argument("--variants", nargs="+", default=["dacerf", "sac"], choices=sorted(VARIANTS))
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--timesteps", type=int, default=20_000)
    parser.add_argument("--eval-freq", type=int, default=2_000)
    parser.add_argument("--eval-episodes", type=int, default=5)
    parser.add_argument("--workers", type=int, default=2, help="parallel training processes")
    parser.add_argument("--device", default="cpu")
    parser.add_argument(
        "--env-kwargs",
        type=json.loads,
        default={},
        help='keyword arguments of gym.make, as JSON, e.g. \'{"config": {"collision_penalty": 500}}\' (use another --out)',
    )
    parser.add_argument("--out", help="results folder (default: benchmarks/results, with --quick benchmarks/results/quick)")
    parser.add_argument("--first-seed", type=int, default=0, help="seeds are first-seed .. first-seed + seeds - 1")
    parser.add_argument("--quick", action="store_true", help="2 seeds, 3k steps: checks the pipeline in minutes")
    parser.add_argument(
        "--report-only", action="store_true", help="train nothing: report the runs of --variants found under --out"
    )
    args = parser.parse_args()
    if args.quick:
        args.seeds, args.timesteps, args.eval_freq, args.eval_episodes = 2, 3_000, 1_000, 3

    out = Path(args.out or ("benchmarks/results/quick" if args.quick else "benchmarks/results"))
    out.mkdir(parents=True, exist_ok=True)
    if args.report_only:
        folder = run_file(out, args.env, "x", 0).parent
        rows = [row for v in args.variants for path in sorted(folder.glob(f"{v}-seed*.csv")) for row in read_rows(path)]
        if not rows:
            raise SystemExit(f"No runs of {args.variants} under {folder}: run without --report-only first")
        print(f"\n{args.env}: runs found under {folder}\n")
        print(report(rows, args.env, out))
        print(f"\nsaved {out / args.env.replace('/', '_')}.csv and .png")
        return
    jobs = [
        dict(
            env=args.env,
            variant=variant,
            seed=seed,
            timesteps=args.timesteps,
            eval_freq=args.eval_freq,
            eval_episodes=args.eval_episodes,
            device=args.device,
            out=str(out),
            env_kwargs=args.env_kwargs,
        )
        for seed in range(args.first_seed, args.first_seed + args.seeds)
        for variant in args.variants
    ]
    with mp.get_context("spawn").Pool(args.workers) as pool:
        rows = [row for result in pool.map(run_one, jobs, chunksize=1) for row in result]
    print(f"\n{args.env}, {args.timesteps} steps, {args.seeds} seeds, {args.eval_episodes} evaluation episodes\n")
    print(report(rows, args.env, out))
    print(f"\nsaved {out / args.env.replace('/', '_')}.csv and .png")


if __name__ == "__main__":
    main()
