"""
Render driving episodes as an animated GIF and a PNG strip of frames, like the paper's figures.

By default, one episode of each scenario driven by the scripted reference tracker
:class:`sb3_dacerf.envs.driving.scripted.ScriptedDriver` (pure pursuit on the observed waypoints, speed control,
braking for the vehicle ahead; its yielding to crossing traffic is off here): a lane change on the multi-lane
highway and an unprotected left turn at the intersection. It reads only the observation, so its source also shows
how the observation is laid out.

With ``--model STEM``, one episode of a trained driver (DACERF, DACER, DSAC or SAC, its deterministic actions):
``STEM.zip`` with the ``STEM.json`` metadata and
``STEM_vecnormalize.json`` statistics beside it (written by ``examples/train_driving.py --save`` or
``benchmarks/export_driver.py``; the models in ``examples/models/``), on the scenario and config it was trained
with, loaded by ``evaluate_driving.load_driver``. ``--seed`` picks the episode; the default, 10,000, is the first
episode ``evaluate_driving.py`` evaluates, a seed no training reset uses.

Each frame shows the time, the ego's reference path (green) and the path the ego has driven so far (magenta);
``--no-overlays`` leaves the frames as highway-env draws them. The GIF plays in real time and shows every
``--gif-every``-th step.

Examples::

    python examples/render_driving.py --out-dir driving_frames
    python examples/render_driving.py --model examples/models/dacerf_multilane_rl --seed 10002 --frames 6
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np

import sb3_dacerf  # noqa: F401  (registers the environment ids)
from sb3_dacerf.envs.driving.scripted import ScriptedDriver

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from evaluate_driving import ALGORITHMS, evaluation_config, load_driver

SCENARIOS = {
    # Seeds picked where the scripted tracker completes the manoeuvre; frame times [s] (None: spread over the episode).
    "DACERF-Multilane-v0": {
        "config": {"reference_lane": "left", "duration": 6},
        "seed": 0,
        "name": "lane_change",
        "times": [0.0, 0.8, 1.6, 2.4, 4.0],
    },
    "DACERF-Intersection-v0": {"config": {"routes": ["left"]}, "seed": 5, "name": "left_turn", "times": None},
}
EVALUATION_SEED = 10_000
REFERENCE_COLOR = (0, 170, 0)
TRACE_COLOR = (220, 0, 220)


def draw_overlays(frame: np.ndarray, env: gym.Env, trace: list[np.ndarray], time: float) -> np.ndarray:
    """
    The frame with the time, the reference path and the ego's trace drawn in. Call it right after ``env.render()``:
    the view follows the ego, and ``viewer.sim_surface.pos2pix`` maps world metres to this frame's pixels only.
    """
    from PIL import Image, ImageDraw, ImageFont

    surface = env.unwrapped.viewer.sim_surface
    image = Image.fromarray(frame)
    draw = ImageDraw.Draw(image)
    draw.line([surface.pos2pix(x, y) for x, y in env.unwrapped.reference.points], fill=REFERENCE_COLOR, width=2)
    if len(trace) > 1:
        draw.line([surface.pos2pix(x, y) for x, y in trace], fill=TRACE_COLOR, width=3, joint="curve")
    font = ImageFont.load_default(size=15 if frame.shape[0] < 300 else 20)  # the highway's 150 or the crossing's 600 px
    x = 4
    for text, color in ((f"t = {time:.1f} s", (0, 0, 0)), ("reference", REFERENCE_COLOR), ("driven", TRACE_COLOR)):
        box = draw.textbbox((x, 3), text, font=font)
        draw.rectangle((box[0] - 3, box[1] - 2, box[2] + 3, box[3] + 2), fill=(255, 255, 255))
        draw.text((x, 3), text, fill=color, font=font)
        x = box[2] + 10
    return np.asarray(image)


def run_episode(env: gym.Env, act: Callable[[np.ndarray], Any], seed: int, overlays: bool = True) -> dict[str, Any]:
    """
    Drive one episode, rendering every step.

    :param env: an environment made with ``render_mode="rgb_array"``
    :param act: the driver, observation -> action
    :param seed: the reset seed
    :param overlays: draw the time, the reference path and the ego's trace into the frames
    :return: ``frames`` (one more than ``steps``), their ``times`` [s], ``steps`` and the last ``info``
    """
    obs, _ = env.reset(seed=seed)
    unwrapped = env.unwrapped
    trace = [unwrapped.vehicle.position.copy()]
    frames, times, done, info = [], [], False, {}

    def capture() -> None:
        frame = env.render()
        times.append(float(unwrapped.time))
        frames.append(draw_overlays(frame, env, trace, times[-1]) if overlays else frame)

    capture()
    while not done:
        obs, _, terminated, truncated, info = env.step(act(obs))
        trace.append(unwrapped.vehicle.position.copy())
        capture()
        done = terminated or truncated
    return {"frames": frames, "times": times, "steps": len(frames) - 1, "info": info}


def outcome(info: dict[str, Any]) -> str:
    """``arrival``, ``collision``, ``off-road`` (both if both), or ``no arrival`` at the time limit."""
    events = [name for name, key in (("collision", "collision"), ("off-road", "off_road")) if info[key]]
    return "arrival" if info["is_success"] else " and ".join(events) or "no arrival"


def save_strip(frames: list[np.ndarray], picks: np.ndarray, path: str) -> None:
    """The frames ``picks`` side by side in one PNG."""
    from PIL import Image

    Image.fromarray(np.concatenate([frames[i] for i in picks], axis=1)).save(path)


def save_gif(frames: list[np.ndarray], path: str, frame_seconds: float, every: int = 2, colors: int = 64) -> int:
    """
    An animated GIF of every ``every``-th frame (and the last), playing in real time and holding the last frame.
    All frames share one palette of ``colors`` colours without dithering: the flat colours of the rendering stay
    flat, and the file small.

    :return: the number of frames in the GIF
    """
    from PIL import Image

    picks = list(range(0, len(frames), every))
    if picks[-1] != len(frames) - 1:
        picks.append(len(frames) - 1)
    sample = np.concatenate([frames[i] for i in picks[:: max(1, len(picks) // 8)]], axis=0)
    palette = Image.fromarray(sample).quantize(colors=colors, method=Image.Quantize.MEDIANCUT)
    images = [Image.fromarray(frames[i]).quantize(palette=palette, dither=Image.Dither.NONE) for i in picks]
    durations = [round(1000 * frame_seconds * every)] * (len(images) - 1) + [1500]
    images[0].save(path, save_all=True, append_images=images[1:], duration=durations, loop=0, optimize=True)
    return len(images)


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out-dir", default="driving_frames", help="folder of the PNG strips and GIFs")
    parser.add_argument("--frames", type=int, default=5, help="frames per strip, spread over the episode")
    parser.add_argument("--model", help="a trained driver, STEM or STEM.zip (default: the scripted tracker)")
    parser.add_argument("--algo", choices=list(ALGORITHMS), help="class of --model (default: from its metadata)")
    parser.add_argument("--config", type=json.loads, help="env config overrides of --model's, as JSON")
    parser.add_argument(
        "--seed",
        type=int,
        help=f"episode seed (default: {EVALUATION_SEED} with --model, else each scenario's seed of a completed manoeuvre)",
    )
    parser.add_argument("--gif-every", type=int, default=2, help="GIF frame every that many steps")
    parser.add_argument("--no-overlays", action="store_true", help="no time, reference path and trace in the frames")
    args = parser.parse_args(argv)
    if args.frames < 1 or args.gif_every < 1:
        parser.error("--frames and --gif-every must be >= 1")
    if not args.model and (args.algo or args.config):
        parser.error("--algo and --config apply to --model: pass the model to render")

    runs: list[tuple[gym.Env, Callable[[np.ndarray], Any], int, str, list[float] | None]] = []
    if args.model:
        driver = load_driver(args.model, algo=args.algo, config=args.config, render_mode="rgb_array")
        print(
            f"{type(driver.model).__name__} from {driver.path}"
            + (f", observations normalised with {driver.stats_path}" if driver.stats_path else "")
        )
        name = os.path.basename(driver.path)[: -len(".zip")]
        seed = EVALUATION_SEED if args.seed is None else args.seed
        runs.append((driver.env, driver.act, seed, name, None))
    else:
        for env_id, scenario in SCENARIOS.items():
            env = gym.make(env_id, render_mode="rgb_array", config=evaluation_config(env_id, config=scenario["config"]))
            seed = scenario["seed"] if args.seed is None else args.seed
            times = scenario["times"] if args.seed is None else None
            runs.append((env, ScriptedDriver(env, yield_to_crossing=False), seed, scenario["name"], times))

    os.makedirs(args.out_dir, exist_ok=True)
    results = []
    for env, act, seed, name, strip_times in runs:
        episode = run_episode(env, act, seed, overlays=not args.no_overlays)
        frames, times = episode["frames"], episode["times"]
        if strip_times:
            picks = np.searchsorted(np.round(times, 6), strip_times).clip(0, len(frames) - 1)
        else:
            picks = np.linspace(0, len(frames) - 1, args.frames).round().astype(int)
        strip = os.path.join(args.out_dir, f"{name}.png")
        gif = os.path.join(args.out_dir, f"{name}.gif")
        save_strip(frames, picks, strip)
        gif_frames = save_gif(frames, gif, 1 / env.unwrapped.config["policy_frequency"], args.gif_every)
        result = {
            "env_id": env.spec.id,
            "seed": seed,
            "steps": episode["steps"],
            "outcome": outcome(episode["info"]),
            "strip": strip,
            "gif": gif,
            "gif_frames": gif_frames,
        }
        print(
            f"{result['env_id']}: seed {seed}, {result['steps']} steps, {result['outcome']}; "
            f"frames at t = {', '.join(f'{times[i]:.1f}' for i in picks)} s -> {strip}; "
            f"{gif_frames} frames ({os.path.getsize(gif) / 1e6:.2f} MB) -> {gif}"
        )
        results.append(result)
        env.close()
    return results


if __name__ == "__main__":
    main()
