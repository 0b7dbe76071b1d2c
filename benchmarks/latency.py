"""
Single-observation latency of a DACER-F policy beside SAC with the same actor size, in four forms:

- ``model.predict``: SB3's ``model.predict(obs, deterministic=True)`` (numpy in, numpy out, all of SB3's checks);
- ``torch actor``: the actor module on a ready tensor, ``model.actor(obs, deterministic=True)`` under ``no_grad``
  (no preprocessing outside the actor, no action unscaling);
- ``TorchScript`` and ``onnxruntime``: the exported graphs, raw observation in, action in the environment's
  units out (DACERF: ``sb3_dacerf.export.export_policy``; SAC: its deterministic policy, ``tanh`` of the mean
  action, with the same preprocessing and unscaling inside, exported with the same exporter settings).

The models are untrained (latency does not depend on the weights) on an environment that only has spaces:
by default 25 observations and 2 actions, the size of highway-env's Kinematics observation (5 vehicles x
5 features) with ContinuousAction. Every call is timed alone; the eight forms are called in turn, in a
shuffled order each round, so that machine load hits them alike; the table gives medians. PyTorch and
onnxruntime use one thread (``torch.set_num_threads(1)``, ``intra_op_num_threads=1``): one observation is too
little work to share, and the timings are steadier on a shared machine.

Usage::

    python benchmarks/latency.py [--quick] [--device cpu|cuda] [--calls 20000] [--out latency.md]
"""

from __future__ import annotations

import argparse
import copy
import random
import tempfile
import warnings
from collections.abc import Callable
from pathlib import Path

import _checkout  # noqa: F401  (the repository's sb3_dacerf, not an installed copy)
import numpy as np
import onnxruntime as ort
import torch as th
from stable_baselines3 import SAC
from stable_baselines3.sac.policies import SACPolicy
from timing import SpacesOnly, interleaved_medians, load_average, machine_name
from torch import nn

from sb3_dacerf import DACERF
from sb3_dacerf.export import export_policy


class SACDeployment(nn.Module):
    """
    SAC's deterministic policy ``tanh(mu(latent_pi(s)))`` from raw observation to action in the environment's units:
    the plain MLP that a one-step flow policy is compared with (``actor(obs, deterministic=True)`` would also trace
    the unused log-std head and Gaussian distribution into the graph).
    """

    def __init__(self, policy: SACPolicy):
        super().__init__()
        self.actor = copy.deepcopy(policy.actor).cpu().requires_grad_(False)
        self.actor.set_training_mode(False)
        low, high = policy.action_space.low.astype(np.float64), policy.action_space.high.astype(np.float64)
        self.register_buffer("action_center", th.as_tensor((high + low) / 2, dtype=th.float32))
        self.register_buffer("action_half_range", th.as_tensor((high - low) / 2, dtype=th.float32))

    def forward(self, obs: th.Tensor) -> th.Tensor:
        features = self.actor.extract_features(obs, self.actor.features_extractor)
        return th.addcmul(self.action_center, self.action_half_range, th.tanh(self.actor.mu(self.actor.latent_pi(features))))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="2000 calls per form (under 30 s on 2 cores)")
    parser.add_argument("--calls", type=int, default=20_000, help="timed calls per form")
    parser.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    parser.add_argument("--obs-dim", type=int, default=25)
    parser.add_argument("--action-dim", type=int, default=2)
    parser.add_argument("--net-arch", type=int, nargs="+", default=[256, 256])
    parser.add_argument("--threads", type=int, default=1, help="torch and onnxruntime intra-op threads")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, help="also write the markdown table to this file")
    args = parser.parse_args()
    n_calls = 2_000 if args.quick else args.calls
    if args.device == "cuda" and not th.cuda.is_available():
        parser.error("--device cuda: no CUDA device visible to PyTorch")
    th.set_num_threads(args.threads)
    th.manual_seed(args.seed)
    device = th.device(args.device)

    env = SpacesOnly(args.obs_dim, args.action_dim)
    policy_kwargs = dict(net_arch=args.net_arch)
    models = {
        "DACERF": DACERF("MlpPolicy", env, policy_kwargs=dict(policy_kwargs), buffer_size=1, seed=args.seed, device=device),
        "SAC": SAC("MlpPolicy", env, policy_kwargs=dict(policy_kwargs), buffer_size=1, seed=args.seed, device=device),
    }
    for model in models.values():
        model.policy.set_training_mode(False)

    session_options = ort.SessionOptions()
    session_options.intra_op_num_threads = args.threads
    session_options.inter_op_num_threads = 1
    session_options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    session_options.log_severity_level = 3  # the DACERF graph's overridable a0 default is intended, not worth a warning
    providers = ["CUDAExecutionProvider"] if args.device == "cuda" else ["CPUExecutionProvider"]
    has_ort = providers[0] in ort.get_available_providers()

    obs = env.observation_space.sample()[None]
    obs_tensor = th.as_tensor(obs, device=device)
    timed: dict[tuple[str, str], Callable[[], object]] = {}
    with tempfile.TemporaryDirectory() as folder:
        for name, model in models.items():
            onnx_path, ts_path = Path(folder, f"{name}.onnx"), Path(folder, f"{name}.pt")
            if name == "DACERF":
                export_policy(model, onnx_path, "onnx")
                export_policy(model, ts_path, "torchscript")
            else:
                module = SACDeployment(model.policy)
                example = obs_tensor.cpu()
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", DeprecationWarning)
                    th.onnx.export(
                        module,
                        (example,),
                        str(onnx_path),
                        dynamo=False,
                        input_names=["obs"],
                        output_names=["action"],
                        dynamic_axes={"obs": {0: "batch"}, "action": {0: "batch"}},
                        opset_version=17,
                    )
                th.jit.save(th.jit.trace(module, example), str(ts_path))
            scripted = th.jit.load(str(ts_path), map_location=device)
            timed[(name, "model.predict")] = lambda model=model: model.predict(obs, deterministic=True)
            timed[(name, "torch actor")] = lambda actor=model.actor: actor(obs_tensor, deterministic=True)
            timed[(name, "TorchScript")] = lambda scripted=scripted: scripted(obs_tensor)
            if has_ort:
                session = ort.InferenceSession(str(onnx_path), session_options, providers=providers)
                timed[(name, "onnxruntime")] = lambda session=session: session.run(None, {"obs": obs})

        random.seed(args.seed)
        with th.no_grad():
            # Warm-up rounds (allocator, TorchScript profiling executor), not counted
            interleaved_medians(timed, 200, synchronize=args.device == "cuda")
            seconds = interleaved_medians(timed, n_calls, synchronize=args.device == "cuda")
    median = {key: 1e6 * value for key, value in seconds.items()}

    forms = ["model.predict", "torch actor", "TorchScript", "onnxruntime"]
    lines = [
        f"Single-observation latency, median of {n_calls} interleaved calls, {args.device.upper()}, "
        f"{args.threads} thread(s); actor {'x'.join(map(str, args.net_arch))}, {args.obs_dim} observations, "
        f"{args.action_dim} actions; {machine_name()}, onnxruntime {ort.__version__}; {load_average()} at the end.",
        "",
        "| form | DACERF (µs) | SAC (µs) | DACERF / SAC | DACERF speed-up over its `model.predict` |",
        "|---|---:|---:|---:|---:|",
    ]
    for form in forms:
        if ("DACERF", form) not in median:
            lines.append(f"| {form} | n/a | n/a | | |")
            continue
        dacerf, sac = median[("DACERF", form)], median[("SAC", form)]
        speedup = median[("DACERF", "model.predict")] / dacerf
        lines.append(f"| {form} | {dacerf:.1f} | {sac:.1f} | {dacerf / sac:.2f}x | {speedup:.1f}x |")
    table = "\n".join(lines)
    print(table)
    if not has_ort:
        print(f"\nonnxruntime: no {providers[0]} (install onnxruntime-gpu for CUDA)")
    if args.out is not None:
        args.out.write_text(table + "\n")


if __name__ == "__main__":
    main()
